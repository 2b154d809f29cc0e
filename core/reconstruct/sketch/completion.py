"""The airborne variant: :class:`SketchCompletion` completes a point-cloud skeleton with the sketch paper's
self-similar small branches (§6) inside the crown silhouettes of the tree's own points
(:func:`crown_silhouettes`, seen from the south and from the east)."""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from ...progress import CancelCheck, Progress, check, report, scaled
from ..model import Reconstruction, TreePoints
from .params import SketchTree
from .small_branches import grow_small_branches


# --------------------------------------------------------------------------- airborne completion

def crown_silhouettes(xyz: np.ndarray, crown_base_z: float, concavity: float = 0.5, margin_m: float = 0.3):
    """Crown silhouettes of a point cloud seen from the south (x–z) and the east (y–z).

    The hull (shapely concave hull with ``concavity`` as its ratio, 1 = convex)
    of the points above ``crown_base_z`` projected on each plane, widened by ``margin_m``.
    """
    import shapely

    out = []
    crown = xyz[xyz[:, 2] >= crown_base_z]
    if len(crown) < 3:
        crown = xyz
    for cols in ((0, 2), (1, 2)):
        mp = shapely.MultiPoint(crown[:, cols])
        hull = shapely.concave_hull(mp, ratio=concavity) if concavity < 1 else shapely.convex_hull(mp)
        out.append(hull.buffer(margin_m))
    return tuple(out)


@dataclass(frozen=True)
class SketchCompletion:
    """Airborne trees completed with the sketch paper's small branches (§6).

    ``primary`` builds the main skeleton from the points (default Hu et al.'s
    :class:`GreedySkeleton`); then :func:`grow_small_branches` adds
    self-similar sub-branches (``sketch`` parameters, Table 1 defaults) inside
    the crown silhouettes of the points seen from two orthogonal sides
    (:func:`crown_silhouettes`, ``concavity``, ``margin_m``), with trunk buds
    only above the crown base (the lowest fork of the main skeleton).  A method
    value for :func:`sylva.core.reconstruct.reconstruct_tree`; ``name`` is
    "sketch_completion" and ``stats["n_small_nodes"]`` counts the added nodes.
    """

    primary: Any = None
    sketch: SketchTree = SketchTree()
    concavity: float = 0.5
    margin_m: float = 0.3

    name = "sketch_completion"

    def reconstruct(self, tree: TreePoints, progress: Progress = None,
                    cancelled: CancelCheck = None) -> Reconstruction:
        from ..skeleton import GreedySkeleton

        t0 = time.perf_counter()
        primary = self.primary if self.primary is not None else GreedySkeleton()
        rec = primary.reconstruct(tree, progress=scaled(progress, 0.0, 0.7), cancelled=cancelled)
        sk = rec.skeleton
        if len(sk) < 3 or len(tree.xyz) < 3:
            rec.flags = list(rec.flags) + ["not_completed"]
            return rec
        check(cancelled)
        forks = sk.nodes[sk.n_children() >= 2, 2]
        crown_base = float(forks.min()) if len(forks) else float(tree.ground_z)
        fs, ss = crown_silhouettes(tree.xyz, crown_base, self.concavity, self.margin_m)
        height = float(tree.xyz[:, 2].max() - tree.ground_z)
        grown, level = grow_small_branches(sk, self.sketch, fs, ss, crown_base, height, cancelled)
        out = grown
        stats = dict(rec.stats)
        stats.update(primary_method=rec.method, n_small_nodes=int((level > 0).sum()),
                     t_completion_s=time.perf_counter() - t0)
        report(progress, 1.0, f"tree {tree.tree_id}: crown completed")
        return Reconstruction(out, self.name, rec.visited_fraction, rec.connected, stats, list(rec.flags),
                              rec.tree_id)
