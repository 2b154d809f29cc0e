"""The 3D main branches by depth retrieval: the sketch paper §5 (Eq. 1-6), branch extension (§5.2) and
branch complementarity (§5.3).

:func:`depth_retrieval` matches every branch of the front view's 2D skeleton with a branch of the side
view's (Eq. 1, 3) and takes each point's depth from it at the same height; the side view's unused parts
are built the same way with the roles swapped.
"""
from __future__ import annotations

from typing import List, Optional

import numpy as np

from ...progress import Progress, report
from .strokes import StrokeGraph, View, skeleton_2d


# --------------------------------------------------------------------------- §5 depth retrieval

class _Builder:
    """3D nodes being built: (u, v, height) with u the front and v the side horizontal axis."""

    def __init__(self, n_a: int, n_b: int):
        self.nodes: List[np.ndarray] = []
        self.parent: List[int] = []
        self.map = [np.full(n_a, -1, dtype=np.int64), np.full(n_b, -1, dtype=np.int64)]

    def add(self, p, parent: int) -> int:
        self.nodes.append(np.asarray(p, dtype=np.float64))
        self.parent.append(int(parent))
        return len(self.nodes) - 1

    def ancestors(self, i: int) -> set:
        out = set()
        while i >= 0:
            out.add(i)
            i = self.parent[i]
        return out


def _match(view: View, V: float, m_target: float, near: Optional[float] = None, tol: float = 0.0,
           strict: bool = False) -> int:
    """Eq. 1 + 3: the branch passing height V with the closest maximum extension height (-1: none).

    With ``near`` (Sylva, for continuity): only branches that pass height V within ``tol`` of the
    horizontal position ``near`` compete, when there are any (with ``strict``: -1 when there are none)."""
    ok = (view.hmin <= V + 1e-12) & (view.hmax >= V - 1e-12)
    cand = np.flatnonzero(ok)
    if len(cand) == 0:
        return -1
    if near is not None and (len(cand) > 1 or strict):
        close = np.array([abs(_at_height(view.nodes[view.chains[c]], V)[0] - near) <= tol for c in cand])
        if close.any():
            cand = cand[close]
        elif strict:
            return -1
    f = np.abs(view.mext[cand] - m_target)
    return int(cand[np.argmin(f)])  # ties: the lower branch index (closer to the trunk)


def _at_height(pts: np.ndarray, V: float, start: int = 0):
    """(horizontal value, segment index) where the polyline ``pts`` first reaches height V at or after
    segment ``start``; the nearest vertex in height when it never does."""
    y = pts[:, 1]
    if len(pts) == 1:
        return float(pts[0, 0]), 0
    lo = np.minimum(y[:-1], y[1:])
    hi = np.maximum(y[:-1], y[1:])
    segs = np.flatnonzero((lo <= V) & (hi >= V))
    if len(segs):
        after = segs[segs >= start]
        j = int(after[0]) if len(after) else int(segs[-1])
        dy = y[j + 1] - y[j]
        t = 0.5 if dy == 0 else (V - y[j]) / dy
        return float(pts[j, 0] + t * (pts[j + 1, 0] - pts[j, 0])), j
    j = int(np.argmin(np.abs(y - V)))
    return float(pts[j, 0]), min(j, len(pts) - 2)


def _descending(view: View, node: int) -> List[int]:
    """Descending path p(λ) from ``node`` to the root (node indices, node first)."""
    out = []
    while node >= 0:
        out.append(node)
        node = int(view.parent[node])
    return out


