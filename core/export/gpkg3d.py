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


def models_table(models: Sequence[TreeModel], frame: ExportFrame, leaves: bool = False, coarsest: bool = True,
                 name: str = "models_3d") -> VectorTable:
    """The 3D layer of ``models`` (see the module docstring); geometry None for a tree with no triangles."""
    import shapely

    models = check_models(models, "3D layer")
    units = frame.resolved_units()
    scale = np.array([units.horizontal_m, units.horizontal_m, units.vertical_m])
    rings, owner = [], []
    counts = np.zeros(len(models), dtype=np.int64)
    for i, m in enumerate(models):
        parts = [m.wood_arrays(_pick(m, coarsest))]
        if leaves:
            parts.append(m.leaf_arrays()[:2])
        for v, f in parts:
            if len(f) == 0:
                continue
            tri = v[f]                                                   # (k, 3, 3) local metres
            area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
            tri = tri[area >= MIN_TRIANGLE_AREA_M2]
            src = m.base + tri / scale                                   # source CRS coordinates
            rings.append(np.concatenate([src, src[:, :1]], axis=1))      # closed rings (k, 4, 3)
            owner.append(np.full(len(src), i, dtype=np.int64))
            counts[i] += len(src)
    geometries = np.full(len(models), None, dtype=object)
    if rings:
        polygons = shapely.polygons(np.concatenate(rings))
        idx = np.concatenate(owner)
        multi = shapely.multipolygons(polygons, indices=idx)     # one per tree that has triangles
        geometries[np.unique(idx)] = multi
    columns = attribute_columns([m.json_attributes() for m in models])
    columns["n_triangles"] = counts
    return VectorTable(name, "polygon", geometries, columns, frame.pyproj_crs(), has_z=True)
