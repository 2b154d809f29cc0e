"""Trees from two sketched profiles: Sketch-based tree modeling from two views (the sketch paper), §4–§7.

The user digitises the main branches of a tree as line strokes over two
photos taken from roughly orthogonal sides (a *front* and a *side* view),
optionally a crown silhouette polygon per view, and gives the tree's height.
The method builds:

1. a 2D skeleton per view from the strokes (§4.1).  The paper traverses
   single-pixel strokes pixel by pixel; digitised strokes are already
   polylines, so the "pixels" are the vertices, and the junctions the paper
   finds by local pixel analysis are the strokes' intersections plus the
   stroke ends that stop within ``snap_fraction`` of another stroke
   (:func:`stroke_graph`).  The graph is traversed breadth-first from the
   lowest vertex of the trunk stroke (§4.1.2 "from the lowest one"), which
   gives a rooted tree (cycles of crossing strokes are cut where the traversal
   meets itself), and decomposed into branches with the least-bending
   continuation of :func:`sylva.core.geometry.branches`;
2. the 3D main branches by *depth retrieval* (§5): for every branch λ of the
   front skeleton A, level by level, the branch μ of the side skeleton B that
   passes the bud height V = b(λ) and minimises F = |M(μ) − M(λ)| (Eq. 1, 3;
   M the maximum extension height) gives each point of λ its depth at the same
   height (Eq. 4–6, y up in the paper: x from λ, depth z from μ, y shared); when λ climbs above H(μ)
   (or dips below h(μ)) a new μ is matched at that height (§5.1 rule 3).
   Branch extension (§5.2): when the point P_b of μ at the bud height is not on
   μ's *available descending path* (the side-view nodes already used by the 3D
   ancestors of λ's bud), λ and μ are extended down their descending paths to
   the highest used node, so the new 3D branch leaves the structure there and
   projects onto both drawings.  Branch complementarity (§5.3): the side-view
   stroke parts left unused are built the same way with the roles swapped;
3. small branches by self-similarity (§6, Fig. 16, Table 1): a sub-branch is a
   copy of the first σ·k nodes of its parent branch η (Eq. 8), attached at a
   bud S_x of η with angle θ to η (cos θ1 ≥ cos θ ≥ cos θ2 is Table 1's
   0.5…0.9) and angle φ to the previous sub-branch of η (cos φ in −0.5…0.5),
   for ``levels`` l = 2 generations; buds in crowded places are removed, and
   nodes whose projection leaves a crown silhouette are cut off (the branch
   keeps its part up to the first node outside);
4. radii (da Vinci's rule, §7: the pipe model of :mod:`sylva.core.geometry`),
   meshes and leaves are the shared code's (see ``algorithms/sketch.py``).

Drawing frame (Sylva's convention, documented for the user): each view's
strokes are in any 2D units with y up.  The lowest vertex of the trunk stroke
(the stroke holding the lowest vertex of the view) is the base; each view is
scaled on its own so that its drawing height (highest vertex − base) equals
``height_m``.  The front view's horizontal axis becomes x (east) and the side
view's becomes y (north), both through the base, z up: with
``front_azimuth_deg`` = 0 the front photo is taken looking north (its right
is east) and the side photo looking west (its right is north).  A non-zero
``front_azimuth_deg`` (compass bearing the front photo looks along) turns the
tree about its base: the front drawing's right is then the bearing
``azimuth + 90°`` and the side drawing's right the bearing ``azimuth``.

Where Sylva differs from the printed method (each documented where it is done):
digitised strokes carry no width, so Eq. 2 and Eq. 7 (brush radii) are not
used and radii come from the pipe model; the *used path* of §5.2 is read from
the 3D structure (side-view nodes whose 3D node is an ancestor of the bud);
when no side branch passes a height, the branch nearest in height is used;
re-matches (§5.1 rule 3) prefer a branch passing within the snapping
tolerance of the current depth, and complementary runs (§5.3) are not
extended, prefer a front branch passing near the node they hang from, and keep
that node's depth when there is none; a sub-branch's first copied node S_1
sits on the bud S_x; the bud count and crowding limits are Sylva's values.

The airborne variant :class:`SketchCompletion` completes the crown of a
:class:`~sylva.core.reconstruct.skeleton.GreedySkeleton` with the same
self-similar small branches, pruned by silhouettes computed from the tree's
own points seen from the south (x–z) and from the east (y–z).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence

import numpy as np

from ..errors import EmptyInputError, InputError
from ..progress import CancelCheck, Progress, check, report, scaled
from .model import Reconstruction, Skeleton, TreePoints

__all__ = ["SketchTree", "SketchResult", "StrokeGraph", "SketchCompletion", "stroke_graph",
           "skeleton_2d", "depth_retrieval", "grow_small_branches", "tree_from_sketch",
           "crown_silhouettes", "project_front", "project_side", "projection_error"]


# --------------------------------------------------------------------------- parameters

@dataclass(frozen=True)
class SketchTree:
    """Parameters of the sketch method (paper defaults from Table 1 where it gives them).

    * ``sigma`` σ = 0.3: a sub-branch copies the first σ·k nodes of its parent (§6, Eq. 8);
    * ``cos_theta1`` = 0.5, ``cos_theta2`` = 0.9: range of cos θ, the angle between a
      sub-branch and its parent branch at the bud (Table 1; θ from 25.8° to 60°);
    * ``cos_phi1`` = −0.5, ``cos_phi2`` = 0.5: range of cos φ, the angle between two
      consecutive sub-branches of one branch (Table 1; φ from 60° to 120°);
    * ``levels`` l = 2: generations of small branches (Table 1);
    * ``buds_per_branch`` buds per branch η before crowding removal (not given by
      the paper: 8); they are spread evenly along η, and on the trunk only above
      the lowest main fork (the crown base);
    * ``crowd_radius_fraction`` and ``crowd_max``: a bud is removed when more than
      ``crowd_max`` small-branch nodes already lie within ``crowd_radius_fraction`` ×
      height of it (§6 "removing buds in crowded areas"; the paper gives no values:
      0.05 and 12);
    * ``step_fraction`` strokes are resampled every ``step_fraction`` × height
      (Sylva: 0.01), so depth retrieval pairs points of equal height (Eq. 5);
    * ``snap_fraction`` a stroke end within ``snap_fraction`` × drawing height of
      another stroke joins it (digitising rarely hits a line exactly; Sylva: 0.02);
    * ``grow`` False keeps the main branches only;
    * ``seed`` of the random generator (θ, φ, bud jitter): same inputs, same tree.
    """

    sigma: float = 0.3
    cos_theta1: float = 0.5
    cos_theta2: float = 0.9
    cos_phi1: float = -0.5
    cos_phi2: float = 0.5
    levels: int = 2
    buds_per_branch: int = 8
    crowd_radius_fraction: float = 0.05
    crowd_max: int = 12
    step_fraction: float = 0.01
    snap_fraction: float = 0.02
    grow: bool = True
    seed: int = 0

    name = "sketch"

    def __post_init__(self):
        if not 0 < self.sigma <= 1:
            raise InputError(f"SketchTree: sigma must be in (0, 1], got {self.sigma!r}")
        for a, b in (("cos_theta1", "cos_theta2"), ("cos_phi1", "cos_phi2")):
            lo, hi = getattr(self, a), getattr(self, b)
            if not (-1 <= lo <= 1 and -1 <= hi <= 1 and lo <= hi):
                raise InputError(f"SketchTree: {a} and {b} must be cosines with {a} <= {b}, got {lo!r}, {hi!r}")
        if int(self.levels) != self.levels or self.levels < 0:
            raise InputError(f"SketchTree: levels must be a whole number >= 0, got {self.levels!r}")
        if int(self.buds_per_branch) != self.buds_per_branch or self.buds_per_branch < 0:
            raise InputError(f"SketchTree: buds_per_branch must be a whole number >= 0, got {self.buds_per_branch!r}")
        if int(self.crowd_max) != self.crowd_max or self.crowd_max < 0:
            raise InputError(f"SketchTree: crowd_max must be a whole number >= 0, got {self.crowd_max!r}")
        for attr in ("crowd_radius_fraction", "step_fraction", "snap_fraction"):
            if not (getattr(self, attr) > 0 and getattr(self, attr) < 1):
                raise InputError(f"SketchTree: {attr} must be in (0, 1), got {getattr(self, attr)!r}")


# --------------------------------------------------------------------------- §4 stroke graph

@dataclass
class StrokeGraph:
    """One view's strokes as a rooted 2D skeleton in metres (§4).

    ``nodes`` (n, 2) horizontal offset from the base and height, metres;
    ``parent`` (n,) parents before children, -1 at the root (the base);
    ``scale`` metres per drawing unit, ``origin`` the base in drawing units;
    ``dropped`` the number of stroke vertices not connected to the trunk.
    """

    nodes: np.ndarray
    parent: np.ndarray
    scale: float
    origin: np.ndarray
    dropped: int = 0
    name: str = "view"

    def to_metres(self, xy) -> np.ndarray:
        """Drawing coordinates (k, 2) to this view's metric frame."""
        return (np.asarray(xy, dtype=np.float64).reshape(-1, 2) - self.origin) * self.scale

    def skeleton(self) -> Skeleton:
        """The 2D skeleton as a :class:`Skeleton` in the vertical plane (x, 0, height)."""
        n = self.nodes
        return Skeleton(np.column_stack([n[:, 0], np.zeros(len(n)), n[:, 1]]), self.parent)


