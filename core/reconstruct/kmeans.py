"""Variational k-means segmentation and branch reconstruction of dense scans (Yan et al. 2009).

Yan, Wintz, Mourrain, Wang, Boudon & Godin (2009), "Efficient and robust
reconstruction of botanical branching structure from laser scanned points"
(``../shared/papers/yan2009_variational_kmeans_branching.txt``), three steps:

1. **Segmentation** (§2, :func:`segment`): a kd-tree kNN graph (k = 8, §2.1);
   clusters grown from seeds and refined by Lloyd iterations on the energy of
   Eq. 1, ``E = sum_i sum_{p in C_i} |p - c_i|^2`` (§2.2); a bounding cylinder
   per cluster (principal axis + minimal enclosing circle of the projected
   points) and the RMS tightness test against δ (§2.3); unfixed clusters are
   split (parent seed + farthest point) until every cluster fits or the
   cluster budget is reached (§2.4).  Region growing is one multi-source
   Dijkstra on the kNN graph (``scipy.sparse.csgraph.dijkstra`` with
   ``min_only=True``): every point joins its geodesically nearest seed, which is
   the flooding of [CSAD04] on a point graph.  Fixed clusters keep their
   points ("will not be changed any further", §2.3): later rounds flood the
   unfixed points only.
2. **Branch reconstruction** (§3, :func:`branch_structure`): cluster adjacency
   from kNN edges that cross clusters (§3.1); a junction point per adjacent
   pair, the centre of their boundary points, and edge weights
   ``|J - c_i| + |J - c_j|`` (§3.2); the shortest-path tree from the cluster
   holding the lowest point (§3.2); extra junctions for leaf clusters and the
   root, symmetric to their junction about the cluster centre (§3.2, Fig. 4);
   branches by the longest-path rule of Algorithm 3.1 with a FIFO queue, and
   branch orders (trunk 0, a branch off a branch of order o has order o + 1).
3. **Modelling** (§4, :func:`model_branches`): a cubic B-spline (Eq. 2) fitted
   to each branch's skeleton vertices (``scipy.interpolate.splprep``), radii
   linearly interpolated from the bounding cylinders along it (§4.2), lofting
   with rotation-minimising frames (:func:`sylva.core.geometry.sweep_tube`,
   ``n2 = 10`` sides and 30 samples per branch as in §4.2 / §5), and the
   resulting cylinder list (:mod:`sylva.core.qsm`).

Additions that are not in the paper, each measured by ``benchmarks/dense.py``:
a branch whose first clusters run inside its parent (a second chain of
clusters up the other side of a thick stem) leaves from the parent's centre
line where it exits the parent (:func:`_trim_in_parent`); with
``refit=True`` the cylinders' radii and axes are fitted to the points
nearest each (circle fits, :func:`sylva.core.qsm.refit_radii`), the centre
lines moved onto the fitted axes (:func:`_recentre`), a branch's base inside
its parent gets its first outside radius, no branch is thicker than the
cylinder it leaves (:func:`sylva.core.qsm.taper_radii`), and branches whose
fitted curve stays within ``prune_factor`` radii of an earlier branch are dropped
(:func:`_outside_earlier_branches`).

All thresholds are in metres (the paper normalised each scan into the unit
cube; its δ in [1e-3, 1e-2] of the tree size is 1–10 cm for a 10 m tree).

:func:`is_dense_scan` is the automatic rule that sends a tree to this method
instead of the airborne methods.
"""
from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass
from typing import List, Optional, Tuple

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from ..errors import InputError, SylvaError
from ..progress import CancelCheck, Progress, check, report
from .model import Reconstruction, Skeleton, TreePoints, screen

__all__ = ["VariationalKMeans", "Segmentation", "BranchStructure", "DenseModel", "knn_graph",
           "segment", "lloyd", "bounding_cylinders", "energy", "branch_structure", "model_branches",
           "is_dense_scan", "DENSE_SPACING_M", "DENSE_LOW_SHARE", "DENSE_MIN_POINTS", "point_normals",
           "prune_branches"]

_EPS = 1e-12
#: Lloyd re-floods only the clusters whose seed moved (and their neighbours) on graphs of
#: more points than this; smaller graphs are flooded whole, which is faster there.
LOCAL_FLOOD_MIN_POINTS = 100_000


# --------------------------------------------------------------------------- §2.1 kNN graph

def knn_graph(xyz: np.ndarray, k: int = 8) -> Tuple[sparse.csr_matrix, np.ndarray]:
    """Symmetric kNN graph (Yan §2.1, k = 8) as a CSR matrix of Euclidean edge lengths.

    Returns ``(graph, nbr)`` with ``nbr`` the (n, k) neighbour indices (self excluded).
    Zero-length edges (duplicate points) get 1e-9 m so csgraph keeps them.
    """
    n = len(xyz)
    k = int(min(k, n - 1))
    d, nbr = cKDTree(xyz).query(xyz, k=k + 1, workers=-1)
    d, nbr = d[:, 1:], nbr[:, 1:]
    rows = np.repeat(np.arange(n), k)
    g = sparse.csr_matrix((np.maximum(d.ravel(), 1e-9), (rows, nbr.ravel())), shape=(n, n))
    g = g.maximum(g.T).tocsr()
    return g, nbr


# --------------------------------------------------------------------------- §2.2 Lloyd

def _group_argmin(values: np.ndarray, labels: np.ndarray, n: int) -> np.ndarray:
    """Per label, the index of the smallest value (lowest index on ties; -1 for empty labels).

    Unbuffered ``minimum.at`` twice (group minima, then the first index
    reaching them): no sort, O(m)."""
    out = np.full(n, -1, dtype=np.int64)
    m = len(values)
    if m == 0:
        return out
    gmin = np.full(n, np.inf)
    np.minimum.at(gmin, labels, values)
    cand = np.flatnonzero(values <= gmin[labels])
    first = np.full(n, m, dtype=np.int64)
    np.minimum.at(first, labels[cand], cand)
    ok = first < m
    out[ok] = first[ok]
    return out


def _group_argmax(values: np.ndarray, labels: np.ndarray, n: int) -> np.ndarray:
    return _group_argmin(-values, labels, n)


def _centroids(xyz: np.ndarray, labels: np.ndarray, n: int) -> Tuple[np.ndarray, np.ndarray]:
    counts = np.bincount(labels, minlength=n).astype(np.float64)
    c = np.empty((n, 3))
    for j in range(3):
        c[:, j] = np.bincount(labels, weights=xyz[:, j], minlength=n)
    return c / np.maximum(counts, 1.0)[:, None], counts


def energy(xyz: np.ndarray, labels: np.ndarray, centres: np.ndarray) -> float:
    """Yan Eq. 1: sum over clusters of the squared distances of their points to the centre (m²)."""
    ok = labels >= 0
    d = xyz[ok] - centres[labels[ok]]
    return float(np.einsum("ij,ij->", d, d))


