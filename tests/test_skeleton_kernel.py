"""The compiled kernels of the greedy skeleton (Hu et al. 2017, §4.2 trunk points, §5.1
voxels and thinning, §5.2 graph, §5.3 direction field, §5.4 Algorithm 2, the screening of
degenerate trees) against straightforward references: the numpy/heapq/cKDTree
implementations they replaced, kept here verbatim except that the greedy
reference writes its dot products out as (x·x' + y·y') + z·z' (the kernel's
arithmetic; a BLAS gemv may round differently on another CPU).  The kernels that
sum coordinates (trunk points) do it in point order, as numpy reduces an (n, 3)
array along axis 0; the comparisons are bit for bit on this machine."""
from __future__ import annotations

import heapq

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
from sylva.core.reconstruct.thinning import _DIRECTIONS, _OFFSETS, is_simple, thin_voxels
from sylva.core.reconstruct.trunk import add_trunk_points


# --- references: the implementations the kernels replaced ------------------------------

def reference_graph(points, radius_m=1.2, k=30):
    """Algorithm 1 with scipy's k-d tree (the previous build_graph)."""
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


def _reference_prune(close, beyond):
    c = len(close)
    alive = np.ones(c, dtype=bool)
    kept, released = [], []
    for l in range(c):
        if alive[l]:
            kept.append(l)
            pruned = alive & close[l]
            alive &= ~close[l]
            if beyond is not None:
                released.extend(np.flatnonzero(pruned & beyond[l]).tolist())
    return kept, released


def _dot3(a, b):
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def reference_greedy(points, adjacency, directions, start, end, alpha_max_deg=70.0, beta_max_deg=70.0,
                     phi_max_deg=30.0, regrow_pruned=True):
    """Algorithm 2 with heapq keyed by α/α_max (the previous greedy_skeleton)."""
    points = np.asarray(points, dtype=np.float64)
    n = len(points)
    indptr = adjacency.indptr
    indices = adjacency.indices.astype(np.int64)
    rows = np.repeat(np.arange(n), np.diff(indptr))
    vec = points[indices] - points[rows]
    length = np.sqrt(_dot3(vec, vec))
    order = np.lexsort((-length, rows))
    indices, vec, length = indices[order], vec[order], length[order]
    good = length > 1e-12
    unit = np.zeros_like(vec)
    unit[good] = vec[good] / length[good, None]
    cos_a = np.cos(np.radians(alpha_max_deg))
    cos_b = np.cos(np.radians(beta_max_deg))
    cos_p = np.cos(np.radians(phi_max_deg))
    beta_ok = good & (_dot3(unit, directions[indices]) > cos_b)
    indices, unit, length = indices[beta_ok], unit[beta_ok], length[beta_ok]
    indptr = np.r_[0, np.cumsum(np.bincount(rows[order][beta_ok], minlength=n))]
    visited = np.zeros(n, dtype=bool)
    visited[start] = visited[end] = True
    node_of_point = np.full(n, -1, dtype=np.int64)
    point_of_node, parent, alphas = [start], [-1], [np.nan]
    node_of_point[start] = 0
    queue = []
    if end != start:
        point_of_node.append(end)
        parent.append(0)
        alphas.append(np.nan)
        node_of_point[end] = 1
        first_seg = points[end] - points[start]
        queue.append((1.0, 0, end, first_seg / np.linalg.norm(first_seg)))
    counter = 1
    while queue:
        _, _, i, v_parent = heapq.heappop(queue)
        a, b = indptr[i], indptr[i + 1]
        js = indices[a:b]
        u_all = unit[a:b]
        cos_all = _dot3(u_all, v_parent[None, :])
        cand = ((cos_all > cos_a) & ~visited[js]).nonzero()[0]
        if cand.size == 0:
            continue
        visited[js[cand]] = True
        parent_node = node_of_point[i]
        if cand.size == 1:
            kept = cand
        else:
            cand = cand[np.argsort(-np.rint(cos_all[cand] * 1e12), kind="stable")]
            far = length[a:b][cand]
            u = u_all[cand]
            close = _dot3(u[:, None, :], u[None, :, :]) > cos_p
            beyond = far[None, :] > far[:, None]
            kept, released = _reference_prune(close, beyond if regrow_pruned else None)
            if released:
                visited[js[cand[released]]] = False
            kept = cand[kept]
        alpha = np.degrees(np.arccos(np.minimum(cos_all[kept], 1.0))).tolist()
        for l, al in zip(kept.tolist(), alpha):
            j = int(js[l])
            node_of_point[j] = len(point_of_node)
            point_of_node.append(j)
            parent.append(parent_node)
            alphas.append(al)
            heapq.heappush(queue, (al / alpha_max_deg, counter, j, u_all[l]))
            counter += 1
    return (np.asarray(point_of_node, dtype=np.int64), np.asarray(parent, dtype=np.int64), visited,
            np.asarray(alphas))


