"""A view's strokes as a rooted 2D skeleton (the sketch paper §4.1, adapted to digitised lines) and its
branches with the features h(λ), H(λ), M(λ) of §3.

The strokes are read from shapely (Multi)LineStrings or arrays (:func:`vertices_xy`), split at their
junctions (intersections and snapped ends), resampled, traversed breadth-first from the base
(:func:`stroke_graph`, a :class:`StrokeGraph` in metres) and decomposed into branches
(:func:`skeleton_2d`, a :class:`View`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import List

import numpy as np

from ...errors import EmptyInputError, InputError
from ..model import Skeleton
from .params import SketchTree


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


def vertices_xy(geom) -> np.ndarray:
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
                c = vertices_xy(p)
                if len(c) >= 2:
                    out.append(c)
            elif p.geom_type == "Polygon":
                c = vertices_xy(p.exterior)
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
                    c = vertices_xy(p)[0]
                    extra[i].append(c)
                    extra[j].append(c)
                elif not p.is_empty:  # overlapping pieces: their ends are shared vertices
                    for c in vertices_xy(p)[[0, -1]]:
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
                c = vertices_xy(q)[0]
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
class View:
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


def skeleton_2d(graph: StrokeGraph) -> View:
    """Branches and their features h(λ), H(λ), M(λ) (§3) of a view's 2D skeleton."""
    from ...geometry import branches

    bset = branches(graph.skeleton())
    y = graph.nodes[:, 1]
    hmin = np.array([y[c].min() for c in bset.chains])
    hmax = np.array([y[c].max() for c in bset.chains])
    mext = hmax.copy()
    for b in range(len(bset.chains) - 1, 0, -1):  # children after parents
        p = bset.parent[b]
        if p >= 0:
            mext[p] = max(mext[p], mext[b])
    return View(graph.nodes, graph.parent, list(bset.chains), bset.parent, bset.order, bset.node_branch,
                 hmin, hmax, mext)
