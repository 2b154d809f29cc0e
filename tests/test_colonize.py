"""Guided growth (Guo et al. 2018 §5.2, §6.1): core/reconstruct/colonize/."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import ConvexHull, cKDTree

from sylva.core.errors import Cancelled, EmptyInputError, InputError
from sylva.core.reconstruct.colonize import (
    SPECIES_PRESETS, GuidedGrowth, crown_fill_markers, find_root_clusters, influence_distance,
    interior_fraction, pca_weights,
)
from sylva.core.reconstruct.model import Reconstruction, TreePoints
from sylva.core.skeleton import Skeleton
from sylva.testing.synth import CROWN, STEM, ScanSpec, StandSpec, make_stand, simulate_scan


# --------------------------------------------------------------------------- helpers
def assert_valid_tree(skel: Skeleton):
    m = len(skel)
    assert m >= 1
    assert skel.parent[0] == -1
    assert (skel.parent == -1).sum() == 1
    assert np.all(skel.parent[1:] < np.arange(1, m))
    assert np.all(skel.parent[1:] >= 0)
    assert skel.nodes.shape == (m, 3) and np.all(np.isfinite(skel.nodes))


def sphere_shell(n, centre, radii, rng, top_only=False):
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    if top_only:
        u[:, 2] = np.abs(u[:, 2])
    return np.asarray(centre) + u * np.asarray(radii)


def cone_tree(rng, n=900, height=12.0, crown_base=4.0, radius=2.5, ground=100.0, xy=(5.0, -3.0)):
    """Airborne-like conifer: points on the surface of a cone (no stem points)."""
    z = crown_base + (height - crown_base) * (1.0 - np.sqrt(rng.random(n)))
    r = radius * (height - z) / (height - crown_base)
    a = rng.uniform(0, 2 * np.pi, n)
    xyz = np.c_[xy[0] + r * np.cos(a), xy[1] + r * np.sin(a), ground + z]
    return xyz + rng.normal(0, 0.03, xyz.shape)


def shrub(rng, k=3, spacing=1.6):
    """A multi-stem shrub: k clumps, each a stem (points from the ground) under an ellipsoid."""
    pts = []
    for i in range(k):
        a = 2 * np.pi * i / k
        c = np.array([spacing * np.cos(a), spacing * np.sin(a)])
        z = rng.uniform(0.0, 1.0, 40)
        pts.append(np.c_[c[0] + rng.normal(0, 0.05, 40), c[1] + rng.normal(0, 0.05, 40), z])
        pts.append(sphere_shell(300, [c[0], c[1], 2.0], [0.8, 0.8, 1.0], rng))
    return np.concatenate(pts)


@pytest.fixture(scope="module")
def synth_trees():
    """Trees of a synthetic stand whose crowns lie inside the scanned extent (no edge cuts)."""
    spec = StandSpec(width_m=60, depth_m=60, stems_per_ha=100, crown_overlap=0.0,
                     species=("conifer", "broadleaf"), species_weights=(0.5, 0.5), seed=3)
    stand = make_stand(spec)
    scan = simulate_scan(stand, ScanSpec(pulse_density=10, seed=3))
    x0, y0 = spec.origin
    xyz = scan.cloud.xyz - np.array([x0, y0, 0.0])
    out = []
    for t in stand.trees:
        R = t.crown_radius_m + 1.0
        if not (t.x - x0 > R and t.x - x0 < 60 - R and t.y - y0 > R and t.y - y0 < 60 - R):
            continue
        sel = (scan.truth_tree == t.tree_id) & np.isin(scan.truth_kind, (STEM, CROWN))
        if sel.sum() < 50:
            continue
        out.append((t, TreePoints(t.tree_id, xyz[sel], t.ground_z), np.array([t.x - x0, t.y - y0])))
    assert len(out) >= 8
    assert {t.species for t, _, _ in out[:10]} == {"conifer", "broadleaf"}
    return out[:10]


# --------------------------------------------------------------------------- building blocks
def test_influence_distance_is_eq7_times_l():
    l, H, h0, rho0 = 0.25, 20.0, 2.0, 0.3
    K = H / l
    t = np.arange(0, 60, dtype=float)
    # Eq. 6 and its numerical derivative
    Ht = lambda tt: K / (1 + (K / h0 - 1) * np.exp(-rho0 * tt))  # noqa: E731
    num = (Ht(t + 1e-5) - Ht(t - 1e-5)) / 2e-5
    got = influence_distance(t, H, l, h0, rho0, min_units=0.0, max_units=np.inf)
    np.testing.assert_allclose(got, num * l, rtol=1e-5, atol=1e-8)
    # maximum of ρ_t is K ρ0 / 4 at t* = ln(K/H0 - 1)/ρ0
    tstar = np.log(K / h0 - 1) / rho0
    assert influence_distance(tstar, H, l, h0, rho0, 0.0, np.inf) == pytest.approx(K * rho0 / 4 * l)
    # clamped to Pałubicki's [4l, 12l]
    clamped = influence_distance(t, H, l)
    assert clamped.min() == pytest.approx(4 * l) and clamped.max() <= 12 * l + 1e-12
    assert clamped.max() == pytest.approx(min(12, K * rho0 / 4) * l, rel=1e-2)


def test_pca_weights_eq8_counts_similar_neighbours():
    # Two parallel lines along x (1 m apart) and an isotropic clutter blob.
    x = np.arange(0, 3.0, 0.1)
    line = np.r_[np.c_[x, np.zeros_like(x), np.zeros_like(x)], np.c_[x, np.ones_like(x), np.zeros_like(x)]]
    rng = np.random.default_rng(1)
    blob = rng.uniform(-0.3, 0.3, (60, 3)) + [10, 10, 10]
    w, axis = pca_weights(np.r_[line, blob], radius_m=0.25, cos_min=0.9, k=5)
    assert np.all(w >= 1)
    # axes along the lines are ±x
    assert np.all(np.abs(axis[:len(line), 0]) > 0.99)
    # an interior line point: itself + 2 neighbours each side within 0.25 m, all parallel -> 5
    assert w[10] == 5
    # end points have fewer (itself + 2)
    assert w[0] == 3
    assert np.median(w[:len(line)]) > np.median(w[len(line):])
    # brute force Eq. 8 on the blob
    P = np.r_[line, blob]
    d = np.linalg.norm(P[:, None] - P[None], axis=2)
    sim = np.abs(axis @ axis.T) > 0.9
    np.testing.assert_array_equal(w, ((d < 0.25) & sim).sum(axis=1))


def test_interior_fraction_full_ball_vs_shell():
    rng = np.random.default_rng(0)
    ball = rng.uniform(-1, 1, (20000, 3))
    ball = ball[np.linalg.norm(ball, axis=1) < 1]
    assert interior_fraction(ball) == pytest.approx(1 / 8, abs=0.02)
    shell = sphere_shell(3000, [0, 0, 0], [2, 2, 2], rng, top_only=True)
    assert interior_fraction(shell) < 0.01
    assert interior_fraction(np.c_[rng.random((50, 2)), np.zeros(50)]) == 0.0   # flat: no hull


def test_crown_fill_markers_inside_hull_poisson_disk_and_seeded():
    rng = np.random.default_rng(2)
    crown = sphere_shell(800, [0, 0, 10], [3, 3, 2], rng, top_only=True)
    fill = crown_fill_markers(crown, 0.7, seed=5)
    assert len(fill) > 50
    # only inside the hull: adding them leaves the hull unchanged, and the hull of points on a
    # half-ellipsoid lies inside the half-ellipsoid
    assert ConvexHull(np.r_[crown, fill]).volume == pytest.approx(ConvexHull(crown).volume, rel=1e-12)
    assert np.all(((fill[:, :2] / 3.0) ** 2).sum(axis=1) + ((fill[:, 2] - 10.0) / 2.0) ** 2 <= 1.0)
    assert np.all(fill[:, 2] >= 10.0)
    pair_d = cKDTree(fill).query(fill, k=2)[0][:, 1]
    assert pair_d.min() >= 0.5 * 0.7 - 1e-9                          # Poisson-disk radius
    assert cKDTree(crown).query(fill)[0].min() >= 0.5 * 0.7 - 1e-9   # away from measured points
    np.testing.assert_array_equal(fill, crown_fill_markers(crown, 0.7, seed=5))
    assert not np.array_equal(fill, crown_fill_markers(crown, 0.7, seed=6))
    assert len(crown_fill_markers(np.c_[rng.random((40, 2)), np.zeros(40)], 0.5)) == 0


def test_find_root_clusters():
    rng = np.random.default_rng(3)
    c = find_root_clusters(shrub(rng, k=3), 0.0, band_m=1.0, link_m=0.75)
    assert c is not None and len(c.centres) == 3
    r = np.hypot(*c.centres.T)
    np.testing.assert_allclose(r, 1.6, atol=0.1)
    assert find_root_clusters(cone_tree(rng), 100.0, 1.0, 0.75) is None   # nothing near the ground


# --------------------------------------------------------------------------- the method
def test_synthetic_stand_trees(synth_trees):
    gg = GuidedGrowth()
    for truth, tree, base in synth_trees:
        rec = gg.reconstruct(tree)
        assert isinstance(rec, Reconstruction)
        assert rec.method == "guided_growth" and rec.connected and rec.tree_id == truth.tree_id
        skel = rec.skeleton
        assert_valid_tree(skel)
        coverage = float((skel.distance(tree.xyz) < 0.5).mean())
        assert coverage >= 0.9, (truth.tree_id, coverage)
        assert rec.visited_fraction >= 0.9
        root = skel.nodes[skel.root]
        assert np.hypot(*(root[:2] - base)) < 1.0, (truth.tree_id, root, base)
        assert root[2] == pytest.approx(truth.ground_z)
        top = skel.nodes[:, 2].max() - truth.ground_z
        assert abs(top - truth.height) < 0.1 * truth.height, (truth.tree_id, top, truth.height)
        assert skel.is_added[0]


def test_cone_without_stem_points_grows_trunk_from_ground_and_fills_crown():
    rng = np.random.default_rng(4)
    xyz = cone_tree(rng)
    rec = GuidedGrowth().reconstruct(TreePoints(3, xyz, 100.0))
    skel = rec.skeleton
    assert_valid_tree(skel)
    assert "crown_filled" in rec.flags and rec.stats["n_fill"] > 0
    assert rec.stats["interior_fraction"] < 0.0625
    root = skel.nodes[0]
    assert root[2] == pytest.approx(100.0)
    assert np.hypot(root[0] - 5.0, root[1] + 3.0) < 0.5
    # an added trunk bridges the 4 m without points
    low = skel.nodes[:, 2] < 103.5
    assert low.sum() >= 10 and skel.is_added[low].all()
    assert (skel.distance(xyz) < 0.5).mean() >= 0.95
    assert abs(skel.nodes[:, 2].max() - 112.0) < 1.2
    # filling off: fewer nodes, still no fill markers
    rec2 = GuidedGrowth(crown_fill="never").reconstruct(TreePoints(3, xyz, 100.0))
    assert rec2.stats["n_fill"] == 0 and "crown_filled" not in rec2.flags


def test_growth_follows_points_eq9():
    """A Y: a vertical trunk line and two inclined branch lines; the skeleton follows them."""
    t = np.linspace(0, 1, 60)[:, None]
    trunk = np.array([0, 0, 0.2]) + t * [0, 0, 3.8]
    b1 = np.array([0, 0, 4.0]) + t * [2.5, 0, 2.0]
    b2 = np.array([0, 0, 4.0]) + t * [-1.5, 2.0, 2.5]
    xyz = np.r_[trunk, b1, b2] + np.random.default_rng(5).normal(0, 0.02, (180, 3))
    rec = GuidedGrowth(crown_fill="never").reconstruct(TreePoints(1, xyz, 0.0))
    assert rec.stats["root_rule"] == "low_points"
    assert np.linalg.norm(rec.skeleton.nodes[0] - [0, 0, 0]) < 0.1     # under the lowest points
    skel = rec.skeleton
    assert_valid_tree(skel)
    # every branch end is reached
    for end in (trunk[-1], b1[-1], b2[-1]):
        assert np.linalg.norm(skel.nodes - end, axis=1).min() < 0.5
    # nodes stay close to the lines (the weighted attraction dominates the heading)
    lines = Skeleton(np.r_[[trunk[0]], [trunk[-1]], [b1[-1]], [b2[-1]]], [-1, 0, 1, 1])
    assert np.percentile(lines.distance(skel.nodes), 90) < 0.35
    assert rec.visited_fraction == 1.0


def test_multi_stem_shrub_has_several_stems_from_the_ground():
    rng = np.random.default_rng(6)
    xyz = shrub(rng, k=3)
    rec = GuidedGrowth(species="shrub").reconstruct(TreePoints(9, xyz, 0.0))
    skel = rec.skeleton
    assert_valid_tree(skel)
    assert "multi_root" in rec.flags and rec.stats["n_roots"] == 3
    stems = skel.children()[0]
    assert len(stems) >= 2
    assert np.allclose(skel.nodes[stems, 2], 0.0) and skel.is_added[stems].all()
    assert skel.is_added[0] and skel.nodes[0, 2] == 0.0
    # every clump is reached from its own stem: the first-level subtree of each clump's points
    depth_one = np.zeros(len(skel), dtype=np.int64) - 1
    for i in range(1, len(skel)):
        depth_one[i] = i if skel.parent[i] == 0 else depth_one[skel.parent[i]]
    nearest = cKDTree(skel.nodes[1:]).query(xyz)[1] + 1
    owner = depth_one[nearest]
    majority = []
    for k in range(3):
        clump = owner[k * 340 + 40:(k + 1) * 340]        # the ellipsoid points of clump k
        top = np.bincount(clump).argmax()
        assert (clump == top).mean() > 0.9                 # one stem carries the clump
        majority.append(top)
    assert sorted(majority) == sorted(stems.tolist())      # three clumps, three stems
    assert (skel.distance(xyz) < 0.5).mean() >= 0.9
    # switched off: one root, the Hu §4.2 trunk
    one = GuidedGrowth(species="shrub", multi_root=False).reconstruct(TreePoints(9, xyz, 0.0))
    assert "multi_root" not in one.flags and one.stats["n_roots"] == 1
    assert_valid_tree(one.skeleton)
    # a single cone does not get several roots
    rec1 = GuidedGrowth().reconstruct(TreePoints(1, cone_tree(rng), 100.0))
    assert "multi_root" not in rec1.flags and rec1.stats["n_roots"] == 1


def test_deterministic(synth_trees):
    _, tree, _ = synth_trees[0]
    a = GuidedGrowth().reconstruct(tree)
    b = GuidedGrowth().reconstruct(TreePoints(tree.tree_id, tree.xyz.copy(), tree.ground_z))
    np.testing.assert_array_equal(a.skeleton.nodes, b.skeleton.nodes)
    np.testing.assert_array_equal(a.skeleton.parent, b.skeleton.parent)
    assert a.visited_fraction == b.visited_fraction and a.flags == b.flags


@pytest.mark.parametrize("xyz, flag", [
    (np.array([[0.0, 0.0, 5.0]]), "too_few_points"),
    (np.random.default_rng(0).random((9, 3)) * 3, "too_few_points"),
    (np.repeat(np.array([[1.0, 2.0, 5.0], [1.0, 2.0, 6.0]]), 10, axis=0), "duplicate_points"),
    (np.c_[np.zeros(30), np.zeros(30), np.linspace(1, 8, 30)], "collinear_points"),
    (np.c_[np.random.default_rng(1).random((40, 2)) * 3, np.full(40, 6.0)], "coplanar_points"),
])
def test_degenerate_inputs_give_minimal_skeleton(xyz, flag):
    rec = GuidedGrowth().reconstruct(TreePoints(5, xyz, 0.0))
    assert flag in rec.flags
    assert_valid_tree(rec.skeleton)
    assert len(rec.skeleton) <= 2 and rec.skeleton.is_added.all()
    assert rec.skeleton.nodes[0, 2] == 0.0
    assert 0.0 <= rec.visited_fraction <= 1.0 and rec.method == "guided_growth"


def test_small_tree_ten_points_and_no_points_below_crown():
    rng = np.random.default_rng(7)
    xyz = sphere_shell(10, [0, 0, 15], [1, 1, 1], rng)
    rec = GuidedGrowth().reconstruct(TreePoints(1, xyz, 0.0))
    assert_valid_tree(rec.skeleton)
    assert rec.skeleton.nodes[0, 2] == 0.0 and rec.skeleton.nodes[:, 2].max() > 14.0
    assert rec.visited_fraction >= 0.9


def test_points_below_ground_and_empty():
    rng = np.random.default_rng(8)
    xyz = cone_tree(rng, n=300, ground=0.0)
    xyz[0, 2] = -1.0
    rec = GuidedGrowth().reconstruct(TreePoints(1, xyz, 0.0))
    assert "points_below_ground" in rec.flags and rec.skeleton.nodes[0, 2] == -1.0
    with pytest.raises(EmptyInputError, match="tree 4"):
        GuidedGrowth().reconstruct(TreePoints(4, np.zeros((0, 3)), 0.0))


def test_species_presets_and_validation():
    assert set(SPECIES_PRESETS) == {"conifer", "broadleaf", "shrub"}
    c = GuidedGrowth(species="conifer")
    assert c.branching_angle_deg == SPECIES_PRESETS["conifer"]["branching_angle_deg"]
    assert GuidedGrowth(species="conifer", branching_angle_deg=50.0).branching_angle_deg == 50.0
    s = GuidedGrowth(species="shrub")
    assert s.step_m == 0.15 and s.kill_distance_m == 0.3
    d = GuidedGrowth()
    assert (d.step_m, d.attraction_weight, d.tropism, d.similarity_cos) == (0.25, 1.6, 0.3, 0.9)
    assert (d.influence_h0, d.influence_rho0, d.perception_angle_deg) == (2.0, 0.3, 90.0)
    with pytest.raises(InputError, match="species"):
        GuidedGrowth(species="palm")
    with pytest.raises(InputError, match="step_m"):
        GuidedGrowth(step_m=0)
    with pytest.raises(InputError, match="crown_fill"):
        GuidedGrowth(crown_fill="sometimes")
    with pytest.raises(Exception):
        d.step_m = 1.0            # frozen


def test_species_changes_the_result():
    rng = np.random.default_rng(9)
    xyz = cone_tree(rng)
    a = GuidedGrowth(species="conifer").reconstruct(TreePoints(1, xyz, 100.0))
    b = GuidedGrowth(species="broadleaf").reconstruct(TreePoints(1, xyz, 100.0))
    assert not (len(a.skeleton) == len(b.skeleton) and np.allclose(a.skeleton.nodes, b.skeleton.nodes))
    for rec in (a, b):
        assert (rec.skeleton.distance(xyz) < 0.5).mean() >= 0.9


def test_progress_cancel_and_dispatch():
    from sylva.core.reconstruct import reconstruct_tree

    rng = np.random.default_rng(10)
    tree = TreePoints(2, cone_tree(rng, n=400), 100.0)
    seen = []
    rec = reconstruct_tree(tree, GuidedGrowth(), progress=lambda f, m: seen.append(f))
    assert rec.method == "guided_growth" and seen and seen[-1] == 1.0
    assert all(0.0 <= f <= 1.0 for f in seen)
    with pytest.raises(Cancelled):
        GuidedGrowth().reconstruct(tree, cancelled=lambda: True)