def reference_thinning(nbr, vkeep, max_passes=100):
    """The directional sub-iterations of §5.1 in numpy (the previous thin_voxels loop)."""
    v = len(nbr)
    black = np.ones(v + 1, dtype=bool)
    black[v] = False
    passes = 0
    while passes < max_passes:
        passes += 1
        deleted = 0
        for d in _DIRECTIONS:
            cfg = black[nbr]
            ids = np.flatnonzero(black[:v] & ~vkeep & ~cfg[:, d] & (np.count_nonzero(cfg, axis=1) >= 2))
            while len(ids):
                cfg = black[nbr[ids]]
                ok = ~cfg[:, d] & (np.count_nonzero(cfg, axis=1) >= 2)
                ids, cfg = ids[ok], cfg[ok]
                if len(ids) == 0:
                    break
                ids = ids[is_simple(cfg)]
                if len(ids) == 0:
                    break
                is_cand = np.zeros(v + 1, dtype=bool)
                is_cand[ids] = True
                nb = nbr[ids]
                lower = (is_cand[nb] & (nb < ids[:, None])).any(axis=1)
                go = ids[~lower]
                black[go] = False
                deleted += len(go)
                ids = ids[lower]
        if deleted == 0:
            break
    return np.flatnonzero(black[:v]), passes


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


def reference_voxels(xyz, voxel_m, keep):
    """The numpy voxelisation of the previous thin_voxels: (inverse, means, protected, neighbour table)."""
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    origin = xyz.min(axis=0)
    ijk = np.floor((xyz - origin) / voxel_m).astype(np.int64) + 1   # +1: room for -1 offsets
    dims = ijk.max(axis=0) + 2
    key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    ukey, inv = np.unique(key, return_inverse=True)
    v = len(ukey)
    counts = np.bincount(inv, minlength=v).astype(np.float64)
    means = np.stack([np.bincount(inv, weights=xyz[:, c], minlength=v) for c in range(3)], axis=1)
    means /= counts[:, None]
    vkeep = np.zeros(v, dtype=bool)
    if keep is not None:
        vkeep[inv[np.asarray(keep, dtype=bool)]] = True
    nkey = ukey[:, None] + ((_OFFSETS[:, 0] * dims[1] + _OFFSETS[:, 1]) * dims[2] + _OFFSETS[:, 2])[None, :]
    cells = int(np.prod(dims))
    if cells <= 16_000_000:
        grid = np.full(cells, v, dtype=np.int32)
        grid[ukey] = np.arange(v, dtype=np.int32)
        nbr = grid[nkey].astype(np.int64)                               # (v, 26), v = white
    else:
        pos = np.minimum(np.searchsorted(ukey, nkey), v - 1)
        nbr = np.where(ukey[pos] == nkey, pos, v)
    return inv, means, vkeep, nbr


def _reference_interpolate(start, stop, spacing_m):
    length = float(np.linalg.norm(stop - start))
    if length < 1e-12:
        return start[None, :].copy()
    n = max(1, int(np.ceil(length / spacing_m)))
    t = np.linspace(0.0, 1.0, n + 1)[:, None]
    return start[None, :] + t * (stop - start)[None, :]


