"""Quantitative structure models (QSM): cylinder and branch tables and tree measurements.

The output follows TreeQSM (Raumonen et al. 2013, Remote Sens. 5, 491–520):
a tree is a list of cylinders, each with its parent cylinder, its branch
and branch order, start point, unit axis, length and radius; branches are
runs of cylinders; per tree a DBH, height, trunk and total wood volume and
branch counts by order.  Sylva builds the cylinders from the sampled
B-spline centre lines of Yan et al. 2009 §4 (:mod:`.reconstruct.kmeans`),
but :func:`cylinders_from_curves` takes any list of centre lines + radii, and
:func:`cylinders_from_skeleton` any skeleton with radii (one cylinder per edge).
:func:`refit_radii` fits each cylinder's radius and axis offset to the points
nearest it, :func:`taper_radii` keeps branches no thicker than their parent,
:func:`surface_distance` measures points against a model.

DBH (:func:`measure_qsm`): the points within ``band_m`` of 1.3 m above the
stem base and within 2 stem radii (+5 cm) of the stem axis there are fitted
with a circle (:func:`sylva.core.measure.fit_stem_circle`; up to three
passes dropping points more than 2 RMS, at least 1 cm, off it) under the
:class:`~sylva.core.measure.DbhRule` acceptance tests; ``dbh_source`` is then
``"measured"``, else the stem cylinder's diameter at 1.3 m is used
(``"cylinder"``).  Volumes are sums of ``π r² L``.

Tables are :class:`~sylva.core.table.VectorTable` (cylinders as 3-D lines
from start to end, or without geometry) and CSV files written atomically.
"""
from __future__ import annotations

import csv
import io
from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np
from scipy.spatial import cKDTree

from .atomic import atomic_open
from .errors import InputError
from .circles import arc_sectors, fit_circles
from .measure import DbhRule, fit_stem_circle
from .table import VectorTable

__all__ = ["QSM", "cylinders_from_curves", "cylinders_from_skeleton", "branch_table_arrays", "measure_qsm",
           "cylinders_table", "branches_table", "trees_table", "write_cylinders_csv",
           "write_branches_csv", "write_trees_csv", "write_table_csv", "surface_distance", "refit_radii",
           "taper_radii", "CYLINDER_FIELDS", "BRANCH_FIELDS"]

CYLINDER_FIELDS = ("id", "parent", "branch", "order", "start_x", "start_y", "start_z",
                   "axis_x", "axis_y", "axis_z", "length", "radius")
BRANCH_FIELDS = ("id", "parent", "order", "n_cylinders", "length", "base_diameter", "volume",
                 "angle_deg", "base_height")


