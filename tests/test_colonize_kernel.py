"""Invariants of the compiled guided-growth loop (core/reconstruct/colonize/growth.py, ``grow_kernel``).

Guo et al. 2018 §5.2 space colonisation, on ~20 trees generated here (a synthetic airborne stand, an
airborne cone with no stem points, a multi-stem shrub, a stem exactly on the z axis, other parameter
sets), reaching every path of the loop (crown filling, stalls, several roots, the roll-angle table
refill):

* deterministic: a second run gives the same skeleton, bit for bit;
* every skeleton is a tree grown in growth units: one root on the ground (or one node per root
  cluster under a multi-stem tree), parents before children, every grown node one internode l from
  its parent; a tree whose growth ended "done" reaches every one of its points;
* golden figures of all the skeletons with tolerances (nodes, forks, mean height, spread and depth),
  so a last-bit difference of another CPU passes (it may change single skeletons: LAPACK's 3x3
  eigenvectors, the PCA weights of Eq. 8, round differently) and a real change of the growth does not;
* reallocating the node arrays and refilling the roll-angle tables change nothing; the kernels run
  as Python (``SYLVA_NO_JIT``) grow the same skeleton as compiled;
* the small kernels equal the numpy/scipy functions they stand for (einsum, ``cKDTree``).

(The vectorised numpy/cKDTree loop the kernel replaced was kept here as a bit-for-bit reference; it
is in git history.)
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from sylva.core.reconstruct.colonize import GuidedGrowth
from sylva.core.reconstruct.colonize import markers as col_markers
from sylva.core.reconstruct.colonize import method as col_method
from sylva.core.reconstruct.colonize.growth import Nodes
from sylva.core.reconstruct.model import TreePoints
from sylva.testing.synth import CROWN, STEM, ScanSpec, StandSpec, make_stand, simulate_scan


def _cone(rng, n=900, height=12.0, crown_base=4.0, radius=2.5, ground=100.0):
    z = crown_base + (height - crown_base) * (1.0 - np.sqrt(rng.random(n)))
    r = radius * (height - z) / (height - crown_base)
    a = rng.uniform(0, 2 * np.pi, n)
    xyz = np.c_[5.0 + r * np.cos(a), -3.0 + r * np.sin(a), ground + z]
    return xyz + rng.normal(0, 0.03, xyz.shape)


def _shrub(rng, k=3, spacing=1.6):
    pts = []
    for i in range(k):
        a = 2 * np.pi * i / k
        c = np.array([spacing * np.cos(a), spacing * np.sin(a)])
        z = rng.uniform(0.0, 1.0, 40)
        pts.append(np.c_[c[0] + rng.normal(0, 0.05, 40), c[1] + rng.normal(0, 0.05, 40), z])
        u = rng.normal(size=(300, 3))
        u /= np.linalg.norm(u, axis=1)[:, None]
        pts.append(np.array([c[0], c[1], 2.0]) + u * np.array([0.8, 0.8, 1.0]))
    return np.concatenate(pts)


def cases():
    """(name, GuidedGrowth keyword arguments, TreePoints); everything generated here, seeded."""
    spec = StandSpec(width_m=40, depth_m=40, stems_per_ha=150, crown_overlap=0.3,
                     species=("conifer", "broadleaf"), species_weights=(0.5, 0.5), seed=11)
    stand = make_stand(spec)
    scan = simulate_scan(stand, ScanSpec(pulse_density=8, seed=11))
    xyz = scan.cloud.xyz - np.array([spec.origin[0], spec.origin[1], 0.0])
    out = []
    for t in stand.trees:                   # edge-cut trees too: irregular, stalls, fill
        sel = (scan.truth_tree == t.tree_id) & np.isin(scan.truth_kind, (STEM, CROWN))
        if sel.sum() >= 30:
            out.append((f"stand_{t.tree_id}", {}, TreePoints(t.tree_id, xyz[sel], t.ground_z)))
    out = out[:14]
    cone = TreePoints(3, _cone(np.random.default_rng(4)), 100.0)
    shrub = TreePoints(5, _shrub(np.random.default_rng(5)), 0.0)
    # A stem of points exactly on the z axis: V_opt parallel to the heading, so the
    # lateral direction comes from the roll angle φ (the "no azimuth" branch).
    # (From z = 0.1: a point at z = 0 would give two coincident root nodes.)
    z = np.arange(0.1, 12.0, 0.2)
    stem = np.r_[np.c_[np.zeros_like(z), np.zeros_like(z), z],
                 np.random.default_rng(0).normal(size=(200, 3)) * [1.5, 1.5, 1.0] + [0.0, 0.0, 9.0]]
    out += [("cone", {}, cone),
            ("cone_never_fill", dict(crown_fill="never"), cone),
            ("cone_conifer", dict(species="conifer"), cone),
            ("shrub", {}, shrub),
            ("shrub_preset", dict(species="shrub"), shrub),
            ("shrub_single_root", dict(multi_root=False, crown_fill="always"), shrub),
            ("stem_on_axis", {}, TreePoints(6, stem, 0.0))]
    return out


def assert_same_growth(a, b, name=""):
    """Two reconstructions of one tree are the same, bit for bit."""
    for x, y in ((a.skeleton.nodes, b.skeleton.nodes), (a.skeleton.parent, b.skeleton.parent),
                 (a.skeleton.radius, b.skeleton.radius), (a.skeleton.is_added, b.skeleton.is_added)):
        np.testing.assert_array_equal(x, y, err_msg=name)
    assert a.flags == b.flags, name
    assert a.visited_fraction == b.visited_fraction, name
    for key in ("n_iterations", "n_nodes", "n_fill", "n_roots"):
        assert a.stats[key] == b.stats[key], (name, key)


@pytest.fixture(scope="module")
def grown():
    """Every case with its reconstruction, computed once: (name, GuidedGrowth, TreePoints, Reconstruction)."""
    out = []
    for name, kw, tree in cases():
        method = GuidedGrowth(**kw)
        out.append((name, method, tree, method.reconstruct(tree)))
    return out


def test_growth_is_deterministic(grown):
    for name, method, tree, rec in grown:
        again = method.reconstruct(TreePoints(tree.tree_id, tree.xyz.copy(), tree.ground_z))
        assert_same_growth(again, rec, name)


def test_every_skeleton_is_a_tree_grown_in_growth_units(grown):
    assert len(grown) >= 18
    flags = set()
    for name, method, tree, rec in grown:
        s = rec.skeleton
        m = len(s.nodes)
        flags.update(rec.flags)
        assert m == rec.stats["n_nodes"] > 1 and np.isfinite(s.nodes).all(), name
        # one root, every parent before its child (what Skeleton checks), node 0 on the ground
        assert s.parent[0] == -1 and (s.parent == -1).sum() == 1, name
        assert (s.parent[1:] >= 0).all() and (s.parent[1:] < np.arange(1, m)).all(), name
        assert s.nodes[0, 2] == pytest.approx(tree.ground_z, abs=1e-9), name
        assert s.is_added[0], name
        if "multi_root" in rec.flags:          # one ground node per root cluster, children of node 0
            roots = np.flatnonzero(s.parent == 0)
            assert len(roots) == rec.stats["n_roots"] > 1, name
            np.testing.assert_allclose(s.nodes[roots, 2], tree.ground_z, atol=1e-9, err_msg=name)
        else:
            assert rec.stats["n_roots"] == 1, name
        # every grown (not added) node is one internode l (step_m) from its parent (L-system 1, rule 2)
        grown_nodes = np.flatnonzero(~s.is_added)
        assert len(grown_nodes) > 0.5 * m, name
        length = np.linalg.norm(s.nodes[grown_nodes] - s.nodes[s.parent[grown_nodes]], axis=1)
        np.testing.assert_allclose(length, method.step_m, rtol=1e-9, err_msg=name)
        assert (s.nodes[:, 2] >= tree.ground_z - 1e-9).all(), name
        # growth that ended "done" killed every measured point: each lies within d_k of a node
        if not {"stalled", "max_iterations", "node_limit"} & set(rec.flags):
            assert rec.visited_fraction == 1.0, name
        else:
            assert rec.visited_fraction < 1.0, name
    assert {"crown_filled", "stalled", "multi_root"} <= flags          # the cases reach every path


#: Golden figures of all the cases' skeletons (issue 19), each with its relative tolerance: inputs
#: perturbed by 1e-13 (what another CPU's last bits do) moved them by at most 0.04 %; a branching angle
#: of 50° instead of the species' (nodes -2.8 %) or a perception angle of 100° (forks -3.5 %) fails.
GOLDEN = {
    "nodes": (24_670, 0.01),                  # skeleton nodes
    "forks": (4_899, 0.01),                   # nodes with two children or more
    "fill": (1_216, 0.01),                    # crown-filling markers (Poisson disks, seeded)
    "mean_height_m": (19.0859, 0.003),        # of the nodes above the tree's ground
    "mean_spread_m": (2.4243, 0.003),         # horizontal distance of the nodes from the root
    "mean_depth": (90.617, 0.003),            # internodes from the root
}


def skeleton_figures(grown) -> dict:
    nodes = forks = fill = 0
    height, spread, depth = [], [], []
    for _, _, tree, rec in grown:
        s = rec.skeleton
        m = len(s.nodes)
        nodes += m
        forks += int((np.bincount(s.parent[1:], minlength=m) >= 2).sum())
        fill += rec.stats["n_fill"]
        height.append(s.nodes[:, 2] - tree.ground_z)
        spread.append(np.hypot(*(s.nodes[:, :2] - s.nodes[0, :2]).T))
        d = np.zeros(m)
        for i in range(1, m):                 # parents before children
            d[i] = d[s.parent[i]] + 1.0
        depth.append(d)
    return {"nodes": nodes, "forks": forks, "fill": fill, "mean_height_m": float(np.concatenate(height).mean()),
            "mean_spread_m": float(np.concatenate(spread).mean()), "mean_depth": float(np.concatenate(depth).mean())}


def test_growth_matches_the_golden_figures(grown):
    got = skeleton_figures(grown)
    off = {k: got[k] for k, (want, rtol) in GOLDEN.items() if abs(got[k] - want) > rtol * abs(want)}
    assert not off, f"differ from the golden figures {GOLDEN}: {off}"
    assert min(rec.visited_fraction for *_, rec in grown) >= 0.99


def test_reallocation_and_roll_table_refill_change_nothing(grown, monkeypatch):
    """Tiny initial node arrays and roll tables: the kernel grows them (code 5 re-runs an iteration)."""
    codes = []
    kernel = col_method.grow_kernel

    def spy(*args):
        res = kernel(*args)
        codes.append(int(res[-1]))
        return res

    class SmallNodes(Nodes):
        def __init__(self, cap=256):
            super().__init__(4)

    tables = col_method.roll_tables

    def short_first(roll, size):           # the first table of every tree is too short
        cos, sin = tables(roll, size)
        return (cos[:1], sin[:1]) if size < 10 else (cos, sin)

    monkeypatch.setattr(col_method, "grow_kernel", spy)
    monkeypatch.setattr(col_method, "Nodes", SmallNodes)
    monkeypatch.setattr(col_method, "roll_tables", short_first)
    for name, method, tree, rec in grown:
        codes.clear()
        assert_same_growth(method.reconstruct(tree), rec, name)
        if name == "stem_on_axis":
            assert 5 in codes              # the roll-angle table refill was exercised


def test_pure_python_kernels_match(grown, monkeypatch):
    """Without numba (``SYLVA_NO_JIT``) the same code runs as Python: the same skeleton as compiled."""
    for module, name in ((col_method, "grow_kernel"), (col_markers, "_inside_hull_kernel"),
                         (col_markers, "_pca_cov_kernel"), (col_markers, "near_any_kernel"),
                         (col_method, "near_any_kernel")):
        monkeypatch.setattr(module, name, getattr(module, name).py_func)
    name, method, tree, rec = next(c for c in grown if c[0] == "shrub")
    assert_same_growth(method.reconstruct(tree), rec, name)


def test_inside_hull_kernel_equals_einsum_test():
    """The early-exit hull test gives exactly the booleans of the einsum half-space test."""
    from scipy.spatial import ConvexHull
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(300, 3)) * [3.0, 2.0, 5.0] + [100.0, -50.0, 300.0]
    hull = ConvexHull(pts)
    q = rng.normal(size=(20000, 3)) * [4.0, 3.0, 7.0] + [100.0, -50.0, 300.0]
    eq = hull.equations
    ref = (np.einsum("ni,fi->nf", q, eq[:, :3]) + eq[:, 3] <= 1e-9).all(axis=1)
    got = col_markers._inside_hull(hull, q)
    assert 0.2 < ref.mean() < 0.9
    np.testing.assert_array_equal(got, ref)


def test_pca_covariance_kernel_equals_einsum():
    """Neighbourhood covariances of Eq. 8's PCA: identical to the numpy mean/einsum formulation."""
    rng = np.random.default_rng(3)
    xyz = rng.normal(size=(2000, 3)) * [2.0, 2.0, 6.0] + [500_000.0, 5_000_000.0, 300.0]
    _, idx = cKDTree(xyz).query(xyz, k=10)
    nb = xyz[idx]
    c = nb - nb.mean(axis=1, keepdims=True)
    ref = np.einsum("nki,nkj->nij", c, c) / 10
    np.testing.assert_array_equal(col_markers._pca_cov_kernel(xyz, idx.astype(np.int64)), ref)


@pytest.mark.parametrize("r", [0.15, 0.5, 3.0])
def test_near_any_kernel_equals_kdtree_bound(r):
    """"A centre closer than r" equals cKDTree's distance_upper_bound test, on a clustered cloud."""
    rng = np.random.default_rng(4)
    centres = np.r_[rng.normal(size=(500, 3)), rng.normal(size=(50, 3)) * 20.0] + [10.0, -4.0, 250.0]
    points = rng.normal(size=(5000, 3)) * 6.0 + [10.0, -4.0, 250.0]
    d, _ = cKDTree(centres).query(points, distance_upper_bound=r)
    got = col_markers.near_any_kernel(points, centres, r)
    assert got.any() and not got.all()
    np.testing.assert_array_equal(got, np.isfinite(d))
    assert not col_markers.near_any_kernel(points, centres[:0], r).any()
