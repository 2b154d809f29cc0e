"""Data classes shared by every tree-reconstruction method.

* :class:`TreePoints` — the points of one segmented tree in a local metric
  frame (z up) plus the terrain height under it: what every method takes.
* :class:`~sylva.core.skeleton.Skeleton` (defined below the geometry, in
  :mod:`sylva.core.skeleton`) — what every method returns.
* :class:`Reconstruction` — a skeleton plus how it was obtained: method name,
  share of candidate points reached, graph connectivity, per-step timings and
  counts, and flags such as ``"too_few_points"``.

The paper's y axis is up; Sylva's z axis is up everywhere in this package.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import List, Optional

import numpy as np

from ..errors import EmptyInputError, InputError
from ..jit import njit
from ..skeleton import Skeleton


@dataclass
class TreePoints:
    """The points of one tree.

    ``xyz`` is (n, 3) float64 in metres in a local frame with z up (any
    origin); ``ground_z`` the terrain height under the tree in the same frame;
    ``intensity`` optional per-point values (unused by the greedy skeleton).
    """

    tree_id: int
    xyz: np.ndarray
    ground_z: float
    intensity: Optional[np.ndarray] = None

    def __post_init__(self):
        xyz = np.asarray(self.xyz, dtype=np.float64)
        if xyz.size == 0:
            xyz = xyz.reshape(0, 3)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise InputError(
                f"tree {self.tree_id}: points must be an (n, 3) array of x, y, z in metres, "
                f"got shape {np.shape(self.xyz)}"
            )
        if not np.all(np.isfinite(xyz)):
            raise InputError(f"tree {self.tree_id}: {int((~np.isfinite(xyz)).any(axis=1).sum())} "
                             "points have NaN or infinite coordinates")
        try:
            ground_z = float(self.ground_z)
        except (TypeError, ValueError):
            raise InputError(f"tree {self.tree_id}: ground_z must be a number, got {self.ground_z!r}")
        if not np.isfinite(ground_z):
            raise InputError(f"tree {self.tree_id}: ground_z is {ground_z}, expected a finite height")
        self.xyz = xyz
        self.ground_z = ground_z
        if self.intensity is not None:
            self.intensity = np.asarray(self.intensity)
            if len(self.intensity) != len(xyz):
                raise InputError(f"tree {self.tree_id}: {len(self.intensity)} intensity values "
                                 f"for {len(xyz)} points")

    def __len__(self) -> int:
        return len(self.xyz)


@dataclass
class Reconstruction:
    """One tree's skeleton and how it was obtained.

    ``visited_fraction`` is the share of candidate (thinned) points the
    method reached (Hu et al. §6.2: trees under 85 % go to the fallback);
    for the greedy skeleton it counts only candidates that hold measured
    points, not those made of added trunk points alone (which the skeleton
    reaches by construction; ``stats["visited_fraction_all"]`` counts all);
    ``connected`` whether the method's neighbourhood graph was connected;
    ``stats`` per-step timings (``t_<step>_s``, seconds) and counts;
    ``flags`` short machine-readable notes such as ``"too_few_points"``.
    """

    skeleton: Skeleton
    method: str
    visited_fraction: float
    connected: bool
    stats: dict = field(default_factory=dict)
    flags: List[str] = field(default_factory=list)
    tree_id: int = -1


def minimal_skeleton(xyz: np.ndarray, ground_z: float) -> Skeleton:
    """A vertical stem from the ground to the top of the points, under their centre.

    The stand-in for trees too small or too degenerate to model (two added
    nodes; a single root node when the points do not rise above the ground).
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    cx, cy = (lo[:2] + hi[:2]) / 2.0
    root = [cx, cy, ground_z]
    if hi[2] > ground_z:
        return Skeleton(np.array([root, [cx, cy, hi[2]]]), np.array([-1, 0]),
                        is_added=np.array([True, True]))
    return Skeleton(np.array([root]), np.array([-1]), is_added=np.array([True]))


