"""The compiled parts of the normalised cut (core/segment/ncut/, Hu et al. 2017 §4.1) are exact.

The multi-source Dijkstra, the two-tree sub-problems (submatrix, degrees, the
normalised Laplacian's products inside LOBPCG, Shi & Malik's threshold search)
and the start-boundary NCut of every pair moved from scipy.sparse / numpy into
numba kernels.  The implementations they replaced are kept below verbatim
(``reference_*``) and every sub-problem of a segmentation is compared with them
bit for bit, as is the whole segmentation.
"""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg
import scipy.sparse as sp

from sylva.core.jit import njit
from sylva.core.segment import NormalizedCut
from sylva.core.segment.base import ground_mask
from sylva.core.segment import ncut as N
from sylva.core.segment.ncut import cleanup as NC
from sylva.core.segment.ncut import cut as NX
from sylva.core.segment.ncut import graph as NG
from sylva.core.segment.ncut import FIEDLER_ITERATIONS, voxel_graph


def _test_segment():
    spec = importlib.util.spec_from_file_location("segment_helpers", Path(__file__).with_name("test_segment.py"))
    mod = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("segment_helpers", mod)
    spec.loader.exec_module(mod)
    return mod


# --- references: the implementations the kernels replaced (verbatim but for their names) ---

def reference_lobpcg1(L: sp.csr_matrix, x: np.ndarray, y: np.ndarray, maxiter: int,
             tol: float = 1e-4) -> np.ndarray:
    """Smallest eigenvector of symmetric ``L`` orthogonal to unit vector ``y``.

    Knyazev's LOBPCG (2001) with block size one and no preconditioner (the
    normalised Laplacian has a unit diagonal, so Jacobi would change nothing):
    Rayleigh–Ritz on span{x, residual, previous step} per iteration.  A lean
    version of :func:`scipy.sparse.linalg.lobpcg`, whose per-call overhead
    dominates on the many small two-tree problems.
    """
    x = x - y * (y @ x)
    x /= np.linalg.norm(x)
    ax = L @ x
    lam = x @ ax
    p = None
    for _ in range(maxiter):
        r = ax - lam * x
        r -= y * (y @ r)
        if np.linalg.norm(r) < tol:
            break
        cols = [x, r] if p is None else [x, r, p]
        Q, R = np.linalg.qr(np.column_stack(cols))
        keep = np.abs(np.diag(R)) > 1e-10 * np.abs(R[0, 0])
        Q = Q[:, keep]
        Q -= np.outer(y, y @ Q)
        AQ = L @ Q
        G = Q.T @ AQ
        vals, vecs = np.linalg.eigh((G + G.T) / 2.0)
        c = vecs[:, 0]
        x_new = Q @ c
        p = Q[:, 1:] @ c[1:]
        norm = np.linalg.norm(x_new)
        x = x_new / norm
        ax = (AQ @ c) / norm
        lam = x @ ax
    return x