def cylinders_from_curves(curves: Sequence[np.ndarray], radii: Sequence[np.ndarray],
                          branch_parent: Sequence[int], branch_order: Optional[Sequence[int]] = None,
                          segment_radii: bool = False) -> dict:
    """A TreeQSM-like cylinder table from one sampled centre line + radii per branch.

    Consecutive samples of branch ``b`` become cylinders of branch ``b`` (radius
    the mean of the two end radii, or, with ``segment_radii``, ``radii[b]`` holds
    one radius per segment, ``len(curve) - 1``); a cylinder's parent is the previous
    cylinder of its branch, and the first cylinder of a branch has as parent
    the cylinder of its parent branch nearest its start (-1 for the trunk).
    ``branch_order`` defaults to the depth of the branch in ``branch_parent``.
    Returns a dict of arrays keyed by :data:`CYLINDER_FIELDS` names plus
    ``start`` (n, 3) and ``axis`` (n, 3).
    """
    bp = np.asarray(branch_parent, dtype=np.int64).reshape(-1)
    nb = len(curves)
    if branch_order is None:
        order = np.zeros(nb, dtype=np.int64)
        for b in range(nb):
            if bp[b] >= 0:
                order[b] = order[bp[b]] + 1
    else:
        order = np.asarray(branch_order, dtype=np.int64)
    starts, axes, lens, rads, bids, pars = [], [], [], [], [], []
    first_of = np.full(nb, -1, dtype=np.int64)
    mids = {}
    offset = 0
    for b, (pts, r) in enumerate(zip(curves, radii)):
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
        r = np.asarray(r, dtype=np.float64).reshape(-1)
        if len(pts) < 2:
            continue
        vec = np.diff(pts, axis=0)
        L = np.linalg.norm(vec, axis=1)
        ok = L > 1e-9
        if not ok.any():
            continue
        s, v, L = pts[:-1][ok], vec[ok], L[ok]
        rr = (r[:len(L)] if segment_radii else (r[:-1] + r[1:]) / 2)[ok]
        m = len(L)
        par = offset + np.arange(m) - 1
        if bp[b] >= 0 and first_of[bp[b]] >= 0:
            pids, pmid = mids[int(bp[b])]      # the parent branch's cylinders only
            par[0] = pids[int(np.argmin(np.linalg.norm(pmid - s[0], axis=1)))]
        else:
            par[0] = -1
        mids[b] = (offset + np.arange(m), s + v / 2)
        first_of[b] = offset
        starts.append(s)
        axes.append(v / L[:, None])
        lens.append(L)
        rads.append(rr)
        bids.append(np.full(m, b, dtype=np.int64))
        pars.append(par)
        offset += m
    if not starts:
        z3 = np.zeros((0, 3))
        zi = np.zeros(0, dtype=np.int64)
        zf = np.zeros(0)
        return dict(id=zi, parent=zi, branch=zi, order=zi, start=z3, axis=z3, length=zf, radius=zf)
    start = np.concatenate(starts)
    branch = np.concatenate(bids)
    return dict(id=np.arange(len(start), dtype=np.int64), parent=np.concatenate(pars).astype(np.int64),
                branch=branch, order=order[branch], start=start, axis=np.concatenate(axes),
                length=np.concatenate(lens), radius=np.concatenate(rads))


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
    from .geometry import branches

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


def _group_median(values: np.ndarray, groups: np.ndarray, n: int) -> np.ndarray:
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
    med = _group_median(rho_all[near], jn, n)
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


def _branch_depth(bp: np.ndarray) -> np.ndarray:
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


def branch_table_arrays(cyl: dict, branch_parent: Sequence[int]) -> dict:
    """Per-branch columns from a cylinder table (see :data:`BRANCH_FIELDS`).

    ``base_diameter`` twice the radius of the branch's first cylinder;
    ``angle_deg`` between the first cylinder and its parent cylinder (0 for
    the trunk); ``base_height`` z of the branch start.
    """
    bp = np.asarray(branch_parent, dtype=np.int64).reshape(-1)
    nb = len(bp)
    br = cyl["branch"]
    ncyl = np.bincount(br, minlength=nb)
    length = np.bincount(br, weights=cyl["length"], minlength=nb)
    vol = np.bincount(br, weights=np.pi * cyl["radius"] ** 2 * cyl["length"], minlength=nb)
    first = np.full(nb, -1, dtype=np.int64)
    if len(br):
        idx = np.arange(len(br))[::-1]
        first[br[idx]] = idx              # smallest index wins (written last)
    has = first >= 0
    base_d = np.zeros(nb)
    base_d[has] = 2 * cyl["radius"][first[has]]
    base_h = np.full(nb, np.nan)
    base_h[has] = cyl["start"][first[has], 2]
    angle = np.zeros(nb)
    b = np.flatnonzero(has)
    p = cyl["parent"][first[b]]
    b, fc, p = b[p >= 0], first[b][p >= 0], p[p >= 0]
    if len(b):
        ax = np.asarray(cyl["axis"], dtype=np.float64)
        c = np.matmul(ax[fc][:, None, :], ax[p][:, :, None])[:, 0, 0]
        angle[b] = np.degrees(np.arccos(np.clip(c, -1, 1)))
    order = _branch_depth(bp)
    return dict(id=np.arange(nb, dtype=np.int64), parent=bp, order=order, n_cylinders=ncyl.astype(np.int64),
                length=length, base_diameter=base_d, volume=vol, angle_deg=angle, base_height=base_h)