@njit
def _screen_kernel(xyz, min_points):
    """Distinct points (counted up to ``min_points``) and a lower bound of the
    smallest eigenvalue of the points' covariance: λ3 ≥ 4·det(C)/tr(C)²
    (λ1·λ2 ≤ (tr/2)²); plain loops for numba."""
    n = xyz.shape[0]
    first = np.empty(min_points, np.int64)      # one point of each distinct position found
    distinct = 0
    for p in range(n):
        if distinct >= min_points:
            break
        new = True
        for q in range(distinct):
            o = first[q]
            if xyz[p, 0] == xyz[o, 0] and xyz[p, 1] == xyz[o, 1] and xyz[p, 2] == xyz[o, 2]:
                new = False
                break
        if new:
            first[distinct] = p
            distinct += 1
    mx = 0.0
    my = 0.0
    mz = 0.0
    for p in range(n):
        mx += xyz[p, 0]
        my += xyz[p, 1]
        mz += xyz[p, 2]
    mx /= n
    my /= n
    mz /= n
    sxx = sxy = sxz = syy = syz = szz = 0.0
    for p in range(n):
        dx = xyz[p, 0] - mx
        dy = xyz[p, 1] - my
        dz = xyz[p, 2] - mz
        sxx += dx * dx
        sxy += dx * dy
        sxz += dx * dz
        syy += dy * dy
        syz += dy * dz
        szz += dz * dz
    det = sxx * (syy * szz - syz * syz) - sxy * (sxy * szz - syz * sxz) + sxz * (sxy * syz - syy * sxz)
    tr = sxx + syy + szz
    bound = 4.0 * det / (tr * tr) / (n - 1) if tr > 0 and n > 1 else 0.0
    return distinct, bound


#: λ3 lower bounds above this (twice the 1 cm spread², a margin for rounding) settle
#: "neither collinear nor coplanar" without the eigen decomposition.
_SPREAD_SURE = 2.0 * 0.01 ** 2


def degenerate_flags(xyz: np.ndarray, min_points: int) -> List[str]:
    """Why a tree cannot be modelled (empty list: it can): too few points, too few distinct
    points, or all points within ~1 cm of a line or of a plane (spread along the principal axes)."""
    if len(xyz) < min_points:
        return ["too_few_points"]
    # (no points: one "distinct" point, as counting the changes along a sort gives)
    distinct, bound = (_screen_kernel(np.ascontiguousarray(xyz, dtype=np.float64), max(int(min_points), 1))
                       if len(xyz) else (1, 0.0))
    if distinct < min_points:
        return ["duplicate_points"]
    if bound > _SPREAD_SURE:            # Sylva, not in the paper: the spreads are surely > 1 cm
        return []
    spread = np.sqrt(np.clip(np.linalg.eigvalsh(np.cov(xyz.T)), 0.0, None))[::-1]
    if spread[1] < 0.01:
        return ["collinear_points"]
    if spread[2] < 0.01:
        return ["coplanar_points"]
    return []


def screen(tree: TreePoints, min_points: int, method: str, progress=None):
    """The checks every method starts with: (ground_z, flags, degenerate reconstruction or None).

    Raises :class:`EmptyInputError` for a tree without points; points below
    ``tree.ground_z`` lower the ground to them (flag ``points_below_ground``);
    a tree :func:`degenerate_flags` rejects gets, as third item, the
    :func:`minimal_skeleton` as a Reconstruction of ``method`` (nothing reached,
    not connected) with those flags; None when the tree can be modelled.
    """
    import time

    from ..progress import report

    t0 = time.perf_counter()
    xyz = tree.xyz
    if len(xyz) == 0:
        raise EmptyInputError(f"tree {tree.tree_id} has no points to reconstruct")
    flags: List[str] = []
    ground_z = tree.ground_z
    if xyz[:, 2].min() < ground_z:
        flags.append("points_below_ground")
        ground_z = float(xyz[:, 2].min())
    bad = degenerate_flags(xyz, min_points)
    if not bad:
        return ground_z, flags, None
    skel = minimal_skeleton(xyz, ground_z)
    report(progress, 1.0, f"tree {tree.tree_id}: {bad[0].replace('_', ' ')}")
    stats = {"n_points": int(len(xyz)), "t_total_s": time.perf_counter() - t0}
    return ground_z, flags, Reconstruction(skel, method, 0.0, False, stats, flags + bad, tree.tree_id)
