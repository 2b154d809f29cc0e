"""The normalised cut (core/segment/ncut/, Hu et al. 2017 §4.1): its compiled parts against their definitions,
and the whole segmentation against truth and golden figures.

* the two-tree sub-problems: the submatrix and degrees are scipy's ``W[nodes][:, nodes]`` and its row
  sums; the Fiedler vector solves (D - W) x = λ D x (dense path: LAPACK's second eigenvector; LOBPCG
  path: D-orthogonal to 1, Rayleigh quotient between λ₂ and the start's); the threshold search returns
  the smallest NCut (Eq. 1) of all the thresholds that separate the two tops, counted directly;
* the start-boundary NCut and saddle of every touching pair: Eq. 1 counted directly;
* (I - M) X, the clean-up's union-find and grid searches, the column maxima and every tree's top:
  scipy / numpy / a direct search;
* the one-pass kernels that replaced whole-cloud numpy passes (voxel keys, canopy columns and density, steep
  tops, apex-edge cells, free edges): the numpy forms they replaced, or a direct count;
* the whole method: the 25 cones of a synthetic stand give 25 trees, one per cone, and the shipped
  sample its golden number of trees and detection scores within tolerances.

Elsewhere: the geodesic partition equals scipy's Dijkstra and one pair's NCut and saddle are counted
directly (tests/test_segment.py, also determinism), and 3 x 3 tiles give the trees of one tile
(tests/test_catalog.py).  (The scipy.sparse / numpy implementations the kernels replaced were kept here
as bit-for-bit references; they are in git history.)
"""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg
import scipy.sparse as sp

from sylva.core.segment import NormalizedCut
from sylva.core.segment.base import ground_mask
from sylva.core.segment import ncut as N
from sylva.core.segment.ncut import cleanup as NC
from sylva.core.segment.ncut import cut as NX
from sylva.core.segment.ncut import graph as NG
from sylva.core.segment.ncut import voxel_graph


def _test_segment():
    spec = importlib.util.spec_from_file_location("segment_helpers", Path(__file__).with_name("test_segment.py"))
    mod = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("segment_helpers", mod)
    spec.loader.exec_module(mod)
    return mod


# --- a dense synthetic stand ------------------------------------------------------------------

#: 25 conical crowns, 5 x 5, touching along the rows (x, y, height, crown radius in local metres).
STAND_TREES = [(6.0 + 5.5 * i + (j % 2) * 2.0, 6.0 + 5.0 * j, 14.0 + 3.0 * ((i * 7 + j * 3) % 5), 3.0)
               for i in range(5) for j in range(5)]


@pytest.fixture(scope="module")
def stand():
    """The cloud, true tree per point, voxel graph, start regions of 40 random tops and their touching
    pairs of the stand."""
    T = _test_segment()
    cloud, truth = T.cones(STAND_TREES, (36, 34), density=25.0, seed=3)
    params = NormalizedCut()
    h = cloud.attrs["height"]
    crown = (h >= params.min_height_m) & ~ground_mask(cloud, h)
    graph = voxel_graph(cloud, cloud.local_xyz(), h, crown, params)
    rng = np.random.default_rng(5)
    tops = np.sort(rng.choice(graph.n, 40, replace=False))
    region = NX._geodesic_partition(graph, tops, params.climb)
    a, b = graph.edges[:, 0], graph.edges[:, 1]
    ra, rb = region[a], region[b]
    touch = (ra >= 0) & (rb >= 0) & (ra != rb)
    pairs = np.unique(np.sort(np.column_stack([ra[touch], rb[touch]]), axis=1), axis=0)
    return cloud, truth, graph, tops, region, pairs


