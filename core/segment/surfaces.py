"""Hard surfaces: segments that are roofs, decks or vehicles, not trees.

A laser pulse that hits a roof, a bridge deck or a truck ends there: one
return, on a plane.  A pulse that hits a crown goes on through the leaves and
branches: several returns, on a rough surface.  Both cues are the classic
tellers of buildings from trees in airborne LiDAR (Rottensteiner, Trinder,
Clode & Kubik 2005, "Using the Dempster-Shafer method for the fusion of LIDAR
data and multi-spectral images for building detection", Information Fusion
6(4), 283-300: the first/last pulse difference and the surface roughness).

A segment is a hard surface when fewer than :data:`MULTI_RETURN_SHARE` of its
points come from pulses of two or more returns *and* its upper surface (the
highest point of every :data:`SURFACE_CELL_M` column) lies on a plane within
:data:`PLANE_RMS_M` (RMS distance; a sloping deck or one face of a roof is a
plane too).  Either cue alone is not enough: a dense low crown can give few
multiple returns, and a small crown's cap can be nearly flat (8 of the 275
crowns NormalizedCut finds on MixedConifer.laz have an upper surface within
0.35 m of a plane).  Without a ``number_of_returns`` attribute (text files,
some exports) nothing is dropped.  Measured on ``autzen_trim.laz``
(unclassified park, footbridge and parking; 343 -> 305 segments): the pieces
of a footbridge ramp rising 8 -> 10 m over 55 m (37 "trees" before, 6 after:
those that hold points under the deck) and a few low single-return objects
have plane RMS 0.10-0.32 m and a multiple-return share of 0-0.10; the next
segment has 0.37 m (Sylva rule, not in Hu et al. 2017).

Every number is a segment's own: no statistic of the tile (tiling invariance).
"""
from __future__ import annotations

import numpy as np

from ..groups import group_covariances

#: Columns of this size give a segment's upper surface.
SURFACE_CELL_M = 1.0

#: A hard surface's upper points are within this RMS distance of a plane.
PLANE_RMS_M = 0.35

#: Fewer than this share of a hard surface's points come from pulses of two or more returns.
MULTI_RETURN_SHARE = 0.1

#: A plane needs at least this many surface columns to be told from a small crown's cap.
MIN_SURFACE_CELLS = 4


def hard_surfaces(cloud, labels: np.ndarray) -> np.ndarray:
    """The labels (sorted int array) of the segments of a height-normalised
    :class:`~sylva.core.cloud.PointCloud` that are hard surfaces, not trees.

    ``labels``: per point, 0 = none.  A segment with a point whose
    ``number_of_returns`` is 0 (unknown), or a cloud without the attribute, is
    never a hard surface."""
    none = np.zeros(0, dtype=labels.dtype)
    returns = cloud.attr("number_of_returns")
    if returns is None or len(labels) == 0 or labels.max() <= 0:
        return none
    # per label, by bincount over the label values (no sort of the tile's points unless the values are
    # sparse, e.g. tree IDs of given tops)
    n_returns = np.asarray(returns)
    lab = np.maximum(labels, 0)
    if lab.max() >= 2 * len(lab):
        lab = np.unique(lab, return_inverse=True)[1].reshape(lab.shape) + (lab.min() > 0)
    size = int(lab.max()) + 1
    points = np.bincount(lab, minlength=size)
    multi = np.bincount(lab, weights=n_returns > 1, minlength=size)
    unknown = np.bincount(lab, weights=n_returns < 1, minlength=size)
    few = (points > 0) & (multi < MULTI_RETURN_SHARE * points) & (unknown == 0)
    few[0] = False
    if not few.any():
        return none
    sel = np.flatnonzero(few[lab])
    ids, lab = np.unique(labels[sel], return_inverse=True)
    k = len(ids)
    # the upper surface: the highest point of every column of every segment (metres on the cloud's
    # anchored local frame, so any tiling draws the same columns)
    local = np.empty((len(sel), 3))
    local[:, :2] = (cloud.xyz[sel, :2] - cloud.origin[:2]) * cloud.units.horizontal_m
    local[:, 2] = np.asarray(cloud.attr("height"), dtype=np.float64)[sel]
    ij = np.floor(local[:, :2] / SURFACE_CELL_M).astype(np.int64)
    order = np.lexsort((-local[:, 2], ij[:, 1], ij[:, 0], lab))
    first = np.ones(len(order), dtype=bool)
    first[1:] = ((lab[order][1:] != lab[order][:-1]) | (ij[order][1:, 0] != ij[order][:-1, 0])
                 | (ij[order][1:, 1] != ij[order][:-1, 1]))
    top = order[first]
    cov, _, cells = group_covariances(local[top], lab[top], k)
    rms = np.sqrt(np.maximum(np.linalg.eigvalsh(cov)[:, 0], 0.0))
    hard = (cells >= MIN_SURFACE_CELLS) & (rms < PLANE_RMS_M)
    return ids[hard]
