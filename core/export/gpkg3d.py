"""Tree models as a QGIS-native 3D layer: one MultiPolygonZ of triangles per tree.

    table = models_table(models, frame)            # VectorTable "models_3d", geometry "polygon"
    write_gpkg("trees_3d.gpkg", [table])           # or a QGIS feature sink

Each tree becomes one feature whose geometry is a MultiPolygon Z: every
triangle of its (coarsest available) wood mesh is one polygon part, with
vertices in SOURCE CRS coordinates (``base + v / units``, see
:mod:`.model`), so the layer sits exactly on the point cloud, the crowns and
the tree tops.  QGIS 3.22's 3D map view draws it as it is with a polygon 3D
symbol, altitude clamping "absolute" and extrusion 0 (the style
``resources/styles/models_3d.qml`` sets that up); no plugin or external
viewer is needed, and a GeoPackage keeps it.

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
from typing import Dict, List, Sequence

import numpy as np

from ..table import VectorTable
from .model import ExportFrame, TreeModel, check_models

__all__ = ["models_table", "attribute_columns", "MIN_TRIANGLE_AREA_M2"]

#: Triangles smaller than this (m^2) are dropped.
MIN_TRIANGLE_AREA_M2 = 1e-6


def attribute_columns(rows: Sequence[dict]) -> Dict[str, np.ndarray]:
    """Columns (key -> array) from per-feature dicts of JSON scalars, typed by their values.

    All ints (bools counted as ints) -> int64 (a missing value makes the column real);
    ints and floats -> float64 with NaN for missing; anything else -> object array of str/None.
    """
    keys: List[str] = []
    for r in rows:
        keys.extend(k for k in r if k not in keys)
    out = {}
    for key in keys:
        values = [r.get(key) for r in rows]
        present = [v for v in values if v is not None]
        numeric = present and all(isinstance(v, (bool, int, float, np.integer, np.floating)) for v in present)
        if numeric and len(present) == len(values) and all(
                isinstance(v, (bool, int, np.integer)) for v in present):
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


def models_table(models: Sequence[TreeModel], frame: ExportFrame, leaves: bool = False, coarsest: bool = True,
                 name: str = "models_3d") -> VectorTable:
    """The 3D layer of ``models`` (see the module docstring); geometry None for a tree with no triangles.

    The MultiPolygon Z geometries are encoded as ISO WKB straight from the
    triangle arrays (``VectorTable.wkb``): a tile's trees hold hundreds of
    thousands of triangles, too many to build as shapely objects."""
    models = check_models(models, "3D layer")
    units = frame.resolved_units()
    scale = np.array([units.horizontal_m, units.horizontal_m, units.vertical_m])
    geometries = np.full(len(models), None, dtype=object)
    counts = np.zeros(len(models), dtype=np.int64)
    lo, hi = np.full(2, np.inf), np.full(2, -np.inf)
    for i, m in enumerate(models):
        parts = [m.wood_arrays(_pick(m, coarsest))]
        if leaves:
            parts.append(m.leaf_arrays()[:2])
        tris = []
        for v, f in parts:
            if len(f):
                tri = v[f]                                               # (k, 3, 3) local metres
                area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
                tris.append(tri[area >= MIN_TRIANGLE_AREA_M2])
        src = m.base + np.concatenate(tris) / scale if tris else np.zeros((0, 3, 3))   # source CRS
        if len(src) == 0:
            continue
        rec = np.empty(len(src), dtype=_TRIANGLE)
        rec["order"], rec["type"], rec["rings"], rec["points"] = 1, 1003, 1, 4
        rec["xyz"][:, :3] = src
        rec["xyz"][:, 3] = src[:, 0]                                     # closed ring
        geometries[i] = struct.pack("<BII", 1, 1006, len(src)) + rec.tobytes()
        counts[i] = len(src)
        lo = np.minimum(lo, src[..., :2].min(axis=(0, 1)))
        hi = np.maximum(hi, src[..., :2].max(axis=(0, 1)))
    columns = attribute_columns([m.json_attributes() for m in models])
    columns["n_triangles"] = counts
    extent = (lo[0], lo[1], hi[0], hi[1]) if counts.any() else None
    return VectorTable(name, "polygon", geometries, columns, frame.pyproj_crs(), has_z=True, wkb=True,
                       extent=extent)
