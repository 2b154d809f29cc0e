"""Yan et al. 2009 variational k-means branch reconstruction (core/reconstruct/kmeans/)."""
from pathlib import Path

import numpy as np
import pytest

from sylva.core.errors import EmptyInputError, InputError, SylvaError
from sylva.core.qsm import measure_qsm
from sylva.testing.cylinders import cylinder_tree, sample_cylinder_surfaces
from sylva.core.reconstruct import TreePoints, reconstruct_tree
from sylva.core.reconstruct.kmeans import (VariationalKMeans, bounding_cylinders, energy, is_dense_scan,
                                           knn_graph, lloyd, point_normals, segment)

TLS = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "tls"
TLS_METHOD = VariationalKMeans(axis="normals", radius="fit")
# what sylva:reconstructtrees uses for dense trees (algorithms/reconstruct.py)
SYLVA_METHOD = VariationalKMeans(axis="normals", radius="fit", refit=True, min_cluster_points=30)


def psi_tree():
    """A vertical trunk (30 cm at the base) with two side branches at 2.0 and 2.6 m."""
    return [
        dict(start=(0, 0, 0), direction=(0, 0, 1), length=4.0, radius=(0.15, 0.08), parent=-1, n=8),
        dict(start=(0, 0, 2.0), direction=(1, 0, 0.8), length=1.6, radius=(0.05, 0.03), parent=0, n=4),
        dict(start=(0, 0, 2.6), direction=(-0.7, 0.5, 0.8), length=1.4, radius=(0.05, 0.03), parent=0, n=4),
    ]


@pytest.fixture(scope="module")
def psi():
    truth = cylinder_tree(psi_tree())
    pts = sample_cylinder_surfaces(truth, spacing_m=0.02, noise_m=0.002, seed=3)
    model = TLS_METHOD.model(TreePoints(1, pts, 0.0))
    return truth, pts, model


def tube(n=3000, r=0.05, length=1.0, seed=0, noise=0.001):
    rng = np.random.default_rng(seed)
    th = rng.uniform(0, 2 * np.pi, n)
    z = rng.uniform(0, length, n)
    rr = r + rng.normal(0, noise, n)
    return np.c_[rr * np.cos(th), rr * np.sin(th), z]


def test_lloyd_energy_decreases():
    # a bent tube: two straight pieces, so the clustering has something to settle
    a = tube(4000, 0.05, 1.0, seed=1)
    b = tube(4000, 0.05, 1.0, seed=2)[:, [2, 1, 0]] + np.array([0.0, 0, 1.0])
    xyz = np.vstack([a, b])
    g, _ = knn_graph(xyz, 8)
    seeds = np.random.default_rng(0).choice(len(xyz), 6, replace=False)
    lab, s, _, en = lloyd(xyz, g, seeds, max_iter=30, epsilon_rel=0.0)
    assert len(en) >= 3
    assert np.all(np.diff(en) < 0)            # Eq. 1 strictly decreases
    assert en[-1] < 0.8 * en[0]
    # the returned partition is the one of the last recorded energy
    c = np.stack([xyz[lab == i].mean(axis=0) for i in range(6)])
    assert energy(xyz, lab, c) == pytest.approx(en[-1], rel=1e-9)
    assert np.array_equal(lab[s], np.arange(6))
    # plain (non-local) Lloyd also decreases
    _, _, _, en2 = lloyd(xyz, g, seeds, max_iter=30, epsilon_rel=0.0, local=False)
    assert np.all(np.diff(en2) < 0)


