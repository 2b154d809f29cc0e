"""Cylinder tables of a QSM: from centre lines or skeletons, radii tapered and refitted to the points,
and the distance of points to the model (see :mod:`sylva.core.qsm`)."""
from __future__ import annotations

from typing import Optional, Sequence

import numpy as np
from scipy.spatial import cKDTree

from ..circles import arc_sectors, fit_circles

__all__ = ["CYLINDER_FIELDS", "branch_depth", "cylinders_from_curves", "cylinders_from_skeleton", "surface_distance",
           "group_median", "taper_radii", "refit_radii"]

CYLINDER_FIELDS = ("id", "parent", "branch", "order", "start_x", "start_y", "start_z",
                   "axis_x", "axis_y", "axis_z", "length", "radius")


def branch_depth(bp: np.ndarray) -> np.ndarray:
    """Depth of every branch in the branch tree (trunk 0), by pointer jumping when parents precede children."""
    if not np.all(bp < np.arange(len(bp))):     # as the sequential rule order[b] = order[bp[b]] + 1 gives
        order = np.zeros(len(bp), dtype=np.int64)
        for b in range(len(bp)):
            if bp[b] >= 0:
                order[b] = order[bp[b]] + 1
        return order
    order = (bp >= 0).astype(np.int64)
    nxt = bp.copy()
    live = np.flatnonzero(nxt >= 0)
    while len(live):
        tgt = nxt[live]
        order[live] += order[tgt]
        nxt[live] = nxt[tgt]
        live = live[nxt[live] >= 0]
    return order


def cylinders_from_curves(curves: Sequence[np.ndarray], radii: Sequence[np.ndarray],
                          branch_parent: Sequence[int], branch_order: Optional[Sequence[int]] = None,
                          segment_radii: bool = False) -> dict:
    """A TreeQSM-like cylinder table from one sampled centre line + radii per branch, all branches at once.

    Consecutive samples of branch ``b`` become cylinders of branch ``b`` (radius
    the mean of the two end radii, or, with ``segment_radii``, ``radii[b]`` holds
    one radius per segment, ``len(curve) - 1``); segments shorter than 1e-9 m are
    left out.  A cylinder's parent is the previous cylinder of its branch; the first
    cylinder of a branch has as parent the cylinder of its parent branch whose
    mid-point is nearest its start, when the parent branch comes before it and has
    cylinders (-1 otherwise, and for the trunk).  ``branch_order`` defaults to the
    depth of the branch in ``branch_parent`` (:func:`branch_depth`).
    Returns a dict of arrays keyed by :data:`CYLINDER_FIELDS` names plus
    ``start`` (n, 3) and ``axis`` (n, 3).
    """
    bp = np.asarray(branch_parent, dtype=np.int64).reshape(-1)
    nb = len(curves)
    order = branch_depth(bp[:nb]) if branch_order is None else np.asarray(branch_order, dtype=np.int64)
    lens = np.array([len(np.asarray(c).reshape(-1, 3)) for c in curves], dtype=np.int64)
    pts = (np.concatenate([np.asarray(c, dtype=np.float64).reshape(-1, 3) for c in curves]) if nb
           else np.zeros((0, 3)))
    rad = (np.concatenate([np.asarray(r, dtype=np.float64).reshape(-1) for r in radii]) if nb
           else np.zeros(0))
    lid = np.repeat(np.arange(nb), lens)
    seg = np.flatnonzero(lid[:-1] == lid[1:]) if len(pts) > 1 else np.zeros(0, np.int64)
    vec = pts[seg + 1] - pts[seg]
    L = np.linalg.norm(vec, axis=1)
    ok = L > 1e-9
    seg, vec, L = seg[ok], vec[ok], L[ok]
    br = lid[seg]
    n = len(seg)
    if n == 0:
        z3, zi, zf = np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros(0)
        return dict(id=zi, parent=zi, branch=zi, order=zi, start=z3, axis=z3, length=zf, radius=zf)
    if segment_radii:       # radii[b][k]: the k-th segment of branch b (its k-th sample onwards)
        r_off = np.r_[0, np.cumsum([len(np.asarray(r).reshape(-1)) for r in radii])]
        radius = rad[r_off[br] + seg - np.r_[0, np.cumsum(lens)][br]]
    else:
        radius = (rad[seg] + rad[seg + 1]) / 2
    start = pts[seg]
    par = np.arange(n) - 1
    first = np.r_[True, br[1:] != br[:-1]]
    par[first] = -1
    fi = np.flatnonzero(first)
    want = np.where(bp[br[fi]] < br[fi], bp[br[fi]], -1)       # a parent branch that comes before
    mid = start + vec / 2
    kq = min(16, n)
    _, cand = cKDTree(mid).query(start[fi], k=kq)
    cand = np.asarray(cand).reshape(len(fi), kq)
    hit = br[cand] == want[:, None]
    j = np.argmax(hit, axis=1)
    got = hit[np.arange(len(fi)), j]
    par[fi] = np.where(got & (want >= 0), cand[np.arange(len(fi)), j], -1)
    for i, w in zip(fi[~got & (want >= 0)].tolist(), want[~got & (want >= 0)].tolist()):
        pc = np.flatnonzero(br == w)        # rare: the parent's nearest cylinders are farther than 16
        if len(pc):
            par[i] = pc[np.argmin(np.linalg.norm(mid[pc] - start[i], axis=1))]
    return dict(id=np.arange(n, dtype=np.int64), parent=par.astype(np.int64), branch=br.astype(np.int64),
                order=order[br], start=start, axis=vec / L[:, None], length=L, radius=radius)