def two_tree_problems(stand):
    """Every touching pair as the cut sees it: (nodes, _Pair, index of each top in nodes, start vector)."""
    _, _, graph, tops, region, pairs = stand
    W = graph.W
    order = np.argsort(region, kind="stable")
    starts = np.searchsorted(region[order], np.arange(-1, len(tops) + 1))
    local = np.full(graph.n, -1, dtype=np.int64)
    for p, q in pairs:
        nodes = np.sort(np.concatenate([order[starts[p + 1]:starts[p + 2]], order[starts[q + 1]:starts[q + 2]]]))
        pair = NX._Pair(*NX._pair_subgraph(W.indptr, W.indices, W.data, nodes, local))
        assert (local == -1).all()                   # left as it was found
        ia, ib = int(np.searchsorted(nodes, tops[p])), int(np.searchsorted(nodes, tops[q]))
        yield nodes, pair, ia, ib, np.where(region[nodes] == p, -1.0, 1.0)


def as_csr(pair):
    n = len(pair.deg)
    return sp.csr_matrix((pair.data, pair.indices, pair.indptr), shape=(n, n))


def rayleigh(sub, deg, x):
    """Generalised Rayleigh quotient x'(D - W)x / x'Dx."""
    return float(x @ (deg * x - sub @ x)) / float(x @ (deg * x))


def ncut_of(sub, deg, side):
    """Eq. 1 counted directly: cut(A, B) / assoc(A, V) + cut(A, B) / assoc(B, V)."""
    cut = sub[side][:, ~side].sum()
    return cut / deg[side].sum() + cut / deg[~side].sum()


# --- the two-tree sub-problems ---------------------------------------------------------------

def test_pair_subgraph_is_scipys_submatrix_and_row_sums(stand):
    W = stand[2].W
    assert W.has_sorted_indices and not (W.diagonal() != 0).any()    # what _laplacian_times assumes
    count = 0
    for nodes, pair, _, _, _ in two_tree_problems(stand):
        ref = W[nodes][:, nodes].tocsr()
        ref.sort_indices()
        np.testing.assert_array_equal(pair.indptr, ref.indptr)
        np.testing.assert_array_equal(pair.indices, ref.indices)
        np.testing.assert_array_equal(pair.data, ref.data)
        np.testing.assert_allclose(pair.deg, np.asarray(ref.sum(axis=1)).ravel(), rtol=1e-12)
        count += 1
    assert count > 40


def test_fiedler_vector_solves_the_generalised_eigenproblem(stand):
    """(D - W) x = λ D x, Shi & Malik's relaxation of Eq. 1: on the dense path (<= 60 nodes) x is LAPACK's
    second eigenvector; LOBPCG (FIEDLER_ITERATIONS from the start boundary) keeps x D-orthogonal to the
    constant vector and lowers the Rayleigh quotient from the start's towards λ₂, never below."""
    dense = lobpcg = improved = 0
    for nodes, pair, _, _, start in two_tree_problems(stand):
        deg = pair.deg
        if (deg <= 0).any():
            continue
        sub = as_csr(pair)
        x = NX._fiedler(pair, start)
        n = len(deg)
        assert abs(deg @ x) <= 1e-9 * (deg @ np.abs(x))                 # D-orthogonal to 1
        r = rayleigh(sub, deg, x)
        if n <= 300:                                                    # λ₂ by dense LAPACK
            vals, vecs = scipy.linalg.eigh(np.diag(deg) - sub.toarray(), np.diag(deg), subset_by_index=[1, 1])
            lam2 = float(vals[0])
            assert r >= lam2 - 1e-9 * max(lam2, 1.0)
        if n <= 60:
            v = vecs[:, 0]
            cos = abs(x @ (deg * v)) / np.sqrt((x @ (deg * x)) * (v @ (deg * v)))
            assert cos == pytest.approx(1.0, abs=1e-8) and r == pytest.approx(lam2, rel=1e-8, abs=1e-12)
            dense += 1
        else:
            s0 = start - (deg @ start) / deg.sum()                     # the start, D-orthogonal to 1
            r0 = rayleigh(sub, deg, s0)
            assert r <= r0 * (1 + 1e-9)
            improved += r < 0.99 * r0
            lobpcg += 1
    assert dense >= 2 and lobpcg > 40 and improved > 0.5 * lobpcg      # both paths, and LOBPCG moves


