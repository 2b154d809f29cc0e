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

from .jit import njit

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


_WKB_HEADER = np.dtype([("order", "u1"), ("type", "<u4"), ("count", "<u4")])  # packed: 9 bytes


def multilinestring_zm_wkbs(coords: np.ndarray, part_len: np.ndarray, n_parts: np.ndarray) -> list:
    """ISO WKB MultiLineString ZM per feature (little endian, types 3005 / 3002), vectorised.

    ``coords`` (n, 4) x, y, z, m of all parts of all features in order; ``part_len`` (p,) points
    per part; ``n_parts`` (f,) parts per feature.  Shapely has no M coordinate; Sylva's skeleton lines
    carry the branch radius as M, so they are encoded here.
    """
    nf, npart = len(n_parts), len(part_len)
    feat_of_part = np.repeat(np.arange(nf), n_parts)
    # items in buffer order: feature header, then its parts (header + coordinates)
    part_item = feat_of_part + 1 + np.arange(npart)
    feat_item = np.arange(nf) + np.r_[0, np.cumsum(n_parts)[:-1]]
    size = np.empty(nf + npart, dtype=np.int64)
    size[feat_item] = 9
    size[part_item] = 9 + 32 * part_len
    start = np.r_[0, np.cumsum(size)]
    hdr = np.empty(nf + npart, dtype=_WKB_HEADER)
    hdr["order"] = 1
    hdr["type"][feat_item], hdr["count"][feat_item] = 3005, n_parts
    hdr["type"][part_item], hdr["count"][part_item] = 3002, part_len
    body = np.zeros(nf + npart, dtype=np.int64)
    body[part_item] = 32 * part_len
    buf = _wkb_pack(hdr.view(np.uint8).reshape(-1, 9), body,
                    np.ascontiguousarray(coords, dtype="<f8").view(np.uint8).reshape(-1), int(start[-1]))
    ends = start[feat_item + 1 + n_parts].tolist()
    begins = start[feat_item].tolist()
    return [buf[a:b].tobytes() for a, b in zip(begins, ends)]


@njit
def _wkb_pack(headers, body, data, size):
    """The WKB buffer: every item's 9 header bytes, each followed by its next ``body`` bytes of ``data``."""
    buf = np.empty(size, np.uint8)
    pos = 0
    src = 0
    for it in range(headers.shape[0]):
        buf[pos:pos + 9] = headers[it]
        pos += 9
        n = body[it]
        buf[pos:pos + n] = data[src:src + n]
        pos += n
        src += n
    return buf


def multilinestring_zm_wkb(parts) -> bytes:
    """ISO WKB of one MultiLineString ZM from a list of (k, 4) arrays of x, y, z, m
    (:func:`multilinestring_zm_wkbs` of one feature)."""
    parts = [np.asarray(p, dtype=np.float64).reshape(-1, 4) for p in parts]
    coords = np.concatenate(parts) if parts else np.zeros((0, 4))
    return multilinestring_zm_wkbs(coords, np.array([len(p) for p in parts], dtype=np.int64),
                                   np.array([len(parts)], dtype=np.int64))[0]


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
