"""A small, dependency-free GeoPackage 1.2 writer and reader (sqlite3 + shapely WKB).

The CLI runs without QGIS or GDAL, yet its users expect the same layers the
Processing algorithms give; OGC GeoPackage is a SQLite file with three
metadata tables and a binary header in front of ISO WKB (OGC 12-128r18,
§1.1 and §2.1.3), so writing it needs nothing beyond the standard library.
Files are written to a temporary name and renamed when complete.
"""
from __future__ import annotations

import sqlite3
import struct
from pathlib import Path
from typing import Iterable, List

import numpy as np
import shapely

from ..atomic import atomic_path
from ..errors import InputError
from ..table import VectorTable, python_values

_GEOMETRY_NAMES = {"point": "POINT", "line": "MULTILINESTRING", "polygon": "MULTIPOLYGON"}
_SQL_TYPES = {"integer": "INTEGER", "real": "DOUBLE", "text": "TEXT"}
_CUSTOM_SRS_ID = 100000
#: Bound values per INSERT statement: SQLite's smallest default limit (SQLITE_MAX_VARIABLE_NUMBER before 3.32).
MAX_VARIABLES = 999
#: Page size of the files written here: a 3D model's ~75 kB blob spans 5 pages, not 19 (at 4096), for
#: ~4% more bytes (the half-filled last page of each blob).
PAGE_SIZE = 16384


def _srs_row(crs):
    """(srs_id, name, organization, org_id, definition) for a pyproj CRS or None."""
    if crs is None:
        return -1, "Undefined cartesian SRS", "NONE", -1, "undefined"
    wkt = crs.to_wkt("WKT1_GDAL") or crs.to_wkt()
    epsg = crs.to_epsg()
    if epsg:
        return epsg, crs.name, "EPSG", epsg, wkt
    return _CUSTOM_SRS_ID, crs.name, "NONE", _CUSTOM_SRS_ID, wkt


def _header(srs_id: int, empty: bool) -> bytes:
    flags = 0b00000001 | (0b00010000 if empty else 0)  # little endian, no envelope
    return b"GP" + bytes([0, flags]) + struct.pack("<i", srs_id)


def write_gpkg(path, tables: Iterable[VectorTable]) -> Path:
    """Write ``tables`` as the layers of one new GeoPackage at ``path`` (replaced if present)."""
    tables: List[VectorTable] = list(tables)
    with atomic_path(path) as tmp:
        con = sqlite3.connect(tmp)
        try:
            new_file_pragmas(con)
            _write(con, tables)
            con.commit()
        finally:
            con.close()
    return Path(path)


def new_file_pragmas(con: sqlite3.Connection) -> None:
    """Settings for a new GeoPackage written under a temporary name (:func:`~sylva.core.atomic.atomic_path`).

    Call before anything is written.  No rollback journal and no fsync: a
    failed write leaves only the temporary file, which is deleted; larger
    pages (:data:`PAGE_SIZE`) hold geometry blobs in fewer overflow pages.
    Sylva, not in the paper; the rows are the same, only the page layout differs.
    """
    con.execute(f"PRAGMA page_size = {PAGE_SIZE}")
    con.execute("PRAGMA journal_mode = OFF")
    con.execute("PRAGMA synchronous = OFF")


def _write(con: sqlite3.Connection, tables: List[VectorTable]) -> None:
    con.execute("PRAGMA application_id = 1196444487")  # 'GPKG'
    con.execute("PRAGMA user_version = 10200")
    con.executescript(
        """
        CREATE TABLE gpkg_spatial_ref_sys (srs_name TEXT NOT NULL, srs_id INTEGER PRIMARY KEY,
          organization TEXT NOT NULL, organization_coordsys_id INTEGER NOT NULL,
          definition TEXT NOT NULL, description TEXT);
        CREATE TABLE gpkg_contents (table_name TEXT NOT NULL PRIMARY KEY, data_type TEXT NOT NULL,
          identifier TEXT UNIQUE, description TEXT DEFAULT '',
          last_change DATETIME NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ','now')),
          min_x DOUBLE, min_y DOUBLE, max_x DOUBLE, max_y DOUBLE, srs_id INTEGER);
        CREATE TABLE gpkg_geometry_columns (table_name TEXT NOT NULL, column_name TEXT NOT NULL,
          geometry_type_name TEXT NOT NULL, srs_id INTEGER NOT NULL, z TINYINT NOT NULL,
          m TINYINT NOT NULL, CONSTRAINT pk_geom_cols PRIMARY KEY (table_name, column_name));
        """
    )
    srs = {
        (-1, "Undefined cartesian SRS", "NONE", -1, "undefined"),
        (0, "Undefined geographic SRS", "NONE", 0, "undefined"),
        (4326, "WGS 84 geodetic", "EPSG", 4326,
         'GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563]],'
         'PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433],AUTHORITY["EPSG","4326"]]'),
    }
    for table in tables:
        srs.add(_srs_row(table.crs))
    known = set()
    for row in sorted(srs, key=lambda r: r[0]):
        if row[0] not in known:
            known.add(row[0])
            con.execute("INSERT INTO gpkg_spatial_ref_sys (srs_id, srs_name, organization,"
                        " organization_coordsys_id, definition) VALUES (?,?,?,?,?)", row)
    for table in tables:
        _write_table(con, table)


