"""Variational k-means segmentation: Yan et al. 2009 §2.

The kd-tree kNN graph (§2.1), clusters grown from seeds by a multi-source Dijkstra and refined by Lloyd
iterations on the energy of Eq. 1 (§2.2), a bounding cylinder per cluster and its tightness test (§2.3), and
the splitting of unfixed clusters until every cluster fits (§2.4, :func:`segment`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import List, Optional, Tuple

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from ...groups import group_covariances, group_means
from ...progress import CancelCheck, Progress, check, report


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
    cov, mean, counts = group_covariances(p, lab, n)
    d = p - mean[lab]
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
        cent_all, _ = group_means(xyz[labels >= 0], labels[labels >= 0], nc)
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