def _csr_rows(indptr: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Positions in ``indices`` of all entries of the given CSR rows (vectorised)."""
    start, stop = indptr[rows], indptr[rows + 1]
    cnt = stop - start
    if cnt.sum() == 0:
        return np.zeros(0, dtype=np.int64)
    off = np.repeat(start - np.r_[0, np.cumsum(cnt)[:-1]], cnt)
    return np.arange(cnt.sum()) + off


def _subgraph(graph: sparse.csr_matrix, mask: np.ndarray) -> sparse.csr_matrix:
    """The CSR graph induced by the nodes where ``mask`` (renumbered in order), built from
    the CSR arrays of those rows only (no sparse fancy indexing, no re-sorting)."""
    ip, ix = graph.indptr, graph.indices
    idx = np.flatnonzero(mask)
    m = len(idx)
    if m == len(mask):
        return graph
    pos = _csr_rows(ip, idx)
    cnt = ip[idx + 1] - ip[idx]
    keep = mask[ix[pos]]
    loc = np.full(len(mask), -1, dtype=np.int64)
    loc[idx] = np.arange(m)
    indptr = np.zeros(m + 1, dtype=np.int64)
    np.cumsum(np.bincount(np.repeat(np.arange(m), cnt)[keep], minlength=m), out=indptr[1:])
    return sparse.csr_matrix((graph.data[pos[keep]], loc[ix[pos[keep]]], indptr), shape=(m, m), copy=False)


def _flood(graph: sparse.csr_matrix, seeds: np.ndarray, metric: str = "hops"):
    """Grow one region per seed at once: the nearest seed of every point on the kNN graph.

    ``metric="hops"``: multi-source breadth-first search (distance = number of
    kNN edges); ``"metres"``: multi-source Dijkstra on the Euclidean edge
    lengths.  Both run from a virtual node joined to every seed (one
    single-source search; equivalent to ``dijkstra(indices=seeds,
    min_only=True)``) and find each point's seed by pointer jumping along
    the predecessor tree.  Returns (cluster index per point, -1 where no seed
    is reachable; geodesic distance in metres to that seed for ``"metres"``,
    0 / inf (reached or not) for ``"hops"``).
    """
    n = graph.shape[0]
    seeds = np.asarray(seeds, dtype=np.int64)
    ip, ix, dv = graph.indptr, graph.indices, graph.data
    aug = sparse.csr_matrix((np.concatenate([dv, np.full(len(seeds), 1e-12)]),
                             np.concatenate([ix, seeds.astype(ix.dtype)]),
                             np.concatenate([ip, np.array([ip[-1] + len(seeds)], dtype=ip.dtype)])),
                            shape=(n + 1, n + 1), copy=False)
    if metric == "metres":
        dist, pred = csgraph.dijkstra(aug, directed=True, indices=n, return_predecessors=True)
        dist, pred = np.maximum(dist[:n] - 1e-12, 0.0), pred[:n].astype(np.int64)
        reached = np.isfinite(dist)
    else:
        _, pred = csgraph.breadth_first_order(aug, n, directed=True, return_predecessors=True)
        pred = pred[:n].astype(np.int64)
        reached = pred >= 0
    # each point's seed: the root of its branch of the search tree, found by
    # pointer jumping (log2(depth) vectorised gathers)
    ptr = np.where(reached & (pred >= 0) & (pred < n), pred, np.arange(n))
    ptr[seeds] = seeds
    while True:
        nxt = ptr[ptr]
        if np.array_equal(nxt, ptr):
            break
        ptr = nxt
    lut = np.full(n, -1, dtype=np.int64)
    lut[seeds] = np.arange(len(seeds))
    lab = np.where(reached, lut[ptr], -1)
    if metric != "metres":
        dist = np.where(reached, 0.0, np.inf)   # hop counts are not needed downstream
    return lab, dist


def lloyd(xyz: np.ndarray, graph: sparse.csr_matrix, seeds: np.ndarray, max_iter: int = 30,
          epsilon_rel: float = 1e-5, local: bool = True, metric: str = "hops"):
    """Lloyd iterations of Yan §2.2 on the points of ``graph`` from ``seeds`` (point indices).

    Step 2 (clustering): every point joins the seed it reaches first on the
    kNN graph (multi-source breadth-first search or Dijkstra, ``metric``,
    see :func:`_flood`); step 3 (updating): centres ``c_i``,
    new seed = the cluster's point nearest its centre; stop after
    ``max_iter`` iterations, when the Eq. 1 energy drops by less than
    ``epsilon_rel`` of itself, or when no seed moves.  With ``local`` only
    the clusters whose seed moved and their neighbours are flooded again
    (the others keep their points: their seeds did not move and their
    geodesic cells only change at shared borders).  An iteration that does
    not lower the energy (seeds can cycle between two points on a discrete
    graph) ends the loop and is dropped, so the recorded energies strictly
    decrease.  Returns ``(labels, seeds, geodesic distance to own seed,
    energies)``; points no seed reaches get label -1.
    """
    seeds = np.asarray(seeds, dtype=np.int64).copy()
    n = len(seeds)
    npt = len(xyz)
    xyz = xyz - xyz.mean(axis=0) if npt else xyz     # centred: the closed-form energy stays exact
    sq = np.einsum("ij,ij->i", xyz, xyz)
    energies = []
    graph = graph.tocsr()
    indptr, indices = graph.indptr, graph.indices
    lab, dist = _flood(graph, seeds, metric)

    def sums(idx, lb):
        ok = lb >= 0
        i, lb = idx[ok], lb[ok]
        s1 = np.stack([np.bincount(lb, weights=xyz[i, j], minlength=n) for j in range(3)], axis=1)
        return np.bincount(lb, minlength=n).astype(np.float64), s1, np.bincount(lb, weights=sq[i], minlength=n)

    allidx = np.arange(npt)
    cnt, s1, s2 = sums(allidx, lab)
    ridx, aff = allidx, np.ones(n, dtype=bool)
    best = None
    for _ in range(max(1, int(max_iter))):
        # Eq. 1 per cluster in closed form: sum |p|^2 - |sum p|^2 / n
        e = float(np.sum(s2 - np.einsum("ij,ij->i", s1, s1) / np.maximum(cnt, 1.0)))
        if best is not None and e >= best[0]:
            break                      # no further decrease (e.g. a 2-cycle of seeds): keep the best
        energies.append(e)
        prev = best
        best = (e, lab, seeds, dist)
        if prev is not None and prev[0] - e < epsilon_rel * prev[0]:
            break
        c = s1 / np.maximum(cnt, 1.0)[:, None]
        # new seeds of the clusters that changed: their point nearest the centre
        rl = lab[ridx]
        okr = rl >= 0
        pts_r, lab_r = ridx[okr], rl[okr]
        d2 = ((xyz[pts_r] - c[lab_r]) ** 2).sum(axis=1)
        near = _group_argmin(d2, lab_r, n)
        new = seeds.copy()
        upd = aff & (near >= 0)
        new[upd] = pts_r[near[upd]]
        moved = new != seeds
        if not moved.any():
            break
        seeds = new
        if not local:
            lab, dist = _flood(graph, seeds, metric)
            cnt, s1, s2 = sums(allidx, lab)
            ridx, aff = allidx, np.ones(n, dtype=bool)
            continue
        # re-flood the moved clusters and their neighbours only
        mpts = np.flatnonzero(moved[np.maximum(lab, 0)] & (lab >= 0))
        nb_lab = lab[indices[_csr_rows(indptr, mpts)]]
        aff = moved.copy()
        aff[nb_lab[nb_lab >= 0]] = True
        region = (lab < 0) | aff[np.maximum(lab, 0)]
        ridx = np.flatnonzero(region)
        g = _subgraph(graph, region)
        loc = np.full(npt, -1, dtype=np.int64)
        loc[ridx] = np.arange(len(ridx))
        acl = np.flatnonzero(aff)
        sl, dl = _flood(g, loc[seeds[acl]], metric)
        old = sums(ridx, lab[ridx])
        lab = lab.copy()
        dist = dist.copy()
        lab[ridx] = np.where(sl >= 0, acl[np.maximum(sl, 0)], -1)
        dist[ridx] = dl
        new_s = sums(ridx, lab[ridx])
        cnt = cnt - old[0] + new_s[0]
        s1 = s1 - old[1] + new_s[1]
        s2 = s2 - old[2] + new_s[2]
    _, lab, seeds, dist = best
    return lab, seeds, dist, energies


# --------------------------------------------------------------------------- §2.3 cylinders

_DIRS = 16


def _enclosing_circles(p2: np.ndarray, labels: np.ndarray, n: int):
    """Minimal enclosing circle per cluster of 2-D points (Yan §2.3 uses Gärtner's [Gär99]).

    Vectorised: the extreme points of each cluster in 16 directions are the
    candidates; the smallest of all their 2-point (diametral) and 3-point
    (circumscribed) circles containing every candidate is the MEC of the
    candidates; its radius is then grown to the farthest point of the whole
    cluster, so the circle always encloses the cluster and exceeds the exact
    minimum by at most 1 / cos(π/16) - 1 ≈ 2 % of the radius.
    """
    ang = np.pi * 2 * np.arange(_DIRS) / _DIRS
    dirs = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    order = np.argsort(labels, kind="stable")
    lab_s = labels[order]
    starts = np.flatnonzero(np.r_[True, lab_s[1:] != lab_s[:-1]])
    proj = p2[order] @ dirs.T                              # (m, D), grouped by cluster
    gmax = np.maximum.reduceat(proj, starts, axis=0)       # (g, D)
    gid = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, len(lab_s)]))
    pos = np.where(proj >= gmax[gid], np.arange(len(lab_s))[:, None], len(lab_s))
    first = np.minimum.reduceat(pos, starts, axis=0)       # (g, D) position of an extreme point
    cand = np.zeros((n, _DIRS), dtype=np.int64)
    cand[lab_s[starts]] = order[first]
    q = p2[cand]                                           # (n, D, 2)
    ia, ib = np.triu_indices(_DIRS, 1)
    pa, pb = q[:, ia], q[:, ib]
    cen2 = (pa + pb) / 2
    rad2 = np.linalg.norm(pa - pb, axis=2) / 2
    tri = np.array([(a, b, c) for a in range(0, _DIRS, 2) for b in range(a + 1, _DIRS, 2)
                    for c in range(b + 1, _DIRS, 2)]).T     # triples of every other direction
    a, b, cc = q[:, tri[0]], q[:, tri[1]], q[:, tri[2]]
    bx, by = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    cx, cy = cc[..., 0] - a[..., 0], cc[..., 1] - a[..., 1]
    dd = 2 * (bx * cy - by * cx)
    good = np.abs(dd) > 1e-15
    dd = np.where(good, dd, 1.0)
    ux = (cy * (bx ** 2 + by ** 2) - by * (cx ** 2 + cy ** 2)) / dd
    uy = (bx * (cx ** 2 + cy ** 2) - cx * (bx ** 2 + by ** 2)) / dd
    cen3 = a + np.stack([ux, uy], axis=-1)
    rad3 = np.where(good, np.hypot(ux, uy), np.inf)
    cen = np.concatenate([cen2, cen3], axis=1)             # (n, C, 2)
    rad = np.concatenate([rad2, rad3], axis=1)
    # squared distance of the farthest candidate from every circle centre
    dx = cen[:, :, None, 0] - q[:, None, :, 0]
    dy = cen[:, :, None, 1] - q[:, None, :, 1]
    far2 = (dx * dx + dy * dy).max(axis=2)
    rad = np.where(far2 <= (rad * (1 + 1e-9) + 1e-12) ** 2, rad, np.inf)
    best = np.argmin(rad, axis=1)
    centre = cen[np.arange(n), best]
    dist = np.hypot(p2[:, 0] - centre[labels, 0], p2[:, 1] - centre[labels, 1])
    radius = np.zeros(n)
    radius[lab_s[starts]] = np.maximum.reduceat(dist[order], starts)
    return centre, radius, dist


def point_normals(xyz: np.ndarray, nbr: np.ndarray) -> np.ndarray:
    """Unit normal per point: the least-variance direction of the point and its kNN (batched eigh)."""
    q = np.concatenate([xyz[:, None, :], xyz[nbr]], axis=1)
    q = q - q.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", q, q)
    return _smallest_eigvec(cov)


def _smallest_eigvec(a: np.ndarray) -> np.ndarray:
    """Unit eigenvector of the smallest eigenvalue of each symmetric 3x3 matrix (n, 3, 3).

    Closed form: the eigenvalues by the trigonometric solution of the
    characteristic cubic, the vector as the largest cross product of two rows
    of ``A - λ_min I``; matrices where that is ill-conditioned (two nearly
    equal smallest eigenvalues, e.g. points on a line) fall back to ``eigh``.
    """
    a = np.asarray(a, dtype=np.float64)
    n = len(a)
    if n == 0:
        return np.zeros((0, 3))
    scale = np.maximum(np.abs(a).reshape(n, 9).max(axis=1), 1e-300)
    b = a / scale[:, None, None]
    q = (b[:, 0, 0] + b[:, 1, 1] + b[:, 2, 2]) / 3
    p1 = b[:, 0, 1] ** 2 + b[:, 0, 2] ** 2 + b[:, 1, 2] ** 2
    p2 = (b[:, 0, 0] - q) ** 2 + (b[:, 1, 1] - q) ** 2 + (b[:, 2, 2] - q) ** 2 + 2 * p1
    p = np.sqrt(np.maximum(p2 / 6, 0))
    c = b - q[:, None, None] * np.eye(3)
    det = np.linalg.det(c / np.maximum(p, 1e-300)[:, None, None])
    phi = np.arccos(np.clip(det / 2, -1, 1)) / 3
    lam = q + 2 * p * np.cos(phi + 2 * np.pi / 3)          # the smallest root
    m = b - lam[:, None, None] * np.eye(3)
    cr = np.stack([np.cross(m[:, 0], m[:, 1]), np.cross(m[:, 0], m[:, 2]), np.cross(m[:, 1], m[:, 2])], axis=1)
    nn = np.einsum("nki,nki->nk", cr, cr)
    best = np.argmax(nn, axis=1)
    v = cr[np.arange(n), best]
    norm = np.sqrt(nn[np.arange(n), best])
    # ill-conditioned: the cross product is small against the matrix (double smallest eigenvalue)
    bad = norm < 1e-6 * np.maximum(p, 1e-12) ** 2
    out = v / np.maximum(norm, 1e-300)[:, None]
    if bad.any():
        out[bad] = np.linalg.eigh(a[bad])[1][:, :, 0]
    return out


def bounding_cylinders(xyz: np.ndarray, labels: np.ndarray, n: int, normals: Optional[np.ndarray] = None):
    """Bounding cylinder and RMS tightness of every cluster (Yan §2.3).

    Axis = principal eigenvector of the cluster covariance (batched
    ``eigh``), or, with ``normals`` (per point, :func:`point_normals`), the
    direction orthogonal to the cluster's surface normals where they are
    curved enough (short, thick clusters of a stem, whose principal axis
    lies across the stem); the points are projected onto the plane through the centre
    normal to it; the radius is that of their minimal enclosing circle; the
    tightness is the RMS of the points' distances to the cylinder surface,
    ``sqrt(mean((R - ρ_p)^2))`` with ρ_p the distance of p to the axis.
    Returns a dict of (n,) / (n, 3) arrays: centre (on the axis, mid-length),
    axis (unit, pointing up), radius, length, rms, count, mean (point
    centroid), mean_rho (mean distance of the points to the axis),
    fit_radius / fit_centre (least-squares circle of the projected points, its
    centre placed on the axis at mid-length) and rms_fit (RMS distance of the
    points to that fitted cylinder).
    Clusters of fewer than 3 points get radius 0 and rms 0.
    """
    ok = labels >= 0
    p, lab = xyz[ok], labels[ok]
    mean, counts = _centroids(p, lab, n)
    d = p - mean[lab]
    cov = np.empty((n, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            cov[:, i, j] = cov[:, j, i] = np.bincount(lab, weights=d[:, i] * d[:, j], minlength=n)
    cov /= np.maximum(counts, 1.0)[:, None, None]
    _, vec = np.linalg.eigh(cov)
    axis = vec[:, :, 2]
    if normals is not None:
        # the axis of a cylinder is the direction normal to all its surface
        # normals: least eigenvector of sum n n^T; kept where the normals
        # span more than a flat patch (else the principal axis, Yan §2.3)
        nm = normals[ok]
        mm = np.empty((n, 3, 3))
        for i in range(3):
            for j in range(i, 3):
                mm[:, i, j] = mm[:, j, i] = np.bincount(lab, weights=nm[:, i] * nm[:, j], minlength=n)
        lam, nvec = np.linalg.eigh(mm)
        curved = lam[:, 1] > 0.05 * np.maximum(lam[:, 2], _EPS)
        axis = np.where(curved[:, None], nvec[:, :, 0], axis)
    axis = np.where(axis[:, 2:3] < 0, -axis, axis)
    helper = np.where(np.abs(axis[:, 2:3]) < 0.9, np.array([0, 0, 1.0]), np.array([1.0, 0, 0]))
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(axis, e1)
    p2 = np.stack([(d * e1[lab]).sum(1), (d * e2[lab]).sum(1)], axis=1)
    t = (d * axis[lab]).sum(1)
    c2, radius, rho = _enclosing_circles(p2, lab, n)
    rms = np.sqrt(np.bincount(lab, weights=(radius[lab] - rho) ** 2, minlength=n)
                  / np.maximum(counts, 1.0))
    tmin = np.full(n, np.inf)
    tmax = np.full(n, -np.inf)
    np.minimum.at(tmin, lab, t)
    np.maximum.at(tmax, lab, t)
    small = counts < 3
    tmin[small] = tmax[small] = 0.0
    length = tmax - tmin
    centre = mean + c2[:, :1] * e1 + c2[:, 1:] * e2 + ((tmin + tmax) / 2)[:, None] * axis
    radius[small] = rms[small] = 0.0
    mean_rho = np.bincount(lab, weights=rho, minlength=n) / np.maximum(counts, 1.0)
    # least-squares circle (Kasa) of the projected points, all clusters at once:
    # x^2 + y^2 = 2 a x + 2 b y + c  ->  3x3 normal equations per cluster
    x, y = p2[:, 0], p2[:, 1]
    z = x * x + y * y
    cols = (x, y, np.ones_like(x))
    ata = np.empty((n, 3, 3))
    atb = np.empty((n, 3))
    for i in range(3):
        atb[:, i] = np.bincount(lab, weights=cols[i] * z, minlength=n)
        for j in range(i, 3):
            ata[:, i, j] = ata[:, j, i] = np.bincount(lab, weights=cols[i] * cols[j], minlength=n)
    # G y = A^T z with G = sum c c^T over columns (x, y, 1); (a, b, c) = (y0/2, y1/2, y2)
    ata_s = ata + np.eye(3)[None] * 1e-12
    det_ok = np.abs(np.linalg.det(ata_s)) > 1e-30
    sol = np.zeros((n, 3))
    if det_ok.any():
        sol[det_ok] = np.linalg.solve(ata_s[det_ok], atb[det_ok][..., None])[..., 0]
    sol[:, :2] /= 2.0
    fit_r = np.sqrt(np.maximum(sol[:, 2] + sol[:, 0] ** 2 + sol[:, 1] ** 2, 0.0))
    # a circle more than twice as wide as the enclosing one fits an arc of under
    # 60 degrees, which fixes no radius (a flat, noisy patch): not trusted
    good = det_ok & (counts >= 5) & (fit_r <= 2.0 * radius)
    fit_r = np.where(good, fit_r, np.minimum(mean_rho, radius))
    fit_c = np.where(good[:, None], mean + sol[:, :1] * e1 + sol[:, 1:2] * e2
                     + ((tmin + tmax) / 2)[:, None] * axis, centre)
    # RMS distance to the fitted cylinder (a partial arc fits it, not its enclosing circle)
    rho_fit = np.linalg.norm(p2 - sol[lab, :2], axis=1)
    rms_fit = np.sqrt(np.bincount(lab, weights=(rho_fit - fit_r[lab]) ** 2, minlength=n)
                      / np.maximum(counts, 1.0))
    rms_fit = np.where(good, rms_fit, np.maximum(rms, rms_fit))
    return dict(centre=centre, axis=axis, radius=radius, length=length, rms=rms,
                count=counts.astype(np.int64), mean=mean, mean_rho=mean_rho, fit_radius=fit_r,
                fit_centre=fit_c, rms_fit=rms_fit)


# --------------------------------------------------------------------------- §2 driver

@dataclass
class Segmentation:
    """Result of Yan §2: ``labels`` (n,) cluster per point (-1: unreached noise),
    per-cluster ``seeds`` (point indices), ``fixed`` flags and bounding
    ``cylinders`` (see :func:`bounding_cylinders`), the kNN ``graph`` / ``nbr``,
    the Eq. 1 energy of every Lloyd iteration per round (``energies``),
    ``rounds`` of subdivision and ``reason`` it stopped (``"all_fixed"``,
    ``"budget"``, ``"too_small"``)."""

    labels: np.ndarray
    seeds: np.ndarray
    fixed: np.ndarray
    cylinders: dict
    graph: sparse.csr_matrix
    nbr: np.ndarray
    energies: List[List[float]]
    rounds: int
    reason: str

    @property
    def n_clusters(self) -> int:
        return len(self.seeds)


def segment(xyz: np.ndarray, k: int = 8, n_seeds: int = 0, delta_m: float = 0.03,
            max_clusters: int = 2000, min_cluster_points: int = 150, max_iter: int = 30,
            epsilon_rel: float = 1e-5, min_component_points: int = 10, seed: int = 0, metric: str = "hops",
            axis: str = "pca", tightness: str = "bounding",
            cancelled: CancelCheck = None, progress: Progress = None) -> Segmentation:
    """Yan §2 variational k-means segmentation of one tree's points (metres).

    ``n_seeds`` initial random seeds (§2.2 step 1, a user input in the paper;
    0 = one per 250 points, at least 20, which saves subdivision rounds on
    big scans; every kNN component of at
    least ``min_component_points`` points gets one; smaller components stay
    unlabelled, -1); Lloyd (§2.2); cylinders + fixing by RMS < ``delta_m``
    (§2.3; ``tightness="fit"``: RMS to the least-squares cylinder instead of
    the bounding one, which partial arcs of one-sided scans never meet); each unfixed cluster of more than ``min_cluster_points`` points is
    split, parent seed + its point farthest from that seed (§2.4); back to
    Lloyd on the unfixed points until all clusters are fixed, none can be
    split or ``max_clusters`` is reached.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    n = len(xyz)
    rng = np.random.default_rng(seed)
    graph, nbr = knn_graph(xyz, k)
    normals = point_normals(xyz, nbr) if axis == "normals" else None
    ncomp, comp = csgraph.connected_components(graph, directed=False)
    csize = np.bincount(comp, minlength=ncomp)
    big = np.flatnonzero(csize >= min_component_points)
    if len(big) == 0:
        big = np.array([int(np.argmax(csize))])
    usable = np.isin(comp, big)
    # initial seeds: random usable points, plus one per component not hit
    cand = np.flatnonzero(usable)
    if n_seeds <= 0:
        n_seeds = max(20, n // 250)
    s0 = rng.choice(cand, size=min(int(n_seeds), len(cand)), replace=False)
    missing = np.setdiff1d(big, comp[s0])
    extra = [int(rng.choice(np.flatnonzero(comp == c))) for c in missing]
    seeds = np.unique(np.r_[s0, np.asarray(extra, dtype=np.int64)]).astype(np.int64)

    labels = np.full(n, -1, dtype=np.int64)
    fixed = np.zeros(0, dtype=bool)
    all_seeds = np.zeros(0, dtype=np.int64)
    energies: List[List[float]] = []
    active = usable.copy()               # points still free to move (not in fixed clusters)
    new_seeds = seeds
    rounds = 0
    reason = "all_fixed"
    cyl = None
    while True:
        check(cancelled)
        rounds += 1
        act_idx = np.flatnonzero(active)
        lp = np.full(n, -1, dtype=np.int64)
        lp[act_idx] = np.arange(len(act_idx))
        g = _subgraph(graph, active)
        # local re-flooding (see lloyd) pays off on big graphs only (benchmarks/dense.py:
        # 34,542 points 20 % faster without, 217,187 points 8 % faster with)
        lab, s_loc, dist, en = lloyd(xyz[act_idx], g, lp[new_seeds], max_iter, epsilon_rel,
                                     local=len(act_idx) > LOCAL_FLOOD_MIN_POINTS, metric=metric)
        base = len(all_seeds)
        labels[act_idx] = np.where(lab >= 0, lab + base, -1)
        all_seeds = np.r_[all_seeds, act_idx[s_loc]]
        nc = len(all_seeds)
        # full-energy bookkeeping (Eq. 1 over all clusters) for this round
        cent_all, _ = _centroids(xyz[labels >= 0], labels[labels >= 0], nc)
        fixed_e = energy(xyz[~active & (labels >= 0)], labels[~active & (labels >= 0)], cent_all)
        energies.append([fixed_e + e for e in en])
        ok_new = lab >= 0
        cyl_new = bounding_cylinders(xyz[act_idx][ok_new], lab[ok_new], nc - base,
                                     None if normals is None else normals[act_idx][ok_new])
        cyl = cyl_new if cyl is None else {key: np.concatenate([cyl[key], cyl_new[key]]) for key in cyl}
        fixed = np.r_[fixed, cyl_new["rms" if tightness == "bounding" else "rms_fit"] < delta_m]
        newly = np.arange(base, nc)
        report(progress, min(0.95, nc / max(max_clusters, 1)), f"{nc} clusters, {int(fixed.sum())} fixed")
        unfixed = newly[~fixed[newly]]
        if len(unfixed) == 0:
            reason = "all_fixed"
            break
        splittable = unfixed[cyl["count"][unfixed] > min_cluster_points]
        if len(splittable) == 0:
            reason = "too_small"
            break
        if nc >= max_clusters:
            reason = "budget"
            break
        room = max_clusters - nc
        if len(splittable) > room:     # split the loosest clusters first
            splittable = splittable[np.argsort(-cyl["rms"][splittable], kind="stable")[:room]]  # loosest
        # §2.4: the unfixed clusters are re-run; split ones get a second seed
        in_unfixed = np.isin(labels, unfixed)
        dseed = np.linalg.norm(xyz - xyz[all_seeds[np.maximum(labels, 0)]], axis=1)
        far = _group_argmax(np.where(in_unfixed, dseed, -np.inf), np.maximum(labels, 0), nc)
        new_seeds = np.r_[all_seeds[unfixed], far[splittable]].astype(np.int64)
        new_seeds = np.unique(new_seeds)
        # the unfixed clusters are removed and re-created from the new seeds
        keep = np.setdiff1d(np.arange(nc), unfixed)
        remap = np.full(nc, -1, dtype=np.int64)
        remap[keep] = np.arange(len(keep))
        active = usable & in_unfixed
        labels = np.where(labels >= 0, remap[np.maximum(labels, 0)], -1)
        labels[active] = -1
        all_seeds = all_seeds[keep]
        fixed = fixed[keep]
        cyl = {key: v[keep] for key, v in cyl.items()}
    return Segmentation(labels, all_seeds, fixed, cyl, graph, nbr, energies, rounds, reason)


# --------------------------------------------------------------------------- §3 branches

@dataclass
class BranchStructure:
    """Yan §3 on the clusters.

    ``parent`` (n,) parent cluster in the shortest-path tree (-1 root / unreached);
    ``root`` the cluster holding the lowest point; ``junction`` (n, 3) the
    junction point between each cluster and its parent (§3.2; for the root
    its extra junction); ``tip`` (n, 3) extra junction of leaf clusters (NaN
    elsewhere); ``branches`` lists of cluster indices (Algorithm 3.1), each
    starting at the cluster it leaves (none for the trunk, branch 0);
    ``branch_parent`` / ``branch_order`` per branch; ``n_edges`` of the
    adjacency graph; ``bridged`` number of graph components joined by
    their nearest centres."""

    parent: np.ndarray
    root: int
    junction: np.ndarray
    tip: np.ndarray
    centre: np.ndarray
    branches: List[List[int]]
    branch_parent: np.ndarray
    branch_order: np.ndarray
    n_edges: int
    bridged: int


def branch_structure(xyz: np.ndarray, seg: Segmentation, on_axis: bool = False) -> BranchStructure:
    """Adjacency graph, junctions, shortest-path tree and branches (Yan §3.1–3.3, Alg. 3.1).

    Cluster centres are the point centroids ``c_i`` (§2.2).  With ``on_axis``
    (not in the paper) a fixed cluster is represented by the centre of its
    fitted circle on its axis and its junctions are projected onto that
    axis: a stem scanned from one side, or cut into half rings, then keeps a
    straight skeleton instead of zigzagging along the bark.
    """
    labels, nbr = seg.labels, seg.nbr
    nc = seg.n_clusters
    centre = seg.cylinders["mean"]
    if on_axis:
        centre = np.where(seg.fixed[:, None], seg.cylinders["fit_centre"], centre)
    n, k = nbr.shape
    a = np.repeat(labels, k)
    pi = np.repeat(np.arange(n), k)
    qi = nbr.ravel()
    b = labels[qi]
    cross = (a >= 0) & (b >= 0) & (a != b)
    pi, qi, a, b = pi[cross], qi[cross], a[cross], b[cross]
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    key = lo * nc + hi
    # §3.2 boundary points: p in C_i with a neighbour in C_j, and vice versa
    pts = np.r_[pi, qi]
    kk = np.r_[key, key]
    pk = np.unique(np.stack([kk, pts], axis=1), axis=0)
    ukey, inv = np.unique(pk[:, 0], return_inverse=True)
    cnt = np.bincount(inv).astype(np.float64)
    junc = np.stack([np.bincount(inv, weights=xyz[pk[:, 1], j]) for j in range(3)], axis=1) / cnt[:, None]
    ea, eb = ukey // nc, ukey % nc
    w = np.linalg.norm(junc - centre[ea], axis=1) + np.linalg.norm(junc - centre[eb], axis=1)
    w = np.maximum(w, 1e-9)
    # bridge disconnected parts of the adjacency graph by nearest cluster centres
    present = np.bincount(labels[labels >= 0], minlength=nc) > 0
    G = sparse.coo_matrix((w, (ea, eb)), shape=(nc, nc)).tocsr()
    G = G.maximum(G.T)
    ncomp, comp = csgraph.connected_components(G, directed=False)
    low = int(np.argmin(np.where(labels >= 0, xyz[:, 2], np.inf)))
    root = int(labels[low])
    bridged = 0
    extra_j, extra_a, extra_b = [], [], []
    if ncomp > 1:
        comps = [c for c in range(ncomp) if present[comp == c].any()]
        main = comp[root]
        joined = {main}
        rest = [c for c in comps if c != main]
        while rest:
            inj = np.flatnonzero(np.isin(comp, list(joined)) & present)
            t = cKDTree(centre[inj])
            best = None
            for c in rest:
                mem = np.flatnonzero((comp == c) & present)
                d, i = t.query(centre[mem])
                j = int(np.argmin(d))
                if best is None or d[j] < best[0]:
                    best = (d[j], int(mem[j]), int(inj[i[j]]), c)
            _, u, v, c = best
            extra_a.append(u)
            extra_b.append(v)
            extra_j.append((centre[u] + centre[v]) / 2)
            joined.add(c)
            rest.remove(c)
            bridged += 1
        ea = np.r_[ea, extra_a]
        eb = np.r_[eb, extra_b]
        junc = np.vstack([junc, np.asarray(extra_j).reshape(-1, 3)])
        w = np.r_[w, np.linalg.norm(junc[-bridged:] - centre[extra_a], axis=1) * 2 + 1e-9]
        G = sparse.coo_matrix((w, (ea, eb)), shape=(nc, nc)).tocsr()
        G = G.maximum(G.T)
    dist, pred = csgraph.dijkstra(G, directed=False, indices=root, return_predecessors=True)
    parent = np.where(pred >= 0, pred, -1).astype(np.int64)
    parent[root] = -1
    # junction between each cluster and its parent
    jmap = {}
    for i, (u, v) in enumerate(zip(ea.tolist(), eb.tolist())):
        jmap[(min(u, v), max(u, v))] = i
    junction = np.full((nc, 3), np.nan)
    has_p = np.flatnonzero(parent >= 0)
    for c in has_p.tolist():
        p = int(parent[c])
        junction[c] = junc[jmap[(min(c, p), max(c, p))]]
    if on_axis:   # junctions onto the child's axis
        fx = np.flatnonzero(seg.fixed & (parent >= 0))
        ax = seg.cylinders["axis"][fx]
        off = ((junction[fx] - centre[fx]) * ax).sum(axis=1)
        junction[fx] = centre[fx] + off[:, None] * ax
    reached = np.isfinite(dist)
    nkids = np.bincount(parent[parent >= 0], minlength=nc)
    tip = np.full((nc, 3), np.nan)
    leaf = reached & (nkids == 0) & (np.arange(nc) != root)
    tip[leaf] = 2 * centre[leaf] - junction[leaf]          # symmetric junction (Fig. 4)
    # Algorithm 3.1: longest distance to a leaf, then branches by a FIFO queue
    edge_len = np.zeros(nc)
    edge_len[has_p] = dist[has_p] - dist[parent[has_p]]
    order = np.argsort(dist, kind="stable")
    order = order[reached[order]]
    longest = np.zeros(nc)
    for c in order[::-1].tolist():
        p = int(parent[c])
        if p >= 0:
            longest[p] = max(longest[p], longest[c] + edge_len[c])
    kids: List[list] = [[] for _ in range(nc)]
    for c in order.tolist():
        if parent[c] >= 0:
            kids[int(parent[c])].append(c)
    # root's extra junction: mirror of its junction to the child on the main path
    if kids[root]:
        main_kid = max(kids[root], key=lambda c: (longest[c] + edge_len[c], -c))
        junction[root] = 2 * centre[root] - junction[main_kid]
    else:
        junction[root] = centre[root] - np.array([0, 0, max(seg.cylinders["length"][root] / 2, 0.01)])
        tip[root] = 2 * centre[root] - junction[root]
    selected = np.zeros(nc, dtype=bool)
    branch_of = np.full(nc, -1, dtype=np.int64)
    branches: List[List[int]] = []
    bpar: List[int] = []
    bord: List[int] = []
    queue = deque([root])
    selected[root] = True
    while queue:
        t = queue.popleft()
        free = [c for c in kids[t] if not selected[c]]
        if t == root and not branches:
            chain, c, start_parent, ordr = [root], root, -1, 0
        else:
            if not free:
                continue
            c = max(free, key=lambda x: (longest[x] + edge_len[x], -x))
            selected[c] = True
            chain = [t, c]
            start_parent = int(branch_of[t])
            ordr = bord[start_parent] + 1
        while True:
            nxt = [x for x in kids[c] if not selected[x]]
            if not nxt:
                break
            c = max(nxt, key=lambda x: (longest[x] + edge_len[x], -x))
            selected[c] = True
            chain.append(c)
        b = len(branches)
        branches.append(chain)
        bpar.append(start_parent)
        bord.append(ordr)
        for node in (chain if start_parent < 0 else chain[1:]):
            branch_of[node] = b
        for node in chain:
            if any(not selected[x] for x in kids[node]):
                queue.append(node)
    return BranchStructure(parent, root, junction, tip, centre, branches,
                           np.asarray(bpar, dtype=np.int64), np.asarray(bord, dtype=np.int64),
                           int(len(ukey)), bridged)


# --------------------------------------------------------------------------- §4 model

@dataclass
class DenseModel:
    """Everything Yan's pipeline produces for one tree.

    ``reconstruction`` the :class:`Reconstruction` (skeleton of junctions and
    cluster centres with radii); ``segmentation`` / ``structure`` the §2 / §3
    results; ``curves`` per branch the sampled B-spline centre line (k, 3)
    and ``curve_radii`` (k,) metres; ``cylinders`` the cylinder table of
    :func:`sylva.core.qsm.cylinders_from_curves` (dict of arrays)."""

    reconstruction: Reconstruction
    segmentation: Optional[Segmentation]
    structure: Optional[BranchStructure]
    curves: List[np.ndarray]
    curve_radii: List[np.ndarray]
    branch_parent: np.ndarray
    branch_order: np.ndarray
    cylinders: dict
    #: centre lines and radii of the wood mesh when they differ from ``curves`` (levelset.LevelSetQSM)
    mesh_curves: Optional[List[np.ndarray]] = None
    mesh_radii: Optional[List[np.ndarray]] = None

    def mesh(self, sides: int = 10, cap: bool = True) -> Tuple[np.ndarray, np.ndarray]:
        """Lofted surface of all branches (Yan §4.2, ``n2 = 10`` sides, RMF frames) as (vertices, faces)."""
        from ..geometry import sweep_tube
        vs, fs, off = [], [], 0
        for pts, r in zip(self.curves, self.curve_radii):
            if len(pts) < 2:
                continue
            try:
                v, f = sweep_tube(pts, r, sides=sides, cap=cap)
            except InputError:
                continue
            vs.append(v)
            fs.append(f + off)
            off += len(v)
        if not vs:
            return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
        return np.vstack(vs), np.vstack(fs)


def _vertex_radii(seg: Segmentation, clusters: List[int], radius: str = "bounding") -> np.ndarray:
    """Radius per cluster of a branch: the bounding-cylinder radius of fixed clusters
    (§2.3, §4.2); loose (unfixed) clusters, which hold forks or noise, are
    filled by linear interpolation from the fixed ones along the branch, or,
    on a branch without any fixed cluster, get the mean distance of their
    points to their axis (less inflated by a fork than the enclosing circle).
    ``radius="fit"`` uses the least-squares circle of the projected points
    instead of the enclosing circle (unbiased by noise; not in the paper)."""
    r = seg.cylinders["radius" if radius == "bounding" else "fit_radius"][clusters].astype(float)
    ok = seg.fixed[clusters] & (r > 0)
    if ok.sum() == 0:
        return seg.cylinders["mean_rho"][clusters].astype(float)
    x = np.arange(len(r))
    return np.interp(x, x[ok], r[ok])


def _tube_ratio(pts: np.ndarray, line: np.ndarray, rad: np.ndarray) -> np.ndarray:
    """Distance of each point to a polyline divided by the polyline's radius there."""
    if len(line) < 2:
        return np.linalg.norm(pts - line[0], axis=1) / max(float(rad[0]), 1e-6)
    a, b = line[:-1], line[1:]
    ab = b - a
    t = np.clip(((pts[:, None] - a[None]) * ab[None]).sum(2) / np.maximum((ab * ab).sum(1), 1e-18), 0, 1)
    d = np.linalg.norm(pts[:, None] - (a[None] + t[..., None] * ab[None]), axis=2)
    r = np.maximum(rad[:-1] + t * (rad[1:] - rad[:-1]), 1e-6)
    return (d / r).min(axis=1)


def prune_branches(seg: Segmentation, st: BranchStructure, factor: float = 1.5,
                   radius: str = "bounding") -> BranchStructure:
    """Drop branches that stay inside the tube of an ancestor: patches of a thick stem.

    Not in Yan et al.: small clusters on the surface of a stem wider than
    they are become leaves of the shortest-path tree (§3.2) and so short
    "branches" (Alg. 3.1), sometimes routed through a neighbouring branch.
    A branch is kept when one of its vertices (cluster centres and tip
    junction) lies farther than ``factor`` radii from the centre line of
    every ancestor branch (parent, grandparent, ... trunk), or when it
    carries a kept branch.  Children are examined before parents.
    """
    nb = len(st.branches)
    if nb <= 1:
        return st
    keep = np.ones(nb, dtype=bool)
    has_kept_child = np.zeros(nb, dtype=bool)
    lines, lrad = [], []
    for bi, chain in enumerate(st.branches):
        own = chain if st.branch_parent[bi] < 0 else chain[1:]
        r_own = _vertex_radii(seg, own, radius)
        v = [st.junction[own[0]]] if st.branch_parent[bi] < 0 else [st.centre[chain[0]]]
        v += [st.centre[c] for c in own]
        lines.append(np.asarray(v))
        lrad.append(np.r_[r_own[0], r_own])
    for bi in range(nb - 1, 0, -1):
        if st.branch_parent[bi] < 0:
            continue
        if not has_kept_child[bi]:
            chain = st.branches[bi]
            pts = np.vstack([st.centre[chain[1:]], st.tip[chain[-1]][None]])
            pts = pts[np.all(np.isfinite(pts), axis=1)]
            outside = np.ones(len(pts), dtype=bool)
            a = int(st.branch_parent[bi])
            while a >= 0 and outside.any():
                outside &= _tube_ratio(pts, lines[a], lrad[a]) > factor
                a = int(st.branch_parent[a])
            keep[bi] = bool(outside.any())
        if keep[bi]:
            has_kept_child[int(st.branch_parent[bi])] = True
    if keep.all():
        return st
    new_id = np.cumsum(keep) - 1
    branches = [st.branches[b] for b in range(nb) if keep[b]]
    bpar = np.array([new_id[st.branch_parent[b]] if st.branch_parent[b] >= 0 else -1
                     for b in range(nb) if keep[b]], dtype=np.int64)
    bord = st.branch_order[keep]
    return BranchStructure(st.parent, st.root, st.junction, st.tip, st.centre, branches, bpar, bord,
                           st.n_edges, st.bridged)


def _fit_bspline(pts: np.ndarray, samples: int) -> Tuple[np.ndarray, np.ndarray]:
    """Cubic B-spline through the branch vertices (Yan §4.1, Eq. 2); returns samples and their parameter.

    The curve interpolates the vertices (chord-length parameters).  §4.1
    approximates them with ``n`` control points on uniform knots, ``n`` left
    open; least-squares fits tried here (``m / 1.3`` and ``m / 2`` control
    points for ``m`` vertices) oscillated on the uneven vertex spacing of
    sparse branches, and the radius/axis refit (:func:`sylva.core.qsm.refit_radii`)
    corrects the zigzag of the interpolating curve instead.
    """
    from scipy.interpolate import splev, splprep
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    keep = np.r_[True, seg > 1e-6]
    pts = pts[keep]
    if len(pts) < 2:
        return pts, np.zeros(len(pts))
    u = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))]
    u = u / u[-1]
    kdeg = min(3, len(pts) - 1)
    uu = np.linspace(0, 1, max(2, samples))
    try:
        tck, _ = splprep(pts.T, u=u, k=kdeg, s=0.0)
        return np.stack(splev(uu, tck), axis=1), uu
    except Exception:  # scipy raises for degenerate inputs; fall back to the polyline
        return np.stack([np.interp(uu, u, pts[:, j]) for j in range(3)], axis=1), uu