def test_bounding_cylinder_of_known_tube():
    xyz = tube(3000, 0.05, 0.6, noise=0.0)
    cyl = bounding_cylinders(xyz, np.zeros(len(xyz), dtype=np.int64), 1)
    # principal axis (Yan §2.3): a sampling tilt of ~1 degree widens the enclosing circle
    assert abs(cyl["axis"][0] @ np.array([0, 0, 1.0])) > 0.999
    assert cyl["radius"][0] == pytest.approx(0.05, abs=0.006)
    assert cyl["rms"][0] < 0.006
    assert cyl["length"][0] == pytest.approx(0.6, abs=0.01)
    # the surface-normal axis is much closer, and so is the enclosing circle
    _, nbr = knn_graph(xyz, 8)
    cyl = bounding_cylinders(xyz, np.zeros(len(xyz), dtype=np.int64), 1, point_normals(xyz, nbr))
    assert abs(cyl["axis"][0] @ np.array([0, 0, 1.0])) > 0.99995
    assert cyl["radius"][0] == pytest.approx(0.05, abs=0.001)
    assert cyl["fit_radius"][0] == pytest.approx(0.05, abs=2e-4)
    assert cyl["rms"][0] < 0.001


def test_clusters_fit_their_cylinders_after_subdivision():
    # three separate bent tubes: the initial clusters straddle the bends and
    # are split until every one is bounded by a cylinder within delta
    parts = []
    for i in range(3):
        a = tube(2500, 0.04, 0.8, seed=10 + i)
        b = tube(2500, 0.04, 0.8, seed=20 + i)[:, [2, 1, 0]] + np.array([0.0, 0, 0.8])
        parts.append(np.vstack([a, b]) + np.array([3.0 * i, 0, 0]))
    xyz = np.vstack(parts)
    delta = 0.015
    seg = segment(xyz, n_seeds=3, delta_m=delta, min_cluster_points=30, seed=0)
    assert seg.reason == "all_fixed"
    assert seg.fixed.all()
    assert np.all(seg.cylinders["rms"] < delta)
    assert seg.n_clusters > 3                       # subdivision happened
    assert (seg.labels >= 0).all()
    # with a loose delta the initial clusters are already tight enough
    loose = segment(xyz, n_seeds=3, delta_m=1.0, min_cluster_points=30, seed=0)
    assert loose.rounds == 1 and loose.n_clusters <= 4      # one seed per kNN component at least


def test_psi_tree_two_order1_branches(psi):
    truth, pts, model = psi
    orders = model.branch_order
    assert len(model.curves) == 3, model.reconstruction.stats
    assert orders.tolist().count(0) == 1 and orders.tolist().count(1) == 2
    rec = model.reconstruction
    assert rec.method == "variational_kmeans"
    assert rec.connected and rec.visited_fraction == 1.0
    # the skeleton follows the trunk and reaches the tips of both branches
    tips = np.array([[0, 0, 4.0], [1.6 / np.hypot(1, 0.8), 0, 2.0 + 1.6 * 0.8 / np.hypot(1, 0.8)]])
    d = rec.skeleton.distance(tips)
    assert d.max() < 0.25
    assert np.all(rec.skeleton.radius > 0)
    v, f = model.mesh()
    assert len(f) > 0 and np.isfinite(v).all()


def test_psi_tree_qsm_dbh_height_volume(psi):
    truth, pts, model = psi
    q = measure_qsm(model.cylinders, model.branch_parent, pts, base_z=0.0)
    true_dbh = 2 * (0.15 - 0.07 * 1.3 / 4.0)                      # 27.7 cm at 1.3 m
    assert q.dbh_source == "measured"
    assert abs(q.dbh_m - true_dbh) < 0.01
    assert q.height_m == pytest.approx(4.0, abs=0.1)
    true_vol = float((np.pi * truth["radius"] ** 2 * truth["length"]).sum())
    assert q.total_volume_m3 == pytest.approx(true_vol, rel=0.10)
    assert q.branch_counts == {1: 2}


def test_dbh_30cm_trunk_within_1cm():
    truth = cylinder_tree([dict(start=(5, 5, 100), direction=(0, 0, 1), length=3.0, radius=(0.15, 0.15), n=6)])
    pts = sample_cylinder_surfaces(truth, spacing_m=0.02, noise_m=0.003, seed=1,
                                   visible=(1.0, 0.3, 0.0))      # one-sided scan
    model = TLS_METHOD.model(TreePoints(2, pts, 100.0))
    q = measure_qsm(model.cylinders, model.branch_parent, pts, base_z=100.0)
    assert q.dbh_source == "measured"
    assert abs(q.dbh_m - 0.30) < 0.01