@dataclass
class QSM:
    """A TreeQSM-like model of one tree.

    ``cylinders`` dict of arrays (:data:`CYLINDER_FIELDS`, plus ``start`` /
    ``axis`` (n, 3)); ``branches`` dict of arrays (:data:`BRANCH_FIELDS`);
    tree measurements: ``dbh_m`` and ``dbh_source`` (``"measured"`` circle
    fit / ``"cylinder"`` stem cylinder), ``height_m`` (top of points or model
    above the stem base), ``base_z``, ``trunk_volume_m3``, ``total_volume_m3``,
    ``branch_counts`` {order: count} (order >= 1).
    """

    tree_id: int
    cylinders: dict
    branches: dict
    dbh_m: float
    dbh_source: str
    height_m: float
    base_z: float
    trunk_volume_m3: float
    total_volume_m3: float
    branch_counts: dict = field(default_factory=dict)

    def summary(self) -> dict:
        out = dict(tree_id=self.tree_id, dbh_m=self.dbh_m, dbh_source=self.dbh_source, height_m=self.height_m,
                   trunk_volume_m3=self.trunk_volume_m3, total_volume_m3=self.total_volume_m3,
                   n_cylinders=int(len(self.cylinders["id"])), n_branches=int(len(self.branches["id"])))
        for o, c in sorted(self.branch_counts.items()):
            out[f"branches_order{o}"] = int(c)
        return out


def _stem_at(cyl: dict, z: float):
    """Trunk (branch 0) cylinder spanning height z (nearest in z if none spans it)."""
    stem = np.flatnonzero(cyl["branch"] == 0)
    if len(stem) == 0:
        return None
    s = cyl["start"][stem]
    e = s + cyl["axis"][stem] * cyl["length"][stem, None]
    lo, hi = np.minimum(s[:, 2], e[:, 2]), np.maximum(s[:, 2], e[:, 2])
    gap = np.maximum(lo - z, 0) + np.maximum(z - hi, 0)
    i = stem[int(np.argmin(gap))]
    return i


def measure_qsm(cyl: dict, branch_parent: Sequence[int], xyz: Optional[np.ndarray] = None,
                base_z: Optional[float] = None, tree_id: int = -1, rule: DbhRule = DbhRule()) -> QSM:
    """Tree measurements of a cylinder model (TreeQSM's treedata), see the module docstring.

    ``xyz`` the tree's points (metres, z up) for the measured DBH and height;
    ``base_z`` the stem base height (default: lowest point of the stem
    cylinders or of the points).
    """
    if not isinstance(cyl, dict) or "radius" not in cyl:
        raise InputError(f"tree {tree_id}: measure_qsm needs a cylinder table (dict of arrays)")
    br = branch_table_arrays(cyl, branch_parent)
    n = len(cyl["radius"])
    vol = np.pi * cyl["radius"] ** 2 * cyl["length"]
    stem = cyl["branch"] == 0
    ends = cyl["start"] + cyl["axis"] * cyl["length"][:, None] if n else np.zeros((0, 3))
    zs = [cyl["start"][stem, 2], ends[stem, 2]] if n else []
    if base_z is None:
        cand = [np.min(z) for z in zs if len(z)]
        if xyz is not None and len(xyz):
            cand.append(float(np.min(xyz[:, 2])))
        base_z = float(min(cand)) if cand else 0.0
    top = [float(ends[:, 2].max()), float(cyl["start"][:, 2].max())] if n else []
    if xyz is not None and len(xyz):
        top.append(float(np.max(xyz[:, 2])))
    height = (max(top) - base_z) if top else 0.0
    dbh, source = float("nan"), "none"
    zb = base_z + rule.breast_height_m
    i = _stem_at(cyl, zb) if n else None
    if i is not None:
        r_cyl = float(cyl["radius"][i])
        dbh, source = 2 * r_cyl, "cylinder"
        if xyz is not None and len(xyz):
            a = cyl["axis"][i]
            s = cyl["start"][i]
            t = (zb - s[2]) / a[2] if abs(a[2]) > 1e-6 else 0.0
            c = s + a * t
            band = np.abs(xyz[:, 2] - zb) <= rule.band_m
            near = band & (np.linalg.norm(xyz[:, :2] - c[:2], axis=1) <= 2 * r_cyl + 0.05)
            if near.sum() >= rule.min_points:
                xy = xyz[near, :2]
                circ = fit_stem_circle(xy)
                for _ in range(3):      # trim twigs and noise: points off the circle by > 2 rms (>= 1 cm)
                    if circ is None:
                        break
                    off = np.abs(np.hypot(xy[:, 0] - circ.x, xy[:, 1] - circ.y) - circ.radius)
                    keep = off <= max(2.0 * circ.rms, 0.01)
                    if keep.all() or keep.sum() < rule.min_points:
                        break
                    xy = xy[keep]
                    circ = fit_stem_circle(xy)
                if (circ is not None and circ.arc_deg >= rule.min_arc_deg and circ.rms <= rule.max_rms_m
                        and 0.01 <= circ.radius <= rule.max_radius_m):
                    dbh, source = 2 * circ.radius, "measured"
    orders, counts = np.unique(br["order"][br["order"] >= 1], return_counts=True)
    return QSM(tree_id, cyl, br, float(dbh), source, float(height), float(base_z),
               float(vol[stem].sum()) if n else 0.0, float(vol.sum()) if n else 0.0,
               {int(o): int(c) for o, c in zip(orders, counts)})


