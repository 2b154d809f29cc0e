"""Tree geometry: pipe-model and allometric radii, branch chains, Hermite smoothing,
rotation-minimising frames, generalised cylinders, tree meshes and wood measurements."""
import importlib.util
from pathlib import Path

import numpy as np
import pytest
import trimesh

from sylva.core import geometry as G
from sylva.core.errors import InputError
from sylva.core.skeleton import Skeleton

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("geometry_bench", ROOT / "benchmarks" / "geometry.py")
_bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_bench)
random_skeleton = _bench.random_skeleton


def y_skeleton():
    """Root, fork at 2 m, two equal arms."""
    return Skeleton(np.array([[0, 0, 0], [0, 0, 2], [1, 0, 3], [-1, 0, 3.0]]), np.array([-1, 0, 1, 1]))


def vertical(n=11, height=10.0, radius=None):
    nodes = np.c_[np.zeros(n), np.zeros(n), np.linspace(0, height, n)]
    r = None if radius is None else np.full(n, radius)
    return Skeleton(nodes, np.r_[-1, np.arange(n - 1)], radius=r)


# --------------------------------------------------------------------------- radii

def test_pipe_model_on_y_obeys_eq6_exactly():
    sk = y_skeleton()
    r = G.pipe_model_radii(sk, tip_radius_m=0.05)
    assert r[2] == r[3] == 0.05                                     # R_up,tip = R_const
    assert r[1] ** 2 == pytest.approx(r[2] ** 2 + r[3] ** 2, rel=1e-14)  # R_up^2 = sum R_low^2
    assert r[0] == pytest.approx(r[1], rel=1e-14)                   # single child: same pipe
    assert np.all(sk.radius == 0)                                   # not mutated
    G.pipe_model_radii(sk, tip_radius_m=0.05, inplace=True)
    assert np.allclose(sk.radius, r)


@pytest.mark.parametrize("exponent", [2.0, 2.5, 3.0])
def test_pipe_model_relation_and_monotone_on_random_tree(exponent):
    sk = random_skeleton(400, seed=4)
    r = G.pipe_model_radii(sk, tip_radius_m=0.01, exponent=exponent)
    kids = sk.children()
    internal = [i for i in range(len(sk)) if len(kids[i])]
    lhs = np.array([r[i] ** exponent for i in internal])
    rhs = np.array([(r[kids[i]] ** exponent).sum() for i in internal])
    assert np.allclose(lhs, rhs, rtol=1e-12)
    assert np.all(r[sk.tips()] == 0.01)
    child, par = sk.segments()
    assert np.all(r[child] <= r[par] * (1 + 1e-12))                  # non-increasing to the tips
    # the root carries every tip: r_root = R_const * n_tips^(1/e)
    assert r[0] == pytest.approx(0.01 * len(sk.tips()) ** (1 / exponent), rel=1e-12)


def test_pipe_model_scaled_to_trunk_radius_keeps_relation():
    sk = random_skeleton(200, seed=2)
    r = G.pipe_model_radii(sk, tip_radius_m=0.01, trunk_radius_m=0.25)
    assert r[0] == pytest.approx(0.25, rel=1e-14)
    kids = sk.children()
    for i in range(len(sk)):
        if len(kids[i]):
            assert r[i] ** 2 == pytest.approx((r[kids[i]] ** 2).sum(), rel=1e-12)


def test_pipe_model_rejects_bad_parameters():
    with pytest.raises(InputError, match="tip_radius_m"):
        G.pipe_model_radii(y_skeleton(), tip_radius_m=0.0)
    with pytest.raises(InputError, match="exponent"):
        G.pipe_model_radii(y_skeleton(), exponent=-1)
    with pytest.raises(InputError, match="radii"):
        G.with_radii(y_skeleton(), np.ones(3))


