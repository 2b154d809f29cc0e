"""The compiled kernels of the greedy skeleton (Hu et al. 2017, §4.2 trunk points, §5.1 voxels and
thinning, §5.2 graph, §5.3 direction field, §5.4 Algorithm 2, the screening of degenerate trees) against
what each step must give, on the candidate points of ~10 trees (cones and synthetic-stand trees):

* Algorithm 1 (the graph): the edges of the same algorithm written with scipy's k-d tree, exactly
  (ties in the kNN distance included);
* Algorithm 2 (the skeleton): a tree from ``start`` through ``end`` over graph edges, each point a node
  at most once, every step within α_max of its parent's and β_max of the direction field, siblings
  more than φ_max apart, and (without regrowth) nothing admissible left unvisited;
* thinning: protected voxels kept, the 26-connected components of the black voxels unchanged, and the
  result a fixed point (thinning it again deletes nothing); voxels: numpy's unique / bincount;
* trunk points (Eq. 3 / Eq. 4), the direction field (Eq. 5) and the screening: their definitions
  computed here with numpy, within float tolerances;
* Python form == compiled form where test_kernels.py's warm-up does not reach the path (kNN ties).

(The numpy/heapq/cKDTree implementations the kernels replaced were kept here as bit-for-bit references;
they are in git history.)"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from sylva.core import jit
from sylva.core.errors import InputError
from sylva.core.reconstruct import GreedySkeleton, TreePoints, reconstruct_tree
from sylva.core.reconstruct import direction as direction_mod
from sylva.core.reconstruct import graph as graph_mod
from sylva.core.reconstruct import model as model_mod
from sylva.core.reconstruct import skeleton as skel_mod
from sylva.core.reconstruct import thinning as thinning_mod
from sylva.core.reconstruct import trunk as trunk_mod
from sylva.core.reconstruct.direction import direction_angles, direction_field
from sylva.core.reconstruct.graph import build_graph, graph_arrays
from sylva.core.reconstruct.model import degenerate_flags
from sylva.core.reconstruct.skeleton import choose_end, greedy_skeleton
from sylva.core.reconstruct.thinning import _OFFSETS, thin_voxels
from sylva.core.reconstruct.trunk import add_trunk_points


# --- Algorithm 1 with scipy's k-d tree, and the voxels' neighbours with numpy ---------------

def kdtree_graph(points, radius_m=1.2, k=30):
    """Algorithm 1 written with scipy's k-d tree: every pair within r_p (``query_pairs``), and for a point with
    fewer than k of them its k nearest (``query``, whose choice among equal distances the kernel follows);
    (CSR adjacency of edge lengths, components, labels, points that needed the kNN)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = len(points)
    tree = cKDTree(points)
    pairs = tree.query_pairs(radius_m, output_type="ndarray").astype(np.int64)
    n_i = np.bincount(pairs.ravel(), minlength=n)
    need = np.flatnonzero(n_i < k)
    kk = min(k + 1, n)
    if len(need) and kk > 1:
        _, nn = tree.query(points[need], k=kk)
        nn = np.asarray(nn).reshape(len(need), kk)
        src = np.repeat(need, kk)
        dst = nn.ravel()
        ok = (dst != src) & (dst < n)
        pairs = np.concatenate([pairs, np.sort(np.stack([src[ok], dst[ok]], axis=1), axis=1)])
    a, b = pairs[:, 0], pairs[:, 1]
    key = np.unique(np.concatenate([a * n + b, b * n + a]))
    rows, cols = key // n, key % n
    indptr = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(rows, minlength=n), out=indptr[1:])
    length = np.linalg.norm(points[rows] - points[cols], axis=1)
    adj = csr_matrix((length, cols, indptr), shape=(n, n))
    ncomp, labels = connected_components(csr_matrix((np.ones(len(cols)), cols, indptr), shape=(n, n)),
                                         directed=False)
    return adj, ncomp, labels, len(need)


def voxel_neighbours(xyz, voxel_m):
    """The (v, 26) neighbour table thin_voxels builds (v = white)."""
    origin = xyz.min(axis=0)
    ijk = np.floor((xyz - origin) / voxel_m).astype(np.int64) + 1
    dims = ijk.max(axis=0) + 2
    key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    ukey, inv = np.unique(key, return_inverse=True)
    nkey = ukey[:, None] + ((_OFFSETS[:, 0] * dims[1] + _OFFSETS[:, 1]) * dims[2] + _OFFSETS[:, 2])[None, :]
    pos = np.minimum(np.searchsorted(ukey, nkey), len(ukey) - 1)
    return np.where(ukey[pos] == nkey, pos, len(ukey)), inv



# --- test trees ---------------------------------------------------------------------------

def cone_crown(rng, centre=(0.0, 0.0), height=15.0, crown_base=5.0, radius=3.0, density=20.0):
    n = rng.poisson(density * np.pi * radius ** 2)
    r = radius * np.sqrt(rng.random(n))
    a = rng.random(n) * 2 * np.pi
    z = height - (r / radius) * (height - crown_base)
    deep = rng.random(n) < 0.3
    z[deep] -= rng.random(deep.sum()) * (z[deep] - crown_base) * 0.8
    r[deep] *= rng.random(deep.sum())
    pts = np.c_[centre[0] + r * np.cos(a), centre[1] + r * np.sin(a), z]
    return pts + rng.normal(0.0, 0.03, pts.shape)


