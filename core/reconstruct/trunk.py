"""Add trunk and root points to an airborne tree (Hu et al. 2017, §4.2, Eq. 3 and 4).

Airborne scans rarely see the stem, so Hu et al. insert trunk points between
the crown and the ground before building the skeleton.  In Sylva's frame z is
up (the paper's y).  With S the tree points and S' their projection onto the
ground plane (z = ``ground_z``):

* ``v_low`` is the lowest tree point, assumed to be a trunk point, and
  ``h = v_low.z - ground_z`` its height above the ground;
* ``n_avg`` is the normalised mean of the unit directions from ``v_low`` to
  its neighbours within a sphere of radius r (``radius_m``);
* ``g_b`` is the centre of the bounding box of S' (on the ground) and ``v_b``
  the centre of the bounding box of S; ``v_c`` the centroid of S;
* λ1 is the angle between ``n_avg`` and the centre line g_b→v_b, and
  λ2 = |v_low^xy − g_b^xy| / |v_max^xy − g_b^xy| (the paper's xz is Sylva's xy).

If λ1 ≤ λ1_max (30°) and λ2 ≤ λ2_max (0.5) the trunk follows the lowest
points: Eq. 3, v_t = v_low − n_avg·t, t ∈ [0, h / n_avg.z], the root at
t = h / n_avg.z on the ground.  Otherwise (or when v_low has no neighbour
within r) the root is g_b and trunk points are interpolated from the
centroid down to it: Eq. 4, v_t = v_c − (v_c − g_b)/‖v_c − g_b‖·t,
t ∈ [0, ‖v_c − g_b‖].

Sylva adds one guard to the paper's rule: Eq. 3 is used only if the root it
gives also lies within λ2_max of the centre line (|root^xy − g_b^xy| /
|v_max^xy − g_b^xy| ≤ λ2_max).  When the lowest point is high in the crown
(no stem points), a tilt within λ1 ≤ 30° extrapolated over its height can
otherwise put the root metres outside the crown, "probably wrong" in the
paper's own words (Fig. 6b).

The paper does not give r or the spacing of the interpolated points; Sylva
uses r = 1.0 m and a spacing of half the thinning voxel (0.1 m), so the
added trunk is a 26-connected run of voxels in §5.1's voxel space.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ..jit import njit


class Trunk(NamedTuple):
    """Result of :func:`add_trunk_points`."""

    points: np.ndarray      # (m, 3) added trunk points, root first, ascending along the trunk
    root: np.ndarray        # (3,) root position on the ground
    direction: np.ndarray   # (3,) unit vector pointing up the trunk from the root
    rule: str               # "eq3" (follow the lowest points) or "eq4" (centroid to box centre)
    lambda1_deg: float      # angle between n_avg and the centre line (nan if undefined)
    lambda2: float          # horizontal offset of v_low from the centre line, relative
    v_low: np.ndarray       # (3,) lowest tree point


@njit
def _trunk_stats(xyz, radius_m):
    """Bounding box, centroid v_c, lowest point and the mean unit direction from
    it to its neighbours within ``radius_m`` (and their number); plain loops for numba.

    Sums run over the points in order, from the first point on, and lengths
    are sqrt((x² + y²) + z²): what numpy's ``mean(axis=0)`` and
    ``linalg.norm(axis=1)`` compute for a C-ordered (n, 3) array
    (tests/test_skeleton_kernel.py checks the trunk against Eq. 3 / Eq. 4).
    """
    n = xyz.shape[0]
    lo = xyz[0].copy()
    hi = xyz[0].copy()
    total = xyz[0].copy()
    low = 0
    for p in range(1, n):
        for a in range(3):
            v = xyz[p, a]
            lo[a] = min(lo[a], v)
            hi[a] = max(hi[a], v)
            total[a] += v
        if xyz[p, 2] < xyz[low, 2]:
            low = p
    v_c = total / n
    mean = np.zeros(3)
    n_near = 0
    for p in range(n):
        dx = xyz[p, 0] - xyz[low, 0]
        dy = xyz[p, 1] - xyz[low, 1]
        dz = xyz[p, 2] - xyz[low, 2]
        norm = math.sqrt(dx * dx + dy * dy + dz * dz)
        if norm <= radius_m and norm > 1e-9:       # the sphere of radius r, v_low excluded
            if n_near == 0:
                mean[0] = dx / norm
                mean[1] = dy / norm
                mean[2] = dz / norm
            else:
                mean[0] += dx / norm
                mean[1] += dy / norm
                mean[2] += dz / norm
            n_near += 1
    if n_near:
        mean /= n_near
    return lo, hi, v_c, low, n_near, mean


def _interpolate(start: np.ndarray, stop: np.ndarray, spacing_m: float) -> np.ndarray:
    """Points from ``start`` to ``stop`` inclusive, at most ``spacing_m`` apart."""
    length = float(np.linalg.norm(stop - start))
    if length < 1e-12:
        return start[None, :].copy()
    n = max(1, int(np.ceil(length / spacing_m)))
    t = np.arange(n + 1, dtype=np.float64) * (1.0 / n)     # np.linspace(0, 1, n + 1), without its overhead
    t[-1] = 1.0
    return start[None, :] + t[:, None] * (stop - start)[None, :]


def add_trunk_points(
    xyz: np.ndarray,
    ground_z: float,
    radius_m: float = 1.0,
    spacing_m: float = 0.1,
    lambda1_max_deg: float = 30.0,
    lambda2_max: float = 0.5,
) -> Trunk:
    """Estimate the trunk of an airborne tree and sample points along it (Hu et al. §4.2).

    Parameters are r (``radius_m``, neighbourhood of the lowest point), the
    spacing of the added points and the thresholds λ1 ≤ 30°, λ2 ≤ 0.5 that
    choose Eq. 3 over Eq. 4.  ``points`` runs from the root (on the ground,
    ``points[0] == root``) upwards: to ``v_low`` for Eq. 3, to the centroid
    ``v_c`` for Eq. 4.  Pure function of its inputs.
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    if len(xyz) == 0:
        raise ValueError("add_trunk_points: no points")
    lo, hi, v_c, low, n_near, mean = _trunk_stats(np.ascontiguousarray(xyz), float(radius_m))
    if not xyz.flags.c_contiguous:
        v_c = xyz.mean(axis=0)          # numpy sums another layout in another order
    v_b = (lo + hi) / 2.0
    g_b = np.array([v_b[0], v_b[1], ground_z])          # centre of the ground box S'
    v_low = xyz[low]
    h = max(0.0, float(v_low[2] - ground_z))

    # λ2: horizontal distance of v_low from the centre line, relative to the
    # distance of the box corner v_max from it.
    half_diag = float(np.linalg.norm(hi[:2] - g_b[:2]))
    lambda2 = float(np.linalg.norm(v_low[:2] - g_b[:2]) / half_diag) if half_diag > 0 else 0.0

    # n_avg from the unit directions v_low -> v_j of the neighbours within r.
    lambda1 = float("nan")
    n_avg = None
    if n_near:
        mean_norm = np.linalg.norm(mean)
        if mean_norm > 1e-9:
            n_avg = mean / mean_norm
            centre_line = v_b - g_b
            cl_norm = np.linalg.norm(centre_line)
            if cl_norm > 1e-9:
                cl = centre_line / cl_norm
            else:
                cl = np.array([0.0, 0.0, 1.0])
            lambda1 = float(np.degrees(np.arccos(np.clip(n_avg @ cl, -1.0, 1.0))))

    if n_avg is not None and lambda1 <= lambda1_max_deg and lambda2 <= lambda2_max and n_avg[2] > 0:
        # Eq. 3: v_t = v_low - n_avg t, root at t = h / n_avg.z.
        root = v_low - n_avg * (h / n_avg[2])
        root[2] = ground_z
        # Sylva's guard: the root, too, must stay within λ2_max of the centre line
        # (a lowest point high in the crown extrapolates a small tilt far away).
        root_off = float(np.linalg.norm(root[:2] - g_b[:2]) / half_diag) if half_diag > 0 else 0.0
        if root_off <= lambda2_max:
            pts = _interpolate(root, v_low, spacing_m)
            return Trunk(pts, root, n_avg, "eq3", lambda1, lambda2, v_low.copy())

    # Eq. 4: v_t = v_c - (v_c - g_b)/|v_c - g_b| t, from the centroid down to g_b.
    axis = v_c - g_b
    if np.linalg.norm(axis) < 1e-9 or axis[2] <= 0:
        axis = np.array([0.0, 0.0, 1.0])
        top = g_b + axis * max(float(hi[2] - ground_z), 0.0)
    else:
        top = v_c
        axis = axis / np.linalg.norm(axis)
    pts = _interpolate(g_b, top, spacing_m)
    return Trunk(pts, g_b, axis, "eq4", lambda1, lambda2, v_low.copy())