def _trim_in_parent(v: np.ndarray, rv: np.ndarray, pv: np.ndarray, prv: np.ndarray):
    """Cut the start of a branch that runs inside its parent's tube (not in Yan et al.).

    On a stem much thicker than the clusters, the shortest-path tree (§3.2)
    often reaches a side branch through a second chain of clusters on the
    other side of the bark, parallel to the trunk's own chain; Algorithm 3.1
    then makes that chain the start of the branch, and its cylinders lie
    inside the trunk (doubling its volume).  The branch is made to leave from
    the parent's centre line at its last vertex inside the parent's surface
    (ratio of distance to the parent's centre line over the parent's radius
    there <= 1): that vertex is replaced by its projection on the parent line
    and the vertices before it are dropped.  A branch entirely inside is kept.
    """
    ratio = _tube_ratio(v, pv, prv)
    out = np.flatnonzero(ratio > 1.0)
    if len(out) == 0 or out[0] <= 1:
        return v, rv
    j = int(out[0]) - 1            # last vertex inside before the branch leaves the parent
    if len(pv) < 2:
        foot = pv[0]
    else:
        a, b = pv[:-1], pv[1:]
        ab = b - a
        t = np.clip(((v[j] - a) * ab).sum(1) / np.maximum((ab * ab).sum(1), 1e-18), 0, 1)
        cand = a + t[:, None] * ab
        foot = cand[int(np.argmin(np.linalg.norm(cand - v[j], axis=1)))]
    return np.vstack([foot[None], v[j + 1:]]), np.r_[rv[j + 1], rv[j + 1:]]