def test_trunk_volume_within_5_percent():
    truth = cylinder_tree([dict(start=(0, 0, 0), direction=(0, 0.1, 1), length=4.0, radius=(0.15, 0.10), n=8)])
    pts = sample_cylinder_surfaces(truth, spacing_m=0.02, noise_m=0.002, seed=2)
    model = TLS_METHOD.model(TreePoints(3, pts, 0.0))
    q = measure_qsm(model.cylinders, model.branch_parent, pts, base_z=0.0)
    true_vol = float((np.pi * truth["radius"] ** 2 * truth["length"]).sum())
    assert q.total_volume_m3 == pytest.approx(true_vol, rel=0.05)
    assert q.trunk_volume_m3 == pytest.approx(q.total_volume_m3, rel=0.05)


def test_deterministic(psi):
    truth, pts, model = psi
    again = TLS_METHOD.model(TreePoints(1, pts, 0.0))
    assert np.array_equal(again.segmentation.labels, model.segmentation.labels)
    assert np.array_equal(again.reconstruction.skeleton.nodes, model.reconstruction.skeleton.nodes)
    assert np.array_equal(again.cylinders["radius"], model.cylinders["radius"])
    other = VariationalKMeans(axis="normals", radius="fit", seed=5).model(TreePoints(1, pts, 0.0))
    assert other.segmentation.n_clusters > 0


def test_paper_defaults_run_through_reconstruct_tree(psi):
    truth, pts, _ = psi
    rec = reconstruct_tree(TreePoints(1, pts, 0.0), VariationalKMeans())
    assert rec.method == "variational_kmeans"
    assert len(rec.skeleton) > 5
    assert rec.stats["n_clusters"] >= 10 and rec.stats["t_segmentation_s"] > 0


def test_degenerate_inputs():
    m = VariationalKMeans()
    with pytest.raises(EmptyInputError):
        m.reconstruct(TreePoints(9, np.zeros((0, 3)), 0.0))
    few = m.model(TreePoints(9, np.random.default_rng(0).normal(size=(10, 3)), -5.0))
    assert "too_few_points" in few.reconstruction.flags
    assert len(few.reconstruction.skeleton) == 2
    rng = np.random.default_rng(1)
    plane = np.c_[rng.uniform(0, 2, 500), rng.uniform(0, 2, 500), np.zeros(500)]
    flat = m.reconstruct(TreePoints(9, plane, 0.0))
    assert "coplanar_points" in flat.flags
    line = np.c_[np.zeros(300), np.zeros(300), np.linspace(0, 3, 300)]
    assert "collinear_points" in m.reconstruct(TreePoints(9, line, 0.0)).flags
    for bad in (dict(delta_m=0), dict(k=1), dict(metric="euclid"), dict(axis="x"), dict(radius="max")):
        with pytest.raises(InputError):
            VariationalKMeans(**bad)
    assert issubclass(InputError, SylvaError)


def test_two_separate_pieces_are_bridged():
    a = tube(1500, 0.05, 1.0, seed=4)
    b = tube(1500, 0.05, 1.0, seed=5) + np.array([0.0, 0.0, 1.3])   # a 30 cm gap
    rec = TLS_METHOD.reconstruct(TreePoints(4, np.vstack([a, b]), 0.0))
    assert "graph_disconnected" in rec.flags and not rec.connected
    assert rec.skeleton.nodes[:, 2].max() > 2.0


def test_dense_rule_on_synthetic_airborne_trees():
    from sylva.testing.synth import ScanSpec, StandSpec, make_stand, simulate_scan
    stand = make_stand(StandSpec(width_m=30, depth_m=30, stems_per_ha=200, seed=1))
    scan = simulate_scan(stand, ScanSpec(pulse_density=100, seed=1))
    ids = np.unique(scan.truth_tree[scan.truth_tree > 0])
    trees = [scan.cloud.xyz[scan.truth_tree == i] for i in ids]
    trees = [t for t in trees if len(t) >= 500]
    assert len(trees) >= 5
    assert not any(is_dense_scan(t) for t in trees)
    truth = cylinder_tree(psi_tree())
    assert is_dense_scan(sample_cylinder_surfaces(truth, spacing_m=0.02, seed=0))
    assert not is_dense_scan(np.zeros((10, 3)))


