"""Writing: :func:`write_gpkg`, the layers GDAL creates, the rows, geometry blobs and extents SQLite fills in."""
from __future__ import annotations

import shutil
import sqlite3
import struct
from pathlib import Path
from typing import Dict, Iterable, List, Optional, Sequence

import numpy as np
import shapely

from ...atomic import atomic_path
from ...errors import InputError, SylvaError
from ...table import VectorTable, python_values
from .gdal import ConfigOptions, GdalErrors, bindings
from .rtree import add_rtree, blob_bounds
from .sqlite import PAGE_SIZE, insert_rows, quote
from .styles import write_styles

_RESERVED = ("gpkg_", "sqlite_", "rtree_")


def write_gpkg(path, tables: Iterable[VectorTable], styles: Optional[Dict[str, str]] = None,
               spatial_index: bool = True, update: bool = False) -> Path:
    """Write ``tables`` as layers of the GeoPackage ``path``.

    ``update=False``: a new file (an existing one is replaced).  ``update=True``
    and ``path`` an existing GeoPackage: its other layers are kept, layers of
    the same names are replaced.  ``styles``: {layer name: .qml file name in
    :data:`STYLES` or a path}, stored in ``layer_styles`` as the layer's default
    QGIS style.  ``spatial_index=False`` leaves out the R-trees (the pipeline's
    per-tile parts, which only the merge reads).
    """
    tables: List[VectorTable] = list(tables)
    _check_names(tables)
    path = Path(path)
    with atomic_path(path) as tmp:
        existing = update and path.is_file() and path.stat().st_size > 0
        if existing:
            if not _is_gpkg(path):
                raise InputError(f"{path}: exists and is not a GeoPackage; cannot add layers to it")
            shutil.copyfile(path, tmp)
        else:
            tmp.unlink()
        _create_layers(tmp, tables, existing)
        con = sqlite3.connect(tmp)
        try:
            con.execute("PRAGMA journal_mode = OFF")   # a temporary file: a failure leaves nothing to recover
            con.execute("PRAGMA synchronous = OFF")
            for table in tables:
                _fill(con, table, spatial_index)
            if existing and con.execute("SELECT 1 FROM sqlite_master WHERE name = 'layer_styles'").fetchone():
                con.executemany("DELETE FROM layer_styles WHERE f_table_name = ?", [(t.name,) for t in tables])
            if styles:
                write_styles(con, {t.name: styles[t.name] for t in tables if styles.get(t.name)})
            con.commit()
        finally:
            con.close()
    return path


def _check_names(tables: Sequence[VectorTable]) -> None:
    seen = set()
    for t in tables:
        name = str(t.name)
        if not name or name.lower().startswith(_RESERVED) or "\x00" in name:
            raise InputError(f"{name!r}: not a usable GeoPackage layer name (empty, or starting with "
                             f"{'/'.join(_RESERVED)})")
        if name.lower() in seen:
            raise InputError(f"two layers named {name!r} for one GeoPackage (names are case-insensitive)")
        seen.add(name.lower())
        for c in t.columns:
            if str(c).lower() in ("fid", "geom"):
                raise InputError(f"layer {name!r}: a column may not be named {c!r} (the GeoPackage's own)")


def _is_gpkg(path: Path) -> bool:
    with open(path, "rb") as fh:
        head = fh.read(72)
    return head[:16] == b"SQLite format 3\x00" and head[68:72] in (b"GPKG", b"GP10", b"GP11")


def _osr(crs):
    """An osr.SpatialReference for a pyproj CRS (None for None)."""
    if crs is None:
        return None
    _, _, osr = bindings()
    srs = osr.SpatialReference()
    epsg = crs.to_epsg()
    if not (epsg and srs.ImportFromEPSG(epsg) == 0):
        srs = osr.SpatialReference()
        if srs.ImportFromWkt(crs.to_wkt()) != 0:
            raise InputError(f"GDAL cannot use the CRS {crs.name!r}")
    srs.SetAxisMappingStrategy(osr.OAMS_TRADITIONAL_GIS_ORDER)
    return srs