def test_allometric_radii_guo_eq5():
    # fork at 2 m; arm a: one segment of sqrt(2) m; arm b: two segments, 1 m + 3 m
    nodes = np.array([[0, 0, 0], [0, 0, 2], [1, 0, 3], [0, 1, 2], [0, 4, 2.0]])
    sk = Skeleton(nodes, np.array([-1, 0, 1, 1, 3]))
    r = G.allometric_radii(sk, root_radius_m=0.2, gamma=0.5)
    la, lb = np.sqrt(2.0), 4.0
    assert r[0] == r[1] == 0.2                                       # one child keeps d_p
    assert r[2] == pytest.approx(0.2 * (la / (la + lb)) ** 0.5, rel=1e-12)
    assert r[3] == pytest.approx(0.2 * (lb / (la + lb)) ** 0.5, rel=1e-12)
    assert r[4] == pytest.approx(r[3], rel=1e-12)
    # gamma = 0.5: cross-sections add up at the fork (da Vinci)
    assert r[2] ** 2 + r[3] ** 2 == pytest.approx(r[1] ** 2, rel=1e-12)
    assert np.all(sk.radius == 0)
    rr = G.assign_radii(sk, G.Allometric(root_radius_m=0.2, gamma=0.5))
    assert np.array_equal(rr, r)


def test_with_radii_copies():
    sk = y_skeleton()
    r = G.pipe_model_radii(sk)
    sk2 = G.with_radii(sk, r)
    assert np.array_equal(sk2.radius, r) and np.all(sk.radius == 0)
    sk2.nodes[0, 0] = 5.0
    assert sk.nodes[0, 0] == 0.0


# --------------------------------------------------------------------------- branches

def test_branches_follow_the_straightest_child():
    # 1 has children 2 (sideways) and 3 (straight up): the trunk continues into 3
    nodes = np.array([[0, 0, 0], [0, 0, 1], [1, 0, 1.2], [0, 0, 2], [2, 0, 1.4], [0, 0, 3.0]])
    sk = Skeleton(nodes, np.array([-1, 0, 1, 1, 2, 3]))
    b = G.branches(sk)
    assert [list(c) for c in b.chains] == [[0, 1, 3, 5], [1, 2, 4]]
    assert list(b.parent) == [-1, 0] and list(b.attach) == [-1, 1]
    assert list(b.node_branch) == [0, 0, 1, 0, 1, 0]
    assert list(b.order) == [0, 1]


def test_branches_cover_every_segment_once():
    sk = random_skeleton(500, seed=7)
    b = G.branches(sk)
    segs = set()
    for c in b.chains:
        for u, v in zip(c[:-1], c[1:]):
            assert sk.parent[v] == u
            segs.add((int(u), int(v)))
    child, par = sk.segments()
    assert segs == set(zip(par.tolist(), child.tolist()))
    assert len(b) == len(sk.tips())                                  # one chain per tip
    assert all(len(sk.children()[c[-1]]) == 0 for c in b.chains)
    for k in range(1, len(b)):
        assert b.parent[k] < k and b.chains[k][0] == b.attach[k]
        assert b.node_branch[b.attach[k]] == b.parent[k]
        assert b.order[k] == b.order[b.parent[k]] + 1
    # the trunk runs from the root up the stem
    assert b.chains[0][0] == 0 and len(b.chains[0]) >= 40


# --------------------------------------------------------------------------- smoothing and frames

def test_hermite_passes_through_nodes_and_interpolates_radii():
    pts = np.array([[0, 0, 0], [1, 0, 0.5], [2, 1, 1], [2.5, 2, 2.0]])
    rad = np.array([0.4, 0.3, 0.2, 0.1])
    sp, sr = G.hermite_smooth(pts, 5, radii=rad)
    assert sp.shape == (16, 3)
    assert np.allclose(sp[::5], pts, atol=1e-12)
    assert np.allclose(sr[::5], rad)
    assert np.allclose(sr[:6], np.linspace(0.4, 0.3, 6))             # linear between nodes
    line = np.c_[[0.0, 0.5, 2.0, 3.0], np.zeros(4), np.zeros(4)]     # uneven spacing on a line
    s = G.hermite_smooth(line, 4)
    assert np.allclose(s[:, 1:], 0.0) and np.all(np.diff(s[:, 0]) > 0)  # no overshoot


def test_hermite_follows_a_circle_better_than_the_polyline():
    th = np.linspace(0, np.pi, 12)
    circle = np.c_[np.cos(th), np.sin(th), np.zeros(12)]
    s = G.hermite_smooth(circle, 8)
    interior = s[8:-8]                                               # Catmull-Rom tangents inside
    err = np.abs(np.linalg.norm(interior, axis=1) - 1.0).max()
    chord_err = 1 - np.cos(np.pi / 22)                               # polyline sagitta, 0.0102
    assert err < chord_err / 20