def reference_fiedler(W: sp.csr_matrix, deg: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Second-smallest generalised eigenvector x of (D - W) x = λ D x.

    Computed as the second-smallest eigenvector u of the normalised Laplacian
    L = I - D^-1/2 W D^-1/2 (the same eigenproblem, x = D^-1/2 u; the smallest
    is D^1/2 1) by LOBPCG (:func:`_lobpcg1`, ``FIEDLER_ITERATIONS``) started
    from ``start``; dense LAPACK for tiny graphs.  D^-1/2 W D^-1/2 is formed
    by scaling W's stored values in place of two sparse products.
    """
    n = W.shape[0]
    sq = np.sqrt(deg)
    inv = 1.0 / sq
    row = np.repeat(np.arange(n), np.diff(W.indptr))
    M = sp.csr_matrix((W.data * inv[row] * inv[W.indices], W.indices, W.indptr), shape=(n, n))
    if n > 60:
        L = (sp.identity(n, format="csr") - M).tocsr()
        u = reference_lobpcg1(L, start * sq, sq / np.linalg.norm(sq), FIEDLER_ITERATIONS)
    else:
        _, vecs = scipy.linalg.eigh(M.toarray(), subset_by_index=[n - 2, n - 2],
                                    check_finite=False)
        u = vecs[:, 0]
    return u / sq


def reference_submatrix(W: sp.csr_matrix, nodes: np.ndarray, local: np.ndarray) -> sp.csr_matrix:
    """``W[nodes][:, nodes]`` for sorted ``nodes``; ``local`` maps a node to its
    position in ``nodes`` and is -1 elsewhere (it is left as it was found)."""
    local[nodes] = np.arange(len(nodes))
    lo = W.indptr[nodes]
    cnt = W.indptr[nodes + 1] - lo
    offs = np.repeat(lo - np.concatenate([[0], np.cumsum(cnt)[:-1]]), cnt)
    pos = np.arange(int(cnt.sum())) + offs
    cols = local[W.indices[pos]]
    keep = cols >= 0
    rows = np.repeat(np.arange(len(nodes)), cnt)[keep]
    indptr = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=len(nodes)))])
    local[nodes] = -1
    return sp.csr_matrix((W.data[pos][keep], cols[keep], indptr), shape=(len(nodes), len(nodes)))


def reference_best_split(W: sp.csr_matrix, deg: np.ndarray, x: np.ndarray, a: int, b: int):
    """Shi & Malik's threshold search on the sorted Fiedler vector: the split with
    the smallest NCut (Eq. 1) that puts node ``a`` in A and node ``b`` in B.

    Returns (boolean mask of A, NCut of that split)."""
    n = len(x)
    if x[a] > x[b]:
        x = -x
    order = np.argsort(x, kind="stable")
    rank = np.empty(n, dtype=np.int64)
    rank[order] = np.arange(n)
    coo = W.tocoo()
    up = coo.row < coo.col
    r1 = rank[coo.row[up]]
    r2 = rank[coo.col[up]]
    lo = np.minimum(r1, r2)
    hi = np.maximum(r1, r2)
    w = coo.data[up]
    # cut(t) with A = the first t nodes (t = 1..n-1): the edges with lo < t <= hi
    diff = (np.bincount(lo + 1, weights=w, minlength=n + 1)
            - np.bincount(hi + 1, weights=w, minlength=n + 1))
    cut = np.cumsum(diff)[1:n]
    assoc_a = np.cumsum(deg[order])[:n - 1]
    total = deg.sum()
    ncut = cut / assoc_a + cut / np.maximum(total - assoc_a, 1e-300)
    t_lo, t_hi = rank[a] + 1, rank[b]
    if t_hi < t_lo:  # pragma: no cover - ties in x
        return rank <= rank[a], float("inf")
    best = t_lo - 1 + int(np.argmin(ncut[t_lo - 1:t_hi]))
    return rank < best + 1, float(ncut[best])


@njit
def reference_nearest_source(indptr, indices, w, z, climb, sources):
    """Multi-source Dijkstra over a CSR affinity graph: index into ``sources``
    of the nearest source of every node (-1: unreachable).

    The step i -> j costs -log w_ij + 1e-9 + ``climb`` x max(z_j - z_i, 0).

    An indexed binary heap with decrease-key (numba, O(n) memory); scipy's
    ``dijkstra(min_only=True)`` gives the same partition but its Fibonacci
    heap is twice as slow on graphs of millions of voxels.  A node reached by
    two sources at exactly the same cost keeps the first; a voxel holding two
    sources keeps the later one."""
    n = len(indptr) - 1
    dist = np.full(n, np.inf)
    owner = np.full(n, -1, dtype=np.int64)
    heap = np.empty(n, dtype=np.int64)      # nodes, a binary heap on dist
    pos = np.full(n, -1, dtype=np.int64)    # place in heap; -1 never queued, -2 settled
    size = 0
    for k in range(len(sources)):
        s = sources[k]
        owner[s] = k
        if pos[s] == -1:
            dist[s] = 0.0
            heap[size] = s
            pos[s] = size
            size += 1
    while size:
        u = heap[0]
        pos[u] = -2
        size -= 1
        if size:                             # last node to the root, sift down
            x = heap[size]
            dx = dist[x]
            i = 0
            while True:
                c = 2 * i + 1
                if c >= size:
                    break
                if c + 1 < size and dist[heap[c + 1]] < dist[heap[c]]:
                    c += 1
                if dist[heap[c]] < dx:
                    heap[i] = heap[c]
                    pos[heap[i]] = i
                    i = c
                else:
                    break
            heap[i] = x
            pos[x] = i
        du = dist[u]
        zu = z[u]
        o = owner[u]
        for e in range(indptr[u], indptr[u + 1]):
            v = indices[e]
            if pos[v] == -2:
                continue
            nd = du - np.log(max(w[e], 1e-300)) + 1e-9 + climb * max(z[v] - zu, 0.0)
            if nd < dist[v]:
                dist[v] = nd
                owner[v] = o
                i = pos[v]
                if i == -1:
                    i = size
                    size += 1
                while i > 0:                 # sift up
                    p = (i - 1) >> 1
                    if dist[heap[p]] > nd:
                        heap[i] = heap[p]
                        pos[heap[i]] = i
                        i = p
                    else:
                        break
                heap[i] = v
                pos[v] = i
    return owner


def reference_pair_ncut(graph, region: np.ndarray, pairs: np.ndarray, k: int) -> np.ndarray:
    """NCut (Eq. 1) of the start boundary of every pair of regions, in one pass.

    For regions p, q: cut = w(p, q); the association of p within the union is
    2 w(p, p) + w(p, q) (every internal edge counts from both ends)."""
    a, b = graph.edges[:, 0], graph.edges[:, 1]
    w = graph.weights
    ra, rb = region[a], region[b]
    ok = (ra >= 0) & (rb >= 0)
    ra, rb, w = ra[ok], rb[ok], w[ok]
    inner = np.bincount(ra[ra == rb], weights=w[ra == rb], minlength=k)
    lo, hi = np.minimum(ra, rb), np.maximum(ra, rb)
    between = lo != hi
    key = lo[between] * k + hi[between]
    ukey, inv = np.unique(key, return_inverse=True)
    cut_u = np.bincount(inv, weights=w[between], minlength=len(ukey))
    pos = np.searchsorted(ukey, pairs[:, 0] * k + pairs[:, 1])
    cut = cut_u[pos]
    vol_p = 2.0 * inner[pairs[:, 0]] + cut
    vol_q = 2.0 * inner[pairs[:, 1]] + cut
    ncut = cut / np.maximum(vol_p, 1e-300) + cut / np.maximum(vol_q, 1e-300)
    # saddle: the highest boundary edge (the lower of its two voxel heights)
    z = graph.xyz[:, 2]
    zb = np.minimum(z[a[ok]], z[b[ok]])[between]
    top_z = np.full(len(ukey), -np.inf)
    np.maximum.at(top_z, inv, zb)
    return ncut, top_z[pos]


# --- the comparisons ------------------------------------------------------------------------

@pytest.fixture(scope="module")
def stand():
    """The voxel graph, start regions and touching pairs of a small dense synthetic stand."""
    T = _test_segment()
    trees = [(6.0 + 5.5 * i + (j % 2) * 2.0, 6.0 + 5.0 * j, 14.0 + 3.0 * ((i * 7 + j * 3) % 5), 3.0)
             for i in range(5) for j in range(5)]
    cloud, _ = T.cones(trees, (36, 34), density=25.0, seed=3)
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
    return cloud, graph, tops, region, pairs, params


def test_dijkstra_equals_reference(stand):
    _, graph, tops, region, _, params = stand
    W = graph.W
    ref = reference_nearest_source(W.indptr, W.indices, W.data, np.ascontiguousarray(graph.xyz[:, 2]),
                                   float(params.climb), tops.astype(np.int64))
    assert (ref >= 0).mean() > 0.9 and len(np.unique(ref)) > 30
    np.testing.assert_array_equal(region, ref)


def test_pair_ncut_equals_reference(stand):
    _, graph, tops, region, pairs, _ = stand
    got = NX._pair_ncut(graph, region, pairs, len(tops))
    ref = reference_pair_ncut(graph, region, pairs, len(tops))
    assert len(pairs) > 40
    for g, r in zip(got, ref):
        np.testing.assert_array_equal(g, r)


def test_two_tree_subproblems_equal_reference(stand):
    """Every pair's submatrix, degrees, Fiedler vector and best split, bit for bit."""
    _, graph, tops, region, pairs, _ = stand
    W = graph.W
    assert W.has_sorted_indices and not (W.diagonal() != 0).any()    # what _laplacian_times assumes
    order = np.argsort(region, kind="stable")
    starts = np.searchsorted(region[order], np.arange(-1, len(tops) + 1))
    local = np.full(graph.n, -1, dtype=np.int64)
    sizes = []
    for p, q in pairs:
        nodes = np.sort(np.concatenate([order[starts[p + 1]:starts[p + 2]], order[starts[q + 1]:starts[q + 2]]]))
        pair = NX._Pair(*NX._pair_subgraph(W.indptr, W.indices, W.data, nodes, local))
        sub = reference_submatrix(W, nodes, local)
        assert (local == -1).all()
        np.testing.assert_array_equal(pair.indptr, sub.indptr)
        np.testing.assert_array_equal(pair.indices, sub.indices)
        np.testing.assert_array_equal(pair.data, sub.data)
        row_of = np.repeat(np.arange(len(nodes)), np.diff(sub.indptr))
        deg = np.bincount(row_of, weights=sub.data, minlength=len(nodes))
        np.testing.assert_array_equal(pair.deg, deg)
        if (deg <= 0).any():
            continue
        ia, ib = int(np.searchsorted(nodes, tops[p])), int(np.searchsorted(nodes, tops[q]))
        start = np.where(region[nodes] == p, -1.0, 1.0)
        x = NX._fiedler(pair, start)
        np.testing.assert_array_equal(x, reference_fiedler(sub, deg, start))
        side, ncut = NX._best_split(pair, x, ia, ib)
        side_ref, ncut_ref = reference_best_split(sub, deg, x, ia, ib)
        np.testing.assert_array_equal(side, side_ref)
        assert ncut == ncut_ref
        sizes.append(len(nodes))
    assert len(sizes) > 40 and min(sizes) <= 60 < max(sizes)     # dense and LOBPCG paths


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


def test_segmentation_unchanged_by_the_kernels(stand, monkeypatch):
    """The whole normalised cut with the reference pieces gives the same labels."""
    cloud = stand[0]
    got = N.NormalizedCut().segment(cloud)

    def ref_fiedler(pair, start):
        n = len(pair.deg)
        sub = sp.csr_matrix((pair.data, pair.indices, pair.indptr), shape=(n, n))
        return reference_fiedler(sub, pair.deg, start)

    def ref_split(pair, x, a, b):
        n = len(pair.deg)
        sub = sp.csr_matrix((pair.data, pair.indices, pair.indptr), shape=(n, n))
        return reference_best_split(sub, pair.deg, x, a, b)

    monkeypatch.setattr(NX, "_fiedler", ref_fiedler)
    monkeypatch.setattr(NX, "_best_split", ref_split)
    monkeypatch.setattr(NX, "_pair_ncut", reference_pair_ncut)
    monkeypatch.setattr(NX, "_nearest_source", reference_nearest_source)
    ref = N.NormalizedCut().segment(cloud)
    assert len(np.unique(got)) > 15
    np.testing.assert_array_equal(got, ref)


def test_clean_kernels_equal_scipy(stand):
    """The fragment test (union-find) and the attach search (grid) give what connected_components
    and cKDTree.sparse_distance_matrix gave: the same mask, the same pairs and distances."""
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    _, graph, tops, region, _, _ = stand
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
    good[frag[tops]] = vlabel[tops] == top_id
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
    """The grid of :func:`~sylva.core.segment.ncut.graph.column_maxima` picks what the two stable sorts picked, ties included."""
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


def reference_tops_of(xy, height, labels):
    """The lexsort :func:`_tops_of` replaced (verbatim but for its name)."""
    sel = np.flatnonzero(labels > 0)
    order = sel[np.lexsort((xy[sel, 1], xy[sel, 0], -height[sel], labels[sel]))]
    first = np.ones(len(order), dtype=bool)
    first[1:] = labels[order][1:] != labels[order][:-1]
    top = order[first]
    return labels[top], xy[top], height[top]


def test_tops_of_equals_the_sort():
    """Each tree's top in one pass picks the point the lexsort picked: ties in height, in x, and
    exact duplicates (then the first point) included; labels may skip values."""
    rng = np.random.default_rng(11)
    n = 30000
    xy = np.round(rng.uniform(0, 20, size=(n, 2)), 0)        # many equal x and y
    h = np.round(rng.uniform(0, 5, size=n), 0)               # many equal heights
    labels = rng.choice(np.array([0, 1, 2, 5, 9, 40, 41, 300]), size=n).astype(np.int32)
    for a, b in zip(reference_tops_of(xy, h, labels), NC._tops_of(xy, h, labels)):
        np.testing.assert_array_equal(a, b)
    ids, _, _ = NC._tops_of(xy, h, labels)
    assert ids.tolist() == [1, 2, 5, 9, 40, 41, 300]
    none = np.zeros(n, dtype=np.int32)
    assert all(len(v) == 0 for v in NC._tops_of(xy, h, none))