def stages(xyz, ground_z, method=GreedySkeleton()):
    """The inputs GreedySkeleton.reconstruct hands to each step."""
    trunk = add_trunk_points(xyz, ground_z, method.trunk_radius_m, method.trunk_spacing_m)
    added = trunk.points[1:]
    all_xyz = np.concatenate([xyz, added])
    keep = np.r_[np.zeros(len(xyz), bool), np.ones(len(added), bool)]
    cand = np.concatenate([trunk.root[None, :], thin_voxels(all_xyz, method.voxel_m, keep=keep).points])
    graph = build_graph(cand, method.radius_m, method.k)
    u = direction_field(cand)
    end = choose_end(cand, graph.adjacency, 0, trunk.direction, method.alpha_max_deg)
    return dict(all_xyz=all_xyz, keep=keep, cand=cand, graph=graph, u=u, end=end, trunk=trunk)


@pytest.fixture(scope="module")
def trees():
    out = []
    rng = np.random.default_rng(21)
    for i, (density, radius) in enumerate([(20, 3.0), (8, 2.0), (35, 4.0), (12, 3.5)]):
        xyz = cone_crown(rng, centre=(i * 7.0, 0.0), radius=radius, density=density)
        if i == 1:                                    # a stem seen by a few pulses (Eq. 3 trunk)
            xyz = np.r_[xyz, np.c_[np.full(12, 7.05), np.zeros(12), np.linspace(0.8, 4.5, 12)]]
        out.append((f"cone {i}", xyz, 0.0))
    synth = pytest.importorskip("sylva.testing.synth")
    stand = synth.make_stand(synth.StandSpec(width_m=30.0, depth_m=30.0, seed=5))
    scan = synth.simulate_scan(stand, synth.ScanSpec(pulse_density=15.0, seed=5))
    origin = np.array([*stand.spec.origin, 0.0])
    for t in stand.trees:
        m = scan.truth_tree == t.tree_id
        if m.sum() >= 150:
            out.append((f"synth {t.tree_id} {t.species}", scan.cloud.xyz[m] - origin, t.ground_z))
        if len(out) >= 10:
            break
    return [(name, xyz, gz, stages(xyz, gz)) for name, xyz, gz in out]


# --- §5.4 Algorithm 2 --------------------------------------------------------------------

def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def assert_algorithm_2(res, points, adjacency, directions, start, end, alpha_max_deg=70.0, beta_max_deg=70.0,
                       phi_max_deg=30.0, regrow_pruned=True):
    """What Algorithm 2 (with Sylva's documented tie rules) must give, checked on its result."""
    pon, parent, visited, alpha = res.point_of_node, res.parent, res.visited, res.alpha_deg
    m = len(pon)
    assert len(parent) == len(alpha) == m and len(visited) == len(points)
    assert pon[0] == start and parent[0] == -1
    assert len(np.unique(pon)) == m                                  # each point a node at most once
    assert visited[pon].all() and visited[start]
    if end == start:
        assert m == 1
        return
    assert pon[1] == end and parent[1] == 0 and np.isnan(alpha[:2]).all()
    assert (parent[1:] >= 0).all() and (parent[1:] < np.arange(1, m)).all()    # parents before children
    if m == 2:
        return
    i = np.arange(2, m)
    p = parent[i]
    assert (p >= 1).all()                                            # start has one child: end
    edge = np.asarray(adjacency[pon[p], pon[i]]).ravel()
    assert (edge > 0).all()                                          # every step an edge of the graph
    u = _unit(points[pon[i]] - points[pon[p]])
    v_parent = _unit(points[pon[p]] - points[pon[parent[p]]])
    cos_a = np.einsum("ij,ij->i", u, v_parent)
    assert (cos_a > np.cos(np.radians(alpha_max_deg)) - 1e-12).all()
    np.testing.assert_allclose(np.cos(np.radians(alpha[2:])), np.minimum(cos_a, 1.0), rtol=0, atol=1e-9)
    cos_b = np.einsum("ij,ij->i", u, directions[pon[i]])
    assert (cos_b > np.cos(np.radians(beta_max_deg)) - 1e-12).all()
    cos_p = np.cos(np.radians(phi_max_deg))
    order = np.argsort(p, kind="stable")
    groups = np.split(order, np.flatnonzero(np.diff(p[order])) + 1)
    for g in groups:                                                 # siblings: pruned to > φ_max apart
        if len(g) > 1:
            c = u[g] @ u[g].T
            np.fill_diagonal(c, -1.0)
            assert c.max() <= cos_p + 1e-12
    if not regrow_pruned:
        # every node was expanded: each neighbour within α_max and β_max of it ended visited
        seg = np.r_[np.zeros((1, 3)), _unit(points[pon[1:]] - points[pon[parent[1:]]])]
        indptr, indices = adjacency.indptr, adjacency.indices
        for k in range(1, m):
            js = indices[indptr[pon[k]]:indptr[pon[k] + 1]]
            d = points[js] - points[pon[k]]
            ln = np.linalg.norm(d, axis=1)
            ok = ln > 1e-12
            w = d[ok] / ln[ok, None]
            admissible = ((w @ seg[k] > np.cos(np.radians(alpha_max_deg)) + 1e-12)
                          & (np.einsum("ij,ij->i", w, directions[js[ok]]) > np.cos(np.radians(beta_max_deg)) + 1e-12))
            assert visited[js[ok][admissible]].all()


