"""Ground, height above ground and canopy height models.

Everything here computes in the cloud's local metric frame
(:meth:`PointCloud.local_xyz`: metres, origin at the tile's lower-left) and
returns heights in **metres**, whatever the CRS units: a normalised cloud
carries one float64 attribute ``height`` (metres above ground); there is no
separate ``ground_z`` attribute, the ground elevation is ``z - height`` after
converting ``height`` to vertical CRS units.  Rasters come back in the cloud's
CRS (pixel size in CRS units = ``resolution_m / units.horizontal_m``) with
values in metres.

Ground classification, when a tile has none (class 2), is a method value passed
to :func:`classify_ground`:

* :class:`SMRF` — Pingel, Clarke & McBride (2013), "An improved simple
  morphological filter for the terrain classification of airborne LIDAR
  data", ISPRS J. Photogramm. Remote Sens. 77:21-30.
* :class:`CSF` — Zhang, Qi, Wan, Wang, Xie, Wang & Yan (2016), "An easy-to-use
  airborne LiDAR data filtering method based on cloth simulation", Remote
  Sensing 8(6):501.

The default (:data:`DEFAULT_GROUND`) was chosen by the comparison printed by
``benchmarks/terrain.py`` (ground precision/recall and DTM RMSE on synthetic
stands on 0, 15 and 30 degree slopes).

The pit-free CHM follows Khosravipour, Skidmore, Isenburg, Wang & Hussin
(2014), "Generating pit-free canopy height models from airborne lidar",
Photogramm. Eng. Remote Sens. 80(9):863-872: partial CHMs interpolated from
TINs of the first returns above a series of height thresholds, triangles with
an edge longer than a freeze distance removed from all but the lowest layer,
stacked by per-cell maximum.
"""
from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from typing import Optional, Sequence, Union

import numpy as np
from scipy import ndimage
from scipy.spatial import Delaunay, QhullError, cKDTree

from .cloud import PointCloud
from .errors import EmptyInputError, InputError
from .jit import njit
from .kernels.buckets import bucket_by_cell
from .kernels.grid import grid_cells
from .noise import NOISE_CLASSES, isolated_points
from .progress import CancelCheck, Progress, check, report
from .raster import Raster

GROUND_CLASS = 2


# --------------------------------------------------------------------------- ground

def ground_mask(cloud: PointCloud) -> np.ndarray:
    """Boolean mask of the points classified as ground (ASPRS class 2)."""
    cls = cloud.attr("classification")
    if cls is None:
        return np.zeros(len(cloud), dtype=bool)
    return np.asarray(cls) == GROUND_CLASS


def _grid_index(xy: np.ndarray, cell: float, pad: int = 0):
    """Integer cell (row=iy, col=ix) of local points, and the grid shape."""
    ij = np.floor(xy / cell).astype(np.int64) + pad
    shape = (int(ij[:, 1].max()) + 1 + pad, int(ij[:, 0].max()) + 1 + pad)
    return ij[:, 1], ij[:, 0], shape