def model_branches(seg: Segmentation, st: BranchStructure, samples: int = 30, radius: str = "bounding",
                   trim: bool = True):
    """Yan §4: per branch the skeleton vertices (fork centre, junctions and centres, tip
    junction), a cubic B-spline through them sampled at ``samples`` points, radii
    interpolated linearly from the bounding cylinders.  With ``trim`` a branch's
    vertices inside its parent's tube are cut (:func:`_trim_in_parent`).  Returns
    (curves, radii, vertices, vertex_radii)."""
    curves, radii, verts, vrad = [], [], [], []
    own_r = []
    for bi, chain in enumerate(st.branches):
        own = chain if st.branch_parent[bi] < 0 else chain[1:]
        r_own = _vertex_radii(seg, own, radius)
        pb = int(st.branch_parent[bi])
        if pb >= 0:   # a branch is never thicker than its parent at the fork
            pch = st.branches[pb] if st.branch_parent[pb] < 0 else st.branches[pb][1:]
            j = pch.index(chain[0]) if chain[0] in pch else 0
            r_own = np.minimum(r_own, own_r[pb][min(j, len(own_r[pb]) - 1)])
        own_r.append(r_own)
        v, rv = [], []
        if st.branch_parent[bi] < 0:
            v.append(st.junction[own[0]])
            rv.append(r_own[0])
        else:
            v.append(st.centre[chain[0]])     # leaves from the fork cluster's centre
            rv.append(r_own[0])
        for j, c in enumerate(own):
            if j > 0 or st.branch_parent[bi] >= 0:
                v.append(st.junction[c])
                rv.append(r_own[j] if j == 0 else (r_own[j] + r_own[j - 1]) / 2)
            v.append(st.centre[c])
            rv.append(r_own[j])
        last = own[-1]
        if np.all(np.isfinite(st.tip[last])):
            v.append(st.tip[last])
            rv.append(r_own[-1])
        v = np.asarray(v)
        rv = np.asarray(rv)
        if pb >= 0 and trim and len(v) > 2:
            v, rv = _trim_in_parent(v, rv, verts[pb], vrad[pb])
        verts.append(v)
        vrad.append(rv)
        n_s = max(samples, 2) if len(v) > 2 else 2
        curve, uu = _fit_bspline(v, n_s)
        s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(v, axis=0), axis=1))]
        s = s / s[-1] if s[-1] > 0 else np.linspace(0, 1, len(v))
        curves.append(curve)
        radii.append(np.interp(uu, s, rv) if len(uu) == len(curve) else np.full(len(curve), rv.mean()))
    return curves, radii, verts, vrad