@pytest.mark.parametrize("regrow", [True, False])
def test_greedy_skeleton_is_algorithm_2_on_trees(trees, regrow):
    sizes = []
    for name, xyz, gz, st in trees:
        args = (st["cand"], st["graph"].adjacency, st["u"], 0, st["end"], 70.0, 70.0, 30.0, regrow)
        res = greedy_skeleton(*args)
        assert_algorithm_2(res, *args)
        sizes.append(len(res.point_of_node))
    assert min(sizes) > 20 and max(sizes) > 300


def test_greedy_skeleton_is_algorithm_2_with_other_angles(trees):
    for name, xyz, gz, st in trees[:5]:
        for a, b, p in [(45.0, 60.0, 15.0), (90.0, 89.0, 45.0), (30.0, 180.0, 5.0)]:
            for regrow in (True, False):
                args = (st["cand"], st["graph"].adjacency, st["u"], 0, st["end"], a, b, p, regrow)
                assert_algorithm_2(greedy_skeleton(*args), *args)


def test_greedy_kernel_ties_collinear_points_fifo_and_longer_first():
    # a vertical line of evenly spaced points (exact α ties, cos α clamped to 1) with
    # two symmetric side branches: every tie rule is exercised
    z = np.arange(0.0, 6.01, 0.25)
    line = np.c_[np.zeros_like(z), np.zeros_like(z), z]
    side = np.array([[0.5, 0, 3.5], [-0.5, 0, 3.5], [1.0, 0, 4.0], [-1.0, 0, 4.0], [0, 0.5, 3.5]])
    pts = np.r_[line, side]
    g = build_graph(pts, 1.01, 4)
    up = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    for regrow in (True, False):
        args = (pts, g.adjacency, up, 0, 1, 70.0, 70.0, 30.0, regrow)
        res = greedy_skeleton(*args)
        assert_algorithm_2(res, *args)
        assert res.visited[:len(z)].all()
        assert res.point_of_node[2] == 5       # the straight run advances by the longest step (r_p = 1.01: 4 spacings)
        again = greedy_skeleton(*args)         # ties broken the same way every time
        np.testing.assert_array_equal(again.point_of_node, res.point_of_node)
        np.testing.assert_array_equal(again.parent, res.parent)


def assert_same_greedy(res, ref):
    np.testing.assert_array_equal(res.point_of_node, ref.point_of_node)
    np.testing.assert_array_equal(res.parent, ref.parent)
    np.testing.assert_array_equal(res.visited, ref.visited)
    np.testing.assert_allclose(res.alpha_deg, ref.alpha_deg, rtol=0, atol=1e-9, equal_nan=True)


def test_greedy_kernel_compiled_equals_its_python_source(trees):
    name, xyz, gz, st = trees[1]
    adj = st["graph"].adjacency
    seg = st["cand"][st["end"]] - st["cand"][0]
    args = (st["cand"], adj.indptr.astype(np.int64), adj.indices.astype(np.int64), st["u"], 0, st["end"],
            seg / np.linalg.norm(seg), np.cos(np.radians(70)), np.cos(np.radians(70)), np.cos(np.radians(30)), True)
    compiled = skel_mod._greedy_kernel(*args)
    python = skel_mod._greedy_kernel.py_func(*args)
    m = compiled[3]
    assert m == python[3] and m > 20
    for c, p in zip(compiled[:3], python[:3]):
        np.testing.assert_array_equal(c[:m], p[:m])
    np.testing.assert_array_equal(compiled[4], python[4])


def test_greedy_skeleton_rejects_mismatched_input():
    pts = np.array([[0, 0, 0], [0, 0, 1.0], [0, 0, 2]])
    g = build_graph(pts, 1.5, 1)
    with pytest.raises(InputError, match="directions"):
        greedy_skeleton(pts, g.adjacency, np.zeros((2, 3)), 0, 1)
    res = greedy_skeleton(pts, g.adjacency, np.tile([0, 0, 1.0], (3, 1)), 0, 0)   # start == end: no segment
    assert res.point_of_node.tolist() == [0] and res.parent.tolist() == [-1]
    assert res.visited.tolist() == [True, False, False]


# --- §5.2 Algorithm 1 --------------------------------------------------------------------

