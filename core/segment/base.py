"""What every segmentation method shares: input checks, tree tops, ground, and the columns under crowns.

The rules these helpers implement are listed in :mod:`sylva.core.segment`; the methods (ncut/,
chm.py) import them from here, and the package imports the methods: every import runs downward.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..cloud import PointCloud
from ..errors import InputError
from ..progress import CancelCheck, Progress

#: Points lower than this (metres above ground) are ground, never tree points.
GROUND_TOLERANCE_M = 0.5


def validate_cloud(cloud: PointCloud) -> PointCloud:
    """Reject NaN/infinite coordinates (naming the file); normalise when needed."""
    if not isinstance(cloud, PointCloud):
        raise InputError(f"segment_trees expects a PointCloud, got {type(cloud).__name__}")
    finite = np.isfinite(cloud.xyz).all(axis=1)
    if not finite.all():
        bad = np.flatnonzero(~finite)
        raise InputError(
            f"{cloud.name}: {len(bad)} point(s) have NaN or infinite coordinates "
            f"(first at point index {bad[0]}); remove them before segmenting trees")
    if len(cloud) == 0:
        return cloud
    if cloud.attr("height") is None:
        from ..terrain import normalize

        cloud = normalize(cloud)
    height = np.asarray(cloud.attr("height"), dtype=np.float64)
    if not np.isfinite(height).all():
        bad = np.flatnonzero(~np.isfinite(height))
        raise InputError(
            f"{cloud.name}: {len(bad)} point(s) have no height above ground (NaN; first at "
            f"point index {bad[0]}); normalise the tile again")
    return cloud


@dataclass(frozen=True)
class LocalTops:
    """Tree tops in a cloud's local metric frame (see :meth:`PointCloud.local_xyz`).

    ``xy`` (k, 2) metres, ``height`` (k,) metres above ground, ``tree_id`` (k,) int64.
    """

    xy: np.ndarray
    height: np.ndarray
    tree_id: np.ndarray

    def __len__(self) -> int:
        return len(self.tree_id)


def resolve_tops(cloud: PointCloud, tops, min_height_m: float, window_m: float,
                 progress: Progress = None, cancelled: CancelCheck = None,
                 search=None) -> LocalTops:
    """The tops to segment from, in the local frame; found with find_tree_tops if None.

    When found, a ``window_m`` fixed circular window is used (lidR's
    ``lmf(ws = window_m)``).  ``search`` (indices of points, optional)
    restricts the search to those points, e.g. the highest point of each
    narrow column (every top is one; the window maximum is then taken over the
    column maxima only), which is several times faster on dense clouds.
    """
    if tops is None:
        from ..tops import FixedWindow, find_tree_tops

        subset = cloud if search is None or len(search) == 0 else cloud.subset(search)
        tops = find_tree_tops(subset, window=FixedWindow(diameter_m=window_m),
                              min_height_m=min_height_m, progress=progress,
                              cancelled=cancelled)
    xyz = np.asarray(tops.xyz, dtype=np.float64).reshape(-1, 3)
    tree_id = np.asarray(tops.tree_id, dtype=np.int64).reshape(-1)
    height = np.asarray(tops.height, dtype=np.float64).reshape(-1)
    if not (len(xyz) == len(tree_id) == len(height)):
        raise InputError("tree tops: xyz, height and tree_id have different lengths")
    ok = np.isfinite(xyz[:, :2]).all(axis=1) & np.isfinite(height) & (tree_id > 0)
    if len(np.unique(tree_id[ok])) != ok.sum():
        raise InputError("tree tops: tree_id values must be unique and positive")
    if tree_id.max(initial=0) > np.iinfo(np.int32).max:
        raise InputError("tree tops: tree_id values do not fit the int32 treeID dimension")
    xyz, tree_id, height = xyz[ok], tree_id[ok], height[ok]
    origin = cloud.origin
    scale = cloud.units.horizontal_m
    xy = (xyz[:, :2] - origin[:2]) * scale
    return LocalTops(xy=xy, height=height, tree_id=tree_id)


def ground_mask(cloud: PointCloud, height: np.ndarray) -> np.ndarray:
    """Ground points: class 2 when classified, and anything below GROUND_TOLERANCE_M."""
    ground = height < GROUND_TOLERANCE_M
    cls = cloud.attr("classification")
    if cls is not None:
        ground |= np.asarray(cls) == 2
    return ground


def label_columns_below(col_key_labelled: np.ndarray, z_labelled: np.ndarray,
                        label_labelled: np.ndarray, col_key_query: np.ndarray,
                        z_query: np.ndarray) -> np.ndarray:
    """Label of the lowest labelled cell in the same column *above* each query point.

    Used for stems and low branches: a point below ``min_height_m`` takes the
    label of the crown right above it (same horizontal cell), 0 when there is
    none.  Vectorised with a sort and ``searchsorted``.
    """
    out = np.zeros(len(col_key_query), dtype=np.int32)
    if len(col_key_labelled) == 0 or len(col_key_query) == 0:
        return out
    order = np.lexsort((z_labelled, col_key_labelled))
    keys = col_key_labelled[order]
    first = np.ones(len(keys), dtype=bool)
    first[1:] = keys[1:] != keys[:-1]
    ukeys = keys[first]
    ulab = label_labelled[order][first]
    uz = z_labelled[order][first]
    pos = np.searchsorted(ukeys, col_key_query)
    pos = np.minimum(pos, len(ukeys) - 1)
    hit = (ukeys[pos] == col_key_query) & (uz[pos] >= z_query)
    out[hit] = ulab[pos[hit]]
    return out


def column_keys(ix: np.ndarray, iy: np.ndarray) -> np.ndarray:
    """One int64 key per horizontal cell (ix, iy >= 0)."""
    return ix.astype(np.int64) * np.int64(1 << 31) + iy.astype(np.int64)
