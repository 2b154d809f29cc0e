"""Tree-top detection by local-maximum filtering (lidR's ``lmf``).

A tree top is a point (or CHM cell) that is the highest within a circular
window centred on it, and at least ``min_height_m`` above ground.  The window
is a method value:

* :class:`FixedWindow` — one diameter for every height;
* :class:`VariableWindow` — a diameter growing with height, ``a + b h + c h^2``
  clipped to [``min_diameter_m``, ``max_diameter_m``]; the crown-width
  regressions of Popescu & Wynne (2004), "Seeing the trees in the forest: using
  lidar and multispectral data fusion with local filtering and variable window
  size for estimating tree height", Photogramm. Eng. Remote Sens.
  70(5) (the variable-window method; its crown width vs height regressions for
  pines, deciduous trees and both combined) are available as constructors; the default is
  the rule measured best on synthetic stands by ``benchmarks/terrain.py``.

Optionally (point clouds only), :class:`SteepApex` adds the *tucked apices*
a window misses: the tip of a narrow conical crown next to a taller neighbour
whose crown rises within the window's radius.  Such a tip is still a local
maximum of a narrow window, and unlike the bumps of a rounded crown the canopy
falls away from it steeply in most directions.  (A Sylva rule, measured on the
synthetic dense stands of ``benchmarks/segmentation.py``; not from a paper of
the specification.)

Plateaus (neighbouring maxima of equal height) yield one top: the member
nearest the plateau's centroid.  Results are ordered by height descending, then
x, then y, and numbered from 1.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Union

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .cloud import ANCHOR_GRID_M, PointCloud
from .errors import EmptyInputError, InputError
from .jit import njit
from .kernels.grid import grid_cells
from .progress import CancelCheck, Progress, check, report
from .raster import Raster

#: Tops lower than this above the ground are not trees (shrubs, cars, noise): the one default of every
#: tree-top search and segmentation method.
MIN_TREE_HEIGHT_M = 2.0

#: A tree of fewer points is no plausible tree where the scan could give it more: the normalised cut
#: merges it into a neighbour, and where the scan is sparse and keeps it (or where it is higher than
#: every tree around it, or a steep apex beyond its neighbours' crowns,
#: :func:`sylva.core.segment.ncut.cleanup.merge_small`), its row in the trees table says ``quality``
#: "sparse" (:func:`sylva.core.forest.model_trees`).
MIN_TREE_POINTS = 20


@dataclass(frozen=True)
class FixedWindow:
    """A circular window of one diameter (metres) for every height."""

    diameter_m: float = 3.0

    def diameter(self, height_m: np.ndarray) -> np.ndarray:
        return np.full(np.shape(height_m), float(self.diameter_m))

    @property
    def min_diameter(self) -> float:
        return float(self.diameter_m)

    @property
    def max_diameter(self) -> float:
        return float(self.diameter_m)


#: The widest crown (m) of a forest-grown tree that Popescu & Wynne's (2004) crown-width regressions
#: are used for: they are quadratic in height, fitted on stands of usual heights, and extrapolated
#: they grow without bound (the combined rule gives 12 m at 32.4 m, 25 m at 50 m, 35 m at 60 m), so
#: beyond it the crown width stays at this value (Sylva, not in Popescu & Wynne; measured on the
#: suite's tall stands, ``benchmarks/segmentation.py --kinds tall``: mean F1 0.61 -> 0.79 at 5
#: points/m2 and more, the other stands unchanged).
MAX_CROWN_WIDTH_M = 12.0


@dataclass(frozen=True)
class VariableWindow:
    """Window diameter ``a + b*h + c*h**2`` metres for a top ``h`` metres high,
    clipped to [``min_diameter_m``, ``max_diameter_m``].

    The default is a linear rule in lidR's style (``ws = 0.1 h + 1.5``), chosen
    by measured F1 on synthetic stands (``benchmarks/terrain.py``: open, medium
    and dense stands at 5 and 20 pulses/m2, two seeds, mean F1 0.899 on points
    against 0.886 for the best fixed window, 3 m; 0.824 and 0.760 for the
    Popescu & Wynne pine and combined rules, which suit the open stand (0.97)
    but merge neighbours in dense ones).  The Popescu & Wynne (2004)
    regressions are :meth:`pines`, :meth:`deciduous`, :meth:`combined`.
    """

    a: float = 1.5
    b: float = 0.1
    c: float = 0.0
    min_diameter_m: float = 2.0
    max_diameter_m: float = 8.0

    def diameter(self, height_m: np.ndarray) -> np.ndarray:
        h = np.asarray(height_m, dtype=np.float64)
        return np.clip(self.a + self.b * h + self.c * h * h, self.min_diameter_m, self.max_diameter_m)

    @property
    def min_diameter(self) -> float:
        return float(self.min_diameter_m)

    @property
    def max_diameter(self) -> float:
        return float(self.max_diameter_m)

    # Popescu & Wynne (2004): crown width (m) against tree height (m), at most MAX_CROWN_WIDTH_M.
    @classmethod
    def pines(cls, min_diameter_m: float = 2.0, max_diameter_m: float = MAX_CROWN_WIDTH_M) -> "VariableWindow":
        """CW = 3.75105 - 0.17919 h + 0.01241 h^2 (pines)."""
        return cls(3.75105, -0.17919, 0.01241, min_diameter_m, max_diameter_m)

    @classmethod
    def deciduous(cls, min_diameter_m: float = 2.0, max_diameter_m: float = MAX_CROWN_WIDTH_M) -> "VariableWindow":
        """CW = 3.09632 + 0.00895 h^2 (deciduous)."""
        return cls(3.09632, 0.0, 0.00895, min_diameter_m, max_diameter_m)

    @classmethod
    def combined(cls, min_diameter_m: float = 2.0, max_diameter_m: float = MAX_CROWN_WIDTH_M) -> "VariableWindow":
        """CW = 2.51503 + 0.00901 h^2 (pines and deciduous together)."""
        return cls(2.51503, 0.0, 0.00901, min_diameter_m, max_diameter_m)


Window = Union[FixedWindow, VariableWindow]


@dataclass(frozen=True)
class SteepApex:
    """Extra tops: maxima of a narrow window from which the canopy falls away steeply.

    A local maximum of the narrow ``diameter_m`` window (that the main window
    did not already find) is a top when, in at least ``sectors`` of 8
    compass sectors of the ring ``inner_m``..``outer_m`` around it, the median
    slope down to the canopy surface (the highest point of each ``inner_m``
    column) is at least ``slope`` (metres of drop per metre), and no higher top
    (of the window or of this rule) lies within ``separation_m`` (else it is a
    second steep point of the same cone).  A conifer tip
    drops 4-8 m per metre, a rounded crown's bump less than 1, so the rule adds
    the tips of narrow crowns overtopped on one side by a neighbour and almost
    nothing else.  Defaults measured on the synthetic dense stands at 20
    pulses/m2 (``benchmarks/segmentation.py``).
    """

    diameter_m: float = 0.8
    slope: float = 3.0
    sectors: int = 5
    inner_m: float = 0.3
    outer_m: float = 1.2
    separation_m: float = 1.6

    def __post_init__(self):
        if not (self.diameter_m > 0 and self.slope > 0 and 0 < self.inner_m < self.outer_m):
            raise InputError(f"{self!r}: diameter_m and slope must be > 0 and 0 < inner_m < outer_m")
        if not 1 <= int(self.sectors) <= 8:
            raise InputError(f"{self!r}: sectors must be between 1 and 8")


@dataclass(eq=False)
class TreeTops:
    """Detected tops: ``xyz`` (k, 3) float64 in CRS units (z = the top's elevation in the
    CRS's z; from a CHM without a DTM, its height in CRS vertical units), ``height`` (k,)
    metres above ground, ``tree_id`` (k,) int64 from 1, ordered by height descending."""

    xyz: np.ndarray
    height: np.ndarray
    tree_id: np.ndarray
    crs: object = None

    def __len__(self) -> int:
        return len(self.height)


def apex_points(xyz: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Index of each tree's apex, one per label > 0 in increasing label order: its highest point in
    elevation (``xyz[:, 2]``; ties: lowest x, then y, then the first point, not the point order).

    Not the highest point above ground: on a slope the ground falls away under the downhill side
    of a crown, whose points stand higher above it than the apex does, so the highest point of the
    canopy height model lies downhill of the apex and above the tree's height (the downhill
    displacement of CHM tree tops measured by Khosravipour, Skidmore, Wang, Isenburg & Khoshelham
    2015, "Effect of slope on treetop detection using a LiDAR Canopy Height Model", ISPRS J.
    Photogramm. Remote Sens. 104:44-52).  On level ground the two are the same point."""
    labels = np.asarray(labels)
    sel = np.flatnonzero(labels > 0)
    order = sel[np.lexsort((sel, xyz[sel, 1], xyz[sel, 0], -xyz[sel, 2], labels[sel]))]
    first = np.ones(len(order), dtype=bool)
    first[1:] = labels[order][1:] != labels[order][:-1]
    return order[first]


def _ordered(xyz: np.ndarray, height: np.ndarray, crs) -> TreeTops:
    order = np.lexsort((xyz[:, 1], xyz[:, 0], -height))
    xyz = np.asarray(xyz[order], dtype=np.float64).reshape(-1, 3)
    height = np.asarray(height[order], dtype=np.float64)
    return TreeTops(xyz, height, np.arange(1, len(height) + 1, dtype=np.int64), crs)


def union_tops(tops: TreeTops, more: TreeTops, take: np.ndarray) -> TreeTops:
    """``tops`` and the tops of ``more`` where ``take`` (a mask over ``more``) that are not among
    them (the same point), ordered and numbered as :func:`find_tree_tops` orders them."""
    xyz = np.concatenate([np.asarray(tops.xyz, dtype=np.float64).reshape(-1, 3), more.xyz[take]])
    height = np.concatenate([tops.height, more.height[take]])
    _, first = np.unique(xyz, axis=0, return_index=True)
    return _ordered(xyz[first], height[first], tops.crs)


def _one_per_plateau(xy: np.ndarray, height: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Indices keeping one maximum per group of equal-height maxima within each other's window."""
    n = len(xy)
    if n < 2:
        return np.arange(n)
    tree = cKDTree(xy)
    pairs = tree.query_pairs(float(radius.max()), output_type="ndarray")
    if len(pairs):
        i, j = pairs[:, 0], pairs[:, 1]
        d = np.linalg.norm(xy[i] - xy[j], axis=1)
        same = (height[i] == height[j]) & (d <= np.minimum(radius[i], radius[j]))
        i, j = i[same], j[same]
    else:
        i = j = np.zeros(0, dtype=np.int64)
    graph = coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n))
    n_groups, label = connected_components(graph, directed=False)
    if n_groups == n:
        return np.arange(n)
    counts = np.bincount(label, minlength=n_groups)
    centroid = np.column_stack([np.bincount(label, xy[:, k], n_groups) for k in (0, 1)]) / counts[:, None]
    dist = np.linalg.norm(xy - centroid[label], axis=1)
    order = np.lexsort((xy[:, 1], xy[:, 0], dist, label))
    first = np.ones(n, dtype=bool)
    first[1:] = label[order][1:] != label[order][:-1]
    return np.sort(order[first])