def cylinders_from_skeleton(skeleton, radii: Optional[np.ndarray] = None, branch_set=None) -> tuple:
    """Cylinder table of a skeleton with radii: every skeleton edge one cylinder.

    For the methods without fitted cylinders (airborne skeletons with pipe-model
    radii): branches are the chains of :func:`sylva.core.geometry.branches`
    (Hu et al. 2017 §5.5: the trunk is one chain, at each fork the least-bent
    child continues it); the cylinder of the edge (parent node -> node) has
    the node's radius, and its parent cylinder is the edge ending at the parent
    node.  Vectorised; cylinders are grouped by branch, parents first.
    Returns ``(cylinders, branch_parent)`` as :func:`cylinders_from_curves`.
    ``branch_set`` may pass ``branches(skeleton, radii)`` when the caller has it already.
    """
    from ..geometry import branches

    r = np.asarray(skeleton.radius if radii is None else radii, dtype=np.float64)
    if len(skeleton) < 2:
        return cylinders_from_curves([], [], []), np.zeros(0, dtype=np.int64)
    bs = branch_set if branch_set is not None else branches(skeleton, r)
    par = skeleton.parent
    node = np.flatnonzero(par >= 0)                       # one cylinder per non-root node
    nb = np.asarray(bs.node_branch, dtype=np.int64)
    order = np.lexsort((node, nb[node]))
    node = node[order]
    cyl_of = np.full(len(par), -1, dtype=np.int64)
    cyl_of[node] = np.arange(len(node))
    start = skeleton.nodes[par[node]]
    vec = skeleton.nodes[node] - start
    length = np.linalg.norm(vec, axis=1)
    axis = np.where(length[:, None] > 1e-12, vec / np.maximum(length, 1e-12)[:, None], np.array([0, 0, 1.0]))
    branch = nb[node]
    return (dict(id=np.arange(len(node), dtype=np.int64), parent=cyl_of[par[node]], branch=branch,
                 order=np.asarray(bs.order, dtype=np.int64)[branch], start=start, axis=axis, length=length,
                 radius=r[node].copy()),
            np.asarray(bs.parent, dtype=np.int64))


