"""Graph of candidate skeleton points (Hu et al. 2017, §5.2, Algorithm 1).

Algorithm 1 (GraphGenerate(r_p, k)) inserts the candidate points P into a
k-d tree, connects every p_i to all points within the fixed radius r_p
(FRNN), counts its neighbours n_i, and then, for every p_i with n_i < k,
also connects its k nearest points (kNN).  Edges are undirected and weighted
by the Euclidean distance ‖p_i − p_j‖.  The kNN pass connects sparse parts
that a small radius alone leaves apart (Fig. 10), so that the skeleton can
be grown over one connected graph.

Sylva answers both queries from one uniform grid of cells of edge r_p
instead of a k-d tree (a compiled kernel, :mod:`sylva.core.jit`): the FRNN
neighbours of p_i lie in the 27 cells around its own (distance ≤ r_p), and
the kNN search walks shells of cells outward until no unvisited cell can
hold a nearer point, finding the k nearest with a histogram of the
distances instead of sorting them.  A second kernel writes the symmetric
CSR matrix straight from the neighbour rows.  Where the k-th and the
(k+1)-th nearest lie at exactly the same distance (common next to the
evenly spaced trunk points of §4.2) which one is "the k nearest" is the
search's own choice; for those points Sylva asks ``scipy.spatial.cKDTree``,
so the edges are exactly those of Algorithm 1 written with a k-d tree
(tests/test_skeleton_kernel.py compares them).

Defaults (§6.2, Table 1): r_p = 1.2 m, k ∈ [10, 30] "according to r_p";
Sylva uses k = 30 (see :class:`~.skeleton.GreedySkeleton` for why).
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from scipy.sparse import csr_matrix
from scipy.spatial import cKDTree

from ..errors import InputError
from ..jit import njit
from ..kernels.buckets import bucket_by_cell
from ..kernels.unionfind import uf_union

#: Most grid cells the kernel allocates per point (plus a constant); beyond it the cells grow.
_CELLS_PER_POINT = 8
_CELLS_PER_RADIUS = 1          # grid cell edge = r_p
_CELLS_MIN = 1 << 17


class CSRArrays(NamedTuple):
    """The arrays of a CSR matrix, what :func:`~.skeleton.greedy_skeleton` reads of one
    (Sylva, not in the paper: the greedy skeleton takes them without a scipy matrix per tree)."""

    indptr: np.ndarray      # (n + 1,) int64
    indices: np.ndarray     # (nnz,) int64, sorted within each row
    data: np.ndarray        # (nnz,) float64
    shape: tuple

    @property
    def nnz(self) -> int:
        return len(self.indices)


class Graph(NamedTuple):
    """Result of :func:`build_graph` (and of :func:`graph_arrays`, with :class:`CSRArrays`)."""

    adjacency: csr_matrix   # (n, n) symmetric, data = edge length in metres, sorted indices
    n_components: int       # connected components (1 = connected, as Algorithm 2 needs)
    labels: np.ndarray      # (n,) component of every point (numbered by their lowest point)
    n_knn: int              # points that needed the kNN pass (n_i < k)

    @property
    def connected(self) -> bool:
        return self.n_components <= 1

    @property
    def n_edges(self) -> int:
        return self.adjacency.nnz // 2


#: Histogram bins of the kNN selection (see :func:`_graph_frnn_knn`).
_BINS = 32


@njit
def _graph_frnn_knn(points, radius, k, cells_per_radius, cell_limit, nbins, cap):
    """Algorithm 1's two searches on a grid of cubic cells; see :func:`build_graph`.

    The cells are a hair wider than r_p / ``cells_per_radius`` (a pair at
    exactly r_p can then never be two cells apart through the rounding of
    floor((x - lo) / cell)), twice as wide while there are more than
    ``cell_limit`` of them.  Returns whether all points are finite (nothing
    else is computed when not), the FRNN rows (every j != i within
    ``radius``: ``frnn_j[frnn_ptr[i]:frnn_ptr[i + 1]]``; when there are more
    than ``cap`` only ``frnn_ptr`` is right and the caller runs again), the kNN rows of the
    points with n_i < k without the neighbours within ``radius`` (FRNN ones
    already; ``far_j[far_ptr[i]:far_ptr[i + 1]]``, left empty where the k-th
    and the (k+1)-th nearest tie), which points tie, and how many had n_i < k.
    """
    n = points.shape[0]
    lo = points[0].copy()
    hi = points[0].copy()
    finite = True
    for i in range(n):
        for a in range(3):
            v = points[i, a]
            finite = finite and math.isfinite(v)
            lo[a] = min(lo[a], v)
            hi[a] = max(hi[a], v)
    if not finite:
        e = np.zeros(1, np.int64)
        return False, e, e, e, e, np.zeros(1, np.bool_), 0
    cell = radius * (1.0 + 1e-7) / cells_per_radius if radius > 0 else 1.0
    dims = np.empty(3, np.int64)
    while True:
        for a in range(3):
            dims[a] = int(math.floor((hi[a] - lo[a]) / cell)) + 1
        if float(dims[0]) * float(dims[1]) * float(dims[2]) <= cell_limit:
            break
        cell *= 2.0
    reach = max(1, int(math.ceil(radius / cell))) if radius > 0 else 1
    nx, ny, nz = dims[0], dims[1], dims[2]
    ncell = nx * ny * nz
    ci = np.empty((n, 3), np.int64)
    cid = np.empty(n, np.int64)
    for i in range(n):
        for a in range(3):
            c = int(math.floor((points[i, a] - lo[a]) / cell))
            c = min(max(c, 0), dims[a] - 1)
            ci[i, a] = c
        cid[i] = (ci[i, 0] * ny + ci[i, 1]) * nz + ci[i, 2]
    start, members = bucket_by_cell(cid, ncell)     # points of each cell, ascending index,
    xs = np.empty(n)                                # and their coordinates in that order
    ys = np.empty(n)
    zs = np.empty(n)
    for t in range(n):
        xs[t] = points[members[t], 0]
        ys[t] = points[members[t], 1]
        zs[t] = points[members[t], 2]

    r2 = radius * radius if radius >= 0 else -1.0
    far2 = radius * radius              # kNN neighbours within this are taken for FRNN ones
    kk = min(k, n - 1)
    keep = kk + 1
    frnn_ptr = np.zeros(n + 1, np.int64)
    frnn_j = np.empty(max(cap, 1), np.int64)
    nf = 0
    far_ptr = np.zeros(n + 1, np.int64)
    far_j = np.empty(max(kk, 0) * n + 1, np.int64)
    nfar = 0
    tie = np.zeros(n, np.bool_)
    n_knn = 0
    buf_d = np.empty(n)                 # kNN candidates: distance², point, histogram bin
    buf_j = np.empty(n, np.int64)
    buf_b = np.empty(n, np.int64)
    sel = np.empty(n)
    hist = np.zeros(nbins + 1, np.int64)
    top = np.zeros(nbins + 1)           # the largest distance² of each bin
    smax = max(nx, max(ny, nz))
    for i in range(n):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        cx, cy, cz = ci[i, 0], ci[i, 1], ci[i, 2]
        # FRNN: the cells within ``reach`` hold every point within r (a run of
        # consecutive cells per column); all their points are kNN candidates.
        nb = 0
        for gx in range(max(cx - reach, 0), min(cx + reach + 1, nx)):
            for gy in range(max(cy - reach, 0), min(cy + reach + 1, ny)):
                c0 = (gx * ny + gy) * nz
                for t in range(start[c0 + max(cz - reach, 0)], start[c0 + min(cz + reach + 1, nz)]):
                    j = members[t]
                    if j == i:
                        continue
                    dx = px - xs[t]
                    dy = py - ys[t]
                    dz = pz - zs[t]
                    d = dx * dx + dy * dy + dz * dz
                    if nf < cap:
                        frnn_j[nf] = j          # kept when within r
                    nf += d <= r2
                    buf_d[nb] = d
                    buf_j[nb] = j
                    nb += 1
        count = nf - frnn_ptr[i]
        frnn_ptr[i + 1] = nf
        far_ptr[i + 1] = nfar
        if count >= k:
            continue
        n_knn += 1
        if kk < 1:
            continue
        # kNN, for the points with n_i < k: the kk nearest others, gathered
        # shell of cells by shell outward until kk + 1 of them lie nearer than
        # any point outside the shells.  After each shell a histogram of the
        # candidates' distances² finds the bin of the (kk + 1)-th nearest; the
        # farther bins are dropped, and the largest distance² left bounds the
        # cells still worth a look.
        s = reach + 1                   # the next shell to scan
        while True:
            if nb >= keep:
                dmax = 0.0
                for t in range(nb):
                    dmax = max(dmax, buf_d[t])
                scale = nbins / dmax if dmax > 0 else 0.0
                for b in range(nbins + 1):
                    hist[b] = 0
                    top[b] = 0.0
                for t in range(nb):
                    d = buf_d[t]
                    b = min(int(d * scale), nbins - 1)
                    buf_b[t] = b
                    hist[b + 1] += 1
                    top[b] = max(top[b], d)
                for b in range(nbins):
                    hist[b + 1] += hist[b]      # now hist[b]: candidates in the bins below b
                bk = 0
                while hist[bk + 1] < keep:
                    bk += 1
                bound = top[bk]                 # >= the keep-th smallest distance² so far
                m = 0
                for t in range(nb):             # (without branches: kept or not is a coin toss)
                    b = buf_b[t]
                    buf_d[m] = buf_d[t]
                    buf_j[m] = buf_j[t]
                    buf_b[m] = b
                    m += b <= bk
                nb = m
                if s > smax:
                    break
                # every point outside the cube of shells 0..s-1 is at least f away
                f = min(px - (lo[0] + (cx - s + 1) * cell), (lo[0] + (cx + s) * cell) - px)
                f = min(f, min(py - (lo[1] + (cy - s + 1) * cell), (lo[1] + (cy + s) * cell) - py))
                f = min(f, min(pz - (lo[2] + (cz - s + 1) * cell), (lo[2] + (cz + s) * cell) - pz))
                f -= 1e-9 * cell
                if f > 0:
                    f2 = f * f
                    if bound < f2:
                        break
                    near = 0
                    for t in range(nb):
                        near += buf_d[t] < f2
                    if near >= keep:
                        break
            elif s > smax:
                break
            else:
                bound = np.inf
            # shell s: per column (gx, gy) the cells within the bound in z, a run
            # of consecutive cells (all of it on the side of the shell, its top
            # and bottom cells inside); a cell nearer than the bound may hold one
            # of the keep nearest (the 1e-9 and the cell of margin absorb rounding)
            for gx in range(max(cx - s, 0), min(cx + s + 1, nx)):
                ex = max(0.0, max(lo[0] + gx * cell - px, px - (lo[0] + (gx + 1) * cell)))
                if ex * ex * (1.0 - 1e-9) > bound:
                    continue
                for gy in range(max(cy - s, 0), min(cy + s + 1, ny)):
                    ey = max(0.0, max(lo[1] + gy * cell - py, py - (lo[1] + (gy + 1) * cell)))
                    exy = ex * ex + ey * ey
                    if exy * (1.0 - 1e-9) > bound:
                        continue
                    z0 = max(cz - s, 0)
                    z1 = min(cz + s, nz - 1)
                    if bound < np.inf:
                        rz = math.sqrt(max(bound / (1.0 - 1e-9) - exy, 0.0))
                        z0 = max(z0, int(math.floor((pz - rz - lo[2]) / cell)) - 1)
                        z1 = min(z1, int(math.floor((pz + rz - lo[2]) / cell)) + 1)
                    c0 = (gx * ny + gy) * nz
                    side = abs(gx - cx) == s or abs(gy - cy) == s
                    for run in range(2):
                        if side:
                            if run == 1:
                                break
                            a, b = z0, z1
                        else:
                            a = cz - s if run == 0 else cz + s
                            b = a
                            if a < z0 or a > z1:
                                continue
                        for t in range(start[c0 + a], start[c0 + b + 1]):
                            dx = px - xs[t]
                            dy = py - ys[t]
                            dz = pz - zs[t]
                            d = dx * dx + dy * dy + dz * dz
                            buf_d[nb] = d       # kept when within the bound
                            buf_j[nb] = members[t]
                            nb += d <= bound
            s += 1
        if nb < keep:                   # fewer other points than kk + 1: all are neighbours
            for t in range(nb):
                if buf_d[t] > far2:
                    far_j[nfar] = buf_j[t]
                    nfar += 1
            far_ptr[i + 1] = nfar
            continue
        # the kk-th and the keep-th nearest: sort the few candidates of their bins
        b0 = 0
        while hist[b0 + 1] < kk:
            b0 += 1
        m = 0
        for t in range(nb):
            if buf_b[t] >= b0:
                v = buf_d[t]
                q = m - 1
                while q >= 0 and sel[q] > v:
                    sel[q + 1] = sel[q]
                    q -= 1
                sel[q + 1] = v
                m += 1
        kth = sel[kk - 1 - hist[b0]]
        if sel[kk - hist[b0]] <= kth * (1.0 + 1e-12):
            tie[i] = True               # the caller asks the k-d tree
            continue
        for t in range(nb):
            d = buf_d[t]
            far_j[nfar] = buf_j[t]      # kept when among the kk nearest, farther than r
            nfar += (d <= kth) & (d > far2)
        far_ptr[i + 1] = nfar
    # only the filled parts (beyond them the buffers hold whatever was there)
    return True, frnn_ptr, frnn_j[:min(frnn_ptr[n], frnn_j.shape[0])], far_ptr, far_j[:nfar], tie, n_knn


@njit
def _graph_csr(points, frnn_ptr, frnn_j, far_ptr, far_j, tie_i, tie_nn, radius):
    """Symmetric CSR (sorted rows, edge lengths) of the FRNN and far kNN rows, and its components.

    ``tie_i``/``tie_nn``: the points whose kNN rows come from the k-d tree
    (a row may hold the point itself or ``n`` for a missing neighbour; those
    within ``radius`` are FRNN neighbours already and are skipped).  With
    F(c) the far kNN row of c, row c of the matrix is FRNN(c) ∪ F(c) ∪
    {r : c ∈ F(r)}, sorted by a transpose (see below).
    """
    n = points.shape[0]
    r2 = radius * radius
    fptr = np.zeros(n + 1, np.int64)            # F rows: the kernel's, or the k-d tree's for ties
    for i in range(n):
        fptr[i + 1] = far_ptr[i + 1] - far_ptr[i]
    for q in range(tie_i.shape[0]):
        i = tie_i[q]
        for t in range(tie_nn.shape[1]):
            j = tie_nn[q, t]
            if j != i and 0 <= j < n:
                dx = points[i, 0] - points[j, 0]
                dy = points[i, 1] - points[j, 1]
                dz = points[i, 2] - points[j, 2]
                if not dx * dx + dy * dy + dz * dz <= r2:
                    fptr[i + 1] += 1
    for i in range(n):
        fptr[i + 1] += fptr[i]
    fj = np.empty(fptr[n], np.int64)
    for i in range(n):
        o = fptr[i]
        for t in range(far_ptr[i], far_ptr[i + 1]):
            fj[o] = far_j[t]
            o += 1
    for q in range(tie_i.shape[0]):
        i = tie_i[q]
        o = fptr[i]
        for t in range(tie_nn.shape[1]):
            j = tie_nn[q, t]
            if j != i and 0 <= j < n:
                dx = points[i, 0] - points[j, 0]
                dy = points[i, 1] - points[j, 1]
                dz = points[i, 2] - points[j, 2]
                if not dx * dx + dy * dy + dz * dz <= r2:
                    fj[o] = j
                    o += 1
    rptr = np.zeros(n + 1, np.int64)            # R rows, R(c) = {r : c ∈ F(r)}: F transposed
    for t in range(fptr[n]):
        rptr[fj[t] + 1] += 1
    for c in range(n):
        rptr[c + 1] += rptr[c]
    fill = rptr[:-1].copy()
    rj = np.empty(fptr[n], np.int64)
    for r in range(n):
        for t in range(fptr[r], fptr[r + 1]):
            c = fj[t]
            rj[fill[c]] = r
            fill[c] += 1
    # Row c holds FRNN(c) ∪ F(c) ∪ R(c).  The relation is symmetric, so scattering
    # r, for r ascending, into the buckets of FRNN(r), F(r) and R(r) gives every
    # row sorted (a mutual kNN pair comes twice in a row and is written once).
    bptr = np.zeros(n + 1, np.int64)
    for c in range(n):
        bptr[c + 1] = bptr[c] + (frnn_ptr[c + 1] - frnn_ptr[c]) + (fptr[c + 1] - fptr[c]) + (rptr[c + 1] - rptr[c])
    fill = bptr[:-1].copy()
    bucket = np.empty(bptr[n], np.int64)
    for r in range(n):
        for t in range(frnn_ptr[r], frnn_ptr[r + 1]):
            c = frnn_j[t]
            bucket[fill[c]] = r
            fill[c] += 1
        for t in range(fptr[r], fptr[r + 1]):
            c = fj[t]
            bucket[fill[c]] = r
            fill[c] += 1
        for t in range(rptr[r], rptr[r + 1]):
            c = rj[t]
            bucket[fill[c]] = r
            fill[c] += 1
    indptr = np.zeros(n + 1, np.int64)
    indices = np.empty(bptr[n], np.int64)
    length = np.empty(bptr[n])
    m = 0
    for c in range(n):
        prev = -1
        for t in range(bptr[c], bptr[c + 1]):
            j = bucket[t]
            if j == prev:
                continue
            prev = j
            indices[m] = j
            dx = points[c, 0] - points[j, 0]
            dy = points[c, 1] - points[j, 1]
            dz = points[c, 2] - points[j, 2]
            length[m] = math.sqrt(dx * dx + dy * dy + dz * dz)
            m += 1
        indptr[c + 1] = m

    # Connected components (union-find), numbered by their lowest point.
    root = np.empty(n, np.int64)
    for r in range(n):
        root[r] = r
    for r in range(n):
        for t in range(indptr[r], indptr[r + 1]):
            b = indices[t]
            if b < r:
                continue                        # the same edge as (b, r)
            uf_union(root, r, b)
    labels = np.empty(n, np.int32)
    label_of_root = np.empty(n, np.int64)
    for r in range(n):
        label_of_root[r] = -1
    ncomp = 0
    for r in range(n):
        a = r
        while root[a] != a:
            a = root[a]
        if label_of_root[a] < 0:
            label_of_root[a] = ncomp
            ncomp += 1
        labels[r] = label_of_root[a]
    return indptr, indices[:m], m, length[:m], labels, ncomp


def build_graph(points: np.ndarray, radius_m: float = 1.2, k: int = 30) -> Graph:
    """Connect candidate points by FRNN within ``radius_m`` plus kNN where sparse (Algorithm 1).

    A point joins all points within ``radius_m`` (distance ≤ r_p); a point
    with fewer than ``k`` of them also joins its ``k`` nearest others (a
    point whose k-th and (k+1)-th nearest are equidistant takes them from
    ``scipy.spatial.cKDTree``, see the module docstring).  Pure function of
    its inputs; returns the symmetric adjacency (CSR with sorted column
    indices, data = edge lengths), its connected components (numbered by
    their lowest point, as scipy.sparse.csgraph does) and how many points
    needed the kNN pass.  Non-finite coordinates raise
    :class:`~sylva.core.errors.InputError`.
    """
    g = graph_arrays(points, radius_m, k)
    adj = g.adjacency
    n = adj.shape[0]
    # the index dtype scipy would choose (int32 when it can), given directly: no checks, no copy
    idx = np.int32 if max(n, adj.nnz) <= np.iinfo(np.int32).max else np.int64
    matrix = csr_matrix((adj.data, adj.indices.astype(idx), adj.indptr.astype(idx)), shape=(n, n))
    matrix.has_sorted_indices = True
    return g._replace(adjacency=matrix)


def graph_arrays(points: np.ndarray, radius_m: float = 1.2, k: int = 30) -> Graph:
    """:func:`build_graph` with the adjacency as :class:`CSRArrays` (int64 indices) instead of a scipy matrix."""
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    n = len(points)
    if n == 0:
        e = np.zeros(0, dtype=np.int64)
        return Graph(CSRArrays(np.zeros(1, dtype=np.int64), e, np.zeros(0), (0, 0)), 0, np.zeros(0, dtype=np.int32), 0)
    radius = float(radius_m)
    search = (points, radius, int(k), float(_CELLS_PER_RADIUS), float(_CELLS_PER_POINT * n + _CELLS_MIN), _BINS)
    finite, frnn_ptr, frnn_j, far_ptr, far_j, tie, n_knn = _graph_frnn_knn(*search, 32 * n)
    if not finite:
        raise InputError(f"build_graph: {int((~np.isfinite(points).all(axis=1)).sum())} of {n} points are not finite")
    if frnn_ptr[-1] > 32 * n:          # denser than foreseen: once more with room for every neighbour
        finite, frnn_ptr, frnn_j, far_ptr, far_j, tie, n_knn = _graph_frnn_knn(*search, int(frnn_ptr[-1]))
    tie_i = np.flatnonzero(tie)
    if len(tie_i):
        _, nn = cKDTree(points).query(points[tie_i], k=min(int(k) + 1, n))
        nn = np.asarray(nn, dtype=np.int64).reshape(len(tie_i), -1)
    else:
        nn = np.zeros((0, 1), dtype=np.int64)
    indptr, indices, m, length, labels, ncomp = _graph_csr(points, frnn_ptr, frnn_j, far_ptr, far_j, tie_i, nn,
                                                           radius)
    return Graph(CSRArrays(indptr, indices, length, (n, n)), int(ncomp), labels, int(n_knn))
