"""Branch geometry: radii, branch chains, smoothing and generalised cylinders.

From a :class:`~sylva.core.reconstruct.model.Skeleton` (nodes, parents) to a
closed triangle mesh of the wood, following Hu et al. 2017 §5.5 ("Branch
geometry"):

1. **Radii.**  :func:`pipe_model_radii` — the pipe model, Hu et al. Eq. 6
   (``R_up,i^2 = sum_j R_low,j^2``, ``R_low,i = R_up,i``,
   ``R_up,tip = R_const``), generalised to any exponent ``e``;
   :func:`allometric_radii` — Guo et al. 2018 §5.1 Eq. 5
   (``d_ci = d_p (l_ci / sum_j l_cj)^gamma``) root to tip.
2. **Branches.**  :func:`branches` — chains from the root or a branching node
   to a tip; at a branching node the chain continues into the child that
   bends least (Hu §5.5: "branches with a small change of thickness and
   bending angle"), so the trunk is one chain.
3. **Smoothing.**  :func:`hermite_smooth` — cubic Hermite curves through the
   chain's nodes (Hu §5.5; Catmull-Rom tangents), radii interpolated along.
4. **Generalised cylinders.**  :func:`sweep_tube` — a polygon swept along any
   centre line with per-point radii, oriented by rotation-minimising frames
   computed with the double reflection method of Wang, Jüttler, Zheng & Liu,
   "Computation of rotation minimizing frames", ACM Trans. Graph. 27(1), 2008
   (the frames Yan et al. 2009 §4.2 use for lofting, so a B-spline centre line
   can be swept with the same function).
5. **Tree mesh.**  :func:`tree_mesh` — every branch a closed tube (caps at
   both ends), side branches starting on their parent's axis so the union
   looks joined; :class:`LevelOfDetail` trades sides, smoothing samples and
   pruned twigs.

Measurements for the trees table: :func:`wood_volume` (frusta between
nodes), :func:`branch_count`, :func:`total_branch_length`.

The sequential passes over nodes (subtree tip counts for radii, continuation
children and chains, simplification) are compiled loops (:mod:`sylva.core.jit`),
the rest is vectorised, with one segmented parallel prefix product of the
double-reflection rotations for the frames of all tubes at once.  The batch
forms :func:`branches_batch`, :func:`simplify_skeletons`,
:func:`tree_mesh_arrays_batch` and :func:`tree_meshes` run the same passes over
many trees joined into one forest (every step works per node, per chain or
per polyline), so each tree gets exactly what the single-tree call gives it.

Modules: :mod:`.passes` (depth levels, subtree sums, the input check, the forest of many skeletons),
:mod:`.radii` (step 1), :mod:`.branches` (step 2), :mod:`.tubes` (steps 3 and 4: batched polylines,
frames, sweeps), :mod:`.mesh` (step 5), :mod:`.measure` (the measurements) and :mod:`.simplify` (the
simplification); the public names are re-exported here.
"""
from __future__ import annotations

from .branches import (BranchSet, branches, branches_batch, build_branch_set, continuation_child, continuations,
                       split_branch_set, tree_branches)
from .measure import branch_count, total_branch_length, wood_volume
from .mesh import (DEFAULT_LOD, LOD, LevelOfDetail, TreeMeshParts, forest_polylines, forest_wood, tree_mesh,
                   tree_mesh_arrays, tree_mesh_arrays_batch, tree_meshes)
from .passes import (check_skeleton, depth_levels, join_forest, localise_parents, subtree_sum, tree_name,
                     trusted_skeleton)
from .radii import (Allometric, PipeModel, allometric_radii, assign_radii, pipe_model_radii, radii_or_default,
                    tip_counts, with_radii)
from .simplify import simplify_forest, simplify_skeleton, simplify_skeletons
from .tubes import dedupe, hermite_batch, hermite_smooth, norm3, rotation_minimizing_frames, sweep_tube, tube_batch

__all__ = [
    "PipeModel", "Allometric", "assign_radii", "pipe_model_radii", "allometric_radii",
    "with_radii", "BranchSet", "branches", "branches_batch", "hermite_smooth", "rotation_minimizing_frames",
    "sweep_tube", "LevelOfDetail", "LOD", "tree_mesh", "tree_meshes", "TreeMeshParts", "tree_mesh_arrays",
    "tree_mesh_arrays_batch",
    "wood_volume", "branch_count", "total_branch_length", "depth_levels", "simplify_skeleton",
    "simplify_skeletons",
]