def _write_table(con: sqlite3.Connection, table: VectorTable) -> None:
    name = table.name
    srs_id = _srs_row(table.crs)[0]
    types = table.field_types()
    cols = ", ".join(f'"{c}" {_SQL_TYPES[t]}' for c, t in types.items())
    spatial = table.geometry_type != "none"
    geom_col = "geom BLOB, " if spatial else ""
    con.execute(f'CREATE TABLE "{name}" (fid INTEGER PRIMARY KEY AUTOINCREMENT, {geom_col}{cols})'.replace(", )", ")"))
    n = len(table)
    values = [_python_values(v, types[c]) for c, v in table.columns.items()]
    bounds = (None,) * 4
    if spatial and table.raw:
        header = bytearray(_header(srs_id, False))   # bytearray + bytes: bytearray, bound fastest
        values = [[None if w is None else header + w for w in list(table.geometries)]] + values
        if table.extent is not None:
            bounds = tuple(float(v) for v in table.extent)
        elif n:
            geoms = shapely.from_wkb(np.asarray(table.geometries, dtype=object))
            bounds = tuple(float(v) for v in shapely.total_bounds(geoms))
    elif spatial:
        geoms = _promote(np.asarray(table.geometries, dtype=object), table.geometry_type)
        blobs = _blobs(geoms, srs_id, table.has_z)
        values = [blobs] + values
        if n:
            b = shapely.total_bounds(geoms)
            bounds = tuple(float(v) for v in b) if np.all(np.isfinite(b)) else bounds
    names = (["geom"] if spatial else []) + list(types)
    _insert_rows(con, name, names, values, n)
    con.execute(
        "INSERT INTO gpkg_contents (table_name, data_type, identifier, min_x, min_y, max_x, max_y, srs_id)"
        " VALUES (?,?,?,?,?,?,?,?)",
        (name, "features" if spatial else "attributes", name, *bounds, srs_id if spatial else None),
    )
    if spatial:
        con.execute(
            "INSERT INTO gpkg_geometry_columns VALUES (?,?,?,?,?,?)",
            (name, "geom", _GEOMETRY_NAMES[table.geometry_type], srs_id, 1 if table.has_z else 0,
             1 if table.has_m else 0),
        )


