"""Tree-segmentation accuracy measures shared by benchmarks/segmentation.py and the tests.

Load it from a test with importlib (benchmarks/ is not a package)::

    spec = importlib.util.spec_from_file_location("seg_metrics", ROOT / "benchmarks" / "metrics.py")

Matching rule (project issue 3): a detected tree matches a true tree when
their tops are within ``0.5 x`` the true crown radius horizontally and their
heights differ by less than 15 % of the true height; matches are one-to-one,
chosen by a Hungarian assignment (:func:`scipy.optimize.linear_sum_assignment`)
on horizontal distance with infeasible pairs excluded.  A segmented tree's
top is its apex, its highest point in elevation (sylva.core.tops.apex_points),
with that point's height above ground.
"""

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

_INFEASIBLE = 1e12


@dataclass(frozen=True)
class Detection:
    """Detection scores and the matched pairs (detected id, true id)."""

    n_detected: int
    n_true: int
    n_matched: int
    pairs: np.ndarray  # (m, 2) int64: detected tree id, true tree id

    @property
    def precision(self) -> float:
        return self.n_matched / self.n_detected if self.n_detected else 0.0

    @property
    def recall(self) -> float:
        return self.n_matched / self.n_true if self.n_true else 0.0

    @property
    def f1(self) -> float:
        p, r = self.precision, self.recall
        return 2 * p * r / (p + r) if p + r > 0 else 0.0


def segment_tops(xyz: np.ndarray, height: np.ndarray, labels: np.ndarray):
    """(ids, x, y, height) of the apex of each segmented tree (label > 0): its highest point in
    elevation (sylva.core.tops.apex_points, what Sylva reports as the tree's top), with that point's
    height above ground."""
    from sylva.core.tops import apex_points

    top = apex_points(xyz, labels)
    labels = np.asarray(labels)
    return labels[top].astype(np.int64), xyz[top, 0], xyz[top, 1], height[top]


def match_trees(det_id, det_x, det_y, det_h, true_id, true_x, true_y, true_h, true_r,
                radius_factor: float = 0.5, height_tolerance: float = 0.15) -> Detection:
    """One-to-one matching of detected to true trees (Hungarian on distance)."""
    det_id = np.asarray(det_id, dtype=np.int64)
    true_id = np.asarray(true_id, dtype=np.int64)
    nd, nt = len(det_id), len(true_id)
    pairs = np.zeros((0, 2), dtype=np.int64)
    if nd == 0 or nt == 0:
        return Detection(nd, nt, 0, pairs)
    true_xy = np.column_stack([true_x, true_y])
    det_xy = np.column_stack([det_x, det_y])
    rmax = radius_factor * float(np.max(true_r))
    near = cKDTree(true_xy).query_ball_point(det_xy, rmax)
    rows = np.repeat(np.arange(nd), [len(v) for v in near])
    cols = np.fromiter((j for v in near for j in v), dtype=np.int64, count=len(rows))
    if len(rows) == 0:
        return Detection(nd, nt, 0, pairs)
    dist = np.hypot(det_xy[rows, 0] - true_xy[cols, 0], det_xy[rows, 1] - true_xy[cols, 1])
    true_h = np.asarray(true_h, dtype=np.float64)
    ok = (dist <= radius_factor * np.asarray(true_r)[cols]) & (
        np.abs(np.asarray(det_h)[rows] - true_h[cols]) < height_tolerance * true_h[cols])
    rows, cols, dist = rows[ok], cols[ok], dist[ok]
    if len(rows) == 0:
        return Detection(nd, nt, 0, pairs)
    # the assignment only needs the rows / columns that have a feasible pair
    ur, ri = np.unique(rows, return_inverse=True)
    uc, ci = np.unique(cols, return_inverse=True)
    cost = np.full((len(ur), len(uc)), _INFEASIBLE)
    cost[ri, ci] = dist
    r, c = linear_sum_assignment(cost)
    good = cost[r, c] < _INFEASIBLE
    pairs = np.column_stack([det_id[ur[r[good]]], true_id[uc[c[good]]]])
    return Detection(nd, nt, int(good.sum()), pairs)


