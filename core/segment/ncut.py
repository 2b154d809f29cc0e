"""Normalised-cut tree segmentation on a voxel graph (Hu et al. 2017, §4.1).

Hu, Li, Zhang, Xie, Wang, Guo, Xiao, Su (2017), "Efficient tree modeling from
airborne LiDAR point clouds", Computers & Graphics 67, §4.1 and §6.1.

Steps
-----
1. **Voxels.** Points at least ``min_height_m`` above ground are binned into
   cubes of pitch ``voxel_m`` (the paper's d_s; 0.7 m for 36 k points, 0.9 m
   for 3.7 M points, §6.1) in the local metric frame, z = height above ground
   (so huge UTM coordinates and sloping terrain do not matter).  A voxel's
   features are the mean local (x, y, height), the mean intensity and the
   mean RGB colour when the cloud has them.
2. **Graph (Eq. 2).** The paper writes ``w_ij = e^{-H} e^{-V} e^{-I} e^{-C}``
   without scales; we use

       w_ij = exp(-H/σ_h) · exp(-V/σ_v) · exp(-I/σ_i) · exp(-C/σ_c)

   with H, V the horizontal and vertical distances of the voxel means
   (metres), I the absolute difference of mean intensities divided by the
   tile's intensity inter-quartile range, and C the Euclidean distance of
   mean colours scaled to [0, 1].  The exponent stays linear in the distance
   as Eq. 2 writes it (not squared as in Shi & Malik's Gaussian kernel); the
   σ's carry the units the paper leaves implicit (``sigma_h_m``,
   ``sigma_v_m``, ``sigma_intensity``, ``sigma_colour``).  w_ij = 0 beyond
   r^xz = ``radius_m``; to keep the graph sparse the cylinder of Eq. 2 is
   cut to the inscribed ellipsoid of half height ``height_m``
   (``cKDTree.query_pairs`` on z-scaled coordinates); steep conifer apices
   stay connected, far-apart layers are not joined.  No dense
   matrix is ever built.
3. **Start.** Every voxel gets the tree top nearest to it along the graph
   (multi-source Dijkstra); a step costs the Eq. 2 dissimilarity -log w_ij
   plus ``climb`` x the height it gains, so a region runs down its own crown
   and stops at the crease where the neighbouring crown rises again.  Voxels
   of components without a top are not reached (isolated noise).
4. **Cuts (Eq. 1).** The problem is split into independent two-tree
   sub-problems: for every pair of touching regions, the generalised
   eigenproblem (D − W) x = λ D x of their union (normalised Laplacian,
   LOBPCG from the current boundary, ``scipy.linalg.eigh`` for tiny
   problems) gives the Fiedler vector, and Shi & Malik's threshold search
   finds the split with the smallest NCut(A, B) that keeps each top on its
   own side.  The new boundary replaces the old one only if its NCut is
   lower.  A pair whose best cut still costs more than ``merge_ncut`` is one
   tree with two local maxima and is merged (the higher top keeps its id) —
   this is how the cut, not the top detector, decides the number of trees
   (Hu §4.1: no root point is needed per tree).  Each sub-problem holds two
   crowns, so time and memory grow linearly with the tile.
5. **Clean-up and points.** Nothing of a tree lies above its top; voxels cut
   off from their top go to the neighbour they are most strongly joined to;
   crown pieces a sparse scan left unconnected join the nearest tree within
   ``attach_m``.  Points take their voxel's label; points below
   ``min_height_m`` take the label of the crown right above them (stems),
   see :mod:`sylva.core.segment`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components, dijkstra
from scipy.spatial import cKDTree

from ..cloud import PointCloud
from ..progress import CancelCheck, Progress, check, report, scaled
from . import column_keys, ground_mask, label_columns_below, resolve_tops

__all__ = ["NormalizedCut", "VoxelGraph", "voxel_graph"]

#: LOBPCG iterations per two-way cut; started from the current boundary, the
#: threshold search only needs the vector's ordering, not full convergence.
FIEDLER_ITERATIONS = 8

#: Rounds of attaching unconnected crown pieces (each reaches attach_m farther).
ATTACH_ROUNDS = 5

#: A point higher than its tree's top by more than this is not that tree's.
TOP_TOLERANCE_M = 0.02


@dataclass(frozen=True)
class NormalizedCut:
    """Hu et al. (2017) §4.1 normalised cut on a voxel graph, guided by tree tops.

    ``voxel_m``: voxel pitch d_s (paper default 0.7 m, §6.1).
    ``radius_m``: r^xz of Eq. 2, voxels farther apart horizontally are not joined.
    ``height_m``: vertical reach of the neighbourhood (the cylinder's half height).
    ``sigma_h_m``, ``sigma_v_m``: scales of the horizontal / vertical distance in Eq. 2.
    ``sigma_intensity``: scale of the intensity difference, in tile intensity IQRs.
    ``sigma_colour``: scale of the RGB distance (colours scaled to [0, 1]).
    ``min_height_m``: crown points are at least this high (and tops too).
    ``top_window_m``: fixed window of the local-maximum tree-top search when
    no tops are given (small on purpose: the cuts merge surplus tops).
    ``merge_ncut``: two regions whose best two-way cut costs more (Eq. 1) are one tree.
    ``climb``: cost per metre climbed of the geodesic start partition.
    ``attach_m``: reach of unconnected crown pieces to the nearest tree.
    """

    voxel_m: float = 0.7
    radius_m: float = 1.0
    height_m: float = 2.0
    sigma_h_m: float = 1.0
    sigma_v_m: float = 1.0
    sigma_intensity: float = 1.0
    sigma_colour: float = 0.25
    min_height_m: float = 2.0
    top_window_m: float = 2.0
    merge_ncut: float = 0.07
    climb: float = 100.0
    attach_m: float = 2.0

    def __post_init__(self):
        for name in ("voxel_m", "radius_m", "height_m", "sigma_h_m", "sigma_v_m", "sigma_intensity",
                     "sigma_colour", "merge_ncut"):
            if not getattr(self, name) > 0:
                raise ValueError(f"NormalizedCut.{name} must be positive")
        if self.min_height_m < 0:
            raise ValueError("NormalizedCut: min_height_m must be >= 0")

    def segment(self, cloud: PointCloud, tops=None, progress: Progress = None,
                cancelled: CancelCheck = None) -> np.ndarray:
        """Per-point tree IDs (int32, 0 = none) of a height-normalised cloud."""
        n = len(cloud)
        labels = np.zeros(n, dtype=np.int32)
        height = np.asarray(cloud.attr("height"), dtype=np.float64)
        ground = ground_mask(cloud, height)
        crown = (height >= self.min_height_m) & ~ground
        if not crown.any():
            return labels
        check(cancelled)
        report(progress, 0.0, "finding tree tops")
        local_tops = resolve_tops(cloud, tops, self.min_height_m, self.top_window_m,
                                  scaled(progress, 0.0, 0.1), cancelled)
        check(cancelled)
        report(progress, 0.1, "building the voxel graph")
        local = cloud.local_xyz()
        graph = voxel_graph(cloud, local, height, crown, self)
        check(cancelled)
        if len(local_tops) == 0 or graph.n == 0:
            return labels
        top_voxel, top_id, top_height = _top_voxels(graph, local_tops, self)
        report(progress, 0.2, "normalised cuts")
        vlabel = _cut_graph(graph, top_voxel, top_id, top_height, self,
                            scaled(progress, 0.2, 0.95), cancelled)
        # points: crown points take their voxel's label, low points the crown above them
        labels[crown] = vlabel[graph.point_voxel]
        # nothing of a tree is higher than its top (points of a taller neighbour)
        top_h = np.zeros(int(top_id.max()) + 1)
        top_h[top_id] = top_height
        above = labels > 0
        above[above] = height[above] > top_h[labels[above]] + TOP_TOLERANCE_M
        labels[above] = 0
        # stems and low branches (below min_height_m, or crown points no top
        # reached): the label of the crown right above them in their column
        low = np.flatnonzero((labels == 0) & ~ground)
        if len(low):
            has = vlabel > 0
            ixv, iyv, izv = graph.ijk[has].T
            lx = np.floor(local[low, 0] / self.voxel_m).astype(np.int64) - graph.ij0[0]
            ly = np.floor(local[low, 1] / self.voxel_m).astype(np.int64) - graph.ij0[1]
            inside = (lx >= 0) & (ly >= 0)
            q = np.full(len(low), -1, dtype=np.int64)
            q[inside] = column_keys(lx[inside], ly[inside])
            labels[low] = label_columns_below(
                column_keys(ixv, iyv), izv * self.voxel_m, vlabel[has].astype(np.int32),
                q, height[low])
        return labels


# --------------------------------------------------------------------------- voxel graph

@dataclass(eq=False)
class VoxelGraph:
    """Voxels of the crown points and their Eq. 2 affinities.

    ``xyz`` (m, 3) mean local x, y and height of each voxel; ``ijk`` integer
    voxel indices (relative to ``ij0``); ``point_voxel`` the voxel of each
    crown point; ``W`` the symmetric sparse affinity matrix (CSR);
    ``edges`` (e, 2) and ``weights`` (e,) the same as an edge list (i < j).
    """

    xyz: np.ndarray
    ijk: np.ndarray
    ij0: np.ndarray
    point_voxel: np.ndarray
    W: sp.csr_matrix
    edges: np.ndarray
    weights: np.ndarray

    @property
    def n(self) -> int:
        return len(self.xyz)


def _robust_scale(values: np.ndarray) -> float:
    q25, q75 = np.percentile(values, [25, 75])
    scale = float(q75 - q25)
    if not scale > 0:
        scale = float(np.std(values))
    return scale if scale > 0 else 1.0


def voxel_graph(cloud: PointCloud, local: np.ndarray, height: np.ndarray,
                crown: np.ndarray, params: NormalizedCut) -> VoxelGraph:
    """Voxelise the crown points and build the sparse Eq. 2 affinity graph."""
    idx = np.flatnonzero(crown)
    pitch = params.voxel_m
    x = local[idx, 0]
    y = local[idx, 1]
    z = height[idx]
    ix = np.floor(x / pitch).astype(np.int64)
    iy = np.floor(y / pitch).astype(np.int64)
    iz = np.floor(z / pitch).astype(np.int64)
    ij0 = np.array([ix.min(), iy.min()])
    ix -= ij0[0]
    iy -= ij0[1]
    ny = int(iy.max()) + 1
    nz = int(iz.max()) + 1
    key = (ix * ny + iy) * nz + iz
    ukey, inv = np.unique(key, return_inverse=True)
    m = len(ukey)
    count = np.bincount(inv, minlength=m).astype(np.float64)

    def mean(values):
        return np.bincount(inv, weights=values, minlength=m) / count

    vxyz = np.column_stack([mean(x), mean(y), mean(z)])
    ijk = np.column_stack([ukey // (ny * nz), (ukey // nz) % ny, ukey % nz])

    features = []  # per-voxel I and C features, already divided by their scales
    intensity = cloud.attr("intensity")
    if intensity is not None:
        vals = np.asarray(intensity, dtype=np.float64)[idx]
        scale = _robust_scale(vals) * params.sigma_intensity
        features.append(mean(vals)[:, None] / scale)
    rgb = [cloud.attr(c) for c in ("red", "green", "blue")]
    if all(c is not None for c in rgb):
        cols = np.column_stack([np.asarray(c, dtype=np.float64)[idx] for c in rgb])
        top = 65535.0 if cols.max(initial=0) > 255 else 255.0
        vcol = np.column_stack([mean(cols[:, j]) for j in range(3)]) / top
        features.append(vcol / params.sigma_colour)

    # the cylinder of Eq. 2 (horizontal distance < radius_m), cut at +-height_m
    # vertically: an ellipsoid, i.e. a ball in coordinates with z scaled
    squeeze = params.radius_m / params.height_m
    tree = cKDTree(vxyz * np.array([1.0, 1.0, squeeze]))
    pairs = tree.query_pairs(params.radius_m, output_type="ndarray")
    if len(pairs) == 0:
        pairs = np.zeros((0, 2), dtype=np.int64)
    a, b = pairs[:, 0], pairs[:, 1]
    d = vxyz[a] - vxyz[b]
    expo = np.hypot(d[:, 0], d[:, 1]) / params.sigma_h_m + np.abs(d[:, 2]) / params.sigma_v_m
    for values in features:
        diff = values[a] - values[b]
        expo += np.sqrt((diff * diff).sum(axis=1))
    w = np.exp(-expo)
    W = sp.coo_matrix((np.concatenate([w, w]), (np.concatenate([a, b]), np.concatenate([b, a]))),
                      shape=(m, m)).tocsr()
    return VoxelGraph(xyz=vxyz, ijk=ijk, ij0=ij0, point_voxel=inv, W=W,
                      edges=np.column_stack([a, b]), weights=w)


def _top_voxels(graph: VoxelGraph, tops, params: NormalizedCut):
    """The voxel of each tree top (nearest voxel mean, 3-D); tops without one are dropped.

    When several tops fall on one voxel, the first (highest, by TreeTops order) keeps it.
    """
    tree = cKDTree(graph.xyz)
    q = np.column_stack([tops.xy, tops.height])
    limit = max(params.radius_m, 2.0 * params.voxel_m)
    dist, vox = tree.query(q, distance_upper_bound=limit)
    ok = np.isfinite(dist)
    order = np.lexsort((np.arange(len(q)), -tops.height))
    order = order[ok[order]]
    vox_sorted = vox[order]
    _, first = np.unique(vox_sorted, return_index=True)
    keep = order[np.sort(first)]
    return (vox[keep].astype(np.int64), tops.tree_id[keep].astype(np.int64),
            tops.height[keep])


# --------------------------------------------------------------------------- cuts

def _lobpcg1(L: sp.csr_matrix, x: np.ndarray, y: np.ndarray, maxiter: int,
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


def _fiedler(W: sp.csr_matrix, deg: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Second-smallest generalised eigenvector x of (D - W) x = λ D x.

    Computed as the second-smallest eigenvector u of the normalised Laplacian
    L = I - D^-1/2 W D^-1/2 (the same eigenproblem, x = D^-1/2 u; the smallest
    is D^1/2 1) by LOBPCG (:func:`_lobpcg1`, ``FIEDLER_ITERATIONS``) started
    from ``start``; dense LAPACK for tiny graphs.
    """
    n = W.shape[0]
    sq = np.sqrt(deg)
    M = sp.diags(1.0 / sq) @ W @ sp.diags(1.0 / sq)
    if n > 60:
        L = (sp.identity(n, format="csr") - M).tocsr()
        u = _lobpcg1(L, start * sq, sq / np.linalg.norm(sq), FIEDLER_ITERATIONS)
    else:
        _, vecs = scipy.linalg.eigh(M.toarray(), subset_by_index=[n - 2, n - 2],
                                    check_finite=False)
        u = vecs[:, 0]
    return u / sq


def _best_split(W: sp.csr_matrix, deg: np.ndarray, x: np.ndarray, a: int, b: int):
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


def _geodesic_partition(graph: VoxelGraph, top_voxel: np.ndarray, climb: float) -> np.ndarray:
    """Index of the nearest top of every voxel along the graph (-1: unreachable).

    Paths start at the tops; a step costs the Eq. 2 dissimilarity -log w_ij
    plus ``climb`` times the height it gains, so a region runs down its own
    crown and stops at the crease where the neighbour's crown rises again."""
    m = graph.n
    a, b = graph.edges[:, 0], graph.edges[:, 1]
    base = -np.log(np.maximum(graph.weights, 1e-300)) + 1e-9
    dz = graph.xyz[b, 2] - graph.xyz[a, 2]
    src = np.concatenate([a, b])
    dst = np.concatenate([b, a])
    cost = np.concatenate([base + climb * np.maximum(dz, 0.0), base + climb * np.maximum(-dz, 0.0)])
    C = sp.csr_matrix((cost, (src, dst)), shape=(m, m))
    _, _, source = dijkstra(C, directed=True, indices=top_voxel, min_only=True,
                            return_predecessors=True)
    lookup = np.full(m + 1, -1, dtype=np.int64)
    lookup[top_voxel] = np.arange(len(top_voxel))
    return lookup[np.where(source >= 0, source, m)]   # -9999: no top reaches it


def _find(parent: np.ndarray, i: int) -> int:
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


def _cut_graph(graph: VoxelGraph, top_voxel: np.ndarray, top_id: np.ndarray,
               top_height: np.ndarray, params: "NormalizedCut", progress: Progress,
               cancelled: CancelCheck) -> np.ndarray:
    """Tree id of every voxel: geodesic start, pairwise normalised cuts, merges, clean-up.

    1. Every voxel starts with its nearest top along the graph.
    2. For every pair of touching regions, the two-way normalised cut of their
       union (Fiedler vector + Shi–Malik threshold search, the top of each on
       its own side) proposes a new boundary; its NCut value (Eq. 1) says how
       separate the two parts are.
    3. Pairs whose best cut costs more than ``merge_ncut`` are one tree with
       two local maxima: they are merged (the higher top keeps its id).  The
       other proposals move voxels across the boundary (the lowest-NCut
       proposal wins when a voxel gets several).
    """
    region = _geodesic_partition(graph, top_voxel, params.climb)
    a, b = graph.edges[:, 0], graph.edges[:, 1]
    ra, rb = region[a], region[b]
    touch = (ra >= 0) & (rb >= 0) & (ra != rb)
    pairs = np.unique(np.sort(np.column_stack([ra[touch], rb[touch]]), axis=1), axis=0)
    k = len(top_voxel)
    parent = np.arange(k)
    best_ncut = np.full(graph.n, np.inf)
    proposal = region.copy()
    if len(pairs):
        order = np.argsort(region, kind="stable")
        starts = np.searchsorted(region[order], np.arange(-1, k + 1))
        W = graph.W
        step = max(1, len(pairs) // 100)
        for i, (p, q) in enumerate(pairs):
            check(cancelled)
            if i % step == 0:
                report(progress, i / len(pairs), f"normalised cuts: {i}/{len(pairs)} tree pairs")
            nodes = np.sort(np.concatenate([order[starts[p + 1]:starts[p + 2]],
                                            order[starts[q + 1]:starts[q + 2]]]))
            sub = W[nodes][:, nodes]
            row_of = np.repeat(np.arange(len(nodes)), np.diff(sub.indptr))
            deg = np.bincount(row_of, weights=sub.data, minlength=len(nodes))
            if (deg <= 0).any():
                continue
            ia = int(np.searchsorted(nodes, top_voxel[p]))
            ib = int(np.searchsorted(nodes, top_voxel[q]))
            start = np.where(region[nodes] == p, -1.0, 1.0)
            x = _fiedler(sub, deg, start)
            side_a, ncut = _best_split(sub, deg, x, ia, ib)
            if ncut > params.merge_ncut:
                rp, rq = _find(parent, p), _find(parent, q)
                if rp != rq:
                    hi, lo = (rp, rq) if (top_height[rp], -rp) >= (top_height[rq], -rq) else (rq, rp)
                    parent[lo] = hi
                continue
            in_p = start < 0
            cut_now = float(sub.data[in_p[row_of] != in_p[sub.indices]].sum()) / 2.0
            ncut_now = cut_now / deg[in_p].sum() + cut_now / deg[~in_p].sum()
            if not ncut < ncut_now:
                continue   # the start boundary is already the better cut (Eq. 1)
            new = np.where(side_a, p, q)
            moved = (new != region[nodes]) & (ncut < best_ncut[nodes])
            proposal[nodes[moved]] = new[moved]
            best_ncut[nodes[moved]] = ncut
    roots = np.array([_find(parent, i) for i in range(k)], dtype=np.int64)
    vlabel = np.where(proposal >= 0, top_id[roots[np.maximum(proposal, 0)]], 0)
    alive = roots == np.arange(k)
    return _clean(graph, vlabel, top_voxel[alive], top_id[alive], top_height[alive],
                  0.0, params.attach_m)


def _clean(graph: VoxelGraph, vlabel: np.ndarray, top_voxel: np.ndarray,
           top_id: np.ndarray, top_height: np.ndarray, tolerance_m: float,
           attach_m: float) -> np.ndarray:
    """Physical consistency of the labels, then fill the gaps.

    * A tree holds nothing higher than its top (+ ``tolerance_m``).
    * A tree's voxels not connected to its top through the tree itself are
      fragments; they are released.
    * Released voxels go to the neighbouring tree they are most strongly joined
      to (largest w_ij) among the trees whose top is high enough.
    * Voxels of top-less graph components (crown pieces a sparse scan left
      unconnected) join the nearest labelled voxel within ``attach_m`` (3-D)
      when that tree's top is high enough; farther ones (isolated noise) stay 0.
    """
    m = graph.n
    a, b = graph.edges[:, 0], graph.edges[:, 1]
    w = graph.weights
    z = graph.xyz[:, 2]
    size = int(max(top_id.max(initial=0), vlabel.max(initial=0))) + 1
    height_of = np.full(size, -np.inf)
    height_of[top_id] = top_height
    vlabel = np.where(z <= height_of[vlabel] + tolerance_m, vlabel, 0)
    same = (vlabel[a] == vlabel[b]) & (vlabel[a] > 0)
    G = sp.coo_matrix((np.ones(same.sum()), (a[same], b[same])), shape=(m, m))
    _, frag = connected_components(G, directed=False)
    good = np.zeros(frag.max() + 1, dtype=bool)
    good[frag[top_voxel]] = vlabel[top_voxel] == top_id
    vlabel = np.where(good[frag], vlabel, 0)
    # flood the unlabelled voxels from labelled neighbours, strongest edge first
    src = np.concatenate([a, b])
    dst = np.concatenate([b, a])
    ww = np.concatenate([w, w])
    keep = vlabel[src] == 0            # only edges into unlabelled voxels matter
    src, dst, ww = src[keep], dst[keep], ww[keep]
    while len(src):
        cand = (vlabel[src] == 0) & (vlabel[dst] > 0)
        cand &= z[src] <= height_of[vlabel[dst]] + tolerance_m
        if not cand.any():
            break
        s, d, wc = src[cand], dst[cand], ww[cand]
        o = np.lexsort((-wc, s))
        s, d = s[o], d[o]
        first = np.ones(len(s), dtype=bool)
        first[1:] = s[1:] != s[:-1]
        vlabel[s[first]] = vlabel[d[first]]
        still = vlabel[src] == 0
        src, dst, ww = src[still], dst[still], ww[still]
    # crown pieces the graph left unconnected (sparse scans): nearest tree within attach_m
    for _ in range(ATTACH_ROUNDS):
        free = np.flatnonzero(vlabel == 0)
        done = np.flatnonzero(vlabel > 0)
        if not (len(free) and len(done) and attach_m > 0):
            break
        dist, near = cKDTree(graph.xyz[done]).query(graph.xyz[free], distance_upper_bound=attach_m)
        ok = np.isfinite(dist)
        lab = vlabel[done[near[ok]]]
        fit = z[free[ok]] <= height_of[lab] + tolerance_m
        if not fit.any():
            break
        vlabel[free[ok][fit]] = lab[fit]
    return vlabel