@pytest.mark.parametrize("name", ["tree1", "tree7", "tree13"])
def test_tls_trees_are_dense_and_reconstruct(name):
    path = TLS / f"{name}.xyz"
    if not path.exists():
        pytest.skip(f"{path} not available")
    xyz = np.loadtxt(path)
    assert is_dense_scan(xyz)
    model = TLS_METHOD.model(TreePoints(0, xyz, float(xyz[:, 2].min())))
    rec = model.reconstruction
    assert len(rec.skeleton) > 10 and len(model.curves) >= 2
    q = measure_qsm(model.cylinders, model.branch_parent, xyz)
    assert 0.02 < q.dbh_m < 0.8
    assert q.height_m == pytest.approx(np.ptp(xyz[:, 2]), abs=0.5)
    if "sparse_scan" in rec.flags:       # tree13: 19 cm to the 8th neighbour, radii not trusted
        assert rec.stats["spacing_k_m"] > 0.1
    else:
        assert 0 < q.total_volume_m3 < 3.0          # sanity only: no ground truth for these trees
    assert ("sparse_scan" in rec.flags) == (name == "tree13")
    # the points lie close to the refitted model's surface (first increment: 3-18 cm)
    from sylva.core.qsm import surface_distance
    refit = SYLVA_METHOD.model(TreePoints(0, xyz, float(xyz[:, 2].min())))
    d = surface_distance(xyz, refit.cylinders)
    assert np.mean(d) < {"tree1": 0.03, "tree7": 0.025, "tree13": 0.07}[name]


# --------------------------------------------------------------------------- refit, trimming, speed-ups


def _branched_tree():
    """A 45 cm trunk, 8 m, with three order-1 branches and one order-2 branch (known cylinders)."""
    return cylinder_tree([
        dict(start=(0, 0, 0), direction=(0, 0, 1), length=8.0, radius=(0.225, 0.06), parent=-1, n=16),
        dict(start=(0, 0, 3.0), direction=(1, 0, 0.7), length=2.0, radius=(0.08, 0.02), parent=0, n=4),
        dict(start=(0, 0, 4.2), direction=(-0.6, 0.8, 0.7), length=1.8, radius=(0.07, 0.02), parent=0, n=4),
        dict(start=(0, 0, 5.4), direction=(0.1, -1, 0.8), length=1.5, radius=(0.06, 0.02), parent=0, n=3),
        dict(start=(0.82, 0, 3.57), direction=(0.3, 0.8, 0.6), length=0.8, radius=(0.04, 0.015), parent=1, n=2),
    ])


@pytest.fixture(scope="module")
def branched():
    truth = _branched_tree()
    pts = sample_cylinder_surfaces(truth, spacing_m=0.02, noise_m=0.003, seed=7)
    return truth, pts


def test_refit_model_is_close_to_the_surface_and_the_volume(branched):
    """The refitted model (radii and axes from circle fits, inner branches dropped) against the truth:
    volumes, DBH and the distance of the points to the model surface."""
    from sylva.core.qsm import surface_distance

    truth, pts = branched
    plain = TLS_METHOD.model(TreePoints(0, pts, 0.0))
    model = SYLVA_METHOD.model(TreePoints(0, pts, 0.0))
    vol = np.pi * truth["radius"] ** 2 * truth["length"]
    q = measure_qsm(model.cylinders, model.branch_parent, pts, base_z=0.0)
    assert q.trunk_volume_m3 == pytest.approx(vol[truth["branch"] == 0].sum(), rel=0.05)
    assert q.total_volume_m3 == pytest.approx(vol.sum(), rel=0.08)
    assert q.dbh_source == "measured"
    d_new = surface_distance(pts, model.cylinders)
    d_old = surface_distance(pts, plain.cylinders)
    assert np.mean(d_new) < 0.01 and np.mean(d_new) < np.mean(d_old)
    assert (d_new <= 0.02).mean() > 0.93
    # no branch left inside the trunk: every order-1 branch starts at the trunk and leaves it
    c = model.cylinders
    for b in np.flatnonzero(model.branch_parent == 0):
        i = np.flatnonzero(c["branch"] == b)
        end = c["start"][i[-1]] + c["axis"][i[-1]] * c["length"][i[-1]]
        assert np.hypot(end[0], end[1]) > 0.6
    assert model.reconstruction.stats["n_refit_cylinders"] > 0.5 * len(c["radius"])
    again = SYLVA_METHOD.model(TreePoints(0, pts, 0.0))          # deterministic
    assert np.array_equal(again.cylinders["radius"], c["radius"]) and np.array_equal(again.cylinders["start"],
                                                                                     c["start"])


