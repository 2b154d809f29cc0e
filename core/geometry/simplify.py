"""Skeleton simplification: pass-through nodes within a tolerance of the segment joining their parent and
their only child are dropped (:func:`simplify_skeleton`), every tree of a forest in one compiled loop
(:func:`simplify_skeletons`, :func:`simplify_forest`).
"""
from __future__ import annotations

import math
from typing import List

import numpy as np

from ..jit import njit
from ..skeleton import Skeleton
from .passes import check_skeleton, join_forest, localise_parents, trusted_skeleton


def simplify_skeleton(skeleton: Skeleton, tolerance_m: float = 0.05, max_passes: int = 8) -> Skeleton:
    """Drop pass-through nodes that lie within ``tolerance_m`` of the segment joining their
    parent and their only child (a Douglas–Peucker-like thinning of every chain).

    Branching nodes, tips and the root stay.  Each pass removes an independent set of
    nodes (no removed node's parent is removed in the same pass, alternating by depth
    parity), so the tolerance holds against the nodes kept; one compiled loop.
    Radii, when present, are carried by the kept nodes.
    """
    return simplify_skeletons([skeleton], tolerance_m, max_passes)[0]


def simplify_skeletons(skeletons, tolerance_m: float = 0.05, max_passes: int = 8) -> List[Skeleton]:
    """:func:`simplify_skeleton` of many skeletons, all passes in one compiled loop over all of them.

    Every tree keeps its own stopping rule (it stops when it has fewer than three nodes or a
    pass after the first drops nothing), so each result equals a call for that tree alone.
    """
    skeletons = [check_skeleton(sk) for sk in skeletons]
    if not skeletons:
        return []
    nodes, parent, off = join_forest(skeletons)
    radius = np.concatenate([sk.radius for sk in skeletons])
    added = np.concatenate([sk.is_added for sk in skeletons])
    nodes, parent, radius, added, off = simplify_forest(nodes, parent, radius, added, off, tolerance_m, max_passes)
    local = localise_parents(parent, off)
    bounds = off.tolist()
    return [trusted_skeleton(nodes[a:b], local[a:b], radius[a:b], added[a:b]) for a, b in zip(bounds[:-1], bounds[1:])]


def simplify_forest(nodes, parent, radius, added, off, tolerance_m: float, max_passes: int = 8):
    """:func:`simplify_skeletons` of a forest (see :func:`join_forest`): its kept nodes as a forest
    (nodes, parents, radii, added flags, node offsets)."""
    return _simplify_kernel(np.ascontiguousarray(nodes, dtype=np.float64), np.ascontiguousarray(parent, dtype=np.int64),
                            np.ascontiguousarray(radius, dtype=np.float64), np.ascontiguousarray(added, dtype=np.bool_),
                            np.asarray(off, dtype=np.int64), float(tolerance_m), int(max_passes))


@njit
def _simplify_kernel(nodes, parent, radius, added, off, tol, max_passes):
    """The passes of :func:`simplify_skeleton` over a forest, tree by tree; returns the kept nodes as a
    forest (nodes, parents, radii, added flags, node offsets).

    Pass ``k`` looks at the pass-through nodes (one child, a parent) of depth parity ``k % 2`` of the
    trees still active and drops those within ``tol`` of the segment parent -> child, the child
    taking the dropped node's parent (no dropped node is the parent or child of another, so the
    pass is independent of the order).  A tree stops when it has fewer than three nodes, or when a
    pass after the first finds candidates but drops none.  Sums are written out as 0 + x + y + z,
    the order of numpy's row sums.
    """
    m = parent.shape[0]
    alive = np.ones(m, np.bool_)
    par = parent.copy()
    kids = np.zeros(m, np.int64)
    only = np.full(m, -1, np.int64)
    depth = np.zeros(m, np.int64)
    drop = np.zeros(m, np.bool_)
    for t in range(off.shape[0] - 1):          # the trees are independent: one after the other
        a, b = off[t], off[t + 1]
        size = b - a
        for k in range(max_passes):
            if size < 3:
                break
            for i in range(a, b):
                kids[i] = 0
            for i in range(a, b):
                if alive[i]:
                    p = par[i]
                    if p >= 0:
                        kids[p] += 1
                        only[p] = i
                        depth[i] = depth[p] + 1
                    else:
                        depth[i] = 0
            tried = False
            n_drop = 0
            for i in range(a, b):
                drop[i] = False
                if not alive[i] or kids[i] != 1 or par[i] < 0 or depth[i] % 2 != k % 2:
                    continue
                p = par[i]
                c = only[i]
                sx = nodes[c, 0] - nodes[p, 0]
                sy = nodes[c, 1] - nodes[p, 1]
                sz = nodes[c, 2] - nodes[p, 2]
                length2 = sx * sx + sy * sy + sz * sz
                if length2 < 1e-18:
                    length2 = 1e-18
                u = (0.0 + (nodes[i, 0] - nodes[p, 0]) * sx + (nodes[i, 1] - nodes[p, 1]) * sy
                     + (nodes[i, 2] - nodes[p, 2]) * sz) / length2
                if u == u:                                 # np.clip(u, 0, 1); NaN stays NaN
                    if not u > 0.0:
                        u = 0.0
                    if not u < 1.0:
                        u = 1.0
                dx = nodes[i, 0] - (nodes[p, 0] + u * sx)
                dy = nodes[i, 1] - (nodes[p, 1] + u * sy)
                dz = nodes[i, 2] - (nodes[p, 2] + u * sz)
                tried = True
                if math.sqrt(dx * dx + dy * dy + dz * dz) <= tol:
                    drop[i] = True
                    n_drop += 1
            if n_drop == 0:
                if k >= 1 and tried:     # a pass after the first with candidates that drops nothing stops
                    break
                continue
            for i in range(a, b):
                if drop[i]:
                    par[only[i]] = par[i]
                    alive[i] = False
            size -= n_drop
    index = np.cumsum(alive) - 1
    mk = index[m - 1] + 1 if m else 0
    out_nodes = np.empty((mk, 3))
    out_parent = np.empty(mk, np.int64)
    out_radius = np.empty(mk)
    out_added = np.empty(mk, np.bool_)
    out_off = np.zeros(off.shape[0], np.int64)
    for t in range(off.shape[0] - 1):
        out_off[t + 1] = out_off[t]
        for i in range(off[t], off[t + 1]):
            if alive[i]:
                k = index[i]
                out_nodes[k, 0], out_nodes[k, 1], out_nodes[k, 2] = nodes[i, 0], nodes[i, 1], nodes[i, 2]
                out_parent[k] = index[par[i]] if par[i] >= 0 else -1
                out_radius[k] = radius[i]
                out_added[k] = added[i]
                out_off[t + 1] += 1
    return out_nodes, out_parent, out_radius, out_added, out_off
