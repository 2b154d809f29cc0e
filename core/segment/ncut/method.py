"""The normalised-cut tree segmentation method: Hu et al. 2017 §4.1.

:class:`NormalizedCut` finds the tree tops, builds the voxel graph (:mod:`.graph`), cuts it between
neighbouring tops (:mod:`.cut`), cleans the trees up (:mod:`.cleanup`) and labels the points.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from ...errors import ParameterError
from ...noise import ISOLATION_M
from ...presets import apply_preset
from ...cloud import PointCloud
from ...progress import CancelCheck, Progress, check, report, scaled
from ...tops import MIN_TREE_HEIGHT_M, MIN_TREE_POINTS
from ..base import column_keys, ground_mask, label_columns_below, resolve_tops
from .cleanup import (APEX_REACH, TOP_TOLERANCE_M, apex_near_top, attach_free, crown_radius_m, in_blocks_around,
                      merge_off_centre, merge_plateaus, merge_small, within_crown_reach)
from .cut import CLOSED_COVER, CLOSED_HEIGHT_M, PLATEAU_REACH, cut_graph
from .graph import (LOWER_CROWN_REACH, canopy_columns, canopy_cover, column_maxima, coord_max, coord_min,
                    local_canopy_density, top_voxels, topless_crowns, voxel_graph)
from .islands import merge_round_islands
from .layers import lower_layer_apexes


#: Tops are searched among the highest points of columns this wide (d_s / 2).
TOP_CELL_M = 0.35

#: The sparsest canopy (first returns per m2) whose pulse spacing widens the search for a steep tip's
#: next return (:meth:`NormalizedCut._isolated`): a spacing of at most 1.4 m, a reach of at most 8.5 m
#: at ``apex_slope`` 3, so a stray return over open ground searches a bounded neighbourhood.
SPARSEST_CANOPY_PER_M2 = 0.5


#: A tree holds at least min_tree_points points, or the canopy first returns of this many m²
#: at the scan's density around its top when fewer (a 1.25 m crown radius: 10 points at 2 per m²).
MIN_TREE_AREA_M2 = 5.0


#: The canopy cover around a top (open-grown crowns) is judged within this many of its allometric
#: crown radii, and never farther than COVER_MAX_M (inside the pipeline's 15 m buffer: any tiling
#: gives the same value).
COVER_REACH = 2.0
COVER_MAX_M = 10.0


#: At low density the steep-apex window is widened to hold this many canopy
#: first returns (0.8 m at about 19 points/m², 1.6 m at 5 points/m²).
APEX_WINDOW_POINTS = 10.0


#: Crown radius of a tree grown in the open (park, street, pasture, orchard) as a multiple of Popescu &
#: Wynne's forest-grown allometry: the isolated park crowns of autzen_trim.laz are 2-3.5 x as wide
#: (4.6-7 m radius on trees 10-18 m high; :mod:`.islands`), Hasenauer (1997) measures open-grown
#: crowns likewise much wider than stand-grown ones.
OPEN_GROWN = 2.5

#: Named sets of defaults for how the trees grew (``NormalizedCut.growth``); a preset's values replace
#: the fields left at their defaults.  "forest": trees grown in a stand, the defaults.  "open-grown":
#: crowns OPEN_GROWN x as wide, and a graph that reaches 1.5 m across and 3 m up (a wide clumped crown's
#: gaps between leaf clumps are wider than the forest's 1 m); a lower top rising less than 25 % of its
#: height above the saddle (``merge_prominence``), or a rounded one within 1.2 crown radii where the
#: canopy is open (``open_reach``), is a leader of the same crown: an open-grown crown's leaders rise
#: higher above their saddles, and farther from its apex, than a forest crown's bumps (parkland,
#: open-grown preset, F1 mean of the 12 stands 0.770 -> 0.803 at seed 0, 0.762 -> 0.788 at seed 1).
#: Measured with ``benchmarks/segmentation.py --kinds parkland --growth open-grown`` (issue 16).
GROWTH_PRESETS = {
    "forest": {},
    "open-grown": dict(crown_scale=OPEN_GROWN, radius_m=1.5, height_m=3.0, closed_window=1.0,
                       merge_prominence=0.25, open_reach=1.2, lower_crown_reach=0.0),
}


@dataclass(frozen=True)
class NormalizedCut:
    """Hu et al. (2017) §4.1 normalised cut on a voxel graph, guided by tree tops.

    ``voxel_m``: voxel pitch d_s (paper default 0.7 m, §6.1).
    ``radius_m``: r^xz of Eq. 2, voxels farther apart horizontally are not joined.
    ``height_m``: vertical reach of the neighbourhood (the cylinder's half height).
    ``sigma_h_m``, ``sigma_v_m``: scales of the horizontal / vertical distance in Eq. 2.
    ``sigma_intensity``: scale of the intensity difference, in natural-log units (ln I).
    ``sigma_colour``: scale of the RGB distance (colours scaled to [0, 1]).
    ``min_height_m``: crown points are at least this high (and tops too).
    ``top_window_m``: fixed window of the local-maximum tree-top search when
    no tops are given (small on purpose: the cuts merge surplus tops); None
    means the default.
    ``top_window_points``: at low point density the window is widened so that
    it holds at least this many canopy first returns (0: off).
    ``top_window_crown``: the window is at least this share of the crown width
    Popescu & Wynne's (2004) allometry gives a tree as high as the point
    (:func:`~.cleanup.crown_radius_m`): their variable window, narrowed because
    the cuts merge surplus tops (0: off).
    ``closed_window``: where the canopy around a top is closed (at least
    ``CLOSED_COVER`` of the ground within ``COVER_REACH`` crown radii, as the
    open-canopy reach below judges it) the crowns are narrowed by their
    neighbours: the maxima of a window whose crown share is this factor x
    ``top_window_crown`` are tops too (1: off; the "open-grown" preset, whose
    crowns grew without neighbours).
    ``apex_window_m``, ``apex_slope``, ``apex_sectors``: the steep-apex rule
    (:class:`sylva.core.tops.SteepApex`): a maximum of this narrow window is a
    top too when the canopy drops at least ``apex_slope`` m per m from it in
    ``apex_sectors`` of 8 directions (conifer tips overtopped on one side by
    a neighbour); ``apex_window_m`` 0 turns the rule off.  ``apex_slope`` also
    tells the tip of a steep crown in a sparse scan from noise (step 3).
    ``merge_ncut``, ``merge_dip``: two regions whose best two-way cut costs more
    than ``merge_ncut`` (Eq. 1) *and* whose crowns dip between their tops by less
    than ``merge_dip`` x the lower top's height are one tree.
    ``always_merge_ncut``: regions whose best cut costs more than this are one
    tree whatever the dip.
    ``merge_reach``, ``merge_prominence``: the crown-reach merge of step 4 (a
    lower top within ``merge_reach`` x the higher tree's allometric crown
    radius, rising less than ``merge_prominence`` x its height above the
    saddle, is a bump of that crown); ``merge_plateau``: two such tops whose
    heights differ by less than this fraction are one flat crown up to
    ``PLATEAU_REACH`` crown radii apart, also when their regions do not
    touch if both are rounded and the canopy is not closed
    (:func:`~.cut.unjoined_plateaus`; needs ``open_cover`` > 0), and, judged
    again on the finished crowns, when the lower one's crown touches the
    higher's less than half ``merge_prominence`` below its top
    (:func:`~.cleanup.merge_plateaus`; 0 turns both off).
    ``merge_height_ratio``: a lower top under this fraction of the higher
    top's height that rises above their saddle, beyond ``UNDER_CROWN`` crown
    radii of it, is the apex of a tree of a lower crown class, not a bump of
    the higher crown: only a cut dearer than ``always_merge_ncut`` merges it
    (0: off).
    ``open_cover``, ``open_reach``: where the canopy around the higher top is
    open (:func:`canopy_cover` below ``open_cover``; 0: off), the
    crown-reach merge reaches ``open_reach`` crown radii for a rounded lower
    top (not a steep apex of the :class:`~sylva.core.tops.SteepApex` rule);
    a tree under ``min_tree_points`` whose top is a steep apex farther than
    ``open_reach`` crown radii from every tree as high is kept (flagged
    "sparse"): beyond the reach of a crown's bumps, it is a tree of its own.
    ``understory_points``, ``understory_extent_m``: a connected piece of the
    voxel graph that no top reaches (a crown under the canopy, more than
    ``height_m`` below the crowns above it) is a tree of its own, its top the
    highest point, when it holds at least ``understory_points`` crown points
    and spans ``understory_extent_m`` horizontally (0 points: off; not when
    tops are given), unless it is centred within ``lower_crown_reach`` crown
    radii of a taller tree's apex: the skirt of a steep crown that a sparse
    scan cut off from its tip (0: off, as in the "open-grown" preset, whose
    broad crowns are no spires: parkland dense at 2-50 points/m2 lost 0.008
    to 0.010 with it).
    ``lower_layer``: apexes of a lower crown layer under the edge of a higher
    crown (a gap above them, a crown below, a closed canopy) are tops too
    (:func:`~.layers.lower_layer_apexes`; not when tops are given).
    ``min_tree_points``: smaller trees are merged into their neighbours (where
    the scan is sparse, the first returns of ``MIN_TREE_AREA_M2`` of canopy
    around the top, if fewer).
    ``crown_reach``: points farther from their top than this many allometric
    crown radii move to a tree within reach (0: off).
    ``crown_scale``: the trees' crown radius as a multiple of Popescu & Wynne's
    (2004) allometry for trees grown in a stand (:func:`~.cleanup.crown_radius_m`),
    which scales every crown radius above (top window, merge reaches, crown
    reach, the off-centre and small-tree merges); 1 for forests,
    :data:`OPEN_GROWN` for trees grown in the open (the "open-grown" preset).
    ``growth``: a key of :data:`GROWTH_PRESETS` ("forest", "open-grown"), whose
    values replace the fields left at their defaults.
    ``climb``: cost per metre climbed of the geodesic start partition.
    ``attach_m``: reach of unconnected crown pieces to the nearest tree.
    """

    voxel_m: float = 0.7
    radius_m: float = 1.0
    height_m: float = 2.0
    sigma_h_m: float = 1.0
    sigma_v_m: float = 1.0
    sigma_intensity: float = 1.0
    sigma_colour: float = 0.25
    min_height_m: float = MIN_TREE_HEIGHT_M
    top_window_m: float = 2.0
    top_window_points: float = 25.0
    top_window_crown: float = 0.4
    closed_window: float = 0.4
    apex_window_m: float = 0.8
    apex_slope: float = 3.0
    apex_sectors: int = 5
    merge_ncut: float = 0.05
    merge_dip: float = 0.04
    always_merge_ncut: float = 0.15
    merge_reach: float = 0.7
    merge_prominence: float = 0.15
    merge_plateau: float = 0.05
    merge_height_ratio: float = 0.8
    open_cover: float = 0.6
    open_reach: float = 0.9
    understory_points: int = 40
    understory_extent_m: float = 2.5
    lower_crown_reach: float = LOWER_CROWN_REACH
    lower_layer: bool = True
    min_tree_points: int = MIN_TREE_POINTS
    crown_reach: float = 1.25
    crown_scale: float = 1.0
    climb: float = 100.0
    attach_m: float = 2.0
    growth: str = "forest"

    def __post_init__(self):
        if self.top_window_m is None:   # "not given" (an optional GUI/CLI parameter)
            object.__setattr__(self, "top_window_m", 2.0)
        if self.growth not in GROWTH_PRESETS:
            raise ParameterError(f"NormalizedCut: unknown growth {self.growth!r}; choose one of "
                                 f"{', '.join(GROWTH_PRESETS)}")
        apply_preset(self, GROWTH_PRESETS[self.growth])
        for name in ("voxel_m", "radius_m", "height_m", "sigma_h_m", "sigma_v_m", "sigma_intensity",
                     "sigma_colour", "merge_ncut", "always_merge_ncut", "crown_scale"):
            if not 0 < getattr(self, name) < float("inf"):
                raise ParameterError(f"NormalizedCut.{name} must be a positive finite number, "
                                     f"not {getattr(self, name)}")
        if not 0 <= self.min_height_m < float("inf"):
            raise ParameterError(f"NormalizedCut: min_height_m must be >= 0 and finite, not {self.min_height_m}")
        if not 0 <= self.merge_dip < float("inf"):
            raise ParameterError("NormalizedCut: merge_dip must be >= 0")
        if not all(0 <= v < float("inf") for v in (self.merge_reach, self.merge_prominence, self.crown_reach,
                                                   self.min_tree_points, self.understory_points,
                                                   self.understory_extent_m, self.open_cover, self.open_reach,
                                                   self.merge_height_ratio, self.lower_crown_reach)):
            raise ParameterError("NormalizedCut: merge_reach, merge_prominence, crown_reach, min_tree_points, "
                                 "understory_points, understory_extent_m, open_cover, open_reach, "
                                 "merge_height_ratio and lower_crown_reach must be >= 0 and finite")
        if not 0 <= self.closed_window <= 1:
            raise ParameterError(f"NormalizedCut: closed_window must be between 0 and 1, not {self.closed_window}")
        if not (0 <= self.top_window_points and 0 <= self.top_window_crown < float("inf")
                and 0 <= self.apex_window_m < float("inf") and 0 < self.top_window_m < float("inf")):
            raise ParameterError("NormalizedCut: top_window_points, top_window_crown and apex_window_m must be "
                                 ">= 0, top_window_m positive and finite")
        if not 0 < self.apex_slope < float("inf") or (self.apex_window_m > 0 and not 1 <= self.apex_sectors <= 8):
            raise ParameterError("NormalizedCut: apex_slope must be > 0 and finite and apex_sectors in 1..8")

    def windows(self, cloud: PointCloud, local: np.ndarray, height: np.ndarray,
                crown: np.ndarray, density: np.ndarray = None, share: float = 1.0):
        """(top window, apex window) diameters in metres, one per point of the cloud.

        Each is widened where the scan is sparse to hold ``top_window_points`` /
        ``APEX_WINDOW_POINTS`` canopy first returns, by the canopy density
        around the point (:func:`local_canopy_density`: a neighbourhood of
        fixed size, never a statistic of the tile, so any tiling gives the same
        windows), and the top window to ``top_window_crown`` x the allometric
        crown width at the point's height.  An apex window as wide as the top
        window adds nothing.  ``share`` scales the crown's widening (``closed_window``: the
        window of a closed canopy)."""
        if density is None:
            density = local_canopy_density(cloud, local, crown)
        return self._diameters(height, density, share)

    def _diameters(self, height: np.ndarray, density: np.ndarray, share: float = 1.0):
        """:meth:`windows` of points of these heights and canopy densities."""
        wide = np.full(len(height), float(self.top_window_m))
        if self.top_window_points > 0:
            wide = np.maximum(wide, 2.0 * np.sqrt(self.top_window_points / (np.pi * density)))
        if self.top_window_crown > 0:
            wide = np.maximum(wide, share * self.top_window_crown * 2.0 * crown_radius_m(height, self.crown_scale))
        apex = np.zeros(len(height))
        if self.apex_window_m > 0:
            apex = np.maximum(float(self.apex_window_m),
                              2.0 * np.sqrt(APEX_WINDOW_POINTS / (np.pi * density)))
            apex = np.minimum(apex, wide)
        return wide, apex

    def _find_tops(self, cloud, local, height, crown, progress, cancelled, density=None, cover=None):
        """Tree tops among the highest point of every TOP_CELL_M column (see step 3): the maxima of
        each point's window and, where the canopy around them is closed, those of the narrower
        ``closed_window`` one; then the apexes of a lower crown layer (``lower_layer``).
        ``density``, ``cover``: :func:`local_canopy_density` and :meth:`_cover` of the cloud."""
        from ...tops import FixedWindow, SteepApex, TreeTops, find_tree_tops, union_tops

        if density is None:
            density = local_canopy_density(cloud, local, crown)
        if cover is None:
            cover = self._cover(local, height, crown)
        sel = np.flatnonzero(crown)
        search = sel[column_maxima(local[sel, :2], height[sel], TOP_CELL_M)]
        search = search[~self._isolated(cloud, local, crown, search, density)]
        subset = cloud.subset(search)
        rule = None
        if self.apex_window_m > 0 and self.apex_window_m < self.top_window_m:
            rule = SteepApex(float(self.apex_window_m), self.apex_slope, int(self.apex_sectors))

        def maxima(share, prog):
            wide, apex = self._diameters(height[search], density[search], share)
            return find_tree_tops(subset, window=FixedWindow(float(self.top_window_m)),
                                  min_height_m=self.min_height_m, progress=prog, cancelled=cancelled,
                                  isolation_m=None, apex=rule, diameters=wide,
                                  apex_diameters=apex if rule is not None else None)

        tops = maxima(1.0, scaled(progress, 0.0, 0.5))
        if self.closed_window < 1 and self.top_window_crown > 0:
            more = maxima(self.closed_window, scaled(progress, 0.5, 1.0))
            xy = (more.xyz[:, :2] - cloud.origin[:2]) * cloud.units.horizontal_m
            tops = union_tops(tops, more, cover(xy, more.height) >= CLOSED_COVER)
        if not self.lower_layer:
            return tops
        check(cancelled)
        top_xy = (tops.xyz[:, :2] - cloud.origin[:2]) * cloud.units.horizontal_m
        apex = sel[lower_layer_apexes(local[sel, :2], height[sel], density[sel], top_xy, tops.height,
                                      self.crown_scale, cover)]
        more = TreeTops(cloud.xyz[apex], height[apex], np.arange(1, len(apex) + 1, dtype=np.int64), cloud.crs)
        return union_tops(tops, more, np.ones(len(apex), dtype=bool))

    def _isolated(self, cloud, local, crown, search, density):
        """Mask of the ``search`` points that are noise, not a tree top: no other crown point
        within ``ISOLATION_M`` in 3-D (:func:`sylva.core.noise.isolated_points`), nor, where the
        scan is sparse, below them as steeply as a conifer's apex drops (at least ``apex_slope`` x
        the horizontal distance) within ``2 * apex_slope`` pulse spacings (1 / sqrt of the canopy
        density around the point; no wider than at ``SPARSEST_CANOPY_PER_M2``).

        A conifer's highest return stands above the next one by the crown's slope times the
        pulse spacing: at 2 points/m2 a spire rising 3-7 m per metre puts 2-5 m between them,
        and the fixed 2 m test threw the tops of steep crowns away.  A stray return beside a
        crown, or over ground, is still noise (Sylva, not in Hu et al.; figures in step 3 of the
        package docstring)."""
        from ...noise import isolated_points

        alone = isolated_points(cloud, ISOLATION_M, among=crown, loc=local)[search]
        cand = np.flatnonzero(alone)
        reach = 2.0 * self.apex_slope / np.sqrt(np.maximum(density[search[cand]], SPARSEST_CANOPY_PER_M2))
        sparse = reach > ISOLATION_M
        if sparse.any():
            cand, reach = cand[sparse], reach[sparse]
            alone[cand[_steep_support(local, crown, local[search[cand]], reach,
                                      self.apex_slope)]] = False
        return alone

    def _cover(self, local, height, crown):
        """``cover(top_xy, top_height)``: the canopy cover around each top (local metres) within
        ``COVER_REACH`` of its allometric crown radii, at most ``COVER_MAX_M``
        (:func:`canopy_cover`); the cloud's columns are gridded once, on the first call."""
        @functools.cache
        def columns():
            return canopy_columns(local, height, crown)

        def cover(top_xy, top_height):
            reach = np.minimum(COVER_REACH * crown_radius_m(top_height, self.crown_scale), COVER_MAX_M)
            return canopy_cover(columns(), top_xy, top_height, reach)
        return cover

    def _openness(self, local, height, crown, local_tops, top_id, top_height, graph, top_voxel, cover_of):
        """(canopy cover around each top, whether it is a steep apex) for the open-canopy reach of the
        crown-reach merge; (None, None) when ``open_cover`` is 0.  ``cover_of``: :meth:`_cover`."""
        if self.open_cover <= 0:
            return None, None
        cover = cover_of(graph.xyz[top_voxel, :2], top_height)
        steep = np.zeros(len(top_id), dtype=bool)
        if self.apex_window_m > 0:
            from ...tops import SteepApex, steep_tops

            row = {int(t): i for i, t in enumerate(local_tops.tree_id)}
            rows = np.array([row.get(int(t), -1) for t in top_id], dtype=np.int64)
            have = np.flatnonzero(rows >= 0)          # the surface tops (not the understory's)
            steep[have] = steep_tops(local[crown, :2], height[crown], local_tops.xy[rows[have]],
                                     local_tops.height[rows[have]],
                                     SteepApex(float(self.apex_window_m), self.apex_slope, int(self.apex_sectors)))
        return cover, steep

    def segment(self, cloud: PointCloud, tops=None, progress: Progress = None,
                cancelled: CancelCheck = None) -> np.ndarray:
        """Per-point tree IDs (int32, 0 = none) of a height-normalised cloud."""
        n = len(cloud)
        labels = np.zeros(n, dtype=np.int32)
        height = np.asarray(cloud.attr("height"), dtype=np.float64)
        ground = ground_mask(cloud, height)
        crown = (height >= self.min_height_m) & ~ground
        if not crown.any():
            return labels
        check(cancelled)
        report(progress, 0.0, "building the voxel graph")
        local = cloud.local_xyz()
        graph = voxel_graph(cloud, local, height, crown, self)
        check(cancelled)
        report(progress, 0.1, "finding tree tops")
        # canopy first returns per m2 around every point (top windows, minimum tree size)
        rho = local_canopy_density(cloud, local, crown)
        cover_of = self._cover(local, height, crown)
        found = tops is None
        if tops is None and graph.n:
            tops = self._find_tops(cloud, local, height, crown, scaled(progress, 0.1, 0.2),
                                   cancelled, rho, cover_of)
        local_tops = resolve_tops(cloud, tops, self.min_height_m, self.top_window_m,
                                  scaled(progress, 0.1, 0.2), cancelled)
        check(cancelled)
        if len(local_tops) == 0 or graph.n == 0:
            return labels
        top_voxel, top_id, top_height = top_voxels(graph, local_tops, self)
        if len(top_voxel) == 0:          # given tops, none of them on (or near) a crown
            return labels
        if found and self.understory_points > 0:
            # crowns under the canopy that no surface top reaches: trees of their own
            extra, extra_h = topless_crowns(graph, height[crown], local[crown, :2], top_voxel,
                                            self.understory_points, self.understory_extent_m, top_height,
                                            crown_radius_m(top_height), self.lower_crown_reach)
            top_voxel = np.r_[top_voxel, extra]
            top_id = np.r_[top_id, top_id.max(initial=0) + 1 + np.arange(len(extra))]
            top_height = np.r_[top_height, extra_h]
        cover, steep = self._openness(local, height, crown, local_tops, top_id, top_height, graph, top_voxel,
                                      cover_of)
        # the minimum size of a tree, in points, at the scan's density around its top
        voxel_rho = np.zeros(graph.n)
        is_top = np.zeros(graph.n, dtype=bool)
        is_top[top_voxel] = True
        on_top = is_top[graph.point_voxel]             # the crown points of the top voxels
        np.maximum.at(voxel_rho, graph.point_voxel[on_top], rho[np.flatnonzero(crown)[on_top]])
        min_points = np.minimum(float(self.min_tree_points), MIN_TREE_AREA_M2 * voxel_rho[top_voxel])
        report(progress, 0.2, "normalised cuts")
        vlabel = cut_graph(graph, top_voxel, top_id, top_height, self,
                           scaled(progress, 0.2, 0.95), cancelled, cover, steep)
        # points: crown points take their voxel's label, low points the crown above them
        labels[crown] = vlabel[graph.point_voxel]
        # nothing of a tree is higher than its top (points of a taller neighbour)
        top_h = np.zeros(int(top_id.max()) + 1)
        top_h[top_id] = top_height
        above = labels > 0
        above[above] = height[above] > top_h[labels[above]] + TOP_TOLERANCE_M
        labels[above] = 0
        if self.crown_reach > 0:
            labels = within_crown_reach(local[:, :2], height, labels, self.crown_reach * self.crown_scale)
        # stems and low branches (below min_height_m, or crown points no top
        # reached): the label of the crown right above them in their column
        low = np.flatnonzero((labels == 0) & ~ground)
        if len(low):
            has = vlabel > 0
            ixv, iyv, izv = graph.ijk[has].T
            lx = np.floor(local[low, 0] / self.voxel_m).astype(np.int64) - graph.ij0[0]
            ly = np.floor(local[low, 1] / self.voxel_m).astype(np.int64) - graph.ij0[1]
            inside = (lx >= 0) & (ly >= 0)
            q = np.full(len(low), -1, dtype=np.int64)
            q[inside] = column_keys(lx[inside], ly[inside])
            labels[low] = label_columns_below(
                column_keys(ixv, iyv), izv * self.voxel_m, vlabel[has].astype(np.int32),
                q, height[low])
        # pieces of a crown: a tree's apex is near its crown's centre
        steep_id = np.zeros(int(top_id.max()) + 1, dtype=bool)
        steep_id[top_id] = steep
        xy = local[:, :2]
        bounds = (*coord_min(xy), *coord_max(xy))
        elev = local[:, 2]
        labels = merge_off_centre(xy, height, labels, steep_id, bounds, scale=self.crown_scale, elev=elev)
        # an open-grown crown: a round canopy island too wide for a forest crown
        labels = merge_round_islands(xy, height, labels, bounds, self.min_height_m)
        # a closed canopy bounds the crowns (as in the cut's merges): where the canopy around a top is
        # closed, its tree is judged as one at most CLOSED_HEIGHT_M high
        max_height = None
        if cover is not None:
            max_height = np.full(int(top_id.max()) + 1, np.inf)
            max_height[top_id[cover >= CLOSED_COVER]] = CLOSED_HEIGHT_M
        # crown points no top reached (graph pieces beyond radius_m of every tree, under no crown): the
        # tree within crown reach whose top is nearest, as within_crown_reach places strays; before
        # trees are judged by their size (the lower crown of a spire a sparse scan cut off is its own)
        own = labels
        if self.crown_reach > 0:
            labels = attach_free(xy, height, labels, np.flatnonzero(crown & (labels == 0)),
                                 self.crown_reach * self.crown_scale)
        if self.min_tree_points > 1:
            need = np.zeros(int(top_id.max()) + 1)
            need[top_id] = min_points
            labels = merge_small(local[:, :2], height, labels, need, max(self.crown_reach, 1.0) * self.crown_scale,
                                 steep=steep_id, apart=self.open_reach, scale=self.crown_scale,
                                 max_height=max_height, own=own)
        # a top that rises nowhere above the crown it touches: a leader or flank of a flat crown
        if self.merge_plateau > 0:
            labels = merge_plateaus(xy, height, labels, bounds, self.merge_plateau,
                                    0.5 * self.merge_prominence, PLATEAU_REACH, self.radius_m, self.crown_scale,
                                    elev=elev, max_height=max_height)
        # a tree's apex is near a top it grew from, not a neighbour's point at its crown's edge
        pts, vox = np.flatnonzero(crown)[on_top], graph.point_voxel[on_top]
        o = np.lexsort((-xy[pts, 1], -xy[pts, 0], height[pts], vox))   # per top voxel, its highest last
        last = np.r_[vox[o][1:] != vox[o][:-1], True]
        voxel_label = np.zeros(graph.n, dtype=np.int64)
        voxel_label[vox[o][last]] = labels[pts[o][last]]
        reach = APEX_REACH * crown_radius_m(top_height, self.crown_scale)
        return apex_near_top(xy, elev, labels, graph.xyz[top_voxel, :2], voxel_label[top_voxel], reach)


def _steep_support(local: np.ndarray, crown: np.ndarray, q: np.ndarray, reach: np.ndarray,
                   slope: float) -> np.ndarray:
    """Per point of ``q`` (local x, y, z): whether a crown point within ``reach`` of it (3-D) lies
    below it at least ``slope`` times as far down as across (a steep crown's next return under its
    tip).  Only the crown points in the cells around ``q`` are searched (:func:`in_blocks_around`)."""
    from scipy.spatial import cKDTree

    pts = local[in_blocks_around(local[:, :2], crown, np.ascontiguousarray(q[:, :2]), float(reach.max()))]
    out = np.zeros(len(q), dtype=bool)
    if len(pts) == 0:
        return out
    near = cKDTree(pts).query_ball_point(q, reach)
    row = np.repeat(np.arange(len(q)), [len(v) for v in near])
    if len(row) == 0:
        return out
    other = pts[np.concatenate(near).astype(np.int64)]
    drop = q[row, 2] - other[:, 2]
    steep = (drop > 0) & (drop >= slope * np.hypot(*(other[:, :2] - q[row, :2]).T))
    out[row[steep]] = True
    return out