def reference_trunk(xyz, ground_z, radius_m=1.0, spacing_m=0.1, lambda1_max_deg=30.0, lambda2_max=0.5):
    """The previous add_trunk_points (numpy reductions, np.linspace), as a tuple of its fields."""
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    v_b = (lo + hi) / 2.0
    g_b = np.array([v_b[0], v_b[1], ground_z])
    v_c = xyz.mean(axis=0)
    low = int(np.argmin(xyz[:, 2]))
    v_low = xyz[low]
    h = max(0.0, float(v_low[2] - ground_z))
    half_diag = float(np.linalg.norm(hi[:2] - g_b[:2]))
    lambda2 = float(np.linalg.norm(v_low[:2] - g_b[:2]) / half_diag) if half_diag > 0 else 0.0
    lambda1 = float("nan")
    n_avg = None
    d = xyz - v_low
    norms = np.linalg.norm(d, axis=1)
    near = (norms <= radius_m) & (norms > 1e-9)
    d = d[near] / norms[near, None]
    if len(d):
        mean = d.mean(axis=0)
        if np.linalg.norm(mean) > 1e-9:
            n_avg = mean / np.linalg.norm(mean)
            centre_line = v_b - g_b
            if np.linalg.norm(centre_line) > 1e-9:
                cl = centre_line / np.linalg.norm(centre_line)
            else:
                cl = np.array([0.0, 0.0, 1.0])
            lambda1 = float(np.degrees(np.arccos(np.clip(n_avg @ cl, -1.0, 1.0))))
    if n_avg is not None and lambda1 <= lambda1_max_deg and lambda2 <= lambda2_max and n_avg[2] > 0:
        root = v_low - n_avg * (h / n_avg[2])
        root[2] = ground_z
        root_off = float(np.linalg.norm(root[:2] - g_b[:2]) / half_diag) if half_diag > 0 else 0.0
        if root_off <= lambda2_max:
            pts = _reference_interpolate(root, v_low, spacing_m)
            return (pts, root, n_avg, "eq3", lambda1, lambda2, v_low.copy())
    axis = v_c - g_b
    if np.linalg.norm(axis) < 1e-9 or axis[2] <= 0:
        axis = np.array([0.0, 0.0, 1.0])
        top = g_b + axis * max(float(hi[2] - ground_z), 0.0)
    else:
        top = v_c
        axis = axis / np.linalg.norm(axis)
    pts = _reference_interpolate(g_b, top, spacing_m)
    return (pts, g_b, axis, "eq4", lambda1, lambda2, v_low.copy())


def reference_degenerate_flags(xyz, min_points):
    """The previous degenerate_flags (lexsort, covariance eigenvalues)."""
    if len(xyz) < min_points:
        return ["too_few_points"]
    srt = xyz[np.lexsort(xyz.T)]
    distinct = 1 + int(np.count_nonzero(np.any(srt[1:] != srt[:-1], axis=1)))
    if distinct < min_points:
        return ["duplicate_points"]
    spread = np.sqrt(np.clip(np.linalg.eigvalsh(np.cov(xyz.T)), 0.0, None))[::-1]
    if spread[1] < 0.01:
        return ["collinear_points"]
    if spread[2] < 0.01:
        return ["coplanar_points"]
    return []


def _reference_frame(points, centre_xy, z_range, radius_m):
    lo, hi = points.min(axis=0), points.max(axis=0)
    centre_xy = (lo[:2] + hi[:2]) / 2.0 if centre_xy is None else np.asarray(centre_xy, dtype=np.float64)
    z0, z1 = (lo[2], hi[2]) if z_range is None else (float(z_range[0]), float(z_range[1]))
    radial = points[:, :2] - centre_xy[None, :]
    dist = np.hypot(radial[:, 0], radial[:, 1])
    if radius_m is None:
        radius_m = float(dist.max()) if len(dist) else 0.0
    return centre_xy, z0, z1, radial, dist, radius_m


