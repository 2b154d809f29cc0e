"""The clean-up of the normalised cut's trees (Sylva, not in the papers; Hu et al. 2017 §4.1 step 5).

Nothing of a tree above its top, voxels cut off from their top joined to the neighbour they are most
strongly joined to, unconnected crown pieces attached within ``attach_m`` (:func:`clean_labels`); points
beyond the allometric crown reach of their tree's top reassigned (:func:`within_crown_reach`,
:func:`crown_radius_m`, Popescu & Wynne 2004), and trees of too few points merged into a neighbour
(:func:`merge_small`).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ...jit import helper, njit
from ...kernels.buckets import bucket_by_cell
from ...kernels.unionfind import uf_union
from ...tops import MAX_CROWN_WIDTH_M
from .graph import VoxelGraph


#: Rounds of attaching unconnected crown pieces (each reaches attach_m farther).
ATTACH_ROUNDS = 5

#: A point higher than its tree's top by more than this is not that tree's.
TOP_TOLERANCE_M = 0.02


def label_tops(xy, height, labels):
    """(ids, top xy, top height) of every label > 0: its highest point above ground, which the merge
    rules were measured on (the top Sylva reports is the apex in elevation,
    :func:`sylva.core.tops.apex_points`; the same point on level ground; ties: lowest x, then y,
    then the first point; never the point order alone, which depends on the tiling).  One pass
    (:func:`_label_maxima`), not a sort of every labelled point."""
    top = _label_maxima(xy, height, labels, int(labels.max(initial=0)) + 1)
    return labels[top], xy[top], height[top]


def tree_relative(xy, elev, height, labels):
    """(every labelled point's height above the ground under its tree's apex, that ground's
    elevation per label, 0 for none).

    The apex is the tree's highest point in elevation (ties as :func:`label_tops`), and these
    heights keep the crown's own shape on sloping ground, where heights above the local ground
    lift its downhill side and put its highest point downhill of its apex (Khosravipour et al.
    2015).  On level ground they are the heights above ground.  Points of no tree keep their
    height."""
    size = int(labels.max(initial=0)) + 1
    top = _label_maxima(xy, elev, labels, size)
    gnd = np.zeros(size)
    gnd[labels[top]] = elev[top] - height[top]
    return _above(elev, height, labels, gnd), gnd


@njit
def _above(elev, height, labels, gnd):
    """Per point: ``elev - gnd[label]`` for a labelled point, its ``height`` for another."""
    out = np.empty(len(labels))
    for i in range(len(labels)):
        out[i] = elev[i] - gnd[labels[i]] if labels[i] > 0 else height[i]
    return out


def _tops_within(xy, height, labels, bounds, scale):
    """label_tops plus every label's top height (``top_h[id]``, 0 for none), the tops' allometric
    crown radii and whether that crown lies within ``bounds`` (xmin, ymin, xmax, ymax: the data's
    extent, a tile's buffer edge; a crown reaching past it may be cut by it)."""
    tid, txy, th = label_tops(xy, height, labels)
    top_h = np.zeros(int(labels.max()) + 1)
    top_h[tid] = th
    r = crown_radius_m(th, scale)
    inside = ((txy[:, 0] - r >= bounds[0]) & (txy[:, 1] - r >= bounds[1])
              & (txy[:, 0] + r <= bounds[2]) & (txy[:, 1] + r <= bounds[3]))
    return tid, txy, th, top_h, r, inside


@njit
def _label_maxima(xy, h, labels, size):
    """Ascending by label: the index of the highest point of every label > 0 (ties: lowest x,
    then lowest y, then the lowest index), as a lexsort on (label, -h, x, y) picks it."""
    best = np.full(size, -1, dtype=np.int64)
    for i in range(len(labels)):
        lab = labels[i]
        if lab <= 0:
            continue
        b = best[lab]
        if b < 0 or h[i] > h[b] or (h[i] == h[b] and (xy[i, 0] < xy[b, 0] or (
                xy[i, 0] == xy[b, 0] and xy[i, 1] < xy[b, 1]))):
            best[lab] = i
    n = 0
    for lab in range(size):
        if best[lab] >= 0:
            n += 1
    out = np.empty(n, dtype=np.int64)
    k = 0
    for lab in range(size):
        if best[lab] >= 0:
            out[k] = best[lab]
            k += 1
    return out


def _reassign(xy, height, labels, bad, tid, txy, th, reach, fallback):
    """Labels of the points ``bad`` set to the tree (of tops tid/txy/th) within ``reach`` allometric
    crown radii whose top is nearest in those units and not lower than the point; ``fallback``
    (per bad point) where there is none."""
    out = labels.copy()
    if len(bad) == 0:
        return out
    if len(tid) == 0:
        out[bad] = fallback
        return out
    k = min(8, len(tid))
    dd, jj = cKDTree(txy).query(xy[bad], k=k)
    dd, jj = dd.reshape(len(bad), k), jj.reshape(len(bad), k)
    norm = dd / (reach * crown_radius_m(th[jj]))
    ok = (norm <= 1.0) & (th[jj] >= height[bad][:, None] - TOP_TOLERANCE_M)
    norm = np.where(ok, norm, np.inf)
    best = np.argmin(norm, axis=1)
    rows = np.arange(len(bad))
    out[bad] = np.where(np.isfinite(norm[rows, best]), tid[jj[rows, best]], fallback)
    return out


def within_crown_reach(xy: np.ndarray, height: np.ndarray, labels: np.ndarray,
                       reach: float) -> np.ndarray:
    """Labels with every point farther (horizontally) from its tree's top than ``reach`` x the
    crown radius that top's height implies (:func:`crown_radius_m`) moved to the tree
    within reach whose top is nearest in those units and not lower than the point (a point
    no other top reaches keeps its tree: open-grown crowns are wider than the allometry).

    Dalponte & Coomes (2016) bound a crown by a maximum crown diameter; here the bound
    follows the tree's height (Popescu & Wynne 2004 crown width).  It removes the strays
    that graph paths carry across neighbouring crowns (Sylva, not in Hu et al.; measured on
    MixedConifer.laz against lidR's crowns, ``benchmarks/segmentation.py``)."""
    if not (labels > 0).any():
        return labels
    tid, txy, th = label_tops(xy, height, labels)
    pos = np.zeros(int(tid.max()) + 1, dtype=np.int64)
    pos[tid] = np.arange(len(tid))
    sel = np.flatnonzero(labels > 0)
    p = pos[labels[sel]]
    far = np.hypot(xy[sel, 0] - txy[p, 0], xy[sel, 1] - txy[p, 1]) > reach * crown_radius_m(th[p])
    bad = sel[far]
    return _reassign(xy, height, labels, bad, tid, txy, th, reach, labels[bad])


def attach_free(xy: np.ndarray, height: np.ndarray, labels: np.ndarray, free: np.ndarray,
                reach: float) -> np.ndarray:
    """Labels with the points ``free`` (indices of crown points of no tree: graph pieces no top
    reached) given to the tree within ``reach`` crown radii whose top is nearest, as
    :func:`within_crown_reach` places its strays; with none in reach they stay 0."""
    if len(free) == 0 or not (labels > 0).any():
        return labels
    tid, txy, th = label_tops(xy, height, labels)
    return _reassign(xy, height, labels, free, tid, txy, th, reach, 0)


#: A tree's apex (its highest point in elevation, the top Sylva reports) lies within this many
#: allometric crown radii of a top its crown was grown from.  Measured on the extended suite
#: (``benchmarks/segmentation.py``): 0.5 also judged trees whose top the search had placed on a
#: flank, off their apex, and lost some (mixed dense 20 points/m2 F1 -0.005); 0.75 lost none; 1.0
#: kept half the gains.
APEX_REACH = 0.75

#: A crown point above its tree's apex beyond APEX_REACH is the neighbour's when a point of
#: another tree lies within this many metres of it (as far as the forest graph reaches across,
#: ``NormalizedCut.radius_m``: the two are touching crowns).
APEX_EDGE_M = 1.0


def apex_near_top(xy: np.ndarray, elev: np.ndarray, labels: np.ndarray, top_xy: np.ndarray,
                  top_label: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """Labels with the points that rise above their tree's apex at the edge of its crown given to
    the neighbouring tree they touch.

    ``top_xy``, ``top_label``, ``reach``: every top the crowns were grown from, the tree it ended
    in (0: none) and ``APEX_REACH`` x its allometric crown radius.  A tree's apex is its highest
    point in elevation within ``reach`` of one of its tops; a point of the tree higher still (so
    farther out), with a point of another tree within ``APEX_EDGE_M``, is a point of that
    neighbour's crown that the cut left on this side of the boundary (a leaf clump of an
    interlocking crown, a few centimetres higher): left there, it becomes the tree's reported
    apex, metres from its stem.  It goes to the tree of the nearest such point, if that tree's
    own highest point is at least as high.  Points inside the crown (no other tree near) stay.
    No per-tile statistic.  Sylva, not in Hu et al."""
    keep = top_label > 0
    if not keep.any():
        return labels
    top_xy, top_label, reach = top_xy[keep], top_label[keep], reach[keep]
    # the trees whose highest point lies beyond the reach of all their tops (few): only they are judged
    size = int(labels.max()) + 1
    apex = _label_maxima(xy, elev, labels, size)
    at = np.full((size, 2), np.nan)
    at[labels[apex]] = xy[apex]
    near = np.zeros(size, dtype=bool)
    near[top_label[np.hypot(*(at[top_label] - top_xy).T) <= reach]] = True
    far = np.zeros(size, dtype=bool)
    far[labels[apex]] = ~near[labels[apex]]
    far_tops = np.flatnonzero(far[top_label])
    if len(far_tops) == 0:
        return labels
    sel = np.flatnonzero(far[labels])
    lab = labels[sel]
    top = np.full(size, -np.inf)             # each judged tree's apex: its highest point near a top
    for t, idx in zip(far_tops, cKDTree(xy[sel]).query_ball_point(top_xy[far_tops], reach[far_tops])):
        idx = np.asarray(idx, dtype=np.int64)
        idx = idx[lab[idx] == top_label[t]]
        if len(idx):
            top[top_label[t]] = max(top[top_label[t]], elev[sel[idx]].max())
    high = sel[np.isfinite(top[lab]) & (elev[sel] > top[lab])]
    if len(high) == 0:
        return labels
    whole = np.full(size, -np.inf)
    whole[labels[apex]] = elev[apex]
    # the labelled points of the APEX_EDGE_M cells around the high points (a 3 x 3 block each)
    other = np.flatnonzero(in_blocks_around(xy, labels > 0, np.ascontiguousarray(xy[high]), APEX_EDGE_M))
    kd = cKDTree(xy[other])
    out = labels.copy()
    for p, idx in zip(high, kd.query_ball_point(xy[high], APEX_EDGE_M)):
        idx = other[np.asarray(idx, dtype=np.int64)]
        idx = idx[labels[idx] != labels[p]]
        if len(idx) == 0:
            continue
        q = idx[np.argmin(np.hypot(xy[idx, 0] - xy[p, 0], xy[idx, 1] - xy[p, 1]))]
        if whole[labels[q]] >= elev[p]:
            out[p] = labels[q]
    return out


@njit
def in_blocks_around(xy, keep, centres, cell):
    """Mask of the points (``xy``, first two columns) with ``keep`` in the 3 x 3 blocks of ``cell``
    columns around the ``centres``: every such point within ``cell`` of a centre, and a few more
    (a hash set of the blocks' columns: one pass over the points, whatever the extent)."""
    marked = set()
    for p in range(len(centres)):
        i = int(np.floor(centres[p, 0] / cell))
        j = int(np.floor(centres[p, 1] / cell))
        for di in range(-1, 2):
            for dj in range(-1, 2):
                marked.add((i + di, j + dj))
    out = np.zeros(len(keep), dtype=np.bool_)
    for k in range(len(keep)):
        if keep[k]:
            out[k] = (int(np.floor(xy[k, 0] / cell)), int(np.floor(xy[k, 1] / cell))) in marked
    return out


def merge_small(xy: np.ndarray, height: np.ndarray, labels: np.ndarray, min_points: np.ndarray,
                reach: float, steep=None, apart: float = 0.0, scale: float = 1.0, max_height=None,
                own=None) -> np.ndarray:
    """Trees of fewer than ``min_points[id]`` points merged into the tree within ``reach`` crown radii
    whose top is nearest (as :func:`within_crown_reach`); with none in reach their points are
    no tree (0): a handful of points apart from every crown is not a tree.  But a small tree whose
    top no tree within reach is high enough to take is the apex of the tallest crown around, whose
    lower crown the graph gave to its neighbours (a sparse scan of a tall, narrow spire: its returns
    lie farther apart than the graph reaches up), not a fragment: it stays (the trees table flags it,
    ``quality`` "sparse").  So does a small tree whose top is a steep apex (``steep[id]``, the
    :class:`~sylva.core.tops.SteepApex` test: the canopy drops steeply around it) farther than ``apart``
    crown radii (:func:`crown_radius_m` times ``scale``, the neighbour judged at most ``max_height[id]``
    high) from every tree as high: the narrow top of a conifer whose lower crown the graph gave to its
    neighbours (a sparse scan), outside their crowns, not a leaf clump of one.  ``own``: the labels
    before the crown points no top reached were attached (:func:`attach_free`); a tree is small by
    its own points, but one with no tree within reach by ``labels``' (a spire over the lower crown a
    sparse scan cut off from it, attached to it).  Sylva, not in Hu et al."""
    if not (labels > 0).any():
        return labels
    n = max(int(labels.max()) + 1, len(min_points))
    size = np.bincount(labels, minlength=n)
    own_size = size if own is None else np.bincount(own[own > 0], minlength=n)[:n]
    need = np.zeros(len(size))
    need[:len(min_points)] = min_points
    small = (own_size < need) & (size > 0)
    small[0] = False
    if not small.any():
        return labels
    tid, txy, th = label_tops(xy, height, labels)
    big = ~small[tid]
    lone = np.flatnonzero(~big)
    reached = np.zeros(len(lone), dtype=bool)
    if big.any():
        # the small trees with a tree within reach, none of them as high: the tallest crowns around
        k = min(8, int(big.sum()))
        dd, jj = cKDTree(txy[big]).query(txy[lone], k=k)
        dd, jj = dd.reshape(len(lone), k), jj.reshape(len(lone), k)
        inside = dd <= reach * crown_radius_m(th[big][jj])
        reached = inside.any(axis=1)
        as_high = inside & (th[big][jj] >= th[lone][:, None] - TOP_TOLERANCE_M)
        small[tid[lone[reached & ~as_high.any(axis=1)]]] = False
        if steep is not None and apart > 0:
            # a steep apex farther than `apart` crown radii from every tree as high: a narrow top of its own
            cap = np.full(len(th), np.inf) if max_height is None else max_height[tid]
            beside = as_high & (dd < apart * crown_radius_m(np.minimum(th[big][jj], cap[big][jj]), scale))
            alone = np.zeros(len(lone), dtype=bool)
            known = tid[lone] < len(steep)
            alone[known] = steep[tid[lone][known]]
            small[tid[lone[alone & ~beside.any(axis=1)]]] = False
    # a small tree with no tree within reach is judged with the crown points no tree took that were
    # attached to it (``labels`` against ``own``): a spire over the lower crown a sparse scan cut off
    small[tid[lone[~reached & (size[tid[lone]] >= need[tid[lone]])]]] = False
    bad = np.flatnonzero(small[labels])
    return _reassign(xy, height, labels, bad, tid[big], txy[big], th[big], reach, 0)


#: A tree's apex is off-centre when it lies farther than this many RMS crown radii from the
#: centroid of its crown (its points at least ``CROWN_TOP_SHARE`` of its height high).
OFF_CENTRE = 0.8

#: The part of a tree's points its crown centroid is taken from, as a share of its height.
CROWN_TOP_SHARE = 0.6

#: The tree an off-centre piece joins is at least this share of its height ...
LEAN_HEIGHT_RATIO = 0.85

#: ... and its top within this many of its allometric crown radii.
LEAN_REACH = 2.0


def merge_off_centre(xy: np.ndarray, height: np.ndarray, labels: np.ndarray, steep: np.ndarray,
                     bounds, height_ratio: float = LEAN_HEIGHT_RATIO,
                     reach: float = LEAN_REACH, scale: float = 1.0, elev=None) -> np.ndarray:
    """Labels with every piece of a crown (an off-centre rounded "tree") merged into the tree
    beside whose crown it lies.

    A tree's crown is centred on its apex: of the trees ncut keeps that match a true tree on 6
    stands of the extended suite, 0-4 % have their highest point farther than ``OFF_CENTRE``
    (0.8) x the RMS radius of their crown from the crown's centroid, against 30-53 % of the
    pieces of a split crown (a leader or leaf clump at the edge of a wide crown, cut off with
    the crown's rim around it, has its rim on the far side of its apex).  Such a tree is merged
    into the tree whose top lies the way its crown leans (within 45 degrees of the apex-to-centroid
    direction, within ``reach`` x that tree's allometric crown radius, :func:`crown_radius_m` times ``scale``),
    at least ``height_ratio`` x as high; the nearest if several.  A steep apex (``steep[id]``, the
    :class:`~sylva.core.tops.SteepApex` test) is a conifer overtopped on one side, whose exposed
    crown does lean away from its neighbour, and a tree whose allometric crown reaches past
    ``bounds`` (xmin, ymin, xmax, ymax: the data's extent; a tile's buffer edge) may be cut by
    it: both are left alone.  ``elev`` (the points' elevations, optional): each tree is judged from its
    apex in elevation, its heights measured from the ground under it (:func:`tree_relative`), so on
    sloping ground a round crown is not taken off-centre.  No per-tile statistic.  Sylva, not in
    Hu et al."""
    if not (labels > 0).any():
        return labels
    if elev is not None:
        height, _ = tree_relative(xy, elev, height, labels)
    tid, txy, th, top_h, r, inside = _tops_within(xy, height, labels, bounds, scale)
    size = len(top_h)
    w, sx, sy, sq = _crown_moments(xy[:, 0], xy[:, 1], height, labels, top_h, CROWN_TOP_SHARE)
    w, sx, sy, sq = w[tid], sx[tid], sy[tid], sq[tid]
    cx, cy = sx / w, sy / w
    ms = np.maximum(sq / w - cx * cx - cy * cy, 0.0)
    lean = np.column_stack([cx - txy[:, 0], cy - txy[:, 1]])
    off = np.hypot(lean[:, 0], lean[:, 1])
    steep_t = np.zeros(len(tid), dtype=bool)
    known = tid < len(steep)
    steep_t[known] = steep[tid[known]]
    cand = np.flatnonzero((off > OFF_CENTRE * np.sqrt(ms)) & inside & ~steep_t)
    if len(cand) == 0:
        return labels
    is_cand = np.zeros(len(tid), dtype=bool)
    is_cand[cand] = True
    kd = cKDTree(txy)
    target = np.full(size, -1, dtype=np.int64)
    far = reach * crown_radius_m(th.max(), scale)
    for c, near in zip(cand, kd.query_ball_point(txy[cand], far)):
        near = np.asarray(near, dtype=np.int64)
        near = near[(near != c) & ~is_cand[near] & (th[near] >= height_ratio * th[c])]
        v = txy[near] - txy[c]
        d = np.hypot(v[:, 0], v[:, 1])
        ok = (d <= reach * r[near]) & (v @ lean[c] >= np.sqrt(0.5) * d * off[c])
        if ok.any():
            k = near[ok][np.lexsort((tid[near[ok]], d[ok]))[0]]
            target[tid[c]] = tid[k]
    move = target[labels] > 0
    out = labels.copy()
    out[move] = target[labels[move]]
    return out


def merge_plateaus(xy: np.ndarray, height: np.ndarray, labels: np.ndarray, bounds, plateau: float,
                   prominence: float, reach: float, contact_m: float, scale: float = 1.0, elev=None,
                   max_height=None) -> np.ndarray:
    """Labels with every tree whose top is a level shoulder of a neighbour's crown merged into it.

    The plateau rule of the cut (:func:`~.cut.unjoined_plateaus`, step 4 of
    :mod:`sylva.core.segment.ncut`) judged again on the finished crowns: a tree whose top is less
    than ``plateau`` x lower than a neighbour's, within ``reach`` allometric crown radii of it
    (:func:`crown_radius_m` times ``scale``), and whose crown touches that neighbour's (points
    within ``contact_m``, the graph's reach) less than ``prominence`` x its height below its top,
    rises nowhere above the crown it touches (its prominence above their saddle): it is a leader
    or a flank of one flat crown, not a summit of its own.  The cut judges the saddle on its start
    partition, before the cuts and clean-up move the boundary; on the finished crowns 20 of the 25
    crown pieces left in the suite's open broadleaf stand (20 points/m², seed 0) have their top
    within 2 % of its height of a taller crown's points.  Trees whose crown may be cut by
    ``bounds`` (xmin, ymin, xmax, ymax: the data's extent, a tile's buffer edge) are left alone.
    A lower tree with several such neighbours joins the one across the highest contact.  ``elev``
    (the points' elevations, optional): the tops, their contacts and how level they are are judged in
    elevation, the tops from their apex in elevation (:func:`tree_relative`): two leaders of one
    crown stand at one elevation, not at one height above a sloping ground.  ``max_height``
    (optional, per label): the most height a tree is judged by, its crown radius and the prominence
    and levelness of a top beside it (a closed canopy's bound, :data:`~.cut.CLOSED_HEIGHT_M`, as the
    cut's merges judge them).  No per-tile statistic.  Sylva, not in Hu et al.;
    measured in :mod:`sylva.core.segment.ncut` (step 5)."""
    if not (labels > 0).any():
        return labels
    gnd = np.zeros(int(labels.max()) + 1)
    if elev is not None:
        height, gnd = tree_relative(xy, elev, height, labels)
    tid, txy, th, top_h, r, inside = _tops_within(xy, height, labels, bounds, scale)
    size = len(top_h)
    top_z = top_h + gnd                 # the tops' elevations (their heights when elev is None)
    tx, ty, far = np.zeros(size), np.zeros(size), np.zeros(size)
    judged = top_h.copy()               # the height each tree is judged by
    if max_height is not None:
        judged[tid] = np.minimum(th, max_height[tid])
        r = crown_radius_m(judged[tid], scale)
    tx[tid], ty[tid], far[tid] = txy[:, 0], txy[:, 1], reach * r
    # the trees with a top of nearly one elevation within reach (from the tops alone)
    tz = top_z[tid]
    p, q = cKDTree(txy).query_pairs(float(far.max(initial=0.0)), output_type="ndarray").T
    hi, lo = np.where(tz[p] >= tz[q], p, q), np.where(tz[p] >= tz[q], q, p)
    near = ((tz[hi] - tz[lo] <= plateau * judged[tid[hi]]) & (np.hypot(*(txy[hi] - txy[lo]).T) < far[tid[hi]])
            & inside[hi] & inside[lo])
    usable = np.zeros(size, dtype=bool)
    usable[tid[hi[near]]] = True
    usable[tid[lo[near]]] = True
    # of those, the crowns' caps: only they can touch within the prominence of a level top
    cap = np.flatnonzero(_crown_caps(labels, height, usable, top_h, (prominence + plateau) * judged))
    if len(cap) < 2:
        return labels
    pts = np.column_stack([xy[cap], height[cap] + gnd[labels[cap]]]).astype(np.float64)   # elevations
    partner = _level_contacts(pts, labels[cap].astype(np.int64), float(contact_m), judged, top_z, tx, ty, far,
                              float(plateau), float(prominence))
    target = np.where(partner >= 0, partner, np.arange(size))
    for _ in range(size):                                  # chains end at a tree that stays (higher tops)
        nxt = target[target]
        if np.array_equal(nxt, target):
            break
        target = nxt
    return target[labels].astype(labels.dtype)


@njit
def _crown_caps(labels, height, usable, top_h, depth):
    """Mask of the points of the ``usable`` labels at most ``depth[label]`` below their top ``top_h[label]``."""
    out = np.zeros(len(labels), dtype=np.bool_)
    for i in range(len(labels)):
        lab = labels[i]
        out[i] = usable[lab] and height[i] >= top_h[lab] - depth[lab]
    return out


@njit
def _crown_moments(x, y, h, labels, top_h, share):
    """Per label: the count, sum of x, sum of y and sum of x² + y² of its points at least ``share``
    x its top's height ``top_h[label]`` high (one pass; the crown moments of :func:`merge_off_centre`)."""
    size = len(top_h)
    w = np.zeros(size)
    sx = np.zeros(size)
    sy = np.zeros(size)
    sq = np.zeros(size)
    for i in range(len(labels)):
        lab = labels[i]
        if lab <= 0 or h[i] < share * top_h[lab]:
            continue
        w[lab] += 1.0
        sx[lab] += x[i]
        sy[lab] += y[i]
        sq[lab] += x[i] * x[i] + y[i] * y[i]
    return w, sx, sy, sq


def crown_radius_m(height_m, scale: float = 1.0):
    """Expected crown radius (m) of a tree ``height_m`` metres high: half the crown width of
    Popescu & Wynne (2004), CW = 2.51503 + 0.00901 h² (pines and deciduous trees together;
    :meth:`sylva.core.tops.VariableWindow.combined`), at most
    :data:`~sylva.core.tops.MAX_CROWN_WIDTH_M` (12 m, reached at 32.4 m: the quadratic is not
    extrapolated to tall trees), times ``scale`` (1: trees grown in a stand;
    :attr:`NormalizedCut.crown_scale <sylva.core.segment.ncut.NormalizedCut.crown_scale>`)."""
    h = np.asarray(height_m, dtype=np.float64)
    return 0.5 * scale * np.minimum(2.51503 + 0.00901 * h * h, MAX_CROWN_WIDTH_M)


def crown_height_m(width_m: float) -> float:
    """The height (m) at which Popescu & Wynne's (2004) crown width (:func:`crown_radius_m`) is
    ``width_m``: the inverse of CW = 2.51503 + 0.00901 h²."""
    return float(np.sqrt(max(width_m - 2.51503, 0.0) / 0.00901))


@helper
def _grid3(xyz, r):
    """A uniform grid of cells of edge >= ``r`` over the points (at most about 4 cells per point):
    (cell of each point, bucket starts, members, gx, gy, gz)."""
    n = xyz.shape[0]
    lo = np.empty(3)
    hi = np.empty(3)
    for a in range(3):
        lo[a] = xyz[0, a]
        hi[a] = xyz[0, a]
    for i in range(n):
        for a in range(3):
            lo[a] = min(lo[a], xyz[i, a])
            hi[a] = max(hi[a], xyz[i, a])
    cell = max(r, 1e-9)
    while True:
        gx = int((hi[0] - lo[0]) / cell) + 1
        gy = int((hi[1] - lo[1]) / cell) + 1
        gz = int((hi[2] - lo[2]) / cell) + 1
        if gx * gy * gz <= 4 * n + 4096:
            break
        cell *= 1.5
    ncell = gx * gy * gz
    cid = np.empty(n, dtype=np.int64)
    for i in range(n):
        cx = min(int((xyz[i, 0] - lo[0]) / cell), gx - 1)
        cy = min(int((xyz[i, 1] - lo[1]) / cell), gy - 1)
        cz = min(int((xyz[i, 2] - lo[2]) / cell), gz - 1)
        cid[i] = (cx * gy + cy) * gz + cz
    start, member = bucket_by_cell(cid, ncell)
    return cid, start, member, gx, gy, gz


@helper
def _near_cells(c, gx, gy, gz, out):
    """The cells of a :func:`_grid3` grid around and including cell ``c`` (up to 27) into ``out``;
    returns how many."""
    cx, cy, cz = c // (gy * gz), (c // gz) % gy, c % gz
    k = 0
    for ix in range(max(cx - 1, 0), min(cx + 2, gx)):
        for iy in range(max(cy - 1, 0), min(cy + 2, gy)):
            for iz in range(max(cz - 1, 0), min(cz + 2, gz)):
                out[k] = (ix * gy + iy) * gz + iz
                k += 1
    return k


@njit
def _pairs_within(xyz, query, r):
    """Every (query[i], j, distance) with point j within ``r`` of point query[i] (d² <= r²,
    d = sqrt((dx² + dy²) + dz²): the pairs and values of ``cKDTree.sparse_distance_matrix``),
    found on a uniform grid of cells of edge >= r (counted, then filled).  Sylva, not in
    the paper."""
    cid, start, member, gx, gy, gz = _grid3(xyz, r)
    r2 = r * r
    out_i = np.empty(0, dtype=np.int64)
    out_j = np.empty(0, dtype=np.int64)
    out_d = np.empty(0)
    cells = np.empty(27, dtype=np.int64)
    for rnd in range(2):            # count, then fill
        k = 0
        for q in range(len(query)):
            p = query[q]
            px, py, pz = xyz[p, 0], xyz[p, 1], xyz[p, 2]
            for m in range(_near_cells(cid[p], gx, gy, gz, cells)):
                g = cells[m]
                for t in range(start[g], start[g + 1]):
                    j = member[t]
                    dx = px - xyz[j, 0]
                    dy = py - xyz[j, 1]
                    dz = pz - xyz[j, 2]
                    d2 = (dx * dx + dy * dy) + dz * dz
                    if d2 <= r2:
                        if rnd == 1:
                            out_i[k] = p
                            out_j[k] = j
                            out_d[k] = np.sqrt(d2)
                        k += 1
        if rnd == 0:
            out_i = np.empty(k, dtype=np.int64)
            out_j = np.empty(k, dtype=np.int64)
            out_d = np.empty(k)
    return out_i, out_j, out_d


@njit
def _level_contacts(xyz, labels, r, top_h, top_z, tx, ty, reach, plateau, prominence):
    """Per label a: the neighbour b its crown touches highest (points within ``r``, d as in
    :func:`_pairs_within`) among those :func:`merge_plateaus` joins it to (-1: none); one pass
    over the points of ``a`` that stand within ``prominence`` of its top (``top_h``: the heights
    the trees are judged by)."""
    cid, start, member, gx, gy, gz = _grid3(xyz, r)
    size = len(top_h)
    best = np.full(size, -np.inf)
    partner = np.full(size, -1, dtype=np.int64)
    r2 = r * r
    cells = np.empty(27, dtype=np.int64)
    for p in range(xyz.shape[0]):
        a = labels[p]
        px, py, pz = xyz[p, 0], xyz[p, 1], xyz[p, 2]
        if top_z[a] - pz >= prominence * top_h[a]:
            continue
        for m in range(_near_cells(cid[p], gx, gy, gz, cells)):
            g = cells[m]
            for t in range(start[g], start[g + 1]):
                j = member[t]
                b = labels[j]
                if b == a or top_z[b] < top_z[a] or (top_z[b] == top_z[a] and b > a):
                    continue                    # b must be the higher top (ties: the lower id)
                dx = px - xyz[j, 0]
                dy = py - xyz[j, 1]
                dz = pz - xyz[j, 2]
                if (dx * dx + dy * dy) + dz * dz > r2:
                    continue
                saddle = min(pz, xyz[j, 2])
                if (top_z[b] - top_z[a] > plateau * top_h[b] or top_z[a] - saddle >= prominence * top_h[a]
                        or np.hypot(tx[a] - tx[b], ty[a] - ty[b]) >= reach[b]):
                    continue
                if saddle > best[a] or (saddle == best[a] and b < partner[a]):
                    best[a] = saddle
                    partner[a] = b
    return partner


@njit
def _joined_to_top(a, b, vlabel, top_voxel, top_id):
    """Per voxel: is it joined to one of its tree's tops through voxels of that tree?

    The components of the edges (a, b) whose ends share a label > 0 (union-find);
    a component is good when it holds a top voxel whose label is that top's id
    (``top_id`` may list one tree several times: the tops merged into it).
    Sylva, not in the paper: the fragment test of :func:`clean_labels`."""
    m = len(vlabel)
    root = np.arange(m)
    for e in range(len(a)):
        u, v = a[e], b[e]
        if vlabel[u] > 0 and vlabel[u] == vlabel[v]:
            uf_union(root, u, v)
    for i in range(m):                  # flatten: root[i] is i's representative
        r = i
        while root[r] != r:
            r = root[r]
        root[i] = r
    good = np.zeros(m, dtype=np.bool_)
    for t in range(len(top_voxel)):
        if vlabel[top_voxel[t]] == top_id[t]:
            good[root[top_voxel[t]]] = True
    out = np.empty(m, dtype=np.bool_)
    for i in range(m):
        out[i] = good[root[i]]
    return out


@njit
def _edges_from_free(a, b, w, vlabel):
    """(src, dst, w) of the edges (a, b, w) read from their unlabelled end (``vlabel`` 0): those
    with a free ``a`` as (a, b), then those with a free ``b`` as (b, a), each in edge order."""
    n = 0
    for e in range(len(a)):
        n += int(vlabel[a[e]] == 0) + int(vlabel[b[e]] == 0)
    src = np.empty(n, dtype=np.int64)
    dst = np.empty(n, dtype=np.int64)
    ww = np.empty(n)
    t = 0
    for side in range(2):
        for e in range(len(a)):
            u, v = (a[e], b[e]) if side == 0 else (b[e], a[e])
            if vlabel[u] == 0:
                src[t], dst[t], ww[t] = u, v, w[e]
                t += 1
    return src, dst, ww


def clean_labels(graph: VoxelGraph, vlabel: np.ndarray, top_voxel: np.ndarray,
                 top_id: np.ndarray, top_height: np.ndarray, tolerance_m: float,
                 attach_m: float, seeds=None) -> np.ndarray:
    """Physical consistency of the labels, then fill the gaps.

    * A tree holds nothing higher than its top (+ ``tolerance_m``).
    * A tree's voxels not connected to its top through the tree itself are
      fragments; they are released.  ``seeds`` (voxels, tree ids) are the tops
      that count, by default ``top_voxel`` and ``top_id``; the cut passes every
      top with the tree it was merged into, so the piece of a crown around a
      merged top stays with its tree: a clumped open-grown crown whose gaps
      the graph does not cross, once its tops are merged, kept only the piece
      of its highest top and lost up to 99 % of its voxels (parkland open at
      20 points/m2, the "open-grown" preset).
    * Released voxels go to the neighbouring tree they are most strongly joined
      to (largest w_ij) among the trees whose top is high enough.
    * Voxels of top-less graph components (crown pieces a sparse scan left
      unconnected) join the nearest labelled voxel within ``attach_m`` (3-D)
      when that tree's top is high enough; farther ones (isolated noise) stay 0.
    """
    a, b = graph.edges[:, 0], graph.edges[:, 1]
    w = graph.weights
    z = graph.xyz[:, 2]
    size = int(max(top_id.max(initial=0), vlabel.max(initial=0))) + 1
    height_of = np.full(size, -np.inf)
    # a given top may lie a little below its voxel's mean (another source or DTM)
    height_of[top_id] = np.maximum(top_height, z[top_voxel])
    vlabel = np.where(z <= height_of[vlabel] + tolerance_m, vlabel, 0)
    seed_voxel, seed_id = (top_voxel, top_id) if seeds is None else seeds
    vlabel = np.where(_joined_to_top(a, b, vlabel, seed_voxel, seed_id), vlabel, 0)
    # flood the unlabelled voxels from labelled neighbours, strongest edge first
    src, dst, ww = _edges_from_free(a, b, w, vlabel)     # only edges out of unlabelled voxels matter
    while len(src):
        cand = (vlabel[src] == 0) & (vlabel[dst] > 0)
        cand &= z[src] <= height_of[vlabel[dst]] + tolerance_m
        if not cand.any():
            break
        s, d, wc = src[cand], dst[cand], ww[cand]
        o = np.lexsort((-wc, s))
        s, d = s[o], d[o]
        first = np.ones(len(s), dtype=bool)
        first[1:] = s[1:] != s[:-1]
        vlabel[s[first]] = vlabel[d[first]]
        still = vlabel[src] == 0
        src, dst, ww = src[still], dst[still], ww[still]
    # crown pieces the graph left unconnected (sparse scans): nearest tree within attach_m
    free = np.flatnonzero(vlabel == 0)
    if not (len(free) and attach_m > 0 and (vlabel > 0).any()):
        return vlabel
    # every voxel within attach_m of a free one, found once (one tree of all voxels)
    fi, vj, dist = _pairs_within(graph.xyz, free, float(attach_m))
    order = np.lexsort((vj, dist, fi))          # per free voxel, nearest first
    fi, vj = fi[order], vj[order]
    for _ in range(ATTACH_ROUNDS):
        lab = vlabel[vj]
        ok = (vlabel[fi] == 0) & (lab > 0)
        ok[ok] = z[fi[ok]] <= height_of[lab[ok]] + tolerance_m
        if not ok.any():
            break
        f, l = fi[ok], lab[ok]
        first = np.ones(len(f), dtype=bool)
        first[1:] = f[1:] != f[:-1]
        vlabel[f[first]] = l[first]
    return vlabel
