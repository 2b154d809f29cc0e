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
hold a nearer point.  Where the k-th and the (k+1)-th nearest lie at exactly
the same distance (common next to the evenly spaced trunk points of §4.2)
which one is "the k nearest" is the search's own choice; for those points
Sylva asks ``scipy.spatial.cKDTree``, as Algorithm 1 with a k-d tree did
before, so the edges are exactly those of the k-d tree implementation
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

#: Most grid cells the kernel allocates per point (plus a constant); beyond it the cells grow.
_CELLS_PER_POINT = 8
_CELLS_PER_RADIUS = 1          # grid cell edge = r_p
_CELLS_MIN = 1 << 17


class Graph(NamedTuple):
    """Result of :func:`build_graph`."""

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


@njit
def _graph_frnn_knn(points, radius, k, cell, lo, dims, reach, cap):
    """Algorithm 1 on a grid of cubic cells of edge ``cell`` (>= radius); see :func:`build_graph`.

    Returns the FRNN pairs i < j (their number; when it exceeds ``cap`` only
    the count is right and the caller runs again), n_i, the kNN rows (-1
    padded) of the points with n_i < k, which of them end in a tie, and
    their count.
    """
    n = points.shape[0]
    nx, ny, nz = dims[0], dims[1], dims[2]
    ncell = nx * ny * nz
    ci = np.empty((n, 3), np.int64)
    cid = np.empty(n, np.int64)
    start = np.zeros(ncell + 1, np.int64)
    for i in range(n):
        for a in range(3):
            c = int(math.floor((points[i, a] - lo[a]) / cell))
            c = min(max(c, 0), dims[a] - 1)
            ci[i, a] = c
        cid[i] = (ci[i, 0] * ny + ci[i, 1]) * nz + ci[i, 2]
        start[cid[i] + 1] += 1
    for c in range(ncell):
        start[c + 1] += start[c]
    fill = np.empty(ncell, np.int64)
    for c in range(ncell):
        fill[c] = start[c]
    members = np.empty(n, np.int64)
    for i in range(n):                       # points of each cell, ascending index
        members[fill[cid[i]]] = i
        fill[cid[i]] += 1

    r2 = radius * radius if radius >= 0 else -1.0
    # One pass per point p_i.  FRNN: the cells within ``reach`` hold every point
    # within r; n_i counts them and the pairs i < j are stored (at most ``cap``).
    # kNN, for the points with n_i < k: the kk nearest others, gathered shell of
    # cells by shell outward until kk + 1 of them lie nearer than any point
    # outside the shells; after each shell a quickselect keeps the kk + 1
    # nearest so far, and farther cells are skipped.  When the kk-th and the
    # (kk+1)-th lie at the same distance the choice is a tie (``tie``).
    src = np.empty(max(cap, 1), np.int64)
    dst = np.empty(max(cap, 1), np.int64)
    ne = 0
    count = np.zeros(n, np.int64)
    kk = min(k, n - 1)
    keep = kk + 1
    n_knn = 0
    buf_d = np.empty(n)
    buf_j = np.empty(n, np.int64)
    knn = np.empty((n, max(kk, 1)), np.int64)
    for i in range(n):
        for t in range(knn.shape[1]):
            knn[i, t] = -1
    tie = np.zeros(n, np.bool_)
    smax = max(nx, max(ny, nz))
    for i in range(n):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        cx, cy, cz = ci[i, 0], ci[i, 1], ci[i, 2]
        nb = 0
        for gx in range(max(cx - reach, 0), min(cx + reach + 1, nx)):
            for gy in range(max(cy - reach, 0), min(cy + reach + 1, ny)):
                for gz in range(max(cz - reach, 0), min(cz + reach + 1, nz)):
                    c = (gx * ny + gy) * nz + gz
                    for t in range(start[c], start[c + 1]):
                        j = members[t]
                        if j == i:
                            continue
                        dx = px - points[j, 0]
                        dy = py - points[j, 1]
                        dz = pz - points[j, 2]
                        d = dx * dx + dy * dy + dz * dz
                        if d <= r2:
                            count[i] += 1
                            if j > i:
                                if ne < cap:
                                    src[ne] = i
                                    dst[ne] = j
                                ne += 1
                        buf_d[nb] = d
                        buf_j[nb] = j
                        nb += 1
        if count[i] >= k:
            continue
        n_knn += 1
        if kk < 1:
            continue
        s = reach + 1                   # the next shell to scan
        bound = np.inf                  # the keep-th smallest distance² found so far
        while True:
            if nb >= keep:
                # quickselect: the kk nearest to buf[:kk], the keep-th (= kk + 1-th) at buf[kk]
                left = 0
                right = nb - 1
                while right > left:
                    pivot = buf_d[(left + right) // 2]
                    a = left
                    b = right
                    while a <= b:
                        while buf_d[a] < pivot:
                            a += 1
                        while buf_d[b] > pivot:
                            b -= 1
                        if a <= b:
                            td = buf_d[a]
                            buf_d[a] = buf_d[b]
                            buf_d[b] = td
                            tj = buf_j[a]
                            buf_j[a] = buf_j[b]
                            buf_j[b] = tj
                            a += 1
                            b -= 1
                    if kk <= b:
                        right = b
                    elif kk >= a:
                        left = a
                    else:
                        break
                bound = buf_d[kk]
                m = kk + 1
                for t in range(kk + 1, nb):     # keep only what can still count (ties with the bound)
                    if buf_d[t] <= bound:
                        buf_d[m] = buf_d[t]
                        buf_j[m] = buf_j[t]
                        m += 1
                nb = m
                if s > smax:
                    break
                # every point outside the cube of shells 0..s-1 is at least f away
                f = min(px - (lo[0] + (cx - s + 1) * cell), (lo[0] + (cx + s) * cell) - px)
                f = min(f, min(py - (lo[1] + (cy - s + 1) * cell), (lo[1] + (cy + s) * cell) - py))
                f = min(f, min(pz - (lo[2] + (cz - s + 1) * cell), (lo[2] + (cz + s) * cell) - pz))
                f -= 1e-9 * cell
                if f > 0 and f * f > bound:
                    break
            elif s > smax:
                break
            for gx in range(max(cx - s, 0), min(cx + s + 1, nx)):
                ex = max(0.0, max(lo[0] + gx * cell - px, px - (lo[0] + (gx + 1) * cell)))
                for gy in range(max(cy - s, 0), min(cy + s + 1, ny)):
                    ey = max(0.0, max(lo[1] + gy * cell - py, py - (lo[1] + (gy + 1) * cell)))
                    shell_xy = abs(gx - cx) == s or abs(gy - cy) == s
                    for gz in range(max(cz - s, 0), min(cz + s + 1, nz)):
                        if not shell_xy and abs(gz - cz) != s:
                            continue
                        c = (gx * ny + gy) * nz + gz
                        if start[c] == start[c + 1]:
                            continue
                        ez = max(0.0, max(lo[2] + gz * cell - pz, pz - (lo[2] + (gz + 1) * cell)))
                        if (ex * ex + ey * ey + ez * ez) * (1.0 - 1e-9) > bound:
                            continue            # no point of this cell can be among the keep nearest
                        for t in range(start[c], start[c + 1]):
                            j = members[t]
                            dx = px - points[j, 0]
                            dy = py - points[j, 1]
                            dz = pz - points[j, 2]
                            d = dx * dx + dy * dy + dz * dz
                            if d <= bound:
                                buf_d[nb] = d
                                buf_j[nb] = j
                                nb += 1
            s += 1
        if nb < keep:                   # fewer other points than kk + 1: all are neighbours
            for t in range(nb):
                knn[i, t] = buf_j[t]
            continue
        kth = buf_d[0]
        for t in range(1, kk):
            if buf_d[t] > kth:
                kth = buf_d[t]
        if buf_d[kk] <= kth * (1.0 + 1e-12):
            tie[i] = True
        for t in range(kk):
            knn[i, t] = buf_j[t]
    return src, dst, ne, count, knn, tie, n_knn


@njit
def _graph_csr(points, src, dst, ne_pairs, knn, radius):
    """Symmetric CSR of the FRNN pairs (src, dst)[:ne_pairs] plus the kNN rows, and its components.

    kNN neighbours within ``radius`` are FRNN pairs already and are skipped.
    """
    n = points.shape[0]
    r2 = radius * radius
    width = knn.shape[1]
    far = np.zeros(n * width, np.bool_)
    ne = 2 * ne_pairs
    for i in range(n):
        for t in range(knn.shape[1]):
            j = knn[i, t]
            if j >= 0:
                dx = points[i, 0] - points[j, 0]
                dy = points[i, 1] - points[j, 1]
                dz = points[i, 2] - points[j, 2]
                if not dx * dx + dy * dy + dz * dz <= r2:
                    far[i * width + t] = True
                    ne += 2
    s2 = np.empty(ne, np.int64)
    d2 = np.empty(ne, np.int64)
    m0 = 0
    for e in range(ne_pairs):
        s2[m0] = src[e]
        d2[m0] = dst[e]
        s2[m0 + 1] = dst[e]
        d2[m0 + 1] = src[e]
        m0 += 2
    for i in range(n):
        for t in range(knn.shape[1]):
            if far[i * width + t]:
                j = knn[i, t]
                s2[m0] = i
                d2[m0] = j
                s2[m0 + 1] = j
                d2[m0 + 1] = i
                m0 += 2
    src = s2
    dst = d2

    # Symmetric CSR: counting sort by column, then (stably) by row; drop repeats.
    cnt = np.zeros(n + 1, np.int64)
    for e in range(ne):
        cnt[dst[e] + 1] += 1
    for a in range(n):
        cnt[a + 1] += cnt[a]
    by_col = np.empty(ne, np.int64)
    for e in range(ne):
        by_col[cnt[dst[e]]] = e
        cnt[dst[e]] += 1
    cnt[:] = 0
    for e in range(ne):
        cnt[src[e] + 1] += 1
    for a in range(n):
        cnt[a + 1] += cnt[a]
    order = np.empty(ne, np.int64)
    for t in range(ne):
        e = by_col[t]
        order[cnt[src[e]]] = e
        cnt[src[e]] += 1
    indptr = np.zeros(n + 1, np.int64)
    indices = np.empty(ne, np.int64)
    m = 0
    prev_r = -1
    prev_c = -1
    for t in range(ne):
        e = order[t]
        r = src[e]
        c = dst[e]
        if r == prev_r and c == prev_c:
            continue
        indices[m] = c
        indptr[r + 1] += 1
        m += 1
        prev_r = r
        prev_c = c
    for a in range(n):
        indptr[a + 1] += indptr[a]
    length = np.empty(m)
    for r in range(n):
        for t in range(indptr[r], indptr[r + 1]):
            c = indices[t]
            dx = points[r, 0] - points[c, 0]
            dy = points[r, 1] - points[c, 1]
            dz = points[r, 2] - points[c, 2]
            length[t] = math.sqrt(dx * dx + dy * dy + dz * dz)

    # Connected components (union-find), numbered by their lowest point.
    root = np.empty(n, np.int64)
    for r in range(n):
        root[r] = r
    for r in range(n):
        for t in range(indptr[r], indptr[r + 1]):
            a = r
            while root[a] != a:
                root[a] = root[root[a]]
                a = root[a]
            b = indices[t]
            while root[b] != b:
                root[b] = root[root[b]]
                b = root[b]
            if a != b:
                if a < b:
                    root[b] = a
                else:
                    root[a] = b
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
    return indptr, indices, m, length, labels, ncomp


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
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    n = len(points)
    if n == 0:
        return Graph(csr_matrix((0, 0)), 0, np.zeros(0, dtype=np.int32), 0)
    if not np.isfinite(points).all():
        raise InputError(f"build_graph: {int((~np.isfinite(points).all(axis=1)).sum())} of {n} points are not finite")
    radius = float(radius_m)
    lo = points.min(axis=0)
    extent = points.max(axis=0) - lo
    # cells a hair wider than r_p / _CELLS_PER_RADIUS: a pair at exactly r_p can then
    # never be two cells apart through the rounding of floor((x - lo) / cell)
    cell = radius * (1.0 + 1e-7) / _CELLS_PER_RADIUS if radius > 0 else 1.0
    limit = _CELLS_PER_POINT * n + _CELLS_MIN
    while True:
        dims = np.floor(extent / cell).astype(np.int64) + 1
        if float(np.prod(dims.astype(np.float64))) <= limit:
            break
        cell *= 2.0
    reach = max(1, int(np.ceil(radius / cell))) if radius > 0 else 1
    cap = 24 * n
    src, dst, ne, count, knn, tie, n_knn = _graph_frnn_knn(points, radius, int(k), cell, lo, dims, reach, cap)
    if ne > cap:                       # denser than foreseen: once more with room for every pair
        src, dst, ne, count, knn, tie, n_knn = _graph_frnn_knn(points, radius, int(k), cell, lo, dims, reach, ne)
    if tie.any():
        kk = min(int(k) + 1, n)
        need = np.flatnonzero(tie)
        _, nn = cKDTree(points).query(points[need], k=kk)
        nn = np.asarray(nn).reshape(len(need), kk)
        rows = np.full((len(need), knn.shape[1] + 1), -1, dtype=np.int64)
        for r, (i, row) in enumerate(zip(need, nn)):
            row = row[(row != i) & (row < n)]
            rows[r, :len(row)] = row
        if rows.shape[1] > knn.shape[1]:
            knn = np.concatenate([knn, np.full((n, 1), -1, dtype=np.int64)], axis=1)
        knn[need] = rows
    indptr, indices, m, length, labels, ncomp = _graph_csr(points, src, dst, ne, knn, radius)
    adj = csr_matrix((length, indices[:m].copy(), indptr), shape=(n, n))
    adj.has_sorted_indices = True
    return Graph(adj, int(ncomp), labels, int(n_knn))