def _xy(geom) -> np.ndarray:
    """(n, 2) float64 x, y of a geometry's vertices.

    ``shapely.get_coordinates``, not ``.coords``: inside QGIS the system GEOS is
    loaded first, and ``.coords`` asks GEOS whether the geometry has M, which
    then fails now and then (GEOSException) in qgis_process.
    """
    import shapely

    return shapely.get_coordinates(geom).astype(np.float64)


def _as_lines(strokes, name: str) -> List[np.ndarray]:
    """Polylines (k, 2) from shapely (Multi)LineStrings or arrays; empty parts dropped."""
    import shapely

    out = []
    if strokes is None:
        raise InputError(f"{name}: the layer is missing: both a front and a side view are needed")
    for g in strokes:
        if g is None:
            continue
        if isinstance(g, np.ndarray) or isinstance(g, (list, tuple)):
            arr = np.asarray(g, dtype=np.float64)
            if arr.ndim == 2 and arr.shape[0] >= 2:
                out.append(arr[:, :2])
            continue
        if g.is_empty:
            continue
        parts = shapely.get_parts(g)
        for p in parts:
            if p.geom_type in ("LineString", "LinearRing"):
                c = _xy(p)
                if len(c) >= 2:
                    out.append(c)
            elif p.geom_type == "Polygon":
                c = _xy(p.exterior)
                out.append(c)
            else:
                raise InputError(f"{name}: strokes must be lines, got a {p.geom_type}")
    out = [l for l in out if np.all(np.isfinite(l))]
    # drop repeated vertices
    out = [l[np.r_[True, np.any(np.diff(l, axis=0) != 0, axis=1)]] for l in out]
    out = [l for l in out if len(l) >= 2]
    if not out:
        raise EmptyInputError(f"{name}: the layer holds no stroke (no line with two distinct vertices)")
    return out


