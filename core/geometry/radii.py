"""Node radii: the pipe model of Hu et al. 2017 §5.5 Eq. 6 and the allometric rule of Guo et al. 2018 §5.1 Eq. 5.

:func:`pipe_model_radii` (:class:`PipeModel`) from the subtree tip counts (:func:`tip_counts`, a compiled
pass), :func:`allometric_radii` (:class:`Allometric`) root to tip; :func:`assign_radii` applies either,
:func:`with_radii` and :func:`radii_or_default` give a skeleton its radii.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Union

import numpy as np

from ..errors import InputError
from ..jit import njit
from ..skeleton import Skeleton
from .passes import check_skeleton, depth_levels, subtree_sum, tree_name


@dataclass(frozen=True)
class PipeModel:
    """Pipe-model radii, Hu et al. 2017 §5.5 Eq. 6 (Shinozaki et al. 1964).

    ``tip_radius_m`` is R_const, the radius of a branch tip (user defined in
    the paper; 1 cm here); ``exponent`` the pipe exponent e in
    ``r_parent^e = sum r_child^e`` (2 in Eq. 6, da Vinci's rule);
    ``trunk_radius_m`` if given rescales all radii so that the root has it
    (e.g. DBH/2 from a measurement or an allometric estimate).
    """

    tip_radius_m: float = 0.01
    exponent: float = 2.0
    trunk_radius_m: Optional[float] = None


@dataclass(frozen=True)
class Allometric:
    """Allometric radii, Guo et al. 2018 §5.1 Eq. 5, from a known root radius.

    ``root_radius_m`` is d_root/2; ``gamma`` the diameter coefficient γ
    (0.5 makes cross-sections proportional to supported length, da Vinci's
    area rule); ``min_radius_m`` an optional floor for the thinnest twigs.
    """

    root_radius_m: float = 0.15
    gamma: float = 0.5
    min_radius_m: float = 0.0


def pipe_model_radii(skeleton: Skeleton, tip_radius_m: float = 0.01, exponent: float = 2.0,
                     trunk_radius_m: Optional[float] = None, inplace: bool = False) -> np.ndarray:
    """Node radii by the pipe model, Hu et al. 2017 §5.5 Eq. 6.

    Eq. 6 sets every tip to ``R_const`` and every parent segment to
    ``R_up,i^2 = sum_j R_low,j^2`` over its child segments.  Here a node's
    radius is the pipe radius at that node (all pipes of its subtree pass
    through it), so with exponent ``e``::

        r_tip = tip_radius_m,      r_i^e = sum_{children c} r_c^e

    which telescopes to ``r_i = tip_radius_m * N_i^(1/e)`` with ``N_i`` the
    number of tips in the subtree of ``i`` — computed with one backward pass
    over the nodes.  Radii are therefore non-increasing from the root to
    the tips, and the frustum between a node and its child tapers as Hu's
    "adjusted upper radius" does.  With ``trunk_radius_m`` all radii are scaled
    by one factor so the root radius equals it (the relation is homogeneous,
    so Eq. 6 still holds exactly).  Returns a new (m,) array; with
    ``inplace=True`` also stores it in ``skeleton.radius``.
    """
    skeleton = check_skeleton(skeleton)
    if not (np.isfinite(tip_radius_m) and tip_radius_m > 0):
        raise InputError(f"{tree_name(skeleton)}: tip_radius_m must be > 0 m, got {tip_radius_m}")
    if not (np.isfinite(exponent) and exponent > 0):
        raise InputError(f"{tree_name(skeleton)}: pipe-model exponent must be > 0, got {exponent}")
    m = len(skeleton)
    if m == 0:
        return np.zeros(0)
    radii = tip_radius_m * tip_counts(skeleton.parent) ** (1.0 / exponent)
    if trunk_radius_m is not None:
        if not (np.isfinite(trunk_radius_m) and trunk_radius_m > 0):
            raise InputError(f"{tree_name(skeleton)}: trunk_radius_m must be > 0 m, got {trunk_radius_m}")
        radii *= trunk_radius_m / radii[skeleton.root]
    if inplace:
        skeleton.radius = radii.copy()
    return radii


def tip_counts(parent: np.ndarray) -> np.ndarray:
    """Number of tips (nodes without children) in the subtree of every node, as float64.

    For one tree or a forest of concatenated trees (parents precede children).  Sums of whole
    numbers: exact, so equal to any other summation order.
    """
    return _tip_count_kernel(np.ascontiguousarray(parent, dtype=np.int64))


@njit
def _tip_count_kernel(parent):
    """Subtree tip counts by one backward pass (children after parents); see :func:`tip_counts`."""
    m = parent.shape[0]
    kids = np.zeros(m, np.int64)
    for i in range(m):
        if parent[i] >= 0:
            kids[parent[i]] += 1
    acc = np.zeros(m)
    for i in range(m - 1, -1, -1):
        if kids[i] == 0:
            acc[i] += 1.0
        if parent[i] >= 0:
            acc[parent[i]] += acc[i]
    return acc


def allometric_radii(skeleton: Skeleton, root_radius_m: float = 0.15, gamma: float = 0.5,
                     min_radius_m: float = 0.0, inplace: bool = False) -> np.ndarray:
    """Node radii by the allometric rule of Guo et al. 2018 §5.1, Eq. 5, root to tip.

    ``d_c = d_p (l_c / sum_j l_cj)^gamma`` for every child ``c`` of ``p``,
    where ``l_c`` is the total branch length the child supports: the length
    of its subtree plus its own segment from ``p``.  The root gets
    ``root_radius_m`` (Guo measures d_root from the points at the plant base);
    a single child keeps its parent's radius.  ``min_radius_m`` floors the
    result.  Vectorised: subtree lengths by a reverse pass per depth level,
    then products of the ratios by a forward pass per depth level.
    """
    skeleton = check_skeleton(skeleton)
    if not (np.isfinite(root_radius_m) and root_radius_m > 0):
        raise InputError(f"{tree_name(skeleton)}: root_radius_m must be > 0 m, got {root_radius_m}")
    if not (np.isfinite(gamma) and gamma >= 0):
        raise InputError(f"{tree_name(skeleton)}: gamma must be >= 0, got {gamma}")
    m = len(skeleton)
    if m == 0:
        return np.zeros(0)
    parent = skeleton.parent
    levels = depth_levels(skeleton)
    child, par = skeleton.segments()
    seg = np.zeros(m)
    seg[child] = np.linalg.norm(skeleton.nodes[child] - skeleton.nodes[par], axis=1)
    supported = subtree_sum(parent, seg, levels)          # subtree length incl. own segment
    sibling_total = np.zeros(m)
    np.add.at(sibling_total, par, supported[child])
    ratio = np.ones(m)
    tot = sibling_total[par]
    ok = tot > 0
    # zero-length children (duplicate nodes) share equally
    nsib = np.bincount(par, minlength=m)[par]
    ratio[child] = np.where(ok, supported[child] / np.where(ok, tot, 1.0), 1.0 / nsib)
    factor = ratio ** gamma
    radii = np.empty(m)
    radii[levels[0]] = root_radius_m
    for idx in levels[1:]:
        radii[idx] = radii[parent[idx]] * factor[idx]
    if min_radius_m > 0:
        radii = np.maximum(radii, min_radius_m)
    if inplace:
        skeleton.radius = radii.copy()
    return radii


def assign_radii(skeleton: Skeleton, method: Union[PipeModel, Allometric] = PipeModel(),
                 inplace: bool = False) -> np.ndarray:
    """Radii of ``skeleton`` by ``method`` (:class:`PipeModel` or :class:`Allometric`)."""
    if isinstance(method, PipeModel):
        return pipe_model_radii(skeleton, method.tip_radius_m, method.exponent,
                                method.trunk_radius_m, inplace=inplace)
    if isinstance(method, Allometric):
        return allometric_radii(skeleton, method.root_radius_m, method.gamma,
                                method.min_radius_m, inplace=inplace)
    raise InputError(f"unknown radius method {method!r}: use PipeModel(...) or Allometric(...)")


def with_radii(skeleton: Skeleton, radii: np.ndarray) -> Skeleton:
    """A copy of ``skeleton`` whose ``radius`` is ``radii`` (the input is not changed)."""
    skeleton = check_skeleton(skeleton)
    radii = np.asarray(radii, dtype=np.float64).reshape(-1)
    if len(radii) != len(skeleton):
        raise InputError(f"{tree_name(skeleton)}: {len(radii)} radii for {len(skeleton)} skeleton nodes")
    if not np.all(np.isfinite(radii)) or (radii < 0).any():
        raise InputError(f"{tree_name(skeleton)}: radii must be finite and >= 0 m")
    return Skeleton(skeleton.nodes.copy(), skeleton.parent.copy(), radii.copy(),
                    skeleton.is_added.copy())


def radii_or_default(skeleton: Skeleton, radii) -> np.ndarray:
    if radii is not None:
        r = np.asarray(radii, dtype=np.float64).reshape(-1)
        if len(r) != len(skeleton):
            raise InputError(f"{tree_name(skeleton)}: {len(r)} radii for {len(skeleton)} skeleton nodes")
        if not np.all(np.isfinite(r)) or (r < 0).any():
            raise InputError(f"{tree_name(skeleton)}: radii must be finite and >= 0 m")
        return r
    if len(skeleton) and np.any(skeleton.radius > 0):
        return skeleton.radius
    return pipe_model_radii(skeleton) if len(skeleton) else np.zeros(0)