def test_best_split_is_the_smallest_ncut_between_the_two_tops(stand):
    """Shi & Malik's threshold search: A = the nodes below a threshold on the Fiedler vector, holding the first
    top and not the second; the split returned has the NCut (Eq. 1) it reports, counted directly, and on the
    smaller problems no threshold gives less (every one tried, each NCut counted from the dense matrix)."""
    checked = searched = 0
    for nodes, pair, ia, ib, start in two_tree_problems(stand):
        deg = pair.deg
        if (deg <= 0).any():
            continue
        sub = as_csr(pair)
        x = NX._fiedler(pair, start)
        side, ncut = NX._best_split(pair, x, ia, ib)
        if not np.isfinite(ncut):                    # x ties the two tops: nothing to search
            continue
        assert side[ia] and not side[ib]
        xs = -x if x[ia] > x[ib] else x
        assert xs[side].max() <= xs[~side].min()     # A lies below a threshold
        assert ncut == pytest.approx(ncut_of(sub, deg, side), rel=1e-9)
        checked += 1
        if len(deg) <= 300:
            order = np.argsort(xs, kind="stable")
            rank = np.empty(len(xs), dtype=np.int64)
            rank[order] = np.arange(len(xs))
            dense = sub.toarray()
            best = np.inf
            for t in range(rank[ia] + 1, rank[ib] + 1):          # A = the t lowest: a in A, b not
                a_side = rank < t
                cut = dense[np.ix_(a_side, ~a_side)].sum()
                best = min(best, cut / deg[a_side].sum() + cut / deg[~a_side].sum())
            assert ncut <= best * (1 + 1e-9)
            searched += 1
    assert checked > 40 and searched > 10


def test_start_boundary_ncut_and_saddle_of_every_pair_are_eq1(stand):
    """The NCut (Eq. 1) of the start boundary of every touching pair, and its saddle (the highest boundary
    edge, at the lower of its two voxels), counted region by region."""
    _, _, graph, tops, region, pairs = stand
    mine, ncut, saddle = NX._pair_ncut(graph, region, len(tops))
    assert np.array_equal(mine, pairs)      # every touching pair, as the edges list them
    W = graph.W
    a, b = graph.edges[:, 0], graph.edges[:, 1]
    z = graph.xyz[:, 2]
    for k, (p, q) in enumerate(pairs):
        P, Q = np.flatnonzero(region == p), np.flatnonzero(region == q)
        both = np.r_[P, Q]
        cut = W[P][:, Q].sum()
        expected = cut / W[P][:, both].sum() + cut / W[Q][:, both].sum()
        assert ncut[k] == pytest.approx(expected, rel=1e-9)
        across = ((region[a] == p) & (region[b] == q)) | ((region[a] == q) & (region[b] == p))
        assert saddle[k] == np.minimum(z[a], z[b])[across].max()
    assert len(pairs) > 40


def test_laplacian_times_equals_assembled_product():
    """(I - M) X as scipy computes it with the assembled Laplacian, including rows with no entries."""
    rng = np.random.default_rng(1)
    n = 50
    A = sp.random(n, n, density=0.1, random_state=2, format="csr")
    A = sp.triu(A, 1)
    A = (A + A.T).tocsr()
    A.sort_indices()
    X = rng.normal(size=(n, 3))
    L = (sp.identity(n, format="csr") - A).tocsr()
    got = NX._laplacian_times(A.indptr, A.indices, A.data, X)
    np.testing.assert_array_equal(got, L @ X)
    np.testing.assert_array_equal(NX._laplacian_times(A.indptr, A.indices, A.data, X[:, :1])[:, 0], L @ X[:, 0])


