"""Tree models as a QGIS-native 3D layer: one MultiPolygonZ of triangles per tree.

    table = models_table(models, frame)            # VectorTable "models_3d", geometry "polygon"
    write_gpkg("trees_3d.gpkg", [table])           # or a QGIS feature sink

Each tree becomes one feature whose geometry is a MultiPolygon Z: every
triangle of its (coarsest available) wood mesh is one polygon part, with
vertices in SOURCE CRS coordinates (``base + v / units``, see
:mod:`.model`), so the layer sits exactly on the point cloud, the crowns and
the tree tops.  QGIS 3.22's 3D map view draws it as it is with a polygon 3D
symbol, extrusion 0 and altitude clamping "relative" with a height of minus
the tree's base (the style ``resources/styles/models_3d.qml`` sets that up:
each tree stands on the terrain, flat or the run's DTM); no plugin or
external viewer is needed, and a GeoPackage keeps it.

Light by design: the coarsest mesh a model has (``TreeModel.lods[min]``,
else its wood) and no leaf cards unless asked (``leaves=True`` adds them as
further triangles of the same feature).  Degenerate triangles (area under
1 mm^2) are left out: they carry nothing visible and GEOS calls them invalid.

Attributes: the trees' own (``TreeModel.json_attributes``: tree_id first,
then the rest in first-seen order) plus ``n_triangles``.  Column types come
from the values: integers, reals (None -> NaN) or text.
"""
from __future__ import annotations

import struct
from typing import Dict, Optional, Sequence

import numpy as np

from ..jit import njit
from ..table import VectorTable
from .model import ExportFrame, TreeModel, cached_attributes, check_models, mesh_arrays

__all__ = ["models_table", "attribute_columns", "triangle_records", "multipolygon_wkb", "MIN_TRIANGLE_AREA_M2"]

#: Triangles smaller than this (m^2) are dropped.
MIN_TRIANGLE_AREA_M2 = 1e-6


def attribute_columns(rows: Sequence[dict]) -> Dict[str, np.ndarray]:
    """Columns (key -> array) from per-feature dicts of JSON scalars, typed by their values.

    All ints (bools counted as ints) -> int64 (a missing value makes the column real);
    ints and floats -> float64 with NaN for missing; anything else -> object array of str/None.
    """
    keys = list(dict.fromkeys(k for r in rows for k in r))     # in first-seen order
    out = {}
    for key in keys:
        values = [r.get(key) for r in rows]
        present = [v for v in values if v is not None]
        types = set(map(type, present))
        numeric = types and all(issubclass(t, (bool, int, float, np.integer, np.floating)) for t in types)
        if numeric and len(present) == len(values) and all(issubclass(t, (bool, int, np.integer)) for t in types):
            out[key] = np.array([int(v) for v in values], dtype=np.int64)
        elif numeric:
            out[key] = np.array([np.nan if v is None else float(v) for v in values], dtype=np.float64)
        else:
            out[key] = np.array([None if v is None else str(v) for v in values], dtype=object)
    return out


def _pick(model: TreeModel, coarsest: bool):
    return min(model.lods) if (coarsest and model.lods) else None


#: One triangle as an ISO WKB Polygon Z (little endian): one closed ring of four points.
_TRIANGLE = np.dtype([("order", "u1"), ("type", "<u4"), ("rings", "<u4"), ("points", "<u4"),
                      ("xyz", "<f8", (4, 3))])
_HEADER = np.frombuffer(struct.pack("<BIII", 1, 1003, 1, 4), dtype=np.uint8)   # its fields before xyz