def _fill_nearest(grid: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Copy of ``grid`` whose unknown cells take the value of the nearest known cell."""
    if known.all():
        return grid.copy()
    if not known.any():
        raise ValueError("no known cells to fill from")
    idx = ndimage.distance_transform_edt(~known, return_distances=False, return_indices=True)
    return grid[tuple(idx)]


def _fill_linear(grid: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Fill unknown cells by linear interpolation (Delaunay of known cell centres), nearest outside."""
    if known.all():
        return grid.copy()
    out = _fill_nearest(grid, known)
    rows, cols = np.nonzero(known)
    if len(rows) >= 3:
        q_rows, q_cols = np.nonzero(~known)
        values = _tin_interpolate(np.column_stack([cols, rows]).astype(np.float64), grid[rows, cols],
                                  np.column_stack([q_cols, q_rows]).astype(np.float64))
        ok = np.isfinite(values)
        out[q_rows[ok], q_cols[ok]] = values[ok]
    return out


def _disk(radius: int) -> np.ndarray:
    r = np.arange(-radius, radius + 1)
    return (r[:, None] ** 2 + r[None, :] ** 2) <= radius * radius


def _bilinear(grid: np.ndarray, x: np.ndarray, y: np.ndarray, cell: float, pad: int = 0) -> np.ndarray:
    """Sample a grid whose cell (iy, ix) is centred at ((ix - pad + .5) cell, (iy - pad + .5) cell)."""
    coords = np.vstack([y / cell - 0.5 + pad, x / cell - 0.5 + pad])
    return ndimage.map_coordinates(grid, coords, order=1, mode="nearest")


def _disk_filter(grid: np.ndarray, radius: int, dilate: bool) -> np.ndarray:
    """``ndimage.grey_erosion`` (``dilate``: ``grey_dilation``) of a finite ``grid`` by
    ``_disk(radius)``, edges extended (``mode="nearest"``): :func:`_chord_filter`."""
    r = int(radius)
    half = np.array([math.isqrt(r * r - dy * dy) for dy in range(r + 1)], dtype=np.int64)
    return _chord_filter(np.ascontiguousarray(grid, dtype=np.float64), half, bool(dilate))


@njit
def _chord_filter(grid, half, dilate):
    """Minimum (``dilate``: maximum) of ``grid`` over the disk whose chord ``dy`` rows off
    the centre spans ``half[|dy|]`` cells either side, rows and columns clamped at the edges.

    Sylva, not in the paper: by chords, a minimum of minima, so the same values as the
    disk filter (a tie of 0.0 and -0.0 may keep the other one: equal to every comparison):
    each source row's minima over every half-width, grown one cell at a time,
    are combined into the output rows within reach; about (4 r + 1) comparisons per cell
    instead of the disk's area, and one row of minima per half-width in memory."""
    h, w = grid.shape
    r = len(half) - 1
    out = np.full((h, w), -np.inf if dilate else np.inf)
    row = np.empty((half[0] + 1, w))
    for s in range(h):
        for x in range(w):
            row[0, x] = grid[s, x]
        for k in range(1, half[0] + 1):
            for x in range(w):
                m = row[k - 1, x]
                a = grid[s, max(x - k, 0)]
                b = grid[s, min(x + k, w - 1)]
                if dilate:
                    m = a if a > m else m
                    m = b if b > m else m
                else:
                    m = a if a < m else m
                    m = b if b < m else m
                row[k, x] = m
        for dy in range(-r, r + 1):
            k = half[abs(dy)]
            first = 0 if s == 0 else max(s - dy, 0)             # output rows y with
            last = h - 1 if s == h - 1 else min(s - dy, h - 1)  # clamp(y + dy) == s
            for y in range(first, last + 1):
                for x in range(w):
                    v = row[k, x]
                    if dilate:
                        out[y, x] = v if v > out[y, x] else out[y, x]
                    else:
                        out[y, x] = v if v < out[y, x] else out[y, x]
    return out


def _progressive_opening(surface: np.ndarray, radii: Sequence[int], thresholds: Sequence[float]) -> np.ndarray:
    """Pingel et al. (2013), progressive filter: flag cells whose drop under an opening of growing radius
    exceeds the radius' threshold; each opening is applied to the previous opened surface.
    The opening (erosion then dilation by a disk) is :func:`_disk_filter`'s."""
    flagged = np.zeros(surface.shape, dtype=bool)
    last = surface
    for radius, threshold in zip(radii, thresholds):
        opened = _disk_filter(_disk_filter(last, int(radius), False), int(radius), True)
        flagged |= (last - opened) > threshold
        last = opened
    return flagged


def low_outliers(cloud_or_local, cell_m: float = 1.0, slope: float = 5.0) -> np.ndarray:
    """Points far below their neighbours (Pingel et al. 2013, low-outlier step: a morphological
    closing of the minimum surface with a one-cell disk; a point more than
    ``slope * cell_m`` below it is a low outlier)."""
    loc = cloud_or_local.local_xyz() if isinstance(cloud_or_local, PointCloud) else cloud_or_local
    if len(loc) == 0:
        return np.zeros(0, dtype=bool)
    rows, cols, shape = _grid_index(loc[:, :2], cell_m)
    zmin = np.full(shape, np.inf)
    np.minimum.at(zmin, (rows, cols), loc[:, 2])
    empty = ~np.isfinite(zmin)
    surface = _fill_nearest(np.where(empty, 0.0, zmin), ~empty)
    closed = ndimage.grey_closing(surface, footprint=_disk(1), mode="nearest")
    return loc[:, 2] < closed[rows, cols] - slope * cell_m


@dataclass(frozen=True)
class SMRF:
    """Simple Morphological Filter, Pingel, Clarke & McBride (2013).

    ``cell_m``: minimum-surface cell size (paper: 1 m); ``slope``: slope
    threshold, rise over run (0.15); ``window_m``: maximum opening radius
    (18 m); ``elevation_threshold_m`` (0.5 m) and ``elevation_scaler``
    (1.25): a point is ground when ``|z - DEM| <= elevation_threshold_m +
    elevation_scaler * slope_of_DEM``.  The paper's parameter values for
    its ISPRS benchmark are the defaults.

    Steps, in the paper's order: (1) minimum surface on a ``cell_m`` grid, empty cells
    filled; (2) low outliers: the same progressive filter on the negated surface
    with radius one cell and a 500 % slope; (3) progressive morphological
    opening with disk radii 1..``window_m``/``cell_m`` cells, flagging cells
    whose elevation drop exceeds ``slope * radius``; (4) provisional DEM by
    interpolating the unflagged cells; (5) point classification against the
    DEM with the slope-dependent threshold.
    """

    cell_m: float = 1.0
    slope: float = 0.15
    window_m: float = 18.0
    elevation_threshold_m: float = 0.5
    elevation_scaler: float = 1.25

    def classify(self, cloud: PointCloud) -> np.ndarray:
        if len(cloud) == 0:
            return np.zeros(0, dtype=bool)
        loc = cloud.local_xyz()
        c = float(self.cell_m)
        rows, cols, shape = _grid_index(loc[:, :2], c)
        zmin = np.full(shape, np.inf)
        np.minimum.at(zmin, (rows, cols), loc[:, 2])
        empty = ~np.isfinite(zmin)
        surface = _fill_nearest(np.where(empty, 0.0, zmin), ~empty)
        # (2) low outliers: progressive filter of the negated surface, radius 1, slope 5.
        low = _progressive_opening(-surface, [1], [5.0 * c]) & ~empty
        known = ~empty & ~low
        surface = _fill_nearest(surface, known)
        # (3) progressive opening with linearly increasing radius.
        n_radii = max(1, int(np.ceil(self.window_m / c)))
        radii = np.arange(1, n_radii + 1)
        objects = _progressive_opening(surface, radii, self.slope * radii * c)
        ground_cells = known & ~objects
        if not ground_cells.any():
            return np.zeros(len(cloud), dtype=bool)
        # (4) provisional DEM.
        dem = _fill_linear(surface, ground_cells)
        gy, gx = np.gradient(dem, c)
        slope = np.hypot(gx, gy)
        # (5) classify points against the DEM.
        x, y, z = loc[:, 0], loc[:, 1], loc[:, 2]
        dz = z - _bilinear(dem, x, y, c)
        threshold = self.elevation_threshold_m + self.elevation_scaler * _bilinear(slope, x, y, c)
        return np.abs(dz) <= threshold


@dataclass(frozen=True)
class CSF:
    """Cloth Simulation Filter, Zhang et al. (2016), vectorised over the cloth grid.

    The cloud is turned upside down and a cloth of particles spaced
    ``cloth_resolution_m`` falls onto it (the paper's particle model: Verlet integration
    with ``time_step`` and damping): a particle stops when it reaches the
    highest inverted point under it (its "intersection height value");
    internal forces pull neighbouring particles together ``rigidness`` times per
    step (paper: 1 steep slopes, 2 terraced relief, 3 flat terrain).  A point is
    ground when it lies within ``class_threshold_m`` of the final cloth.
    Paper/reference implementation defaults: resolution 0.5 m,
    rigidness 3, time step 0.65, class threshold 0.5 m, 500 iterations.

    Differences from the reference implementation: the spring constraints are
    solved for all particles at once (Jacobi) instead of one spring at a time,
    the optional post-processing of steep slopes is not done, and low outliers
    (:func:`low_outliers`), which the paper assumes removed beforehand, are
    ignored by the cloth and never ground.
    """

    cloth_resolution_m: float = 0.5
    rigidness: int = 3
    time_step: float = 0.65
    class_threshold_m: float = 0.5
    iterations: int = 500
    gravity: float = 0.2
    damping: float = 0.01
    convergence_m: float = 0.005

    def cloth(self, cloud: PointCloud):
        """Simulate the cloth; returns (cloth heights in inverted local metres, cell, pad, local xyz)."""
        loc = cloud.local_xyz()
        c = float(self.cloth_resolution_m)
        pad = 2
        inv = -loc[:, 2]
        rows, cols, shape = _grid_index(loc[:, :2] + 0.5 * c, c, pad)  # nodes at multiples of c
        ok = ~low_outliers(loc, max(1.0, c))
        ihv = np.full(shape, -np.inf)
        np.maximum.at(ihv, (rows[ok], cols[ok]), inv[ok])
        known = np.isfinite(ihv)
        ihv = _fill_nearest(np.where(known, ihv, 0.0), known)
        top = inv.max() + 1.0
        z = np.full(shape, top)
        z_old = z.copy()
        movable = np.ones(shape, dtype=bool)
        step = self.gravity * self.time_step ** 2
        for _ in range(int(self.iterations)):
            moved = z + (z - z_old) * (1.0 - self.damping) - step
            z_old = z
            z = np.where(movable, moved, z)
            for _ in range(max(1, int(self.rigidness))):
                z = self._springs(z, movable)
                hit = movable & (z <= ihv)
                z[hit] = ihv[hit]
                movable &= ~hit
            change = np.abs(z - z_old)[movable]
            if change.size == 0 or change.max() < self.convergence_m:
                break
        return z, c, pad, loc

    @staticmethod
    def _springs(z: np.ndarray, movable: np.ndarray) -> np.ndarray:
        """One Jacobi pass of the springs between 4-neighbours: a movable particle moves half-way
        towards a movable neighbour and all the way towards an immovable one, averaged."""
        zp = np.pad(z, 1, mode="edge")
        mp = np.pad(movable, 1, mode="edge")
        total = np.zeros_like(z)
        centre = (slice(1, -1), slice(1, -1))
        for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            nb = (slice(1 + dr, zp.shape[0] - 1 + dr), slice(1 + dc, zp.shape[1] - 1 + dc))
            weight = np.where(mp[nb], 0.5, 1.0)
            total += weight * (zp[nb] - zp[centre])
        return np.where(movable, z + total / 4.0, z)

    def classify(self, cloud: PointCloud) -> np.ndarray:
        if len(cloud) == 0:
            return np.zeros(0, dtype=bool)
        z, c, pad, loc = self.cloth(cloud)
        # node (iy, ix) sits at ((ix - pad) c, (iy - pad) c): sample with a half-cell shift.
        cloth_at = _bilinear(z, loc[:, 0] + 0.5 * c, loc[:, 1] + 0.5 * c, c, pad)
        return (np.abs(-loc[:, 2] - cloth_at) <= self.class_threshold_m) & ~low_outliers(loc, max(1.0, c))


GroundMethod = Union[SMRF, CSF]
# Chosen by benchmarks/terrain.py (synthetic medium stands, 10 pulses/m2, slopes 0/15/30
# degrees, seeds 0 and 1): SMRF had precision 0.999, recall 0.987 and a 1 m DTM RMSE of
# 0.04-0.13 m in every case (mean 0.07 m, 0.75 s); CSF with rigidness 3 had a higher
# recall (0.996) but its DTM RMSE jumped to 0.89 m on one 30-degree stand (mean 0.18 m),
# rigidness 1 and 2 were worse (1.56 m, 0.54 m).
DEFAULT_GROUND: GroundMethod = SMRF()


def classify_ground(cloud: PointCloud, method: Optional[GroundMethod] = None) -> np.ndarray:
    """Boolean ground mask computed by ``method`` (default :data:`DEFAULT_GROUND`)."""
    method = DEFAULT_GROUND if method is None else method
    if not hasattr(method, "classify"):
        raise InputError(f"unknown ground classification method {method!r}; use SMRF() or CSF()")
    if len(cloud) == 0:
        raise EmptyInputError(f"{cloud.name}: no points to classify")
    return np.asarray(method.classify(cloud), dtype=bool)


# --------------------------------------------------------------------------- interpolation

def _spatial_order(xy: np.ndarray) -> np.ndarray:
    """A permutation visiting points row by row of a coarse grid, alternating direction.

    Qhull's point location walks from the previous answer, so querying (and
    triangulating) in this order instead of at random is hundreds of times faster.
    The permutation is ``np.lexsort((serpentine column, row))``'s, computed by a
    counting sort (:func:`_serpentine_sort`; Sylva, not in the paper).
    """
    if len(xy) < 2:
        return np.arange(len(xy))
    order = _serpentine_sort(np.ascontiguousarray(xy, dtype=np.float64), 4 * len(xy) + 1024)
    if len(order) == len(xy):
        return order
    lo = xy.min(axis=0)                                # a degenerate extent: too many cells
    span = np.maximum(xy.max(axis=0) - lo, 1e-9)
    cell = max(np.sqrt(span[0] * span[1] / len(xy)) * 4.0, 1e-9)
    ij = np.floor((xy - lo) / cell).astype(np.int64)
    serpentine = np.where(ij[:, 1] % 2 == 0, ij[:, 0], -ij[:, 0])
    return np.lexsort((serpentine, ij[:, 1]))


@njit
def _serpentine_sort(xy, max_cells):
    """:func:`_spatial_order`'s permutation: points in square cells of 4 times the mean
    spacing from the lower-left corner, sorted by row, then by column (descending in odd
    rows), then by index (a stable counting sort).  Empty when the grid would have more
    than ``max_cells`` cells."""
    n = len(xy)
    x0, y0, x1, y1 = xy[0, 0], xy[0, 1], xy[0, 0], xy[0, 1]
    for i in range(1, n):
        x0, y0 = min(x0, xy[i, 0]), min(y0, xy[i, 1])
        x1, y1 = max(x1, xy[i, 0]), max(y1, xy[i, 1])
    cell = max(np.sqrt(max(x1 - x0, 1e-9) * max(y1 - y0, 1e-9) / n) * 4.0, 1e-9)
    ix = np.empty(n, dtype=np.int64)
    iy = np.empty(n, dtype=np.int64)
    nx, ny = 0, 0
    for i in range(n):
        fx = np.floor((xy[i, 0] - x0) / cell)
        fy = np.floor((xy[i, 1] - y0) / cell)
        if not (fx >= 0 and fy >= 0 and fx < max_cells and fy < max_cells):
            return np.empty(0, dtype=np.int64)
        ix[i], iy[i] = int(fx), int(fy)
        nx, ny = max(nx, ix[i] + 1), max(ny, iy[i] + 1)
    if nx * ny > max_cells:
        return np.empty(0, dtype=np.int64)
    key = np.empty(n, dtype=np.int64)
    for i in range(n):
        col = ix[i] if iy[i] % 2 == 0 else nx - 1 - ix[i]
        key[i] = iy[i] * nx + col
    return bucket_by_cell(key, nx * ny)[1]


def _int32(index: np.ndarray) -> np.ndarray:
    """Qhull's simplex and neighbour indices as the kernels take them (C int32: no copy)."""
    return np.ascontiguousarray(index, dtype=np.int32)


def _barycentric(tri: Delaunay, simplex: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (n, 3) of ``query`` in triangles ``simplex`` (no qhull transform)."""
    p = tri.points[tri.simplices[simplex]]                    # (n, 3, 2)
    v0, v1, v2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], query - p[:, 0]
    det = v0[:, 0] * v1[:, 1] - v0[:, 1] * v1[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        l1 = (v2[:, 0] * v1[:, 1] - v2[:, 1] * v1[:, 0]) / det
        l2 = (v0[:, 0] * v2[:, 1] - v0[:, 1] * v2[:, 0]) / det
    bary = np.column_stack([1.0 - l1 - l2, l1, l2])
    return np.where(np.isfinite(bary), bary, -np.inf)


def _locate(tri: Delaunay, query: np.ndarray, max_steps: int = 500,
            at_vertex: Optional[np.ndarray] = None):
    """Triangle holding each query point (-1 outside the hull) and its barycentric coordinates.

    A visibility walk (which terminates on Delaunay triangulations), compiled:
    the queries are visited in a serpentine order (:func:`_spatial_order`) and
    each walk starts in the triangle of the previous one, stepping across the
    edge facing the most negative barycentric coordinate, so a walk is a few
    steps.  Faster than ``Delaunay.find_simplex``, whose per-simplex
    transforms dominate the cost on large ground sets.

    A walk longer than ``max_steps`` is *lost* (the first queries, walking from
    triangle 0, usually are); lost queries get ``find_simplex``'s answers
    (:func:`_settle_lost`).  ``at_vertex``: optional mask of ``tri.points``;
    see :func:`_settle_lost`.
    """
    query = np.ascontiguousarray(query, dtype=np.float64)
    order = _spatial_order(query)
    points = np.ascontiguousarray(tri.points)
    simplices, neighbors = _int32(tri.simplices), _int32(tri.neighbors)
    simplex, bary, _ = _walk(points, simplices, neighbors, query, order, max_steps)
    lost = np.flatnonzero(simplex == -2)
    if len(lost) and not _settle_lost(tri, query, order[simplex[order] == -2], simplex, bary, at_vertex):
        found = tri.find_simplex(query[lost])
        simplex[lost] = found
        ok = found >= 0
        bary[lost[ok]] = _barycentric(tri, found[ok], query[lost[ok]])
    return simplex, bary


# a lost query this far inside its triangle or outside a hull edge (in barycentric coordinates)
# has one answer, whichever exact-enough method finds it (Sylva, not in the paper)
_CLEAR = 1e-9


def _settle_lost(tri: Delaunay, query: np.ndarray, lost: np.ndarray, simplex: np.ndarray,
                 bary: np.ndarray, at_vertex: Optional[np.ndarray]) -> bool:
    """Answer the lost queries (indices, in walk order) as ``Delaunay.find_simplex`` would, in place;
    False (nothing changed) when one of them is ambiguous.

    Sylva, not in the paper.  The lost queries walk again, without a step limit, each
    from the previous one's triangle.  A query clearly inside its triangle (every
    barycentric coordinate >= ``_CLEAR``) lies in no other; one clearly outside a hull
    edge, or outside the points' bounding box, in none: ``find_simplex`` finds the same.
    With ``at_vertex``, a query exactly on a vertex flagged there may keep any triangle
    around it: each gives it the coordinates (1, 0, 0) up to order and sign of zero, so
    a finite interpolated value that is not zero at that vertex comes out the same.
    Anything else (on or near an edge) is ambiguous: the caller asks ``find_simplex``
    about all lost queries in one call, as it would without this step.
    """
    q = query[lost]
    points = np.ascontiguousarray(tri.points)
    simplices = _int32(tri.simplices)
    s, _, low = _walk(points, simplices, _int32(tri.neighbors), q, np.arange(len(q)),
                      len(simplices) + 1)
    found = s >= 0
    clear = np.where(found, low >= _CLEAR, (s == -1) & (low <= -_CLEAR))
    eps = 100 * np.finfo(np.float64).eps      # find_simplex's own bounding-box test
    clear |= (s == -1) & np.any((q < tri.min_bound - eps) | (q > tri.max_bound + eps), axis=1)
    if at_vertex is not None:
        corners = simplices[np.where(found, s, 0)]                          # (n, 3)
        on = np.all(points[corners] == q[:, None, :], axis=2) & at_vertex[corners]
        clear |= found & on.any(axis=1)
    if not clear.all():
        return False
    simplex[lost] = s
    bary[lost] = 0.0
    bary[lost[found]] = _barycentric(tri, s[found], q[found])
    return True


@njit
def _walk(points, simplices, neighbors, query, order, max_steps):
    """:func:`_locate`'s walks, queries visited in ``order``; triangle of each query
    (-1 outside the hull, -2 lost), its barycentric coordinates, and the lowest
    coordinate where its walk stopped (>= -1e-12 in the triangle found; below when
    it left the hull)."""
    n = len(query)
    simplex = np.full(n, -1, dtype=np.int64)
    bary = np.zeros((n, 3))
    margin = np.zeros(n)
    eps = -1e-12
    start = 0
    for q in order:
        qx, qy = query[q, 0], query[q, 1]
        cur = start
        for _ in range(max_steps):
            a, b, c = simplices[cur, 0], simplices[cur, 1], simplices[cur, 2]
            v0x, v0y = points[b, 0] - points[a, 0], points[b, 1] - points[a, 1]
            v1x, v1y = points[c, 0] - points[a, 0], points[c, 1] - points[a, 1]
            v2x, v2y = qx - points[a, 0], qy - points[a, 1]
            det = v0x * v1y - v0y * v1x
            l1 = (v2x * v1y - v2y * v1x) / det
            l2 = (v0x * v2y - v0y * v2x) / det
            l0 = 1.0 - l1 - l2
            if not (np.isfinite(l0) and np.isfinite(l1) and np.isfinite(l2)):
                l0 = l1 = l2 = -np.inf
            worst, low = 0, l0
            if l1 < low:
                worst, low = 1, l1
            if l2 < low:
                worst, low = 2, l2
            margin[q] = low
            if low >= eps:
                simplex[q] = cur
                bary[q, 0], bary[q, 1], bary[q, 2] = l0, l1, l2
                start = cur
                break
            nxt = neighbors[cur, worst]
            if nxt < 0:          # crossed the hull: outside it
                break
            cur = nxt
        else:
            simplex[q] = -2
    return simplex, bary, margin


def _tin_interpolate(xy: np.ndarray, values: np.ndarray, query: np.ndarray,
                     max_edge: Optional[float] = None, max_radius: Optional[float] = None) -> np.ndarray:
    """Linear interpolation in the Delaunay triangulation of ``xy``; NaN outside the hull
    and, when ``max_edge`` / ``max_radius`` is given, inside triangles with an edge longer
    than it / with a circumradius larger than it."""
    out = np.full(len(query), np.nan)
    if len(xy) < 3 or len(query) == 0:
        return out
    try:
        first = _spatial_order(xy)
        tri = Delaunay(xy[first])
        values = values[first]
    except QhullError:  # all points collinear or coincident
        return out
    # without max_edge only the values matter: on a vertex, any triangle around it gives its value
    at_vertex = (values != 0) if max_edge is None and np.isfinite(values).all() else None
    simplex, bary = _locate(tri, query, at_vertex=at_vertex)
    inside = simplex >= 0
    if max_edge is not None or max_radius is not None:
        pts = tri.points[tri.simplices]                       # (m, 3, 2)
        sides = np.linalg.norm(pts - np.roll(pts, 1, axis=1), axis=2)
        ok = np.ones(len(pts), dtype=bool)
        if max_edge is not None:
            ok &= sides.max(axis=1) <= max_edge
        if max_radius is not None:                            # R = abc / (4 area)
            u, v = pts[:, 1] - pts[:, 0], pts[:, 2] - pts[:, 0]
            area4 = 2.0 * np.abs(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0])
            ok &= sides.prod(axis=1) <= max_radius * area4
        inside &= np.where(inside, ok[np.maximum(simplex, 0)], False)
    return _tin_values(np.ascontiguousarray(values, dtype=np.float64), _int32(tri.simplices),
                       np.where(inside, simplex, -1), bary)


@njit
def _tin_values(values, simplices, simplex, bary):
    """Interpolated value in each query's triangle (NaN where ``simplex`` < 0), summed as
    numpy's ``(values[corners] * bary).sum(axis=1)`` does: left to right."""
    out = np.full(len(simplex), np.nan)
    for q in range(len(simplex)):
        s = simplex[q]
        if s >= 0:
            out[q] = (values[simplices[s, 0]] * bary[q, 0] + values[simplices[s, 1]] * bary[q, 1]) \
                + values[simplices[s, 2]] * bary[q, 2]
    return out


def _lowest_per_cell(g: np.ndarray, cell_m: float) -> np.ndarray:
    """Indices of the lowest point (first of equals) of each ``cell_m`` square cell of local
    points ``g`` (0: of each distinct (x, y) position), cells in ascending (column, row) order."""
    if cell_m > 0:
        pick = _lowest_per_cell_kernel(np.ascontiguousarray(g, dtype=np.float64), float(cell_m),
                                       4 * len(g) + 1024)
        if len(pick):
            return pick
        ij = np.floor(g[:, :2] / cell_m).astype(np.int64)   # a sparse extent: sort instead
        order = np.lexsort((g[:, 2], ij[:, 1], ij[:, 0]))
        pos = ij[order]
    else:
        order = np.lexsort((g[:, 2], g[:, 1], g[:, 0]))
        pos = g[order, :2]
    first = np.ones(len(g), dtype=bool)
    first[1:] = np.any(pos[1:] != pos[:-1], axis=1)
    return order[first]


@njit
def _lowest_per_cell_kernel(g, cell, max_cells):
    """:func:`_lowest_per_cell` with cells, on a dense grid of cells (Sylva, not in the paper):
    what ``np.lexsort((z, row, column))`` keeps (lowest z, NaN last, first of equals).
    Empty when the grid would have more than ``max_cells`` cells."""
    n = len(g)
    ix, iy, x0, y0, nx, ny = grid_cells(g, cell, max_cells)
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
        elif g[i, 2] < g[b, 2] or (g[b, 2] != g[b, 2] and g[i, 2] == g[i, 2]):
            best[c] = i
    out = np.empty(kept, dtype=np.int64)
    j = 0
    for c in range(nx * ny):
        if best[c] >= 0:
            out[j] = best[c]
            j += 1
    return out


def _idw(tree: cKDTree, values: np.ndarray, query: np.ndarray, k: int, power: float) -> np.ndarray:
    """Inverse-distance weighting of the ``k`` nearest samples (exact at a sample)."""
    k = int(min(k, tree.n))
    dist, idx = tree.query(query, k=k, workers=-1)
    if k == 1:
        return values[idx]
    exact = dist[:, 0] <= 1e-12
    with np.errstate(divide="ignore"):
        w = 1.0 / np.maximum(dist, 1e-12) ** power
    out = (w * values[idx]).sum(axis=1) / w.sum(axis=1)
    out[exact] = values[idx[exact, 0]]
    return out


def ground_elevation(cloud: PointCloud, query_local: np.ndarray, method: str = "tin",
                     k: int = 10, power: float = 2.0, ground: Optional[np.ndarray] = None,
                     cell_m: float = 0.0, tin_radius_m: Optional[float] = None) -> np.ndarray:
    """Ground elevation (local metres) under local (x, y) positions, from the cloud's ground points.

    The ground points are first reduced to the lowest one per ``cell_m`` square
    cell (0: keep every distinct position), the resolution of a fine DTM;
    ``tin_radius_m``: see :func:`height_above_ground`."""
    return _ground_elevation(cloud, cloud.local_xyz(), query_local, method, k, power, ground, cell_m,
                             tin_radius_m)


def _ground_elevation(cloud: PointCloud, loc: np.ndarray, query_local: np.ndarray, method: str,
                      k: int, power: float, ground: Optional[np.ndarray], cell_m: float,
                      tin_radius_m: Optional[float] = None) -> np.ndarray:
    """:func:`ground_elevation` given ``loc = cloud.local_xyz()``."""
    mask = ground_mask(cloud) if ground is None else np.asarray(ground, dtype=bool)
    if not mask.any():
        raise EmptyInputError(
            f"{cloud.name}: no ground points (class 2); classify the ground first ('Normalize height', "
            "sylva:normalizeheight with CLASSIFY_GROUND=always) or use a tile that has a ground class")
    g = loc[mask]
    # One elevation per distinct ground position, or per ``cell_m`` cell: the lowest (duplicates
    # break the TIN; at 0.5 m the triangulation of a 20 pts/m2 tile costs a quarter).
    g = g[_lowest_per_cell(g, cell_m)]
    query = np.asarray(query_local, dtype=np.float64)[:, :2]
    if method == "tin":
        out = _tin_interpolate(g[:, :2], g[:, 2], query, max_radius=tin_radius_m)
        outside = ~np.isfinite(out)
        if outside.any():
            out[outside] = _idw(cKDTree(g[:, :2]), g[:, 2], query[outside], k, power)
        return out
    if method == "knnidw":
        return _idw(cKDTree(g[:, :2]), g[:, 2], query, k, power)
    raise InputError(f"unknown height-above-ground method {method!r}; use 'tin' or 'knnidw'")


def height_above_ground(cloud: PointCloud, method: str = "tin", k: int = 10, power: float = 2.0,
                        ground: Optional[np.ndarray] = None, cell_m: float = 0.0,
                        tin_radius_m: Optional[float] = None) -> np.ndarray:
    """Height of every point above the ground surface, float64 metres.

    ``method="tin"``: linear interpolation in the Delaunay triangulation of the
    ground points (exact on planar ground), with k-nearest IDW outside the hull;
    ``"knnidw"``: inverse-distance weighting (``power``) of the ``k`` nearest
    ground points, as lidR's ``knnidw()``.  ``ground`` overrides the class-2 mask.
    With ``cell_m`` > 0 the ground points are first reduced to the lowest per
    ``cell_m`` square cell (0.5 m makes the TIN of a 20 pts/m2 tile about four
    times cheaper; ground points then get heights of a few cm instead of 0).
    ``tin_radius_m``: triangles whose circumradius exceeds it count as outside
    the TIN (IDW there).  Whether a Delaunay triangle exists depends only on
    the points in its circumcircle, so with it a point's height depends only on
    ground points within ``2 x tin_radius_m``: what makes heights the same in any
    tiling with a buffer of that width (the long thin triangles along a tile's
    outline, which join points far apart, are the ones left out; Sylva, not in
    a paper).  None: every triangle.
    Raises :class:`EmptyInputError` naming the file when there is no ground point.
    """
    loc = cloud.local_xyz()
    return loc[:, 2] - _ground_elevation(cloud, loc, loc, method, k, power, ground, cell_m, tin_radius_m)


def is_normalized(cloud: PointCloud, tolerance_m: float = 0.5) -> bool:
    """True when z already is height above ground (like lidR's MixedConifer.laz).

    With ground points (class 2): at least 90 % of them lie within
    ``tolerance_m`` of z = 0.  Without: the lowest point of at least 80 % of the
    occupied 10 m cells lies within ``tolerance_m`` of 0 and no point is below
    ``-3 * tolerance_m`` beyond 1 % of them (robust against a few low outliers).
    """
    if len(cloud) == 0:
        return False
    z = cloud.xyz[:, 2] * cloud.units.vertical_m
    mask = ground_mask(cloud)
    if mask.sum() >= 10:
        return bool(np.mean(np.abs(z[mask]) <= tolerance_m) >= 0.9)
    xy = cloud.local_xyz()[:, :2]
    rows, cols, shape = _grid_index(xy, 10.0)
    lowest = np.full(shape, np.inf)
    np.minimum.at(lowest, (rows, cols), z)
    lowest = lowest[np.isfinite(lowest)]
    near = np.mean(np.abs(lowest) <= tolerance_m) >= 0.8
    return bool(near and np.mean(z < -3 * tolerance_m) <= 0.01)


def normalize(cloud: PointCloud, method: str = "tin", classify: Optional[GroundMethod] = None,
              k: int = 10, power: float = 2.0, cell_m: float = 0.0,
              tin_radius_m: Optional[float] = None, trust_normalized: bool = True) -> PointCloud:
    """A copy of ``cloud`` with attribute ``height`` (float64, metres above ground).

    An already normalised cloud (:func:`is_normalized`) gets ``height = z *
    vertical unit`` unless ``trust_normalized`` is False (a terrestrial plot whose
    ground happens to lie within half a metre of z = 0 still needs its ground).  Otherwise the ground is the class-2 points; when there
    are none and ``classify`` is a ground method (e.g. ``SMRF()``), the ground
    is classified first and those points get class 2 in the returned copy.
    ``cell_m``, ``tin_radius_m``: see :func:`height_above_ground`.
    """
    if len(cloud) == 0:
        raise EmptyInputError(f"{cloud.name}: no points to normalise")
    if trust_normalized and is_normalized(cloud):
        return cloud.with_attrs(height=cloud.xyz[:, 2] * cloud.units.vertical_m)
    mask = ground_mask(cloud)
    extra = {}
    if not mask.any() and classify is not None:
        mask = classify_ground(cloud, classify)
        cls = cloud.attr("classification")
        cls = np.ones(len(cloud), dtype=np.uint8) if cls is None else np.array(cls, copy=True)
        cls[mask] = GROUND_CLASS
        extra["classification"] = cls
    height = height_above_ground(cloud, method=method, k=k, power=power, ground=mask, cell_m=cell_m,
                                 tin_radius_m=tin_radius_m)
    return cloud.with_attrs(height=height, **extra)




def height_as_z(cloud: PointCloud, height: np.ndarray, elevation: np.ndarray):
    """(``cloud`` whose z is ``height`` (metres above ground, in the CRS's vertical units) and without a
    ``height`` attribute, the extra dimensions {"elevation": ``elevation``}): what lidR's
    ``normalize_height`` writes, the source elevation kept beside it."""
    from dataclasses import replace

    xyz = cloud.xyz.copy()
    xyz[:, 2] = np.asarray(height, dtype=np.float64) / cloud.units.vertical_m
    attrs = {k: v for k, v in cloud.attrs.items() if k != "height"}
    return replace(cloud, xyz=xyz, attrs=attrs), {"elevation": np.asarray(elevation, dtype=np.float64)}


def heights_above_ground(cloud: PointCloud) -> np.ndarray:
    """The cloud's ``height`` attribute, or its heights from :func:`normalize` when it has none."""
    h = cloud.attr("height")
    if h is None:
        h = normalize(cloud).attrs["height"]
    return np.asarray(h, dtype=np.float64)


# --------------------------------------------------------------------------- DTM / CHM

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
        values = _tin_interpolate(pts, vals, centres[box], max_edge=None if i == 0 else max_edge_m)
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


__all__ = [
    "GROUND_CLASS", "low_outliers", "SMRF", "CSF", "DEFAULT_GROUND", "ground_mask", "classify_ground",
    "ground_elevation", "height_above_ground", "is_normalized", "normalize",
    "digital_terrain_model", "canopy_height_model", "NOISE_CLASSES",
]
