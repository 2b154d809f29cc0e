"""VectorTable: a layer as plain arrays (geometries + attribute columns + CRS).

Geometries are shapely objects, or ISO WKB ``bytes`` (little endian) for
measured (M) geometries, which shapely cannot hold, and for layers encoded
straight from arrays (``wkb=True``: the triangles of 3D models, the points
of :func:`point_layer`).  Core functions return VectorTables; the front ends write them: the CLI to a
GeoPackage (:mod:`sylva.core.io.gpkg`), the Processing layer to a QGIS
feature sink (so any format QGIS supports, and temporary layers inside a
Graphical Modeler graph).  Column dtypes decide field types: integers ->
integer, floats -> real, anything else -> text.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np

GEOMETRY_TYPES = ("point", "line", "polygon", "none")


@dataclass
class VectorTable:
    name: str
    geometry_type: str                   # "point" | "line" | "polygon" | "none"
    geometries: Optional[np.ndarray]     # object array of shapely geometries, or None
    columns: dict = field(default_factory=dict)  # field name -> (n,) array, in field order
    crs: Any = None                      # pyproj.CRS or None
    has_z: bool = True
    has_m: bool = False                  # geometries are then ISO WKB bytes (shapely has no M)
    wkb: bool = False                    # geometries are ISO WKB bytes (always so with has_m)
    extent: Optional[tuple] = None       # (min_x, min_y, max_x, max_y) when known, else computed

    @property
    def raw(self) -> bool:
        """True when ``geometries`` hold ISO WKB bytes rather than shapely objects."""
        return self.has_m or self.wkb

    def __post_init__(self):
        if self.geometry_type not in GEOMETRY_TYPES:
            raise ValueError(f"unknown geometry type {self.geometry_type!r}")
        n = len(self)
        for name, values in self.columns.items():
            if len(values) != n:
                raise ValueError(f"column {name!r} has {len(values)} values for {n} features")

    def __len__(self) -> int:
        if self.geometries is not None:
            return len(self.geometries)
        return len(next(iter(self.columns.values()))) if self.columns else 0

    def field_types(self) -> dict:
        """Field name -> "integer" | "real" | "text"."""
        return {name: field_type(values) for name, values in self.columns.items()}


def field_type(values: np.ndarray) -> str:
    kind = np.asarray(values).dtype.kind
    if kind in "iub":
        return "integer"
    if kind == "f":
        return "real"
    return "text"


def python_values(values: np.ndarray, kind: str) -> list:
    """A column as plain Python values for a database or QGIS (NaN -> None)."""
    arr = np.asarray(values)
    if kind == "integer":
        return [int(v) for v in arr]
    if kind == "real":
        return [None if not np.isfinite(v) else float(v) for v in arr.astype(float)]
    return [None if v is None else str(v) for v in arr]


def multilinestring_zm_wkb(parts) -> bytes:
    """ISO WKB of a MultiLineString ZM from a list of (k, 4) arrays of x, y, z, m.

    Shapely has no M coordinate; Sylva's skeleton lines carry the branch
    radius as M, so they are encoded here (little endian, types 3005 / 3002).
    """
    import struct

    chunks = [struct.pack("<BII", 1, 3005, len(parts))]
    for part in parts:
        coords = np.ascontiguousarray(part, dtype="<f8").reshape(-1, 4)
        chunks.append(struct.pack("<BII", 1, 3002, len(coords)))
        chunks.append(coords.tobytes())
    return b"".join(chunks)


#: One ISO WKB Point Z (little endian): byte order, type 1001, x, y, z.
_POINT_Z = np.dtype([("order", "u1"), ("type", "<u4"), ("xyz", "<f8", (3,))])


def point_z_wkb(xyz) -> np.ndarray:
    """ISO WKB Point Z ``bytes`` (object array) per row of an (n, 3) array of finite x, y, z.

    The bytes of ``shapely.to_wkb(shapely.points(xyz), output_dimension=3,
    flavor="iso", byte_order=1)``, encoded from the array (Sylva, not in the
    paper): a tile's ~10^5 crown points are too many to build as shapely objects.
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    rec = np.empty(len(xyz), dtype=_POINT_Z)
    rec["order"], rec["type"], rec["xyz"] = 1, 1001, xyz
    return np.array(rec.view(f"V{_POINT_Z.itemsize}").tolist(), dtype=object).reshape(-1)


def point_layer(name: str, xyz, columns: dict, crs=None) -> VectorTable:
    """A Point Z layer of the rows of ``xyz`` (n, 3), as WKB (``wkb=True``) with its extent.

    The same GeoPackage rows as a layer of ``shapely.points(xyz)``; an array
    with a non-finite coordinate gets those shapely points (their WKB and
    bounds treat NaN as GEOS does).
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    if not np.isfinite(xyz).all():
        import shapely

        return VectorTable(name, "point", shapely.points(xyz), columns, crs)
    extent = (*xyz[:, :2].min(axis=0).tolist(), *xyz[:, :2].max(axis=0).tolist()) if len(xyz) else None
    return VectorTable(name, "point", point_z_wkb(xyz), columns, crs, wkb=True, extent=extent)
