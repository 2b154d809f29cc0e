"""Tree crowns as a QGIS-native 3D layer: one closed, low-poly crown envelope per tree.

    hulls = [crown_hull(points_m, keep=top_m) for ...]     # (vertices, faces) in metres, or None
    table = crowns_table(tree_ids, hulls, origins, scale, base_z, crs)   # VectorTable "crowns_3d"

The wood of ``models_3d`` (:mod:`.gpkg3d`) seen from above is a few sticks; a
forester looks for the crowns.  A crown here is the convex hull of the
*support points* of the tree's crown points along a fixed set of directions
(:func:`hull_directions`: a Fibonacci sphere plus straight up and down): for
each direction the point farthest along it, plus the points the caller must
keep (the tree top).  That hull lies inside the convex hull of all the crown
points, touches it in every direction sampled and has at most ``2 (k + 2 + m) - 4``
triangles for ``k`` directions and ``m`` kept points (82 by default with the top),
whatever the number of points; its faces are
oriented outwards (right-hand rule), so it is a closed surface Phong shading
lights from outside.

The pipeline gives each tree's crown points (above its crown base, see
:mod:`sylva.core.measure`); ``sylva:exportmodels``, whose input is a GLB,
gives the model's leaf vertices, else its wood vertices above the crown base
height (:func:`model_crown_points`).

The layer: one MultiPolygon Z of triangles per tree in the source CRS
(absolute heights), with ``tree_id``, ``base_z`` (the ground under the stem,
as in ``models_3d``), ``height`` and ``n_triangles``;
``resources/styles/crowns_3d.qml`` clamps it like ``models_3d.qml``
(relative, height ``-"base_z"``) so crown and wood stand together on the
terrain.  Pure numpy and scipy (Sylva, not in the papers).
"""
from __future__ import annotations

from typing import Optional, Sequence, Tuple

import numpy as np

from ..table import VectorTable
from .gpkg3d import multipolygon_wkb, triangle_records

__all__ = ["hull_directions", "crown_hull", "point_crowns", "crowns_table", "model_crown_points", "N_DIRECTIONS"]

#: Directions sampled by default (plus up and down): at most 2 * (40 + 2 + 1) - 4 = 82 triangles a crown with its top.
N_DIRECTIONS = 40
_DIRECTIONS = {}


def hull_directions(k: int = N_DIRECTIONS) -> np.ndarray:
    """(k + 2, 3) unit vectors: straight up, straight down and ``k`` on a Fibonacci sphere."""
    if k not in _DIRECTIONS:
        i = np.arange(k) + 0.5
        z = 1.0 - 2.0 * i / k
        r = np.sqrt(1.0 - z * z)
        phi = np.pi * (3.0 - np.sqrt(5.0)) * i
        fib = np.column_stack([r * np.cos(phi), r * np.sin(phi), z])
        _DIRECTIONS[k] = np.vstack([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], fib])
    return _DIRECTIONS[k]


def crown_hull(points: np.ndarray, keep: Optional[np.ndarray] = None,
               directions: Optional[np.ndarray] = None) -> Optional[Tuple[np.ndarray, np.ndarray]]:
    """(vertices (v, 3), faces (f, 3) int64, outward) of a crown's envelope, or None when it has no volume.

    ``points`` (n, 3) in a metric frame (metres on every axis); ``keep`` (m, 3)
    points the hull must contain (e.g. the tree top); ``directions`` default
    :func:`hull_directions`.  See the module docstring.
    """
    from scipy.spatial import ConvexHull, QhullError

    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if keep is not None:
        keep = np.asarray(keep, dtype=np.float64).reshape(-1, 3)
        pts = np.vstack([pts, keep])
    if len(pts) < 4:
        return None
    dirs = hull_directions() if directions is None else np.asarray(directions, dtype=np.float64)
    centre = pts.mean(axis=0)
    local = pts - centre
    picked = np.unique(np.argmax(local @ dirs.T, axis=0))
    if keep is not None:
        picked = np.union1d(picked, np.arange(len(pts) - len(keep), len(pts)))
    sub = local[picked]
    if len(sub) < 4:
        return None
    try:
        hull = ConvexHull(sub)
    except QhullError:              # flat or on a line: no crown volume
        return None
    used, faces = np.unique(hull.simplices, return_inverse=True)
    faces = faces.reshape(-1, 3).astype(np.int64)
    v = sub[used]
    a, b, c = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    flip = np.einsum("ij,ij->i", np.cross(b - a, c - a), hull.equations[:, :3]) < 0
    faces[flip] = faces[flip][:, ::-1]
    return v + centre, faces