def test_rmf_on_a_helix_has_no_twist():
    a, b = 2.0, 0.5
    t = np.linspace(0, 4 * np.pi, 400)
    pts = np.c_[a * np.cos(t), a * np.sin(t), b * t]
    T, R, S = G.rotation_minimizing_frames(pts)
    assert np.allclose(np.einsum("ij,ij->i", T, R), 0, atol=1e-12)
    assert np.allclose(np.linalg.norm(R, axis=1), 1) and np.allclose(np.cross(T, R), S)
    # exact RMF: relative to the Frenet normal it turns at -torsion * ds (Wang et al. 2008)
    frenet_n = np.c_[-np.cos(t), -np.sin(t), np.zeros_like(t)]
    frenet_b = np.cross(T, frenet_n)
    ang = np.unwrap(np.arctan2(np.einsum("ij,ij->i", R, frenet_b), np.einsum("ij,ij->i", R, frenet_n)))
    rate = -b / (a * a + b * b) * np.hypot(a, b) * (t[1] - t[0])
    assert np.allclose(np.diff(ang)[2:-2], rate, rtol=1e-6)
    # consecutive normals turn no more than the tangent does: no flips, no spin about t
    normal_turn = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", R[1:], R[:-1]), -1, 1)))
    tangent_turn = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", T[1:], T[:-1]), -1, 1)))
    assert normal_turn.max() < 2.0 and normal_turn.max() <= tangent_turn.max() * 1.01
    twist = np.abs(np.einsum("ij,ij->i", R[1:], S[:-1]))
    assert twist.max() < 3e-4


def test_rmf_sharp_90_degree_bend_and_straight_line():
    leg = np.linspace(0, 5, 11)
    pts = np.r_[np.c_[0 * leg, 0 * leg, leg], np.c_[leg[1:], 0 * leg[1:], 5 + 0 * leg[1:]]]
    T, R, S = G.rotation_minimizing_frames(pts)
    assert np.abs(S - S[0]).max() < 1e-12                            # planar curve: binormal fixed
    assert np.allclose(R[0], [1, 0, 0]) and np.allclose(R[-1], [0, 0, -1], atol=1e-12)
    assert np.einsum("ij,ij->i", R[1:], R[:-1]).min() > np.cos(np.radians(45.01))  # no flip
    line = np.c_[np.linspace(0, 1, 20), np.linspace(0, 2, 20), np.linspace(0, 3, 20)]
    T, R, S = G.rotation_minimizing_frames(line, normal0=[0, 0, 1])
    assert np.abs(R - R[0]).max() < 1e-12 and np.abs(S - S[0]).max() < 1e-12
    assert abs(R[0] @ T[0]) < 1e-12


# --------------------------------------------------------------------------- tubes

