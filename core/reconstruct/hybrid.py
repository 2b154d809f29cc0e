"""The hybrid rule of Hu et al. 2017, §6.2: greedy skeleton first, guided growth where it fails.

Hu et al. exported a tree model "when the percentage of visited points was
greater than 85 %"; the trees that failed ("problematic because it was
difficult to generate corresponding connected graphs", Fig. 32) were rebuilt
with a space-colonisation algorithm, "the hybrid method" of Fig. 33.  Sylva's
space colonisation is Guo et al.'s point-cloud-guided growth
(:class:`~.colonize.GuidedGrowth`).

:class:`Hybrid` runs ``primary`` (default :class:`~.skeleton.GreedySkeleton`)
and keeps its result unless

* its ``visited_fraction`` is below ``min_visited`` (0.85, §6.2), or
* its graph is not ``connected``, or
* it flagged failure (``"needs_fallback"``, ``"graph_disconnected"`` or one of
  the degenerate-input flags), or
* it raised a :class:`~sylva.core.errors.SylvaError` other than
  :class:`~sylva.core.errors.Cancelled` / :class:`~sylva.core.errors.EmptyInputError`;

then it returns ``fallback``'s reconstruction (``method == "guided_growth"``
for the default fallback) with the flag ``"fallback"`` plus one
``"fallback:<reason>"`` per reason, and in ``stats`` the primary's method,
visited fraction, connectivity and flags (``primary_*``) and
``hybrid_reasons``.  Either way ``stats["hybrid_used"]`` names the method
actually used.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

from ..errors import Cancelled, EmptyInputError, InputError, SylvaError
from ..progress import CancelCheck, Progress, check, report, scaled
from .colonize import GuidedGrowth
from .model import Reconstruction, TreePoints
from .skeleton import GreedySkeleton

__all__ = ["Hybrid", "FAILURE_FLAGS"]

#: Primary flags that send a tree to the fallback whatever its visited fraction.
FAILURE_FLAGS = ("needs_fallback", "graph_disconnected", "too_few_points", "duplicate_points",
                 "collinear_points", "coplanar_points")


def _method_name(method: Any) -> str:
    return str(getattr(method, "name", type(method).__name__))


@dataclass(frozen=True)
class Hybrid:
    """Hu et al. §6.2 hybrid: ``primary``, and ``fallback`` when it visits < ``min_visited`` or fails."""

    primary: Any = field(default_factory=GreedySkeleton)
    fallback: Any = field(default_factory=GuidedGrowth)
    min_visited: float = 0.85

    name = "hybrid"

    def __post_init__(self):
        for role in ("primary", "fallback"):
            if not hasattr(getattr(self, role), "reconstruct"):
                raise InputError(f"Hybrid: {role} {getattr(self, role)!r} is not a reconstruction method "
                                 "(it has no .reconstruct)")
        if not 0.0 <= self.min_visited <= 1.0:
            raise InputError(f"Hybrid: min_visited must be in [0, 1], got {self.min_visited!r}")

    def reasons(self, rec: Reconstruction) -> list:
        """Why ``rec`` (a primary result) needs the fallback; empty when it does not."""
        out = []
        if not rec.visited_fraction >= self.min_visited:
            out.append("low_visited")
        if not rec.connected:
            out.append("disconnected")
        out.extend(f for f in rec.flags if f in FAILURE_FLAGS)
        return out

    def reconstruct(self, tree: TreePoints, progress: Progress = None,
                    cancelled: CancelCheck = None) -> Reconstruction:
        """Run the hybrid rule on one tree; see :func:`sylva.core.reconstruct.reconstruct_tree`."""
        t0 = time.perf_counter()
        check(cancelled)
        primary_name = _method_name(self.primary)
        try:
            first = self.primary.reconstruct(tree, progress=scaled(progress, 0.0, 0.5),
                                             cancelled=cancelled)
        except (Cancelled, EmptyInputError):
            raise
        except SylvaError as exc:
            first = None
            why = ["primary_error"]
            error = str(exc)
        else:
            why = self.reasons(first)
            error = None
        if not why:
            first.stats["hybrid_used"] = first.method
            first.stats["hybrid_reasons"] = []
            report(progress, 1.0, f"tree {tree.tree_id}: {primary_name}")
            return first

        check(cancelled)
        report(progress, 0.5, f"tree {tree.tree_id}: {primary_name} failed ({', '.join(why)}), "
                              f"rebuilding with {_method_name(self.fallback)}")
        rec = self.fallback.reconstruct(tree, progress=scaled(progress, 0.5, 1.0), cancelled=cancelled)
        rec.stats.update(
            hybrid_used=rec.method,
            hybrid_reasons=list(why),
            primary_method=first.method if first is not None else primary_name,
            primary_visited_fraction=float(first.visited_fraction) if first is not None else float("nan"),
            primary_connected=bool(first.connected) if first is not None else False,
            primary_flags=list(first.flags) if first is not None else [],
            t_hybrid_total_s=time.perf_counter() - t0,
        )
        if error is not None:
            rec.stats["primary_error"] = error
        rec.flags = list(rec.flags) + ["fallback"] + [f"fallback:{r}" for r in why]
        report(progress, 1.0, f"tree {tree.tree_id}: {rec.method}")
        return rec