def test_branch_running_inside_its_parent_is_trimmed():
    from sylva.core.reconstruct.kmeans.bspline import _trim_in_parent

    parent = np.array([[0, 0, 0.0], [0, 0, 2.0], [0, 0, 4.0]])
    prad = np.array([0.2, 0.2, 0.2])
    # a chain that climbs inside the trunk (x = 0.1) from z = 1 to 2.5, then leaves sideways
    v = np.array([[0.1, 0, 1.0], [0.1, 0, 1.8], [0.1, 0, 2.5], [0.5, 0, 2.8], [1.0, 0, 3.1]])
    rv = np.array([0.2, 0.2, 0.19, 0.05, 0.03])
    v2, r2 = _trim_in_parent(v, rv, parent, prad)
    assert np.allclose(v2[0], [0, 0, 2.5])             # leaves from the parent's centre line
    assert np.allclose(v2[1:], v[3:]) and np.allclose(r2, [0.05, 0.05, 0.03])
    # a branch that leaves at once is unchanged
    v3, r3 = _trim_in_parent(v[2:], rv[2:], parent, prad)
    assert np.array_equal(v3, v[2:]) and np.array_equal(r3, rv[2:])


def test_fast_kernels_match_the_reference():
    from scipy import sparse

    from sylva.core.reconstruct.kmeans.segmentation import _flood, _smallest_eigvec, _subgraph

    rng = np.random.default_rng(3)
    x = rng.normal(size=(4000, 9, 3)) * np.array([1.0, 0.4, 0.02])
    x -= x.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", x, x)
    v = _smallest_eigvec(cov)
    ref = np.linalg.eigh(cov)[1][:, :, 0]
    assert np.allclose(np.abs((v * ref).sum(axis=1)), 1.0, atol=1e-9)
    line = np.zeros((5, 3, 3))
    line[:, 2, 2] = 1.0                                # double zero eigenvalue: falls back to eigh
    assert np.allclose(np.abs(_smallest_eigvec(line)[:, 2]), 0.0)
    xyz = tube(3000, 0.05, 1.0, seed=6)
    g, _ = knn_graph(xyz, 8)
    mask = rng.uniform(size=len(xyz)) < 0.4
    sub = _subgraph(g, mask)
    idx = np.flatnonzero(mask)
    assert (sub != g[idx][:, idx]).nnz == 0
    seeds = np.array([0, 1000, 2000])
    lab, _ = _flood(g, seeds)
    dist = sparse.csgraph.dijkstra(g, unweighted=True, indices=seeds)
    assert np.all(dist[lab, np.arange(len(xyz))] == dist.min(axis=0))   # every point joins a nearest seed


def test_the_dense_scan_preset_is_what_the_plugin_runs():
    """METHOD=yan of reconstructtrees is VariationalKMeans.dense_scan(), a preset of the core class."""
    from sylva.algorithms.reconstruct import _methods
    from sylva.core.reconstruct import VariationalKMeans

    args = {"METHOD": "yan"}
    method, dense = _methods(args)
    assert method == VariationalKMeans.dense_scan() and dense is None
    assert method != VariationalKMeans() and method.min_cluster_points == 30 and method.refit