def _geometry_type(table: VectorTable):
    _, ogr, _ = bindings()
    base = {"point": ogr.wkbPoint, "line": ogr.wkbMultiLineString, "polygon": ogr.wkbMultiPolygon,
            "none": ogr.wkbNone}[table.geometry_type]
    if base == ogr.wkbNone:
        return base
    return ogr.GT_SetModifier(base, bool(table.has_z), bool(table.has_m))


def _create_layers(tmp: Path, tables: Sequence[VectorTable], existing: bool) -> None:
    """GDAL creates the file (or opens the copy of an existing one) and every layer, without rows."""
    gdal, ogr, _ = bindings()
    kinds = {"integer": ogr.OFTInteger64, "real": ogr.OFTReal, "text": ogr.OFTString}
    with GdalErrors() as err, ConfigOptions(OGR_SQLITE_PRAGMA=f"page_size={PAGE_SIZE}",
                                              OGR_SQLITE_SYNCHRONOUS="OFF", OGR_SQLITE_JOURNAL="OFF"):
        if existing:
            ds = ogr.Open(str(tmp), 1)
        else:
            ds = ogr.GetDriverByName("GPKG").CreateDataSource(str(tmp))
        if ds is None:
            raise SylvaError(f"{tmp.name}: GDAL cannot create a GeoPackage ({err.message()})")
        try:
            for table in tables:
                old = ds.GetLayerByName(table.name)
                if old is not None:
                    for i in range(ds.GetLayerCount()):
                        if ds.GetLayer(i).GetName() == old.GetName():
                            ds.DeleteLayer(i)
                            break
                options = ["FID=fid", "SPATIAL_INDEX=NO"]
                if table.geometry_type != "none":
                    options.append("GEOMETRY_NAME=geom")
                layer = ds.CreateLayer(table.name, _osr(table.crs), _geometry_type(table), options)
                if layer is None:
                    raise SylvaError(f"layer {table.name!r}: GDAL cannot create it ({err.message()})")
                for name, kind in table.field_types().items():
                    if layer.CreateField(ogr.FieldDefn(str(name), kinds[kind])) != 0:
                        raise SylvaError(f"layer {table.name!r}: GDAL cannot create field {name!r} "
                                         f"({err.message()})")
        finally:
            ds = None


def _fill(con: sqlite3.Connection, table: VectorTable, spatial_index: bool) -> None:
    """Insert ``table``'s rows into the (empty) layer GDAL created; extents, feature count, R-tree."""
    name = table.name
    spatial = table.geometry_type != "none"
    types = table.field_types()
    n = len(table)
    values = [_python_values(v, types[c]) for c, v in table.columns.items()]
    names = list(types)
    bounds = None
    if spatial:
        srs_id = _fix_srs(con, table)
        blobs = _geometry_blobs(table, srs_id)
        bounds = blob_bounds(blobs)
        values = [blobs] + values
        names = ["geom"] + names
    triggers = _drop_triggers(con, name)        # GDAL's feature-count triggers: one UPDATE per row otherwise
    insert_rows(con, name, names, values, n)
    for sql in triggers:
        con.execute(sql)
    con.execute("UPDATE gpkg_ogr_contents SET feature_count = ? WHERE lower(table_name) = lower(?)", (n, name))
    if spatial:
        extent = table.extent
        if extent is None and n and np.isfinite(bounds).any():
            extent = (np.nanmin(bounds[:, 0]), np.nanmin(bounds[:, 2]), np.nanmax(bounds[:, 1]),
                      np.nanmax(bounds[:, 3]))
        if extent is not None:
            con.execute("UPDATE gpkg_contents SET min_x = ?, min_y = ?, max_x = ?, max_y = ? WHERE table_name = ?",
                        (*(float(v) for v in extent), name))
        if spatial_index:
            add_rtree(con, name, "geom", np.arange(1, n + 1, dtype=np.int64), bounds)


