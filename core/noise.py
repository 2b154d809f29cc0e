"""Noise points: the classes that mark them, and an isolated-voxel filter for those that are not marked.

Airborne tiles carry birds, multipath echoes and low outliers.  A single
high outlier becomes a spike in a canopy height model, a false tree top and
a tree of one point, so every algorithm leaves noise out:

* points of ASPRS class 7 (low noise) and 18 (high noise), and withheld points;
* points in an *isolated voxel neighbourhood*, as lidR's ``ivf`` does: the
  tile is cut into cubes of ``voxel_m``; a point is noise when its cube and
  the 26 around it hold fewer than ``min_points`` points in all
  (:func:`noise_mask`, applied to whole tiles by every algorithm);
* for canopy surfaces and tree tops, also any canopy point with no other
  within ``isolation_m`` in 3-D (:func:`isolated_points`): a single stray
  return above the canopy is a false top even inside a populated voxel block.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from .cloud import PointCloud
from .jit import njit
from .kernels.buckets import bucket_by_cell

NOISE_CLASSES = (7, 18)

#: A canopy point with no other within this many metres (3-D) is noise for canopy surfaces and tops.
ISOLATION_M = 2.0


@dataclass(frozen=True)
class IsolatedVoxels:
    """lidR's ivf defaults: 5 m cubes, fewer than 6 points in the 3 x 3 x 3 block is noise."""

    voxel_m: float = 5.0
    min_points: int = 6


def _keys(ijk: np.ndarray) -> np.ndarray:
    """One int64 per voxel index triple (21 bits each, offset to stay positive)."""
    ijk = ijk + (1 << 20)
    return (ijk[:, 0] << 42) | (ijk[:, 1] << 21) | ijk[:, 2]


def isolated(cloud: PointCloud, method: IsolatedVoxels = IsolatedVoxels()) -> np.ndarray:
    """Boolean mask of points in isolated voxel neighbourhoods (counts on a dense voxel grid,
    :func:`_isolated_voxels`; 27 sorted look-ups when that grid would be too large)."""
    if len(cloud) == 0:
        return np.zeros(0, dtype=bool)
    loc = cloud.local_xyz()
    out = _isolated_voxels(np.ascontiguousarray(loc), float(method.voxel_m), int(method.min_points),
                           4 * len(loc) + 65536)
    if len(out) == len(loc):
        return out
    ijk = np.floor(loc / method.voxel_m).astype(np.int64)
    ijk -= ijk.min(axis=0)
    keys = _keys(ijk)
    occupied, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    cells = ijk[np.unique(inverse, return_index=True)[1]]  # index triple of each occupied voxel
    total = np.zeros(len(occupied), dtype=np.int64)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                probe = _keys(cells + (dx, dy, dz))
                pos = np.clip(np.searchsorted(occupied, probe), 0, len(occupied) - 1)
                hit = occupied[pos] == probe
                total[hit] += counts[pos[hit]]
    return (total < method.min_points)[inverse]


@njit
def _isolated_voxels(loc, voxel, min_points, max_cells):
    """:func:`isolated` on a dense grid of ``voxel`` cubes: True where the 3 x 3 x 3 block
    around a point's cube holds fewer than ``min_points`` points.  Empty when the grid
    would have more than ``max_cells`` cubes (or a coordinate is not finite)."""
    n = len(loc)
    ijk = np.empty((n, 3), dtype=np.int64)
    lo = np.zeros(3, dtype=np.int64)
    hi = np.zeros(3, dtype=np.int64)
    for i in range(n):
        for a in range(3):
            f = np.floor(loc[i, a] / voxel)
            if not abs(f) < max_cells:
                return np.empty(0, dtype=np.bool_)
            v = int(f)
            ijk[i, a] = v
            if i == 0 or v < lo[a]:
                lo[a] = v
            if i == 0 or v > hi[a]:
                hi[a] = v
    nx, ny, nz = hi[0] - lo[0] + 1, hi[1] - lo[1] + 1, hi[2] - lo[2] + 1
    if nx * ny * nz > max_cells:
        return np.empty(0, dtype=np.bool_)
    count = np.zeros((nx + 2, ny + 2, nz + 2), dtype=np.int32)   # one empty cube all round
    for i in range(n):
        count[ijk[i, 0] - lo[0] + 1, ijk[i, 1] - lo[1] + 1, ijk[i, 2] - lo[2] + 1] += 1
    total = np.full((nx, ny, nz), -1, dtype=np.int32)
    out = np.empty(n, dtype=np.bool_)
    for i in range(n):
        x, y, z = ijk[i, 0] - lo[0], ijk[i, 1] - lo[1], ijk[i, 2] - lo[2]
        if total[x, y, z] < 0:
            t = 0
            for gx in range(x, x + 3):
                for gy in range(y, y + 3):
                    for gz in range(z, z + 3):
                        t += count[gx, gy, gz]
            total[x, y, z] = t
        out[i] = total[x, y, z] < min_points
    return out


def noise_mask(cloud: PointCloud, method: IsolatedVoxels = IsolatedVoxels()) -> np.ndarray:
    """Points to leave out: noise classes, withheld flags and isolated points."""
    mask = isolated(cloud, method)
    cls = cloud.attr("classification")
    if cls is not None:
        mask |= np.isin(np.asarray(cls), NOISE_CLASSES)
    withheld = cloud.attr("withheld")
    if withheld is not None:
        mask |= np.asarray(withheld).astype(bool)
    return mask