def _outside_earlier_branches(curves, radii, branch_parent, factor: float) -> np.ndarray:
    """Branches to keep after modelling (not in Yan et al.).

    A branch is dropped when every sample of its B-spline curve lies within
    ``factor`` radii (of the final model) of the centre line of an earlier
    branch (its ancestors, and the earlier branches it duplicates: at a fork
    on a thick stem the shortest-path tree of §3.2 often reaches the same limb
    through two or three parallel chains of clusters, each of which Algorithm
    3.1 makes a branch), unless it carries a kept branch.  As
    :func:`prune_branches`, on the fitted curves and radii; children are
    examined before parents.
    """
    nb = len(curves)
    bp = np.asarray(branch_parent, dtype=np.int64)
    keep = np.ones(nb, dtype=bool)
    has_kept_child = np.zeros(nb, dtype=bool)
    # all centre-line segments of all branches, with their branch, end points and radii
    sa, sb, ra, rb, sid = [], [], [], [], []
    for b, (c, r) in enumerate(zip(curves, radii)):
        c, r = np.asarray(c, dtype=np.float64).reshape(-1, 3), np.asarray(r, dtype=np.float64).reshape(-1)
        if len(c) >= 2:
            sa.append(c[:-1]), sb.append(c[1:]), ra.append(r[:-1]), rb.append(r[1:])
            sid.append(np.full(len(c) - 1, b))
        elif len(c) == 1:
            sa.append(c), sb.append(c), ra.append(r[:1]), rb.append(r[:1]), sid.append(np.full(1, b))
    if not sa:
        return keep
    sa, sb, ra, rb, sid = (np.concatenate(x) for x in (sa, sb, ra, rb, sid))
    ab = sb - sa
    ab2 = np.maximum((ab * ab).sum(axis=1), 1e-18)
    # candidates: the segments with the nearest mid-points of each sample (all branches)
    tree = cKDTree((sa + sb) / 2)
    kq = int(min(48, len(sa)))
    for b in range(nb - 1, 0, -1):
        if bp[b] < 0:
            continue
        if not has_kept_child[b]:
            pts = np.asarray(curves[b], dtype=np.float64).reshape(-1, 3)
            if len(pts):
                _, ci = tree.query(pts, k=kq)
                ci = ci.reshape(len(pts), kq)
                ok = (sid[ci] < b) & keep[sid[ci]]
                a0, v = sa[ci], ab[ci]
                t = np.clip(((pts[:, None] - a0) * v).sum(2) / ab2[ci], 0, 1)
                d = np.linalg.norm(pts[:, None] - (a0 + t[..., None] * v), axis=2)
                ratio = np.where(ok, d / np.maximum(ra[ci] + t * (rb[ci] - ra[ci]), 1e-6), np.inf)
                keep[b] = bool((ratio.min(axis=1) > factor).any())
        if keep[b]:
            has_kept_child[int(bp[b])] = True
    return keep