def _cell_maxima(xy: np.ndarray, h: np.ndarray, cell: float) -> np.ndarray:
    """Index of the highest point (then lowest x, then lowest y, then first) of each square
    ``cell``, cells in ascending (column, row) order: the first of each cell in
    ``np.lexsort((y, x, -h, row, column))``, kept on a dense grid of cells
    (:func:`_cell_maxima_kernel`; Sylva, not in the paper)."""
    pick = _cell_maxima_kernel(np.ascontiguousarray(xy, dtype=np.float64),
                               np.ascontiguousarray(h, dtype=np.float64), float(cell), 4 * len(xy) + 1024)
    if len(pick) or len(xy) == 0:
        return pick
    key = np.floor(xy / cell).astype(np.int64)           # a sparse extent or a point off any grid
    order = np.lexsort((xy[:, 1], xy[:, 0], -h, key[:, 1], key[:, 0]))
    first = np.ones(len(order), dtype=bool)
    first[1:] = np.any(key[order][1:] != key[order][:-1], axis=1)
    return order[first]


@njit
def _cell_maxima_kernel(xy, h, cell, max_cells):
    """:func:`_cell_maxima` on a dense grid; empty when it would exceed ``max_cells`` cells
    (or a coordinate is not finite)."""
    n = len(xy)
    ix, iy, x0, y0, nx, ny = grid_cells(xy, cell, max_cells)
    if nx == 0:
        return np.empty(0, dtype=np.int64)
    best = np.full(nx * ny, -1, dtype=np.int64)
    kept = 0
    for i in range(n):
        c = (ix[i] - x0) * ny + (iy[i] - y0)
        b = best[c]
        if b < 0:
            best[c] = i
            kept += 1
        elif h[i] > h[b] or (h[i] == h[b] and (xy[i, 0] < xy[b, 0]
                                               or (xy[i, 0] == xy[b, 0] and xy[i, 1] < xy[b, 1]))):
            best[c] = i
    out = np.empty(kept, dtype=np.int64)
    j = 0
    for c in range(nx * ny):
        if best[c] >= 0:
            out[j] = best[c]
            j += 1
    return out


