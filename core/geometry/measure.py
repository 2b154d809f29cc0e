"""Measurements for the trees table: :func:`wood_volume` (frusta between nodes), :func:`branch_count`,
:func:`total_branch_length`.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from ..skeleton import Skeleton
from .branches import BranchSet, branches, continuation_child
from .passes import check_skeleton
from .radii import radii_or_default


def wood_volume(skeleton: Skeleton, radii: Optional[np.ndarray] = None,
                branch_set: Optional[BranchSet] = None) -> float:
    """Wood volume in m³: the sum of truncated cones (frusta) between nodes.

    ``V = pi h (r1^2 + r1 r2 + r2^2) / 3`` per segment, with the node radii of
    ``radii`` (default ``skeleton.radius``).  As in :func:`tree_mesh`, a side
    branch's first segment starts with the branch's own radius, not the
    (thicker) radius of the node it leaves; the overlap of a side branch with
    its parent near the joint is not subtracted.  ``branch_set`` may pass
    ``branches(skeleton, radii)`` when the caller has it already.
    """
    skeleton = check_skeleton(skeleton)
    rad = skeleton.radius if radii is None else radii_or_default(skeleton, radii)
    child, par = skeleton.segments()
    if len(child) == 0:
        return 0.0
    h = np.linalg.norm(skeleton.nodes[child] - skeleton.nodes[par], axis=1)
    cont = branch_set.continuation if branch_set is not None else continuation_child(skeleton, rad)
    r2 = rad[child]
    r1 = np.where(cont[par] == child, rad[par], r2)
    return float((np.pi * h * (r1 * r1 + r1 * r2 + r2 * r2) / 3.0).sum())


def _stored_radii(skeleton: Skeleton) -> Optional[np.ndarray]:
    return skeleton.radius if len(skeleton) and np.any(skeleton.radius > 0) else None


def branch_count(skeleton: Skeleton, include_stem: bool = False, branch_set: Optional[BranchSet] = None) -> int:
    """Number of branches (chains of :func:`branches`); the stem is not counted unless asked.

    ``branch_set`` may pass ``branches(skeleton, skeleton.radius)`` when the caller has it already.
    """
    if not len(skeleton):
        n = 0
    else:
        n = len(branch_set if branch_set is not None else branches(skeleton, _stored_radii(skeleton)))
    if n == 0:
        return 0
    return n if include_stem else n - 1


def total_branch_length(skeleton: Skeleton, include_stem: bool = False,
                        branch_set: Optional[BranchSet] = None) -> float:
    """Summed length in metres of all branches (the stem chain left out unless asked).

    ``branch_set`` may pass ``branches(skeleton, skeleton.radius)`` when the caller has it already.
    """
    skeleton = check_skeleton(skeleton)
    if len(skeleton) < 2:
        return 0.0
    total = skeleton.length()
    if include_stem:
        return total
    bset = branch_set if branch_set is not None else branches(skeleton, _stored_radii(skeleton))
    stem = bset.nodes[bset.offsets[0]:bset.offsets[1]]
    return float(total - np.linalg.norm(np.diff(skeleton.nodes[stem], axis=0), axis=1).sum())