def assert_same_graph(points, radius, k):
    g = build_graph(points, radius, k)
    adj, ncomp, labels, n_knn = kdtree_graph(points, radius, k)
    np.testing.assert_array_equal(g.adjacency.indptr, adj.indptr)
    np.testing.assert_array_equal(g.adjacency.indices, adj.indices)
    np.testing.assert_array_equal(g.adjacency.data, adj.data)
    assert g.n_components == ncomp and g.n_knn == n_knn
    np.testing.assert_array_equal(g.labels, labels)
    return g


def test_graph_kernel_equals_kdtree_graph_on_candidates(trees):
    # the candidates include the evenly spaced trunk points: exact kNN distance ties
    for name, xyz, gz, st in trees:
        for radius, k in [(1.2, 30), (0.6, 10), (2.0, 5)]:
            assert_same_graph(st["cand"], radius, k)


def test_graph_kernel_ties_duplicates_and_small_sets():
    rng = np.random.default_rng(3)
    grid = np.stack(np.meshgrid(np.arange(5.0), np.arange(4.0), np.arange(3.0)), axis=-1).reshape(-1, 3)
    for pts, radius, k in [
        (grid, 1.0, 8),                                      # a lattice: ties everywhere
        (grid * 0.5, 0.75, 30),
        (grid * 1.2 + [1000.3, 2000.7, 10.1], 1.2, 6),      # pairs at r_p, off the origin
        (grid * 0.6 - [7.7, 0.1, 3.3], 1.2, 40),
        (np.r_[grid, grid[:7]], 1.0, 3),                     # duplicate points
        (rng.random((40, 3)) * [30, 30, 1], 0.5, 4),         # sparse: kNN reaches far
        (rng.random((3, 3)), 0.1, 30),                       # fewer points than k
        (np.zeros((1, 3)), 1.2, 30),
        (np.r_[rng.random((50, 3)), rng.random((50, 3)) + 500.0], 1.2, 5),   # two clusters far apart
    ]:
        g = assert_same_graph(pts, radius, k)
        assert (g.adjacency != g.adjacency.T).nnz == 0
    assert build_graph(np.zeros((0, 3))).n_components == 0
    assert build_graph(grid, -1.0, 0).n_edges == 0                   # no radius, no kNN: no edges
    with pytest.raises(InputError, match="not finite"):
        build_graph(np.r_[grid, [[np.nan, 0, 0]]])


def test_graph_of_a_wide_sparse_cloud_grows_the_grid_cells():
    rng = np.random.default_rng(4)
    pts = np.r_[rng.random((30, 3)), rng.random((30, 3)) * 3 + [5000.0, 4000.0, 300.0]]
    g = assert_same_graph(pts, 0.2, 6)
    assert g.n_components == 2


# --- §5.1 voxels and thinning ---------------------------------------------------------------

def _components(nbr, members):
    """Number of 26-connected components of the voxels ``members`` (bool over the rows of ``nbr``)."""
    v = len(nbr)
    src = np.repeat(np.arange(v), nbr.shape[1])
    dst = nbr.ravel()
    ok = (dst < v) & members[src] & members[np.minimum(dst, v - 1)]
    g = csr_matrix((np.ones(int(ok.sum())), (src[ok], dst[ok])), shape=(v, v))
    n, lab = connected_components(g, directed=False)
    return len(np.unique(lab[members]))


def _thin_again(nbr, vkeep, survivors):
    """The thinning kernel run on the survivors alone (their own neighbour table)."""
    v, s = len(nbr), len(survivors)
    new = np.full(v + 1, s, dtype=np.int64)
    new[survivors] = np.arange(s)
    nbr2 = new[nbr[survivors]]
    return thinning_mod._thin_kernel(nbr2, vkeep[survivors].copy(), thinning_mod._DIRECTIONS_ARR,
                                     thinning_mod._ADJ26_MASK, thinning_mod._ADJ6_MASK, thinning_mod._N18_MASK,
                                     thinning_mod._FACE_MASK, 100)


def test_thinning_keeps_topology_and_protected_voxels_and_is_a_fixed_point(trees):
    rng = np.random.default_rng(5)
    block = rng.random((3000, 3)) * [2.0, 1.5, 3.0]                # a solid: many simple voxels
    clouds = [(st["all_xyz"], st["keep"]) for name, xyz, gz, st in trees] + [(block, None)]
    deleted = 0
    for xyz, keep in clouds:
        th = thin_voxels(xyz, 0.2, keep=keep)
        nbr, inv = voxel_neighbours(xyz, 0.2)
        v = len(nbr)
        black = np.zeros(v, dtype=bool)
        black[th.voxel_index] = True
        assert th.voxel_keep[~black].sum() == 0                     # protected voxels survive
        if keep is not None:
            assert black[inv[keep]].all()
        assert th.passes < 100
        assert _components(nbr, black) == _components(nbr, np.ones(v, dtype=bool))
        black2, passes2 = _thin_again(nbr, th.voxel_keep, th.voxel_index)
        assert black2[:len(th.voxel_index)].all() and passes2 == 1  # nothing left to delete
        np.testing.assert_array_equal(th.points, th.voxel_means[th.voxel_index])
        deleted += v - len(th.voxel_index)
    assert deleted > 0
    th = thin_voxels(block, 0.2)
    assert len(th.voxel_index) < len(th.voxel_means) / 2