def point_accuracy(labels: np.ndarray, truth_tree: np.ndarray, pairs: np.ndarray) -> float:
    """Fraction of true tree points (truth > 0) labelled with their matched tree's id.

    Points of a true tree without a match count as wrong."""
    truth_tree = np.asarray(truth_tree)
    labels = np.asarray(labels)
    tree_pts = truth_tree > 0
    if not tree_pts.any():
        return float("nan")
    lookup = np.full(int(truth_tree.max()) + 1, -1, dtype=np.int64)
    if len(pairs):
        lookup[pairs[:, 1]] = pairs[:, 0]
    expected = lookup[truth_tree[tree_pts]]
    return float(np.mean(labels[tree_pts] == expected))


def evaluate(xyz, height, labels, truth_tree, trees) -> dict:
    """Detection P/R/F1 and point accuracy of ``labels`` against a synthetic scan's truth.

    ``xyz`` CRS coordinates, ``height`` metres above ground, ``trees`` a list of
    :class:`sylva.testing.synth.TrueTree`."""
    ids, x, y, h = segment_tops(xyz, height, labels)
    true_id = np.array([t.tree_id for t in trees], dtype=np.int64)
    det = match_trees(ids, x, y, h, true_id,
                      np.array([t.x for t in trees]), np.array([t.y for t in trees]),
                      np.array([t.height for t in trees]),
                      np.array([t.crown_radius_m for t in trees]))
    return {"precision": det.precision, "recall": det.recall, "f1": det.f1,
            "n_detected": det.n_detected, "n_true": det.n_true,
            "point_accuracy": point_accuracy(labels, truth_tree, det.pairs),
            **losses(xyz, height, labels, truth_tree, trees, det.pairs)}


def _majority(a: np.ndarray, b: np.ndarray, size_a: int) -> np.ndarray:
    """Per value of ``a`` (0..size_a-1): the most frequent ``b`` among its points (0: none; ties:
    the lowest), over points with a > 0 and b > 0."""
    sel = (a > 0) & (b > 0)
    out = np.zeros(size_a, dtype=np.int64)
    if not sel.any():
        return out
    pairs, counts = np.unique(np.column_stack([a[sel], b[sel]]), axis=0, return_counts=True)
    order = np.lexsort((pairs[:, 1], -counts, pairs[:, 0]))
    pairs = pairs[order]
    first = np.ones(len(pairs), dtype=bool)
    first[1:] = pairs[1:, 0] != pairs[:-1, 0]
    out[pairs[first, 0]] = pairs[first, 1]
    return out


def losses(xyz, height, labels, truth_tree, trees, pairs, overtop_radius_m: float = 1.0) -> dict:
    """Where the detection F1 is lost: the unmatched detected trees (false positives) and the
    unmatched true trees (false negatives) by cause.

    * ``fp_split``: the majority of its points belong to a true tree that is matched to another
      detected tree (a piece of a crown: over-segmentation);
    * ``fp_offset``: its majority true tree is unmatched (its top is too far from the stem or of
      the wrong height: the crown is there, the top is not where the matching looks);
    * ``fn_merged``: most of its points lie in a detected tree whose majority is another true
      tree (under-segmentation);
    * ``fn_overtopped``: :func:`overtopped`, its apex under a neighbour's crown (counted among
      fn_merged / the rest as well);
    * ``overtopped``, ``tp_overtopped``: the true trees under a neighbour's crown, and how many of
      them are matched all the same.
    Sylva benchmark measure, not from a paper."""
    labels = np.asarray(labels, dtype=np.int64)
    truth_tree = np.asarray(truth_tree, dtype=np.int64)
    size_d = int(labels.max(initial=0)) + 1
    size_t = max(int(truth_tree.max(initial=0)), max((t.tree_id for t in trees), default=0)) + 1
    maj_d = _majority(labels, truth_tree, size_d)      # detected tree -> its majority true tree
    maj_t = _majority(truth_tree, labels, size_t)      # true tree -> the detected tree holding most of it
    matched_d = np.zeros(size_d, dtype=bool)
    matched_t = np.zeros(size_t, dtype=bool)
    if len(pairs):
        matched_d[pairs[:, 0]] = True
        matched_t[pairs[:, 1]] = True
    det = np.unique(labels[labels > 0])
    un_d = det[~matched_d[det]]
    fp_split = int(np.sum(matched_t[maj_d[un_d]] & (maj_d[un_d] > 0)))
    true_ids = np.array([t.tree_id for t in trees], dtype=np.int64)
    un_t = true_ids[~matched_t[true_ids]]
    holder = maj_t[un_t]
    fn_merged = int(np.sum((holder > 0) & (maj_d[holder] != un_t)))
    over = overtopped(xyz, height, truth_tree, true_ids, overtop_radius_m)
    return {"fp_split": fp_split, "fp_offset": int(len(un_d) - fp_split), "fn_merged": fn_merged,
            "fn_overtopped": int(over[~matched_t[true_ids]].sum()), "fn": int(len(un_t)),
            "overtopped": int(over.sum()), "tp_overtopped": int(over[matched_t[true_ids]].sum())}