def _local_maxima(xy: np.ndarray, h: np.ndarray, window: Window,
                  progress: Progress, cancelled: CancelCheck, cand=None, diameters=None):
    """Indices of the window maxima among points (xy, h).

    ``cand``: indices known to hold every maximum (e.g. the maxima of a
    narrower window); by default the highest point of each grid cell.
    ``diameters`` (per point, optional): a point's window is at least this wide."""
    from .noise import column_bounds, grid_buckets

    if cand is None:
        # A top is the highest point of its grid cell when the cell fits in the smallest window.
        cand = _cell_maxima(xy, h, max(window.min_diameter / 2.0 / np.sqrt(2.0), 1e-3))
    if len(cand) == 0:
        return cand
    radius = window.diameter(h[cand]) / 2.0
    if diameters is not None:
        radius = np.maximum(radius, np.asarray(diameters)[cand] / 2.0)
    # points bucketed in square cells half as wide as the median window radius (a wider window scans
    # more cells: one widest window, e.g. a tall tree's allometric one, does not make every search
    # scan its area), and few enough cells for the extent, CSR by cell
    lo, hi = column_bounds(xy)
    span = np.maximum(hi - lo, 1e-6)
    cell = max(0.5 * float(np.median(radius)), float(np.sqrt(span[0] * span[1] / (2.0 * len(xy) + 1024))), 1e-3)
    nx, ny = (np.floor(span / cell).astype(np.int64) + 1).tolist()
    order, starts, _ = grid_buckets(xy, float(lo[0]), float(lo[1]), cell, nx, ny)
    pts = np.ascontiguousarray(xy[order])
    hs = np.ascontiguousarray(h[order])
    is_top = np.zeros(len(cand), dtype=bool)
    chunk = 200_000
    for start in range(0, len(cand), chunk):
        check(cancelled)
        sl = slice(start, start + chunk)
        is_top[sl] = _window_tops(pts, hs, starts, xy[cand[sl]], h[cand[sl]], radius[sl],
                                  float(lo[0]), float(lo[1]), cell, nx, ny)
        report(progress, min(1.0, (start + chunk) / len(cand)), "tree tops")
    tops = cand[is_top]
    keep = _one_per_plateau(xy[tops], h[tops], radius[is_top])
    return tops[keep]


