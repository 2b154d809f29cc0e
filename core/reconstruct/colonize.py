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

Each iteration (vectorised; the Python loop runs over iterations only):
every active marker is assigned to the nearest bud that perceives it within
d_i (a ``cKDTree`` of the current buds, rebuilt per iteration; one nearest
query of all active markers finds the growth front, one k = 8 query of the
front gives the candidates for the perception test), per-bud direction sums
use ``np.add.at``, every bud with markers grows, and markers within the
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
"""
from __future__ import annotations

import time
from dataclasses import dataclass, fields
from typing import NamedTuple, Optional

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import ConvexHull, QhullError, cKDTree

from ..errors import InputError
from ..progress import CancelCheck, Progress, check, report
from .model import Reconstruction, Skeleton, TreePoints, screen
from .trunk import add_trunk_points

__all__ = ["GuidedGrowth", "SPECIES_PRESETS", "pca_weights", "influence_distance",
           "crown_fill_markers", "interior_fraction", "find_root_clusters"]

#: Species parameter sets (Guo et al. §5.1: parameters "pre-generated ... in a species
#: library").  The paper's Table 2 measures broadleaved plants only (ψ 34–41°,
#: φ 87–130°); the conifer and shrub sets are Sylva's: conifer branches leave the stem
#: nearly horizontally (ψ 70°) and droop (stronger tropism); shrubs have short
#: internodes, narrow branching and several stems from the ground.  A preset
#: overrides a field only where the field still has its default value.
SPECIES_PRESETS = {
    "conifer": dict(branching_angle_deg=70.0, roll_angle_deg=137.5, tropism=0.5),
    "broadleaf": dict(branching_angle_deg=38.0, roll_angle_deg=105.0, tropism=0.3),
    "shrub": dict(step_m=0.15, kill_distance_m=0.3, branching_angle_deg=30.0,
                  roll_angle_deg=95.0, tropism=0.2, root_band_m=0.6, root_link_m=0.5),
}

_UP = np.array([0.0, 0.0, 1.0])
_DOWN = np.array([0.0, 0.0, -1.0])
_K_BUDS = 8          # nearest buds examined per marker for the perception test
_STALL_LIMIT = 6     # consecutive iterations without growth (d_i widened x1.5 each) before stopping


# --------------------------------------------------------------------------- building blocks
def pca_weights(xyz: np.ndarray, radius_m: float, cos_min: float = 0.9, k: int = 10):
    """Guo et al. §5.2, Eq. 8: (weights, principal axes) of every point.

    The principal axis n_i is the eigenvector of the largest eigenvalue of
    the covariance of p_i's ``k`` nearest neighbours; the weight counts the
    points within ``radius_m`` (ε_D) whose axis is within ``cos_min`` (ε_A)
    of n_i in absolute value, p_i itself included (w_i ≥ 1).  Vectorised.
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    n = len(xyz)
    if n == 0:
        return np.zeros(0), np.zeros((0, 3))
    tree = cKDTree(xyz)
    kk = max(1, min(int(k), n))
    _, idx = tree.query(xyz, k=kk)
    nb = xyz[np.asarray(idx).reshape(n, kk)]
    c = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", c, c) / kk
    _, vec = np.linalg.eigh(cov)
    axis = vec[:, :, -1]
    pairs = tree.query_pairs(radius_m, output_type="ndarray")
    w = np.ones(n)
    if len(pairs):
        sim = np.abs((axis[pairs[:, 0]] * axis[pairs[:, 1]]).sum(axis=1)) > cos_min
        p = pairs[sim]
        w += np.bincount(p[:, 0], minlength=n) + np.bincount(p[:, 1], minlength=n)
    return w, axis