def test_clean_kernels_equal_scipy(stand):
    """The fragment test (union-find) and the attach search (grid) give what connected_components
    and cKDTree.sparse_distance_matrix gave: the same mask, the same pairs and distances."""
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    _, _, graph, tops, region, _ = stand
    a, b = graph.edges[:, 0], graph.edges[:, 1]
    rng = np.random.default_rng(7)
    vlabel = np.where(region >= 0, region + 1, 0)
    vlabel[rng.random(graph.n) < 0.05] = 0                       # holes cut fragments off
    top_id = np.arange(1, len(tops) + 1)
    top_id[::7] += 1                                             # some tops not their voxel's id
    same = (vlabel[a] == vlabel[b]) & (vlabel[a] > 0)
    G = sp.coo_matrix((np.ones(same.sum()), (a[same], b[same])), shape=(graph.n, graph.n))
    _, frag = connected_components(G, directed=False)
    good = np.zeros(frag.max() + 1, dtype=bool)
    good[frag[tops[vlabel[tops] == top_id]]] = True              # a component holding any of its tops
    got = NC._joined_to_top(a, b, vlabel, tops.astype(np.int64), top_id)
    assert 0.3 < got.mean() < 0.95
    np.testing.assert_array_equal(got, good[frag])

    free = np.flatnonzero(vlabel == 0)
    for r in (0.7, 2.0):
        near = cKDTree(graph.xyz[free]).sparse_distance_matrix(cKDTree(graph.xyz), r, output_type="ndarray")
        ref = (free[near["i"]], near["j"].astype(np.int64), near["v"])
        mine = NC._pairs_within(graph.xyz, free, r)
        o1, o2 = np.lexsort(ref[::-1]), np.lexsort(mine[::-1])
        assert len(ref[0]) > 100
        for x, y in zip(ref, mine):
            np.testing.assert_array_equal(x[o1], y[o2])


def test_column_maxima_grid_equals_sorts():
    """The grid of :func:`~sylva.core.segment.ncut.graph.column_maxima` keeps the highest point of every cell, ties
    to the lowest index: the first of each cell in a stable sort by descending height (numpy's argsort and unique)."""
    rng = np.random.default_rng(9)
    xy = rng.uniform(0, 40, size=(20000, 2))
    z = np.round(rng.uniform(0, 30, size=20000), 1)          # many exact ties
    ij = np.floor(xy / 0.35).astype(np.int64)                # cells of the local frame, not of the extent
    ij -= ij.min(axis=0)
    key = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
    order = np.argsort(-z, kind="stable")
    _, first = np.unique(key[order], return_index=True)
    np.testing.assert_array_equal(NG.column_maxima(xy, z, 0.35), np.sort(order[first]))
    far = np.r_[xy, [[1e6, 1e6]]]                             # a huge extent takes the sorting path
    assert len(NG.column_maxima(far, np.r_[z, 1.0], 0.35)) == len(first) + 1


def test_voxel_keys_are_numpys_unique():
    """The voxel keys by two counting sorts are ``np.unique(key, return_inverse=True)``, cells from floor(x / pitch)."""
    rng = np.random.default_rng(3)
    x, y = rng.uniform(-30, 45, 30000), rng.uniform(5, 60, 30000)
    z = np.round(rng.uniform(2, 25, 30000), 1)
    x[:50] = x[50]                                             # a column of many points
    ix, iy, iz, i0, j0 = NG._voxel_cells(x, y, z, 0.5)
    fx, fy = np.floor(x / 0.5).astype(np.int64), np.floor(y / 0.5).astype(np.int64)
    assert (i0, j0) == (fx.min(), fy.min())
    assert np.array_equal(ix, fx - fx.min()) and np.array_equal(iy, fy - fy.min())
    assert np.array_equal(iz, np.floor(z / 0.5).astype(np.int64))
    nx, ny, nz = ix.max() + 1, iy.max() + 1, iz.max() + 1
    ukey, inv = NG._voxel_keys(ix, iy, iz, nx, ny, nz)
    ref_key, ref_inv = np.unique((ix * ny + iy) * nz + iz, return_inverse=True)
    assert np.array_equal(ukey, ref_key) and np.array_equal(inv, ref_inv)