def _fix_srs(con: sqlite3.Connection, table: VectorTable) -> int:
    """The layer's srs_id; a layer without CRS gets -1 (undefined Cartesian), not GDAL's 0 (geographic)."""
    (srs_id,) = con.execute("SELECT srs_id FROM gpkg_geometry_columns WHERE table_name = ?",
                            (table.name,)).fetchone()
    if table.crs is None and srs_id != -1:
        srs_id = -1
        con.execute("UPDATE gpkg_geometry_columns SET srs_id = -1 WHERE table_name = ?", (table.name,))
        con.execute("UPDATE gpkg_contents SET srs_id = -1 WHERE table_name = ?", (table.name,))
    return int(srs_id)


def _drop_triggers(con: sqlite3.Connection, table: str) -> List[str]:
    rows = con.execute("SELECT name, sql FROM sqlite_master WHERE type = 'trigger' AND tbl_name = ?",
                       (table,)).fetchall()
    for trigger, _ in rows:
        con.execute(f"DROP TRIGGER {quote(trigger)}")
    return [sql for _, sql in rows]


def _header(srs_id: int, empty: bool) -> bytes:
    """GeoPackage binary header (OGC 12-128r18 §2.1.3): version 0, little endian, no envelope."""
    flags = 0b00000001 | (0b00010000 if empty else 0)
    return b"GP" + bytes([0, flags]) + struct.pack("<i", srs_id)


def _geometry_blobs(table: VectorTable, srs_id: int) -> list:
    """GeoPackage geometry blobs (header + ISO WKB, little endian), None for missing geometries."""
    header = bytearray(_header(srs_id, False))       # bytearray + bytes: bytearray, bound fastest
    if table.raw:
        geoms = list(table.geometries)
        if table.geometry_type != "point":
            geoms = [_promote_wkb(w) for w in geoms]
        return [None if w is None else header + w for w in geoms]
    geoms = _promote(np.asarray(table.geometries, dtype=object), table.geometry_type)
    wkb = shapely.to_wkb(geoms, output_dimension=3 if table.has_z else 2, flavor="iso", byte_order=1)
    # an empty geometry: the layer's own type and dimensions, no coordinates (a point: NaN ones), empty flag
    code = {"point": 1, "line": 5, "polygon": 6}[table.geometry_type] + (1000 if table.has_z else 0)
    tail = (struct.pack("<" + "d" * (3 if table.has_z else 2), *[float("nan")] * (3 if table.has_z else 2))
            if table.geometry_type == "point" else struct.pack("<I", 0))
    empty = bytearray(_header(srs_id, True)) + struct.pack("<BI", 1, code) + tail
    is_empty = shapely.is_empty(geoms).tolist()       # False for missing (None) geometries
    return [None if w is None else (empty if e else header + w) for w, e in zip(wkb.tolist(), is_empty)]


def _promote_wkb(wkb):
    """ISO WKB of a single LineString/Polygon (any dimensions) as a one-part Multi- geometry; others as they are."""
    if wkb is None or len(wkb) < 5:
        return wkb
    code = struct.unpack("<I" if wkb[0] == 1 else ">I", bytes(wkb[1:5]))[0]
    if code % 1000 in (2, 3) and code < 4000:
        return struct.pack("<BII", 1, code + 3, 1) + bytes(wkb)
    return wkb


def _promote(geoms: np.ndarray, geometry_type: str) -> np.ndarray:
    """Single lines/polygons become multi-part, so a layer holds one geometry type."""
    if geometry_type == "line":
        return np.array([shapely.MultiLineString([g]) if g is not None and g.geom_type == "LineString" else g
                         for g in geoms], dtype=object)
    if geometry_type == "polygon":
        return np.array([shapely.MultiPolygon([g]) if g is not None and g.geom_type == "Polygon" else g
                         for g in geoms], dtype=object)
    return geoms


def _python_values(values, kind: str) -> list:
    """:func:`sylva.core.table.python_values` (NaN -> None), by ``tolist`` for numeric columns."""
    arr = np.asarray(values)
    if kind == "integer" and arr.dtype.kind in "iub":
        return (arr.astype(np.int64) if arr.dtype.kind == "b" else arr).tolist()
    if kind == "real" and arr.dtype.kind in "iufb":
        a = arr.astype(float)
        out = a.tolist()
        for i in np.flatnonzero(~np.isfinite(a)).tolist():
            out[i] = None
        return out
    return python_values(values, kind)
