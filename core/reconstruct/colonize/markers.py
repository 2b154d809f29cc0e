"""The markers of guided growth and their weights: Guo et al. 2018 §5.2 (Eq. 6-8) and §6.1.

The PCA weights of the points (Eq. 8), the influence distance of the logistic growth model (Eq. 6-7), the
share of points in the shrunk crown hull and the Poisson-disk-like markers that fill it (§6.1), and the
clusters of low points that seed several roots (§6.1, multiple roots), with the small compiled kernels of
the PCA covariances, the hull test and the "any point within r" test (the kernels are Sylva's).
"""
from __future__ import annotations

from typing import NamedTuple, Optional

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import ConvexHull, QhullError, cKDTree

from ...jit import njit
from ...kernels.buckets import bucket_by_cell


# --------------------------------------------------------------------------- building blocks
def pca_weights(xyz: np.ndarray, radius_m: float, cos_min: float = 0.9, k: int = 10):
    """Guo et al. §5.2, Eq. 8: (weights, principal axes) of every point.

    The principal axis n_i is the eigenvector of the largest eigenvalue of
    the covariance of p_i's ``k`` nearest neighbours; the weight counts the
    points within ``radius_m`` (ε_D) whose axis is within ``cos_min`` (ε_A)
    of n_i in absolute value, p_i itself included (w_i ≥ 1).  Vectorised.
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    n = len(xyz)
    if n == 0:
        return np.zeros(0), np.zeros((0, 3))
    tree = cKDTree(xyz)
    kk = max(1, min(int(k), n))
    _, idx = tree.query(xyz, k=kk)
    cov = _pca_cov_kernel(np.ascontiguousarray(xyz), np.asarray(idx, dtype=np.int64).reshape(n, kk))
    _, vec = np.linalg.eigh(cov)
    axis = vec[:, :, -1]
    pairs = tree.query_pairs(radius_m, output_type="ndarray")
    w = np.ones(n)
    if len(pairs):
        sim = np.abs((axis[pairs[:, 0]] * axis[pairs[:, 1]]).sum(axis=1)) > cos_min
        p = pairs[sim]
        w += np.bincount(p[:, 0], minlength=n) + np.bincount(p[:, 1], minlength=n)
    return w, axis


def influence_distance(t, height_m: float, step_m: float, h0: float = 2.0, rho0: float = 0.3,
                       min_units: float = 4.0, max_units: float = 12.0):
    """Guo et al. §5.2, Eq. 6–7: influence distance d_i = ρ_t · l at iteration ``t`` (metres).

    K = H_max / l internodes (H_max = ``height_m``), H_t = K / (1 + (K/H_0 − 1) e^(−ρ_0 t))
    (Eq. 6), ρ_t = dH_t/dt (Eq. 7), clamped to [min_units, max_units]
    (Pałubicki's d_i ∈ [4l, 12l] quoted by Guo).  Works on arrays of t.
    """
    K = max(float(height_m) / step_m, h0 * 1.0001)
    a = K / h0 - 1.0
    e = a * np.exp(-rho0 * np.asarray(t, dtype=np.float64))
    rho = K * rho0 * e / (1.0 + e) ** 2
    return np.clip(rho, min_units, max_units) * step_m


def _inside_hull(hull: ConvexHull, points: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Per point: inside ``hull`` (its facet half-spaces ``A x + b <= 0``, vectorised)."""
    eq = np.ascontiguousarray(hull.equations, dtype=np.float64)
    p = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    return _inside_hull_kernel(p, eq, float(tol))


def hull_of(xyz: np.ndarray) -> Optional[ConvexHull]:
    """Convex hull of ``xyz``, None when it is flat or has too few points."""
    if len(xyz) < 4:
        return None
    try:
        return ConvexHull(xyz)
    except (QhullError, ValueError):
        return None


def interior_fraction(xyz: np.ndarray, shrink: float = 0.5) -> float:
    """Share of points inside the convex hull shrunk by ``shrink`` about the points' centroid.

    A crown filled uniformly gives ``shrink**3`` (1/8); an airborne crown,
    whose interior is occluded, much less (Guo §6.1's "invisible interior").
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    return interior_fraction_in_hull(xyz, hull_of(xyz), shrink)


def interior_fraction_in_hull(xyz: np.ndarray, hull: Optional[ConvexHull], shrink: float = 0.5) -> float:
    """:func:`interior_fraction` with the hull of ``xyz`` already computed (or None when flat)."""
    if hull is None:
        return 0.0
    c = xyz.mean(axis=0)
    # x is inside the hull shrunk about c  <=>  c + (x - c) / shrink is inside the hull.
    return float(_inside_hull(hull, c + (xyz - c) / shrink).mean())


def crown_fill_markers(xyz: np.ndarray, spacing_m: float, seed: int = 0,
                       max_markers: int = 50_000) -> np.ndarray:
    """Guo et al. §6.1: Poisson-disk-like markers inside the convex hull of ``xyz``.

    A grid of pitch ``spacing_m`` over the hull's bounding box, each cell
    centre jittered uniformly by ±¼ pitch per axis (seeded), so two markers
    are at least ½ pitch apart; kept where the hull's facet half-spaces
    (``ConvexHull.equations``) put them inside and at least ½ pitch from every point of ``xyz``.
    The pitch grows if the box would hold more than ``max_markers`` cells.
    Returns (m, 3); empty when the hull is flat.
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    return crown_fill_markers_in_hull(xyz, hull_of(xyz), spacing_m, seed, max_markers)


def crown_fill_markers_in_hull(xyz: np.ndarray, hull: Optional[ConvexHull], spacing_m: float, seed: int = 0,
                               max_markers: int = 50_000) -> np.ndarray:
    """:func:`crown_fill_markers` with the hull of ``xyz`` already computed (or None when flat)."""
    if hull is None:
        return np.zeros((0, 3))
    v = xyz[hull.vertices]
    lo, hi = v.min(axis=0), v.max(axis=0)
    s = float(spacing_m)
    cells = np.ceil((hi - lo) / s).astype(np.int64) + 1
    if cells.prod() > max_markers:
        s *= (cells.prod() / max_markers) ** (1.0 / 3.0)
        cells = np.ceil((hi - lo) / s).astype(np.int64) + 1
    ii = np.indices(cells).reshape(3, -1).T
    rng = np.random.default_rng([int(seed), 0x6C0])
    cand = lo + ii * s + rng.uniform(-0.25 * s, 0.25 * s, size=ii.shape)
    cand = cand[_inside_hull(hull, cand)]
    if len(cand):
        cand = cand[~near_any_kernel(np.ascontiguousarray(cand), np.ascontiguousarray(xyz), 0.5 * s)]
    return cand


class RootClusters(NamedTuple):
    """Result of :func:`find_root_clusters`."""

    centres: np.ndarray     # (k, 2) xy centroids of the low clusters, k >= 1
    sizes: np.ndarray       # (k,) points per cluster


def find_root_clusters(xyz: np.ndarray, ground_z: float, band_m: float, link_m: float,
                       min_points: int = 5) -> Optional[RootClusters]:
    """Separate clusters of points within ``band_m`` of the ground (Guo §6.1, multiple roots).

    The low points are linked in xy when closer than ``link_m`` (single
    linkage: ``cKDTree.query_pairs`` + connected components); clusters of at
    least ``min_points`` points and 10 % of the low points count.  Returns
    None when there is none.  Clusters are ordered by x, then y.
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    low = xyz[xyz[:, 2] - ground_z < band_m, :2]
    if len(low) < 2 * min_points:
        return None
    pairs = cKDTree(low).query_pairs(link_m, output_type="ndarray")
    m = len(low)
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(m, m)) if len(pairs) \
        else coo_matrix((m, m))
    _, lab = connected_components(g, directed=False)
    sizes = np.bincount(lab)
    keep = np.flatnonzero(sizes >= max(min_points, 0.1 * m))
    if len(keep) < 1:
        return None
    cx = np.bincount(lab, weights=low[:, 0])[keep] / sizes[keep]
    cy = np.bincount(lab, weights=low[:, 1])[keep] / sizes[keep]
    order = np.lexsort((cy, cx))
    return RootClusters(np.stack([cx, cy], axis=1)[order], sizes[keep][order])


# --------------------------------------------------------------------------- compiled kernels
@njit
def _inside_hull_kernel(points, eq, tol):
    """Per point: inside the hull (``eq`` rows a·x + b <= tol), stopping at the first facet outside.

    Same arithmetic as numpy's einsum formulation, which sums a 3-vector dot
    product as (a0 x + a2 z) + a1 y, then + b: identical booleans; Sylva, not in the paper (a speed-up of the §6.1 hull test).
    """
    n = points.shape[0]
    f = eq.shape[0]
    out = np.ones(n, dtype=np.bool_)
    for i in range(n):
        x = points[i, 0]
        y = points[i, 1]
        z = points[i, 2]
        for j in range(f):
            s = (x * eq[j, 0] + z * eq[j, 2]) + y * eq[j, 1]
            if not s + eq[j, 3] <= tol:
                out[i] = False
                break
    return out


@njit
def _pca_cov_kernel(xyz, idx):
    """Covariance of every point's neighbourhood ``xyz[idx[i]]`` (Guo et al. §5.2, Eq. 8's PCA).

    Centred on the neighbourhood mean and divided by k; sums run over the
    neighbours in the order of ``idx`` (as numpy's mean and einsum do), so the
    matrices are those of numpy's mean/einsum on the gathered neighbourhoods
    (tests/test_colonize_kernel.py; Sylva, not in the paper).
    """
    n, k = idx.shape
    cov = np.empty((n, 3, 3))
    c = np.empty((k, 3))
    for p in range(n):
        m0 = 0.0
        m1 = 0.0
        m2 = 0.0
        for q in range(k):
            j = idx[p, q]
            m0 += xyz[j, 0]
            m1 += xyz[j, 1]
            m2 += xyz[j, 2]
        m0 = m0 / k
        m1 = m1 / k
        m2 = m2 / k
        for q in range(k):
            j = idx[p, q]
            c[q, 0] = xyz[j, 0] - m0
            c[q, 1] = xyz[j, 1] - m1
            c[q, 2] = xyz[j, 2] - m2
        for a in range(3):
            for b in range(3):
                s = 0.0
                for q in range(k):
                    s += c[q, a] * c[q, b]
                cov[p, a, b] = s / k
    return cov


@njit
def near_any_kernel(points, centres, r):
    """Per point: is a centre closer than ``r`` (d² < r², the test of ``cKDTree.query``'s
    ``distance_upper_bound``)?  A uniform grid of cell r over the centres (Sylva, not in the paper)."""
    n = points.shape[0]
    mc = centres.shape[0]
    out = np.zeros(n, dtype=np.bool_)
    if n == 0 or mc == 0:
        return out
    lo0 = centres[0, 0]
    lo1 = centres[0, 1]
    lo2 = centres[0, 2]
    hi0 = lo0
    hi1 = lo1
    hi2 = lo2
    for i in range(mc):
        lo0 = min(lo0, centres[i, 0])
        lo1 = min(lo1, centres[i, 1])
        lo2 = min(lo2, centres[i, 2])
        hi0 = max(hi0, centres[i, 0])
        hi1 = max(hi1, centres[i, 1])
        hi2 = max(hi2, centres[i, 2])
    cs = r
    while True:
        gx = int((hi0 - lo0) / cs) + 1
        gy = int((hi1 - lo1) / cs) + 1
        gz = int((hi2 - lo2) / cs) + 1
        if gx * gy * gz <= 4 * mc + 4096:
            break
        cs *= 1.5
    ncell = gx * gy * gz
    cell = np.empty(mc, dtype=np.int64)
    for i in range(mc):
        cx = min(max(int(np.floor((centres[i, 0] - lo0) / cs)), 0), gx - 1)
        cy = min(max(int(np.floor((centres[i, 1] - lo1) / cs)), 0), gy - 1)
        cz = min(max(int(np.floor((centres[i, 2] - lo2) / cs)), 0), gz - 1)
        cell[i] = (cx * gy + cy) * gz + cz
    start, order = bucket_by_cell(cell, ncell)
    r2 = r * r
    for p in range(n):
        px = points[p, 0]
        py = points[p, 1]
        pz = points[p, 2]
        cx = min(max(int(np.floor((px - lo0) / cs)), 0), gx - 1)
        cy = min(max(int(np.floor((py - lo1) / cs)), 0), gy - 1)
        cz = min(max(int(np.floor((pz - lo2) / cs)), 0), gz - 1)
        found = False
        for ix in range(max(cx - 1, 0), min(cx + 2, gx)):
            for iy in range(max(cy - 1, 0), min(cy + 2, gy)):
                for iz in range(max(cz - 1, 0), min(cz + 2, gz)):
                    c = (ix * gy + iy) * gz + iz
                    for s in range(start[c], start[c + 1]):
                        i = order[s]
                        dx = px - centres[i, 0]
                        dy = py - centres[i, 1]
                        dz = pz - centres[i, 2]
                        if dx * dx + dy * dy + dz * dz < r2:
                            found = True
                            break
                    if found:
                        break
                if found:
                    break
            if found:
                break
        out[p] = found
    return out
