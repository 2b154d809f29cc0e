"""Variational k-means segmentation and branch reconstruction of dense scans (Yan et al. 2009).

Yan, Wintz, Mourrain, Wang, Boudon & Godin (2009), "Efficient and robust
reconstruction of botanical branching structure from laser scanned points"
(``../shared/papers/yan2009_variational_kmeans_branching.txt``), three steps:

1. **Segmentation** (§2, :func:`segment`): a kd-tree kNN graph (k = 8, §2.1);
   clusters grown from seeds and refined by Lloyd iterations on the energy of
   Eq. 1, ``E = sum_i sum_{p in C_i} |p - c_i|^2`` (§2.2); a bounding cylinder
   per cluster (principal axis + minimal enclosing circle of the projected
   points) and the RMS tightness test against δ (§2.3); unfixed clusters are
   split (parent seed + farthest point) until every cluster fits or the
   cluster budget is reached (§2.4).  Region growing is one multi-source
   Dijkstra on the kNN graph (``scipy.sparse.csgraph.dijkstra`` with
   ``min_only=True``): every point joins its geodesically nearest seed, which is
   the flooding of [CSAD04] on a point graph.  Fixed clusters keep their
   points ("will not be changed any further", §2.3): later rounds flood the
   unfixed points only.
2. **Branch reconstruction** (§3, :func:`branch_structure`): cluster adjacency
   from kNN edges that cross clusters (§3.1); a junction point per adjacent
   pair, the centre of their boundary points, and edge weights
   ``|J - c_i| + |J - c_j|`` (§3.2); the shortest-path tree from the cluster
   holding the lowest point (§3.2); extra junctions for leaf clusters and the
   root, symmetric to their junction about the cluster centre (§3.2, Fig. 4);
   branches by the longest-path rule of Algorithm 3.1 with a FIFO queue, and
   branch orders (trunk 0, a branch off a branch of order o has order o + 1).
3. **Modelling** (§4, :func:`model_branches`): a cubic B-spline (Eq. 2) fitted
   to each branch's skeleton vertices (``scipy.interpolate.splprep``), radii
   linearly interpolated from the bounding cylinders along it (§4.2), lofting
   with rotation-minimising frames (:func:`sylva.core.geometry.sweep_tube`,
   ``n2 = 10`` sides and 30 samples per branch as in §4.2 / §5), and the
   resulting cylinder list (:mod:`sylva.core.qsm`).

Additions that are not in the paper, each measured by ``benchmarks/dense.py``:
a branch whose first clusters run inside its parent (a second chain of
clusters up the other side of a thick stem) leaves from the parent's centre
line where it exits the parent (:func:`.bspline._trim_in_parent`); with
``refit=True`` the cylinders' radii and axes are fitted to the points
nearest each (circle fits, :func:`sylva.core.qsm.refit_radii`), the centre
lines moved onto the fitted axes (:func:`.refit.recentre`), a branch's base inside
its parent gets its first outside radius, no branch is thicker than the
cylinder it leaves (:func:`sylva.core.qsm.taper_radii`), and branches whose
fitted curve stays within ``prune_factor`` radii of an earlier branch are dropped
(:func:`.refit.outside_earlier_branches`).

All thresholds are in metres (the paper normalised each scan into the unit
cube; its δ in [1e-3, 1e-2] of the tree size is 1–10 cm for a 10 m tree).

:func:`is_dense_scan` is the automatic rule that sends a tree to this method
instead of the airborne methods.

Modules: :mod:`.segmentation` (§2), :mod:`.branches` (§3), :mod:`.bspline` (§4), :mod:`.refit`
(Sylva's refits) and :mod:`.method` (:class:`VariationalKMeans`, :func:`is_dense_scan`); the public
names are re-exported here.
"""
from __future__ import annotations

from .branches import BranchStructure, branch_structure
from .bspline import DenseModel, model_branches, prune_branches
from .method import (DENSE_LOW_M, DENSE_LOW_SHARE, DENSE_MIN_POINTS, DENSE_SPACING_M, SPARSE_SPACING_M,
                     VariationalKMeans, is_dense_scan)
from .segmentation import (LOCAL_FLOOD_MIN_POINTS, Segmentation, bounding_cylinders, energy, knn_graph, lloyd,
                           point_normals, segment)

__all__ = ["VariationalKMeans", "Segmentation", "BranchStructure", "DenseModel", "knn_graph",
           "segment", "lloyd", "bounding_cylinders", "energy", "branch_structure", "model_branches",
           "is_dense_scan", "DENSE_SPACING_M", "DENSE_LOW_SHARE", "DENSE_MIN_POINTS", "point_normals",
           "prune_branches"]
