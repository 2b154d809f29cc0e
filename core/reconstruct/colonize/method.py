"""The guided-growth method: Guo et al. 2018 §5.2, §5.3 and §6.1.

:class:`GuidedGrowth` seeds the roots (one, several, or the Hu et al. 2017 §4.2 trunk), weights the
points, fills a hollow crown with markers and grows the skeleton with :mod:`.growth`;
:data:`SPECIES_PRESETS` are the species parameter sets (§5.1).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Optional

import numpy as np

from ...errors import InputError
from ...presets import apply_preset
from ...progress import CancelCheck, Progress, check, report
from ..model import Reconstruction, Skeleton, TreePoints, screen
from ..trunk import add_trunk_points
from .growth import Nodes, grow_kernel, roll_tables
from .markers import (crown_fill_markers_in_hull, find_root_clusters, hull_of, influence_distance,
                      interior_fraction_in_hull, near_any_kernel, pca_weights)


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


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(n > 1e-12, v / np.maximum(n, 1e-12), 0.0)


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
            apply_preset(self, SPECIES_PRESETS[self.species])
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
    def _seed(self, nodes: Nodes, xyz: np.ndarray, ground_z: float, stats: dict, flags: list):
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
        crown_hull = hull_of(crown)       # one hull for the interior test and the fill
        frac = interior_fraction_in_hull(crown, crown_hull)
        stats["interior_fraction"] = frac
        fill = np.zeros((0, 3))
        if self.crown_fill == "always" or (self.crown_fill == "auto" and frac < self.interior_min_fraction):
            fill = crown_fill_markers_in_hull(crown, crown_hull, self.fill_spacing_m, self.seed,
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
        nodes = Nodes(max(256, 2 * n))
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
        near = near_any_kernel(np.ascontiguousarray(xyz, dtype=np.float64),
                               np.ascontiguousarray(nodes, dtype=np.float64),
                               float(self.kill_distance_m * (1 + 1e-9)))
        return float(near.mean()) if len(xyz) else 0.0

    def _grow(self, nodes: Nodes, markers: np.ndarray, weight: np.ndarray, n_measured: int,
              height_m: float, progress: Progress, cancelled: CancelCheck):
        """Iterate space colonisation until no marker is left; returns (iterations, reason).

        ``markers[:n_measured]`` are the tree's points, the rest crown-filling
        markers; ``reason`` is "done", "stalled" or "max_iterations" (the
        last two only when measured points are left unreached) or
        "node_limit" (more than 20 nodes per marker: a safety net).  The
        iterations run in the compiled :func:`grow_kernel`, 16 at a time
        between progress reports and cancel checks.
        """
        l = float(self.step_m)
        dk = float(self.kill_distance_m)
        cos_apical = float(np.cos(np.radians(min(self.perception_angle_deg / 2.0, 180.0))))
        half_lat = min(self.perception_angle_deg / 2.0 + self.branching_angle_deg, 180.0)
        cos_lateral = float(np.cos(np.radians(half_lat)))
        psi = np.radians(self.branching_angle_deg)
        roll = np.radians(self.roll_angle_deg)
        alpha, beta = float(self.attraction_weight), float(self.tropism)
        di_max = float(self.influence_max_units) * l
        max_it = int(self.max_iterations)
        node_limit = 20 * len(markers) + 10_000      # a safety net, never reached in practice
        di_of_t = influence_distance(np.arange(max_it), height_m, l, self.influence_h0,
                                     self.influence_rho0, self.influence_min_units,
                                     self.influence_max_units)
        markers = np.ascontiguousarray(markers, dtype=np.float64)
        weight = np.ascontiguousarray(weight, dtype=np.float64)

        # Markers already within d_k of the seeds are taken.
        active = ~near_any_kernel(markers, np.ascontiguousarray(nodes.pos[:nodes.m]), dk)

        cos_tab, sin_tab = roll_tables(roll, len(nodes.pos) + 2)
        stall, boost = 0, 1.0
        total = len(markers)
        it, code, checked = 1, 0, 0
        while it <= max_it:
            if it % 16 == 0 and checked != it:
                checked = it
                check(cancelled)
                report(progress, 0.1 + 0.85 * (1.0 - active.sum() / max(total, 1)), "growing")
            hi = min(it - it % 16 + 16, max_it + 1)
            (nodes.pos, nodes.heading, nodes.parent, nodes.n_children, nodes.seed, nodes.bud_free,
             nodes.added, nodes.leader, m, stall, boost, it, code) = grow_kernel(
                markers, weight, active, nodes.pos, nodes.heading, nodes.parent, nodes.n_children,
                nodes.seed, nodes.bud_free, nodes.added, nodes.leader, nodes.m, stall, boost, it, hi,
                di_of_t, cos_tab, sin_tab, l, dk, cos_apical, cos_lateral, float(np.cos(psi)),
                float(np.sin(psi)), alpha, beta, di_max, node_limit)
            nodes.m = int(m)
            if code == 5:
                cos_tab, sin_tab = roll_tables(roll, 2 * len(nodes.pos) + 2)
                continue
            if code != 0:
                break
        reason = {0: "done", 1: "done", 2: "node_limit", 3: "stalled", 4: "stalled"}[int(code)]
        if code == 0:
            it = max_it
            if active[:n_measured].any():
                reason = "max_iterations"
        if reason == "stalled" and not active[:n_measured].any():
            reason = "done"        # only crown-filling markers were left out of reach
        return int(it), reason