def point_crowns(xyz: np.ndarray, labels: np.ndarray, tree_ids: np.ndarray, origins: np.ndarray,
                 scale: np.ndarray, tops: np.ndarray) -> list:
    """:func:`crown_hull` of every tree ``tree_ids[i]`` from the points ``xyz[labels == tree_ids[i]]``
    (source CRS), in metres from ``origins[i]`` (``scale``: metres per CRS unit on x, y, z), each
    keeping its top ``tops[i]`` (source CRS)."""
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    labels = np.asarray(labels)
    tree_ids = np.asarray(tree_ids)
    scale = np.asarray(scale, dtype=np.float64).reshape(3)
    order = np.argsort(labels, kind="stable")
    sorted_labels = labels[order]
    starts = np.searchsorted(sorted_labels, tree_ids, side="left")
    ends = np.searchsorted(sorted_labels, tree_ids, side="right")
    out = []
    for i in range(len(tree_ids)):
        origin = np.asarray(origins[i], dtype=np.float64)
        pts = (xyz[order[starts[i]:ends[i]]] - origin) * scale
        out.append(crown_hull(pts, keep=(np.asarray(tops[i], dtype=np.float64) - origin) * scale))
    return out


def model_crown_points(model, cache: Optional[dict] = None) -> Tuple[np.ndarray, np.ndarray]:
    """(crown points (n, 3), top (1, 3)) of a :class:`~.model.TreeModel`, in its local metres.

    The leaf vertices when it has leaves; else the wood vertices at or above its
    ``crown_base_height`` attribute (all of them without one, or when none is that
    high).  The top is the model's highest vertex (wood or leaves).
    """
    from .model import mesh_arrays

    cache = {} if cache is None else cache
    wood = mesh_arrays(model, "wood", cache)[0]
    leaves = mesh_arrays(model, "leaves", cache)[0]
    every = np.vstack([wood, leaves])
    top = every[[int(np.argmax(every[:, 2]))]] if len(every) else np.zeros((0, 3))
    if len(leaves):
        return leaves, top
    base = model.attributes.get("crown_base_height")
    try:
        base = float(base)
    except (TypeError, ValueError):
        base = float("nan")
    if np.isfinite(base):
        above = wood[wood[:, 2] >= base]
        if len(above) >= 4:
            return above, top
    return wood, top


def crowns_table(tree_ids: Sequence[int], hulls: Sequence, origins: np.ndarray, scale: np.ndarray,
                 base_z: np.ndarray, crs, height: Optional[np.ndarray] = None,
                 name: str = "crowns_3d") -> VectorTable:
    """The 3D crown layer: tree ``i``'s hull ``hulls[i]`` (``crown_hull``'s output, in metres, or None)
    placed at ``origins[i] + vertices / scale`` in the source CRS (``scale``: metres per CRS unit on x,
    y, z); ``base_z`` the ground under each stem (source CRS), ``height`` the tree heights (m)."""
    n = len(tree_ids)
    origins = np.asarray(origins, dtype=np.float64).reshape(n, 3)
    scale = np.asarray(scale, dtype=np.float64).reshape(3)
    geometries = np.full(n, None, dtype=object)
    counts = np.zeros(n, dtype=np.int64)
    lo, hi = np.full(2, np.inf), np.full(2, -np.inf)
    for i, h in enumerate(hulls):
        if h is None:
            continue
        v, f = h
        xyz = origins[i] + v / scale
        geometries[i] = multipolygon_wkb(triangle_records(xyz[np.column_stack([f, f[:, :1]])]))   # a, b, c, a
        counts[i] = len(f)
        lo, hi = np.minimum(lo, xyz[:, :2].min(axis=0)), np.maximum(hi, xyz[:, :2].max(axis=0))
    columns = {"tree_id": np.asarray(tree_ids, dtype=np.int64), "base_z": np.asarray(base_z, dtype=np.float64)}
    if height is not None:
        columns["height"] = np.asarray(height, dtype=np.float64)
    columns["n_triangles"] = counts
    extent = (lo[0], lo[1], hi[0], hi[1]) if counts.any() else None
    return VectorTable(name, "polygon", geometries, columns, crs, has_z=True, wkb=True, extent=extent)