def overtopped(xyz, height, truth_tree, tree_ids, radius_m: float = 1.0) -> np.ndarray:
    """Per tree of ``tree_ids``: its apex (highest point in elevation) has a point of another tree
    more than 0.5 m higher within ``radius_m`` horizontally (bool; False for a tree with no point):
    the tree is under a neighbour's crown, and a top searched on the canopy surface with a window of
    ``radius_m`` or more is not at its apex.  Sylva benchmark measure, not from a paper."""
    from sylva.core.tops import apex_points

    tree_ids = np.asarray(tree_ids, dtype=np.int64)
    truth_tree = np.asarray(truth_tree, dtype=np.int64)
    out = np.zeros(len(tree_ids), dtype=bool)
    size = max(int(truth_tree.max(initial=0)), int(tree_ids.max(initial=0))) + 1
    first = apex_points(xyz, truth_tree)
    apex = np.full(size, -1, dtype=np.int64)
    apex[truth_tree[first]] = first
    has = apex[tree_ids] >= 0
    if not has.any():
        return out
    a = apex[tree_ids[has]]
    near = cKDTree(xyz[:, :2]).query_ball_point(xyz[a, :2], radius_m)
    out[has] = [bool(np.any((height[v] > height[p] + 0.5) & (truth_tree[v] != t)))
                for v, p, t in zip((np.asarray(v, dtype=np.int64) for v in near), a, tree_ids[has])]
    return out


def crown_iou(xy: np.ndarray, labels_a: np.ndarray, labels_b: np.ndarray, min_points: int = 3):
    """Agreement of two segmentations: trees matched one-to-one (Hungarian on
    2-D convex-hull IoU, over pairs that share points) and the IoU of each match.

    Returns (n_trees_a, n_trees_b, ious of the matched pairs)."""
    from shapely import MultiPoint

    def hulls(labels):
        out = {}
        sel = np.flatnonzero(labels > 0)
        order = sel[np.argsort(labels[sel], kind="stable")]
        lab = labels[order]
        cuts = np.flatnonzero(np.diff(lab)) + 1
        for group in np.split(order, cuts):
            if len(group) >= min_points:
                hull = MultiPoint(xy[group]).convex_hull
                if hull.area > 0:
                    out[int(labels[group[0]])] = hull
        return out

    ha, hb = hulls(np.asarray(labels_a)), hulls(np.asarray(labels_b))
    both = (labels_a > 0) & (labels_b > 0)
    cand = np.unique(np.column_stack([labels_a[both], labels_b[both]]), axis=0)
    cand = [(int(a), int(b)) for a, b in cand if int(a) in ha and int(b) in hb]
    if not cand:
        return len(ha), len(hb), np.zeros(0)
    ia = {k: i for i, k in enumerate(sorted({a for a, _ in cand}))}
    ib = {k: i for i, k in enumerate(sorted({b for _, b in cand}))}
    score = np.zeros((len(ia), len(ib)))
    for a, b in cand:
        pa, pb = ha[a], hb[b]
        inter = pa.intersection(pb).area
        score[ia[a], ib[b]] = inter / (pa.area + pb.area - inter)
    r, c = linear_sum_assignment(-score)
    ious = score[r, c]
    return len(ha), len(hb), ious[ious > 0]