def skeleton_qsms(nodes: np.ndarray, parent: np.ndarray, radius: np.ndarray, branch_set, node_off: np.ndarray,
                  branch_off: np.ndarray, tree_ids, base_z, top_z, dbh_m, dbh_source) -> list:
    """The QSM of every tree of a forest of skeletons with radii, all trees in one vectorised pass.

    The forest is the trees' skeletons joined (``nodes``, ``parent`` with global indices, ``radius``;
    tree ``t`` owns nodes ``node_off[t]:node_off[t + 1]``), ``branch_set`` its
    :func:`~sylva.core.geometry.branches` (tree ``t`` owns chains ``branch_off[t]:branch_off[t + 1]``).
    Tree ``t`` gets ``measure_qsm(*cylinders_from_skeleton(skeleton, branch_set=bs), xyz,
    base_z=base_z[t], tree_id=tree_ids[t])`` with ``top_z[t]`` the highest of its points ``xyz``,
    except that its DBH is ``dbh_m[t]`` / ``dbh_source[t]`` (the caller's measurement, so no circle
    is fitted here).  Per-tree sums are numpy sums over each tree's slice, so every value is the
    one of the per-tree functions, bit for bit (Sylva, not in the paper).
    """
    from .geometry import norm3

    bs = branch_set
    node_off = np.asarray(node_off, dtype=np.int64)
    nt = len(node_off) - 1
    sizes = np.diff(node_off)
    tree_of_node = np.repeat(np.arange(nt), sizes)
    # one cylinder per non-root node, grouped by branch, by node within a branch: the chains without
    # their first entry (the attachment node, or the root for a trunk)
    own = np.ones(len(bs.nodes), dtype=bool)
    own[bs.offsets[:-1][np.diff(bs.offsets) > 0]] = False
    node = bs.nodes[own]
    par = parent[node]
    ctree = tree_of_node[node]
    c_off = np.r_[0, np.cumsum(np.bincount(ctree, minlength=nt))]
    cyl_of = np.full(len(parent), -1, dtype=np.int64)
    cyl_of[node] = np.arange(len(node))
    pcyl = cyl_of[par]
    start = nodes[par]
    vec = nodes[node] - start
    length = norm3(vec)
    axis = np.where(length[:, None] > 1e-12, vec / np.maximum(length, 1e-12)[:, None], np.array([0, 0, 1.0]))
    branch = bs.node_branch[node]
    rad = radius[node]
    local_id = np.arange(len(node)) - c_off[:-1][ctree]
    local_parent = np.where(pcyl >= 0, pcyl - c_off[:-1][ctree], -1)
    local_branch = branch - branch_off[:-1][ctree]
    cyl_order = bs.order[branch]
    # branch table (branch_table_arrays): bincounts over the forest's chains
    nbr = len(bs)
    ncyl = np.bincount(branch, minlength=nbr)
    vol = np.pi * rad ** 2 * length
    b_len = np.bincount(branch, weights=length, minlength=nbr)
    b_vol = np.bincount(branch, weights=vol, minlength=nbr)
    has = ncyl > 0
    first = np.r_[0, np.cumsum(ncyl)][:-1]
    base_d = np.zeros(nbr)
    base_d[has] = 2 * rad[first[has]]
    base_h = np.full(nbr, np.nan)
    base_h[has] = start[first[has], 2]
    angle = np.zeros(nbr)
    b = np.flatnonzero(has)
    p = pcyl[first[b]]
    b, fc, p = b[p >= 0], first[b][p >= 0], p[p >= 0]
    if len(b):
        c = np.matmul(axis[fc][:, None, :], axis[p][:, :, None])[:, 0, 0]
        angle[b] = np.degrees(np.arccos(np.clip(c, -1, 1)))
    tree_of_branch = np.repeat(np.arange(nt), np.diff(branch_off))
    b_id = np.arange(nbr) - branch_off[:-1][tree_of_branch]
    b_parent = np.where(bs.parent >= 0, bs.parent - branch_off[:-1][tree_of_branch], -1)
    counted = bs.order >= 1
    n_orders = int(bs.order.max()) + 1 if nbr else 1
    by_order = np.bincount(tree_of_branch[counted] * n_orders + bs.order[counted],
                           minlength=nt * n_orders).reshape(nt, n_orders)
    n_stem = np.bincount(ctree[local_branch == 0], minlength=nt)
    end_z = start[:, 2] + axis[:, 2] * length
    co, bo = c_off.tolist(), np.asarray(branch_off).tolist()
    ns, sz = n_stem.tolist(), sizes.tolist()
    empty = cylinders_from_curves([], [], [])
    out = []
    for t in range(nt):
        c0, c1, b0, b1 = co[t], co[t + 1], bo[t], bo[t + 1]
        tops = [float(top_z[t])]
        if c1 > c0:
            tops = [float(end_z[c0:c1].max()), float(start[c0:c1, 2].max())] + tops
            cyl = dict(id=local_id[c0:c1], parent=local_parent[c0:c1], branch=local_branch[c0:c1],
                       order=cyl_order[c0:c1], start=start[c0:c1], axis=axis[c0:c1], length=length[c0:c1],
                       radius=rad[c0:c1])
            trunk, total = float(vol[c0:c0 + ns[t]].sum()), float(vol[c0:c1].sum())
        else:
            cyl, trunk, total = dict(empty), 0.0, 0.0
        if sz[t] >= 2:
            br = dict(id=b_id[b0:b1], parent=b_parent[b0:b1], order=bs.order[b0:b1], n_cylinders=ncyl[b0:b1],
                      length=b_len[b0:b1], base_diameter=base_d[b0:b1], volume=b_vol[b0:b1],
                      angle_deg=angle[b0:b1], base_height=base_h[b0:b1])
            counts = {o: int(k) for o, k in enumerate(by_order[t].tolist()) if k}
        else:           # a lone root: no cylinder, no branch (cylinders_from_skeleton's empty table)
            br, counts = branch_table_arrays(cyl, np.zeros(0, dtype=np.int64)), {}
        out.append(QSM(int(tree_ids[t]), cyl, br, float(dbh_m[t]), dbh_source[t], float(max(tops) - base_z[t]),
                       float(base_z[t]), trunk, total, counts))
    return out