def models_table(models: Sequence[TreeModel], frame: ExportFrame, leaves: bool = False, coarsest: bool = True,
                 name: str = "models_3d", cache: Optional[dict] = None) -> VectorTable:
    """The 3D layer of ``models`` (see the module docstring); geometry None for a tree with no triangles.

    The MultiPolygon Z geometries are encoded as ISO WKB straight from the
    triangle arrays (``VectorTable.wkb``): a tile's trees hold hundreds of
    thousands of triangles, too many to build as shapely objects.  ``cache``: see
    :func:`~.model.cached` (the GLB and tileset exports of the same models may share it).
    """
    cache = {} if cache is None else cache
    models = check_models(models, "3D layer", cache)
    units = frame.resolved_units()
    scale = np.array([units.horizontal_m, units.horizontal_m, units.vertical_m])
    parts, owner = [], []
    for i, m in enumerate(models):
        parts.append(mesh_arrays(m, "wood", cache, _pick(m, coarsest)))
        owner.append(i)
        if leaves:
            parts.append(mesh_arrays(m, "leaves", cache)[:2])
            owner.append(i)
    pv = np.r_[0, np.cumsum([len(v) for v, _ in parts])[:-1]].astype(np.int64)
    pf = np.r_[0, np.cumsum([len(f) for _, f in parts])].astype(np.int64)
    rings, counts, lo, hi = _triangle_rings(np.concatenate([v for v, _ in parts]).reshape(-1, 3),
                                            np.concatenate([f for _, f in parts]).reshape(-1, 3),
                                            pv, pf, np.array(owner, dtype=np.int64),
                                            np.array([m.base for m in models]), scale, MIN_TRIANGLE_AREA_M2)
    rec = triangle_records(rings)
    geometries = np.full(len(models), None, dtype=object)
    ends = np.cumsum(counts).tolist()
    for i in np.flatnonzero(counts).tolist():
        geometries[i] = multipolygon_wkb(rec[ends[i] - int(counts[i]):ends[i]])
    columns = attribute_columns([cached_attributes(m, cache) for m in models])
    columns["n_triangles"] = counts
    extent = (lo[0], lo[1], hi[0], hi[1]) if counts.any() else None
    return VectorTable(name, "polygon", geometries, columns, frame.pyproj_crs(), has_z=True, wkb=True,
                       extent=extent)


def triangle_records(rings: np.ndarray) -> np.ndarray:
    """ISO WKB Polygon Z records of triangles, as bytes (t, 125): ``rings`` (t, 4, 3) holds corners a, b, c, a."""
    rec = np.empty((len(rings), _TRIANGLE.itemsize), dtype=np.uint8)      # _TRIANGLE records, as bytes
    rec[:, :_HEADER.size] = _HEADER
    rec[:, _HEADER.size:] = np.ascontiguousarray(rings, dtype="<f8").reshape(len(rings), 12).view(np.uint8)
    return rec


def multipolygon_wkb(records: np.ndarray) -> bytes:
    """An ISO WKB MultiPolygon Z of the :func:`triangle_records` ``records``."""
    return struct.pack("<BII", 1, 1006, len(records)) + records.tobytes()


@njit
def _triangle_rings(vertices, faces, pv, pf, owner, bases, scale, min_area):
    """(rings (t, 4, 3), triangles per tree, xy min, xy max) of the triangles kept for the 3D layer.

    Part ``p`` (a tree's mesh) owns the faces ``pf[p]:pf[p+1]`` indexing its vertices from
    ``pv[p]``; its tree is ``owner[p]``, with base ``bases[owner[p]]``.  A triangle is kept when
    its area (``0.5 |(b - a) x (c - a)|``, the numbers of ``np.cross`` and ``np.linalg.norm``) is at
    least ``min_area``; its ring is ``base + v / scale`` for its corners a, b, c, a (source CRS),
    in part order.  Sylva, not in the paper.
    """
    rings = np.empty((len(faces), 4, 3))
    counts = np.zeros(len(bases), dtype=np.int64)
    lo = np.full(2, np.inf)
    hi = np.full(2, -np.inf)
    k = 0
    for p in range(len(pv)):
        v0, tree = pv[p], owner[p]
        for t in range(pf[p], pf[p + 1]):
            a, b, c = faces[t, 0] + v0, faces[t, 1] + v0, faces[t, 2] + v0
            ux, wx = vertices[b, 0] - vertices[a, 0], vertices[c, 0] - vertices[a, 0]
            uy, wy = vertices[b, 1] - vertices[a, 1], vertices[c, 1] - vertices[a, 1]
            uz, wz = vertices[b, 2] - vertices[a, 2], vertices[c, 2] - vertices[a, 2]
            nx, ny, nz = uy * wz - uz * wy, uz * wx - ux * wz, ux * wy - uy * wx
            if not 0.5 * np.sqrt((nx * nx + ny * ny) + nz * nz) >= min_area:
                continue
            for corner in range(4):
                j = faces[t, corner % 3] + v0
                for d in range(3):
                    rings[k, corner, d] = bases[tree, d] + vertices[j, d] / scale[d]
                for d in range(2):
                    x = rings[k, corner, d]
                    if x < lo[d]:
                        lo[d] = x
                    if x > hi[d]:
                        hi[d] = x
            counts[tree] += 1
            k += 1
    return rings[:k], counts, lo, hi
