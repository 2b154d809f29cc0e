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

NOISE_CLASSES = (7, 18)


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
    """Boolean mask of points in isolated voxel neighbourhoods (vectorised: 27 sorted look-ups)."""
    if len(cloud) == 0:
        return np.zeros(0, dtype=bool)
    ijk = np.floor(cloud.local_xyz() / method.voxel_m).astype(np.int64)
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


def _alone(xyz: np.ndarray, radius: float) -> np.ndarray:
    """Mask of the points with no other point nearer than ``radius`` (3-D; a
    duplicate counts as a neighbour).  Points are bucketed in columns of
    ``radius`` (fewer when the extent is large and the points few)."""
    lo = xyz[:, :2].min(axis=0)
    span = np.maximum(xyz[:, :2].max(axis=0) - lo, 1e-6)
    cell = max(radius, float(np.sqrt(span[0] * span[1] / (2.0 * len(xyz) + 1024))))
    nx, ny = (np.floor(span / cell).astype(np.int64) + 1).tolist()
    ij = np.floor((xyz[:, :2] - lo) / cell).astype(np.int64)
    key = ij[:, 0] * ny + ij[:, 1]
    order = np.argsort(key, kind="stable")
    starts = np.searchsorted(key[order], np.arange(nx * ny + 1))
    alone = np.empty(len(xyz), dtype=bool)
    alone[order] = _alone_sorted(np.ascontiguousarray(xyz[order]), key[order], starts, ny, radius)
    return alone


@njit
def _alone_sorted(pts, key, starts, ny, radius):
    """:func:`_alone` on points sorted by column ``key`` (CSR ``starts``)."""
    r2 = radius * radius
    out = np.empty(len(pts), dtype=np.bool_)
    nx = (len(starts) - 1) // ny
    for i in range(len(pts)):
        ix = key[i] // ny
        iy = key[i] - ix * ny
        alone = True
        for gx in range(max(ix - 1, 0), min(ix + 1, nx - 1) + 1):
            if not alone:
                break
            for gy in range(max(iy - 1, 0), min(iy + 1, ny - 1) + 1):
                if not alone:
                    break
                g = gx * ny + gy
                for j in range(starts[g], starts[g + 1]):
                    if j != i:
                        dx = pts[j, 0] - pts[i, 0]
                        dy = pts[j, 1] - pts[i, 1]
                        dz = pts[j, 2] - pts[i, 2]
                        if dx * dx + dy * dy + dz * dz < r2:
                            alone = False
                            break
        out[i] = alone
    return out


def isolated_points(cloud: PointCloud, isolation_m: Optional[float] = 2.0,
                    among: Optional[np.ndarray] = None) -> np.ndarray:
    """Classified noise (7, 18) and, when ``isolation_m`` is given, points with no other point
    (of those selected by ``among``, default all) within ``isolation_m`` metres in 3-D."""
    noise = np.zeros(len(cloud), dtype=bool)
    cls = cloud.attr("classification")
    if cls is not None:
        noise |= np.isin(np.asarray(cls), NOISE_CLASSES)
    if isolation_m is not None and isolation_m > 0:
        idx = np.nonzero(~noise if among is None else (~noise & among))[0]
        if len(idx) > 1:
            noise[idx[_alone(cloud.local_xyz()[idx], float(isolation_m))]] = True
        elif len(idx) == 1:
            noise[idx] = True
    return noise