# --------------------------------------------------------------------------- tables

def _cyl_columns(q: QSM) -> dict:
    c = q.cylinders
    n = len(c["id"])
    return {"tree_id": np.full(n, q.tree_id, dtype=np.int64), "id": c["id"], "parent": c["parent"],
            "branch": c["branch"], "order": c["order"],
            "start_x": c["start"][:, 0], "start_y": c["start"][:, 1], "start_z": c["start"][:, 2],
            "axis_x": c["axis"][:, 0], "axis_y": c["axis"][:, 1], "axis_z": c["axis"][:, 2],
            "length": c["length"], "radius": c["radius"]}


def cylinders_table(qsms, crs=None, geometry: bool = True, origin=(0.0, 0.0, 0.0)) -> VectorTable:
    """Cylinders of one or more QSMs as a VectorTable: 3-D lines start -> end (``geometry``)
    or a no-geometry table.  ``origin`` is added to the local coordinates of the lines."""
    from shapely import linestrings
    qs = [qsms] if isinstance(qsms, QSM) else list(qsms)
    cols = [_cyl_columns(q) for q in qs]
    names = cols[0].keys() if cols else _cyl_columns(QSM(-1, cylinders_from_curves([], [], []),
                                                         branch_table_arrays(cylinders_from_curves([], [], []), []),
                                                         0, "none", 0, 0, 0, 0)).keys()
    merged = {k: np.concatenate([c[k] for c in cols]) if cols else np.zeros(0) for k in names}
    if not geometry:
        return VectorTable("cylinders", "none", None, merged, crs)
    o = np.asarray(origin, dtype=float)
    s = np.stack([merged["start_x"], merged["start_y"], merged["start_z"]], axis=1).reshape(-1, 3) + o
    a = np.stack([merged["axis_x"], merged["axis_y"], merged["axis_z"]], axis=1).reshape(-1, 3)
    e = s + a * np.asarray(merged["length"]).reshape(-1, 1)
    geoms = linestrings(np.stack([s, e], axis=1)) if len(s) else np.zeros(0, dtype=object)
    return VectorTable("cylinders", "line", np.asarray(geoms, dtype=object), merged, crs)