def surface_distance(points: np.ndarray, cyl: dict, k: int = 16, return_index: bool = False):
    """Distance (m) from each point to the nearest cylinder surface of a model.

    Candidates are the ``k`` cylinders with the nearest mid-points; the
    distance to a cylinder is ``|ρ - r|`` beside it (ρ the distance to the
    axis) and the distance to its rim beyond its ends.  With ``return_index``
    also the index of that nearest cylinder per point.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(cyl["radius"]) == 0:
        d = np.full(len(points), np.inf)
        return (d, np.full(len(points), -1, dtype=np.int64)) if return_index else d
    s, a, L, r = cyl["start"], cyl["axis"], cyl["length"], cyl["radius"]
    mid = s + a * (L / 2)[:, None]
    k = min(k, len(r))
    _, idx = cKDTree(mid).query(points, k=k, workers=-1)
    idx = idx.reshape(len(points), k)
    p = points[:, None, :] - s[idx]
    t = (p * a[idx]).sum(axis=2)
    rho = np.linalg.norm(p - t[..., None] * a[idx], axis=2)
    out_t = np.maximum(0, np.maximum(-t, t - L[idx]))
    d = np.where(out_t > 0, np.hypot(np.maximum(rho - r[idx], 0), out_t), np.abs(rho - r[idx]))
    j = np.argmin(d, axis=1)
    best = d[np.arange(len(points)), j]
    return (best, idx[np.arange(len(points)), j]) if return_index else best


def group_median(values: np.ndarray, groups: np.ndarray, n: int) -> np.ndarray:
    """Median of ``values`` per group id in [0, n) (NaN for empty groups), vectorised."""
    out = np.full(n, np.nan)
    if len(values) == 0:
        return out
    order = np.lexsort((values, groups))
    g, v = groups[order], values[order]
    starts = np.flatnonzero(np.r_[True, g[1:] != g[:-1]])
    cnt = np.diff(np.r_[starts, len(g)])
    lo = starts + (cnt - 1) // 2
    hi = starts + cnt // 2
    out[g[starts]] = (v[lo] + v[hi]) / 2
    return out


def taper_radii(cyl: dict, slack: float = np.inf) -> dict:
    """Radii that do not grow away from the stem base (TreeQSM-like correction).

    Not in Yan et al.: the first cylinder of a branch is at most as thick as the
    parent cylinder it leaves, and along a branch a cylinder is at most ``slack``
    times the previous one (default: no limit; a running cap lets one thin,
    badly fitted cylinder thin the whole branch above it).  Cylinders are in branch order with parents before
    children (as :func:`cylinders_from_curves` makes them).
    """
    r = np.asarray(cyl["radius"], dtype=np.float64).copy()
    par = cyl["parent"]
    br = cyl["branch"]
    for i in range(len(r)):
        p = int(par[i])
        if p < 0:
            continue
        if br[p] == br[i] and not np.isfinite(slack):
            continue
        cap = r[p] if br[p] != br[i] else slack * r[p]
        if r[i] > cap:
            r[i] = cap
    out = dict(cyl)
    out["radius"] = r
    return out


def refit_radii(points: np.ndarray, cyl: dict, min_points: int = 12, min_arc_deg: float = 120.0,
                max_change: float = 2.0, iterations: int = 5, return_shift: bool = False) -> tuple:
    """Least-squares radius of every cylinder from the points nearest to its surface.

    Not in Yan et al. (whose radii come from the clusters' enclosing circles,
    §2.3 / §4.2, biased by noise and by clusters that are only a patch of a
    thick stem): each point goes to its nearest cylinder
    (:func:`surface_distance`, only points within half a radius + 2 cm of
    that surface and beside it); the points of a cylinder, projected onto the
    plane normal to its axis, get a circle fit (Kasa's algebraic fit refined
    by ``iterations`` Gauss-Newton steps of the geometric fit, all cylinders at
    once).  A cylinder takes the fitted radius when it has ``min_points``
    points covering at least ``min_arc_deg`` of its circumference (30°
    sectors around the axis) and the radius changes by less than a factor
    ``max_change``, and the fitted axis lies inside the cylinder; the others,
    thin or sparsely scanned branches whose points scatter about the centre
    line, take the median distance of the points beside them (within 1.5
    radii + 2 cm of the axis) to their axis when that is smaller than their
    radius (at least 3 points); cylinders with fewer points beside them take
    radii interpolated along their branch from the others.  Returns ``(new_cylinders, refit)`` with ``refit`` (n,) True
    where the radius was replaced, and with ``return_shift`` also the (n, 3)
    offset of the fitted axis from the cylinder's axis (0 where not refit).
    """
    n = len(cyl["radius"])
    out = dict(cyl)
    if n == 0 or len(points) == 0:
        return out, np.zeros(n, dtype=bool)
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    d, j = surface_distance(points, cyl, k=4, return_index=True)
    r0 = cyl["radius"]
    s, a, L = cyl["start"][j], cyl["axis"][j], cyl["length"][j]
    p = points - s
    t = (p * a).sum(axis=1)
    beside = (t >= 0) & (t <= L)
    rho_all = np.linalg.norm(p - t[:, None] * a, axis=1)
    ax = cyl["axis"]
    helper = np.where(np.abs(ax[:, 2:3]) < 0.9, np.array([0, 0, 1.0]), np.array([1.0, 0, 0]))
    e1 = np.cross(ax, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(ax, e1)
    # fallback for thin / sparse branches: median distance to the axis of the points beside it,
    # and their centroid in the cross-section (where the axis moves)
    near = beside & (rho_all <= 1.5 * r0[j] + 0.02)
    jn, pn = j[near], p[near]
    n_near = np.bincount(jn, minlength=n)
    mx = np.bincount(jn, weights=(pn * e1[jn]).sum(axis=1), minlength=n) / np.maximum(n_near, 1)
    my = np.bincount(jn, weights=(pn * e2[jn]).sum(axis=1), minlength=n) / np.maximum(n_near, 1)
    med = group_median(rho_all[near], jn, n)
    ok = (d <= 0.5 * r0[j] + 0.02) & beside
    p, j, a = p[ok], j[ok], a[ok]
    x, y = (p * e1[j]).sum(axis=1), (p * e2[j]).sum(axis=1)
    cnt = np.bincount(j, minlength=n).astype(np.float64)
    arc = arc_sectors(x, y, j, n)                      # seen from the axis
    good = (cnt >= max(min_points, 3)) & (arc >= min_arc_deg)
    cx, cy, r, _, _ = fit_circles(x, y, j, n, iterations=iterations, fit=good)
    good &= np.isfinite(r) & (r > 0) & (r <= max_change * r0) & (r >= r0 / max_change)
    good &= np.hypot(cx, cy) <= np.maximum(r0, r)       # the fitted axis stays inside the cylinder
    # no circle: a thin or sparsely scanned branch, whose points scatter about its centre line
    thin = ~good & (n_near >= 3) & np.isfinite(med)
    new_r = np.where(good, r, np.where(thin, np.minimum(med, r0), r0))
    # cylinders with (almost) no points beside them: radius interpolated along the
    # branch from the supported ones (their prior, a sparse cluster's circle, is a guess)
    supported = good | thin
    br = cyl["branch"]
    starts = np.flatnonzero(np.r_[True, br[1:] != br[:-1]])
    for a0, b0 in zip(starts, np.r_[starts[1:], n]):
        sup = supported[a0:b0]
        if sup.all() or not sup.any():
            continue
        x = np.arange(b0 - a0)
        new_r[a0:b0] = np.where(sup, new_r[a0:b0], np.interp(x, x[sup], new_r[a0:b0][sup]))
    out["radius"] = new_r
    shift = np.where(good[:, None], cx[:, None] * e1 + cy[:, None] * e2,
                     np.where(thin[:, None], mx[:, None] * e1 + my[:, None] * e2, 0.0))
    return (out, good, shift) if return_shift else (out, good)