def test_canopy_columns_and_density_count_every_1m_column():
    """The canopy grid (every observed column, the highest crown point of each) and the canopy density around a
    point, counted directly."""
    from sylva.core.cloud import PointCloud

    rng = np.random.default_rng(4)
    local = np.c_[rng.uniform(0, 30, (5000, 2)), rng.uniform(0, 1, 5000)]
    h = np.round(rng.uniform(0, 20, 5000), 1)
    crown = h >= 2.0
    cols = NG.canopy_columns(local, h, crown)
    ij = np.floor(local[:, :2]).astype(np.int64) - cols.lo
    for i, j in [(0, 0), (7, 12), (29, 29), (15, 3)]:
        here = (ij[:, 0] == i) & (ij[:, 1] == j)
        assert cols.observed[i, j] == here.any()
        assert cols.canopy[i, j] == h[here & crown].max(initial=0.0)
    dens = NG.local_canopy_density(PointCloud(local), local, crown)
    for k in (0, 1, 2500):
        box = np.all(np.abs(np.floor(local[crown, :2]) - np.floor(local[k, :2])) <= NG.DENSITY_HALF_WIDTH_M, axis=1)
        occupied = len(np.unique(np.floor(local[crown][box, :2]), axis=0))
        assert dens[k] == pytest.approx(box.sum() / occupied)


def test_steep_tops_judge_the_tops_against_the_points_surface():
    """Joining the tops to the points' own column maxima is joining them to every point (same ties)."""
    from sylva.core.tops import SteepApex, _steep, steep_tops

    rng = np.random.default_rng(6)
    xy = rng.uniform(0, 30, (8000, 2))
    h = np.round(rng.uniform(0, 4, 8000), 1)
    h[xy[:, 0] > 15] += 6.0                                  # half the ground high: tops there are not steep
    top_xy = rng.uniform(2, 28, (40, 2))
    top_h = rng.uniform(8, 12, 40)
    rule = SteepApex(2.0, 1.0, 3)
    every = _steep(np.r_[xy, top_xy], np.r_[h, top_h], np.arange(8000, 8040), rule)
    assert 0 < every.sum() < 40
    assert np.array_equal(steep_tops(xy, h, top_xy, top_h, rule), every)


def test_blocks_around_and_free_edges_equal_their_numpy_forms():
    """The apex-edge cell blocks (``np.isin`` on cell keys) and the flood's free edges (masked concatenations)."""
    rng = np.random.default_rng(8)
    xy = rng.uniform(0, 50, (20000, 2))
    labels = rng.integers(0, 4, 20000).astype(np.int32)
    high = rng.integers(0, 20000, 30)
    cell = np.floor(xy).astype(np.int64)
    cell -= cell.min(axis=0) - 1
    rows = int(cell[:, 1].max()) + 2
    step = np.array([-1, 0, 1])
    around = (cell[high, 0, None, None] + step[:, None]) * rows + cell[high, 1, None, None] + step
    expected = (labels > 0) & np.isin(cell[:, 0] * rows + cell[:, 1], around.ravel())
    assert np.array_equal(NC.in_blocks_around(xy, labels > 0, np.ascontiguousarray(xy[high]), 1.0), expected)
    a, b = rng.integers(0, 500, 3000), rng.integers(0, 500, 3000)
    w, vlabel = rng.uniform(size=3000), rng.integers(0, 3, 500)
    fa, fb = vlabel[a] == 0, vlabel[b] == 0
    src, dst, ww = NC._edges_from_free(a, b, w, vlabel)
    assert np.array_equal(src, np.r_[a[fa], b[fb]]) and np.array_equal(dst, np.r_[b[fa], a[fb]])
    assert np.array_equal(ww, np.r_[w[fa], w[fb]])