def column_bounds(a: np.ndarray):
    """``(a.min(axis=0), a.max(axis=0))`` of the first two columns, column by column
    (numpy reduces a narrow array along axis 0 slowly)."""
    return (np.array([a[:, 0].min(), a[:, 1].min()]), np.array([a[:, 0].max(), a[:, 1].max()]))


def _alone(xyz: np.ndarray, radius: float) -> np.ndarray:
    """Mask of the points with no other point nearer than ``radius`` (3-D; a
    duplicate counts as a neighbour).  Points are bucketed in columns of
    ``radius`` (fewer when the extent is large and the points few)."""
    lo, hi = column_bounds(xyz)
    span = np.maximum(hi - lo, 1e-6)
    cell = max(radius, float(np.sqrt(span[0] * span[1] / (2.0 * len(xyz) + 1024))))
    nx, ny = (np.floor(span / cell).astype(np.int64) + 1).tolist()
    order, starts, key = grid_buckets(xyz, float(lo[0]), float(lo[1]), cell, nx, ny)
    alone = np.empty(len(xyz), dtype=bool)
    alone[order] = _alone_sorted(np.ascontiguousarray(xyz[order]), key, starts, ny, radius)
    return alone


def grid_buckets(xy: np.ndarray, x0: float, y0: float, cell: float, nx: int, ny: int):
    """Points bucketed by square cell, CSR: (``order``, ``starts``, ``key[order]``) where cell
    ``key = floor((x - x0) / cell) * ny + floor((y - y0) / cell)`` (``nx`` by ``ny``
    cells), ``order`` sorts by key (stable) and cell ``g`` holds ``order[starts[g]:starts[g + 1]]``.
    Exactly ``np.argsort(key, kind="stable")`` and its ``searchsorted`` starts, by a
    counting sort (:func:`_grid_buckets`; Sylva, not in a paper)."""
    order, starts, key = _grid_buckets(np.ascontiguousarray(xy, dtype=np.float64),
                                       float(x0), float(y0), float(cell), int(nx), int(ny))
    if len(order) == len(xy):
        return order, starts, key
    key = (np.floor((xy[:, 0] - x0) / cell).astype(np.int64) * ny    # a point off the grid
           + np.floor((xy[:, 1] - y0) / cell).astype(np.int64))
    order = np.argsort(key, kind="stable")
    return order, np.searchsorted(key[order], np.arange(nx * ny + 1)), key[order]


@njit
def _grid_buckets(xy, x0, y0, cell, nx, ny):
    """:func:`grid_buckets`'s counting sort; empty arrays when a point falls off the grid."""
    n = len(xy)
    key = np.empty(n, dtype=np.int64)
    for i in range(n):
        fx = np.floor((xy[i, 0] - x0) / cell)
        fy = np.floor((xy[i, 1] - y0) / cell)
        if not (fx >= 0 and fx < nx and fy >= 0 and fy < ny):
            return np.empty(0, dtype=np.int64), np.zeros(nx * ny + 1, dtype=np.int64), key
        key[i] = int(fx) * ny + int(fy)
    starts, order = bucket_by_cell(key, nx * ny)
    return order, starts, key[order]


@njit
def _alone_sorted(pts, key, starts, ny, radius):
    """:func:`_alone` on points sorted by column ``key`` (CSR ``starts``).  A point's own
    column is searched first, outwards from the point (file order keeps neighbours close)."""
    r2 = radius * radius
    out = np.empty(len(pts), dtype=np.bool_)
    nx = (len(starts) - 1) // ny
    for i in range(len(pts)):
        ix = key[i] // ny
        iy = key[i] - ix * ny
        alone = True
        lo, hi = starts[key[i]], starts[key[i] + 1]
        for step in range(1, max(i - lo, hi - 1 - i) + 1):
            for j in (i - step, i + step):
                if lo <= j < hi:
                    dx = pts[j, 0] - pts[i, 0]
                    dy = pts[j, 1] - pts[i, 1]
                    dz = pts[j, 2] - pts[i, 2]
                    if dx * dx + dy * dy + dz * dz < r2:
                        alone = False
            if not alone:
                break
        for gx in range(max(ix - 1, 0), min(ix + 1, nx - 1) + 1):
            if not alone:
                break
            for gy in range(max(iy - 1, 0), min(iy + 1, ny - 1) + 1):
                g = gx * ny + gy
                if not alone or g == key[i]:
                    continue
                for j in range(starts[g], starts[g + 1]):
                    dx = pts[j, 0] - pts[i, 0]
                    dy = pts[j, 1] - pts[i, 1]
                    dz = pts[j, 2] - pts[i, 2]
                    if dx * dx + dy * dy + dz * dz < r2:
                        alone = False
                        break
        out[i] = alone
    return out


def isolated_points(cloud: PointCloud, isolation_m: Optional[float] = ISOLATION_M,
                    among: Optional[np.ndarray] = None, loc: Optional[np.ndarray] = None) -> np.ndarray:
    """Classified noise (7, 18) and, when ``isolation_m`` is given, points with no other point
    (of those selected by ``among``, default all) within ``isolation_m`` metres in 3-D.
    ``loc``: ``cloud.local_xyz()`` when the caller has it already."""
    noise = np.zeros(len(cloud), dtype=bool)
    cls = cloud.attr("classification")
    if cls is not None:
        noise |= np.isin(np.asarray(cls), NOISE_CLASSES)
    if isolation_m is not None and isolation_m > 0:
        idx = np.nonzero(~noise if among is None else (~noise & among))[0]
        if len(idx) > 1:
            loc = cloud.local_xyz() if loc is None else loc
            noise[idx[_alone(loc[idx], float(isolation_m))]] = True
        elif len(idx) == 1:
            noise[idx] = True
    return noise