def _densify(line: np.ndarray, step: float) -> np.ndarray:
    seg = np.linalg.norm(np.diff(line, axis=0), axis=1)
    n = np.maximum(1, np.ceil(seg / step).astype(int))
    parts = [line[i] + (line[i + 1] - line[i]) * (np.arange(n[i])[:, None] / n[i]) for i in range(len(seg))]
    return np.vstack(parts + [line[-1:]])


def stroke_graph(strokes, height_m: float, method: SketchTree = SketchTree(), name: str = "view") -> StrokeGraph:
    """A view's strokes as a rooted 2D skeleton in metres (§4.1, adapted to digitised lines).

    Junctions are the strokes' mutual intersections and the stroke ends within
    ``snap_fraction`` × drawing height of another stroke; every stroke is
    resampled every ``step_fraction`` × ``height_m``; the graph is traversed
    breadth-first from the base (lowest vertex of the trunk stroke), so
    parents precede children.  Vertices not connected to the trunk are
    dropped (counted in ``dropped``).  Raises :class:`InputError` naming
    ``name`` for an empty layer, a drawing without height or ``height_m`` <= 0.
    """
    import shapely
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order
    from scipy.spatial import cKDTree

    if not (height_m is not None and np.isfinite(height_m) and height_m > 0):
        raise InputError(f"the tree height must be a positive number of metres, got {height_m!r}")
    lines = _as_lines(strokes, name)
    allpts = np.vstack(lines)
    ilow = int(np.argmin(allpts[:, 1]))
    base = allpts[ilow].copy()
    extent = float(allpts[:, 1].max() - base[1])
    width = float(np.ptp(allpts[:, 0]))
    if not extent > 1e-9 * max(width, 1.0):
        raise InputError(f"{name}: no trunk: the strokes have no height (all vertices at the same level); "
                         "draw the trunk from the ground up")
    snap = method.snap_fraction * extent
    eps = 1e-9 * extent

    # split parameters per stroke: intersections and snapped ends (§4.1 junctions)
    geoms = [shapely.LineString(l) for l in lines]
    extra: List[List[np.ndarray]] = [[] for _ in lines]
    links = []  # (point a, point b) pairs to join by an edge
    tree = shapely.STRtree(geoms)
    for i, g in enumerate(geoms):
        for j in tree.query(g.buffer(snap)):
            j = int(j)
            if j <= i:
                continue
            inter = g.intersection(geoms[j])
            for p in shapely.get_parts(inter):
                if p.geom_type == "Point":
                    c = _xy(p)[0]
                    extra[i].append(c)
                    extra[j].append(c)
                elif not p.is_empty:  # overlapping pieces: their ends are shared vertices
                    for c in _xy(p)[[0, -1]]:
                        extra[i].append(c)
                        extra[j].append(c)
    for i, l in enumerate(lines):
        for end in (l[0], l[-1]):
            pe = shapely.Point(end)
            best, bd = None, snap
            for j in tree.query(pe.buffer(snap)):
                j = int(j)
                if j == i:
                    continue
                d = geoms[j].distance(pe)
                if d <= bd and d > eps:
                    best, bd = j, d
            if best is not None:
                q = geoms[best].interpolate(geoms[best].project(pe))
                c = _xy(q)[0]
                extra[best].append(c)
                links.append((end.copy(), c))
    # insert the split points into their strokes (ordered along the stroke), then densify
    step = method.step_fraction * extent
    pts_list, edges, offset = [], [], 0
    for i, l in enumerate(lines):
        if extra[i]:
            g = geoms[i]
            cum = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(l, axis=0), axis=1))]
            ex = np.asarray(extra[i])
            s = np.array([g.project(shapely.Point(c)) for c in ex])
            allp = np.vstack([l, ex])
            alls = np.r_[cum, s]
            order = np.argsort(alls, kind="stable")
            l = allp[order]
            l = l[np.r_[True, np.linalg.norm(np.diff(l, axis=0), axis=1) > eps]]
        d = _densify(l, step)
        pts_list.append(d)
        k = len(d)
        edges.append(np.column_stack([np.arange(offset, offset + k - 1), np.arange(offset + 1, offset + k)]))
        offset += k
    pts = np.vstack(pts_list)
    edges = np.vstack(edges) if edges else np.zeros((0, 2), int)
    if links:
        la = np.array([a for a, _ in links])
        lb = np.array([b for _, b in links])
        pts = np.vstack([pts, la, lb])
        n0 = offset
        k = len(links)
        edges = np.vstack([edges, np.column_stack([np.arange(n0, n0 + k), np.arange(n0 + k, n0 + 2 * k)])])
    # merge coincident vertices (shared junctions)
    n = len(pts)
    kd = cKDTree(pts)
    pairs = kd.query_pairs(max(eps, 1e-6 * step), output_type="ndarray")
    rep = np.arange(n)
    if len(pairs):
        from scipy.sparse.csgraph import connected_components

        g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
        _, lab = connected_components(g, directed=False)
        first = np.full(lab.max() + 1, n)
        np.minimum.at(first, lab, np.arange(n))
        rep = first[lab]
    e = rep[edges]
    e = e[e[:, 0] != e[:, 1]]
    adj = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
    adj = adj + adj.T
    root = int(rep[int(np.argmin(pts[:, 1]))])
    order, pred = breadth_first_order(adj, root, directed=False, return_predecessors=True)
    reached_unique = len(order)
    uniq_total = len(np.unique(rep))
    new_index = np.full(n, -1, dtype=np.int64)
    new_index[order] = np.arange(len(order))
    parent = np.where(pred[order] >= 0, new_index[np.maximum(pred[order], 0)], -1)
    parent[0] = -1
    scale = height_m / extent
    nodes = (pts[order] - base) * scale
    return StrokeGraph(nodes, parent.astype(np.int64), scale, base, uniq_total - reached_unique, name)