def numpy_voxels(xyz, voxel_m, keep):
    """Voxel of each point, voxel means and protected voxels with numpy's unique and bincount."""
    ijk = np.floor((xyz - xyz.min(axis=0)) / voxel_m).astype(np.int64)
    _, inv = np.unique(ijk, axis=0, return_inverse=True)     # ordered by x, then y, then z
    inv = inv.ravel()
    v = int(inv.max()) + 1
    counts = np.bincount(inv, minlength=v)
    means = np.stack([np.bincount(inv, weights=xyz[:, c], minlength=v) for c in range(3)], axis=1) / counts[:, None]
    vkeep = np.zeros(v, dtype=bool)
    if keep is not None:
        vkeep[inv[np.asarray(keep, dtype=bool)]] = True
    return inv, means, vkeep


def test_voxel_kernel_equals_numpy_voxels(trees):
    rng = np.random.default_rng(6)
    clouds = [(st["all_xyz"], st["keep"], 0.2) for name, xyz, gz, st in trees]
    clouds += [(trees[0][3]["all_xyz"], trees[0][3]["keep"], 0.15),
               (rng.random((3000, 3)) * [2.0, 1.5, 3.0], None, 0.2),           # a solid
               (rng.random((400, 3)) * [2000.0, 1500.0, 30.0], None, 0.2),     # > 16 M cells: searchsorted
               (np.repeat(rng.random((5, 3)), 4, axis=0), None, 0.2),          # repeated points
               (rng.random((1, 3)), None, 0.1)]
    for xyz, keep, voxel_m in clouds:
        th = thin_voxels(xyz, voxel_m, keep=keep)
        inv, means, vkeep = numpy_voxels(xyz, voxel_m, keep)
        np.testing.assert_array_equal(th.voxel_of_point, inv)
        np.testing.assert_allclose(th.voxel_means, means, rtol=1e-12, atol=0)
        np.testing.assert_array_equal(th.voxel_keep, vkeep)
        flags = np.zeros(len(xyz), bool) if keep is None else keep
        got = thinning_mod._voxel_grid(np.ascontiguousarray(xyz), float(voxel_m), flags, thinning_mod._COLUMNS)
        np.testing.assert_array_equal(got[3], voxel_neighbours(xyz, voxel_m)[0])


# --- §4.2 trunk points, screening, §5.3 direction field --------------------------------------

def assert_trunk_is_eq3_or_eq4(t, xyz, gz, radius_m=1.0, spacing_m=0.1, lambda1_max_deg=30.0, lambda2_max=0.5):
    """The definitions of trunk.py's docstring (Hu et al. §4.2 and Sylva's root guard), computed here."""
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    g_b = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, gz])
    v_b = (lo + hi) / 2
    v_low = xyz[np.argmin(xyz[:, 2])]
    np.testing.assert_array_equal(t.v_low, v_low)
    half_diag = np.linalg.norm(hi[:2] - g_b[:2])
    lambda2 = np.linalg.norm(v_low[:2] - g_b[:2]) / half_diag if half_diag > 0 else 0.0
    assert t.lambda2 == pytest.approx(lambda2, rel=1e-12, abs=1e-12)
    d = xyz - v_low
    dist = np.linalg.norm(d, axis=1)
    near = (dist <= radius_m) & (dist > 1e-9)
    mean = (d[near] / dist[near, None]).mean(axis=0) if near.any() else np.zeros(3)
    n_avg = mean / np.linalg.norm(mean) if np.linalg.norm(mean) > 1e-9 else None
    if n_avg is None:
        assert np.isnan(t.lambda1_deg)
    else:
        cl = v_b - g_b
        cl = cl / np.linalg.norm(cl) if np.linalg.norm(cl) > 1e-9 else np.array([0.0, 0.0, 1.0])
        assert t.lambda1_deg == pytest.approx(np.degrees(np.arccos(np.clip(n_avg @ cl, -1, 1))), abs=1e-6)
    # the points: root first, on the ground, evenly spaced (<= spacing_m) on a straight line along `direction`
    pts = t.points
    np.testing.assert_array_equal(pts[0], t.root)
    assert t.root[2] == gz
    assert np.linalg.norm(t.direction) == pytest.approx(1.0, abs=1e-12)
    steps = np.diff(pts, axis=0)
    if len(steps):
        length = np.linalg.norm(steps, axis=1)
        np.testing.assert_allclose(length, length[0], rtol=1e-9, atol=1e-12)
        assert length[0] <= spacing_m * (1 + 1e-9)
        assert np.abs(np.cross(steps, t.direction)).max() <= 1e-9 * max(1.0, length.max())
    ok3 = n_avg is not None and t.lambda1_deg <= lambda1_max_deg and lambda2 <= lambda2_max and n_avg[2] > 0
    if t.rule == "eq3":                                        # Eq. 3: from the root up to v_low along n_avg
        assert ok3
        np.testing.assert_allclose(t.direction, n_avg, atol=1e-12)
        np.testing.assert_allclose(pts[-1], v_low, atol=1e-9)
        assert np.linalg.norm(t.root[:2] - g_b[:2]) <= lambda2_max * half_diag * (1 + 1e-9)
    else:                                                      # Eq. 4: from g_b up to the centroid
        assert t.rule == "eq4"
        np.testing.assert_allclose(t.root, g_b, atol=1e-12)
        v_c = xyz.mean(axis=0)
        if v_c[2] > gz and np.linalg.norm(v_c - g_b) > 1e-9:
            np.testing.assert_allclose(pts[-1], v_c, atol=1e-9)
        else:
            np.testing.assert_allclose(pts[-1], [g_b[0], g_b[1], max(hi[2], gz)], atol=1e-9)
        if ok3:                                                # Sylva's guard put the root too far out
            root = v_low - n_avg * ((v_low[2] - gz) / n_avg[2])
            assert np.linalg.norm(root[:2] - g_b[:2]) > lambda2_max * half_diag * (1 - 1e-9)


