"""Trees from two sketched profiles: Sketch-based tree modeling from two views (the sketch paper), §4–§7.

The user digitises the main branches of a tree as line strokes over two
photos taken from roughly orthogonal sides (a *front* and a *side* view),
optionally a crown silhouette polygon per view, and gives the tree's height.
The method builds:

1. a 2D skeleton per view from the strokes (§4.1).  The paper traverses
   single-pixel strokes pixel by pixel; digitised strokes are already
   polylines, so the "pixels" are the vertices, and the junctions the paper
   finds by local pixel analysis are the strokes' intersections plus the
   stroke ends that stop within ``snap_fraction`` of another stroke
   (:func:`stroke_graph`).  The graph is traversed breadth-first from the
   lowest vertex of the trunk stroke (§4.1.2 "from the lowest one"), which
   gives a rooted tree (cycles of crossing strokes are cut where the traversal
   meets itself), and decomposed into branches with the least-bending
   continuation of :func:`sylva.core.geometry.branches`;
2. the 3D main branches by *depth retrieval* (§5): for every branch λ of the
   front skeleton A, level by level, the branch μ of the side skeleton B that
   passes the bud height V = b(λ) and minimises F = |M(μ) − M(λ)| (Eq. 1, 3;
   M the maximum extension height) gives each point of λ its depth at the same
   height (Eq. 4–6, y up in the paper: x from λ, depth z from μ, y shared); when λ climbs above H(μ)
   (or dips below h(μ)) a new μ is matched at that height (§5.1 rule 3).
   Branch extension (§5.2): when the point P_b of μ at the bud height is not on
   μ's *available descending path* (the side-view nodes already used by the 3D
   ancestors of λ's bud), λ and μ are extended down their descending paths to
   the highest used node, so the new 3D branch leaves the structure there and
   projects onto both drawings.  Branch complementarity (§5.3): the side-view
   stroke parts left unused are built the same way with the roles swapped;
3. small branches by self-similarity (§6, Fig. 16, Table 1): a sub-branch is a
   copy of the first σ·k nodes of its parent branch η (Eq. 8), attached at a
   bud S_x of η with angle θ to η (cos θ1 ≥ cos θ ≥ cos θ2 is Table 1's
   0.5…0.9) and angle φ to the previous sub-branch of η (cos φ in −0.5…0.5),
   for ``levels`` l = 2 generations; buds in crowded places are removed, and
   nodes whose projection leaves a crown silhouette are cut off (the branch
   keeps its part up to the first node outside);
4. radii (da Vinci's rule, §7: the pipe model of :mod:`sylva.core.geometry`),
   meshes and leaves are the shared code's (see ``algorithms/sketch.py``).

Drawing frame (Sylva's convention, documented for the user): each view's
strokes are in any 2D units with y up.  The lowest vertex of the trunk stroke
(the stroke holding the lowest vertex of the view) is the base; each view is
scaled on its own so that its drawing height (highest vertex − base) equals
``height_m``.  The front view's horizontal axis becomes x (east) and the side
view's becomes y (north), both through the base, z up: with
``front_azimuth_deg`` = 0 the front photo is taken looking north (its right
is east) and the side photo looking west (its right is north).  A non-zero
``front_azimuth_deg`` (compass bearing the front photo looks along) turns the
tree about its base: the front drawing's right is then the bearing
``azimuth + 90°`` and the side drawing's right the bearing ``azimuth``.

Where Sylva differs from the printed method (each documented where it is done):
digitised strokes carry no width, so Eq. 2 and Eq. 7 (brush radii) are not
used and radii come from the pipe model; the *used path* of §5.2 is read from
the 3D structure (side-view nodes whose 3D node is an ancestor of the bud);
when no side branch passes a height, the branch nearest in height is used;
re-matches (§5.1 rule 3) prefer a branch passing within the snapping
tolerance of the current depth, and complementary runs (§5.3) are not
extended, prefer a front branch passing near the node they hang from, and keep
that node's depth when there is none; a sub-branch's first copied node S_1
sits on the bud S_x; the bud count and crowding limits are Sylva's values.

The airborne variant :class:`SketchCompletion` completes the crown of a
:class:`~sylva.core.reconstruct.skeleton.GreedySkeleton` with the same
self-similar small branches, pruned by silhouettes computed from the tree's
own points seen from the south (x–z) and from the east (y–z).

Modules: :mod:`.params` (:class:`SketchTree`), :mod:`.strokes` (step 1: strokes to 2D skeletons, §4),
:mod:`.depth` (step 2: depth retrieval, §5), :mod:`.small_branches` (step 3, §6), :mod:`.tree` (the whole
method, :func:`tree_from_sketch`) and :mod:`.completion` (:class:`SketchCompletion`); the public names are
re-exported here.
"""
from __future__ import annotations

from .completion import SketchCompletion, crown_silhouettes
from .depth import depth_retrieval
from .params import SketchTree
from .small_branches import grow_small_branches
from .strokes import StrokeGraph, View, skeleton_2d, stroke_graph, vertices_xy
from .tree import SketchResult, project_front, project_side, projection_error, tree_from_sketch

__all__ = ["SketchTree", "SketchResult", "StrokeGraph", "SketchCompletion", "stroke_graph",
           "skeleton_2d", "depth_retrieval", "grow_small_branches", "tree_from_sketch",
           "crown_silhouettes", "project_front", "project_side", "projection_error"]
