"""Per-tree measurements from a segmented cloud: the `trees` table, crowns, crown and stem points.

Everything is computed per tree from its points (label = treeID > 0) in one
vectorised pass over points sorted by (treeID, height):

* **top**: the tree's apex, its highest point in elevation
  (:func:`~sylva.core.tops.apex_points`: on a slope the highest point above
  ground lies downhill of it); ``x``, ``y`` are its horizontal position (CRS
  units) and ``height`` its height above ground (m); ``ground_z`` is the
  terrain elevation under the top (CRS vertical units) = top z - height.
* **crown base** (``crown_base_height``, m above ground): the crown is the
  top part of the tree's vertical point profile that has no empty height
  interval wider than ``gap_m``; scanning the tree's point heights downwards
  from the top, the crown base is the lowest point reached before the first
  such gap, provided the gap lies in the lower ``max_base_fraction`` of the
  tree (a gap higher up is a sampling hole inside the crown, not the stem).
  Points of the tree below the crown base are its **stem points**; the
  others are its **crown points**.  This is the gap rule foresters use on
  vertical profiles (e.g. Popescu & Zhao 2008's height-bin approach, here on
  the points themselves so it needs no bin size).
* **crown**: the 2-D hull of the crown points (convex, or concave with
  shapely's concave hull and a ``concavity`` ratio), ``crown_area`` (m²) and
  ``crown_diameter`` (m) = the diameter of the circle of the same area.
* **quality**: ``sparse`` for a tree of fewer than
  :data:`~sylva.core.tops.MIN_TREE_POINTS` (20) points, which a segmentation
  keeps only where the scan is sparse (its height and crown rest on few
  echoes), ``ok`` otherwise; a reconstruction refines the same column
  (:func:`sylva.core.forest.model_trees`: ``fallback``, ``noise``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import shapely

from .cloud import PointCloud
from .tops import MIN_TREE_POINTS, apex_points


@dataclass(frozen=True)
class CrownBase:
    """Crown-base rule parameters (see module docstring)."""

    gap_m: float = 1.5
    max_base_fraction: float = 0.8


@dataclass(eq=False)
class TreeMetrics:
    """Columns of the trees table (one entry per tree, ordered by tree_id) and per-point roles."""

    tree_id: np.ndarray
    x: np.ndarray
    y: np.ndarray
    top_z: np.ndarray
    ground_z: np.ndarray
    height: np.ndarray
    crown_base_height: np.ndarray
    crown_area: np.ndarray
    crown_diameter: np.ndarray
    n_points: np.ndarray
    crowns: np.ndarray           # object array of shapely Polygons (2-D), None when degenerate
    is_stem: np.ndarray          # per point of the cloud: True for stem points of some tree

    def __len__(self) -> int:
        return len(self.tree_id)

    def columns(self) -> dict:
        """The documented `trees` fields, in order."""
        return {
            "tree_id": self.tree_id, "x": self.x, "y": self.y, "ground_z": self.ground_z,
            "height": self.height, "crown_area": self.crown_area, "crown_diameter": self.crown_diameter,
            "crown_base_height": self.crown_base_height, "n_points": self.n_points,
            "quality": np.where(self.n_points < MIN_TREE_POINTS, "sparse", "ok").astype(object),
        }


def _group_bounds(sorted_labels: np.ndarray):
    """Start index and size of each run of equal labels in a sorted array."""
    change = np.flatnonzero(np.diff(sorted_labels)) + 1
    starts = np.concatenate([[0], change])
    sizes = np.diff(np.concatenate([starts, [len(sorted_labels)]]))
    return starts, sizes


def crown_base_heights(labels_sorted: np.ndarray, h_sorted: np.ndarray, starts: np.ndarray,
                       sizes: np.ndarray, rule: CrownBase) -> np.ndarray:
    """Crown base per tree from heights sorted ascending within each tree (see module docstring)."""
    n_trees = len(starts)
    tops = h_sorted[starts + sizes - 1]
    lowest = h_sorted[starts]
    base = lowest.copy()
    if len(h_sorted) < 2:
        return base
    gap = np.diff(h_sorted)                     # gap between point i and i+1
    same_tree = labels_sorted[1:] == labels_sorted[:-1]
    tree_of = np.repeat(np.arange(n_trees), sizes)[:-1]
    upper = h_sorted[1:]                         # height of the point above the gap
    wide = same_tree & (gap > rule.gap_m) & (upper <= rule.max_base_fraction * tops[tree_of] + rule.gap_m)
    # The highest qualifying gap of each tree sets its crown base at the point above it.
    idx = np.flatnonzero(wide)
    if len(idx):
        best = np.full(n_trees, -np.inf)
        np.maximum.at(best, tree_of[idx], upper[idx])
        has = np.isfinite(best)
        base[has] = best[has]
    return base


def tree_metrics(cloud: PointCloud, labels: np.ndarray, hull: str = "convex", concavity: float = 0.3,
                 crown_base: CrownBase = CrownBase()) -> TreeMetrics:
    """Measure every tree of a segmented, height-normalised cloud (attr ``height``, metres).

    ``labels`` is the per-point treeID (0 = no tree).  ``hull`` is "convex" or
    "concave" (``concavity`` in (0, 1]: shapely's ratio, 1 = convex).
    """
    labels = np.asarray(labels)
    height = np.asarray(cloud.attrs["height"], dtype=np.float64)
    in_tree = np.flatnonzero(labels > 0)
    order = in_tree[np.lexsort((height[in_tree], labels[in_tree]))]
    lab = labels[order]
    h = height[order]
    empty = np.zeros(0)
    if len(order) == 0:
        return TreeMetrics(np.zeros(0, np.int64), empty, empty, empty, empty, empty, empty, empty, empty,
                           np.zeros(0, np.int64), np.zeros(0, object), np.zeros(len(cloud), bool))
    starts, sizes = _group_bounds(lab)
    top_idx = apex_points(cloud.xyz, labels)          # one per tree, in the order of lab[starts]
    tree_id = lab[starts].astype(np.int64)
    base = crown_base_heights(lab, h, starts, sizes, crown_base)
    tree_of = np.repeat(np.arange(len(starts)), sizes)
    stem_sorted = h < base[tree_of]
    is_stem = np.zeros(len(cloud), dtype=bool)
    is_stem[order[stem_sorted]] = True

    crown_pts = order[~stem_sorted]
    crown_tree = tree_of[~stem_sorted]
    xy = cloud.xyz[crown_pts, :2]
    multipoints = shapely.multipoints(xy, indices=crown_tree)
    if hull == "concave":
        crowns = shapely.concave_hull(multipoints, ratio=concavity)
    else:
        crowns = shapely.convex_hull(multipoints)
    crowns = np.array([c if c.geom_type == "Polygon" else None for c in crowns], dtype=object)
    unit2 = cloud.units.horizontal_m ** 2
    area = np.array([0.0 if c is None else c.area * unit2 for c in crowns])
    top_z = cloud.xyz[top_idx, 2]
    top_h = height[top_idx]
    return TreeMetrics(
        tree_id=tree_id,
        x=cloud.xyz[top_idx, 0].copy(),
        y=cloud.xyz[top_idx, 1].copy(),
        top_z=top_z,
        ground_z=top_z - top_h / cloud.units.vertical_m,
        height=top_h,
        crown_base_height=base,
        crown_area=area,
        crown_diameter=2.0 * np.sqrt(area / np.pi),
        n_points=sizes.astype(np.int64),
        crowns=crowns,
        is_stem=is_stem,
    )


# --------------------------------------------------------------------------- DBH

#: Jucker et al. (2017), "Allometric equations for integrating remote sensing imagery into forest
#: monitoring programmes", Global Change Biology 23: 177-190: the global model
#: DBH [cm] = 0.557 (H [m] x CD [m])^0.809 exp(0.056^2 / 2).
JUCKER_ALPHA, JUCKER_BETA, JUCKER_SIGMA = 0.557, 0.809, 0.056


def allometric_dbh_m(height_m, crown_diameter_m) -> np.ndarray:
    """DBH (m) from tree height and crown diameter by Jucker et al. (2017)'s global equation."""
    h = np.maximum(np.asarray(height_m, dtype=np.float64), 0.0)
    cd = np.maximum(np.asarray(crown_diameter_m, dtype=np.float64), 0.0)
    cm = JUCKER_ALPHA * (h * cd) ** JUCKER_BETA * np.exp(JUCKER_SIGMA ** 2 / 2.0)
    return cm / 100.0


@dataclass(frozen=True)
class StemCircle:
    """A circle fitted to stem points at breast height (local metres)."""

    x: float
    y: float
    radius: float
    rms: float
    n_points: int
    arc_deg: float


def fit_stem_circle(xy: np.ndarray) -> Optional[StemCircle]:
    """Least-squares circle (Kasa's algebraic fit, refined by Gauss-Newton) of horizontal positions."""
    xy = np.asarray(xy, dtype=np.float64)
    if len(xy) < 3:
        return None
    c = xy.mean(axis=0)
    p = xy - c
    a = np.column_stack([2 * p, np.ones(len(p))])
    b = (p ** 2).sum(axis=1)
    try:
        sol, *_ = np.linalg.lstsq(a, b, rcond=None)
    except np.linalg.LinAlgError:
        return None
    centre = sol[:2]
    r = np.sqrt(max(sol[2] + centre @ centre, 0.0))
    for _ in range(10):  # geometric refinement: minimise sum (|p - c| - r)^2
        d = p - centre
        dist = np.linalg.norm(d, axis=1)
        if np.any(dist < 1e-12):
            break
        jac = np.column_stack([-d / dist[:, None], -np.ones(len(p))])
        res = dist - r
        step, *_ = np.linalg.lstsq(jac, -res, rcond=None)
        centre, r = centre + step[:2], r + step[2]
        if np.abs(step).max() < 1e-7:
            break
    d = p - centre
    ang = np.sort(np.arctan2(d[:, 1], d[:, 0]))
    gaps = np.diff(np.concatenate([ang, [ang[0] + 2 * np.pi]]))
    arc = np.degrees(2 * np.pi - gaps.max())
    rms = float(np.sqrt(np.mean((np.linalg.norm(d, axis=1) - r) ** 2)))
    return StemCircle(float(centre[0] + c[0]), float(centre[1] + c[1]), float(abs(r)), rms, len(xy), float(arc))


@dataclass(frozen=True)
class DbhRule:
    """When a DBH is `measured`: at least ``min_points`` stem points within ``band_m`` of
    1.3 m above the ground covering ``min_arc_deg`` of the circle, and a plausible, tight fit."""

    breast_height_m: float = 1.3
    band_m: float = 0.25
    min_points: int = 8
    min_arc_deg: float = 120.0
    max_rms_m: float = 0.03
    max_radius_m: float = 1.5


def estimate_dbh(local_xyz: np.ndarray, height_m: np.ndarray, tree_height_m: float, crown_diameter_m: float,
                 rule: DbhRule = DbhRule()):
    """(dbh_m, source): a circle fit at breast height when the points allow it, else Jucker et al. (2017)."""
    h = np.asarray(height_m)
    band = np.abs(h - rule.breast_height_m) <= rule.band_m
    if band.sum() >= rule.min_points:
        circle = fit_stem_circle(local_xyz[band, :2])
        if (circle is not None and circle.arc_deg >= rule.min_arc_deg and circle.rms <= rule.max_rms_m
                and 0.01 <= circle.radius <= rule.max_radius_m):
            return 2.0 * circle.radius, "measured"
    return float(allometric_dbh_m(tree_height_m, crown_diameter_m)), "allometric"


def estimate_dbhs(local_xyz: np.ndarray, height_m: np.ndarray, offsets, tree_heights_m, crown_diameters_m,
                  rule: DbhRule = DbhRule()) -> list:
    """:func:`estimate_dbh` of every tree whose points are ``local_xyz[offsets[t]:offsets[t + 1]]``.

    The breast-height band is counted for all trees in one pass; only trees with enough points in it
    are fitted, the others get the allometric DBH straight away (the same values as tree by tree).
    """
    off = np.asarray(offsets, dtype=np.int64)
    band = np.abs(np.asarray(height_m) - rule.breast_height_m) <= rule.band_m
    n_band = np.diff(np.r_[0, np.cumsum(band)][off]).tolist()
    bounds = off.tolist()
    out = []
    for t, (h, cd) in enumerate(zip(tree_heights_m, crown_diameters_m)):
        if n_band[t] >= rule.min_points:
            a, b = bounds[t], bounds[t + 1]
            out.append(estimate_dbh(local_xyz[a:b], height_m[a:b], h, cd, rule))
        else:
            out.append((float(allometric_dbh_m(h, cd)), "allometric"))
    return out
