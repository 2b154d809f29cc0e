"""Height above ground: the ground elevation under any position (TIN of the ground points, IDW
outside its hull, or k-nearest IDW as lidR's ``knnidw()``), :func:`height_above_ground`,
:func:`is_normalized`, :func:`normalize` (the ``height`` attribute), :func:`height_as_z` (lidR's
``normalize_height`` output) and :func:`heights_above_ground`.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
from scipy.spatial import cKDTree

from ..cloud import PointCloud
from ..errors import EmptyInputError, InputError
from .ground import GROUND_CLASS, GroundMethod, classify_ground, grid_index, ground_mask
from .interpolation import idw, lowest_per_cell, tin_interpolate


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
    g = g[lowest_per_cell(g, cell_m)]
    query = np.asarray(query_local, dtype=np.float64)[:, :2]
    if method == "tin":
        out = tin_interpolate(g[:, :2], g[:, 2], query, max_radius=tin_radius_m)
        outside = ~np.isfinite(out)
        if outside.any():
            out[outside] = idw(cKDTree(g[:, :2]), g[:, 2], query[outside], k, power)
        return out
    if method == "knnidw":
        return idw(cKDTree(g[:, :2]), g[:, 2], query, k, power)
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
    rows, cols, shape = grid_index(xy, 10.0)
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