def reference_direction_field(points, theta_upper_deg=80.0, theta_lower_deg=-40.0, k1=1.4, k2=1.0,
                              centre_xy=None, z_range=None, radius_m=None):
    """The previous direction_angles + direction_field (Eq. 5), one after the other."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    _, z0, z1, _, dist, lc = _reference_frame(points, centre_xy, z_range, radius_m)
    height = z1 - z0
    mu1 = np.clip((points[:, 2] - z0) / height, 0.0, 1.0) ** k1 if height > 0 else np.zeros(len(points))
    mu2 = np.clip(dist / lc, 0.0, 1.0) ** k2 if lc > 0 else np.zeros(len(points))
    angles = 90.0 - (90.0 - theta_lower_deg - mu1 * (theta_upper_deg - theta_lower_deg)) * mu2
    theta = np.radians(angles)
    _, _, _, radial, dist, _ = _reference_frame(points, centre_xy, z_range, radius_m)
    out = np.zeros((len(points), 3))
    on_line = dist < 1e-9
    outward = np.zeros_like(radial)
    outward[~on_line] = radial[~on_line] / dist[~on_line, None]
    out[:, :2] = np.cos(theta)[:, None] * outward
    out[:, 2] = np.where(on_line, 1.0, np.sin(theta))
    return angles, out


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

def assert_same_greedy(res, ref):
    np.testing.assert_array_equal(res.point_of_node, ref[0])
    np.testing.assert_array_equal(res.parent, ref[1])
    np.testing.assert_array_equal(res.visited, ref[2])
    np.testing.assert_allclose(res.alpha_deg, ref[3], rtol=0, atol=1e-9, equal_nan=True)


@pytest.mark.parametrize("regrow", [True, False])
def test_greedy_kernel_equals_reference_on_trees(trees, regrow):
    sizes = []
    for name, xyz, gz, st in trees:
        args = (st["cand"], st["graph"].adjacency, st["u"], 0, st["end"], 70.0, 70.0, 30.0, regrow)
        res = greedy_skeleton(*args)
        assert_same_greedy(res, reference_greedy(*args))
        sizes.append(len(res.point_of_node))
    assert min(sizes) > 20 and max(sizes) > 300


def test_greedy_kernel_equals_reference_with_other_angles(trees):
    for name, xyz, gz, st in trees[:5]:
        for a, b, p in [(45.0, 60.0, 15.0), (90.0, 89.0, 45.0), (30.0, 180.0, 5.0)]:
            args = (st["cand"], st["graph"].adjacency, st["u"], 0, st["end"], a, b, p, True)
            assert_same_greedy(greedy_skeleton(*args), reference_greedy(*args))


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
        assert_same_greedy(res, reference_greedy(*args))
        assert res.visited[:len(z)].all()
    # the straight run advances by the longest step (r_p = 1.01 -> 4 spacings)
    assert res.point_of_node[2] == 5


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
    adj, ncomp, labels, n_knn = reference_graph(points, radius, k)
    np.testing.assert_array_equal(g.adjacency.indptr, adj.indptr)
    np.testing.assert_array_equal(g.adjacency.indices, adj.indices)
    np.testing.assert_array_equal(g.adjacency.data, adj.data)
    assert g.n_components == ncomp and g.n_knn == n_knn
    np.testing.assert_array_equal(g.labels, labels)
    return g


def test_graph_kernel_equals_kdtree_reference_on_candidates(trees):
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


# --- §5.1 thinning -------------------------------------------------------------------------

def test_thinning_kernel_equals_reference(trees):
    for name, xyz, gz, st in trees:
        th = thin_voxels(st["all_xyz"], 0.2, keep=st["keep"])
        nbr, inv = voxel_neighbours(st["all_xyz"], 0.2)
        vkeep = np.zeros(len(nbr), dtype=bool)
        vkeep[inv[st["keep"]]] = True
        survivors, passes = reference_thinning(nbr, vkeep)
        np.testing.assert_array_equal(th.voxel_index, survivors)
        assert th.passes == passes
    rng = np.random.default_rng(5)
    block = rng.random((3000, 3)) * [2.0, 1.5, 3.0]                # a solid: many simple voxels
    th = thin_voxels(block, 0.2)
    nbr, _ = voxel_neighbours(block, 0.2)
    survivors, passes = reference_thinning(nbr, np.zeros(len(nbr), bool))
    np.testing.assert_array_equal(th.voxel_index, survivors)
    assert len(survivors) < len(nbr) / 2


def assert_bit_equal(got, want):
    got, want = np.asarray(got), np.asarray(want)
    assert got.dtype == want.dtype and got.shape == want.shape
    assert got.tobytes() == want.tobytes()


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
        inv, means, vkeep, nbr = reference_voxels(xyz, voxel_m, keep)
        assert_bit_equal(th.voxel_of_point, inv)
        assert_bit_equal(th.voxel_means, means)
        assert_bit_equal(th.voxel_keep, vkeep)
        flags = np.zeros(len(xyz), bool) if keep is None else keep
        got = thinning_mod._voxel_grid(np.ascontiguousarray(xyz), float(voxel_m), flags, thinning_mod._COLUMNS)
        assert_bit_equal(got[3], nbr)


def assert_same_trunk(trunk, ref):
    for got, want in zip(trunk, ref):
        if isinstance(want, np.ndarray):
            assert_bit_equal(got, want)
        elif isinstance(want, float) and np.isnan(want):
            assert np.isnan(got)
        else:
            assert got == want and type(got) is type(want)


def test_trunk_kernel_equals_numpy_trunk(trees):
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
            assert_same_trunk(trunk, reference_trunk(xyz, gz, **kw))
            rules.add(trunk.rule)
    assert rules == {"eq3", "eq4"}


def test_screen_kernel_equals_numpy_screening(trees):
    rng = np.random.default_rng(8)
    line = np.c_[np.zeros(30), np.zeros(30), np.linspace(0, 5, 30)] + rng.normal(0, 0.002, (30, 3))
    plane = np.c_[rng.random(40), rng.random(40), np.zeros(40)] + rng.normal(0, 0.002, (40, 3))
    slab = np.c_[rng.random(40), rng.random(40), np.zeros(40)] + rng.normal(0, 0.012, (40, 3))
    cases = [xyz for name, xyz, gz, st in trees]
    cases += [line, plane, slab, np.repeat(rng.random((4, 3)), 10, axis=0), np.array([[0.0, 0, 0], [-0.0, 0, 0]] * 6),
              rng.random((9, 3)), rng.random((30, 3)) * 1e-3]
    assert model_mod._screen_kernel(slab, 10)[1] < model_mod._SPREAD_SURE      # the eigenvalues decide, not the bound
    seen = set()
    for xyz in cases:
        for min_points in (1, 3, 10, 25):
            flags = degenerate_flags(xyz, min_points)
            assert flags == reference_degenerate_flags(xyz, min_points)
            seen.update(flags)
    assert seen == {"too_few_points", "duplicate_points", "collinear_points", "coplanar_points"}
    assert degenerate_flags(slab, 10) == []


def test_direction_field_equals_numpy_formulation(trees):
    rng = np.random.default_rng(9)
    clouds = [st["cand"] for name, xyz, gz, st in trees]
    clouds += [np.r_[np.zeros((1, 3)), rng.random((20, 3)) * 2 - 1], np.zeros((4, 3))]   # points on the centre line
    for pts in clouds:
        for kw in [{}, dict(k1=2.0, k2=0.5), dict(k2=2.0),
                   dict(centre_xy=np.array([0.1, 0.2]), z_range=(0.0, 5.0), radius_m=3.0)]:
            angles, field = reference_direction_field(pts, **kw)
            assert_bit_equal(direction_angles(pts, **kw), angles)
            assert_bit_equal(direction_field(pts, **kw), field)


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
                           reference_greedy(args[0], g.adjacency, *args[1:]))


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