def test_trunk_points_are_eq3_or_eq4(trees):
    rng = np.random.default_rng(7)
    cases = [(xyz, gz) for name, xyz, gz, st in trees]
    stem = np.c_[np.full(12, 0.05), np.zeros(12), np.linspace(0.8, 4.5, 12)]
    cases += [(np.r_[rng.random((300, 3)) * [4, 4, 6] + [0, 0, 5], stem], 0.0),          # Eq. 3
              (np.asfortranarray(np.r_[rng.random((50, 3)) + [0, 0, 3], [[0.5, 0.5, 2.0], [0.7, 0.5, 2.0]]]), 0.0),
              (rng.random((5, 3)) * 10, 0.0),                                          # no neighbour within r
              (np.ones((4, 3)), 1.0)]                                                  # no height at all
    rules = set()
    for xyz, gz in cases:
        for kw in [{}, dict(radius_m=0.3, spacing_m=0.07), dict(radius_m=3.0, lambda1_max_deg=60.0, lambda2_max=1.0)]:
            trunk = add_trunk_points(xyz, gz, **kw)
            assert_trunk_is_eq3_or_eq4(trunk, np.asarray(xyz), gz, **kw)
            rules.add(trunk.rule)
    assert rules == {"eq3", "eq4"}


def test_screening_flags_and_its_shortcut(trees, monkeypatch):
    """Degenerate trees get the flag their shape calls for; the kernel counts distinct points as numpy's
    unique does (up to min_points), its bound never exceeds the smallest covariance eigenvalue, and the
    shortcut it allows changes no flag."""
    rng = np.random.default_rng(8)
    line = np.c_[np.zeros(30), np.zeros(30), np.linspace(0, 5, 30)] + rng.normal(0, 0.002, (30, 3))
    plane = np.c_[rng.random(40), rng.random(40), np.zeros(40)] + rng.normal(0, 0.002, (40, 3))
    slab = np.c_[rng.random(40), rng.random(40), np.zeros(40)] + rng.normal(0, 0.012, (40, 3))
    four = np.repeat(rng.random((4, 3)), 10, axis=0)
    zeros = np.array([[0.0, 0, 0], [-0.0, 0, 0]] * 6)                 # -0.0 == 0.0: one distinct point
    nine = rng.random((9, 3))
    tiny = rng.random((30, 3)) * 1e-3
    expected = {  # min_points 1, 3, 10, 25
        "line": ["collinear_points"] * 4, "plane": ["coplanar_points"] * 4, "slab": [None] * 4,
        "four": [None, None, "duplicate_points", "duplicate_points"],
        "zeros": ["collinear_points", "duplicate_points", "duplicate_points", "too_few_points"],
        "nine": [None, None, "too_few_points", "too_few_points"], "tiny": ["collinear_points"] * 4,
    }
    cases = dict(line=line, plane=plane, slab=slab, four=four, zeros=zeros, nine=nine, tiny=tiny)
    cases.update({name: xyz for name, xyz, gz, st in trees})
    assert model_mod._screen_kernel(slab, 10)[1] < model_mod._SPREAD_SURE      # the eigenvalues decide, not the bound
    got = {}
    for name, xyz in cases.items():
        lam3 = np.linalg.eigvalsh(np.cov(xyz.T))[0]
        for min_points in (1, 3, 10, 25):
            distinct, bound = model_mod._screen_kernel(np.ascontiguousarray(xyz), min_points)
            assert distinct == min(len(np.unique(xyz, axis=0)), min_points)
            assert bound <= max(lam3, 0.0) * (1 + 1e-9) + 1e-15
            flags = degenerate_flags(xyz, min_points)
            got[name, min_points] = flags
            want = expected.get(name, [None] * 4)[(1, 3, 10, 25).index(min_points)]
            assert flags == ([] if want is None else [want]), (name, min_points)
    monkeypatch.setattr(model_mod, "_SPREAD_SURE", np.inf)              # always the eigen decomposition
    for (name, min_points), flags in got.items():
        assert degenerate_flags(cases[name], min_points) == flags


