"""CHM-based seeded region growing, the baseline users know (Dalponte & Coomes 2016).

Dalponte M., Coomes D.A. (2016), "Tree-centric mapping of forest carbon density
from airborne laser scanning and hyperspectral data", Methods in Ecology and
Evolution 7(10), 1236–1245 — the algorithm of R's ``itcSegment`` and of lidR's
``dalponte2016()``.

On a canopy height model (:func:`sylva.core.terrain.canopy_height_model`),
regions grow from the tree-top cells.  A cell joins the crown of a
4-neighbour already in crown t when

* its height > ``th_tree_m``,
* its height > ``th_seed`` × the height of t's top,
* its height > ``th_cr`` × the mean height of t's crown so far,
* its height <= 1.05 × the height of t's top, and
* it lies within ``max_crown_diameter_m / 2`` of t's top.

When two crowns reach a cell in the same step, the neighbour with the highest
CHM value wins (a deterministic form of itcSegment's scan order).  Growth
proceeds in rounds, every round vectorised over the whole raster, and the mean
crown heights are updated after each round.

Points then take the label of their CHM cell (non-ground points only): crown
points by construction, and stems and low branches because they stand in the
crown's column — the same rule as :mod:`sylva.core.segment` states for every
method.  Points of a cell that no crown reached stay 0.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ParameterError
from ..cloud import PointCloud
from ..progress import CancelCheck, Progress, check, report, scaled
from ..tops import MIN_TREE_HEIGHT_M
from .base import ground_mask, resolve_tops

__all__ = ["ChmRegionGrowing", "grow_regions"]


@dataclass(frozen=True)
class ChmRegionGrowing:
    """Dalponte & Coomes (2016) seeded region growing on a pit-free CHM.

    ``resolution_m``: CHM pixel size; ``pit_free``: Khosravipour et al. CHM.
    ``th_tree_m``, ``th_seed``, ``th_cr``, ``max_crown_diameter_m``: the
    growing rules above (itcSegment / lidR defaults: 2 m, 0.45, 0.55, 10 m).
    ``min_height_m`` and ``top_window_m``: tree-top search when no tops are given.
    """

    resolution_m: float = 0.5
    pit_free: bool = True
    th_tree_m: float = 2.0
    th_seed: float = 0.45
    th_cr: float = 0.55
    max_crown_diameter_m: float = 10.0
    min_height_m: float = MIN_TREE_HEIGHT_M
    top_window_m: float = 3.0

    def __post_init__(self):
        if not 0 < self.resolution_m < float("inf") or not 0 < self.max_crown_diameter_m < float("inf"):
            raise ParameterError("ChmRegionGrowing: resolution_m and max_crown_diameter_m must be "
                                 "positive finite numbers")

    def segment(self, cloud: PointCloud, tops=None, progress: Progress = None,
                cancelled: CancelCheck = None) -> np.ndarray:
        from ..terrain import canopy_height_model

        n = len(cloud)
        labels = np.zeros(n, dtype=np.int32)
        height = np.asarray(cloud.attr("height"), dtype=np.float64)
        ground = ground_mask(cloud, height)
        if not (height[~ground] >= self.min_height_m).any():
            return labels
        report(progress, 0.0, "canopy height model")
        chm = canopy_height_model(cloud, resolution_m=self.resolution_m, pit_free=self.pit_free)
        check(cancelled)
        local_tops = resolve_tops(cloud, tops, self.min_height_m, self.top_window_m,
                                  scaled(progress, 0.3, 0.4), cancelled)
        if len(local_tops) == 0:
            return labels
        origin = cloud.origin
        tx = local_tops.xy[:, 0] / cloud.units.horizontal_m + origin[0]
        ty = local_tops.xy[:, 1] / cloud.units.horizontal_m + origin[1]
        row, col = chm.index_of(tx, ty)
        pixel_m = chm.pixel * cloud.units.horizontal_m
        grid = grow_regions(chm.data, row, col, local_tops.tree_id, pixel_m, self,
                            scaled(progress, 0.4, 0.95), cancelled)
        prow, pcol = chm.index_of(cloud.xyz[:, 0], cloud.xyz[:, 1])
        ok = chm.inside(prow, pcol) & ~ground
        labels[ok] = grid[prow[ok], pcol[ok]]
        return labels


def grow_regions(chm: np.ndarray, row: np.ndarray, col: np.ndarray, tree_id: np.ndarray,
                 pixel_m: float, params: ChmRegionGrowing, progress: Progress = None,
                 cancelled: CancelCheck = None) -> np.ndarray:
    """Dalponte & Coomes (2016) region growing; returns an int32 grid of tree ids."""
    rows, cols = chm.shape
    h = np.where(np.isfinite(chm), chm, -np.inf).astype(np.float64)
    out = np.zeros((rows, cols), dtype=np.int32)
    ok = (row >= 0) & (row < rows) & (col >= 0) & (col < cols)
    row, col, tree_id = row[ok], col[ok], tree_id[ok]
    flat = row * cols + col
    _, first = np.unique(flat, return_index=True)   # one seed per cell, first top wins
    first = np.sort(first)
    row, col, tree_id, flat = row[first], col[first], tree_id[first], flat[first]
    seed_h = h.ravel()[flat]
    good = seed_h > params.th_tree_m
    row, col, tree_id, flat, seed_h = row[good], col[good], tree_id[good], flat[good], seed_h[good]
    k = len(flat)
    if k == 0:
        return out
    region = np.full(rows * cols, -1, dtype=np.int64)   # index of the seed, -1 = none
    region[flat] = np.arange(k)
    csum = seed_h.copy()
    ccount = np.ones(k)
    hf = h.ravel()
    radius_px2 = (params.max_crown_diameter_m / 2.0 / pixel_m) ** 2
    r_all = np.arange(rows * cols) // cols
    c_all = np.arange(rows * cols) % cols
    frontier = flat
    max_rounds = int(params.max_crown_diameter_m / pixel_m) + 2
    for it in range(max_rounds):
        check(cancelled)
        if len(frontier) == 0:
            break
        fr, fc = frontier // cols, frontier % cols
        cand_p, cand_t, cand_s = [], [], []
        for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            nr, nc = fr + dr, fc + dc
            inside = (nr >= 0) & (nr < rows) & (nc >= 0) & (nc < cols)
            p = nr[inside] * cols + nc[inside]
            src = frontier[inside]
            free = region[p] < 0
            cand_p.append(p[free])
            cand_t.append(region[src[free]])
            cand_s.append(hf[src[free]])
        p = np.concatenate(cand_p)
        t = np.concatenate(cand_t)
        s = np.concatenate(cand_s)
        hp = hf[p]
        mean_t = csum[t] / ccount[t]
        d2 = (r_all[p] - row[t]) ** 2 + (c_all[p] - col[t]) ** 2
        accept = ((hp > params.th_tree_m) & (hp > params.th_seed * seed_h[t])
                  & (hp > params.th_cr * mean_t) & (hp <= 1.05 * seed_h[t]) & (d2 < radius_px2))
        p, t, s = p[accept], t[accept], s[accept]
        if len(p) == 0:
            break
        o = np.lexsort((t, -s, p))
        p, t = p[o], t[o]
        firstp = np.ones(len(p), dtype=bool)
        firstp[1:] = p[1:] != p[:-1]
        p, t = p[firstp], t[firstp]
        region[p] = t
        csum += np.bincount(t, weights=hf[p], minlength=k)
        ccount += np.bincount(t, minlength=k)
        frontier = p
        report(progress, (it + 1) / max_rounds, "growing crowns on the CHM")
    has = region >= 0
    out.ravel()[has] = tree_id[region[has]].astype(np.int32)
    return out
