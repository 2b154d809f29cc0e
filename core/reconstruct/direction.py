"""Direction field of branch growth (Hu et al. 2017, §5.3, Eq. 5).

Hu et al. model the growth direction of a branch at point p_i from its
position in the crown.  In a 2-D image with bounding box (p_min, p_max) and
centre line at distance L_c from p_min, the direction angle (from the
horizontal, pointing away from the centre line) is, Eq. 5:

    θ_i = 90° ∓ (90° − θ_l − μ1 (θ_u − θ_l)) μ2,
    μ1 = (p_i.y / (p_max.y − p_min.y))^k1,   μ2 = (|p_i.x − L_c| / L_c)^k2,

(− right of the centre line, + left: the mirror image).  On the centre line
μ2 = 0 and the direction is vertical; at the side of the box it is θ_l at
the bottom and θ_u at the top.  The 3-D field is this 2-D field rotated
about the centre line: u_i is the unit vector of
(p_i.x − p_c.x, ‖p_i − p_c‖ tan θ_i, p_i.z − p_c.z) in the paper's y-up
frame, i.e. the outward horizontal direction raised by θ_i.

In Sylva's z-up frame: height is p.z − z_min over z_max − z_min (z_min is
the bottom of the candidate points, the root on the ground); the horizontal
distance is measured from the vertical centre line through the box centre;
and L_c, the half width of the 2-D box, becomes the radius of the box's
solid of revolution — the largest horizontal distance of a point from the
centre line — so that μ2 stays in [0, 1] in every direction.

Defaults (§6.2): θ_u = 80°, θ_l = −40°, k1 = 1.4, k2 = 1.0.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from ..jit import njit


@njit
def _bounds(points):
    """Per-axis minimum and maximum of (n, 3) points, n >= 1 (numpy's ``min(axis=0)`` is slow on 3 columns)."""
    lo = points[0].copy()
    hi = points[0].copy()
    for i in range(1, points.shape[0]):
        for a in range(3):
            lo[a] = min(lo[a], points[i, a])
            hi[a] = max(hi[a], points[i, a])
    return lo, hi


def _frame(points, centre_xy, z_range, radius_m):
    lo, hi = _bounds(points)
    centre_xy = (lo[:2] + hi[:2]) / 2.0 if centre_xy is None else np.asarray(centre_xy, dtype=np.float64)
    z0, z1 = (lo[2], hi[2]) if z_range is None else (float(z_range[0]), float(z_range[1]))
    radial = points[:, :2] - centre_xy[None, :]
    dist = np.hypot(radial[:, 0], radial[:, 1])
    if radius_m is None:
        radius_m = float(dist.max()) if len(dist) else 0.0
    return centre_xy, z0, z1, radial, dist, radius_m


def _angles(points, frame, theta_upper_deg, theta_lower_deg, k1, k2):
    _, z0, z1, _, dist, lc = frame
    height = z1 - z0
    mu1 = np.clip((points[:, 2] - z0) / height, 0.0, 1.0) ** k1 if height > 0 else np.zeros(len(points))
    mu2 = np.clip(dist / lc, 0.0, 1.0) ** k2 if lc > 0 else np.zeros(len(points))
    return 90.0 - (90.0 - theta_lower_deg - mu1 * (theta_upper_deg - theta_lower_deg)) * mu2


def direction_angles(points: np.ndarray, theta_upper_deg: float = 80.0, theta_lower_deg: float = -40.0,
                     k1: float = 1.4, k2: float = 1.0, centre_xy: Optional[np.ndarray] = None,
                     z_range: Optional[tuple] = None, radius_m: Optional[float] = None) -> np.ndarray:
    """Eq. 5: elevation θ_i in degrees above the outward horizontal at each point.

    ``centre_xy`` (default: centre of the points' bounding box), ``z_range``
    (default: the points' z extent) and ``radius_m`` (L_c, default: the
    largest horizontal distance from the centre line) define the box.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) == 0:
        return np.zeros(0)
    return _angles(points, _frame(points, centre_xy, z_range, radius_m), theta_upper_deg, theta_lower_deg, k1, k2)


def direction_field(points: np.ndarray, theta_upper_deg: float = 80.0, theta_lower_deg: float = -40.0,
                    k1: float = 1.4, k2: float = 1.0, centre_xy: Optional[np.ndarray] = None,
                    z_range: Optional[tuple] = None, radius_m: Optional[float] = None) -> np.ndarray:
    """Eq. 5 rotated about the centre line: (n, 3) unit growth directions u_i (z up).

    u_i = cos θ_i · (outward horizontal unit vector) + sin θ_i · z; on the
    centre line itself u_i is vertical.  Arguments as :func:`direction_angles`.
    Pure function of its inputs.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) == 0:
        return np.zeros((0, 3))
    frame = _frame(points, centre_xy, z_range, radius_m)
    theta = np.radians(_angles(points, frame, theta_upper_deg, theta_lower_deg, k1, k2))
    radial, dist = frame[3], frame[4]
    out = np.empty((len(points), 3))
    on_line = dist < 1e-9
    if on_line.any():
        outward = np.zeros_like(radial)
        outward[~on_line] = radial[~on_line] / dist[~on_line, None]
        out[:, 2] = np.where(on_line, 1.0, np.sin(theta))
    else:
        outward = radial / dist[:, None]
        out[:, 2] = np.sin(theta)
    out[:, :2] = np.cos(theta)[:, None] * outward
    return out