def _keep_branches(st: BranchStructure, cyl: dict, keep: np.ndarray):
    """The branch structure and cylinder table restricted to the kept branches (renumbered;
    a kept branch's parent is always kept)."""
    new_id = np.cumsum(keep) - 1
    nb = len(keep)
    branches = [st.branches[b] for b in range(nb) if keep[b]]
    bpar = np.array([new_id[st.branch_parent[b]] if st.branch_parent[b] >= 0 else -1
                     for b in range(nb) if keep[b]], dtype=np.int64)
    st2 = BranchStructure(st.parent, st.root, st.junction, st.tip, st.centre, branches, bpar,
                          st.branch_order[keep], st.n_edges, st.bridged)
    rows = keep[cyl["branch"]]
    cid = np.full(len(rows), -1, dtype=np.int64)
    cid[rows] = np.arange(int(rows.sum()))
    out = {k: v[rows] for k, v in cyl.items()}
    out["id"] = np.arange(int(rows.sum()), dtype=np.int64)
    par = cyl["parent"][rows]
    out["parent"] = np.where(par >= 0, cid[np.maximum(par, 0)], -1)
    out["branch"] = new_id[cyl["branch"][rows]]
    return st2, out


def _recentre(curves, cyl: dict, shift: np.ndarray, good: np.ndarray, branch_parent):
    """Move each branch's centre line onto the axes of its refitted circles (not in Yan et al.).

    A curve sample moves by the mean offset of the refitted cylinders on either
    side of it (:func:`sylva.core.qsm.refit_radii`); the first sample of a
    branch (its fork on the parent's centre line) stays.  The cylinders are
    rebuilt from the moved curves with their radii.  Branches whose cylinders
    do not match their samples one to one are left as they are.
    """
    from ..qsm import cylinders_from_curves
    new_curves, seg_r = [], []
    for b, c in enumerate(curves):
        idx = np.flatnonzero(cyl["branch"] == b)
        c = np.asarray(c, dtype=np.float64)
        if len(idx) != len(c) - 1 or len(idx) == 0:
            new_curves.append(c)
            seg_r.append(cyl["radius"][idx] if len(idx) == len(c) - 1 else
                         np.full(max(len(c) - 1, 0), cyl["radius"][idx].mean() if len(idx) else 0.0))
            continue
        sh, ok = shift[idx], good[idx].astype(float)
        num = np.zeros((len(c), 3))
        den = np.zeros(len(c))
        for off in (0, 1):      # cylinder i touches samples i and i + 1
            num[off:len(c) - 1 + off] += sh * ok[:, None]
            den[off:len(c) - 1 + off] += ok
        move = num / np.maximum(den, 1)[:, None]
        if branch_parent[b] >= 0:
            move[0] = 0.0
        new_curves.append(c + move)
        seg_r.append(cyl["radius"][idx])
    return new_curves, cylinders_from_curves(new_curves, seg_r, branch_parent, segment_radii=True)


