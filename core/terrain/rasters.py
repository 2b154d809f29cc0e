"""Rasters in the cloud's CRS, values in metres: the DTM (:func:`digital_terrain_model`, a TIN of the
ground points) and the CHM (:func:`canopy_height_model`: highest first return per cell, or the pit-free
CHM of Khosravipour et al. 2014).
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor, as_completed
from typing import Optional, Sequence

import numpy as np
from scipy import ndimage

from ..cloud import PointCloud
from ..errors import EmptyInputError, InputError
from ..noise import isolated_points
from ..progress import CancelCheck, Progress, check, report
from ..raster import Raster
from .heights import ground_elevation, heights_above_ground
from .interpolation import tin_interpolate


def _grid_for(cloud: PointCloud, resolution_m: float):
    """Pixel (CRS units), west and north edges aligned on multiples of the pixel, shape."""
    if not resolution_m > 0:
        raise InputError(f"resolution must be positive, got {resolution_m} m")
    pixel = resolution_m / cloud.units.horizontal_m
    xmin, ymin, _, xmax, ymax, _ = cloud.bounds()
    x0 = np.floor(xmin / pixel) * pixel
    y0 = np.ceil(ymax / pixel) * pixel
    if y0 == ymax:
        y0 += pixel
    cols = int(np.floor((xmax - x0) / pixel)) + 1
    rows = int(np.floor((y0 - ymin) / pixel)) + 1
    return pixel, x0, y0, (rows, cols)


def digital_terrain_model(cloud: PointCloud, resolution_m: float = 1.0,
                          ground: Optional[np.ndarray] = None) -> Raster:
    """DTM (metres, local frame elevation + origin z = CRS elevation in metres) from a TIN of
    the ground points, georeferenced in the cloud's CRS; IDW outside the ground hull."""
    pixel, x0, y0, shape = _grid_for(cloud, resolution_m)
    raster = Raster(np.zeros(shape, np.float32), x0, y0, pixel, cloud.crs)
    cx, cy = raster.cell_centres()
    query = np.column_stack([cx.ravel(), cy.ravel(), np.zeros(cx.size)])
    local = (query - cloud.origin) * cloud.units.horizontal_m
    z = ground_elevation(cloud, local, method="tin", ground=ground)
    raster.data[:] = z.reshape(shape)
    return raster


def _rasterize_max(rows, cols, values, shape) -> np.ndarray:
    grid = np.full(shape, -np.inf)
    np.maximum.at(grid, (rows, cols), values)
    grid[~np.isfinite(grid)] = np.nan
    return grid


def _fill_small_holes(grid: np.ndarray, min_neighbours: int = 5) -> np.ndarray:
    """Fill empty cells having at least ``min_neighbours`` of 8 neighbours with data by their mean."""
    valid = np.isfinite(grid)
    kernel = np.ones((3, 3))
    kernel[1, 1] = 0
    count = ndimage.convolve(valid.astype(np.float64), kernel, mode="constant")
    total = ndimage.convolve(np.where(valid, grid, 0.0), kernel, mode="constant")
    fill = ~valid & (count >= min_neighbours)
    out = grid.copy()
    out[fill] = total[fill] / count[fill]
    return out