@pytest.mark.parametrize("sides", [4, 8, 16])
def test_straight_tube_is_watertight_with_cylinder_volume(sides):
    v, f = G.sweep_tube(np.array([[0, 0, 0], [0, 0, 4.0], [0, 0, 10.0]]), 0.2, sides=sides)
    mesh = trimesh.Trimesh(v, f, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    polygon = sides / 2 * 0.2 ** 2 * np.sin(2 * np.pi / sides)       # inscribed polygon area
    assert mesh.volume == pytest.approx(polygon * 10.0, rel=1e-9)    # > 0: outward normals
    if sides == 16:
        assert mesh.volume == pytest.approx(np.pi * 0.04 * 10, rel=0.03)
    assert len(f) == 2 * sides * 2 + 2 * sides
    v2, f2 = G.sweep_tube(np.array([[0, 0, 0], [0, 0, 10.0]]), 0.2, sides=sides, cap=False)
    assert not trimesh.Trimesh(v2, f2, process=False).is_watertight


def test_tapered_bent_tube_is_watertight():
    t = np.linspace(0, 3 * np.pi, 120)
    helix = np.c_[np.cos(t), np.sin(t), 0.3 * t]
    v, f = G.sweep_tube(helix, np.linspace(0.2, 0.05, 120), sides=12)
    mesh = trimesh.Trimesh(v, f, process=False)
    assert mesh.is_watertight and mesh.volume > 0
    length = np.linalg.norm(np.diff(helix, axis=0), axis=1).sum()
    frustum = np.pi * length / 3 * (0.2 ** 2 + 0.2 * 0.05 + 0.05 ** 2)
    assert mesh.volume == pytest.approx(frustum, rel=0.05)
    with pytest.raises(InputError):
        G.sweep_tube(np.zeros((3, 3)), 0.1)


def test_tree_mesh_tubes_watertight_and_lods_monotone():
    sk = random_skeleton(300, seed=5)
    sk = G.with_radii(sk, G.pipe_model_radii(sk, tip_radius_m=0.008))
    faces = []
    for lod in range(3):
        mesh = G.tree_mesh(sk, lod)
        faces.append(len(mesh.faces))
        fb = mesh.metadata["face_branch"]
        assert len(fb) == len(mesh.faces)
        tubes = G.tree_mesh(sk, lod, per_branch=True)
        assert len(tubes) == len(np.unique(fb))
        assert all(t.is_watertight and t.volume > 0 for t in tubes)
    assert faces[0] < faces[1] < faces[2]
    # the fine level keeps every branch, the coarse one prunes twigs but keeps the trunk
    parts2 = G.tree_mesh_arrays(sk, 2)
    parts0 = G.tree_mesh_arrays(sk, 0)
    assert parts2.kept.all() and parts0.kept[0] and not parts0.kept.all()
    # pruned branches take their sub-branches with them
    b = parts0.branches
    assert not np.any(parts0.kept[1:] & ~parts0.kept[b.parent[1:]])


def test_side_branch_starts_inside_parent_with_own_radius():
    sk = y_skeleton()
    r = G.pipe_model_radii(sk, tip_radius_m=0.05)
    parts = G.tree_mesh_arrays(sk, G.LevelOfDetail(sides=8, samples_per_segment=1), radii=r)
    side = parts.faces[parts.face_branch == 1]
    vs = parts.vertices[np.unique(side)]
    near_fork = vs[np.linalg.norm(vs - sk.nodes[1], axis=1) < 0.06]
    # first ring of the side branch: on a circle of the child's radius around the fork node
    d = np.linalg.norm(near_fork - sk.nodes[1], axis=1)
    assert np.allclose(d[d > 1e-9], 0.05)
    assert (d[d > 1e-9] < r[1]).all()                                 # inside the parent tube


def test_tree_mesh_defaults_to_pipe_model_and_handles_tiny_skeletons():
    mesh = G.tree_mesh(y_skeleton(), 1)
    assert len(mesh.faces) > 0
    single = Skeleton(np.zeros((1, 3)), np.array([-1]))
    assert len(G.tree_mesh(single, 1).faces) == 0
    dup = Skeleton(np.array([[0, 0, 0], [0, 0, 0], [0, 0, 1.0]]), np.array([-1, 0, 1]))
    tubes = G.tree_mesh(dup, 2, per_branch=True)
    assert len(tubes) == 1 and tubes[0].is_watertight
    with pytest.raises(InputError, match="lod"):
        G.tree_mesh(y_skeleton(), 7)


# --------------------------------------------------------------------------- measurements

def test_wood_volume_and_counts():
    sk = vertical(11, 10.0, radius=0.2)
    assert abs(G.wood_volume(sk) - np.pi * 0.04 * 10) < 1e-9
    cone = Skeleton(sk.nodes, sk.parent, radius=np.linspace(0.3, 0.1, 11))
    h = 1.0
    r = cone.radius
    expect = (np.pi * h / 3 * (r[:-1] ** 2 + r[:-1] * r[1:] + r[1:] ** 2)).sum()
    assert G.wood_volume(cone) == pytest.approx(expect, rel=1e-12)
    y = y_skeleton()
    r = G.pipe_model_radii(y, tip_radius_m=0.05)
    side = np.sqrt(2.0)
    expect = (np.pi * 2 * r[1] ** 2                                   # stem: cylinder
              + np.pi * side / 3 * (r[1] ** 2 + r[1] * 0.05 + 0.05 ** 2)  # leader tapers from the fork
              + np.pi * side * 0.05 ** 2)                             # side arm: its own radius
    assert G.wood_volume(y, r) == pytest.approx(expect, rel=1e-12)
    assert G.branch_count(y) == 1 and G.branch_count(y, include_stem=True) == 2
    assert G.total_branch_length(y) == pytest.approx(side)
    assert G.total_branch_length(y, include_stem=True) == pytest.approx(2 + 2 * side)
    assert G.branch_count(vertical()) == 0


def test_depth_levels_match_skeleton_depth():
    sk = random_skeleton(600, seed=9)
    levels = G.depth_levels(sk)
    depth = sk.depth()
    assert sum(len(lv) for lv in levels) == len(sk)
    for d, lv in enumerate(levels):
        assert np.all(depth[lv] == d)
