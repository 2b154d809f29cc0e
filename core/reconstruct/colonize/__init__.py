"""Point-cloud-guided growth (Guo et al. 2018, §5.2 and §6.1): the :class:`GuidedGrowth` method.

Space colonisation (Runions et al. 2007; Pałubicki et al. 2009) grows a
skeleton from a seed towards *markers*; Guo et al. make the tree's own points
the markers and adapt it in three ways (§5.2), all implemented here:

1. **Markers = points, weighted (Eq. 8).**  Every point p_i gets the principal
   axis n_i of its local covariance (PCA over its ``pca_k`` nearest
   neighbours, one batched ``numpy.linalg.eigh``), and the weight
   w_i = #{p_j : ‖p_i − p_j‖ < ε_D, |n_i · n_j| > ε_A} (itself included, so
   w_i ≥ 1).  Branch-like (linear) neighbourhoods get large weights, leaf
   clutter small ones.  Principal axes have no sign, hence |·|.
2. **Influence distance from a logistic model (Eq. 6–7).**  With
   K = H_max / l internodes from the root to the top (H_max the tree's
   height above ground, l = ``step_m``), Eq. 6
   H_t = K / (1 + (K/H_0 − 1) e^(−ρ_0 t)) and its derivative Eq. 7 give the
   growth units ρ_t (internodes per iteration t), and d_i = ρ_t · l.  The
   paper quotes Pałubicki's typical range d_i ∈ [4l, 12l]; Sylva clamps ρ_t
   to [``influence_min_units``, ``influence_max_units``] = [4, 12] so that
   early iterations still perceive markers.  H_0 = 2 and ρ_0 = 0.3 are the
   paper's defaults.
3. **Growth direction (Eq. 9).**  V_A = V_default + α V_opt + β V_tropism,
   V_opt = Σ w_i V_i / Σ w_i over the unit vectors V_i from the bud to its
   markers, α = 1.6, β = 0.3, V_tropism = (0, 0, −1) (the paper's (0, −1, 0)
   with y up).  A growing bud produces one growth unit (L-system 1, rule 2:
   a shoot of metamers along V_A/‖V_A‖): ⌊ρ_t⌋ internodes of length l at
   most, and no more than reach the weighted centroid of its markers (the
   growing distance of Pałubicki et al., quoted in §5.2).  Every new node
   is a metamer with its own buds.

Buds and perception (§5.2, L-system 1).  Every node carries buds: a tip its
apical bud (V_default = its heading, perception cone of half-angle θ/2,
θ = ``perception_angle_deg`` = 90°), a node that already has its apical child
one lateral bud (L-system rule 3: one lateral bud per metamer) whose
direction leaves the heading at the branching angle ψ (Table 2: 34–41°,
``branching_angle_deg`` = 38°).  The roll angle φ would fix the azimuth of
each lateral bud; since the points tell where branches are, Sylva turns the
lateral bud towards its markers (the component of V_opt across the heading)
and uses φ (``roll_angle_deg``) only when the markers give no azimuth.  The
union of the cones of lateral buds rolled around the axis is a cone of
half-angle ψ + θ/2, the lateral perception cone.  Seeds (roots, added trunk
nodes) perceive with the lateral cone from the start.  A node grows at most
one apical and one lateral child; nodes without free buds leave the bud set,
and so do buds with no marker left within the largest d_i (checked every 8
iterations).

Each iteration: every active marker is assigned to the nearest of its
k = 8 nearest buds within d_i that perceives it (the markers with a bud
within d_i form the growth front), per-bud direction sums are accumulated
in marker order, every bud with markers grows, and markers within the
kill distance d_k (``kill_distance_m``; Pałubicki: d_k = 0.5 d_i, i.e. 2l at
d_i = 4l) of a new node are removed.  When no bud perceives any marker, the
stem's apical bud (the tip of the chain of apical children from the root)
keeps growing upward — L-system rule 2 without V_opt; a stem is
orthotropic, so its heading turns halfway to the vertical per unit instead
of following the tropism — while it is below the highest marker left: this
bridges an unscanned stretch of stem between the added trunk and the crown.
Otherwise d_i is widened (×1.5 per iteration, up to 12l).  Growth stops
when no marker is left, after ``max_iterations``, or after 6 iterations
without growth; flags ``"stalled"`` / ``"max_iterations"`` are set only when
measured points are left unreached.

Implementation (Sylva, not in the paper).  The iterations are sequential, so
they run in one compiled kernel (:func:`.growth.grow_kernel`, numba through
:mod:`sylva.core.jit`; plain Python without numba), 16 iterations per call
between progress reports and cancel checks; uniform grids replace the
per-iteration ``cKDTree`` of the buds and the kill/retirement queries.  A
marker takes its buds in order of distance (the strict ``d² < d_i²`` test of
a k-d tree query), *exactly* equidistant buds (e.g. two coincident nodes) by
node index; 3-vector dot products are summed as (x₀y₀ + x₂y₂) + x₁y₁, as
numpy's einsum does.  tests/test_colonize_kernel.py guards the loop: runs are
deterministic, the Python and compiled kernels grow the same skeletons,
growing the node arrays changes nothing, and the skeletons of ~20 synthetic
trees keep golden figures within tolerances.  The PCA covariances, the hull
test and the "any point within r" tests are small kernels as well, and the
crown's convex hull is computed once for the interior test and the fill.

Crown filling (§6.1).  Airborne scans see the crown's top surface and little
of its interior.  When fewer than ``interior_min_fraction`` of the points lie
in the crown hull shrunk to half its size about the centroid (a uniformly
filled crown puts 1/8 there), Sylva adds Poisson-disk markers inside the
convex hull of the crown (points above the 5th height percentile):
a jittered grid of pitch ``fill_spacing_m`` (jitter ±¼ pitch, so any two
markers are at least half a pitch apart — the grid approximation of
Poisson-disk dart throwing), kept where the hull's facet half-spaces
(``ConvexHull.equations``) say inside and at least half a pitch from every
measured point.  Their weight is ``fill_weight`` × the median point weight (0.5: the paper gives
none; measured points dominate where both are perceived).

Root (§5.3 and §6.1).  Points within ``root_band_m`` of the ground are
clustered in xy (single linkage at ``root_link_m``; clusters of at least
``root_min_points`` points and 10 % of the low points count).

* No such cluster (the airborne case: nothing seen under the crown): the
  root and the trunk up to the crown come from Hu et al. 2017 §4.2 (Eq. 3/4,
  :func:`~.trunk.add_trunk_points`); the trunk points, one internode apart,
  become the first nodes (``is_added``).  When Eq. 3 applies (the lowest
  point v_low is on the stem), Sylva drops the trunk vertically from v_low
  rather than along n_avg: n_avg, the mean direction to v_low's few
  neighbours, is noisy, and extrapolating it over v_low's height put the
  root up to 2 m off the stem on synthetic stands.
* One cluster: the points reach the ground, and the root is put on the
  ground under the cluster's centroid (Guo §5.3 puts the root at the
  centroid of the densest cluster of projected points).
* Two or more (multi-stem shrubs, Guo §6.1, Fig. 9: "the top k cluster
  centroids", one seed each, competing for the points): every cluster gets
  a seed on the ground under its centroid and, since a :class:`Skeleton` has
  one root, the seeds hang from a virtual root on the ground under their
  size-weighted mean (``is_added``, no buds of its own; flag
  ``"multi_root"``).  ``multi_root=False`` falls back to the first rule.

Sylva parameters not in the paper are named and documented on
:class:`GuidedGrowth`; every result is deterministic (the only random draw,
the crown-filling jitter, uses ``numpy.random.default_rng(seed)``).

Modules: :mod:`.markers` (Eq. 6-8, the crown fill and the root clusters), :mod:`.growth` (the
compiled loop of §5.2) and :mod:`.method` (:class:`GuidedGrowth`); the public names are re-exported here.
"""
from __future__ import annotations

from .markers import (RootClusters, crown_fill_markers, find_root_clusters, influence_distance, interior_fraction,
                      pca_weights)
from .method import GuidedGrowth, SPECIES_PRESETS

__all__ = ["GuidedGrowth", "SPECIES_PRESETS", "pca_weights", "influence_distance",
           "crown_fill_markers", "interior_fraction", "find_root_clusters"]
