"""Least-squares circles of many groups of 2-D points at once.

Kåsa's algebraic fit (x² + y² = 2ax + 2by + c, one 3×3 normal system per group, in coordinates
centred on each group's mean, which keeps the systems well conditioned) refined by Gauss-Newton steps
of the geometric fit (minimise Σ (|p − c| − r)²).  Every step is a handful of ``np.bincount`` sums over
all points, so thousands of stem sections, QSM cylinders or level-set nodes cost a few array passes.
Used by stem detection (:mod:`sylva.core.segment.stems`), the QSM radius refit
(:func:`sylva.core.qsm.refit_radii`) and the level-set QSM (:mod:`sylva.core.reconstruct.levelset`);
each caller applies its own acceptance rules to what this returns.
"""

from __future__ import annotations

from typing import Optional, Tuple

import numpy as np

__all__ = ["fit_circles", "arc_sectors"]


def arc_sectors(dx: np.ndarray, dy: np.ndarray, g: np.ndarray, m: int) -> np.ndarray:
    """Degrees of the circumference the offsets (dx, dy) of every group cover, in 30° sectors."""
    sector = (np.floor((np.arctan2(dy, dx) + np.pi) / (np.pi / 6)).astype(np.int64)) % 12
    return (np.bincount(g * 12 + sector, minlength=12 * m).reshape(m, 12) > 0).sum(1) * 30.0


def _normal_sums(cols, rhs, g: np.ndarray, m: int) -> Tuple[np.ndarray, np.ndarray]:
    lhs, right = np.zeros((m, 3, 3)), np.zeros((m, 3))
    for i in range(3):
        right[:, i] = np.bincount(g, weights=cols[i] * rhs, minlength=m)
        for j in range(i, 3):
            lhs[:, i, j] = lhs[:, j, i] = np.bincount(g, weights=cols[i] * cols[j], minlength=m)
    return lhs, right


def fit_circles(x: np.ndarray, y: np.ndarray, g: np.ndarray, m: int, iterations: int = 6,
                fit: Optional[np.ndarray] = None):
    """Circles of the ``m`` groups ``g`` (ints in [0, m)) of the points (x, y).

    Returns ``(cx, cy, r, rms, arc)`` per group: centre, radius, RMS of the geometric residuals and the
    degrees of circumference the points cover around the fitted centre (30° sectors); cx, cy, r and rms
    are NaN for groups with fewer than 3 points, a degenerate system, or ``fit`` (m,) False."""
    x, y, g = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64), np.asarray(g, dtype=np.int64)
    cnt = np.bincount(g, minlength=m).astype(np.float64)
    mx = np.bincount(g, weights=x, minlength=m) / np.maximum(cnt, 1)
    my = np.bincount(g, weights=y, minlength=m) / np.maximum(cnt, 1)
    u, v = x - mx[g], y - my[g]
    ata, atb = _normal_sums((u, v, np.ones_like(u)), u * u + v * v, g, m)
    ok = (cnt >= 3) & (np.abs(np.linalg.det(ata)) > 1e-24)
    if fit is not None:
        ok &= np.asarray(fit, dtype=bool)
    sol = np.zeros((m, 3))
    if ok.any():
        sol[ok] = np.linalg.solve(ata[ok], atb[ok][..., None])[..., 0]
    a, b = sol[:, 0] / 2, sol[:, 1] / 2
    r = np.sqrt(np.maximum(sol[:, 2] + a * a + b * b, 0.0))
    for _ in range(max(0, int(iterations))):
        dx, dy = u - a[g], v - b[g]
        dd = np.maximum(np.hypot(dx, dy), 1e-12)
        jtj, jtr = _normal_sums((-dx / dd, -dy / dd, -np.ones_like(dd)), dd - r[g], g, m)
        o2 = ok & (np.abs(np.linalg.det(jtj)) > 1e-24)
        step = np.zeros((m, 3))
        if o2.any():
            step[o2] = -np.linalg.solve(jtj[o2], jtr[o2][..., None])[..., 0]
        a, b, r = a + step[:, 0], b + step[:, 1], r + step[:, 2]
    dx, dy = u - a[g], v - b[g]
    res = np.hypot(dx, dy) - r[g]
    rms = np.sqrt(np.bincount(g, weights=res ** 2, minlength=m) / np.maximum(cnt, 1))
    arc = arc_sectors(dx, dy, g, m)
    ok &= np.isfinite(r) & (r > 0)
    nan = np.where(ok, 1.0, np.nan)
    return (a + mx) * nan, (b + my) * nan, r * nan, rms * nan, arc