@njit
def _window_tops(pts, hs, starts, cxy, ch, radius, x0, y0, cell, nx, ny):
    """For each candidate (cxy, ch, radius): True when no point of ``pts``
    (bucketed by cell: ``starts``) within ``radius`` is higher.  Stops at the
    first higher point found, which is most candidates' fate."""
    out = np.empty(len(ch), dtype=np.bool_)
    for k in range(len(ch)):
        px, py, own, r = cxy[k, 0], cxy[k, 1], ch[k], radius[k]
        reach = int(np.ceil(r / cell))
        ix = int(np.floor((px - x0) / cell))
        iy = int(np.floor((py - y0) / cell))
        top = True
        for gx in range(max(ix - reach, 0), min(ix + reach, nx - 1) + 1):
            if not top:
                break
            for gy in range(max(iy - reach, 0), min(iy + reach, ny - 1) + 1):
                if not top:
                    break
                g = gx * ny + gy
                for j in range(starts[g], starts[g + 1]):
                    if hs[j] > own:
                        dx = pts[j, 0] - px
                        dy = pts[j, 1] - py
                        if np.sqrt(dx * dx + dy * dy) <= r:
                            top = False
                            break
        out[k] = top
    return out


def _shadowed(xy: np.ndarray, h: np.ndarray, cand: np.ndarray, others: np.ndarray,
              radius_m: float) -> np.ndarray:
    """Mask of the candidates with a higher point of ``others`` within ``radius_m``."""
    out = np.zeros(len(cand), dtype=bool)
    if len(cand) == 0 or len(others) == 0 or not radius_m > 0:
        return out
    near = cKDTree(xy[cand]).sparse_distance_matrix(cKDTree(xy[others]), radius_m,
                                                    output_type="ndarray")
    higher = h[others[near["j"]]] > h[cand[near["i"]]]
    out[near["i"][higher]] = True
    return out


