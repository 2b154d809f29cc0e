"""Individual-tree segmentation: one verb, one module per method.

    labels = segment_trees(cloud, NormalizedCut())          # Hu et al. 2017, §4.1
    labels = segment_trees(cloud, ChmRegionGrowing())       # Dalponte & Coomes 2016

:func:`segment_trees` returns one ``int32`` tree ID per point (0 = ground,
noise or unassigned), as lidR's ``segment_trees`` writes ``treeID``.  The IDs
are the ``tree_id`` values of the tree tops the method was guided by, so a
tree's top (:class:`sylva.core.tops.TreeTops`) and its points share one ID.

A method is a frozen dataclass of its parameters with a
``segment(cloud, tops, progress, cancelled) -> int32 array`` method;
:func:`segment_trees` only validates the input and dispatches, so adding a
method adds a module, not a branch.

Rules every method follows (shared helpers in :mod:`.base`):

* ``cloud`` must be height-normalised (attribute ``height``, metres above
  ground); if it is not, :func:`sylva.core.terrain.normalize` is called.
* Points with NaN/infinite coordinates raise :class:`InputError` naming the
  file; duplicated points are fine.
* Ground points (class 2, or ``height < ground_tolerance_m``) are 0, and so
  are points of the ASPRS classes that are never a tree
  (:data:`NOT_TREE_CLASSES`: buildings, water, rail, roads, wires, towers,
  bridge decks): the method runs without them, so a classified roof or power
  line is neither a tree nor part of one.
* Points below ``min_height_m`` are not crown: they are labelled only when
  they stand in the *column* of a labelled crown, i.e. directly below the
  crown's lowest labelled voxel/cell in the same horizontal cell (stems and
  lower branches under a crown belong to its tree).  A low point in a gap
  between crowns stays 0, so isolated shrubs and low noise are not swallowed.
  (A shrub or low noise point right under a crown does get that tree's ID: from
  the air it cannot be told from the stem.)
* Isolated points (noise) stay 0: a crown point must be connected to a tree top
  through the method's neighbourhood structure (or stand in a labelled crown's
  column, as above), and nothing of a tree is higher than its top.
* A segment of single returns on a plane (an unclassified roof, bridge deck or
  truck: :func:`.surfaces.hard_surfaces`) is not a tree: its points are 0.
"""
from __future__ import annotations

import numpy as np

from ..cloud import PointCloud
from ..errors import InputError
from ..progress import CancelCheck, Progress, report
from .base import LocalTops, validate_cloud
from .chm import ChmRegionGrowing
from .ncut import NormalizedCut
from .surfaces import hard_surfaces

__all__ = ["segment_trees", "NormalizedCut", "ChmRegionGrowing", "LocalTops", "NOT_TREE_CLASSES"]

#: ASPRS classes that are never part of a tree (LAS 1.4 R15, Table 17): building (6), water (9),
#: rail (10), road surface (11), wire guard (13), wire conductor (14), transmission tower (15),
#: wire-structure connector (16), bridge deck (17).  Never classified (0), unclassified (1) and
#: vegetation (3-5) can be trees; ground (2) and noise (7, 18) are left out by their own rules.
#: (Sylva, not in Hu et al.: a classified national survey tile near a village or a power line.)
NOT_TREE_CLASSES = (6, 9, 10, 11, 13, 14, 15, 16, 17)

# --------------------------------------------------------------------------- the verb


def segment_trees(cloud: PointCloud, method=NormalizedCut(), tops=None,
                  progress: Progress = None, cancelled: CancelCheck = None) -> np.ndarray:
    """Per-point tree IDs (``int32``, 0 = ground, noise or unassigned).

    ``cloud``: a :class:`PointCloud`, height-normalised (attribute ``height``
    in metres) or not (then :func:`sylva.core.terrain.normalize` is called).
    ``method``: a segmentation method value, e.g. :class:`NormalizedCut`
    (default, Hu et al. 2017 §4.1) or :class:`ChmRegionGrowing`.
    ``tops``: :class:`sylva.core.tops.TreeTops` to guide the segmentation; when
    None the method finds them with :func:`sylva.core.tops.find_tree_tops`.
    The output IDs are the tops' ``tree_id`` values.
    ``progress(fraction, message)`` / ``cancelled()``: the usual callbacks;
    :class:`sylva.core.errors.Cancelled` is raised when cancelled.
    """
    if not hasattr(method, "segment"):
        raise InputError(f"{method!r} is not a tree segmentation method")
    cloud = validate_cloud(cloud)
    if len(cloud) == 0:
        return np.zeros(0, dtype=np.int32)
    cls = cloud.attr("classification")
    other = np.isin(np.asarray(cls), NOT_TREE_CLASSES) if cls is not None else None
    if other is not None and other.any():
        labels = np.zeros(len(cloud), dtype=np.int32)
        labels[~other] = _segment(method, cloud.subset(~other), tops, progress, cancelled)
    else:
        labels = _segment(method, cloud, tops, progress, cancelled)
    hard = hard_surfaces(cloud, labels)
    if len(hard):
        labels[np.isin(labels, hard)] = 0
    report(progress, 1.0, "tree segmentation done")
    return labels


def _segment(method, cloud: PointCloud, tops, progress: Progress, cancelled: CancelCheck) -> np.ndarray:
    labels = np.asarray(method.segment(cloud, tops, progress, cancelled), dtype=np.int32)
    if labels.shape != (len(cloud),):
        raise AssertionError(f"{type(method).__name__} returned {labels.shape} labels "
                             f"for {len(cloud)} points")
    return labels