def _inside_parent_radii(cyl: dict, branch_parent) -> dict:
    """Cylinders at the base of a branch that lie inside the parent branch take the radius
    of the branch's first cylinder outside it (not in Yan et al.).

    A branch leaves from the parent's centre line (§4.1, the fork cluster's
    centre); the points nearest its first cylinders are the parent's bark, so
    their refitted radii are the parent's.  Inside = the mid-point within the
    parent's radius of the parent's centre line.
    """
    out = dict(cyl)
    r = np.asarray(cyl["radius"], dtype=np.float64).copy()
    br = cyl["branch"]
    mid = cyl["start"] + cyl["axis"] * (cyl["length"] / 2)[:, None]
    for b, pb in enumerate(np.asarray(branch_parent).tolist()):
        if pb < 0:
            continue
        idx = np.flatnonzero(br == b)
        pidx = np.flatnonzero(br == pb)
        if len(idx) < 2 or len(pidx) == 0:
            continue
        line = np.vstack([cyl["start"][pidx], cyl["start"][pidx[-1]] + cyl["axis"][pidx[-1]] * cyl["length"][pidx[-1]]])
        lr = np.r_[r[pidx], r[pidx[-1]]]
        inside = _tube_ratio(mid[idx], line, lr) <= 1.0
        if not inside[0] or inside.all():
            continue
        first_out = int(np.argmin(inside))         # first cylinder outside the parent
        r[idx[:first_out]] = r[idx[first_out]]
    out["radius"] = r
    return out


def _radii_from_cylinders(cyl: dict, curves, radii, verts, vrad):
    """Per-sample and per-vertex radii of each branch from its (refitted) cylinders:
    a sample between two cylinders gets their mean, an end sample its cylinder's,
    a skeleton vertex the radius of the branch's cylinder with the nearest mid-point."""
    new_r, new_v = [], []
    mid = cyl["start"] + cyl["axis"] * (cyl["length"] / 2)[:, None]
    for b, (c, r, v, rv) in enumerate(zip(curves, radii, verts, vrad)):
        idx = np.flatnonzero(cyl["branch"] == b)
        cr = cyl["radius"][idx]
        if len(idx) == 0:
            new_r.append(r)
            new_v.append(rv)
            continue
        if len(idx) == len(c) - 1:
            new_r.append(np.r_[cr[0], (cr[:-1] + cr[1:]) / 2, cr[-1]])
        else:
            new_r.append(r)
        dd = np.linalg.norm(np.asarray(v)[:, None, :] - mid[idx][None], axis=2)
        new_v.append(cr[np.argmin(dd, axis=1)])
    return new_r, new_v


def _skeleton_from(st: BranchStructure, verts, vrad) -> Skeleton:
    """A Sylva Skeleton from the branch vertex chains (parents before children)."""
    nodes, parent, radius, added = [], [], [], []
    branch_nodes = []
    for bi, (v, rv) in enumerate(zip(verts, vrad)):
        ids = []
        if st.branch_parent[bi] < 0:
            start_parent = -1
            k0 = 0
        else:
            # attach to the nearest node of the parent branch (the fork cluster's centre)
            pb = branch_nodes[st.branch_parent[bi]]
            d = np.linalg.norm(np.asarray([nodes[i] for i in pb]) - v[0], axis=1)
            start_parent = pb[int(np.argmin(d))]
            k0 = 1
        prev = start_parent
        for j in range(k0, len(v)):
            nodes.append(v[j])
            parent.append(prev)
            radius.append(rv[j])
            added.append(j == 0 and st.branch_parent[bi] < 0 or j == len(v) - 1)
            prev = len(nodes) - 1
            ids.append(prev)
        if st.branch_parent[bi] >= 0 and not ids:
            ids = [start_parent]
        branch_nodes.append(([start_parent] if start_parent >= 0 else []) + ids)
    return Skeleton(np.asarray(nodes), np.asarray(parent), np.asarray(radius), np.asarray(added))


# --------------------------------------------------------------------------- dense rule

#: Median distance (m) from a point to its 8th nearest neighbour at or under
#: which a tree counts as densely sampled.  Airborne scans of 20 / 100 / 400
#: pulses/m² (testing.synth) put it at 0.57–0.81 / 0.27–0.41 / 0.14–0.23 m; the
#: TLS trees of ../shared/data/tls at 0.03–0.19 m.
DENSE_SPACING_M = 0.25
#: Share of the points within ``DENSE_LOW_M`` above the tree's lowest point at
#: or above which the lower stem is seen, as from the ground.  Airborne trees
#: of testing.synth (20–400 pulses/m²): at most 2.2 %; the TLS trees: 3.6–25 %.
DENSE_LOW_SHARE = 0.03
DENSE_LOW_M = 2.0
#: A dense scan also needs this many points (too few points carry no branches).
DENSE_MIN_POINTS = 2000
#: Median distance (m) to the k-th (8th) neighbour above which a dense-scan model is
#: flagged ``sparse_scan``: branches thinner than that spacing get guessed radii, and
#: volumes are not to be trusted (TLS tree13 of ../shared/data/tls: 0.19 m; trees 1
#: and 7: 0.06 / 0.03 m).
SPARSE_SPACING_M = 0.1