def _insert_rows(con: sqlite3.Connection, name: str, names: List[str], values: List[list], n: int) -> None:
    """INSERT ``n`` rows given as one list per column, many rows per statement.

    One ``INSERT ... VALUES (...), (...), ...`` of up to :data:`MAX_VARIABLES`
    values steps SQLite once for hundreds of rows: a tile's ~10^5 points
    cost a few thousand statement steps, not one each.  Rows keep their
    order, so their fids are those of a row-by-row insert.  Sylva, not in
    the paper.
    """
    if not names:
        con.executemany(f'INSERT INTO "{name}" DEFAULT VALUES', [()] * n)
        return
    width = len(names)
    flat = [None] * (n * width)
    for j, column in enumerate(values):
        flat[j::width] = column
    quoted = ",".join(f'"{c}"' for c in names)
    head = f'INSERT INTO "{name}" ({quoted}) VALUES '
    row = "(" + ",".join("?" * width) + ")"
    per = max(1, MAX_VARIABLES // width)            # rows per statement
    whole = n - n % per                             # rows in statements of ``per`` rows; one more for the rest
    step = per * width
    if whole:
        con.executemany(head + ",".join([row] * per), (flat[i:i + step] for i in range(0, whole * width, step)))
    if whole < n:
        con.execute(head + ",".join([row] * (n - whole)), flat[whole * width:])


def _promote(geoms: np.ndarray, geometry_type: str) -> np.ndarray:
    """Single lines/polygons become multi-part, so a layer holds one geometry type."""
    if geometry_type == "line":
        return np.array([shapely.MultiLineString([g]) if g is not None and g.geom_type == "LineString" else g
                         for g in geoms], dtype=object)
    if geometry_type == "polygon":
        return np.array([shapely.MultiPolygon([g]) if g is not None and g.geom_type == "Polygon" else g
                         for g in geoms], dtype=object)
    return geoms


def _blobs(geoms: np.ndarray, srs_id: int, has_z: bool) -> list:
    wkb = shapely.to_wkb(geoms, output_dimension=3 if has_z else 2, flavor="iso", byte_order=1)
    full, empty = bytearray(_header(srs_id, False)), bytearray(_header(srs_id, True))
    is_empty = shapely.is_empty(geoms).tolist()       # False for missing (None) geometries
    return [None if w is None else (empty if e else full) + w for w, e in zip(wkb.tolist(), is_empty)]


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


def read_gpkg(path, layer: str) -> VectorTable:
    """Read one layer written by :func:`write_gpkg` (or any simple GeoPackage layer)."""
    import pyproj

    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: file not found")
    con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        row = con.execute("SELECT data_type, srs_id FROM gpkg_contents WHERE table_name=?", (layer,)).fetchone()
        if row is None:
            raise InputError(f"{path}: no layer named {layer!r}")
        data_type, srs_id = row
        crs = None
        if srs_id is not None and srs_id > 0:
            (definition,) = con.execute(
                "SELECT definition FROM gpkg_spatial_ref_sys WHERE srs_id=?", (srs_id,)).fetchone()
            crs = pyproj.CRS.from_wkt(definition)
        geom_col, gtype = None, "none"
        if data_type == "features":
            geom_col, name = con.execute(
                "SELECT column_name, geometry_type_name FROM gpkg_geometry_columns WHERE table_name=?",
                (layer,)).fetchone()
            gtype = _geometry_kind(name)
        cur = con.execute(f'SELECT * FROM "{layer}" ORDER BY fid')
        names = [d[0] for d in cur.description]
        rows = cur.fetchall()
    except sqlite3.DatabaseError as exc:
        raise InputError(f"{path}: cannot read layer {layer!r} as a GeoPackage layer ({exc})") from None
    finally:
        con.close()
    columns = {}
    geoms = None
    for i, name in enumerate(names):
        vals = [r[i] for r in rows]
        if name == geom_col:
            geoms = np.array([None if b is None else shapely.from_wkb(_strip_header(b)) for b in vals], dtype=object)
        elif name != "fid":
            columns[name] = _column(vals)
    return VectorTable(layer, gtype, geoms, columns, crs)


def _geometry_kind(name: str) -> str:
    """"point" | "line" | "polygon" for a GeoPackage geometry type name (MULTI- and Z/M forms too)."""
    name = name.upper()
    for word, kind in (("POINT", "point"), ("LINE", "line"), ("CURVE", "line"), ("POLYGON", "polygon"),
                       ("SURFACE", "polygon")):
        if word in name:
            return kind
    return "polygon"


def layer_names(path) -> List[str]:
    """The names of the feature and attribute layers of a GeoPackage, in file order."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: file not found")
    try:
        con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
        try:
            rows = con.execute("SELECT table_name FROM gpkg_contents "
                               "WHERE data_type IN ('features', 'attributes') ORDER BY rowid").fetchall()
        finally:
            con.close()
    except sqlite3.DatabaseError as exc:
        raise InputError(f"{path}: not a GeoPackage ({exc})") from None
    return [r[0] for r in rows]


def read_layer(source: str) -> VectorTable:
    """A vector layer named as QGIS names it: ``file.gpkg`` (its only layer) or ``file.gpkg|layername=NAME``."""
    path, _, options = str(source).partition("|")
    layer = None
    for option in filter(None, options.split("|")):
        key, _, value = option.partition("=")
        if key.strip().lower() == "layername":
            layer = value.strip()
    if layer is None:
        names = layer_names(path)
        if len(names) != 1:
            raise InputError(f"{path}: holds {len(names)} layers ({', '.join(names) or 'none'}); "
                             f"name one as {path}|layername=NAME")
        layer = names[0]
    return read_gpkg(path, layer)


def _strip_header(blob: bytes) -> bytes:
    flags = blob[3]
    envelope = (flags >> 1) & 0b111
    size = {0: 0, 1: 32, 2: 48, 3: 48, 4: 64}[envelope]
    return bytes(blob[8 + size:])


def _column(vals: list) -> np.ndarray:
    if vals and all(isinstance(v, int) for v in vals):
        return np.array(vals, dtype=np.int64)
    if vals and all(isinstance(v, (int, float)) or v is None for v in vals):
        return np.array([np.nan if v is None else v for v in vals], dtype=np.float64)
    return np.array(vals, dtype=object)
