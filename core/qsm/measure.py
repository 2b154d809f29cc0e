"""Branch tables and tree measurements of a QSM (TreeQSM's branch data and treedata; DBH as the
module docstring of :mod:`sylva.core.qsm` says), one tree or a forest of skeletons at once."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np

from ..errors import InputError
from ..measure import DbhRule, fit_stem_circle
from .cylinders import branch_depth, cylinders_from_curves

__all__ = ["BRANCH_FIELDS", "branch_table_arrays", "QSM", "measure_qsm", "skeleton_qsms"]

BRANCH_FIELDS = ("id", "parent", "order", "n_cylinders", "length", "base_diameter", "volume",
                 "angle_deg", "base_height")


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
    order = branch_depth(bp)
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
    from ..geometry import norm3

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
