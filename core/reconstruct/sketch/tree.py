"""The whole sketch method: :func:`tree_from_sketch` (§4-§6) from two views' strokes, silhouettes and the
tree height to a :class:`SketchResult` (the drawing frame is the package docstring's), with the views'
projections and :func:`projection_error`."""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Dict, List, Sequence

import numpy as np

from ...errors import InputError
from ...progress import CancelCheck, Progress, check, report, scaled
from ..model import Skeleton
from .depth import depth_retrieval
from .params import SketchTree
from .small_branches import grow_small_branches
from .strokes import StrokeGraph, stroke_graph


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