def steep_column_m(inner_m: float) -> float:
    """The widest column no wider than ``inner_m`` that divides :data:`~sylva.core.cloud.ANCHOR_GRID_M`
    (0.3 m gives 70/234 = 0.2991 m): in an anchored local frame its columns are the same in every tile."""
    return ANCHOR_GRID_M / np.ceil(ANCHOR_GRID_M / inner_m - 1e-9)


def _steep(xy: np.ndarray, h: np.ndarray, cand: np.ndarray, rule: SteepApex) -> np.ndarray:
    """Mask of the candidates (indices into xy/h) the canopy falls away from steeply."""
    if len(cand) == 0:
        return np.zeros(0, dtype=bool)
    nsec = 8
    # the canopy surface: the highest point of every column, columns as wide as inner_m or a little less,
    # so that they divide the anchor grid and fall on the same places whatever the tile; ties by position,
    # not by the points' order (Sylva)
    surf = _cell_maxima(xy, h, steep_column_m(rule.inner_m))
    near = cKDTree(xy[cand]).sparse_distance_matrix(cKDTree(xy[surf]), rule.outer_m,
                                                    output_type="ndarray")
    i, j, d = near["i"], surf[near["j"]], near["v"]
    ring = d > rule.inner_m
    i, j, d = i[ring], j[ring], d[ring]
    slope = (h[cand[i]] - h[j]) / d
    # a steep sector holds at least one steep point: fewer than `sectors` such
    # points rule a candidate out before the (costlier) sector medians
    hopeful = np.bincount(i, weights=slope >= rule.slope, minlength=len(cand)) >= int(rule.sectors)
    keep = hopeful[i]
    i, j, d, slope = i[keep], j[keep], d[keep], slope[keep]
    c = cand[i]
    ang = np.arctan2(xy[j, 1] - xy[c, 1], xy[j, 0] - xy[c, 0])
    sector = np.floor((ang + np.pi) / (2.0 * np.pi) * nsec).astype(np.int64) % nsec
    key = i * nsec + sector
    order = np.lexsort((slope, key))
    key, slope = key[order], slope[order]
    ukey, start, count = np.unique(key, return_index=True, return_counts=True)
    median = slope[start + count // 2]          # the upper median of each sector
    steep = np.bincount(ukey // nsec, weights=median >= rule.slope, minlength=len(cand))
    return steep >= int(rule.sectors)


def steep_tops(xy: np.ndarray, h: np.ndarray, top_xy: np.ndarray, top_h: np.ndarray,
               rule: SteepApex) -> np.ndarray:
    """Mask of the tops (``top_xy``, ``top_h``) the canopy of the points (``xy``, ``h``) falls away
    from steeply, by ``rule``'s sectors and slope (the test of :class:`SteepApex`).  Only the points'
    own surface joins the tops: its column maxima are those of all the points (same tie rule)."""
    surf = _cell_maxima(xy, h, steep_column_m(rule.inner_m))
    n = len(surf)
    return _steep(np.r_[xy[surf], top_xy], np.r_[h[surf], top_h], np.arange(n, n + len(top_xy)), rule)


def _tops_from_points(cloud: PointCloud, window: Window, min_height_m: float,
                      isolation_m: Optional[float], apex: Optional[SteepApex],
                      progress: Progress, cancelled: CancelCheck, diameters=None,
                      apex_diameters=None) -> TreeTops:
    from .noise import isolated_points
    from .terrain import heights_above_ground

    height = heights_above_ground(cloud)
    high = np.isfinite(height) & (height >= min_height_m)
    loc = cloud.local_xyz()
    high = np.nonzero(high & ~isolated_points(cloud, isolation_m, among=high, loc=loc))[0]
    if len(high) == 0:
        return _ordered(np.zeros((0, 3)), np.zeros(0), cloud.crs)
    xy = loc[high, :2]
    h = height[high]
    dia = None if diameters is None else np.asarray(diameters, dtype=np.float64)[high]
    adia = None if apex_diameters is None else np.asarray(apex_diameters, dtype=np.float64)[high]
    if dia is not None and adia is not None:
        adia = np.minimum(adia, np.maximum(dia, window.min_diameter))
    if apex is not None and apex.diameter_m < window.min_diameter:
        # every maximum of the window is one of the narrow window: test only those
        narrow = _local_maxima(xy, h, FixedWindow(apex.diameter_m), None, cancelled, diameters=adia)
        tops = _local_maxima(xy, h, window, progress, cancelled, cand=narrow, diameters=dia)
        narrow = np.setdiff1d(narrow, tops)
        # a second steep point of one cone: a higher top stands right next to it
        # (tested against the window's tops first: it spares most sector tests)
        narrow = narrow[~_shadowed(xy, h, narrow, tops, apex.separation_m)]
        narrow = narrow[_steep(xy, h, narrow, apex)]
        narrow = narrow[~_shadowed(xy, h, narrow, narrow, apex.separation_m)]
        tops = np.concatenate([tops, narrow])
    else:
        tops = _local_maxima(xy, h, window, progress, cancelled, diameters=dia)
    tops = high[tops]
    return _ordered(cloud.xyz[tops], height[tops], cloud.crs)


def _metres_per_unit(crs) -> float:
    if crs is None:
        return 1.0
    try:
        return float(crs.axis_info[0].unit_conversion_factor)
    except Exception:  # pragma: no cover
        return 1.0


def _tops_from_chm(chm: Raster, window: Window, min_height_m: float,
                   progress: Progress, cancelled: CancelCheck) -> TreeTops:
    unit = _metres_per_unit(chm.crs)
    pixel_m = chm.pixel * unit
    data = np.where(np.isfinite(chm.data), chm.data, -np.inf).astype(np.float64)
    valid = data >= min_height_m
    # Window radius in whole cells per pixel, grouped into bands of equal radius.
    radius_cells = np.round(window.diameter(np.where(valid, data, 0.0)) / 2.0 / pixel_m).astype(np.int64)
    radius_cells = np.maximum(radius_cells, 1)
    maxima = np.zeros(data.shape, dtype=bool)
    bands = np.unique(radius_cells[valid])
    for k, r in enumerate(bands):
        check(cancelled)
        r = int(r)
        grid = np.arange(-r, r + 1)
        footprint = (grid[:, None] ** 2 + grid[None, :] ** 2) <= r * r
        wmax = ndimage.maximum_filter(data, footprint=footprint, mode="constant", cval=-np.inf)
        band = valid & (radius_cells == r)
        maxima |= band & (data >= wmax)
        report(progress, (k + 1) / len(bands), "tree tops")
    rows, cols = np.nonzero(maxima)
    if len(rows) == 0:
        return _ordered(np.zeros((0, 3)), np.zeros(0), chm.crs)
    x, y = chm.xy_of(rows, cols)
    h = data[rows, cols]
    xy_m = np.column_stack([x, y]) * unit
    keep = _one_per_plateau(xy_m, h, np.maximum(radius_cells[rows, cols] * pixel_m, 1.5 * pixel_m))
    xyz = np.column_stack([x[keep], y[keep], h[keep] / unit])
    return _ordered(xyz, h[keep], chm.crs)


def find_tree_tops(cloud_or_chm: Union[PointCloud, Raster], window: Optional[Window] = None,
                   min_height_m: float = MIN_TREE_HEIGHT_M, isolation_m: Optional[float] = 2.0,
                   progress: Progress = None, cancelled: CancelCheck = None,
                   apex: Optional[SteepApex] = None, diameters=None,
                   apex_diameters=None) -> TreeTops:
    """Tree tops by local-maximum filtering on a normalised cloud or on a CHM raster.

    Cloud: a point is a top when no point within the window (diameter from its
    own height) is higher; only the highest point of each grid cell smaller than
    the narrowest window is tested (cKDTree neighbourhoods, vectorised).  The
    cloud's ``height`` attribute is used, or the cloud is normalised first.
    Noise never makes a top: points of classes 7/18 and points above
    ``min_height_m`` with no other within ``isolation_m`` metres (3-D) are left
    out (:func:`sylva.core.noise.isolated_points`; ``isolation_m=None`` keeps them).
    CHM: a cell is a top when it equals the maximum of the circular window
    centred on it; variable windows are applied per band of equal radius in cells.
    Either way, equal-height maxima within each other's window count once.
    ``apex``: a :class:`SteepApex` rule adding the steep tips a wide window
    misses (point clouds only).  ``diameters`` / ``apex_diameters`` (point
    clouds only, one per point, metres): each point's window (its apex window)
    is at least this wide, e.g. widened where the scan is sparse
    (:meth:`sylva.core.segment.NormalizedCut.windows`).
    """
    window = FixedWindow() if window is None else window
    if not hasattr(window, "diameter"):
        raise InputError(f"unknown tree-top window {window!r}; use FixedWindow() or VariableWindow()")
    report(progress, 0.0, "tree tops")
    if apex is not None and not isinstance(apex, SteepApex):
        raise InputError(f"unknown apex rule {apex!r}; use SteepApex() or None")
    if isinstance(cloud_or_chm, Raster):
        if apex is not None:
            raise InputError("the steep-apex rule (SteepApex) needs a point cloud, not a CHM raster")
        tops = _tops_from_chm(cloud_or_chm, window, min_height_m, progress, cancelled)
    elif isinstance(cloud_or_chm, PointCloud):
        if len(cloud_or_chm) == 0:
            raise EmptyInputError(f"{cloud_or_chm.name}: no points to find tree tops in")
        tops = _tops_from_points(cloud_or_chm, window, min_height_m, isolation_m, apex,
                                 progress, cancelled, diameters, apex_diameters)
    else:
        raise InputError(f"find_tree_tops needs a PointCloud or a Raster, got {type(cloud_or_chm).__name__}")
    report(progress, 1.0, "tree tops")
    return tops


__all__ = ["FixedWindow", "VariableWindow", "SteepApex", "TreeTops", "apex_points", "find_tree_tops",
           "steep_tops", "union_tops"]