def test_direction_field_is_eq5(trees):
    """θ = 90° - (90° - θ_l - μ1 (θ_u - θ_l)) μ2 with μ1 = (height in the box)^k1, μ2 = (distance from the
    centre line / L_c)^k2; the field is the unit vector at elevation θ pointing away from the centre line
    (straight up on it)."""
    rng = np.random.default_rng(9)
    clouds = [st["cand"] for name, xyz, gz, st in trees]
    clouds += [np.r_[np.zeros((1, 3)), rng.random((20, 3)) * 2 - 1], np.zeros((4, 3))]   # points on the centre line
    for pts in clouds:
        for kw in [{}, dict(k1=2.0, k2=0.5), dict(k2=2.0),
                   dict(centre_xy=np.array([0.1, 0.2]), z_range=(0.0, 5.0), radius_m=3.0)]:
            lo, hi = pts.min(axis=0), pts.max(axis=0)
            c = kw.get("centre_xy", (lo[:2] + hi[:2]) / 2)
            z0, z1 = kw.get("z_range", (lo[2], hi[2]))
            radial = pts[:, :2] - c
            dist = np.hypot(radial[:, 0], radial[:, 1])
            lc = kw.get("radius_m", dist.max())
            k1, k2 = kw.get("k1", 1.4), kw.get("k2", 1.0)
            mu1 = np.clip((pts[:, 2] - z0) / (z1 - z0), 0, 1) ** k1 if z1 > z0 else np.zeros(len(pts))
            mu2 = np.clip(dist / lc, 0, 1) ** k2 if lc > 0 else np.zeros(len(pts))
            theta = 90.0 - (90.0 + 40.0 - mu1 * 120.0) * mu2
            angles = direction_angles(pts, **kw)
            np.testing.assert_allclose(angles, theta, rtol=0, atol=1e-9)
            field = direction_field(pts, **kw)
            np.testing.assert_allclose(np.linalg.norm(field, axis=1), 1.0, atol=1e-12)
            on = dist < 1e-9
            np.testing.assert_allclose(field[on], np.tile([0.0, 0.0, 1.0], (on.sum(), 1)), atol=1e-12)
            off = ~on
            np.testing.assert_allclose(field[off, 2], np.sin(np.radians(angles[off])), atol=1e-12)
            outward = radial[off] / dist[off, None]
            np.testing.assert_allclose(field[off, :2], np.cos(np.radians(angles[off]))[:, None] * outward,
                                       atol=1e-12)


def assert_bit_equal(got, want):
    got, want = np.asarray(got), np.asarray(want)
    assert got.dtype == want.dtype and got.shape == want.shape
    assert got.tobytes() == want.tobytes()


def test_graph_arrays_are_the_arrays_of_build_graph(trees):
    for name, xyz, gz, st in trees[:4]:
        g, a = build_graph(st["cand"]), graph_arrays(st["cand"])
        np.testing.assert_array_equal(a.adjacency.indptr, g.adjacency.indptr)
        np.testing.assert_array_equal(a.adjacency.indices, g.adjacency.indices)
        assert_bit_equal(a.adjacency.data, g.adjacency.data)
        assert a.adjacency.shape == g.adjacency.shape and a.n_edges == g.n_edges
        assert (a.n_components, a.n_knn) == (g.n_components, g.n_knn)
        assert_bit_equal(a.labels, g.labels)
        assert g.adjacency.indices.dtype == np.int32 and a.adjacency.indices.dtype == np.int64
        args = (st["cand"], st["u"], 0, st["end"])
        assert_same_greedy(greedy_skeleton(args[0], a.adjacency, *args[1:]),
                           greedy_skeleton(args[0], g.adjacency, *args[1:]))


def test_graph_kernel_dense_clouds_and_equal_distances():
    rng = np.random.default_rng(10)
    dense = rng.random((300, 3))        # most pairs within r_p: more FRNN rows than foreseen (32 per point)
    g = assert_same_graph(dense, 1.2, 30)
    assert g.adjacency.nnz > 32 * 300
    twins = np.r_[np.zeros((25, 3)), np.full((25, 3), 3.0), rng.random((40, 3)) * 6]
    for radius, k in [(0.5, 10), (0.5, 30), (2.0, 45)]:
        assert_same_graph(twins, radius, k)
    # no radius, kNN among copies (all distances 0, one histogram bin); as before, kNN
    # neighbours within r_p² (here 1) count as FRNN ones, and there are none
    g = build_graph(np.zeros((12, 3)), -1.0, 5)
    assert g.n_knn == 12 and g.n_edges == 0
    g = build_graph(np.r_[np.zeros((12, 3)), np.full((3, 3), 2.0)], -1.0, 13)
    assert g.n_knn == 15 and g.n_edges > 0 and (g.adjacency.data == np.sqrt(12.0)).all()


