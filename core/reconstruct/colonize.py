"""Point-cloud-guided growth (Guo et al. 2018, §5.2 and §6.1): the :class:`GuidedGrowth` method.

Space colonisation (Runions et al. 2007; Pałubicki et al. 2009) grows a
skeleton from a seed towards *markers*; Guo et al. make the tree's own points
the markers and adapt it in three ways (§5.2), all implemented here:

1. **Markers = points, weighted (Eq. 8).**  Every point p_i gets the principal
   axis n_i of its local covariance (PCA over its ``pca_k`` nearest
   neighbours, one batched ``numpy.linalg.eigh``), and the weight
   w_i = #{p_j : ‖p_i − p_j‖ < ε_D, |n_i · n_j| > ε_A} (itself included, so
   w_i ≥ 1).  Branch-like (linear) neighbourhoods get large weights, leaf
   clutter small ones.  Principal axes have no sign, hence |·|.
2. **Influence distance from a logistic model (Eq. 6–7).**  With
   K = H_max / l internodes from the root to the top (H_max the tree's
   height above ground, l = ``step_m``), Eq. 6
   H_t = K / (1 + (K/H_0 − 1) e^(−ρ_0 t)) and its derivative Eq. 7 give the
   growth units ρ_t (internodes per iteration t), and d_i = ρ_t · l.  The
   paper quotes Pałubicki's typical range d_i ∈ [4l, 12l]; Sylva clamps ρ_t
   to [``influence_min_units``, ``influence_max_units``] = [4, 12] so that
   early iterations still perceive markers.  H_0 = 2 and ρ_0 = 0.3 are the
   paper's defaults.
3. **Growth direction (Eq. 9).**  V_A = V_default + α V_opt + β V_tropism,
   V_opt = Σ w_i V_i / Σ w_i over the unit vectors V_i from the bud to its
   markers, α = 1.6, β = 0.3, V_tropism = (0, 0, −1) (the paper's (0, −1, 0)
   with y up).  A growing bud produces one growth unit (L-system 1, rule 2:
   a shoot of metamers along V_A/‖V_A‖): ⌊ρ_t⌋ internodes of length l at
   most, and no more than reach the weighted centroid of its markers (the
   growing distance of Pałubicki et al., quoted in §5.2).  Every new node
   is a metamer with its own buds.

Buds and perception (§5.2, L-system 1).  Every node carries buds: a tip its
apical bud (V_default = its heading, perception cone of half-angle θ/2,
θ = ``perception_angle_deg`` = 90°), a node that already has its apical child
one lateral bud (L-system rule 3: one lateral bud per metamer) whose
direction leaves the heading at the branching angle ψ (Table 2: 34–41°,
``branching_angle_deg`` = 38°).  The roll angle φ would fix the azimuth of
each lateral bud; since the points tell where branches are, Sylva turns the
lateral bud towards its markers (the component of V_opt across the heading)
and uses φ (``roll_angle_deg``) only when the markers give no azimuth.  The
union of the cones of lateral buds rolled around the axis is a cone of
half-angle ψ + θ/2, the lateral perception cone.  Seeds (roots, added trunk
nodes) perceive with the lateral cone from the start.  A node grows at most
one apical and one lateral child; nodes without free buds leave the bud set,
and so do buds with no marker left within the largest d_i (checked every 8
iterations).

Each iteration: every active marker is assigned to the nearest of its
k = 8 nearest buds within d_i that perceives it (the markers with a bud
within d_i form the growth front), per-bud direction sums are accumulated
in marker order, every bud with markers grows, and markers within the
kill distance d_k (``kill_distance_m``; Pałubicki: d_k = 0.5 d_i, i.e. 2l at
d_i = 4l) of a new node are removed.  When no bud perceives any marker, the
stem's apical bud (the tip of the chain of apical children from the root)
keeps growing upward — L-system rule 2 without V_opt; a stem is
orthotropic, so its heading turns halfway to the vertical per unit instead
of following the tropism — while it is below the highest marker left: this
bridges an unscanned stretch of stem between the added trunk and the crown.
Otherwise d_i is widened (×1.5 per iteration, up to 12l).  Growth stops
when no marker is left, after ``max_iterations``, or after 6 iterations
without growth; flags ``"stalled"`` / ``"max_iterations"`` are set only when
measured points are left unreached.

Implementation (Sylva, not in the paper).  The iterations are sequential, so
they run in one compiled kernel (:func:`_grow_kernel`, numba through
:mod:`sylva.core.jit`; plain Python without numba), 16 iterations per call
between progress reports and cancel checks; uniform grids replace the
per-iteration ``cKDTree`` of the buds and the kill/retirement queries.  The
kernel does the numpy formulation's arithmetic in the same order (including
einsum's (x₀y₀ + x₂y₂) + x₁y₁ for 3-vector dot products), so skeletons are
bit-identical to it; the one difference is the order of *exactly*
equidistant buds (e.g. two coincident nodes), which ``cKDTree`` leaves to its
heap and the kernel breaks by node index.  The PCA covariances, the hull
test and the "any point within r" tests are small kernels as well, and the
crown's convex hull is computed once for the interior test and the fill.

Crown filling (§6.1).  Airborne scans see the crown's top surface and little
of its interior.  When fewer than ``interior_min_fraction`` of the points lie
in the crown hull shrunk to half its size about the centroid (a uniformly
filled crown puts 1/8 there), Sylva adds Poisson-disk markers inside the
convex hull of the crown (points above the 5th height percentile):
a jittered grid of pitch ``fill_spacing_m`` (jitter ±¼ pitch, so any two
markers are at least half a pitch apart — the grid approximation of
Poisson-disk dart throwing), kept where the hull's facet half-spaces
(``ConvexHull.equations``) say inside and at least half a pitch from every
measured point.  Their weight is ``fill_weight`` × the median point weight (0.5: the paper gives
none; measured points dominate where both are perceived).

Root (§5.3 and §6.1).  Points within ``root_band_m`` of the ground are
clustered in xy (single linkage at ``root_link_m``; clusters of at least
``root_min_points`` points and 10 % of the low points count).

* No such cluster (the airborne case: nothing seen under the crown): the
  root and the trunk up to the crown come from Hu et al. 2017 §4.2 (Eq. 3/4,
  :func:`~.trunk.add_trunk_points`); the trunk points, one internode apart,
  become the first nodes (``is_added``).  When Eq. 3 applies (the lowest
  point v_low is on the stem), Sylva drops the trunk vertically from v_low
  rather than along n_avg: n_avg, the mean direction to v_low's few
  neighbours, is noisy, and extrapolating it over v_low's height put the
  root up to 2 m off the stem on synthetic stands.
* One cluster: the points reach the ground, and the root is put on the
  ground under the cluster's centroid (Guo §5.3 puts the root at the
  centroid of the densest cluster of projected points).
* Two or more (multi-stem shrubs, Guo §6.1, Fig. 9: "the top k cluster
  centroids", one seed each, competing for the points): every cluster gets
  a seed on the ground under its centroid and, since a :class:`Skeleton` has
  one root, the seeds hang from a virtual root on the ground under their
  size-weighted mean (``is_added``, no buds of its own; flag
  ``"multi_root"``).  ``multi_root=False`` falls back to the first rule.

Sylva parameters not in the paper are named and documented on
:class:`GuidedGrowth`; every result is deterministic (the only random draw,
the crown-filling jitter, uses ``numpy.random.default_rng(seed)``).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, fields
from typing import NamedTuple, Optional

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import ConvexHull, QhullError, cKDTree

from ..errors import InputError
from ..jit import njit
from ..kernels.buckets import bucket_by_cell
from ..progress import CancelCheck, Progress, check, report
from .model import Reconstruction, Skeleton, TreePoints, screen
from .trunk import add_trunk_points

__all__ = ["GuidedGrowth", "SPECIES_PRESETS", "pca_weights", "influence_distance",
           "crown_fill_markers", "interior_fraction", "find_root_clusters"]

#: Species parameter sets (Guo et al. §5.1: parameters "pre-generated ... in a species
#: library").  The paper's Table 2 measures broadleaved plants only (ψ 34–41°,
#: φ 87–130°); the conifer and shrub sets are Sylva's: conifer branches leave the stem
#: nearly horizontally (ψ 70°) and droop (stronger tropism); shrubs have short
#: internodes, narrow branching and several stems from the ground.  A preset
#: overrides a field only where the field still has its default value.
SPECIES_PRESETS = {
    "conifer": dict(branching_angle_deg=70.0, roll_angle_deg=137.5, tropism=0.5),
    "broadleaf": dict(branching_angle_deg=38.0, roll_angle_deg=105.0, tropism=0.3),
    "shrub": dict(step_m=0.15, kill_distance_m=0.3, branching_angle_deg=30.0,
                  roll_angle_deg=95.0, tropism=0.2, root_band_m=0.6, root_link_m=0.5),
}

_UP = np.array([0.0, 0.0, 1.0])
_DOWN = np.array([0.0, 0.0, -1.0])
_K_BUDS = 8          # nearest buds examined per marker for the perception test
_STALL_LIMIT = 6     # consecutive iterations without growth (d_i widened x1.5 each) before stopping


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


def _hull(xyz: np.ndarray) -> Optional[ConvexHull]:
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
    return _interior_fraction(xyz, _hull(xyz), shrink)


def _interior_fraction(xyz: np.ndarray, hull: Optional[ConvexHull], shrink: float = 0.5) -> float:
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
    return _crown_fill_markers(xyz, _hull(xyz), spacing_m, seed, max_markers)


def _crown_fill_markers(xyz: np.ndarray, hull: Optional[ConvexHull], spacing_m: float, seed: int = 0,
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
        cand = cand[~_near_any_kernel(np.ascontiguousarray(cand), np.ascontiguousarray(xyz), 0.5 * s)]
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


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(n > 1e-12, v / np.maximum(n, 1e-12), 0.0)


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
    matrices are identical to the numpy formulation (Sylva, not in the paper).
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
def _near_any_kernel(points, centres, r):
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


@njit
def _grow_kernel(markers, weight, active, pos, heading, parent, n_children, seed, bud_free, added,
                 leader, m, stall, boost, it_lo, it_hi, di_of_t, cos_tab, sin_tab, l, dk,
                 cos_apical, cos_lateral, cos_psi, sin_psi, alpha, beta, di_max, node_limit):
    """Iterations ``it_lo`` .. ``it_hi - 1`` of the guided growth (Guo et al. §5.2, Eq. 6-9).

    The sequential loop of :meth:`GuidedGrowth._grow`, compiled: per iteration
    every active marker finds its ``_K_BUDS`` nearest free buds within d_i
    (a uniform grid of cell d_i over the buds replaces the per-iteration
    ``cKDTree``; same strict ``d² < d_i²`` test and the same distance order)
    and goes to the first that perceives it (apical cone θ/2 for tips, lateral
    cone ψ + θ/2 otherwise); buds with markers grow one growth unit along
    V_A of Eq. 9; markers within d_k of a new node are killed; the stem's
    apical bud bridges gaps; buds with no marker within 12l are retired every
    8 iterations.  The arithmetic is written in the same order as the numpy
    formulation it replaces, so the skeleton is bit-identical (Sylva, not
    in the paper: an implementation detail).

    Node arrays are grown here when full and returned.  ``code``: 0 ran to
    ``it_hi``; 1 no marker left; 2 node limit; 3 no free bud; 4 stalled; 5 the
    roll-angle tables ``cos_tab``/``sin_tab`` are too short (nothing of
    iteration ``it`` was changed: enlarge them and call again from ``it``).
    """
    n = markers.shape[0]
    cap = pos.shape[0]
    # Static grid over the markers (for the kill and retirement searches).
    lo0 = markers[0, 0]
    lo1 = markers[0, 1]
    lo2 = markers[0, 2]
    hi0 = lo0
    hi1 = lo1
    hi2 = lo2
    for i in range(n):
        lo0 = min(lo0, markers[i, 0])
        lo1 = min(lo1, markers[i, 1])
        lo2 = min(lo2, markers[i, 2])
        hi0 = max(hi0, markers[i, 0])
        hi1 = max(hi1, markers[i, 1])
        hi2 = max(hi2, markers[i, 2])
    gs = max(dk, di_max / 4.0)
    while True:
        gx = int((hi0 - lo0) / gs) + 1
        gy = int((hi1 - lo1) / gs) + 1
        gz = int((hi2 - lo2) / gs) + 1
        if gx * gy * gz <= 4 * n + 4096:
            break
        gs *= 1.5
    ncell = gx * gy * gz
    mcell = np.empty(n, dtype=np.int64)
    mstart = np.zeros(ncell + 1, dtype=np.int64)
    for i in range(n):
        cx = min(max(int(np.floor((markers[i, 0] - lo0) / gs)), 0), gx - 1)
        cy = min(max(int(np.floor((markers[i, 1] - lo1) / gs)), 0), gy - 1)
        cz = min(max(int(np.floor((markers[i, 2] - lo2) / gs)), 0), gz - 1)
        c = (cx * gy + cy) * gz + cz
        mcell[i] = c
        mstart[c + 1] += 1
    for c in range(ncell):
        mstart[c + 1] += mstart[c]
    mfill = mstart[:-1].copy()
    morder = np.empty(n, dtype=np.int64)
    for i in range(n):
        c = mcell[i]
        morder[mfill[c]] = i
        mfill[c] += 1
    rk = int(np.ceil(dk / gs))
    rp = int(np.ceil(di_max / gs))
    dk2 = dk * dk
    dimax2 = di_max * di_max

    am = np.empty(n, dtype=np.int64)
    front = np.zeros(n, dtype=np.bool_)
    sel = np.empty(n, dtype=np.int64)
    selu = np.empty((n, 3))
    kb = _K_BUDS
    bd2 = np.empty(kb)
    bid = np.empty(kb, dtype=np.int64)

    code = 0
    it = it_lo
    while it < it_hi:
        n_act = 0
        for i in range(n):
            if active[i]:
                am[n_act] = i
                n_act += 1
        if n_act == 0:
            code = 1
            break
        if m > node_limit:
            code = 2
            break
        buds = np.empty(m, dtype=np.int64)
        nb = 0
        for j in range(m):
            if bud_free[j]:
                buds[nb] = j
                nb += 1
        if nb == 0:
            code = 3
            break
        di0 = di_of_t[it - 1]
        rho_units = di0 / l
        di = min(di0 * boost, di_max)
        di2 = di * di
        # Grid of cell >= d_i over the buds (clamped to the markers' box: still exact).
        bs = di
        while True:
            bx = int((hi0 - lo0) / bs) + 1
            by = int((hi1 - lo1) / bs) + 1
            bz = int((hi2 - lo2) / bs) + 1
            if bx * by * bz <= 4 * n + 4096:
                break
            bs *= 1.5
        nbc = bx * by * bz
        bstart = np.zeros(nbc + 1, dtype=np.int64)
        bcell = np.empty(nb, dtype=np.int64)
        for q in range(nb):
            j = buds[q]
            cx = min(max(int(np.floor((pos[j, 0] - lo0) / bs)), 0), bx - 1)
            cy = min(max(int(np.floor((pos[j, 1] - lo1) / bs)), 0), by - 1)
            cz = min(max(int(np.floor((pos[j, 2] - lo2) / bs)), 0), bz - 1)
            c = (cx * by + cy) * bz + cz
            bcell[q] = c
            bstart[c + 1] += 1
        for c in range(nbc):
            bstart[c + 1] += bstart[c]
        bfill = bstart[:-1].copy()
        border = np.empty(nb, dtype=np.int64)
        for q in range(nb):
            c = bcell[q]
            border[bfill[c]] = buds[q]
            bfill[c] += 1

        any_has = False
        for q in range(n_act):
            i = am[q]
            px = markers[i, 0]
            py = markers[i, 1]
            pz = markers[i, 2]
            cx = min(max(int(np.floor((px - lo0) / bs)), 0), bx - 1)
            cy = min(max(int(np.floor((py - lo1) / bs)), 0), by - 1)
            cz = min(max(int(np.floor((pz - lo2) / bs)), 0), bz - 1)
            cnt = 0
            for ix in range(max(cx - 1, 0), min(cx + 2, bx)):
                for iy in range(max(cy - 1, 0), min(cy + 2, by)):
                    for iz in range(max(cz - 1, 0), min(cz + 2, bz)):
                        c = (ix * by + iy) * bz + iz
                        for s in range(bstart[c], bstart[c + 1]):
                            j = border[s]
                            dx = px - pos[j, 0]
                            dy = py - pos[j, 1]
                            dz = pz - pos[j, 2]
                            d2 = dx * dx + dy * dy + dz * dz
                            if not d2 < di2:
                                continue
                            if cnt == kb and not d2 < bd2[kb - 1]:
                                continue
                            r = cnt if cnt < kb else kb - 1
                            while r > 0 and (d2 < bd2[r - 1] or (d2 == bd2[r - 1] and j < bid[r - 1])):
                                bd2[r] = bd2[r - 1]
                                bid[r] = bid[r - 1]
                                r -= 1
                            bd2[r] = d2
                            bid[r] = j
                            if cnt < kb:
                                cnt += 1
            front[i] = cnt > 0
            sel[q] = -1
            for r in range(cnt):
                j = bid[r]
                vx = px - pos[j, 0]
                vy = py - pos[j, 1]
                vz = pz - pos[j, 2]
                nrm = np.sqrt((vx * vx + vz * vz) + vy * vy)       # einsum's order
                den = max(nrm, 1e-12)
                ux = vx / den
                uy = vy / den
                uz = vz / den
                cmin = cos_apical if (n_children[j] == 0 and not seed[j]) else cos_lateral
                if nrm > 1e-9 and (ux * heading[j, 0] + uz * heading[j, 2]) + uy * heading[j, 1] > cmin:
                    sel[q] = j
                    selu[q, 0] = ux
                    selu[q, 1] = uy
                    selu[q, 2] = uz
                    any_has = True
                    break

        if not any_has:
            # No bud perceives a marker: the stem's apical bud bridges (L-system 1, rule 2).
            zmax = markers[am[0], 2]
            for q in range(n_act):
                zmax = max(zmax, markers[am[q], 2])
            tips = np.empty(m, dtype=np.int64)
            nt = 0
            for j in range(m):
                if leader[j] and n_children[j] == 0 and bud_free[j] and pos[j, 2] < zmax:
                    tips[nt] = j
                    nt += 1
            if nt > 0 and boost == 1.0:
                ku = max(1, int(rho_units))
                need = m + nt * ku
                if need > cap:
                    cap = max(need, 2 * cap)
                    p2 = np.zeros((cap, 3)); p2[:m] = pos[:m]; pos = p2
                    h2 = np.zeros((cap, 3)); h2[:m] = heading[:m]; heading = h2
                    a2 = np.full(cap, -1, dtype=np.int64); a2[:m] = parent[:m]; parent = a2
                    c2 = np.zeros(cap, dtype=np.int64); c2[:m] = n_children[:m]; n_children = c2
                    s2 = np.zeros(cap, dtype=np.bool_); s2[:m] = seed[:m]; seed = s2
                    f2 = np.zeros(cap, dtype=np.bool_); f2[:m] = bud_free[:m]; bud_free = f2
                    d2a = np.zeros(cap, dtype=np.bool_); d2a[:m] = added[:m]; added = d2a
                    e2 = np.zeros(cap, dtype=np.bool_); e2[:m] = leader[:m]; leader = e2
                first_new = m
                for t in range(nt):
                    j = tips[t]
                    hx = heading[j, 0] + 0.0
                    hy = heading[j, 1] + 0.0
                    hz = heading[j, 2] + 1.0
                    hn = np.sqrt(hx * hx + hy * hy + hz * hz)
                    if hn > 1e-12:
                        hd = max(hn, 1e-12)
                        hx = hx / hd
                        hy = hy / hd
                        hz = hz / hd
                    else:
                        hx = 0.0
                        hy = 0.0
                        hz = 0.0
                    prev = j
                    for k in range(1, ku + 1):
                        step = l * k
                        pos[m, 0] = pos[j, 0] + step * hx
                        pos[m, 1] = pos[j, 1] + step * hy
                        pos[m, 2] = pos[j, 2] + step * hz
                        heading[m, 0] = hx
                        heading[m, 1] = hy
                        heading[m, 2] = hz
                        parent[m] = prev
                        n_children[m] = 0
                        n_children[prev] += 1
                        seed[m] = True
                        added[m] = True
                        bud_free[m] = True
                        leader[m] = True
                        prev = m
                        m += 1
                    bud_free[j] = True
                for q in range(first_new, m):
                    cx = min(max(int(np.floor((pos[q, 0] - lo0) / gs)), 0), gx - 1)
                    cy = min(max(int(np.floor((pos[q, 1] - lo1) / gs)), 0), gy - 1)
                    cz = min(max(int(np.floor((pos[q, 2] - lo2) / gs)), 0), gz - 1)
                    for ix in range(max(cx - rk, 0), min(cx + rk + 1, gx)):
                        for iy in range(max(cy - rk, 0), min(cy + rk + 1, gy)):
                            for iz in range(max(cz - rk, 0), min(cz + rk + 1, gz)):
                                c = (ix * gy + iy) * gz + iz
                                for s in range(mstart[c], mstart[c + 1]):
                                    i = morder[s]
                                    if active[i]:
                                        dx = markers[i, 0] - pos[q, 0]
                                        dy = markers[i, 1] - pos[q, 1]
                                        dz = markers[i, 2] - pos[q, 2]
                                        if dx * dx + dy * dy + dz * dz < dk2:
                                            active[i] = False
                it += 1
                continue
            stall += 1
            if stall >= _STALL_LIMIT:
                code = 4
                break
            boost *= 1.5
            it += 1
            continue

        # Growth (Eq. 9 and one growth unit per growing bud).  Nothing is changed
        # before the new nodes are added, so code 5 can return cleanly.
        sums = np.zeros((m, 3))
        csum = np.zeros((m, 3))
        wsum = np.zeros(m)
        for q in range(n_act):
            j = sel[q]
            if j < 0:
                continue
            i = am[q]
            w = weight[i]
            sums[j, 0] += w * selu[q, 0]
            sums[j, 1] += w * selu[q, 1]
            sums[j, 2] += w * selu[q, 2]
            wsum[j] += w
            csum[j, 0] += w * markers[i, 0]
            csum[j, 1] += w * markers[i, 1]
            csum[j, 2] += w * markers[i, 2]
        grow = np.empty(m, dtype=np.int64)
        ng = 0
        for j in range(m):
            if wsum[j] > 0:
                grow[ng] = j
                ng += 1
        vnew = np.empty((ng, 3))
        units = np.empty(ng, dtype=np.int64)
        tipg = np.empty(ng, dtype=np.bool_)
        maxu = max(1, int(rho_units))
        short = False
        for g in range(ng):
            j = grow[g]
            ws = wsum[j]
            o0 = sums[j, 0] / ws
            o1 = sums[j, 1] / ws
            o2 = sums[j, 2] / ws
            h0 = heading[j, 0]
            h1 = heading[j, 1]
            h2 = heading[j, 2]
            is_tip = n_children[j] == 0
            tipg[g] = is_tip
            dd = o0 * h0 + o1 * h1 + o2 * h2
            a0 = o0 - dd * h0
            a1 = o1 - dd * h1
            a2 = o2 - dd * h2
            if np.sqrt(a0 * a0 + a1 * a1 + a2 * a2) < 1e-6:
                # No azimuth from the markers: the roll angle φ (Table 2).
                if abs(h2) < 0.9:
                    r0 = 0.0
                    r1 = 0.0
                    r2 = 1.0
                else:
                    r0 = 1.0
                    r1 = 0.0
                    r2 = 0.0
                e0 = h1 * r2 - h2 * r1
                e1 = h2 * r0 - h0 * r2
                e2 = h0 * r1 - h1 * r0
                en = np.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
                if en > 1e-12:
                    ed = max(en, 1e-12)
                    e0 = e0 / ed
                    e1 = e1 / ed
                    e2 = e2 / ed
                else:
                    e0 = 0.0
                    e1 = 0.0
                    e2 = 0.0
                f0 = h1 * e2 - h2 * e1
                f1 = h2 * e0 - h0 * e2
                f2 = h0 * e1 - h1 * e0
                ia = j + n_children[j]
                if ia >= cos_tab.shape[0]:
                    short = True
                    break
                ca = cos_tab[ia]
                sa = sin_tab[ia]
                a0 = ca * e0 + sa * f0
                a1 = ca * e1 + sa * f1
                a2 = ca * e2 + sa * f2
            an = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
            if an > 1e-12:
                ad = max(an, 1e-12)
                a0 = a0 / ad
                a1 = a1 / ad
                a2 = a2 / ad
            else:
                a0 = 0.0
                a1 = 0.0
                a2 = 0.0
            if is_tip:
                d0 = h0
                d1 = h1
                d2_ = h2
            else:
                d0 = cos_psi * h0 + sin_psi * a0
                d1 = cos_psi * h1 + sin_psi * a1
                d2_ = cos_psi * h2 + sin_psi * a2
            v0 = d0 + alpha * o0 + beta * 0.0
            v1 = d1 + alpha * o1 + beta * 0.0
            v2 = d2_ + alpha * o2 + beta * -1.0
            vn = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
            if vn > 1e-9:
                vd = max(vn, 1e-12)
                v0 = v0 / vd
                v1 = v1 / vd
                v2 = v2 / vd
            else:
                v0 = d0
                v1 = d1
                v2 = d2_
            vnew[g, 0] = v0
            vnew[g, 1] = v1
            vnew[g, 2] = v2
            c0 = csum[j, 0] / ws - pos[j, 0]
            c1 = csum[j, 1] / ws - pos[j, 1]
            c2 = csum[j, 2] / ws - pos[j, 2]
            reach = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
            u = np.rint(reach / l)
            if u < 1.0:
                u = 1.0
            if u > maxu:
                u = float(maxu)
            units[g] = int(u)
        if short:
            code = 5
            break
        stall = 0
        boost = 1.0
        total = 0
        umax = 0
        for g in range(ng):
            total += units[g]
            umax = max(umax, units[g])
        need = m + total
        if need > cap:
            cap = max(need, 2 * cap)
            p2 = np.zeros((cap, 3)); p2[:m] = pos[:m]; pos = p2
            h2a = np.zeros((cap, 3)); h2a[:m] = heading[:m]; heading = h2a
            a2a = np.full(cap, -1, dtype=np.int64); a2a[:m] = parent[:m]; parent = a2a
            c2a = np.zeros(cap, dtype=np.int64); c2a[:m] = n_children[:m]; n_children = c2a
            s2 = np.zeros(cap, dtype=np.bool_); s2[:m] = seed[:m]; seed = s2
            f2a = np.zeros(cap, dtype=np.bool_); f2a[:m] = bud_free[:m]; bud_free = f2a
            d2a = np.zeros(cap, dtype=np.bool_); d2a[:m] = added[:m]; added = d2a
            e2a = np.zeros(cap, dtype=np.bool_); e2a[:m] = leader[:m]; leader = e2a
        first_new = m
        for g in range(ng):
            j = grow[g]
            lead = tipg[g] and leader[j]
            prev = j
            for k in range(1, units[g] + 1):
                step = l * k
                pos[m, 0] = pos[j, 0] + step * vnew[g, 0]
                pos[m, 1] = pos[j, 1] + step * vnew[g, 1]
                pos[m, 2] = pos[j, 2] + step * vnew[g, 2]
                heading[m, 0] = vnew[g, 0]
                heading[m, 1] = vnew[g, 1]
                heading[m, 2] = vnew[g, 2]
                parent[m] = prev
                n_children[m] = 0
                n_children[prev] += 1
                seed[m] = False
                added[m] = False
                bud_free[m] = True
                leader[m] = lead
                prev = m
                m += 1
        # A node's buds are spent once it has its apical and one lateral child.
        for g in range(ng):
            j = grow[g]
            bud_free[j] = n_children[j] < 2
        # Kill markers within d_k of the new nodes (the front suffices when d_k + shoot <= d_i).
        only_front = dk + l * umax <= di
        for q in range(first_new, m):
            cx = min(max(int(np.floor((pos[q, 0] - lo0) / gs)), 0), gx - 1)
            cy = min(max(int(np.floor((pos[q, 1] - lo1) / gs)), 0), gy - 1)
            cz = min(max(int(np.floor((pos[q, 2] - lo2) / gs)), 0), gz - 1)
            for ix in range(max(cx - rk, 0), min(cx + rk + 1, gx)):
                for iy in range(max(cy - rk, 0), min(cy + rk + 1, gy)):
                    for iz in range(max(cz - rk, 0), min(cz + rk + 1, gz)):
                        c = (ix * gy + iy) * gz + iz
                        for s in range(mstart[c], mstart[c + 1]):
                            i = morder[s]
                            if active[i] and (front[i] or not only_front):
                                dx = markers[i, 0] - pos[q, 0]
                                dy = markers[i, 1] - pos[q, 1]
                                dz = markers[i, 2] - pos[q, 2]
                                if dx * dx + dy * dy + dz * dz < dk2:
                                    active[i] = False
        # Buds with no active marker within the largest influence distance never grow again
        # (except the stem's apical tip, which may still bridge a gap).
        if it % 8 == 0:
            left = False
            for i in range(n):
                if active[i]:
                    left = True
                    break
            if left:
                for j in range(m):
                    if not bud_free[j] or (leader[j] and n_children[j] == 0):
                        continue
                    cx = min(max(int(np.floor((pos[j, 0] - lo0) / gs)), 0), gx - 1)
                    cy = min(max(int(np.floor((pos[j, 1] - lo1) / gs)), 0), gy - 1)
                    cz = min(max(int(np.floor((pos[j, 2] - lo2) / gs)), 0), gz - 1)
                    found = False
                    for ix in range(max(cx - rp, 0), min(cx + rp + 1, gx)):
                        for iy in range(max(cy - rp, 0), min(cy + rp + 1, gy)):
                            for iz in range(max(cz - rp, 0), min(cz + rp + 1, gz)):
                                c = (ix * gy + iy) * gz + iz
                                for s in range(mstart[c], mstart[c + 1]):
                                    i = morder[s]
                                    if active[i]:
                                        dx = markers[i, 0] - pos[j, 0]
                                        dy = markers[i, 1] - pos[j, 1]
                                        dz = markers[i, 2] - pos[j, 2]
                                        if dx * dx + dy * dy + dz * dz < dimax2:
                                            found = True
                                            break
                                if found:
                                    break
                            if found:
                                break
                        if found:
                            break
                    if not found:
                        bud_free[j] = False
        it += 1
    return (pos, heading, parent, n_children, seed, bud_free, added, leader, m, stall, boost, it, code)


def _roll_tables(roll: float, size: int):
    """cos and sin of the roll angle φ·j, j < ``size`` (lateral bud j + its children, Table 2's φ).

    Computed by numpy outside the kernel so that they are the very values the
    numpy formulation used (numpy's vectorised cos/sin may differ from libm's
    in the last bit).
    """
    ang = roll * np.arange(size)
    return np.cos(ang), np.sin(ang)


class _Nodes:
    """Growable node arrays (amortised doubling); parents always before children."""

    def __init__(self, cap: int = 256):
        self.m = 0
        self.pos = np.zeros((cap, 3))
        self.heading = np.zeros((cap, 3))
        self.parent = np.full(cap, -1, dtype=np.int64)
        self.n_children = np.zeros(cap, dtype=np.int64)
        self.seed = np.zeros(cap, dtype=bool)        # roots/trunk: lateral cone from the start
        self.bud_free = np.zeros(cap, dtype=bool)
        self.added = np.zeros(cap, dtype=bool)
        self.leader = np.zeros(cap, dtype=bool)      # on the stem's apical line (root upwards)

    def add(self, pos, heading, parent, seed=False, added=False, buds=True, leader=False):
        pos = np.asarray(pos, dtype=np.float64).reshape(-1, 3)
        k = len(pos)
        need = self.m + k
        if need > len(self.pos):
            cap = max(need, 2 * len(self.pos))
            for name in ("pos", "heading", "parent", "n_children", "seed", "bud_free", "added", "leader"):
                old = getattr(self, name)
                new = np.zeros((cap,) + old.shape[1:], dtype=old.dtype)
                if name == "parent":
                    new[:] = -1
                new[:self.m] = old[:self.m]
                setattr(self, name, new)
        s = slice(self.m, need)
        self.pos[s] = pos
        self.heading[s] = np.asarray(heading, dtype=np.float64).reshape(-1, 3)
        self.parent[s] = parent
        self.seed[s] = seed
        self.added[s] = added
        self.bud_free[s] = buds
        self.leader[s] = leader
        par = np.atleast_1d(np.asarray(parent, dtype=np.int64))
        par = par[par >= 0]
        if len(par):
            np.add.at(self.n_children, par, 1)
        first = self.m
        self.m = need
        return np.arange(first, need)


# --------------------------------------------------------------------------- the method
@dataclass(frozen=True)
class GuidedGrowth:
    """Guo et al. (2018) point-cloud-guided space colonisation (§5.2) with crown filling (§6.1).

    Parameters (paper defaults where the paper gives one):

    * ``step_m`` internode length l (Table 1).  Guo's Table 2 gives
      l ≈ 0.05 for plants scaled into a 10 m box; airborne crowns are sampled
      every ~0.3 m, so Sylva uses 0.25 m;
    * ``kill_distance_m`` d_k; Pałubicki (quoted in §5.2): d_k = 0.5 d_i with
      d_i ≥ 4l, so 2l = 0.5 m.  Also the coverage distance of
      ``visited_fraction``;
    * ``influence_h0`` H_0 = 2, ``influence_rho0`` ρ_0 = 0.3 (Eq. 6–7);
      ``influence_min_units`` / ``influence_max_units`` clamp ρ_t to
      Pałubicki's d_i ∈ [4l, 12l];
    * ``perception_angle_deg`` θ = 90° (§5.2); ``branching_angle_deg`` ψ
      (Table 2: 34–41°, 38°); ``roll_angle_deg`` φ (Table 2: 87–130°, 105°);
    * ``attraction_weight`` α = 1.6 and ``tropism`` β = 0.3 of Eq. 9, the
      tropism vector pointing down;
    * ``similarity_radius_m`` ε_D and ``similarity_cos`` ε_A = 0.9 of Eq. 8.
      The paper's ε_D = 3 cm suits dense photogrammetric clouds in a 10 m
      box; airborne point spacing is ~10× larger, so Sylva uses 0.5 m;
      ``pca_k`` neighbours of the PCA (not given: 10);
    * ``crown_fill`` "auto" (fill when ``interior_fraction`` <
      ``interior_min_fraction`` = 1/16, half of what a uniformly filled
      crown gives), "always" or "never";
      ``fill_spacing_m`` pitch of the fill markers (not given: 1.0 m, the
      smallest influence distance 4l, so the markers form one perceivable field),
      ``fill_weight`` their weight relative to the median point weight (0.5);
      ``fill_max_per_point`` caps the fill grid at that many cells per
      measured point (2.0; the pitch grows beyond ``fill_spacing_m`` for big,
      sparsely sampled crowns, so the fill guides the growth without
      outweighing the data);
    * ``multi_root``, ``root_band_m`` (1.0 m), ``root_link_m`` (0.75 m),
      ``root_min_points`` (5): multi-stem detection (§6.1);
    * ``trunk_radius_m``, ``lambda1_max_deg``, ``lambda2_max``: Hu et al.
      §4.2 root and trunk (1.0 m, 30°, 0.5);
    * ``max_iterations`` (2000), ``min_points`` (10: fewer distinct points
      give a minimal skeleton and a flag), ``seed`` of the fill jitter;
    * ``species`` None or a key of :data:`SPECIES_PRESETS` ("conifer",
      "broadleaf", "shrub"); the preset's values replace fields left at
      their defaults.
    """

    step_m: float = 0.25
    kill_distance_m: float = 0.5
    influence_h0: float = 2.0
    influence_rho0: float = 0.3
    influence_min_units: float = 4.0
    influence_max_units: float = 12.0
    perception_angle_deg: float = 90.0
    branching_angle_deg: float = 38.0
    roll_angle_deg: float = 105.0
    attraction_weight: float = 1.6
    tropism: float = 0.3
    similarity_radius_m: float = 0.5
    similarity_cos: float = 0.9
    pca_k: int = 10
    crown_fill: str = "auto"
    interior_min_fraction: float = 0.0625
    fill_spacing_m: float = 1.0
    fill_weight: float = 0.5
    fill_max_per_point: float = 2.0
    multi_root: bool = True
    root_band_m: float = 1.0
    root_link_m: float = 0.75
    root_min_points: int = 5
    trunk_radius_m: float = 1.0
    lambda1_max_deg: float = 30.0
    lambda2_max: float = 0.5
    max_iterations: int = 2000
    min_points: int = 10
    seed: int = 0
    species: Optional[str] = None

    name = "guided_growth"

    def __post_init__(self):
        if self.species is not None:
            if self.species not in SPECIES_PRESETS:
                raise InputError(f"GuidedGrowth: unknown species {self.species!r}; choose one of "
                                 f"{', '.join(SPECIES_PRESETS)} (or None)")
            defaults = {f.name: f.default for f in fields(self)}
            for key, value in SPECIES_PRESETS[self.species].items():
                if getattr(self, key) == defaults[key]:
                    object.__setattr__(self, key, value)
        for attr in ("step_m", "kill_distance_m", "influence_h0", "influence_rho0", "influence_min_units",
                     "similarity_radius_m", "fill_spacing_m", "root_band_m", "root_link_m",
                     "trunk_radius_m"):
            if not getattr(self, attr) > 0:
                raise InputError(f"GuidedGrowth: {attr} must be positive, got {getattr(self, attr)!r}")
        if not self.influence_max_units >= self.influence_min_units:
            raise InputError("GuidedGrowth: influence_max_units must be >= influence_min_units")
        for attr in ("perception_angle_deg", "branching_angle_deg", "lambda1_max_deg"):
            if not 0 < getattr(self, attr) <= 360:
                raise InputError(f"GuidedGrowth: {attr} must be in (0, 360] degrees, got {getattr(self, attr)!r}")
        if self.attraction_weight < 0 or self.tropism < 0 or self.fill_weight < 0 \
                or self.fill_max_per_point < 0:
            raise InputError("GuidedGrowth: attraction_weight, tropism, fill_weight and "
                             "fill_max_per_point must be >= 0")
        if not 0 <= self.similarity_cos <= 1 or not 0 <= self.interior_min_fraction <= 1:
            raise InputError("GuidedGrowth: similarity_cos and interior_min_fraction must be in [0, 1]")
        if self.crown_fill not in ("auto", "always", "never"):
            raise InputError(f"GuidedGrowth: crown_fill must be 'auto', 'always' or 'never', "
                             f"got {self.crown_fill!r}")
        for attr in ("pca_k", "max_iterations", "min_points", "root_min_points"):
            v = getattr(self, attr)
            if int(v) != v or v < 1:
                raise InputError(f"GuidedGrowth: {attr} must be a whole number >= 1, got {v!r}")

    # -- seeds ---------------------------------------------------------------
    def _seed(self, nodes: _Nodes, xyz: np.ndarray, ground_z: float, stats: dict, flags: list):
        """Root(s) and added trunk nodes; returns nothing, fills ``nodes``."""
        clusters = find_root_clusters(xyz, ground_z, self.root_band_m, self.root_link_m,
                                      int(self.root_min_points))
        if clusters is not None and len(clusters.centres) > 1 and not self.multi_root:
            clusters = None
        if clusters is not None and len(clusters.centres) == 1:
            # The points reach the ground: the root is under them (Guo §5.3: the centroid
            # of the densest cluster of projected points), no trunk needs adding.
            c = clusters.centres[0]
            nodes.add([c[0], c[1], ground_z], _UP, -1, seed=True, added=True, leader=True)
            stats.update(n_roots=1, root_rule="low_points")
            return
        if clusters is not None:
            k = len(clusters.centres)
            centre = (clusters.centres * clusters.sizes[:, None]).sum(axis=0) / clusters.sizes.sum()
            nodes.add([centre[0], centre[1], ground_z], _UP, -1, seed=True, added=True, buds=False)
            pos = np.c_[clusters.centres, np.full(k, ground_z)]
            nodes.add(pos, np.tile(_UP, (k, 1)), np.zeros(k, dtype=np.int64), seed=True, added=True,
                      leader=True)
            stats.update(n_roots=int(k), root_rule="clusters")
            flags.append("multi_root")
            return
        trunk = add_trunk_points(xyz, ground_z, self.trunk_radius_m, self.step_m,
                                 self.lambda1_max_deg, self.lambda2_max)
        pts = trunk.points
        direction = _unit(trunk.direction)
        if trunk.rule == "eq3":
            # Eq. 3 extrapolates the mean direction n_avg from the lowest point's few
            # neighbours over the whole height h; on synthetic stands its ~25° of noise put
            # the root up to 2 m off the stem.  The guided growth follows the stem points
            # upward by itself, so Sylva drops the stem vertically from v_low instead.
            top = trunk.v_low
            h = max(float(top[2] - ground_z), 0.0)
            t = np.linspace(0.0, 1.0, max(1, int(np.ceil(h / self.step_m))) + 1)[:, None]
            root = np.array([top[0], top[1], ground_z])
            pts = root + t * (top - root)
            direction = _UP
        m = len(pts)
        head = np.tile(direction, (m, 1))
        nodes.add(pts, head, np.arange(-1, m - 1), seed=True, added=True, leader=True)
        stats.update(n_roots=1, root_rule=trunk.rule, n_trunk_nodes=int(m))

    # -- the method ----------------------------------------------------------
    def reconstruct(self, tree: TreePoints, progress: Progress = None,
                    cancelled: CancelCheck = None) -> Reconstruction:
        """Grow the skeleton of one tree; see :func:`sylva.core.reconstruct.reconstruct_tree`."""
        t_all = time.perf_counter()
        if not isinstance(tree, TreePoints):
            raise InputError(f"GuidedGrowth expects a TreePoints, got {type(tree).__name__}")
        xyz = tree.xyz
        n = len(xyz)
        ground_z, flags, degenerate = screen(tree, int(self.min_points), self.name, progress)
        if degenerate is not None:
            degenerate.visited_fraction = self._coverage(degenerate.skeleton.nodes, xyz)
            degenerate.connected = True
            return degenerate
        stats = {"n_points": int(n)}

        # Markers and their weights (Eq. 8).
        check(cancelled)
        t0 = time.perf_counter()
        w, _ = pca_weights(xyz, self.similarity_radius_m, self.similarity_cos, int(self.pca_k))
        stats["t_weights_s"] = time.perf_counter() - t0
        stats["weight_median"] = float(np.median(w))

        # Crown filling (§6.1).
        t0 = time.perf_counter()
        crown = xyz[xyz[:, 2] >= np.percentile(xyz[:, 2], 5.0)]
        crown_hull = _hull(crown)       # one hull for the interior test and the fill
        frac = _interior_fraction(crown, crown_hull)
        stats["interior_fraction"] = frac
        fill = np.zeros((0, 3))
        if self.crown_fill == "always" or (self.crown_fill == "auto" and frac < self.interior_min_fraction):
            fill = _crown_fill_markers(crown, crown_hull, self.fill_spacing_m, self.seed,
                                       max_markers=max(64, int(self.fill_max_per_point * n)))
            if len(fill):
                flags.append("crown_filled")
        markers = np.concatenate([xyz, fill])
        weight = np.r_[w, np.full(len(fill), self.fill_weight * float(np.median(w)))]
        stats.update(n_fill=int(len(fill)), n_markers=int(len(markers)),
                     t_fill_s=time.perf_counter() - t0)
        report(progress, 0.1, "markers")

        # Seeds, then growth (§5.2).
        t0 = time.perf_counter()
        nodes = _Nodes(max(256, 2 * n))
        self._seed(nodes, xyz, ground_z, stats, flags)
        height = float(xyz[:, 2].max() - ground_z)
        it, reason = self._grow(nodes, markers, weight, n, height, progress, cancelled)
        if reason != "done":
            flags.append(reason)
        stats.update(t_growth_s=time.perf_counter() - t0, n_iterations=int(it), n_nodes=int(nodes.m))
        m = nodes.m
        skel = Skeleton(nodes.pos[:m].copy(), nodes.parent[:m].copy(), is_added=nodes.added[:m].copy())
        visited = self._coverage(skel.nodes, xyz)
        stats["t_total_s"] = time.perf_counter() - t_all
        report(progress, 1.0, "guided growth")
        return Reconstruction(skel, self.name, visited, True, stats, flags, tree.tree_id)

    def _coverage(self, nodes: np.ndarray, xyz: np.ndarray) -> float:
        """Share of ``xyz`` within the kill distance of a node."""
        near = _near_any_kernel(np.ascontiguousarray(xyz, dtype=np.float64),
                                np.ascontiguousarray(nodes, dtype=np.float64),
                                float(self.kill_distance_m * (1 + 1e-9)))
        return float(near.mean()) if len(xyz) else 0.0

    def _grow(self, nodes: _Nodes, markers: np.ndarray, weight: np.ndarray, n_measured: int,
              height_m: float, progress: Progress, cancelled: CancelCheck):
        """Iterate space colonisation until no marker is left; returns (iterations, reason).

        ``markers[:n_measured]`` are the tree's points, the rest crown-filling
        markers; ``reason`` is "done", "stalled" or "max_iterations" (the
        last two only when measured points are left unreached) or
        "node_limit" (more than 20 nodes per marker: a safety net).  The
        iterations run in the compiled :func:`_grow_kernel`, 16 at a time
        between progress reports and cancel checks.
        """
        l = float(self.step_m)
        dk = float(self.kill_distance_m)
        cos_apical = float(np.cos(np.radians(min(self.perception_angle_deg / 2.0, 180.0))))
        half_lat = min(self.perception_angle_deg / 2.0 + self.branching_angle_deg, 180.0)
        cos_lateral = float(np.cos(np.radians(half_lat)))
        psi = np.radians(self.branching_angle_deg)
        roll = np.radians(self.roll_angle_deg)
        alpha, beta = float(self.attraction_weight), float(self.tropism)
        di_max = float(self.influence_max_units) * l
        max_it = int(self.max_iterations)
        node_limit = 20 * len(markers) + 10_000      # a safety net, never reached in practice
        di_of_t = influence_distance(np.arange(max_it), height_m, l, self.influence_h0,
                                     self.influence_rho0, self.influence_min_units,
                                     self.influence_max_units)
        markers = np.ascontiguousarray(markers, dtype=np.float64)
        weight = np.ascontiguousarray(weight, dtype=np.float64)

        # Markers already within d_k of the seeds are taken.
        active = ~_near_any_kernel(markers, np.ascontiguousarray(nodes.pos[:nodes.m]), dk)

        cos_tab, sin_tab = _roll_tables(roll, len(nodes.pos) + 2)
        stall, boost = 0, 1.0
        total = len(markers)
        it, code, checked = 1, 0, 0
        while it <= max_it:
            if it % 16 == 0 and checked != it:
                checked = it
                check(cancelled)
                report(progress, 0.1 + 0.85 * (1.0 - active.sum() / max(total, 1)), "growing")
            hi = min(it - it % 16 + 16, max_it + 1)
            (nodes.pos, nodes.heading, nodes.parent, nodes.n_children, nodes.seed, nodes.bud_free,
             nodes.added, nodes.leader, m, stall, boost, it, code) = _grow_kernel(
                markers, weight, active, nodes.pos, nodes.heading, nodes.parent, nodes.n_children,
                nodes.seed, nodes.bud_free, nodes.added, nodes.leader, nodes.m, stall, boost, it, hi,
                di_of_t, cos_tab, sin_tab, l, dk, cos_apical, cos_lateral, float(np.cos(psi)),
                float(np.sin(psi)), alpha, beta, di_max, node_limit)
            nodes.m = int(m)
            if code == 5:
                cos_tab, sin_tab = _roll_tables(roll, 2 * len(nodes.pos) + 2)
                continue
            if code != 0:
                break
        reason = {0: "done", 1: "done", 2: "node_limit", 3: "stalled", 4: "stalled"}[int(code)]
        if code == 0:
            it = max_it
            if active[:n_measured].any():
                reason = "max_iterations"
        if reason == "stalled" and not active[:n_measured].any():
            reason = "done"        # only crown-filling markers were left out of reach
        return int(it), reason