def branches_table(qsms, crs=None) -> VectorTable:
    """Branches of one or more QSMs as a no-geometry VectorTable (:data:`BRANCH_FIELDS` + tree_id)."""
    qs = [qsms] if isinstance(qsms, QSM) else list(qsms)
    cols = []
    for q in qs:
        b = dict(q.branches)
        cols.append({"tree_id": np.full(len(b["id"]), q.tree_id, dtype=np.int64), **b})
    keys = ("tree_id",) + BRANCH_FIELDS
    merged = {k: np.concatenate([c[k] for c in cols]) if cols else np.zeros(0) for k in keys}
    return VectorTable("branches", "none", None, merged, crs)


def trees_table(qsms, crs=None) -> VectorTable:
    """One row per QSM with the tree measurements (no geometry)."""
    qs = [qsms] if isinstance(qsms, QSM) else list(qsms)
    max_o = max([max(q.branch_counts, default=0) for q in qs], default=0)
    cols = {
        "tree_id": np.array([q.tree_id for q in qs], dtype=np.int64),
        "dbh_m": np.array([q.dbh_m for q in qs], dtype=float),
        "dbh_source": np.array([q.dbh_source for q in qs], dtype=object),
        "height_m": np.array([q.height_m for q in qs], dtype=float),
        "trunk_volume_m3": np.array([q.trunk_volume_m3 for q in qs], dtype=float),
        "total_volume_m3": np.array([q.total_volume_m3 for q in qs], dtype=float),
        "n_cylinders": np.array([len(q.cylinders["id"]) for q in qs], dtype=np.int64),
    }
    for o in range(1, max_o + 1):
        cols[f"branches_order{o}"] = np.array([q.branch_counts.get(o, 0) for q in qs], dtype=np.int64)
    return VectorTable("trees", "none", None, cols, crs)