@dataclass
class _View:
    """A 2D skeleton split into branches, with the §3 features per branch."""

    nodes: np.ndarray           # (n, 2) horizontal, height
    parent: np.ndarray
    chains: List[np.ndarray]    # node indices, first = bud node (attach) except the trunk
    bparent: np.ndarray
    order: np.ndarray
    node_branch: np.ndarray
    hmin: np.ndarray            # h(λ)
    hmax: np.ndarray            # H(λ)
    mext: np.ndarray            # M(λ) maximum extension height of the up-family


def skeleton_2d(graph: StrokeGraph) -> _View:
    """Branches and their features h(λ), H(λ), M(λ) (§3) of a view's 2D skeleton."""
    from ..geometry import branches

    bset = branches(graph.skeleton())
    y = graph.nodes[:, 1]
    hmin = np.array([y[c].min() for c in bset.chains])
    hmax = np.array([y[c].max() for c in bset.chains])
    mext = hmax.copy()
    for b in range(len(bset.chains) - 1, 0, -1):  # children after parents
        p = bset.parent[b]
        if p >= 0:
            mext[p] = max(mext[p], mext[b])
    return _View(graph.nodes, graph.parent, list(bset.chains), bset.parent, bset.order, bset.node_branch,
                 hmin, hmax, mext)


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