def test_new_kernels_compiled_equal_their_python_source(trees):
    def search_args(st):
        cand = np.ascontiguousarray(st["cand"])
        return (cand, 1.2, 30, 1.0, float(8 * len(cand) + (1 << 17)), 32, 32 * len(cand))

    # the smallest tree with kNN ties (the k-d tree's rows reach the CSR kernel)
    name, xyz, gz, st = min((t for t in trees if graph_mod._graph_frnn_knn(*search_args(t[3]))[5].any()),
                            key=lambda t: len(t[3]["cand"]))
    search = search_args(st)
    cand = search[0]
    compiled = graph_mod._graph_frnn_knn(*search)
    python = graph_mod._graph_frnn_knn.py_func(*search)
    assert compiled[0] and python[0] and compiled[6] == python[6]
    for (ptr_c, rows_c), (ptr_p, rows_p) in [((compiled[1], compiled[2]), (python[1], python[2])),
                                             ((compiled[3], compiled[4]), (python[3], python[4]))]:
        assert_bit_equal(ptr_c, ptr_p)
        assert_bit_equal(rows_c[:ptr_c[-1]], rows_p[:ptr_p[-1]])     # the rest is scratch
    assert_bit_equal(compiled[5], python[5])
    tie_i = np.flatnonzero(compiled[5])
    assert len(tie_i)
    nn = np.asarray(cKDTree(cand).query(cand[tie_i], k=31)[1], dtype=np.int64).reshape(len(tie_i), -1)
    args = (cand, *compiled[1:5], tie_i, nn, 1.2)
    (ptr_c, ind_c, m_c, len_c, lab_c, nc_c) = graph_mod._graph_csr(*args)
    (ptr_p, ind_p, m_p, len_p, lab_p, nc_p) = graph_mod._graph_csr.py_func(*args)
    assert m_c == m_p and nc_c == nc_p
    for c, p in [(ptr_c, ptr_p), (ind_c[:m_c], ind_p[:m_p]), (len_c[:m_c], len_p[:m_p]), (lab_c, lab_p)]:
        assert_bit_equal(c, p)
    vox = (np.ascontiguousarray(st["all_xyz"]), 0.2, st["keep"], thinning_mod._COLUMNS)
    vc, vp = thinning_mod._voxel_grid(*vox), thinning_mod._voxel_grid.py_func(*vox)
    for c, p in zip(vc, vp):
        assert_bit_equal(c, p)
    thin = (vc[3], vc[2], thinning_mod._DIRECTIONS_ARR, thinning_mod._ADJ26_MASK, thinning_mod._ADJ6_MASK,
            thinning_mod._N18_MASK, thinning_mod._FACE_MASK, 100)
    tc, tp = thinning_mod._thin_kernel(*thin), thinning_mod._thin_kernel.py_func(*thin)
    assert_bit_equal(tc[0], tp[0])
    assert tc[1] == tp[1]
    for kernel, args in [(trunk_mod._trunk_stats, (np.ascontiguousarray(xyz), 1.0)),
                         (model_mod._screen_kernel, (np.ascontiguousarray(xyz), 10)),
                         (direction_mod._bounds, (cand,))]:
        for c, p in zip(kernel(*args), kernel.py_func(*args)):
            assert_bit_equal(c, p)


# --- the whole method and the jit module ----------------------------------------------------

def test_reconstruction_uses_the_same_stages(trees):
    name, xyz, gz, st = trees[0]
    a = reconstruct_tree(TreePoints(1, xyz, gz), GreedySkeleton())
    b = reconstruct_tree(TreePoints(1, xyz, gz), GreedySkeleton())
    np.testing.assert_array_equal(a.skeleton.nodes, b.skeleton.nodes)
    np.testing.assert_array_equal(a.skeleton.parent, b.skeleton.parent)
    assert a.stats["n_candidates"] == len(st["cand"]) and a.stats["n_edges"] == st["graph"].n_edges
    assert a.connected and a.visited_fraction > 0.8


def test_load_kernels_compiles_every_kernel():
    from sylva.core.reconstruct import graph, thinning
    assert skel_mod.load_kernels() >= 0.0
    kernels = (skel_mod._greedy_kernel, graph._graph_frnn_knn, graph._graph_csr, thinning._thin_kernel,
               thinning._voxel_grid, trunk_mod._trunk_stats, model_mod._screen_kernel, direction_mod._bounds)
    assert all(k.compiled is not None for k in kernels)


def test_jit_kernel_falls_back_without_cache_and_without_numba(monkeypatch):
    def add(a, b):
        return a + b

    k = jit.njit(add)
    assert k.py_func is add and k.compiled is None
    assert k(2, 3) == 5                     # compiled on first call
    status = jit.jit_status()
    if status["numba"] is None:
        pytest.skip("numba not installed: kernels run as Python")
    assert k.compiled is not add and k.cached is True

    numba = jit._numba()
    real = numba.njit

    def no_cache(*args, **kw):              # as numba does when no cache folder is writable
        if kw.get("cache"):
            raise RuntimeError("cannot cache function 'add': no locator available for file 'x'")
        return real(*args, **kw)

    monkeypatch.setattr(numba, "njit", no_cache)
    k2 = jit.njit(add)
    assert k2(4, 5) == 9 and k2.cached is False
    monkeypatch.setattr(jit, "_NUMBA", False)            # SYLVA_NO_JIT=1 / no numba
    k3 = jit.njit(add)
    assert k3(1, 1) == 2 and k3.compiled is add