def _write_csv(path, table: VectorTable) -> None:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    names = list(table.columns)
    w.writerow(names)
    kinds = table.field_types()
    cols = [np.asarray(table.columns[k]) for k in names]
    for i in range(len(table)):
        row = []
        for k, c in zip(names, cols):
            v = c[i]
            if kinds[k] == "real":
                row.append("" if not np.isfinite(v) else repr(float(v)))
            elif kinds[k] == "integer":
                row.append(int(v))
            else:
                row.append("" if v is None else str(v))
        w.writerow(row)
    with atomic_open(path, "w") as fh:
        fh.write(buf.getvalue())


def write_table_csv(path, table: VectorTable) -> None:
    """Any no-geometry columns of a VectorTable as CSV (header = column names), written atomically."""
    _write_csv(path, table)


def write_cylinders_csv(path, qsms) -> None:
    """Cylinder table as CSV (tree_id + :data:`CYLINDER_FIELDS`), written atomically."""
    _write_csv(path, cylinders_table(qsms, geometry=False))


def write_branches_csv(path, qsms) -> None:
    """Branch table as CSV (tree_id + :data:`BRANCH_FIELDS`), written atomically."""
    _write_csv(path, branches_table(qsms))


def write_trees_csv(path, qsms) -> None:
    """Tree measurements as CSV, written atomically."""
    _write_csv(path, trees_table(qsms))


# --------------------------------------------------------------------------- synthetic truth

def cylinder_tree(segments: Sequence[dict]) -> dict:
    """A cylinder table from branch specs, for validation with known truth.

    Each spec: ``{"start": (3,), "direction": (3,), "length": m, "radius": (r0, r1),
    "parent": branch index or -1, "n": cylinders}``; a branch is ``n`` equal
    cylinders whose radius tapers linearly from r0 to r1.
    """
    curves, radii, parents = [], [], []
    for s in segments:
        d = np.asarray(s["direction"], float)
        d = d / np.linalg.norm(d)
        n = int(s.get("n", 4))
        t = np.linspace(0, s["length"], n + 1)
        curves.append(np.asarray(s["start"], float) + t[:, None] * d)
        r0, r1 = s["radius"]
        rr = np.linspace(r0, r1, n + 1)
        radii.append(rr)
        parents.append(int(s.get("parent", -1)))
    cyl = cylinders_from_curves(curves, radii, parents)
    # exact per-cylinder radii: midpoint of the taper (the mean of end radii)
    return cyl


def sample_cylinder_surfaces(cyl: dict, spacing_m: float = 0.01, noise_m: float = 0.0, seed: int = 0,
                             visible=None) -> np.ndarray:
    """Points on the lateral surfaces of the cylinders, ~one per ``spacing_m``² of area,
    with Gaussian radial noise ``noise_m``.  ``visible`` optional (3,) horizontal view
    direction: only the half of each cylinder facing it is kept (a one-sided scan)."""
    rng = np.random.default_rng(seed)
    area = 2 * np.pi * cyl["radius"] * cyl["length"]
    n_each = np.maximum(1, np.round(area / spacing_m ** 2)).astype(np.int64)
    idx = np.repeat(np.arange(len(area)), n_each)
    a = cyl["axis"][idx]
    helper = np.where(np.abs(a[:, 2:3]) < 0.9, np.array([0, 0, 1.0]), np.array([1.0, 0, 0]))
    u = np.cross(a, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(a, u)
    th = rng.uniform(0, 2 * np.pi, len(idx))
    t = rng.uniform(0, 1, len(idx)) * cyl["length"][idx]
    r = cyl["radius"][idx] + rng.normal(0, noise_m, len(idx)) if noise_m > 0 else cyl["radius"][idx]
    nrm = np.cos(th)[:, None] * u + np.sin(th)[:, None] * v
    pts = cyl["start"][idx] + t[:, None] * a + r[:, None] * nrm
    if visible is not None:
        vd = np.asarray(visible, float)
        pts = pts[(nrm @ vd) < 0]
    return pts