def influence_distance(t, height_m: float, step_m: float, h0: float = 2.0, rho0: float = 0.3,
                       min_units: float = 4.0, max_units: float = 12.0):
    """Guo et al. §5.2, Eq. 6–7: influence distance d_i = ρ_t · l at iteration ``t`` (metres).

    K = H_max / l internodes (H_max = ``height_m``), H_t = K / (1 + (K/H_0 − 1) e^(−ρ_0 t))
    (Eq. 6), ρ_t = dH_t/dt (Eq. 7), clamped to [min_units, max_units]
    (Pałubicki's d_i ∈ [4l, 12l] quoted by Guo).  Works on arrays of t.
    """
    K = max(float(height_m) / step_m, h0 * 1.0001)
    a = K / h0 - 1.0
    e = a * np.exp(-rho0 * np.asarray(t, dtype=np.float64))
    rho = K * rho0 * e / (1.0 + e) ** 2
    return np.clip(rho, min_units, max_units) * step_m


def _inside_hull(hull: ConvexHull, points: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Per point: inside ``hull`` (its facet half-spaces ``A x + b <= 0``, vectorised)."""
    eq = hull.equations
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return (np.einsum("ni,fi->nf", p, eq[:, :3]) + eq[:, 3] <= tol).all(axis=1)


def _hull(xyz: np.ndarray) -> Optional[ConvexHull]:
    """Convex hull of ``xyz``, None when it is flat or has too few points."""
    if len(xyz) < 4:
        return None
    try:
        return ConvexHull(xyz)
    except (QhullError, ValueError):
        return None


def interior_fraction(xyz: np.ndarray, shrink: float = 0.5) -> float:
    """Share of points inside the convex hull shrunk by ``shrink`` about the points' centroid.

    A crown filled uniformly gives ``shrink**3`` (1/8); an airborne crown,
    whose interior is occluded, much less (Guo §6.1's "invisible interior").
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    hull = _hull(xyz)
    if hull is None:
        return 0.0
    c = xyz.mean(axis=0)
    # x is inside the hull shrunk about c  <=>  c + (x - c) / shrink is inside the hull.
    return float(_inside_hull(hull, c + (xyz - c) / shrink).mean())


def crown_fill_markers(xyz: np.ndarray, spacing_m: float, seed: int = 0,
                       max_markers: int = 50_000) -> np.ndarray:
    """Guo et al. §6.1: Poisson-disk-like markers inside the convex hull of ``xyz``.

    A grid of pitch ``spacing_m`` over the hull's bounding box, each cell
    centre jittered uniformly by ±¼ pitch per axis (seeded), so two markers
    are at least ½ pitch apart; kept where the hull's facet half-spaces
    (``ConvexHull.equations``) put them inside and at least ½ pitch from every point of ``xyz``.
    The pitch grows if the box would hold more than ``max_markers`` cells.
    Returns (m, 3); empty when the hull is flat.
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    hull = _hull(xyz)
    if hull is None:
        return np.zeros((0, 3))
    v = xyz[hull.vertices]
    lo, hi = v.min(axis=0), v.max(axis=0)
    s = float(spacing_m)
    cells = np.ceil((hi - lo) / s).astype(np.int64) + 1
    if cells.prod() > max_markers:
        s *= (cells.prod() / max_markers) ** (1.0 / 3.0)
        cells = np.ceil((hi - lo) / s).astype(np.int64) + 1
    ii = np.indices(cells).reshape(3, -1).T
    rng = np.random.default_rng([int(seed), 0x6C0])
    cand = lo + ii * s + rng.uniform(-0.25 * s, 0.25 * s, size=ii.shape)
    cand = cand[_inside_hull(hull, cand)]
    if len(cand):
        d, _ = cKDTree(xyz).query(cand, distance_upper_bound=0.5 * s)
        cand = cand[~np.isfinite(d)]
    return cand


class RootClusters(NamedTuple):
    """Result of :func:`find_root_clusters`."""

    centres: np.ndarray     # (k, 2) xy centroids of the low clusters, k >= 1
    sizes: np.ndarray       # (k,) points per cluster


def find_root_clusters(xyz: np.ndarray, ground_z: float, band_m: float, link_m: float,
                       min_points: int = 5) -> Optional[RootClusters]:
    """Separate clusters of points within ``band_m`` of the ground (Guo §6.1, multiple roots).

    The low points are linked in xy when closer than ``link_m`` (single
    linkage: ``cKDTree.query_pairs`` + connected components); clusters of at
    least ``min_points`` points and 10 % of the low points count.  Returns
    None when there is none.  Clusters are ordered by x, then y.
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    low = xyz[xyz[:, 2] - ground_z < band_m, :2]
    if len(low) < 2 * min_points:
        return None
    pairs = cKDTree(low).query_pairs(link_m, output_type="ndarray")
    m = len(low)
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(m, m)) if len(pairs) \
        else coo_matrix((m, m))
    _, lab = connected_components(g, directed=False)
    sizes = np.bincount(lab)
    keep = np.flatnonzero(sizes >= max(min_points, 0.1 * m))
    if len(keep) < 1:
        return None
    cx = np.bincount(lab, weights=low[:, 0])[keep] / sizes[keep]
    cy = np.bincount(lab, weights=low[:, 1])[keep] / sizes[keep]
    order = np.lexsort((cy, cx))
    return RootClusters(np.stack([cx, cy], axis=1)[order], sizes[keep][order])


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(n > 1e-12, v / np.maximum(n, 1e-12), 0.0)


class _Nodes:
    """Growable node arrays (amortised doubling); parents always before children."""

    def __init__(self, cap: int = 256):
        self.m = 0
        self.pos = np.zeros((cap, 3))
        self.heading = np.zeros((cap, 3))
        self.parent = np.full(cap, -1, dtype=np.int64)
        self.n_children = np.zeros(cap, dtype=np.int64)
        self.seed = np.zeros(cap, dtype=bool)        # roots/trunk: lateral cone from the start
        self.bud_free = np.zeros(cap, dtype=bool)
        self.added = np.zeros(cap, dtype=bool)
        self.leader = np.zeros(cap, dtype=bool)      # on the stem's apical line (root upwards)

    def add(self, pos, heading, parent, seed=False, added=False, buds=True, leader=False):
        pos = np.asarray(pos, dtype=np.float64).reshape(-1, 3)
        k = len(pos)
        need = self.m + k
        if need > len(self.pos):
            cap = max(need, 2 * len(self.pos))
            for name in ("pos", "heading", "parent", "n_children", "seed", "bud_free", "added", "leader"):
                old = getattr(self, name)
                new = np.zeros((cap,) + old.shape[1:], dtype=old.dtype)
                if name == "parent":
                    new[:] = -1
                new[:self.m] = old[:self.m]
                setattr(self, name, new)
        s = slice(self.m, need)
        self.pos[s] = pos
        self.heading[s] = np.asarray(heading, dtype=np.float64).reshape(-1, 3)
        self.parent[s] = parent
        self.seed[s] = seed
        self.added[s] = added
        self.bud_free[s] = buds
        self.leader[s] = leader
        par = np.atleast_1d(np.asarray(parent, dtype=np.int64))
        par = par[par >= 0]
        if len(par):
            np.add.at(self.n_children, par, 1)
        first = self.m
        self.m = need
        return np.arange(first, need)


# --------------------------------------------------------------------------- the method
@dataclass(frozen=True)
class GuidedGrowth:
    """Guo et al. (2018) point-cloud-guided space colonisation (§5.2) with crown filling (§6.1).

    Parameters (paper defaults where the paper gives one):

    * ``step_m`` internode length l (Table 1).  Guo's Table 2 gives
      l ≈ 0.05 for plants scaled into a 10 m box; airborne crowns are sampled
      every ~0.3 m, so Sylva uses 0.25 m;
    * ``kill_distance_m`` d_k; Pałubicki (quoted in §5.2): d_k = 0.5 d_i with
      d_i ≥ 4l, so 2l = 0.5 m.  Also the coverage distance of
      ``visited_fraction``;
    * ``influence_h0`` H_0 = 2, ``influence_rho0`` ρ_0 = 0.3 (Eq. 6–7);
      ``influence_min_units`` / ``influence_max_units`` clamp ρ_t to
      Pałubicki's d_i ∈ [4l, 12l];
    * ``perception_angle_deg`` θ = 90° (§5.2); ``branching_angle_deg`` ψ
      (Table 2: 34–41°, 38°); ``roll_angle_deg`` φ (Table 2: 87–130°, 105°);
    * ``attraction_weight`` α = 1.6 and ``tropism`` β = 0.3 of Eq. 9, the
      tropism vector pointing down;
    * ``similarity_radius_m`` ε_D and ``similarity_cos`` ε_A = 0.9 of Eq. 8.
      The paper's ε_D = 3 cm suits dense photogrammetric clouds in a 10 m
      box; airborne point spacing is ~10× larger, so Sylva uses 0.5 m;
      ``pca_k`` neighbours of the PCA (not given: 10);
    * ``crown_fill`` "auto" (fill when ``interior_fraction`` <
      ``interior_min_fraction`` = 1/16, half of what a uniformly filled
      crown gives), "always" or "never";
      ``fill_spacing_m`` pitch of the fill markers (not given: 1.0 m, the
      smallest influence distance 4l, so the markers form one perceivable field),
      ``fill_weight`` their weight relative to the median point weight (0.5);
      ``fill_max_per_point`` caps the fill grid at that many cells per
      measured point (2.0; the pitch grows beyond ``fill_spacing_m`` for big,
      sparsely sampled crowns, so the fill guides the growth without
      outweighing the data);
    * ``multi_root``, ``root_band_m`` (1.0 m), ``root_link_m`` (0.75 m),
      ``root_min_points`` (5): multi-stem detection (§6.1);
    * ``trunk_radius_m``, ``lambda1_max_deg``, ``lambda2_max``: Hu et al.
      §4.2 root and trunk (1.0 m, 30°, 0.5);
    * ``max_iterations`` (2000), ``min_points`` (10: fewer distinct points
      give a minimal skeleton and a flag), ``seed`` of the fill jitter;
    * ``species`` None or a key of :data:`SPECIES_PRESETS` ("conifer",
      "broadleaf", "shrub"); the preset's values replace fields left at
      their defaults.
    """

    step_m: float = 0.25
    kill_distance_m: float = 0.5
    influence_h0: float = 2.0
    influence_rho0: float = 0.3
    influence_min_units: float = 4.0
    influence_max_units: float = 12.0
    perception_angle_deg: float = 90.0
    branching_angle_deg: float = 38.0
    roll_angle_deg: float = 105.0
    attraction_weight: float = 1.6
    tropism: float = 0.3
    similarity_radius_m: float = 0.5
    similarity_cos: float = 0.9
    pca_k: int = 10
    crown_fill: str = "auto"
    interior_min_fraction: float = 0.0625
    fill_spacing_m: float = 1.0
    fill_weight: float = 0.5
    fill_max_per_point: float = 2.0
    multi_root: bool = True
    root_band_m: float = 1.0
    root_link_m: float = 0.75
    root_min_points: int = 5
    trunk_radius_m: float = 1.0
    lambda1_max_deg: float = 30.0
    lambda2_max: float = 0.5
    max_iterations: int = 2000
    min_points: int = 10
    seed: int = 0
    species: Optional[str] = None

    name = "guided_growth"

    def __post_init__(self):
        if self.species is not None:
            if self.species not in SPECIES_PRESETS:
                raise InputError(f"GuidedGrowth: unknown species {self.species!r}; choose one of "
                                 f"{', '.join(SPECIES_PRESETS)} (or None)")
            defaults = {f.name: f.default for f in fields(self)}
            for key, value in SPECIES_PRESETS[self.species].items():
                if getattr(self, key) == defaults[key]:
                    object.__setattr__(self, key, value)
        for attr in ("step_m", "kill_distance_m", "influence_h0", "influence_rho0", "influence_min_units",
                     "similarity_radius_m", "fill_spacing_m", "root_band_m", "root_link_m",
                     "trunk_radius_m"):
            if not getattr(self, attr) > 0:
                raise InputError(f"GuidedGrowth: {attr} must be positive, got {getattr(self, attr)!r}")
        if not self.influence_max_units >= self.influence_min_units:
            raise InputError("GuidedGrowth: influence_max_units must be >= influence_min_units")
        for attr in ("perception_angle_deg", "branching_angle_deg", "lambda1_max_deg"):
            if not 0 < getattr(self, attr) <= 360:
                raise InputError(f"GuidedGrowth: {attr} must be in (0, 360] degrees, got {getattr(self, attr)!r}")
        if self.attraction_weight < 0 or self.tropism < 0 or self.fill_weight < 0 \
                or self.fill_max_per_point < 0:
            raise InputError("GuidedGrowth: attraction_weight, tropism, fill_weight and "
                             "fill_max_per_point must be >= 0")
        if not 0 <= self.similarity_cos <= 1 or not 0 <= self.interior_min_fraction <= 1:
            raise InputError("GuidedGrowth: similarity_cos and interior_min_fraction must be in [0, 1]")
        if self.crown_fill not in ("auto", "always", "never"):
            raise InputError(f"GuidedGrowth: crown_fill must be 'auto', 'always' or 'never', "
                             f"got {self.crown_fill!r}")
        for attr in ("pca_k", "max_iterations", "min_points", "root_min_points"):
            v = getattr(self, attr)
            if int(v) != v or v < 1:
                raise InputError(f"GuidedGrowth: {attr} must be a whole number >= 1, got {v!r}")

    # -- seeds ---------------------------------------------------------------
    def _seed(self, nodes: _Nodes, xyz: np.ndarray, ground_z: float, stats: dict, flags: list):
        """Root(s) and added trunk nodes; returns nothing, fills ``nodes``."""
        clusters = find_root_clusters(xyz, ground_z, self.root_band_m, self.root_link_m,
                                      int(self.root_min_points))
        if clusters is not None and len(clusters.centres) > 1 and not self.multi_root:
            clusters = None
        if clusters is not None and len(clusters.centres) == 1:
            # The points reach the ground: the root is under them (Guo §5.3: the centroid
            # of the densest cluster of projected points), no trunk needs adding.
            c = clusters.centres[0]
            nodes.add([c[0], c[1], ground_z], _UP, -1, seed=True, added=True, leader=True)
            stats.update(n_roots=1, root_rule="low_points")
            return
        if clusters is not None:
            k = len(clusters.centres)
            centre = (clusters.centres * clusters.sizes[:, None]).sum(axis=0) / clusters.sizes.sum()
            nodes.add([centre[0], centre[1], ground_z], _UP, -1, seed=True, added=True, buds=False)
            pos = np.c_[clusters.centres, np.full(k, ground_z)]
            nodes.add(pos, np.tile(_UP, (k, 1)), np.zeros(k, dtype=np.int64), seed=True, added=True,
                      leader=True)
            stats.update(n_roots=int(k), root_rule="clusters")
            flags.append("multi_root")
            return
        trunk = add_trunk_points(xyz, ground_z, self.trunk_radius_m, self.step_m,
                                 self.lambda1_max_deg, self.lambda2_max)
        pts = trunk.points
        direction = _unit(trunk.direction)
        if trunk.rule == "eq3":
            # Eq. 3 extrapolates the mean direction n_avg from the lowest point's few
            # neighbours over the whole height h; on synthetic stands its ~25° of noise put
            # the root up to 2 m off the stem.  The guided growth follows the stem points
            # upward by itself, so Sylva drops the stem vertically from v_low instead.
            top = trunk.v_low
            h = max(float(top[2] - ground_z), 0.0)
            t = np.linspace(0.0, 1.0, max(1, int(np.ceil(h / self.step_m))) + 1)[:, None]
            root = np.array([top[0], top[1], ground_z])
            pts = root + t * (top - root)
            direction = _UP
        m = len(pts)
        head = np.tile(direction, (m, 1))
        nodes.add(pts, head, np.arange(-1, m - 1), seed=True, added=True, leader=True)
        stats.update(n_roots=1, root_rule=trunk.rule, n_trunk_nodes=int(m))

    # -- the method ----------------------------------------------------------
    def reconstruct(self, tree: TreePoints, progress: Progress = None,
                    cancelled: CancelCheck = None) -> Reconstruction:
        """Grow the skeleton of one tree; see :func:`sylva.core.reconstruct.reconstruct_tree`."""
        t_all = time.perf_counter()
        if not isinstance(tree, TreePoints):
            raise InputError(f"GuidedGrowth expects a TreePoints, got {type(tree).__name__}")
        xyz = tree.xyz
        n = len(xyz)
        ground_z, flags, degenerate = screen(tree, int(self.min_points), self.name, progress)
        if degenerate is not None:
            degenerate.visited_fraction = self._coverage(degenerate.skeleton.nodes, xyz)
            degenerate.connected = True
            return degenerate
        stats = {"n_points": int(n)}

        # Markers and their weights (Eq. 8).
        check(cancelled)
        t0 = time.perf_counter()
        w, _ = pca_weights(xyz, self.similarity_radius_m, self.similarity_cos, int(self.pca_k))
        stats["t_weights_s"] = time.perf_counter() - t0
        stats["weight_median"] = float(np.median(w))

        # Crown filling (§6.1).
        t0 = time.perf_counter()
        crown = xyz[xyz[:, 2] >= np.percentile(xyz[:, 2], 5.0)]
        frac = interior_fraction(crown)
        stats["interior_fraction"] = frac
        fill = np.zeros((0, 3))
        if self.crown_fill == "always" or (self.crown_fill == "auto" and frac < self.interior_min_fraction):
            fill = crown_fill_markers(crown, self.fill_spacing_m, self.seed,
                                      max_markers=max(64, int(self.fill_max_per_point * n)))
            if len(fill):
                flags.append("crown_filled")
        markers = np.concatenate([xyz, fill])
        weight = np.r_[w, np.full(len(fill), self.fill_weight * float(np.median(w)))]
        stats.update(n_fill=int(len(fill)), n_markers=int(len(markers)),
                     t_fill_s=time.perf_counter() - t0)
        report(progress, 0.1, "markers")

        # Seeds, then growth (§5.2).
        t0 = time.perf_counter()
        nodes = _Nodes(max(256, 2 * n))
        self._seed(nodes, xyz, ground_z, stats, flags)
        height = float(xyz[:, 2].max() - ground_z)
        it, reason = self._grow(nodes, markers, weight, n, height, progress, cancelled)
        if reason != "done":
            flags.append(reason)
        stats.update(t_growth_s=time.perf_counter() - t0, n_iterations=int(it), n_nodes=int(nodes.m))
        m = nodes.m
        skel = Skeleton(nodes.pos[:m].copy(), nodes.parent[:m].copy(), is_added=nodes.added[:m].copy())
        visited = self._coverage(skel.nodes, xyz)
        stats["t_total_s"] = time.perf_counter() - t_all
        report(progress, 1.0, "guided growth")
        return Reconstruction(skel, self.name, visited, True, stats, flags, tree.tree_id)

    def _coverage(self, nodes: np.ndarray, xyz: np.ndarray) -> float:
        """Share of ``xyz`` within the kill distance of a node."""
        d, _ = cKDTree(nodes).query(xyz, distance_upper_bound=self.kill_distance_m * (1 + 1e-9))
        return float(np.isfinite(d).mean()) if len(xyz) else 0.0

    def _grow(self, nodes: _Nodes, markers: np.ndarray, weight: np.ndarray, n_measured: int,
              height_m: float, progress: Progress, cancelled: CancelCheck):
        """Iterate space colonisation until no marker is left; returns (iterations, reason).

        ``markers[:n_measured]`` are the tree's points, the rest crown-filling
        markers; ``reason`` is "done", "stalled" or "max_iterations" (the
        last two only when measured points are left unreached) or
        "node_limit" (more than 20 nodes per marker: a safety net).
        """
        l = float(self.step_m)
        dk = float(self.kill_distance_m)
        cos_apical = np.cos(np.radians(min(self.perception_angle_deg / 2.0, 180.0)))
        half_lat = min(self.perception_angle_deg / 2.0 + self.branching_angle_deg, 180.0)
        cos_lateral = np.cos(np.radians(half_lat))
        psi = np.radians(self.branching_angle_deg)
        roll = np.radians(self.roll_angle_deg)
        alpha, beta = float(self.attraction_weight), float(self.tropism)
        di_max = float(self.influence_max_units) * l
        node_limit = 20 * len(markers) + 10_000      # a safety net, never reached in practice
        di_of_t = influence_distance(np.arange(int(self.max_iterations)), height_m, l, self.influence_h0,
                                     self.influence_rho0, self.influence_min_units,
                                     self.influence_max_units)

        active = np.ones(len(markers), dtype=bool)
        # Markers already within d_k of the seeds are taken.
        d, _ = cKDTree(nodes.pos[:nodes.m]).query(markers, distance_upper_bound=dk)
        active &= ~np.isfinite(d)
        stall = 0
        boost = 1.0
        it = 0
        reason = "done"
        total = len(markers)
        for it in range(1, int(self.max_iterations) + 1):
            if it % 16 == 0:
                check(cancelled)
                report(progress, 0.1 + 0.85 * (1.0 - active.sum() / max(total, 1)), "growing")
            am = np.flatnonzero(active)
            if len(am) == 0:
                break
            m = nodes.m
            if m > node_limit:
                reason = "node_limit"
                break
            buds = np.flatnonzero(nodes.bud_free[:m])
            if len(buds) == 0:
                reason = "stalled"
                break
            di0 = float(di_of_t[it - 1])
            rho_units = di0 / l
            di = min(di0 * boost, di_max)
            bud_tree = cKDTree(nodes.pos[buds])
            # Only markers with a bud within d_i can be perceived (the growth front).
            d1, _ = bud_tree.query(markers[am], distance_upper_bound=di)
            front = am[np.isfinite(d1)]
            has = np.zeros(0, dtype=bool)
            if len(front):
                kq = min(_K_BUDS, len(buds))
                mp = markers[front]
                _, j = bud_tree.query(mp, k=kq, distance_upper_bound=di)
                j = j.reshape(len(front), kq)
                valid = j < len(buds)
                b = buds[np.where(valid, j, 0)]                              # (a, kq) node ids
                vec = mp[:, None, :] - nodes.pos[b]
                norm = np.sqrt(np.einsum("akx,akx->ak", vec, vec))
                unit = vec / np.maximum(norm, 1e-12)[..., None]
                tip = (nodes.n_children[b] == 0) & ~nodes.seed[b]
                cos_min = np.where(tip, cos_apical, cos_lateral)
                ok = valid & (norm > 1e-9) & (np.einsum("akx,akx->ak", unit, nodes.heading[b]) > cos_min)
                has = ok.any(axis=1)
            if not has.any():
                # No bud perceives a marker.  The apical bud of the stem keeps growing
                # (L-system 1, rule 2, with no V_opt) while it is below the highest marker
                # left: it bridges an unscanned stretch of stem.  A stem is orthotropic, so
                # instead of the tropism its heading turns halfway to the vertical each unit
                # (z always rises, so this ends).
                seed_tips = np.flatnonzero(nodes.leader[:m] & (nodes.n_children[:m] == 0)
                                           & nodes.bud_free[:m])
                seed_tips = seed_tips[nodes.pos[seed_tips, 2] < markers[am, 2].max()]
                if len(seed_tips) and boost == 1.0:
                    v = _unit(nodes.heading[seed_tips] + _UP)
                    k = np.arange(1, max(1, int(rho_units)) + 1)
                    new_pos = (nodes.pos[seed_tips][:, None, :] + (l * k)[None, :, None]
                               * v[:, None, :]).reshape(-1, 3)
                    first_id = nodes.m
                    parent = np.arange(first_id - 1, first_id - 1 + len(new_pos))
                    parent[::len(k)] = seed_tips
                    nodes.add(new_pos, np.repeat(v, len(k), axis=0), parent, seed=True, added=True,
                              leader=True)
                    nodes.bud_free[seed_tips] = True
                    d, _ = cKDTree(new_pos).query(markers[am], distance_upper_bound=dk)
                    active[am[np.isfinite(d)]] = False
                    continue
                stall += 1
                if stall >= _STALL_LIMIT:
                    reason = "stalled"
                    break
                boost *= 1.5
                continue
            stall = 0
            boost = 1.0
            rows = np.flatnonzero(has)
            first = ok[rows].argmax(axis=1)
            bsel = b[rows, first]
            usel = unit[rows, first]
            wsel = weight[front[rows]]
            sums = np.zeros((m, 3))
            np.add.at(sums, bsel, wsel[:, None] * usel)
            wsum = np.bincount(bsel, weights=wsel, minlength=m)
            grow = np.flatnonzero(wsum > 0)
            v_opt = sums[grow] / wsum[grow, None]                            # Eq. 9, V_opt
            head = nodes.heading[grow]
            is_tip = nodes.n_children[grow] == 0
            # Lateral bud direction: ψ off the heading, towards the markers (φ if they give no azimuth).
            across = v_opt - (v_opt * head).sum(axis=1, keepdims=True) * head
            weak = np.linalg.norm(across, axis=1) < 1e-6
            if weak.any():
                ref = np.where(np.abs(head[weak, 2:3]) < 0.9, _UP, np.array([1.0, 0.0, 0.0]))
                e1 = _unit(np.cross(head[weak], ref))
                e2 = np.cross(head[weak], e1)
                ang = roll * (grow[weak] + nodes.n_children[grow[weak]])
                across[weak] = np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * e2
            lateral = np.cos(psi) * head + np.sin(psi) * _unit(across)
            default = np.where(is_tip[:, None], head, lateral)
            v = default + alpha * v_opt + beta * _DOWN                      # Eq. 9
            vn = np.linalg.norm(v, axis=1)
            v = np.where(vn[:, None] > 1e-9, v / np.maximum(vn, 1e-12)[:, None], default)
            # One growth unit (L-system 1, rule 2): a shoot of up to ρ_t internodes of length l
            # along V_A, no longer than the distance to the weighted centroid of the markers.
            csum = np.zeros((m, 3))
            np.add.at(csum, bsel, wsel[:, None] * markers[front[rows]])
            reach = np.linalg.norm(csum[grow] / wsum[grow, None] - nodes.pos[grow], axis=1)
            units = np.clip(np.rint(reach / l), 1, max(1, int(rho_units))).astype(np.int64)
            k = np.arange(int(units.sum())) - np.repeat(np.cumsum(units) - units, units) + 1
            owner = np.repeat(np.arange(len(grow)), units)
            new_pos = nodes.pos[grow][owner] + (l * k)[:, None] * v[owner]
            first_id = nodes.m
            parent = np.arange(first_id - 1, first_id - 1 + len(k))
            parent[k == 1] = grow
            nodes.add(new_pos, v[owner], parent, leader=(is_tip & nodes.leader[grow])[owner])
            # A node's buds are spent once it has its apical and one lateral child.
            nodes.bud_free[grow] = nodes.n_children[grow] < 2
            # Kill markers within d_k of the new nodes (only the front can be that close
            # when d_k + shoot length <= d_i).
            near = front if dk + l * units.max() <= di else am
            d, _ = cKDTree(new_pos).query(markers[near], distance_upper_bound=dk)
            active[near[np.isfinite(d)]] = False
            # Buds with no active marker within the largest influence distance never grow
            # again (except the stem's apical tip, which may still bridge a gap).
            if it % 8 == 0 and active.any():
                mm = nodes.m
                b_all = np.flatnonzero(nodes.bud_free[:mm] & ~(nodes.leader[:mm] & (nodes.n_children[:mm] == 0)))
                d, _ = cKDTree(markers[active]).query(nodes.pos[b_all], distance_upper_bound=di_max)
                nodes.bud_free[b_all[~np.isfinite(d)]] = False
        else:
            if active[:n_measured].any():
                reason = "max_iterations"
        if reason == "stalled" and not active[:n_measured].any():
            reason = "done"        # only crown-filling markers were left out of reach
        return it, reason
