"""Trees of known cylinders, and their surfaces sampled as a scan (tests and benchmarks of the QSMs)."""
from __future__ import annotations

from typing import Sequence

import numpy as np

from ..core.qsm import cylinders_from_curves

__all__ = ["cylinder_tree", "sample_cylinder_surfaces"]


def cylinder_tree(segments: Sequence[dict]) -> dict:
    """A cylinder table from branch specs, for validation with known truth.

    Each spec: ``{"start": (3,), "direction": (3,), "length": m, "radius": (r0, r1),
    "parent": branch index or -1, "n": cylinders}``; a branch is ``n`` equal
    cylinders whose radius tapers linearly from r0 to r1.
    """
    curves, radii, parents = [], [], []
    for s in segments:
        d = np.asarray(s["direction"], float)
        d = d / np.linalg.norm(d)
        n = int(s.get("n", 4))
        t = np.linspace(0, s["length"], n + 1)
        curves.append(np.asarray(s["start"], float) + t[:, None] * d)
        r0, r1 = s["radius"]
        rr = np.linspace(r0, r1, n + 1)
        radii.append(rr)
        parents.append(int(s.get("parent", -1)))
    return cylinders_from_curves(curves, radii, parents)      # a cylinder's radius: the mean of its ends


def sample_cylinder_surfaces(cyl: dict, spacing_m: float = 0.01, noise_m: float = 0.0, seed: int = 0,
                             visible=None) -> np.ndarray:
    """Points on the lateral surfaces of the cylinders, ~one per ``spacing_m``² of area,
    with Gaussian radial noise ``noise_m``.  ``visible`` optional (3,) horizontal view
    direction: only the half of each cylinder facing it is kept (a one-sided scan)."""
    rng = np.random.default_rng(seed)
    area = 2 * np.pi * cyl["radius"] * cyl["length"]
    n_each = np.maximum(1, np.round(area / spacing_m ** 2)).astype(np.int64)
    idx = np.repeat(np.arange(len(area)), n_each)
    a = cyl["axis"][idx]
    helper = np.where(np.abs(a[:, 2:3]) < 0.9, np.array([0, 0, 1.0]), np.array([1.0, 0, 0]))
    u = np.cross(a, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(a, u)
    th = rng.uniform(0, 2 * np.pi, len(idx))
    t = rng.uniform(0, 1, len(idx)) * cyl["length"][idx]
    r = cyl["radius"][idx] + rng.normal(0, noise_m, len(idx)) if noise_m > 0 else cyl["radius"][idx]
    nrm = np.cos(th)[:, None] * u + np.sin(th)[:, None] * v
    pts = cyl["start"][idx] + t[:, None] * a + r[:, None] * nrm
    if visible is not None:
        vd = np.asarray(visible, float)
        pts = pts[(nrm @ vd) < 0]
    return pts