def _match(view: _View, V: float, m_target: float, near: Optional[float] = None, tol: float = 0.0,
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


def _descending(view: _View, node: int) -> List[int]:
    """Descending path p(λ) from ``node`` to the root (node indices, node first)."""
    out = []
    while node >= 0:
        out.append(node)
        node = int(view.parent[node])
    return out


def _construct(a: _View, b: _View, pieces, builder: _Builder, ia: int, ib: int, tol: float, extend: bool = True):
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


# --------------------------------------------------------------------------- §6 small branches

def _rings(poly) -> np.ndarray:
    """All ring edges (e, 4) x0, y0, x1, y1 of a (multi)polygon."""
    import shapely

    edges = []
    for part in shapely.get_parts(poly):
        if part.geom_type != "Polygon":
            continue
        for ring in [part.exterior, *part.interiors]:
            c = _xy(ring)
            edges.append(np.column_stack([c[:-1], c[1:]]))
    return np.vstack(edges) if edges else np.zeros((0, 4))


def _inside(poly, x: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Points (x, z) inside a (multi)polygon (or its ring edges from :func:`_rings`) by the
    even-odd rule, in numpy.

    Not ``shapely.contains_xy``: inside QGIS the system GEOS (3.11) is loaded first and that
    call (GEOS >= 3.12) crashes the process."""
    if poly is None:
        return np.ones(len(x), dtype=bool)
    e = poly if isinstance(poly, np.ndarray) else _rings(poly)
    x = np.asarray(x, dtype=np.float64)[:, None]
    z = np.asarray(z, dtype=np.float64)[:, None]
    x0, y0, x1, y1 = (e[:, i][None, :] for i in range(4))
    crosses = (y0 > z) != (y1 > z)
    with np.errstate(divide="ignore", invalid="ignore"):
        xc = x0 + (z - y0) * (x1 - x0) / (y1 - y0)
    return ((crosses & (x < xc)).sum(axis=1) % 2) == 1


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _perp_frame(t: np.ndarray):
    ref = np.array([0.0, 0.0, 1.0]) if abs(t[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = _cross(t, ref)
    e1 /= np.linalg.norm(e1)
    e2 = _cross(t, e1)
    return e1, e2


def _rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector a onto unit vector b (Rodrigues)."""
    v = _cross(a, b)
    c = float(a @ b)
    if c < -1 + 1e-9:
        e1, _ = _perp_frame(a)
        return 2.0 * np.outer(e1, e1) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def grow_small_branches(skeleton: Skeleton, method: SketchTree = SketchTree(), front_silhouette=None,
                        side_silhouette=None, crown_base_z: Optional[float] = None,
                        height_m: Optional[float] = None, cancelled: CancelCheck = None):
    """Self-similar small branches (§6, Eq. 8, Fig. 16, Table 1) added to ``skeleton``.

    Parents η are the chains of :func:`sylva.core.geometry.branches` (then, for
    ``levels`` = 2, the new sub-branches).  At each bud S_x (``buds_per_branch``
    evenly spread along η, above ``crown_base_z`` on the trunk, with a random
    shift), a sub-branch copies η's first σ·k nodes, rotated so its chord makes
    angle θ with η's tangent at S_x (cos θ drawn in [cos_theta1, cos_theta2])
    and angle φ with the previous sub-branch of η (cos φ in [cos_phi1, cos_phi2],
    up to 16 draws).  Buds with more than ``crowd_max`` small-branch nodes within
    ``crowd_radius_fraction`` × height are removed.  Nodes are projected on the
    x–z plane (``front_silhouette``, shapely polygon) and on the y–z plane
    (``side_silhouette``); a sub-branch is cut before its first node outside
    either (§6 pruning).  Returns (new Skeleton, level per node: 0 = input).
    """
    from scipy.spatial import cKDTree

    from ..geometry import branches

    rng = np.random.default_rng(method.seed)
    front_silhouette = None if front_silhouette is None else _rings(front_silhouette)
    side_silhouette = None if side_silhouette is None else _rings(side_silhouette)
    nodes = [np.asarray(skeleton.nodes, dtype=np.float64)]
    parent = [np.asarray(skeleton.parent, dtype=np.int64)]
    level = [np.zeros(len(skeleton), dtype=np.int64)]
    total = len(skeleton)
    if total < 2 or method.levels == 0 or method.buds_per_branch == 0:
        return skeleton, level[0]
    base = skeleton.nodes
    h = float(height_m) if height_m else float(np.ptp(base[:, 2]))
    crowd_r = method.crowd_radius_fraction * max(h, 1e-9)
    chains = [np.asarray(c) for c in branches(skeleton)]
    all_nodes = base.copy()
    small_pts = np.zeros((0, 3))
    lo_c, hi_c = sorted((method.cos_theta1, method.cos_theta2))
    for lev in range(1, method.levels + 1):
        check(cancelled)
        new_chains = []
        for ci, chain in enumerate(chains):
            k = len(chain)
            if k < 3:
                continue
            pts = all_nodes[chain]
            m = max(2, int(round(method.sigma * k)))
            piece = pts[:m] - pts[0]
            chord = piece[-1]
            if np.linalg.norm(chord) < 1e-9:
                continue
            chord = chord / np.linalg.norm(chord)
            # buds: evenly spaced with a random shift, not at the first or last node
            nb = method.buds_per_branch
            pos = (np.arange(nb) + rng.uniform(0.25, 0.75, nb)) / nb * (k - 1)
            xs = np.unique(np.clip(np.round(pos).astype(int), 1, k - 2))
            if lev == 1 and ci == 0 and crown_base_z is not None:
                xs = xs[pts[xs, 2] >= crown_base_z]
            prev_dir = None
            kd = cKDTree(small_pts) if len(small_pts) else None
            inside = (_inside(front_silhouette, pts[xs, 0], pts[xs, 2])
                      & _inside(side_silhouette, pts[xs, 1], pts[xs, 2]))
            for x in xs[inside]:
                s = pts[x]
                if kd is not None:
                    if len(kd.query_ball_point(s, crowd_r)) > method.crowd_max:
                        continue
                t = pts[min(x + 1, k - 1)] - pts[x - 1]
                t = t / max(np.linalg.norm(t), 1e-12)
                e1, e2 = _perp_frame(t)
                d = None
                for _ in range(16):
                    ct = rng.uniform(lo_c, hi_c)
                    st = math.sqrt(max(0.0, 1 - ct * ct))
                    psi = rng.uniform(0, 2 * math.pi)
                    cand = ct * t + st * (math.cos(psi) * e1 + math.sin(psi) * e2)
                    d = cand
                    if prev_dir is None:
                        break
                    cphi = float(cand @ prev_dir)
                    if method.cos_phi1 <= cphi <= method.cos_phi2:
                        break
                prev_dir = d
                new = s + piece[1:] @ _rotation(chord, d).T
                ok = _inside(front_silhouette, new[:, 0], new[:, 2]) & _inside(side_silhouette, new[:, 1], new[:, 2])
                bad = np.flatnonzero(~ok)
                keep = int(bad[0]) if len(bad) else len(new)
                if keep < 1:
                    continue
                new = new[:keep]
                first = total
                idx = np.arange(first, first + keep)
                par = np.r_[chain[x], idx[:-1]]
                nodes.append(new)
                parent.append(par)
                level.append(np.full(keep, lev, dtype=np.int64))
                total += keep
                all_nodes = np.vstack([all_nodes, new])
                small_pts = np.vstack([small_pts, new])
                if keep >= 2:
                    new_chains.append(np.r_[chain[x], idx])
        chains = new_chains
        if not chains:
            break
    sk = Skeleton(np.vstack(nodes), np.concatenate(parent),
                  is_added=np.r_[skeleton.is_added, np.zeros(total - len(skeleton), bool)])
    return sk, np.concatenate(level)


# --------------------------------------------------------------------------- the whole method

@dataclass
class SketchResult:
    """A tree built from two sketches.

    ``skeleton`` metres, origin at the base, x east, y north, z up (after the
    front azimuth); ``level`` per node (0 main branches, 1.. small branches);
    ``source`` per main node (0 front pass, 1 complementary pass);
    ``front``/``side`` the two :class:`StrokeGraph` (metric view frames);
    ``main_uvz`` the main nodes in the view frame (u front, v side, z), for
    projection checks; ``stats`` counts and timings; ``warnings`` notes for the user.
    """

    skeleton: Skeleton
    level: np.ndarray
    source: np.ndarray
    front: StrokeGraph
    side: StrokeGraph
    main_uvz: np.ndarray
    height_m: float
    azimuth_deg: float = 0.0
    stats: Dict[str, Any] = field(default_factory=dict)
    warnings: List[str] = field(default_factory=list)


def _silhouette(polys, graph: StrokeGraph, name: str):
    """Silhouette polygons (drawing units) to the view's metric frame, as one shapely geometry."""
    import shapely
    from shapely import affinity

    if polys is None:
        return None
    gs = [g for g in polys if g is not None and not g.is_empty]
    if not gs:
        return None
    g = shapely.union_all([shapely.make_valid(x) for x in gs])
    g = shapely.force_2d(g)
    g = affinity.affine_transform(g, [graph.scale, 0, 0, graph.scale,
                                      -graph.origin[0] * graph.scale, -graph.origin[1] * graph.scale])
    if g.area <= 0:
        raise InputError(f"{name}: the crown silhouette has no area; draw it as a closed polygon")
    return g


def project_front(uvz: np.ndarray) -> np.ndarray:
    """(u, z): the view-frame nodes as seen on the front drawing (metric frame)."""
    return np.asarray(uvz)[:, [0, 2]]


def project_side(uvz: np.ndarray) -> np.ndarray:
    """(v, z): the view-frame nodes as seen on the side drawing (metric frame)."""
    return np.asarray(uvz)[:, [1, 2]]


def _rotate(uvz: np.ndarray, azimuth_deg: float) -> np.ndarray:
    a = math.radians(azimuth_deg)
    u, v = uvz[:, 0], uvz[:, 1]
    x = u * math.cos(a) + v * math.sin(a)
    y = -u * math.sin(a) + v * math.cos(a)
    return np.column_stack([x, y, uvz[:, 2]])


def tree_from_sketch(front, side, height_m: float, method: SketchTree = SketchTree(),
                     front_silhouette=None, side_silhouette=None, front_azimuth_deg: float = 0.0,
                     names: Sequence[str] = ("front", "side"), progress: Progress = None,
                     cancelled: CancelCheck = None) -> SketchResult:
    """Build a tree from two sketched views (§4–§6); see the module docstring for the frame.

    ``front``/``side`` iterables of shapely (Multi)LineStrings or (k, 2) arrays
    in drawing units; silhouettes iterables of shapely polygons in the same
    units (or None); ``height_m`` the tree height.  Errors name the layer
    (``names``): missing or empty layer, no trunk, height <= 0.
    """
    t0 = time.perf_counter()
    if not (height_m is not None and np.isfinite(height_m) and height_m > 0):
        raise InputError(f"the tree height must be a positive number of metres, got {height_m!r}")
    if front is None or side is None:
        missing = names[0] if front is None else names[1]
        raise InputError(f"{missing}: the layer is missing: both a front and a side view are needed")
    check(cancelled)
    fg = stroke_graph(front, height_m, method, names[0])
    sg = stroke_graph(side, height_m, method, names[1])
    warnings = []
    for g in (fg, sg):
        if g.dropped:
            warnings.append(f"{g.name}: {g.dropped} stroke vertices are not connected to the trunk and were left out")
    report(progress, 0.2, "2D skeletons")
    check(cancelled)
    nodes, parent, source = depth_retrieval(fg, sg, scaled(progress, 0.2, 0.5), method.snap_fraction)
    fs = _silhouette(front_silhouette, fg, names[0] + " silhouette")
    ss = _silhouette(side_silhouette, sg, names[1] + " silhouette")
    main = Skeleton(nodes, parent)
    level = np.zeros(len(main), dtype=np.int64)
    if method.grow:
        check(cancelled)
        n_kids = main.n_children()
        forks = nodes[n_kids >= 2, 2]
        crown_base = float(forks.min()) if len(forks) else 0.3 * height_m
        if fs is None:
            fs = _auto_silhouette(fg.nodes)
        if ss is None:
            ss = _auto_silhouette(sg.nodes)
        grown, level = grow_small_branches(main, method, fs, ss, crown_base, height_m, cancelled)
    else:
        grown = main
    report(progress, 0.9, "small branches")
    uvz = grown.nodes
    xyz = _rotate(uvz, front_azimuth_deg) if front_azimuth_deg else uvz.copy()
    skel = Skeleton(xyz, grown.parent)
    stats = {"n_main_nodes": int(len(main)), "n_nodes": int(len(skel)),
             "n_front_nodes": int(len(fg.nodes)), "n_side_nodes": int(len(sg.nodes)),
             "n_complementary_nodes": int((source == 1).sum()), "t_total_s": time.perf_counter() - t0}
    report(progress, 1.0, "sketch tree built")
    return SketchResult(skel, level, source, fg, sg, nodes, float(height_m), float(front_azimuth_deg), stats,
                        warnings)


def _auto_silhouette(nodes2d: np.ndarray):
    """Without a sketched silhouette: the convex hull of the view's strokes widened by 10 % of its height,
    cut at the base and at the top of the drawing."""
    import shapely

    hull = shapely.convex_hull(shapely.MultiPoint(nodes2d))
    h = float(np.ptp(nodes2d[:, 1]))
    lo, hi = nodes2d.min(axis=0), nodes2d.max(axis=0)
    return hull.buffer(0.1 * h).intersection(shapely.box(lo[0] - h, lo[1], hi[0] + h, hi[1]))


def projection_error(result: SketchResult) -> tuple:
    """Mean distance (metres) of the main 3D nodes, projected on each view, to that view's strokes."""
    from scipy.spatial import cKDTree

    out = []
    for g, proj in ((result.front, project_front), (result.side, project_side)):
        d, _ = cKDTree(_dense(g)).query(proj(result.main_uvz))
        out.append(float(d.mean()))
    return tuple(out)


def _dense(g: StrokeGraph) -> np.ndarray:
    ok = g.parent >= 0
    a, b = g.nodes[ok], g.nodes[g.parent[ok]]
    t = np.linspace(0, 1, 5)[:, None, None]
    return (a[None] + t * (b - a)[None]).reshape(-1, 2)


# --------------------------------------------------------------------------- airborne completion

def crown_silhouettes(xyz: np.ndarray, crown_base_z: float, concavity: float = 0.5, margin_m: float = 0.3):
    """Crown silhouettes of a point cloud seen from the south (x–z) and the east (y–z).

    The hull (shapely concave hull with ``concavity`` as its ratio, 1 = convex)
    of the points above ``crown_base_z`` projected on each plane, widened by ``margin_m``.
    """
    import shapely

    out = []
    crown = xyz[xyz[:, 2] >= crown_base_z]
    if len(crown) < 3:
        crown = xyz
    for cols in ((0, 2), (1, 2)):
        mp = shapely.MultiPoint(crown[:, cols])
        hull = shapely.concave_hull(mp, ratio=concavity) if concavity < 1 else shapely.convex_hull(mp)
        out.append(hull.buffer(margin_m))
    return tuple(out)


@dataclass(frozen=True)
class SketchCompletion:
    """Airborne trees completed with the sketch paper's small branches (§6).

    ``primary`` builds the main skeleton from the points (default Hu et al.'s
    :class:`GreedySkeleton`); then :func:`grow_small_branches` adds
    self-similar sub-branches (``sketch`` parameters, Table 1 defaults) inside
    the crown silhouettes of the points seen from two orthogonal sides
    (:func:`crown_silhouettes`, ``concavity``, ``margin_m``), with trunk buds
    only above the crown base (the lowest fork of the main skeleton).  A method
    value for :func:`sylva.core.reconstruct.reconstruct_tree`; ``name`` is
    "sketch_completion" and ``stats["n_small_nodes"]`` counts the added nodes.
    """

    primary: Any = None
    sketch: SketchTree = SketchTree()
    concavity: float = 0.5
    margin_m: float = 0.3

    name = "sketch_completion"

    def reconstruct(self, tree: TreePoints, progress: Progress = None,
                    cancelled: CancelCheck = None) -> Reconstruction:
        from .skeleton import GreedySkeleton

        t0 = time.perf_counter()
        primary = self.primary if self.primary is not None else GreedySkeleton()
        rec = primary.reconstruct(tree, progress=scaled(progress, 0.0, 0.7), cancelled=cancelled)
        sk = rec.skeleton
        if len(sk) < 3 or len(tree.xyz) < 3:
            rec.flags = list(rec.flags) + ["not_completed"]
            return rec
        check(cancelled)
        forks = sk.nodes[sk.n_children() >= 2, 2]
        crown_base = float(forks.min()) if len(forks) else float(tree.ground_z)
        fs, ss = crown_silhouettes(tree.xyz, crown_base, self.concavity, self.margin_m)
        height = float(tree.xyz[:, 2].max() - tree.ground_z)
        grown, level = grow_small_branches(sk, self.sketch, fs, ss, crown_base, height, cancelled)
        out = grown
        stats = dict(rec.stats)
        stats.update(primary_method=rec.method, n_small_nodes=int((level > 0).sum()),
                     t_completion_s=time.perf_counter() - t0)
        report(progress, 1.0, f"tree {tree.tree_id}: crown completed")
        return Reconstruction(out, self.name, rec.visited_fraction, rec.connected, stats, list(rec.flags),
                              rec.tree_id)
