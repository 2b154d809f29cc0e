"""The normalised cut between neighbouring tops: Hu et al. 2017 §4.1 (Eq. 1).

Pairs of touching regions are cut in two by the Fiedler vector of their normalised Laplacian (LOBPCG from
the current boundary) and the best threshold on it, started from the geodesic partition between the two
tops; :func:`cut_graph` runs the rounds until every pair is settled, and merges the pairs that are one
tree (the crown-reach, dip and plateau rules are Sylva's, not in the paper).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.linalg

from ...jit import njit
from ...progress import CancelCheck, Progress, check, report
from .cleanup import clean_labels, crown_height_m, crown_radius_m
from .graph import VoxelGraph


#: LOBPCG iterations per two-way cut; started from the current boundary, the
#: threshold search only needs the vector's ordering, not full convergence
#: (4 and 8 gave the same detection F1 on the synthetic stands).
FIEDLER_ITERATIONS = 4

#: Pairs whose start boundary already costs less than this (Eq. 1) are left as
#: they are: clearly separate crowns, a cut could only move a few weak edges.
SETTLED_NCUT = 0.05


#: Reach (x the allometric crown radius) of the plateau merge (two tops of nearly one height).
PLATEAU_REACH = 1.3

#: A lower top within this many allometric crown radii of a higher one lies under its crown: a
#: bump of it, whatever its height (step 4 of :mod:`sylva.core.segment.ncut`).
UNDER_CROWN = 0.5

#: The canopy around a top is closed where it covers this share of the ground
#: (:func:`~.graph.canopy_cover`): there two tops of one height are one
#: crown only across a saddle of the graph (step 4 of :mod:`sylva.core.segment.ncut`).
CLOSED_COVER = 0.75

#: Where the canopy around the higher top is closed (:data:`CLOSED_COVER`), the merges judge a
#: crown as at most this wide (m, times ``crown_scale``): Popescu & Wynne's crown width grows with
#: height up to :data:`~sylva.core.tops.MAX_CROWN_WIDTH_M` (12 m at 32 m), but in a closed canopy
#: the neighbours bound a crown, not its height (a tall stand's 30-60 m trees at 400 stems/ha have
#: crowns 5 m wide).  A taller tree there is judged as one :data:`CLOSED_HEIGHT_M` high (26.8 m,
#: whose crown is that wide): its crown reach, and the prominence and levelness of a lower top
#: beside it.  Sylva, not in Hu et al.; see step 4 of the package.
CLOSED_CROWN_WIDTH_M = 9.0
CLOSED_HEIGHT_M = crown_height_m(CLOSED_CROWN_WIDTH_M)


# --------------------------------------------------------------------------- cuts

def _lobpcg1(times, x: np.ndarray, y: np.ndarray, maxiter: int, tol: float = 1e-4) -> np.ndarray:
    """Smallest eigenvector of a symmetric matrix L orthogonal to unit vector ``y``.

    ``times(X)`` returns L X for an (n, k) array.  Knyazev's LOBPCG (2001) with
    block size one and no preconditioner (the normalised Laplacian has a unit
    diagonal, so Jacobi would change nothing): Rayleigh–Ritz on span{x,
    residual, previous step} per iteration.  A lean version of
    :func:`scipy.sparse.linalg.lobpcg`, whose per-call overhead dominates on
    the many small two-tree problems.
    """
    x = x - y * (y @ x)
    x /= np.linalg.norm(x)
    ax = times(x[:, None])[:, 0]
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
        AQ = times(Q)
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


class _Pair(NamedTuple):
    """The union of two regions as a CSR graph of its own (rows in ``nodes`` order)."""

    indptr: np.ndarray
    indices: np.ndarray
    data: np.ndarray
    deg: np.ndarray          # D: the row sums of W


@njit
def _pair_subgraph(indptr, indices, data, nodes, local):
    """``W[nodes][:, nodes]`` (CSR arrays, W's entry order kept) and its row sums, for
    sorted ``nodes``; ``local`` maps a node to its place in ``nodes`` and is -1
    elsewhere (it is left as it was found).  Sylva, not in the paper: the
    bookkeeping of the two-tree sub-problems of Hu et al. §4.1."""
    m = len(nodes)
    for t in range(m):
        local[nodes[t]] = t
    count = 0
    for t in range(m):
        u = nodes[t]
        for e in range(indptr[u], indptr[u + 1]):
            if local[indices[e]] >= 0:
                count += 1
    sub_ptr = np.zeros(m + 1, dtype=np.int64)
    sub_idx = np.empty(count, dtype=np.int64)
    sub_dat = np.empty(count)
    deg = np.zeros(m)
    k = 0
    for t in range(m):
        u = nodes[t]
        s = 0.0
        for e in range(indptr[u], indptr[u + 1]):
            j = local[indices[e]]
            if j >= 0:
                sub_idx[k] = j
                sub_dat[k] = data[e]
                s += data[e]
                k += 1
        deg[t] = s
        sub_ptr[t + 1] = k
    for t in range(m):
        local[nodes[t]] = -1
    return sub_ptr, sub_idx, sub_dat, deg


@njit
def _normalised(indptr, indices, data, inv):
    """The stored values of D^-1/2 W D^-1/2: w_ij / sqrt(d_i) / sqrt(d_j) (``inv`` = 1/sqrt(d))."""
    out = np.empty(len(data))
    for i in range(len(indptr) - 1):
        for e in range(indptr[i], indptr[i + 1]):
            out[e] = data[e] * inv[i] * inv[indices[e]]
    return out


@njit
def _laplacian_times(indptr, indices, mdata, X):
    """(I − M) X for M in CSR with sorted column indices and no diagonal entries
    (the normalised Laplacian times a block of vectors).  Each row sums its
    terms in column order, the unit diagonal in its place, exactly as
    scipy's CSR product of the assembled matrix I − M does."""
    n, k = X.shape
    Y = np.zeros((n, k))
    for i in range(n):
        for c in range(k):
            s = 0.0
            diagonal = False
            for e in range(indptr[i], indptr[i + 1]):
                j = indices[e]
                if not diagonal and j > i:
                    s += X[i, c]
                    diagonal = True
                s += -mdata[e] * X[j, c]
            if not diagonal:
                s += X[i, c]
            Y[i, c] = s
    return Y


def _fiedler(pair: _Pair, start: np.ndarray) -> np.ndarray:
    """Second-smallest generalised eigenvector x of (D - W) x = λ D x (Hu et al. §4.1, after Shi & Malik).

    Computed as the second-smallest eigenvector u of the normalised Laplacian
    L = I - D^-1/2 W D^-1/2 (the same eigenproblem, x = D^-1/2 u; the smallest
    is D^1/2 1) by LOBPCG (:func:`_lobpcg1`, ``FIEDLER_ITERATIONS``) started
    from ``start``; dense LAPACK for tiny graphs.  L is never assembled: its
    products are :func:`_laplacian_times` of W's values scaled in place.
    """
    deg = pair.deg
    n = len(deg)
    sq = np.sqrt(deg)
    inv = 1.0 / sq
    mdata = _normalised(pair.indptr, pair.indices, pair.data, inv)
    if n > 60:
        u = _lobpcg1(lambda X: _laplacian_times(pair.indptr, pair.indices, mdata, np.ascontiguousarray(X)),
                     start * sq, sq / np.linalg.norm(sq), FIEDLER_ITERATIONS)
    else:
        M = np.zeros((n, n))
        M[np.repeat(np.arange(n), np.diff(pair.indptr)), pair.indices] = mdata
        _, vecs = scipy.linalg.eigh(M, subset_by_index=[n - 2, n - 2], check_finite=False)
        u = vecs[:, 0]
    return u / sq


@njit
def _split_search(indptr, indices, data, deg, x, a, b, total):
    """The kernel of :func:`_best_split`: (rank of every node, best t, its NCut; t = -1 when
    the Fiedler vector ties ``a`` and ``b``)."""
    n = len(x)
    xs = -x if x[a] > x[b] else x.copy()
    order = np.argsort(xs, kind="mergesort")
    rank = np.empty(n, dtype=np.int64)
    for t in range(n):
        rank[order[t]] = t
    # cut(t) with A = the first t nodes (t = 1..n-1): the edges with lo < t <= hi
    add = np.zeros(n + 1)
    sub = np.zeros(n + 1)
    for i in range(n):
        for e in range(indptr[i], indptr[i + 1]):
            j = indices[e]
            if i < j:
                r1, r2 = rank[i], rank[j]
                add[min(r1, r2) + 1] += data[e]
                sub[max(r1, r2) + 1] += data[e]
    t_lo, t_hi = rank[a] + 1, rank[b]
    if t_hi < t_lo:
        return rank, -1, np.inf
    cut = 0.0       # running sums in numpy's cumsum order
    assoc = 0.0
    best, best_ncut = -1, np.inf
    for t in range(n - 1):
        cut += add[t + 1] - sub[t + 1]
        assoc += deg[order[t]]
        if t_lo - 1 <= t < t_hi:
            ncut = cut / assoc + cut / max(total - assoc, 1e-300)
            if best < 0 or ncut < best_ncut:
                best, best_ncut = t, ncut
    return rank, best, best_ncut


def _best_split(pair: _Pair, x: np.ndarray, a: int, b: int):
    """Shi & Malik's threshold search on the sorted Fiedler vector: the split with
    the smallest NCut (Eq. 1) that puts node ``a`` in A and node ``b`` in B.

    Returns (boolean mask of A, NCut of that split)."""
    rank, best, ncut = _split_search(pair.indptr, pair.indices, pair.data, pair.deg, x, a, b,
                                     float(pair.deg.sum()))
    if best < 0:  # pragma: no cover - ties in x
        return rank <= rank[a], float("inf")
    return rank < best + 1, float(ncut)


def _geodesic_partition(graph: VoxelGraph, top_voxel: np.ndarray, climb: float) -> np.ndarray:
    """Index of the nearest top of every voxel along the graph (-1: unreachable).

    Paths start at the tops; a step costs the Eq. 2 dissimilarity -log w_ij
    plus ``climb`` times the height it gains, so a region runs down its own
    crown and stops at the crease where the neighbour's crown rises again."""
    W = graph.W
    return _nearest_source(W.indptr, W.indices, W.data, np.ascontiguousarray(graph.xyz[:, 2]),
                           float(climb), np.asarray(top_voxel, dtype=np.int64))


@njit
def _nearest_source(indptr, indices, w, z, climb, sources):
    """Multi-source Dijkstra over a CSR affinity graph: index into ``sources``
    of the nearest source of every node (-1: unreachable).

    The step i -> j costs -log w_ij + 1e-9 + ``climb`` x max(z_j - z_i, 0).

    An indexed binary heap with decrease-key (numba, O(n) memory); scipy's
    ``dijkstra(min_only=True)`` gives the same partition but its Fibonacci
    heap is twice as slow on graphs of millions of voxels.  The heap keeps
    each entry's distance beside its node (``key``), so sifting reads the
    heap's own contiguous memory instead of ``dist`` at random voxels (the
    same comparisons, so the same partition, but a tile of millions of
    voxels no longer waits on cache misses).  A node reached by two sources
    at exactly the same cost keeps the first; a voxel holding two sources
    keeps the later one."""
    n = len(indptr) - 1
    dist = np.full(n, np.inf)
    owner = np.full(n, -1, dtype=np.int64)
    heap = np.empty(n, dtype=np.int64)      # nodes, a binary heap on their distance
    key = np.empty(n)                       # key[i] = dist[heap[i]]
    pos = np.full(n, -1, dtype=np.int64)    # place in heap; -1 never queued, -2 settled
    size = 0
    for k in range(len(sources)):
        s = sources[k]
        owner[s] = k
        if pos[s] == -1:
            dist[s] = 0.0
            heap[size] = s
            key[size] = 0.0
            pos[s] = size
            size += 1
    while size:
        u = heap[0]
        pos[u] = -2
        size -= 1
        if size:                             # last node to the root, sift down
            x = heap[size]
            dx = key[size]
            i = 0
            while True:
                c = 2 * i + 1
                if c >= size:
                    break
                if c + 1 < size and key[c + 1] < key[c]:
                    c += 1
                if key[c] < dx:
                    heap[i] = heap[c]
                    key[i] = key[c]
                    pos[heap[i]] = i
                    i = c
                else:
                    break
            heap[i] = x
            key[i] = dx
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
                    if key[p] > nd:
                        heap[i] = heap[p]
                        key[i] = key[p]
                        pos[heap[i]] = i
                        i = p
                    else:
                        break
                heap[i] = v
                key[i] = nd
                pos[v] = i
    return owner


def _pair_ncut(graph: VoxelGraph, region: np.ndarray, k: int):
    """(pairs, ncut, saddle): every pair (p, q), p < q, of the ``k`` regions an edge joins (ascending),
    the NCut (Eq. 1) of its start boundary and its saddle, in one pass over the edges.

    For regions p, q: cut = w(p, q); the association of p within the union is
    2 w(p, p) + w(p, q) (every internal edge counts from both ends)."""
    inner, key, wb, zb = _region_edges(graph.edges[:, 0], graph.edges[:, 1], graph.weights, region,
                                       np.ascontiguousarray(graph.xyz[:, 2]), k)
    ukey, inv = np.unique(key, return_inverse=True)
    pairs = np.column_stack([ukey // k, ukey % k])
    cut = np.bincount(inv, weights=wb, minlength=len(ukey))
    vol_p = 2.0 * inner[pairs[:, 0]] + cut
    vol_q = 2.0 * inner[pairs[:, 1]] + cut
    ncut = cut / np.maximum(vol_p, 1e-300) + cut / np.maximum(vol_q, 1e-300)
    # saddle: the highest boundary edge (the lower of its two voxel heights)
    return pairs, ncut, _group_max(inv, zb, len(ukey))


@njit
def _region_edges(a, b, w, region, z, k):
    """One pass over the edges (a, b, w) for :func:`_pair_ncut`: the weight inside each
    region (summed in edge order), and for the edges between two regions p < q the
    key p·k + q, the weight and the lower end's height (in edge order)."""
    inner = np.zeros(k)
    n = 0
    for e in range(len(a)):
        ra, rb = region[a[e]], region[b[e]]
        if ra >= 0 and rb >= 0:
            if ra == rb:
                inner[ra] += w[e]
            else:
                n += 1
    key = np.empty(n, dtype=np.int64)
    wb = np.empty(n)
    zb = np.empty(n)
    t = 0
    for e in range(len(a)):
        ra, rb = region[a[e]], region[b[e]]
        if ra >= 0 and rb >= 0 and ra != rb:
            key[t] = min(ra, rb) * k + max(ra, rb)
            wb[t] = w[e]
            zb[t] = min(z[a[e]], z[b[e]])
            t += 1
    return inner, key, wb, zb


@njit
def _group_max(group, values, n):
    """Per group 0..n-1 the largest of its ``values`` (-inf when empty); ``np.maximum.at`` without its overhead."""
    out = np.full(n, -np.inf)
    for e in range(len(group)):
        if values[e] > out[group[e]]:
            out[group[e]] = values[e]
    return out


def unjoined_plateaus(xy: np.ndarray, height: np.ndarray, touching: np.ndarray, plateau: float,
                      cover: np.ndarray, steep: np.ndarray, scale: float = 1.0):
    """(higher, lower) top indices of the flat crowns the graph does not join (step 4).

    Pairs of tops whose regions do not touch (``touching``: the (p, q), p < q,
    of the regions that do), whose heights differ by less than ``plateau`` x
    the higher, the lower within :data:`PLATEAU_REACH` allometric crown radii
    of the higher (:func:`crown_radius_m` times ``scale``), both rounded (not ``steep``), the
    canopy around the higher not closed (``cover`` below :data:`CLOSED_COVER`);
    sorted.  With no saddle to judge the pair by, the higher crown is judged as
    one no wider than :data:`CLOSED_CROWN_WIDTH_M` (a tree no taller than
    :data:`CLOSED_HEIGHT_M`): Popescu & Wynne's extrapolated 12 m crown of a
    45 m tree joined the tops of tall neighbours 4-8 m apart (tall medium stand
    at 2 points/m2: 10 of the 15 pairs it joined were two trees).  Sylva, not
    in Hu et al."""
    k = len(height)
    if k < 2:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    from scipy.spatial import cKDTree

    reach = PLATEAU_REACH * crown_radius_m(np.minimum(height, CLOSED_HEIGHT_M), scale)
    near = cKDTree(xy).query_pairs(float(reach.max()), output_type="ndarray").astype(np.int64)
    p, q = near.min(axis=1), near.max(axis=1)
    if len(touching):
        keep = ~np.isin(p * k + q, touching[:, 0].astype(np.int64) * k + touching[:, 1])
        p, q = p[keep], q[keep]
    hi = np.where(height[p] >= height[q], p, q)          # the order of cut_graph: ties to the first top
    lo = p + q - hi
    ok = ((height[hi] - height[lo]) < plateau * height[hi]) & ~steep[hi] & ~steep[lo] \
        & (cover[hi] < CLOSED_COVER) & (np.hypot(*(xy[hi] - xy[lo]).T) < reach[hi])
    order = np.lexsort((hi[ok], lo[ok]))
    return hi[ok][order], lo[ok][order]


def _find(parent: np.ndarray, i: int) -> int:
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


def cut_graph(graph: VoxelGraph, top_voxel: np.ndarray, top_id: np.ndarray,
              top_height: np.ndarray, params: "NormalizedCut", progress: Progress,
              cancelled: CancelCheck, cover: np.ndarray = None, steep: np.ndarray = None) -> np.ndarray:
    """Tree id of every voxel: geodesic start, pairwise normalised cuts, merges, clean-up.

    1. Every voxel starts with its nearest top along the graph.
    2. For every pair of touching regions, the two-way normalised cut of their
       union (Fiedler vector + Shi–Malik threshold search, the top of each on
       its own side) proposes a new boundary; its NCut value (Eq. 1) says how
       separate the two parts are.
    3. Pairs whose start boundary costs less than ``SETTLED_NCUT`` are left
       as they are (no eigenproblem).
    4. Pairs whose best cut (Fiedler split or start boundary) costs more than
       ``always_merge_ncut``, or more than ``merge_ncut`` with a dip to the
       saddle below ``merge_dip`` x the lower top (and the lower top at least
       ``merge_height_ratio`` x the higher, or no summit), are one tree with two local
       maxima: the lower top is merged into the higher one (which keeps its
       id); a lower top with several such neighbours joins only the one across
       the highest saddle.  The other
       proposals move voxels across the boundary (the lowest-NCut proposal
       wins when a voxel gets several).
    """
    region = _geodesic_partition(graph, top_voxel, params.climb)
    k = len(top_voxel)
    pairs, ncut_start, saddle = _pair_ncut(graph, region, k)
    parent = np.arange(k)
    best_ncut = np.full(graph.n, np.inf)
    proposal = region.copy()
    partner = np.full(k, -1, dtype=np.int64)    # the top each lower top merges into
    partner_dip = np.full(k, np.inf)
    if len(pairs):
        order = np.argsort(region, kind="stable")
        starts = np.searchsorted(region[order], np.arange(-1, k + 1))
        W = graph.W
        local = np.full(graph.n, -1, dtype=np.int64)
        step = max(1, len(pairs) // 100)
        for i, (p, q) in enumerate(pairs):
            check(cancelled)
            if i % step == 0:
                report(progress, i / len(pairs), f"normalised cuts: {i}/{len(pairs)} tree pairs")
            ncut_now = ncut_start[i]
            hi, lo = (p, q) if (top_height[p], -p) >= (top_height[q], -q) else (q, p)
            low = top_height[lo]
            dip = (low - saddle[i]) / low
            gap = np.hypot(*(graph.xyz[top_voxel[p], :2] - graph.xyz[top_voxel[q], :2]))
            judged = top_height[hi]                 # the height the higher crown is judged by
            if cover is not None and cover[hi] >= CLOSED_COVER:
                judged = min(judged, CLOSED_HEIGHT_M)   # a closed canopy bounds the crowns
            reach = crown_radius_m(judged, params.crown_scale)
            bump = (low - saddle[i]) / min(low, judged)   # the lower top's prominence, relative
            factor = params.merge_reach
            if cover is not None and cover[hi] < params.open_cover and not steep[lo]:
                factor = params.open_reach          # a rounded bump of an open-grown crown
            level = (top_height[hi] - low) / judged < params.merge_plateau
            # a summit markedly lower than its neighbour's is the apex of a tree of a lower crown class
            # (see step 4); a lower "top" rising nowhere above the saddle, or under the higher crown, is
            # a bump of that crown's flank
            apart = (low < params.merge_height_ratio * top_height[hi] and dip > 0
                     and gap >= UNDER_CROWN * reach)
            if not apart and ((bump < params.merge_prominence and gap < factor * reach)
                    or (level and bump < 0.5 * params.merge_prominence and gap < PLATEAU_REACH * reach)):
                # a bump inside the crown the higher top's height implies (see step 4)
                if (dip, hi) < (partner_dip[lo], partner[lo]):
                    partner[lo], partner_dip[lo] = hi, dip
                continue
            if ncut_now < SETTLED_NCUT:
                continue   # the start boundary is already a near-perfect cut
            nodes = np.sort(np.concatenate([order[starts[p + 1]:starts[p + 2]],
                                            order[starts[q + 1]:starts[q + 2]]]))
            pair = _Pair(*_pair_subgraph(W.indptr, W.indices, W.data, nodes, local))
            if (pair.deg <= 0).any():
                continue
            ia = int(np.searchsorted(nodes, top_voxel[p]))
            ib = int(np.searchsorted(nodes, top_voxel[q]))
            start = np.where(region[nodes] == p, -1.0, 1.0)
            x = _fiedler(pair, start)
            side_a, ncut = _best_split(pair, x, ia, ib)
            best = min(ncut, ncut_now)   # the start boundary is a candidate cut too
            if best > params.always_merge_ncut or (not apart and best > params.merge_ncut
                                                   and dip < params.merge_dip):
                if (dip, hi) < (partner_dip[lo], partner[lo]):   # the highest saddle wins
                    partner[lo], partner_dip[lo] = hi, dip
                continue
            if not ncut < ncut_now:
                continue   # the start boundary is already the better cut (Eq. 1)
            new = np.where(side_a, p, q)
            moved = (new != region[nodes]) & (ncut < best_ncut[nodes])
            proposal[nodes[moved]] = new[moved]
            best_ncut[nodes[moved]] = ncut
    if cover is not None and params.merge_plateau > 0:
        # flat crowns whose tops the graph does not join: as deep as a saddle can be (dip 1), so any
        # merge across a saddle comes first
        for hi, lo in zip(*unjoined_plateaus(graph.xyz[top_voxel, :2], top_height, pairs,
                                             params.merge_plateau, cover, steep, params.crown_scale)):
            if (1.0, hi) < (partner_dip[lo], partner[lo]):
                partner[lo], partner_dip[lo] = hi, 1.0
    for lo in np.flatnonzero(partner >= 0):
        rp, rq = _find(parent, int(lo)), _find(parent, int(partner[lo]))
        if rp != rq:
            hi, low = (rp, rq) if (top_height[rp], -rp) >= (top_height[rq], -rq) else (rq, rp)
            parent[low] = hi
    roots = np.array([_find(parent, i) for i in range(k)], dtype=np.int64)
    vlabel = np.where(proposal >= 0, top_id[roots[np.maximum(proposal, 0)]], 0)
    alive = roots == np.arange(k)
    return clean_labels(graph, vlabel, top_voxel[alive], top_id[alive], top_height[alive],
                        0.0, params.attach_m, seeds=(top_voxel, top_id[roots]))
