"""Tests of Hu et al. (2017) tree skeletons: core/reconstruct (trunk, thinning, graph,
direction field, greedy skeleton, GreedySkeleton, reconstruct_tree, data classes)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from sylva.core.errors import Cancelled, EmptyInputError, InputError
from sylva.core.reconstruct import GreedySkeleton, Reconstruction, Skeleton, TreePoints, reconstruct_tree
from sylva.core.reconstruct.direction import direction_angles, direction_field
from sylva.core.reconstruct.graph import build_graph
from sylva.core.reconstruct.skeleton import greedy_skeleton
from sylva.core.reconstruct.thinning import _OFFSETS, is_simple, thin_voxels
from sylva.core.reconstruct.trunk import add_trunk_points


# --- synthetic single trees -------------------------------------------------------

def cone_crown(rng, centre=(0.0, 0.0), ground_z=0.0, height=15.0, crown_base=5.0, radius=3.0,
               density=20.0, interior=0.3):
    """Airborne-like returns of a conical crown: first returns on the cone surface,
    a share of deeper returns inside it; ``density`` points per m2 of crown area."""
    n = rng.poisson(density * np.pi * radius ** 2)
    r = radius * np.sqrt(rng.random(n))
    a = rng.random(n) * 2 * np.pi
    z = ground_z + height - (r / radius) * (height - crown_base)
    deep = rng.random(n) < interior
    z[deep] -= rng.random(deep.sum()) * (z[deep] - (ground_z + crown_base)) * 0.8
    r[deep] *= rng.random(deep.sum())
    pts = np.c_[centre[0] + r * np.cos(a), centre[1] + r * np.sin(a), z]
    return pts + rng.normal(0.0, 0.03, pts.shape)


def line(a, b, n):
    t = np.linspace(0.0, 1.0, n)[:, None]
    return np.asarray(a, float) + t * (np.asarray(b, float) - np.asarray(a, float))


def angle_deg(u, v):
    u = np.asarray(u, float)
    v = np.asarray(v, float)
    c = np.sum(u * v, axis=-1) / (np.linalg.norm(u, axis=-1) * np.linalg.norm(v, axis=-1))
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


# --- §4.2 trunk points --------------------------------------------------------------

def test_trunk_eq4_reaches_ground_under_crown_centre_without_trunk_points():
    rng = np.random.default_rng(1)
    xyz = cone_crown(rng, centre=(10.0, 20.0), ground_z=100.0)
    trunk = add_trunk_points(xyz, 100.0)
    assert trunk.rule == "eq4"
    assert trunk.lambda2 > 0.5            # lowest point is on the crown rim
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    g_b = np.r_[(lo[:2] + hi[:2]) / 2, 100.0]
    np.testing.assert_allclose(trunk.root, g_b)
    assert np.hypot(*(trunk.root[:2] - [10.0, 20.0])) < 0.3
    np.testing.assert_allclose(trunk.points[0], g_b)
    np.testing.assert_allclose(trunk.points[-1], xyz.mean(axis=0))       # up to the centroid v_c
    steps = np.linalg.norm(np.diff(trunk.points, axis=0), axis=1)
    assert steps.max() <= 0.1 + 1e-9
    # all on the straight line g_b -> v_c (Eq. 4)
    axis = (xyz.mean(axis=0) - g_b) / np.linalg.norm(xyz.mean(axis=0) - g_b)
    rel = trunk.points - g_b
    assert np.abs(rel - (rel @ axis)[:, None] * axis).max() < 1e-9
    np.testing.assert_allclose(trunk.direction, axis)


def test_trunk_eq3_follows_lowest_points_when_lambdas_allow():
    rng = np.random.default_rng(2)
    crown = cone_crown(rng, centre=(0.0, 0.0))
    stem = line([0.3, 0.0, 1.0], [0.0, 0.0, 5.0], 17)          # leaning stem seen by a few pulses
    xyz = np.r_[crown, stem]
    trunk = add_trunk_points(xyz, 0.0)
    assert trunk.rule == "eq3"
    d = (stem[-1] - stem[0]) / np.linalg.norm(stem[-1] - stem[0])
    assert angle_deg(trunk.direction, d) < 2.0
    assert trunk.lambda1_deg <= 30.0 and trunk.lambda2 <= 0.5
    # root = v_low - n_avg * h / n_avg.z, on the ground
    expected_root = stem[0] - d * (1.0 / d[2])
    np.testing.assert_allclose(trunk.root, expected_root, atol=0.02)
    assert trunk.root[2] == 0.0
    np.testing.assert_allclose(trunk.points[-1], stem[0])
    # a stricter λ1 than the stem's 4.3° lean switches to Eq. 4
    strict = add_trunk_points(xyz, 0.0, lambda1_max_deg=1.0)
    assert strict.rule == "eq4"
    assert strict.lambda1_deg == pytest.approx(trunk.lambda1_deg)


def test_trunk_eq3_rejected_when_lowest_point_off_centre():
    rng = np.random.default_rng(3)
    crown = cone_crown(rng)
    stem = line([2.6, 0.0, 1.0], [2.6, 0.0, 4.0], 13)           # vertical but far off the centre line
    trunk = add_trunk_points(np.r_[crown, stem], 0.0)
    assert trunk.lambda1_deg < 30.0 and trunk.lambda2 > 0.5
    assert trunk.rule == "eq4"


# --- §5.1 thinning -------------------------------------------------------------------

def _offset_index(d):
    return int(np.flatnonzero((_OFFSETS == d).all(axis=1))[0])


def test_is_simple_known_configurations():
    full = np.ones((1, 26), bool)
    empty = np.zeros((1, 26), bool)
    one = empty.copy()
    one[0, _offset_index([0, 0, -1])] = True
    two_opposite = one.copy()
    two_opposite[0, _offset_index([0, 0, 1])] = True
    half_space = np.array([[o[2] <= 0 for o in _OFFSETS]])       # flat surface voxel
    octant = np.array([[(o >= 0).all() for o in _OFFSETS]])      # corner of a cube
    res = is_simple(np.r_[full, empty, one, two_opposite, half_space, octant])
    assert res.tolist() == [False, False, True, False, True, True]


def _voxel_components(points, voxel_m, origin):
    ijk = np.floor((points - origin) / voxel_m + 1e-9).astype(int)
    tree = cKDTree(ijk)
    pairs = tree.query_pairs(np.sqrt(3) + 1e-6, output_type="ndarray")
    from scipy.sparse import coo_matrix
    m = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(ijk), len(ijk)))
    return connected_components(m, directed=False)[0]


def test_thinning_reduces_a_solid_and_keeps_it_connected():
    g = np.arange(0.05, 2.0, 0.1)
    block = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    # an L-shaped solid: block plus an arm
    arm = block[(block[:, 0] < 0.6) & (block[:, 1] < 0.6)] + [0.0, 0.0, 2.0]
    xyz = np.r_[block, arm]
    th = thin_voxels(xyz, 0.2)
    assert len(th.voxel_means) == 1000 + 9 * 10
    assert len(th.points) < 0.2 * len(th.voxel_means)
    origin = xyz.min(axis=0)
    assert _voxel_components(th.voxel_means[th.voxel_index], 0.2, origin) == 1
    # every surviving candidate is the mean of its voxel's points
    v = th.voxel_index[0]
    np.testing.assert_allclose(th.points[0], xyz[th.voxel_of_point == v].mean(axis=0))


def test_thinning_keeps_lines_and_protected_voxels():
    stem = line([0, 0, 0], [0, 0, 5], 51)
    th = thin_voxels(stem, 0.2)
    assert len(th.voxel_means) == 26 and len(th.points) == 26      # a curve is already thin
    g = np.arange(0.05, 1.0, 0.1)
    block = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    keep = np.zeros(len(block), bool)
    keep[:50] = True
    th = thin_voxels(block, 0.2, keep=keep)
    kept_voxels = np.unique(th.voxel_of_point[keep])
    assert np.isin(kept_voxels, th.voxel_index).all()
    assert len(th.points) < len(th.voxel_means)


# --- §5.2 graph ---------------------------------------------------------------------

def test_graph_connected_for_dense_cone_and_knn_links_sparse_points():
    rng = np.random.default_rng(4)
    cone = cone_crown(rng, density=20)
    g = build_graph(cone, 1.2, 16)
    assert g.connected and g.n_components == 1
    A = g.adjacency
    assert (abs(A - A.T)).max() < 1e-12
    # FRNN: every pair within r_p is an edge, with its length as weight
    pairs = cKDTree(cone).query_pairs(1.2, output_type="ndarray")
    w = np.asarray(A[pairs[:, 0], pairs[:, 1]]).ravel()
    np.testing.assert_allclose(w, np.linalg.norm(cone[pairs[:, 0]] - cone[pairs[:, 1]], axis=1))
    # an isolated point 5 m away gets its k nearest neighbours (Algorithm 1, second loop)
    far = np.r_[cone, [[20.0, 0.0, 10.0]]]
    g2 = build_graph(far, 1.2, 16)
    assert g2.connected
    assert A.shape[0] + 1 == g2.adjacency.shape[0]
    assert g2.adjacency[len(cone)].nnz == 16
    # a far pair that has its one FRNN neighbour (n_i >= k = 1) is left apart
    g0 = build_graph(np.r_[cone, [[40.0, 0.0, 10.0], [41.0, 0.0, 10.0]]], 1.2, 1)
    assert g0.n_components == 2
    assert g0.labels[-1] == g0.labels[-2] != g0.labels[0]


def test_graph_two_dense_clusters_far_apart_are_not_connected():
    rng = np.random.default_rng(5)
    a = cone_crown(rng, centre=(0, 0), density=20)
    b = cone_crown(rng, centre=(30, 0), density=20)
    g = build_graph(np.r_[a, b], 1.2, 16)
    assert g.n_components == 2 and not g.connected


# --- §5.3 direction field ------------------------------------------------------------

def test_direction_field_matches_eq5_at_top_bottom_and_centre():
    # bounding box: centre line x=y=0, L_c = 4, z in [0, 10]
    pts = np.array([
        [0.0, 0.0, 5.0],      # on the centre line -> 90°
        [4.0, 0.0, 10.0],     # upper right corner -> θu
        [4.0, 0.0, 0.0],      # lower right corner -> θl
        [0.0, -4.0, 0.0],     # lower "left" (any side: rotated) -> θl
        [2.0, 0.0, 5.0],      # middle
        [-4.0, 0.0, 10.0],    # box corners so that the box is symmetric
    ])
    box = dict(centre_xy=[0.0, 0.0], z_range=(0.0, 10.0), radius_m=4.0)
    th = direction_angles(pts, 80, -40, 1.4, 1.0, **box)
    assert th[0] == pytest.approx(90.0)
    assert th[1] == pytest.approx(80.0)
    assert th[2] == pytest.approx(-40.0)
    assert th[3] == pytest.approx(-40.0)
    mu1, mu2 = 0.5 ** 1.4, 0.5 ** 1.0
    assert th[4] == pytest.approx(90 - (90 + 40 - mu1 * 120) * mu2)
    u = direction_field(pts, 80, -40, 1.4, 1.0, **box)
    # defaults derive the same box from the points' bounding box
    sym = np.r_[pts, [[0.0, 4.0, 10.0]]]
    np.testing.assert_allclose(direction_angles(sym)[:6], th)
    np.testing.assert_allclose(np.linalg.norm(u, axis=1), 1.0)
    np.testing.assert_allclose(u[0], [0, 0, 1], atol=1e-12)
    elev = np.degrees(np.arcsin(u[:, 2]))
    np.testing.assert_allclose(elev, th, atol=1e-9)
    # horizontal part points away from the centre line
    np.testing.assert_allclose(u[1, :2] / np.linalg.norm(u[1, :2]), [1, 0], atol=1e-12)
    np.testing.assert_allclose(u[3, :2] / np.linalg.norm(u[3, :2]), [0, -1], atol=1e-12)
    # the paper's 3-D formula: (p.x - pc.x, |p - pc| tan θ, p.z - pc.z) in y-up
    p = pts[4]
    paper = np.array([p[0], np.hypot(p[0], p[1]) * np.tan(np.radians(th[4])), p[1]])
    paper /= np.linalg.norm(paper)
    np.testing.assert_allclose(u[4], [paper[0], paper[2], paper[1]], atol=1e-12)


# --- §5.4 greedy skeleton --------------------------------------------------------------

@pytest.fixture(scope="module")
def cone_tree():
    rng = np.random.default_rng(6)
    xyz = cone_crown(rng, centre=(5.0, 5.0), ground_z=100.0, density=20)
    tree = TreePoints(3, xyz, 100.0)
    return tree, reconstruct_tree(tree, GreedySkeleton())


def test_greedy_skeleton_is_a_tree_rooted_on_the_ground(cone_tree):
    tree, rec = cone_tree
    sk = rec.skeleton
    assert isinstance(rec, Reconstruction) and rec.method == "greedy_skeleton"
    assert sk.parent[0] == -1 and (sk.parent == -1).sum() == 1
    assert (sk.parent[1:] < np.arange(1, len(sk))).all() and (sk.parent[1:] >= 0).all()
    assert sk.nodes[0, 2] == 100.0
    assert np.hypot(*(sk.nodes[0, :2] - 5.0)) < 0.3
    assert len(np.unique(sk.nodes, axis=0)) == len(sk)     # every point used at most once
    assert sk.is_added[0] and sk.is_added[1]                # root and first trunk node are added
    assert len(sk) > 50 and rec.connected
    assert rec.visited_fraction > 0.8       # a cone's lower rim is hard to reach within α_max
    assert (sk.distance(tree.xyz) < 0.5).mean() > 0.85


def test_greedy_skeleton_respects_alpha_and_beta(cone_tree):
    tree, rec = cone_tree
    sk = rec.skeleton
    method = GreedySkeleton()
    idx = np.arange(len(sk))
    has_gp = (sk.parent >= 0) & (sk.parent[np.maximum(sk.parent, 0)] >= 0)
    child = idx[has_gp]
    par = sk.parent[child]
    gp = sk.parent[par]
    v_child = sk.nodes[child] - sk.nodes[par]
    v_parent = sk.nodes[par] - sk.nodes[gp]
    alpha = angle_deg(v_child, v_parent)
    assert alpha.max() < method.alpha_max_deg
    # β against the direction field of the same candidate set, measured nodes only
    from sylva.core.reconstruct.trunk import add_trunk_points as _t
    trunk = _t(tree.xyz, tree.ground_z)
    th = thin_voxels(np.r_[tree.xyz, trunk.points[1:]], 0.2)
    cand = np.r_[trunk.root[None], th.points]
    u = direction_field(cand)
    pos = {tuple(p): i for i, p in enumerate(cand)}
    measured = ~sk.is_added[child]
    ui = u[[pos[tuple(p)] for p in sk.nodes[child[measured]]]]
    assert angle_deg(ui, v_child[measured]).max() < method.beta_max_deg


def test_greedy_skeleton_on_a_hand_made_graph():
    # a vertical trunk with a side branch that bends by 45° and one that bends back (135°)
    pts = np.array([[0, 0, 0], [0, 0, 1], [0, 0, 2], [0.7, 0, 2.7], [-0.7, 0, 0.3], [0, 0, 3]], float)
    g = build_graph(pts, 1.5, 1)
    up = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    res = greedy_skeleton(pts, g.adjacency, up, 0, 1, alpha_max_deg=70, beta_max_deg=70, phi_max_deg=30)
    sk = Skeleton(pts[res.point_of_node], res.parent)
    got = {tuple(pts[p]) for p in res.point_of_node}
    assert (0.7, 0.0, 2.7) in got and (0.0, 0.0, 3.0) in got
    assert (-0.7, 0.0, 0.3) not in got                    # would bend by more than α_max
    assert not res.visited[4]
    assert res.visited[:4].all()
    assert len(sk.tips()) == 2


def test_pruning_removes_close_directions():
    # from p1 three candidates: straight up, 10° off (pruned, φ < 30°), 45° off (kept)
    s10 = np.sin(np.radians(10)); c10 = np.cos(np.radians(10))
    pts = np.array([[0, 0, 0], [0, 0, 1], [0, 0, 2], [s10 * 0.9, 0, 1 + c10 * 0.9],
                    [-np.sqrt(0.5), 0, 1 + np.sqrt(0.5)]])
    g = build_graph(pts, 1.05, 1)
    up = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    res = greedy_skeleton(pts, g.adjacency, up, 0, 1)
    assert set(res.point_of_node.tolist()) == {0, 1, 2, 4}
    assert res.visited.all()                               # the pruned one counts as visited
    assert res.parent.tolist() == [-1, 0, 1, 1]


# --- synthetic stands (testing/synth) ------------------------------------------------------

@pytest.fixture(scope="module")
def synth_trees():
    synth = pytest.importorskip("sylva.testing.synth")
    stand = synth.make_stand(synth.StandSpec(width_m=40.0, depth_m=40.0, seed=3))
    scan = synth.simulate_scan(stand, synth.ScanSpec(pulse_density=20.0, seed=3))
    origin = np.array([*stand.spec.origin, 0.0])
    out = []
    for t in stand.trees:
        m = scan.truth_tree == t.tree_id
        if m.sum() < 50:
            continue
        tp = TreePoints(t.tree_id, scan.cloud.xyz[m] - origin, t.ground_z)
        out.append((t, tp, reconstruct_tree(tp, GreedySkeleton()), np.array([t.x, t.y]) - origin[:2]))
    assert len(out) >= 5
    return out


def test_synth_trees_visited_and_root_position(synth_trees):
    visited = np.array([r.visited_fraction for _, _, r, _ in synth_trees])
    assert np.median(visited) > 0.9
    assert all(r.connected for _, _, r, _ in synth_trees)
    # single-stem trees whose crown is not clipped by the edge of the 40 m stand
    inner = [(t, r, base) for t, tp, r, base in synth_trees if t.species != "multistem"
             and (base > t.crown_radius_m).all() and (base < 40.0 - t.crown_radius_m).all()]
    assert len(inner) >= 10
    err = np.array([np.hypot(*(r.skeleton.nodes[0, :2] - base)) for t, r, base in inner])
    rule = np.array([r.stats["trunk_rule"] for t, r, base in inner])
    assert np.median(err) < 0.25
    assert (err < 0.5).mean() >= 0.8
    # Eq. 4 (root under the crown's box centre) is within 0.5 m on every such tree;
    # Eq. 3 extrapolates from stem returns on the stem's surface (see the report)
    assert (rule == "eq4").sum() >= 5 and (err[rule == "eq4"] < 0.5).all()
    for t, tp, r, base in synth_trees:
        assert r.skeleton.nodes[0, 2] == pytest.approx(min(tp.ground_z, tp.xyz[:, 2].min()))
        assert r.stats["n_candidates"] <= r.stats["n_voxels"] + 1
        assert 0.0 <= r.visited_fraction <= 1.0


def test_best_sampled_synth_tree_visits_over_90_percent(synth_trees):
    t, tp, r, base = max(synth_trees, key=lambda x: len(x[1]) if x[0].species != "multistem" else 0)
    assert r.visited_fraction > 0.9
    assert (r.skeleton.distance(tp.xyz) < 0.5).mean() > 0.9
    assert np.hypot(*(r.skeleton.nodes[0, :2] - base)) < 0.5


# --- degenerate input, errors, determinism, plumbing ---------------------------------------

@pytest.mark.parametrize("xyz, flag", [
    (np.array([[0, 0, 5.0], [0.5, 0, 6], [0, 0.5, 7], [1, 1, 4]]), "too_few_points"),
    (np.repeat(np.array([[0, 0, 5.0], [1, 0, 6], [0, 1, 7]]), 20, axis=0), "duplicate_points"),
    (line([0, 0, 2], [1, 1, 12], 40), "collinear_points"),
    (np.c_[np.random.default_rng(0).random((40, 2)) * 3, np.full(40, 8.0)], "coplanar_points"),
])
def test_degenerate_trees_are_flagged_with_a_minimal_stem(xyz, flag):
    rec = reconstruct_tree(TreePoints(11, xyz, 1.0), GreedySkeleton())
    assert rec.flags == [flag]
    assert rec.visited_fraction == 0.0 and not rec.connected
    sk = rec.skeleton
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    np.testing.assert_allclose(sk.nodes, [[*(lo[:2] + hi[:2]) / 2, 1.0], [*(lo[:2] + hi[:2]) / 2, hi[2]]])
    assert sk.parent.tolist() == [-1, 0] and sk.is_added.all()


def test_bad_input_raises_sylva_errors_naming_the_tree():
    with pytest.raises(EmptyInputError, match="tree 4"):
        reconstruct_tree(TreePoints(4, np.zeros((0, 3)), 0.0))
    with pytest.raises(InputError, match="tree 5"):
        TreePoints(5, np.zeros((10, 2)), 0.0)
    with pytest.raises(InputError, match="tree 6.*NaN"):
        TreePoints(6, np.full((10, 3), np.nan), 0.0)
    with pytest.raises(InputError, match="tree 7"):
        TreePoints(7, np.zeros((10, 3)), float("nan"))
    with pytest.raises(InputError, match="voxel_m"):
        GreedySkeleton(voxel_m=0)
    with pytest.raises(InputError, match="alpha_max_deg"):
        GreedySkeleton(alpha_max_deg=-5)
    with pytest.raises(InputError):
        reconstruct_tree(np.zeros((10, 3)))


def test_lowest_point_on_the_ground_gives_a_clean_trunk():
    rng = np.random.default_rng(12)
    stem = line([0, 0, 0], [0, 0, 5], 20)                       # lowest point exactly at ground_z
    crown = rng.random((300, 3)) * [4, 4, 8] + [-2, -2, 5]
    rec = reconstruct_tree(TreePoints(1, np.r_[stem, crown], 0.0), GreedySkeleton())
    assert rec.stats["trunk_rule"] == "eq3" and rec.stats["n_added"] == 1     # just the root
    sk = rec.skeleton
    np.testing.assert_allclose(sk.nodes[0], [0, 0, 0])
    assert np.linalg.norm(sk.nodes[1] - sk.nodes[0]) > 0.1                   # no zero-length segment
    assert np.all(sk.segment_lengths() > 1e-9)
    assert rec.visited_fraction > 0.85


def test_points_below_ground_are_flagged_not_fatal():
    rng = np.random.default_rng(8)
    xyz = cone_crown(rng)
    rec = reconstruct_tree(TreePoints(1, np.r_[xyz, [[0.1, 0.1, -0.4]]], 0.0), GreedySkeleton())
    assert "points_below_ground" in rec.flags
    assert rec.skeleton.nodes[0, 2] == pytest.approx(-0.4)


def test_determinism():
    rng = np.random.default_rng(9)
    tree = TreePoints(2, cone_crown(rng, density=15), 0.0)
    a, b = reconstruct_tree(tree, GreedySkeleton()), reconstruct_tree(tree, GreedySkeleton())
    np.testing.assert_array_equal(a.skeleton.nodes, b.skeleton.nodes)
    np.testing.assert_array_equal(a.skeleton.parent, b.skeleton.parent)
    assert a.visited_fraction == b.visited_fraction and a.flags == b.flags


def test_progress_cancel_and_dispatch():
    rng = np.random.default_rng(10)
    tree = TreePoints(2, cone_crown(rng, density=10), 0.0)
    seen = []
    reconstruct_tree(tree, GreedySkeleton(), progress=lambda f, m: seen.append(f))
    assert seen == sorted(seen) and seen[-1] == 1.0
    with pytest.raises(Cancelled):
        reconstruct_tree(tree, GreedySkeleton(), cancelled=lambda: True)

    class Stub:
        def reconstruct(self, tree, progress=None, cancelled=None):
            return Reconstruction(Skeleton(tree.xyz[:1], [-1]), "stub", 1.0, True)

    assert reconstruct_tree(tree, Stub()).method == "stub"
    with pytest.raises(InputError):
        reconstruct_tree(tree, object())


def test_paper_verbatim_mode_runs_and_differs_only_by_regrowth():
    rng = np.random.default_rng(11)
    tree = TreePoints(2, cone_crown(rng, density=20), 0.0)
    verbatim = reconstruct_tree(tree, GreedySkeleton(regrow_pruned=False))
    regrow = reconstruct_tree(tree, GreedySkeleton())
    assert verbatim.stats["n_candidates"] == regrow.stats["n_candidates"]
    assert len(regrow.skeleton) >= len(verbatim.skeleton)


# --- Skeleton helpers ---------------------------------------------------------------------

def test_skeleton_helpers():
    #      4   5
    #       \ /
    #   3    2
    #    \  /
    #      1
    #      |
    #      0
    nodes = np.array([[0, 0, 0], [0, 0, 1], [0.2, 0, 2], [-1, 0, 1.8], [0, 0, 3], [1.2, 0, 2.9]], float)
    sk = Skeleton(nodes, [-1, 0, 1, 1, 2, 2])
    assert [c.tolist() for c in sk.children()] == [[1], [2, 3], [4, 5], [], [], []]
    assert sk.tips().tolist() == [3, 4, 5]
    seg = np.linalg.norm(nodes[1:] - nodes[[0, 1, 1, 2, 2]], axis=1)
    assert sk.length() == pytest.approx(seg.sum())
    assert sk.depth().tolist() == [0, 1, 2, 2, 3, 3]
    d = sk.distance(np.array([[0.0, 0.5, 0.5], [0, 0, -2.0]]))
    np.testing.assert_allclose(d, [0.5, 2.0])
    with pytest.raises(ValueError):
        Skeleton(nodes[:2], [1, -1])
