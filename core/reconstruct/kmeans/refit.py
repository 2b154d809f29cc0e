"""Refits of the branch model to the points (Sylva, not in the papers).

With ``VariationalKMeans(refit=True)``: branches that stay within ``prune_factor`` radii of an earlier one
dropped, centre lines moved onto the axes of the refitted circles, the base of a branch inside its parent
given its first outside radius, the per-sample radii taken from the refitted cylinders, and the Sylva
:class:`~sylva.core.reconstruct.model.Skeleton` built from the branch vertex chains.  Each is measured by
``benchmarks/dense.py``.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..model import Skeleton
from .branches import BranchStructure
from .bspline import tube_ratio


def outside_earlier_branches(curves, radii, branch_parent, factor: float) -> np.ndarray:
    """Branches to keep after modelling (not in Yan et al.).

    A branch is dropped when every sample of its B-spline curve lies within
    ``factor`` radii (of the final model) of the centre line of an earlier
    branch (its ancestors, and the earlier branches it duplicates: at a fork
    on a thick stem the shortest-path tree of §3.2 often reaches the same limb
    through two or three parallel chains of clusters, each of which Algorithm
    3.1 makes a branch), unless it carries a kept branch.  As
    :func:`prune_branches`, on the fitted curves and radii; children are
    examined before parents.
    """
    nb = len(curves)
    bp = np.asarray(branch_parent, dtype=np.int64)
    keep = np.ones(nb, dtype=bool)
    has_kept_child = np.zeros(nb, dtype=bool)
    # all centre-line segments of all branches, with their branch, end points and radii
    sa, sb, ra, rb, sid = [], [], [], [], []
    for b, (c, r) in enumerate(zip(curves, radii)):
        c, r = np.asarray(c, dtype=np.float64).reshape(-1, 3), np.asarray(r, dtype=np.float64).reshape(-1)
        if len(c) >= 2:
            sa.append(c[:-1]), sb.append(c[1:]), ra.append(r[:-1]), rb.append(r[1:])
            sid.append(np.full(len(c) - 1, b))
        elif len(c) == 1:
            sa.append(c), sb.append(c), ra.append(r[:1]), rb.append(r[:1]), sid.append(np.full(1, b))
    if not sa:
        return keep
    sa, sb, ra, rb, sid = (np.concatenate(x) for x in (sa, sb, ra, rb, sid))
    ab = sb - sa
    ab2 = np.maximum((ab * ab).sum(axis=1), 1e-18)
    # candidates: the segments with the nearest mid-points of each sample (all branches)
    tree = cKDTree((sa + sb) / 2)
    kq = int(min(48, len(sa)))
    for b in range(nb - 1, 0, -1):
        if bp[b] < 0:
            continue
        if not has_kept_child[b]:
            pts = np.asarray(curves[b], dtype=np.float64).reshape(-1, 3)
            if len(pts):
                _, ci = tree.query(pts, k=kq)
                ci = ci.reshape(len(pts), kq)
                ok = (sid[ci] < b) & keep[sid[ci]]
                a0, v = sa[ci], ab[ci]
                t = np.clip(((pts[:, None] - a0) * v).sum(2) / ab2[ci], 0, 1)
                d = np.linalg.norm(pts[:, None] - (a0 + t[..., None] * v), axis=2)
                ratio = np.where(ok, d / np.maximum(ra[ci] + t * (rb[ci] - ra[ci]), 1e-6), np.inf)
                keep[b] = bool((ratio.min(axis=1) > factor).any())
        if keep[b]:
            has_kept_child[int(bp[b])] = True
    return keep


def keep_branches(st: BranchStructure, cyl: dict, keep: np.ndarray):
    """The branch structure and cylinder table restricted to the kept branches (renumbered;
    a kept branch's parent is always kept)."""
    new_id = np.cumsum(keep) - 1
    nb = len(keep)
    branches = [st.branches[b] for b in range(nb) if keep[b]]
    bpar = np.array([new_id[st.branch_parent[b]] if st.branch_parent[b] >= 0 else -1
                     for b in range(nb) if keep[b]], dtype=np.int64)
    st2 = BranchStructure(st.parent, st.root, st.junction, st.tip, st.centre, branches, bpar,
                          st.branch_order[keep], st.n_edges, st.bridged)
    rows = keep[cyl["branch"]]
    cid = np.full(len(rows), -1, dtype=np.int64)
    cid[rows] = np.arange(int(rows.sum()))
    out = {k: v[rows] for k, v in cyl.items()}
    out["id"] = np.arange(int(rows.sum()), dtype=np.int64)
    par = cyl["parent"][rows]
    out["parent"] = np.where(par >= 0, cid[np.maximum(par, 0)], -1)
    out["branch"] = new_id[cyl["branch"][rows]]
    return st2, out


def recentre(curves, cyl: dict, shift: np.ndarray, good: np.ndarray, branch_parent):
    """Move each branch's centre line onto the axes of its refitted circles (not in Yan et al.).

    A curve sample moves by the mean offset of the refitted cylinders on either
    side of it (:func:`sylva.core.qsm.refit_radii`); the first sample of a
    branch (its fork on the parent's centre line) stays.  The cylinders are
    rebuilt from the moved curves with their radii.  Branches whose cylinders
    do not match their samples one to one are left as they are.
    """
    from ...qsm import cylinders_from_curves
    new_curves, seg_r = [], []
    for b, c in enumerate(curves):
        idx = np.flatnonzero(cyl["branch"] == b)
        c = np.asarray(c, dtype=np.float64)
        if len(idx) != len(c) - 1 or len(idx) == 0:
            new_curves.append(c)
            seg_r.append(cyl["radius"][idx] if len(idx) == len(c) - 1 else
                         np.full(max(len(c) - 1, 0), cyl["radius"][idx].mean() if len(idx) else 0.0))
            continue
        sh, ok = shift[idx], good[idx].astype(float)
        num = np.zeros((len(c), 3))
        den = np.zeros(len(c))
        for off in (0, 1):      # cylinder i touches samples i and i + 1
            num[off:len(c) - 1 + off] += sh * ok[:, None]
            den[off:len(c) - 1 + off] += ok
        move = num / np.maximum(den, 1)[:, None]
        if branch_parent[b] >= 0:
            move[0] = 0.0
        new_curves.append(c + move)
        seg_r.append(cyl["radius"][idx])
    return new_curves, cylinders_from_curves(new_curves, seg_r, branch_parent, segment_radii=True)


def inside_parent_radii(cyl: dict, branch_parent) -> dict:
    """Cylinders at the base of a branch that lie inside the parent branch take the radius
    of the branch's first cylinder outside it (not in Yan et al.).

    A branch leaves from the parent's centre line (§4.1, the fork cluster's
    centre); the points nearest its first cylinders are the parent's bark, so
    their refitted radii are the parent's.  Inside = the mid-point within the
    parent's radius of the parent's centre line.
    """
    out = dict(cyl)
    r = np.asarray(cyl["radius"], dtype=np.float64).copy()
    br = cyl["branch"]
    mid = cyl["start"] + cyl["axis"] * (cyl["length"] / 2)[:, None]
    for b, pb in enumerate(np.asarray(branch_parent).tolist()):
        if pb < 0:
            continue
        idx = np.flatnonzero(br == b)
        pidx = np.flatnonzero(br == pb)
        if len(idx) < 2 or len(pidx) == 0:
            continue
        line = np.vstack([cyl["start"][pidx], cyl["start"][pidx[-1]] + cyl["axis"][pidx[-1]] * cyl["length"][pidx[-1]]])
        lr = np.r_[r[pidx], r[pidx[-1]]]
        inside = tube_ratio(mid[idx], line, lr) <= 1.0
        if not inside[0] or inside.all():
            continue
        first_out = int(np.argmin(inside))         # first cylinder outside the parent
        r[idx[:first_out]] = r[idx[first_out]]
    out["radius"] = r
    return out


def radii_from_cylinders(cyl: dict, curves, radii, verts, vrad):
    """Per-sample and per-vertex radii of each branch from its (refitted) cylinders:
    a sample between two cylinders gets their mean, an end sample its cylinder's,
    a skeleton vertex the radius of the branch's cylinder with the nearest mid-point."""
    new_r, new_v = [], []
    mid = cyl["start"] + cyl["axis"] * (cyl["length"] / 2)[:, None]
    for b, (c, r, v, rv) in enumerate(zip(curves, radii, verts, vrad)):
        idx = np.flatnonzero(cyl["branch"] == b)
        cr = cyl["radius"][idx]
        if len(idx) == 0:
            new_r.append(r)
            new_v.append(rv)
            continue
        if len(idx) == len(c) - 1:
            new_r.append(np.r_[cr[0], (cr[:-1] + cr[1:]) / 2, cr[-1]])
        else:
            new_r.append(r)
        dd = np.linalg.norm(np.asarray(v)[:, None, :] - mid[idx][None], axis=2)
        new_v.append(cr[np.argmin(dd, axis=1)])
    return new_r, new_v


def skeleton_from(st: BranchStructure, verts, vrad) -> Skeleton:
    """A Sylva Skeleton from the branch vertex chains (parents before children)."""
    nodes, parent, radius, added = [], [], [], []
    branch_nodes = []
    for bi, (v, rv) in enumerate(zip(verts, vrad)):
        ids = []
        if st.branch_parent[bi] < 0:
            start_parent = -1
            k0 = 0
        else:
            # attach to the nearest node of the parent branch (the fork cluster's centre)
            pb = branch_nodes[st.branch_parent[bi]]
            d = np.linalg.norm(np.asarray([nodes[i] for i in pb]) - v[0], axis=1)
            start_parent = pb[int(np.argmin(d))]
            k0 = 1
        prev = start_parent
        for j in range(k0, len(v)):
            nodes.append(v[j])
            parent.append(prev)
            radius.append(rv[j])
            added.append(j == 0 and st.branch_parent[bi] < 0 or j == len(v) - 1)
            prev = len(nodes) - 1
            ids.append(prev)
        if st.branch_parent[bi] >= 0 and not ids:
            ids = [start_parent]
        branch_nodes.append(([start_parent] if start_parent >= 0 else []) + ids)
    return Skeleton(np.asarray(nodes), np.asarray(parent), np.asarray(radius), np.asarray(added))