def is_dense_scan(xyz: np.ndarray, spacing_m: float = DENSE_SPACING_M, low_share: float = DENSE_LOW_SHARE,
                  min_points: int = DENSE_MIN_POINTS) -> bool:
    """True when a tree's points are dense enough for Yan et al.'s branch reconstruction.

    Rule (all three): at least ``min_points`` points; the median distance
    to the 8th nearest neighbour (k = 8 as Yan §2.1) at most ``spacing_m``
    (0.25 m), so the kNN graph follows branches instead of jumping between
    them; and at least ``low_share`` (3 %) of the points within 2 m above
    the lowest point, i.e. the stem and low branches are visible, as in
    terrestrial, mobile or below-canopy scans, rather than a crown surface
    seen from above (airborne scans, even at 400 pulses/m², put < 2.5 %
    there).
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    if len(xyz) < max(min_points, 9):
        return False
    z = xyz[:, 2] - xyz[:, 2].min()
    if float((z < DENSE_LOW_M).mean()) < low_share:
        return False
    sub = xyz
    if len(xyz) > 50_000:  # the median is stable on a sample; keep it deterministic
        sub = xyz[np.random.default_rng(0).choice(len(xyz), 50_000, replace=False)]
    d, _ = cKDTree(xyz).query(sub, k=9, workers=-1)
    return bool(np.median(d[:, 8]) <= spacing_m)


# --------------------------------------------------------------------------- method

@dataclass(frozen=True)
class VariationalKMeans:
    """Yan et al. 2009 on one dense tree: §2 segmentation, §3 branches, §4 B-spline model.

    ``k`` neighbours (§2.1, 8); ``n_seeds`` initial clusters (§2.2 user input;
    0 = one per 250 points, at least 20);
    ``delta_m`` RMS tightness δ of a fixed cluster's bounding cylinder in
    metres (§2.3; the paper's 1e-3..1e-2 of the unit cube); ``max_clusters``
    cluster budget and ``min_cluster_points`` smallest cluster still split
    (§2.4); ``max_iter`` / ``epsilon_rel`` Lloyd stop (§5: 30 iterations,
    ε = 1e-5, here relative to the energy); ``samples`` B-spline samples per
    branch (§5: 30); ``sides`` of the lofted polygon (§4.2: n2 = 10);
    ``min_points`` fewer points give a flagged minimal skeleton;
    ``prune_factor`` drops branches that do not reach farther than this
    many parent radii from the parent's centre line (:func:`prune_branches`,
    not in the paper; 0 keeps all); ``metric`` of region growing on the kNN
    graph (``"hops"`` breadth-first, ``"metres"`` Dijkstra); ``axis``
    ``"pca"`` (§2.3) or ``"normals"`` (surface normals, for thick stems);
    ``radius`` ``"bounding"`` (§2.3 enclosing circle, biased up by noise)
    or ``"fit"`` (least-squares circle, also used for the δ test, and
    skeleton vertices of fixed clusters on their axes, see
    :func:`branch_structure`); ``refit`` replaces the radii of the final
    cylinders by circle fits to the points nearest each
    (:func:`sylva.core.qsm.refit_radii`, not in the paper); ``seed`` of the
    random initial seeds.
    """

    k: int = 8
    n_seeds: int = 0
    delta_m: float = 0.03
    max_clusters: int = 2000
    min_cluster_points: int = 150
    max_iter: int = 30
    epsilon_rel: float = 1e-5
    samples: int = 30
    sides: int = 10
    min_points: int = 50
    prune_factor: float = 1.5
    metric: str = "hops"
    axis: str = "pca"
    radius: str = "bounding"
    refit: bool = False
    seed: int = 0

    name = "variational_kmeans"

    @classmethod
    def dense_scan(cls) -> "VariationalKMeans":
        """The preset measured best on thick, densely scanned stems (``benchmarks/dense.py``): cluster axes
        from surface normals, least-squares circle radii, clusters split down to 30 points, radii and axes
        refitted to the points (Sylva, not in the paper; the paper's own settings are the defaults)."""
        return cls(axis="normals", radius="fit", refit=True, min_cluster_points=30)

    def __post_init__(self):
        if self.k < 2 or self.n_seeds < 0 or self.max_clusters < 1 or self.max_iter < 1:
            raise InputError("VariationalKMeans: k >= 2, n_seeds >= 0, max_clusters >= 1 and max_iter >= 1")
        if not self.delta_m > 0:
            raise InputError(f"VariationalKMeans: delta_m must be > 0 metres, got {self.delta_m!r}")
        if self.samples < 2 or self.sides < 3:
            raise InputError("VariationalKMeans: samples >= 2 and sides >= 3")
        for name, val, allowed in (("metric", self.metric, ("hops", "metres")), ("axis", self.axis, ("pca", "normals")),
                                   ("radius", self.radius, ("bounding", "fit"))):
            if val not in allowed:
                raise InputError(f"VariationalKMeans: {name} must be one of {allowed}, got {val!r}")


    def model(self, tree: TreePoints, progress: Progress = None,
              cancelled: CancelCheck = None) -> DenseModel:
        """Run Yan §2–§4 on one tree; the full :class:`DenseModel`."""
        from ..qsm import cylinders_from_curves, refit_radii, taper_radii
        t_all = time.perf_counter()
        xyz = tree.xyz
        ground_z, flags, rec = screen(tree, self.min_points, self.name, progress)
        stats = {"n_points": int(len(xyz))}
        if rec is not None:
            skel = rec.skeleton
            curves = [skel.nodes] if len(skel) > 1 else []
            radii = [np.zeros(len(skel))] if len(skel) > 1 else []
            return DenseModel(rec, None, None, curves, radii, np.array([-1][:len(curves)]),
                              np.array([0][:len(curves)]), cylinders_from_curves(curves, radii,
                                                                                 np.array([-1][:len(curves)])))
        check(cancelled)
        t0 = time.perf_counter()
        seg = segment(xyz, self.k, self.n_seeds, self.delta_m, self.max_clusters, self.min_cluster_points,
                      self.max_iter, self.epsilon_rel, seed=self.seed, metric=self.metric, axis=self.axis,
                      tightness="fit" if self.radius == "fit" else "bounding",
                      cancelled=cancelled,
                      progress=None if progress is None else (lambda f, m="": report(progress, 0.8 * f, m)))
        stats.update(t_segmentation_s=time.perf_counter() - t0, n_clusters=seg.n_clusters,
                     n_fixed=int(seg.fixed.sum()), rounds=seg.rounds, stop_reason=seg.reason,
                     n_unlabelled=int((seg.labels < 0).sum()))
        check(cancelled)
        t0 = time.perf_counter()
        try:
            st = branch_structure(xyz, seg, on_axis=self.radius == "fit")
            n_raw = len(st.branches)
            if self.prune_factor > 0:
                st = prune_branches(seg, st, self.prune_factor, self.radius)
            stats["n_pruned_branches"] = n_raw - len(st.branches)
        except (ValueError, IndexError) as exc:
            raise SylvaError(f"tree {tree.tree_id}: branch reconstruction failed ({exc})") from None
        stats.update(t_branching_s=time.perf_counter() - t0, n_branches=len(st.branches),
                     n_adjacency_edges=st.n_edges, n_bridged=st.bridged)
        report(progress, 0.9, "branches")
        check(cancelled)
        t0 = time.perf_counter()
        curves, radii, verts, vrad = model_branches(seg, st, self.samples, self.radius)
        cyl = cylinders_from_curves(curves, radii, st.branch_parent)
        if self.refit:
            cyl, refit, shift = refit_radii(xyz, cyl, return_shift=True)
            curves, cyl = _recentre(curves, cyl, shift, np.any(shift != 0, axis=1), st.branch_parent)
            cyl, refit = refit_radii(xyz, cyl)
            cyl = taper_radii(_inside_parent_radii(cyl, st.branch_parent))
            stats["n_refit_cylinders"] = int(refit.sum())
            radii, vrad = _radii_from_cylinders(cyl, curves, radii, verts, vrad)
        if self.prune_factor > 0 and len(curves) > 1:
            keep = _outside_earlier_branches(curves, radii, st.branch_parent, self.prune_factor)
            stats["n_pruned_branches"] = stats.get("n_pruned_branches", 0) + int((~keep).sum())
            if not keep.all():
                st, cyl = _keep_branches(st, cyl, keep)
                curves = [c for c, k in zip(curves, keep) if k]
                radii = [r for r, k in zip(radii, keep) if k]
                verts = [v for v, k in zip(verts, keep) if k]
                vrad = [r for r, k in zip(vrad, keep) if k]
                stats["n_branches"] = len(st.branches)
                if self.refit:   # the points of the dropped branches go to the kept cylinders
                    cyl, refit = refit_radii(xyz, cyl)
                    cyl = taper_radii(_inside_parent_radii(cyl, st.branch_parent))
                    stats["n_refit_cylinders"] = int(refit.sum())
                    radii, vrad = _radii_from_cylinders(cyl, curves, radii, verts, vrad)
        skel = _skeleton_from(st, verts, vrad)
        stats["t_modelling_s"] = time.perf_counter() - t0
        stats["n_nodes"] = int(len(skel))
        if st.bridged:
            flags.append("graph_disconnected")
        if seg.reason == "budget":
            flags.append("cluster_budget_reached")
        spacing = float(np.median(np.linalg.norm(xyz[seg.nbr[:, -1]] - xyz, axis=1))) if len(seg.nbr) else 0.0
        stats["spacing_k_m"] = spacing
        if spacing > SPARSE_SPACING_M:
            # branches thinner than the point spacing: their radii are guesses
            flags.append("sparse_scan")
        if seg.n_clusters and seg.fixed.mean() < 0.25:
            # most clusters are not cylinders within delta (sparse or very noisy
            # points): their radii are loose and volumes are not to be trusted
            flags.append("few_fixed_clusters")
        labelled = float((seg.labels >= 0).mean())
        stats["t_total_s"] = time.perf_counter() - t_all
        report(progress, 1.0, "model")
        rec = Reconstruction(skel, self.name, labelled, st.bridged == 0, stats, flags, tree.tree_id)
        return DenseModel(rec, seg, st, curves, radii, st.branch_parent, st.branch_order, cyl)

    def reconstruct(self, tree: TreePoints, progress: Progress = None,
                    cancelled: CancelCheck = None) -> Reconstruction:
        """Run Yan §2–§4 on one tree; see :func:`sylva.core.reconstruct.reconstruct_tree`."""
        return self.model(tree, progress, cancelled).reconstruction