def _construct(a: View, b: View, pieces, builder: _Builder, ia: int, ib: int, tol: float, extend: bool = True):
    """Depth retrieval of ``pieces`` of view ``a`` against view ``b`` (§5.1–§5.2).

    ``ia``/``ib`` are the coordinate slots (0 = u, 1 = v) the two views give.
    Each piece is (branch index in a, node indices of a from the bud node on).
    ``extend`` False skips §5.2 (the complementary pass: its runs hang from
    nodes already built, and extending them would duplicate built paths); the
    run's first match then prefers branches of ``b`` passing within ``tol`` of
    the node it hangs from, and so do the re-matches of §5.1 rule 3 (of the
    current depth): Sylva's choice, so that the 3D branch does not jump when a
    continuing branch exists; Eq. 1 decides among them.  A complementary run
    with no branch of ``b`` near keeps the depth of the node it hangs from
    (the part was drawn on one view only: it stays in that view's plane
    through its fork instead of jumping to an unrelated branch).
    """
    amap, bmap = builder.map[ia], builder.map[ib]
    for lam, idx in pieces:
        bud = int(idx[0])
        bud3 = int(amap[bud])
        ya = a.nodes[idx, 1]
        V = float(ya[0])
        near = None if (extend or bud3 < 0) else float(builder.nodes[bud3][ib])
        mu = _match(b, V, float(a.mext[lam]), near, tol, strict=not extend)
        start_k = 1
        hold = None
        if mu < 0 and not extend:
            hold, mu = near, _match(b, V, float(a.mext[lam]))
        if mu < 0:
            mu = int(np.argmin(np.minimum(np.abs(b.hmin - V), np.abs(b.hmax - V))))
        mpts = b.nodes[b.chains[mu]]
        _, seg = _at_height(mpts, V)
        # §5.2 branch extension: is P_b on b's available descending path?
        if bud3 >= 0 and extend:
            anc = builder.ancestors(bud3)
            pb_nodes = (b.chains[mu][seg], b.chains[mu][min(seg + 1, len(mpts) - 1)])
            on_path = any(bmap[q] in anc for q in pb_nodes)
            if not on_path:
                # walk μ's descending path down from P_b to the highest node used by the bud's ancestors
                path = _descending(b, int(b.chains[mu][seg]))
                hit = next((q for q in path if bmap[q] in anc), None)
                if hit is not None:
                    attach3 = int(bmap[hit])
                    y_star = float(b.nodes[hit, 1])
                    # a's descending path from the bud down to y*: the 3D ancestors between attach3 and bud3
                    chain3 = []
                    i = bud3
                    while i >= 0 and i != attach3:
                        chain3.append(i)
                        i = builder.parent[i]
                    if i == attach3:
                        top = b.chains[mu][min(seg + 1, len(mpts) - 1)]   # P_b lies below this node
                        bpath = np.vstack([b.nodes[path[:path.index(hit) + 1]][::-1], b.nodes[top]])
                        prev = attach3
                        made, heights = [], []
                        for n3 in chain3[::-1]:
                            p3 = builder.nodes[n3]
                            if p3[2] < y_star:
                                continue
                            depth, _ = _at_height(bpath, float(p3[2]))
                            q = np.empty(3)
                            q[ia], q[ib], q[2] = p3[ia], depth, p3[2]
                            prev = builder.add(q, prev)
                            made.append(prev)
                            heights.append(p3[2])
                        if made:  # the side-view path of the extension is used now
                            heights = np.asarray(heights)
                            for q in path[:path.index(hit)]:
                                if bmap[q] < 0:
                                    bmap[q] = made[int(np.argmin(np.abs(heights - b.nodes[q, 1])))]
                        bud3 = prev
        if bud3 < 0:  # the trunk: the root pairs with the side view's base
            q = np.zeros(3)
            q[ia], q[ib], q[2] = a.nodes[bud, 0], b.nodes[0, 0], a.nodes[bud, 1]
            bud3 = builder.add(q, -1)
            amap[bud] = bud3
            if bmap[0] < 0:
                bmap[0] = bud3
            start_k = 1
        prev = bud3
        pos = seg
        for k in range(start_k, len(idx)):
            y = float(ya[k])
            if hold is None and not (b.hmin[mu] - 1e-12 <= y <= b.hmax[mu] + 1e-12):
                # §5.1 rule 3: λ leaves μ's height range: match a new branch at this height
                here = float(builder.nodes[prev][ib])
                new = _match(b, y, float(a.mext[lam]), here, tol, strict=not extend)
                if new >= 0:
                    mu, pos = new, 0
                    mpts = b.nodes[b.chains[mu]]
                elif not extend:
                    hold = here
            if hold is not None:
                depth = hold
            else:
                depth, pos = _at_height(mpts, y, pos)
            q = np.empty(3)
            q[ia], q[ib], q[2] = a.nodes[idx[k], 0], depth, y
            prev = builder.add(q, prev)
            amap[idx[k]] = prev
            if hold is not None:
                continue
            for qb in (b.chains[mu][pos], b.chains[mu][min(pos + 1, len(mpts) - 1)]):
                if bmap[qb] < 0:
                    bmap[qb] = prev


def depth_retrieval(front: StrokeGraph, side: StrokeGraph, progress: Progress = None, snap_fraction: float = 0.02):
    """3D main branches from two 2D skeletons by depth retrieval (§5, Eq. 1–7, §5.2, §5.3).

    Returns (nodes (m, 3) as (u, v, height) in metres — u the front view's
    horizontal, v the side view's —, parent (m,), source (m,) 0 for nodes built
    from a front branch, 1 for the complementary pass over unused side-view parts).
    ``snap_fraction`` × the drawing height is the continuity tolerance of the
    re-matches (see :func:`_construct`).
    """
    a, b = skeleton_2d(front), skeleton_2d(side)
    builder = _Builder(len(a.nodes), len(b.nodes))
    order = np.lexsort((np.arange(len(a.chains)), a.order))  # level by level
    tol = snap_fraction * float(np.ptp(front.nodes[:, 1]))
    _construct(a, b, [(int(l), a.chains[l]) for l in order], builder, 0, 1, tol)
    n_first = len(builder.nodes)
    report(progress, 0.5, "depth retrieval: front view done")
    # §5.3 complementarity: runs of unused side-view nodes, each hanging from a used node
    bmap = builder.map[1]
    pieces = []
    for lam in np.lexsort((np.arange(len(b.chains)), b.order)):
        c = b.chains[lam]
        k = 0
        while k < len(c):
            if bmap[c[k]] >= 0:
                k += 1
                continue
            j = k
            while j < len(c) and bmap[c[j]] < 0:
                j += 1
            start = k - 1 if k > 0 else None
            if start is None:
                par = int(b.parent[c[0]])
                run = np.r_[par, c[k:j]] if par >= 0 else c[k:j]
            else:
                run = c[start:j]
            pieces.append((int(lam), np.asarray(run, dtype=np.int64)))
            k = j
    # attach the complementary runs: their first node must already have a 3D node (runs hanging
    # from a run built earlier in this pass have one by then: pieces are in level order)
    for lam, run in pieces:
        if builder.map[1][run[0]] < 0:
            continue
        _construct(b, a, [(lam, run)], builder, 1, 0, tol, extend=False)
    nodes = np.array(builder.nodes)
    parent = np.array(builder.parent, dtype=np.int64)
    source = np.r_[np.zeros(n_first, np.int8), np.ones(len(nodes) - n_first, np.int8)]
    report(progress, 1.0, "depth retrieval done")
    return nodes, parent, source