def canopy_height_model(cloud: PointCloud, resolution_m: float = 0.5, pit_free: bool = True,
                        thresholds_m: Sequence[float] = (0, 2, 5, 10, 15, 20, 25, 30),
                        max_edge_m: float = 1.5, isolation_m: Optional[float] = 2.0,
                        progress: Progress = None, cancelled: CancelCheck = None) -> Raster:
    """Canopy height model (metres above ground) as a :class:`Raster` in the cloud's CRS.

    Uses the ``height`` attribute (the cloud is normalised first when it has
    none) of the first returns (all points when ``return_number`` is absent),
    without noise (:func:`sylva.core.noise.isolated_points`: classes 7 and 18, and first returns with
    no other within ``isolation_m`` metres in 3-D; ``isolation_m=None`` keeps them).

    ``pit_free=False``: highest first return per cell, then empty cells with at
    least 5 of 8 neighbours filled by their mean.

    ``pit_free=True``: Khosravipour et al. (2014): for each height threshold,
    a TIN of the first returns at or above it (the lowest threshold's from all
    first returns) is interpolated at the cell centres, dropping triangles with an
    edge longer than ``max_edge_m`` (the "freeze distance") in every layer but the
    lowest; the partial CHMs are stacked by per-cell maximum.  The first returns
    are first thinned to the highest per half-pixel sub-cell, as in the LAStools
    pit-free workflow (``lasthin -highest``).  Thresholds above the
    tallest point are skipped.  ``max_edge_m`` should be a few times the mean
    first-return spacing (1.5 m suits 2-20 pts/m2).
    """
    if len(cloud) == 0:
        raise EmptyInputError(f"{cloud.name}: no points for a canopy height model")
    report(progress, 0.0, "canopy height model")
    height = heights_above_ground(cloud)
    first = cloud.attr("return_number")
    keep = np.isfinite(height)
    if first is not None:
        keep &= np.asarray(first) <= 1
    keep &= ~isolated_points(cloud, isolation_m, among=keep)
    if not keep.any():
        raise EmptyInputError(f"{cloud.name}: no first returns for a canopy height model")
    pixel, x0, y0, shape = _grid_for(cloud, resolution_m)
    raster = Raster(np.full(shape, np.nan, np.float32), x0, y0, pixel, cloud.crs)
    xyz = cloud.xyz[keep]
    h = height[keep]
    rows, cols = raster.index_of(xyz[:, 0], xyz[:, 1])
    check(cancelled)
    if not pit_free:
        grid = _rasterize_max(rows, cols, h, shape)
        raster.data[:] = _fill_small_holes(grid)
        report(progress, 1.0, "canopy height model")
        return raster

    # Local metres for the TINs; cell centres in the same frame.
    scale = cloud.units.horizontal_m
    xy = (xyz[:, :2] - cloud.origin[:2]) * scale
    cx, cy = raster.cell_centres()
    centres = np.column_stack([(cx.ravel() - cloud.origin[0]) * scale,
                               (cy.ravel() - cloud.origin[1]) * scale])
    # Keep the highest first return per sub-cell of half a pixel (the thinning step of
    # the LAStools pit-free workflow, "lasthin -highest"): at most 4 points per pixel.
    sub = np.floor(xy / (resolution_m / 2.0)).astype(np.int64)
    order = np.lexsort((-h, sub[:, 1], sub[:, 0]))
    top = np.ones(len(order), dtype=bool)
    top[1:] = np.any(sub[order][1:] != sub[order][:-1], axis=1)
    xy, h = xy[order[top]], h[order[top]]
    stack = np.full(cx.size, -np.inf)
    levels = sorted(float(t) for t in thresholds_m)
    levels = [t for i, t in enumerate(levels) if i == 0 or t <= h.max()]

    def layer(i: int):
        """Partial CHM of threshold ``levels[i]``: (cell indices, values) or None."""
        if cancelled is not None and cancelled():
            return None
        sel = h >= levels[i]
        if sel.sum() < 3:
            return None
        pts, vals = xy[sel], h[sel]
        # Only cells inside the layer's bounding box need interpolating.
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        box = np.nonzero((centres[:, 0] >= lo[0]) & (centres[:, 0] <= hi[0])
                         & (centres[:, 1] >= lo[1]) & (centres[:, 1] <= hi[1]))[0]
        values = tin_interpolate(pts, vals, centres[box], max_edge=None if i == 0 else max_edge_m)
        ok = np.isfinite(values)
        return box[ok], values[ok]

    # Layers are independent and Qhull partly releases the GIL: a few threads help.
    # Stacking by maximum does not depend on the order layers finish in.
    workers = max(1, min(len(levels), os.cpu_count() or 1, 4))
    with ThreadPoolExecutor(max_workers=workers) as pool:
        futures = [pool.submit(layer, i) for i in range(len(levels))]
        for done, future in enumerate(as_completed(futures)):
            result = future.result()
            if result is not None:
                idx, values = result
                stack[idx] = np.maximum(stack[idx], values)
            report(progress, (done + 1) / len(levels), "pit-free CHM layers")
    check(cancelled)
    stack[~np.isfinite(stack)] = np.nan
    raster.data[:] = stack.reshape(shape)
    report(progress, 1.0, "canopy height model")
    return raster
