"""Tree reconstruction: one generic verb, methods as values.

    from sylva.core.reconstruct import TreePoints, reconstruct_tree, GreedySkeleton
    rec = reconstruct_tree(TreePoints(7, xyz, ground_z=0.0))          # Hybrid(): Hu §6.2
    rec = reconstruct_tree(TreePoints(7, xyz, ground_z=0.0), GreedySkeleton(alpha_max_deg=60))
    rec.skeleton.nodes, rec.skeleton.parent, rec.visited_fraction, rec.flags

A method is a small frozen dataclass of its parameters with a
``reconstruct(tree, progress=None, cancelled=None) -> Reconstruction`` method;
adding a method adds a module or package (``skeleton.py``: Hu et al. 2017;
``colonize/``: Guo et al. 2018; ``hybrid.py``: Hu §6.2's rule, the greedy
skeleton with guided growth as the fallback, the default), not a branch here.

Trees too small or too degenerate to model (fewer than ``min_points``
points, fewer distinct points, all points within 1 cm of a line or of a
plane) do not raise: they come back with a minimal skeleton (a vertical stem
from the ground to the top, under the centre of the points' bounding box)
and a flag (``too_few_points``, ``duplicate_points``, ``collinear_points``,
``coplanar_points``).  A tree with no points at all raises
:class:`~sylva.core.errors.EmptyInputError`.
"""
from __future__ import annotations

from ..errors import InputError
from ..progress import CancelCheck, Progress
from .model import Reconstruction, Skeleton, TreePoints, minimal_skeleton
from .colonize import GuidedGrowth
from .hybrid import Hybrid
from .kmeans import VariationalKMeans, is_dense_scan
from .skeleton import GreedySkeleton

__all__ = ["TreePoints", "Skeleton", "Reconstruction", "GreedySkeleton", "GuidedGrowth", "Hybrid",
           "VariationalKMeans", "is_dense_scan", "reconstruct_tree", "minimal_skeleton"]


def reconstruct_tree(tree: TreePoints, method=Hybrid(), progress: Progress = None,
                     cancelled: CancelCheck = None) -> Reconstruction:
    """Reconstruct the skeleton of one tree with ``method`` (default: the Hu §6.2 hybrid).

    ``progress(fraction, message)`` and ``cancelled()`` are the optional
    callbacks of :mod:`sylva.core.progress`; a positive ``cancelled()``
    raises :class:`~sylva.core.errors.Cancelled`.
    """
    if not isinstance(tree, TreePoints):
        raise InputError(f"reconstruct_tree expects a TreePoints, got {type(tree).__name__}")
    if not hasattr(method, "reconstruct"):
        raise InputError(f"{method!r} is not a reconstruction method (it has no .reconstruct)")
    return method.reconstruct(tree, progress=progress, cancelled=cancelled)