def test_tops_of_is_the_highest_point_of_every_tree():
    """Each tree's top in one pass is its highest point, ties to the lowest x, then the lowest y, then the first
    point (a direct search per label); labels may skip values."""
    rng = np.random.default_rng(11)
    n = 30000
    xy = np.round(rng.uniform(0, 20, size=(n, 2)), 0)        # many equal x and y
    h = np.round(rng.uniform(0, 5, size=n), 0)               # many equal heights
    labels = rng.choice(np.array([0, 1, 2, 5, 9, 40, 41, 300]), size=n).astype(np.int32)
    ids, txy, th = NC.label_tops(xy, h, labels)
    assert ids.tolist() == [1, 2, 5, 9, 40, 41, 300]
    duplicated = 0
    for k, label in enumerate(ids):
        members = np.flatnonzero(labels == label)
        top = min(members.tolist(), key=lambda i: (-h[i], xy[i, 0], xy[i, 1], i))
        np.testing.assert_array_equal(txy[k], xy[top])
        assert th[k] == h[top]
        same = members[(h[members] == h[top]) & (xy[members] == xy[top]).all(axis=1)]
        duplicated += len(same) > 1          # the top's point is there twice or more: the first is taken
    assert duplicated > 0
    none = np.zeros(n, dtype=np.int32)
    assert all(len(v) == 0 for v in NC.label_tops(xy, h, none))


# --- the whole method --------------------------------------------------------------------------

def test_the_stand_gives_one_tree_per_cone(stand):
    """The 25 touching cones of the stand: 25 trees, each the largest share of a different cone, and
    nearly every crown point with its cone's tree."""
    cloud, truth = stand[0], stand[1]
    labels = N.NormalizedCut().segment(cloud)
    assert len(np.unique(labels[labels > 0])) == len(STAND_TREES)
    tree = truth > 0
    majority = {}
    for t in range(1, len(STAND_TREES) + 1):
        got, counts = np.unique(labels[truth == t], return_counts=True)
        majority[t] = int(got[np.argmax(counts)])
    assert 0 not in majority.values() and len(set(majority.values())) == len(STAND_TREES)
    lookup = np.array([0] + [majority[t] for t in range(1, len(STAND_TREES) + 1)])
    assert np.mean(labels[tree] == lookup[truth[tree]]) > 0.9           # 0.934 when written


#: NormalizedCut() on resources/sample/sample.laz against sample_trees.csv (239 trees) when written (issue 19;
#: since the crown-class cap of issue 16: 236 trees, was 233),
#: with the tolerance of each: benchmarks/metrics.py's matching (detection within the crown, height within 30 %).
SAMPLE_GOLDEN = {"n_detected": (236, 3), "f1": (0.9727, 0.015), "point_accuracy": (0.9380, 0.015)}


def test_the_sample_gives_its_golden_trees(sample_laz):
    import laspy

    from sylva.core.io.las import read_las
    from sylva.core.terrain import normalize
    from sylva.testing.synth import read_truth

    cloud = normalize(read_las(str(sample_laz)))
    truth = np.asarray(laspy.read(str(sample_laz)).true_tree)
    trees = read_truth(Path(sample_laz).with_name("sample_trees.csv"))
    method = N.NormalizedCut()
    labels = method.segment(cloud)
    scores = _test_segment()._metrics().evaluate(cloud.xyz, cloud.attrs["height"], labels, truth, trees)
    assert scores["n_true"] == 239
    off = {k: scores[k] for k, (want, tol) in SAMPLE_GOLDEN.items() if abs(scores[k] - want) > tol}
    assert not off, f"differ from the golden figures {SAMPLE_GOLDEN}: {off}"
    _, counts = np.unique(labels[labels > 0], return_counts=True)
    assert counts.min() >= method.min_tree_points
