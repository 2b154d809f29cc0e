"""One segmentation chain for every front end: noise, ground, heights, tops, trees.

:func:`segment_tile` is what ``sylva:segmenttrees`` (``algorithms/segment.py``)
and the pipeline (:func:`sylva.core.pipeline.process_tile`) both run on a tile
(with its buffer, for the pipeline), so the same tile gives the same trees
through either.  Steps:

1. noise (classes 7/18, withheld, isolated points) is left out
   (:func:`sylva.core.noise.noise_mask`);
2. heights above ground (:func:`sylva.core.terrain.normalize`): the tile's
   class-2 points, or SMRF (Pingel et al. 2013) when it has none, thinned to
   the lowest point per ``ground_cell_m`` cell, TIN triangles no wider than
   ``tin_radius_m`` (the pipeline passes half its buffer);
3. an automatic method (:class:`sylva.core.segment.stems.AutoSegmentation`) chooses on the
   normalised cloud (stems for terrestrial plot scans); the method segments the cloud and finds its own tree tops (its top search
   is a field of the method, e.g. :class:`NormalizedCut`'s window, window
   points, apex rule and minimum height);
4. the tops reported are each tree's apex, its highest point in elevation
   (:func:`sylva.core.tops.apex_points`; a point of the cloud, so the pipeline
   can tell which tile's file holds it).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..cloud import ANCHOR_GRID_M, AnchoredCloud, PointCloud
from ..progress import CancelCheck, Progress, report, scaled

__all__ = ["SegmentedTile", "prepare_tile", "segment_tile", "tree_tops_of"]


@dataclass(eq=False)
class SegmentedTile:
    """``cloud``: the tile without noise, with ``height``; ``keep``: mask of those points in the
    input; ``labels``: int32 tree ID per point of ``cloud`` (0 = none); ``tops``:
    :class:`sylva.core.tops.TreeTops` at each tree's highest point, ``tree_id`` = its label; ``method``:
    the segmentation method that ran (an automatic method's choice)."""

    cloud: PointCloud
    keep: np.ndarray
    labels: np.ndarray
    tops: object
    method: object = None


def tree_tops_of(cloud: PointCloud, labels: np.ndarray):
    """:class:`TreeTops` at the apex of every label > 0 (:func:`~sylva.core.tops.apex_points`: its
    highest point in elevation; ties: lowest x, then y, then the first point, not the point order,
    which depends on the tiling), with that point's height above ground."""
    from ..tops import TreeTops, apex_points

    height = np.asarray(cloud.attrs["height"], dtype=np.float64)
    top = apex_points(cloud.xyz, labels)
    return TreeTops(cloud.xyz[top], height[top], labels[top].astype(np.int64), cloud.crs)


def prepare_tile(cloud: PointCloud, ground_cell_m: float = 0.5, tin_radius_m: Optional[float] = 7.5,
                 trust_normalized: bool = True):
    """Steps 1-2 of the chain: (the tile anchored on the global grid, without noise, with ``height``;
    the mask of those points in ``cloud``).  What every method of :func:`segment_tile` segments (the
    benchmarks score the methods on it, so their figures are what segmenttrees gives)."""
    from dataclasses import fields

    from ..noise import noise_mask
    from ..terrain import SMRF, normalize

    if not isinstance(cloud, AnchoredCloud) and len(cloud):
        grid = ANCHOR_GRID_M / cloud.units.horizontal_m
        lo = cloud.xyz[:, :2].min(axis=0)
        anchor = np.array([np.floor(lo[0] / grid) * grid, np.floor(lo[1] / grid) * grid, 0.0])
        cloud = AnchoredCloud(**{f.name: getattr(cloud, f.name) for f in fields(cloud)
                                 if f.name != "anchor"}, anchor=anchor)
    keep = ~noise_mask(cloud)
    work = normalize(cloud.subset(keep), classify=SMRF(), cell_m=ground_cell_m, tin_radius_m=tin_radius_m,
                     trust_normalized=trust_normalized)
    return work, keep


def segment_tile(cloud: PointCloud, method=None, ground_cell_m: float = 0.5,
                 tin_radius_m: Optional[float] = 7.5, progress: Progress = None,
                 cancelled: CancelCheck = None) -> SegmentedTile:
    """Segment a tile (see the module docstring); ``method`` defaults to :class:`NormalizedCut`.

    The local frame is anchored on the global grid of
    :data:`sylva.core.cloud.ANCHOR_GRID_M` (voxels and cells fall on the
    same places whatever the tile's extent); ``tin_radius_m`` 7.5 is half the
    pipeline's default buffer."""
    from ..terrain import is_normalized
    from . import NormalizedCut, segment_trees

    method = NormalizedCut() if method is None else method
    report(progress, 0.0, "height above ground")
    work, keep = prepare_tile(cloud, ground_cell_m, tin_radius_m)
    if hasattr(method, "resolve"):            # automatic choice (e.g. stems for a plot scan)
        method = method.resolve(work)
    if (getattr(method, "exact_ground", False) and cloud.attr("height") is None
            and is_normalized(cloud.subset(keep))):
        # taken as normalised (z near 0): a method that measures at breast height needs the ground itself
        # (Sylva: a synthetic plot sloping 5 % around z = 0 had heights off by up to 0.56 m)
        work, keep = prepare_tile(cloud, ground_cell_m, tin_radius_m, trust_normalized=False)
    labels = segment_trees(work, method, progress=scaled(progress, 0.1, 0.95), cancelled=cancelled)
    return SegmentedTile(work, keep, labels, tree_tops_of(work, labels), method)
