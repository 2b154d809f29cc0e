"""GeoPackage layers with GDAL/OGR: conforming files, R-tree indexes, QGIS styles, bulk rows.

    write_gpkg("out.gpkg", [tops, crowns], styles={"crowns": "crowns.qml"})
    write_gpkg("out.gpkg", [trees], update=True)       # add/replace a layer, keep the others
    table = read_layer("out.gpkg|layername=crowns")

GDAL/OGR (``osgeo``: Debian's python3-gdal, in every QGIS install) creates
each file and layer: the metadata tables, the SRS, the geometry column
declared with its type (OGC 12-128r18 Req 25/31), ``gpkg_ogr_contents``;
``validate_gpkg.py`` (GDAL's validator) reports no failure on what is
written here.  The rows are then inserted with SQLite in bulk, many rows per
statement (OGR's per-feature ``CreateFeature`` from Python costs ~30 us a
feature, 20x this; GDAL 3.6 has no Arrow writing), and every geometry
column gets the GeoPackage R-tree extension (``gpkg_rtree_index``, Annex
F.3): the ``rtree_<table>_<column>`` table bulk-loaded from the
geometries' envelopes (sort-tile-recursive packing written straight into the
R-tree's node tables, ~1 us a feature; an R-tree ``INSERT`` costs ~20 us)
and GDAL's seven triggers, so QGIS and GDAL keep it current on later edits.
Styles go into QGIS's ``layer_styles`` table, so a file opens styled in any
QGIS.  Files are written under a temporary name and renamed when complete.
Layer and column names are always quoted as SQL identifiers or bound.
(Sylva, not in the papers.)
"""
from __future__ import annotations

import shutil
import sqlite3
import struct
from pathlib import Path
from typing import Dict, Iterable, List, Optional, Sequence

import numpy as np
import shapely

from ..atomic import atomic_path
from ..errors import InputError, SylvaError
from ..jit import njit
from ..table import VectorTable, python_values

__all__ = ["write_gpkg", "read_gpkg", "read_layer", "layer_names", "GpkgMerge", "STYLES", "quote",
           "split_source", "PAGE_SIZE"]

#: Bound values per INSERT statement: SQLite's smallest default limit (SQLITE_MAX_VARIABLE_NUMBER before 3.32).
MAX_VARIABLES = 999
#: Page size of the files written here: a 3D model's ~75 kB blob spans 5 pages, not 19 (at 4096), for
#: ~4% more bytes (the half-filled last page of each blob).
PAGE_SIZE = 16384
#: The .qml files that ``styles`` and Param.style name.
STYLES = Path(__file__).resolve().parents[2] / "resources" / "styles"
#: Parts are read through a memory map of up to this many bytes each (SQLite's mmap_size), not read() calls.
MERGE_MMAP_BYTES = 1 << 30

_GEOMETRY_NAMES = {"point": "POINT", "line": "MULTILINESTRING", "polygon": "MULTIPOLYGON"}
_RESERVED = ("gpkg_", "sqlite_", "rtree_")


def quote(name: str) -> str:
    """``name`` as an SQL identifier (double quotes, inner quotes doubled)."""
    return '"' + str(name).replace('"', '""') + '"'


def _ogr():
    try:
        from osgeo import gdal, ogr, osr
    except ImportError:
        raise SylvaError("GeoPackage output needs GDAL's Python bindings (osgeo): install python3-gdal "
                         "(Debian/Ubuntu, as QGIS does) or the GDAL wheel matching the system's GDAL") from None
    return gdal, ogr, osr


class _GdalErrors:
    """Collect GDAL's messages quietly (no global UseExceptions, which would change QGIS's GDAL for others)."""

    def __enter__(self):
        gdal = _ogr()[0]
        self.gdal = gdal
        gdal.PushErrorHandler("CPLQuietErrorHandler")
        gdal.ErrorReset()
        return self

    def message(self) -> str:
        return self.gdal.GetLastErrorMsg() or "unknown GDAL error"

    def __exit__(self, *exc):
        self.gdal.PopErrorHandler()
        return False


class _ConfigOptions:
    """GDAL configuration options for this thread only, restored afterwards."""

    def __init__(self, **options):
        self.options = options

    def __enter__(self):
        gdal = _ogr()[0]
        self.gdal = gdal
        self.old = {k: gdal.GetThreadLocalConfigOption(k, None) for k in self.options}
        for k, v in self.options.items():
            gdal.SetThreadLocalConfigOption(k, v)
        return self

    def __exit__(self, *exc):
        for k, v in self.old.items():
            self.gdal.SetThreadLocalConfigOption(k, v)
        return False


# --------------------------------------------------------------------------- writing

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
    _, _, osr = _ogr()
    srs = osr.SpatialReference()
    epsg = crs.to_epsg()
    if not (epsg and srs.ImportFromEPSG(epsg) == 0):
        srs = osr.SpatialReference()
        if srs.ImportFromWkt(crs.to_wkt()) != 0:
            raise InputError(f"GDAL cannot use the CRS {crs.name!r}")
    srs.SetAxisMappingStrategy(osr.OAMS_TRADITIONAL_GIS_ORDER)
    return srs


def _geometry_type(table: VectorTable):
    _, ogr, _ = _ogr()
    base = {"point": ogr.wkbPoint, "line": ogr.wkbMultiLineString, "polygon": ogr.wkbMultiPolygon,
            "none": ogr.wkbNone}[table.geometry_type]
    if base == ogr.wkbNone:
        return base
    return ogr.GT_SetModifier(base, bool(table.has_z), bool(table.has_m))


def _create_layers(tmp: Path, tables: Sequence[VectorTable], existing: bool) -> None:
    """GDAL creates the file (or opens the copy of an existing one) and every layer, without rows."""
    gdal, ogr, _ = _ogr()
    kinds = {"integer": ogr.OFTInteger64, "real": ogr.OFTReal, "text": ogr.OFTString}
    with _GdalErrors() as err, _ConfigOptions(OGR_SQLITE_PRAGMA=f"page_size={PAGE_SIZE}",
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
    _insert_rows(con, name, names, values, n)
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


def _insert_rows(con: sqlite3.Connection, name: str, names: List[str], values: List[list], n: int) -> None:
    """INSERT ``n`` rows given as one list per column, many rows per statement.

    One ``INSERT ... VALUES (...), (...), ...`` of up to :data:`MAX_VARIABLES`
    values steps SQLite once for hundreds of rows: a tile's ~10^5 points
    cost a few thousand statement steps, not one each.  Rows keep their
    order, so their fids are 1..n in order.  Sylva, not in the paper.
    """
    if not names:
        con.executemany(f"INSERT INTO {quote(name)} DEFAULT VALUES", [()] * n)
        return
    width = len(names)
    flat = [None] * (n * width)
    for j, column in enumerate(values):
        flat[j::width] = column
    head = f"INSERT INTO {quote(name)} ({','.join(quote(c) for c in names)}) VALUES "
    row = "(" + ",".join("?" * width) + ")"
    per = max(1, MAX_VARIABLES // width)            # rows per statement
    whole = n - n % per                             # rows in statements of ``per`` rows; one more for the rest
    step = per * width
    if whole:
        con.executemany(head + ",".join([row] * per), (flat[i:i + step] for i in range(0, whole * width, step)))
    if whole < n:
        con.execute(head + ",".join([row] * (n - whole)), flat[whole * width:])


# --------------------------------------------------------------------------- envelopes and R-trees

def blob_bounds(blobs: Sequence) -> np.ndarray:
    """(n, 4) min_x, max_x, min_y, max_y of GeoPackage geometry blobs (NaN rows: missing or empty)."""
    n = len(blobs)
    lengths = np.fromiter((0 if b is None else len(b) for b in blobs), dtype=np.int64, count=n)
    offsets = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(lengths, out=offsets[1:])
    buf = np.frombuffer(b"".join(b for b in blobs if b is not None), dtype=np.uint8)
    out = np.full((n, 4), np.nan)
    if n:
        bad = _blob_bounds(buf, offsets, out)
        if bad >= 0:
            raise SylvaError(f"geometry {bad + 1}: not a GeoPackage geometry blob Sylva can index")
    return out


@njit
def _blob_bounds(buf, offsets, out):
    """Envelopes of GeoPackage blobs ``buf[offsets[i]:offsets[i+1]]`` into ``out`` (min_x, max_x, min_y, max_y).

    Reads the blob header (OGC 12-128r18 §2.1.3: flags, envelope size, empty
    bit) and walks the ISO or extended WKB (either byte order; Point,
    LineString, Polygon and their Multi/Collection forms one level deep; Z, M,
    ZM).  Returns the index of the first blob it cannot read, else -1.
    Sylva, not in the paper.
    """
    word = np.zeros(1, dtype=np.uint64)
    real = word.view(np.float64)
    for i in range(len(offsets) - 1):
        p, end = offsets[i], offsets[i + 1]
        if end - p == 0:
            continue
        if end - p < 8 or buf[p] != 71 or buf[p + 1] != 80:
            return i
        flags = buf[p + 3]
        if flags & 16:
            continue                                            # empty geometry: no envelope, no R-tree entry
        env = (flags >> 1) & 7
        p += 8 + (0 if env == 0 else (32 if env == 1 else (48 if env < 4 else 64)))
        lo_x, hi_x, lo_y, hi_y = np.inf, -np.inf, np.inf, -np.inf
        # stack of pending geometries: (remaining count at this level); depth <= 2 (collection -> part)
        todo_outer = 1
        inner_left = 0
        ok = True
        while ok and (todo_outer > 0 or inner_left > 0):
            if end - p < 5:
                ok = False
                break
            little = buf[p] == 1
            t = 0
            for k in range(4):
                t |= int(buf[p + 1 + k]) << (8 * k if little else 8 * (3 - k))
            p += 5
            dims = 2
            if t & 0x80000000:
                dims += 1
            if t & 0x40000000:
                dims += 1
            t &= 0x0FFFFFFF
            if t >= 1000:
                dims = 2 + (1 if (t // 1000) in (1, 3) else 0) + (1 if (t // 1000) in (2, 3) else 0)
                t %= 1000
            if inner_left > 0:
                inner_left -= 1
            else:
                todo_outer -= 1
            if t >= 4 and t <= 7:                               # multi/collection: its parts follow
                if end - p < 4:
                    ok = False
                    break
                c = 0
                for k in range(4):
                    c |= int(buf[p + k]) << (8 * k if little else 8 * (3 - k))
                p += 4
                inner_left += c
                continue
            if t < 1 or t > 3:
                ok = False
                break
            rings = 1
            if t == 3:
                rings = 0
                for k in range(4):
                    rings |= int(buf[p + k]) << (8 * k if little else 8 * (3 - k))
                p += 4
            for _ in range(rings):
                npts = 1
                if t != 1:
                    npts = 0
                    for k in range(4):
                        npts |= int(buf[p + k]) << (8 * k if little else 8 * (3 - k))
                    p += 4
                if end - p < npts * dims * 8:
                    ok = False
                    break
                for _j in range(npts):
                    for d in range(2):
                        u = np.uint64(0)
                        for k in range(8):
                            u |= np.uint64(buf[p + d * 8 + k]) << np.uint64(8 * k if little else 8 * (7 - k))
                        word[0] = u
                        v = real[0]
                        if d == 0:
                            lo_x = min(lo_x, v)
                            hi_x = max(hi_x, v)
                        else:
                            lo_y = min(lo_y, v)
                            hi_y = max(hi_y, v)
                    p += dims * 8
        if not ok:
            return i
        if lo_x <= hi_x and lo_y <= hi_y:                       # NaN coordinates or no points: not indexed
            out[i, 0], out[i, 1], out[i, 2], out[i, 3] = lo_x, hi_x, lo_y, hi_y
    return -1


_RTREE_TRIGGERS = (
    ("insert", 'AFTER INSERT ON {t} WHEN (new.{g} NOT NULL AND NOT ST_IsEmpty(NEW.{g})) BEGIN INSERT OR REPLACE '
               'INTO {r} VALUES (NEW.{i},ST_MinX(NEW.{g}), ST_MaxX(NEW.{g}),ST_MinY(NEW.{g}), ST_MaxY(NEW.{g})); END'),
    ("update1", 'AFTER UPDATE OF {g} ON {t} WHEN OLD.{i} = NEW.{i} AND (NEW.{g} NOTNULL AND NOT ST_IsEmpty(NEW.{g})) '
                'BEGIN INSERT OR REPLACE INTO {r} VALUES (NEW.{i},ST_MinX(NEW.{g}), ST_MaxX(NEW.{g}),'
                'ST_MinY(NEW.{g}), ST_MaxY(NEW.{g})); END'),
    ("update2", 'AFTER UPDATE OF {g} ON {t} WHEN OLD.{i} = NEW.{i} AND (NEW.{g} ISNULL OR ST_IsEmpty(NEW.{g})) '
                'BEGIN DELETE FROM {r} WHERE id = OLD.{i}; END'),
    ("update3", 'AFTER UPDATE ON {t} WHEN OLD.{i} != NEW.{i} AND (NEW.{g} NOTNULL AND NOT ST_IsEmpty(NEW.{g})) '
                'BEGIN DELETE FROM {r} WHERE id = OLD.{i}; INSERT OR REPLACE INTO {r} VALUES (NEW.{i},'
                'ST_MinX(NEW.{g}), ST_MaxX(NEW.{g}),ST_MinY(NEW.{g}), ST_MaxY(NEW.{g})); END'),
    ("update4", 'AFTER UPDATE ON {t} WHEN OLD.{i} != NEW.{i} AND (NEW.{g} ISNULL OR ST_IsEmpty(NEW.{g})) '
                'BEGIN DELETE FROM {r} WHERE id IN (OLD.{i}, NEW.{i}); END'),
    ("delete", 'AFTER DELETE ON {t} WHEN old.{g} NOT NULL BEGIN DELETE FROM {r} WHERE id = OLD.{i}; END'),
)

_EXTENSIONS_SQL = ("CREATE TABLE IF NOT EXISTS gpkg_extensions (table_name TEXT,column_name TEXT,"
                   "extension_name TEXT NOT NULL,definition TEXT NOT NULL,scope TEXT NOT NULL,"
                   "CONSTRAINT ge_tce UNIQUE (table_name, column_name, extension_name))")


def add_rtree(con: sqlite3.Connection, table: str, column: str, ids: np.ndarray, bounds: np.ndarray) -> None:
    """The GeoPackage R-tree extension for ``table.column`` (Annex F.3), with GDAL's triggers.

    ``ids`` (the rows' fids) and ``bounds`` (n, 4: min_x, max_x, min_y, max_y;
    NaN rows are left out, as missing and empty geometries are; float32 ones
    are taken as already rounded by :func:`outward_float32`) fill
    ``rtree_<table>_<column>`` by :func:`_pack_rtree`.
    """
    rtree = f"rtree_{table}_{column}"
    con.execute(f"CREATE VIRTUAL TABLE {quote(rtree)} USING rtree(id, minx, maxx, miny, maxy)")
    keep = np.isfinite(bounds).all(axis=1)
    boxes = bounds[keep] if bounds.dtype == np.float32 else outward_float32(bounds[keep])
    _pack_rtree(con, rtree, np.asarray(ids, dtype=np.int64)[keep], boxes)
    for suffix, body in _RTREE_TRIGGERS:
        con.execute(f"CREATE TRIGGER {quote(rtree + '_' + suffix)} "
                    + body.format(t=quote(table), g=quote(column), i=quote("fid"), r=quote(rtree)))
    con.execute(_EXTENSIONS_SQL)
    con.execute("INSERT OR REPLACE INTO gpkg_extensions VALUES (?, ?, 'gpkg_rtree_index', "
                "'http://www.geopackage.org/spec120/#extension_rtree', 'write-only')", (table, column))


#: One R-tree cell as SQLite stores it (ext/rtree/rtree.c): 64-bit id, then 4 float32, all big-endian.
_CELL = np.dtype([("id", ">i8"), ("box", ">f4", (4,))])


def outward_float32(bounds: np.ndarray) -> np.ndarray:
    """(n, 4) min_x, max_x, min_y, max_y as float32 rounded outwards, as SQLite's R-tree stores them."""
    box = bounds.astype(np.float32)
    for k, toward in ((0, -np.inf), (1, np.inf), (2, -np.inf), (3, np.inf)):
        v = box[:, k]
        off = (v > bounds[:, k]) if toward < 0 else (v < bounds[:, k])
        v[off] = np.nextafter(v[off], np.float32(toward))
    return box


def _pack_rtree(con: sqlite3.Connection, rtree: str, ids: np.ndarray, box: np.ndarray) -> None:
    """Bulk-load the SQLite R-tree ``rtree`` (created empty) with ``ids`` and their float32 boxes ``box``.

    Sort-tile-recursive packing (Leutenegger et al. 1997): entries sorted into
    vertical slices by x centre, by y centre within a slice, and cut into full
    nodes; the nodes of each level packed the same way until one root remains.
    The nodes are written into the R-tree's ``_node``, ``_parent`` and
    ``_rowid`` tables in SQLite's own layout (node 1 the root, its first two
    bytes the depth; big-endian cells; float32 boxes rounded outwards as
    SQLite's own inserts round them), which ``rtreecheck()`` verifies in the
    tests.  Sylva, not in the paper (GDAL >= 3.7 builds its R-trees so too).
    """
    n = len(ids)
    if n == 0:
        return
    (size,) = con.execute(f"SELECT length(data) FROM {quote(rtree + '_node')} WHERE nodeno = 1").fetchone()
    per = (size - 4) // _CELL.itemsize
    entries, boxes = ids, box
    levels = []                                                  # (entries, boxes, node of each entry)
    while True:
        order = _str_order(boxes, per)
        entries, boxes = entries[order], boxes[order]
        count = len(entries)
        nodes = -(-count // per)
        node_of = np.arange(count) // per
        levels.append((entries, boxes, node_of, nodes))
        if nodes == 1:
            break
        starts = np.arange(nodes) * per
        boxes = np.column_stack([np.minimum.reduceat(boxes[:, 0], starts), np.maximum.reduceat(boxes[:, 1], starts),
                                 np.minimum.reduceat(boxes[:, 2], starts), np.maximum.reduceat(boxes[:, 3], starts)])
        entries = np.arange(nodes, dtype=np.int64)               # numbered below, once every level is known
    # node numbers: the root 1, then each level from the top down
    numbers, next_no = [None] * len(levels), 2
    numbers[-1] = np.array([1], dtype=np.int64)
    for lv in range(len(levels) - 2, -1, -1):
        nodes = levels[lv][3]
        numbers[lv] = np.arange(next_no, next_no + nodes, dtype=np.int64)
        next_no += nodes
    depth = len(levels) - 1
    node_rows, parent_rows = [], []
    for lv, (entries, boxes, node_of, nodes) in enumerate(levels):
        cell_ids = entries if lv == 0 else numbers[lv - 1][entries]
        cells = np.zeros(nodes * per, dtype=_CELL)
        cells["id"][:len(entries)] = cell_ids
        cells["box"][:len(entries)] = boxes
        blobs = np.zeros((nodes, size), dtype=np.uint8)
        blobs[:, 4:4 + per * _CELL.itemsize] = cells.view(np.uint8).reshape(nodes, -1)
        counts = np.bincount(node_of, minlength=nodes).astype(">u2")
        blobs[:, 2:4] = counts.view(np.uint8).reshape(nodes, 2)
        if lv == depth:
            blobs[0, 0:2] = np.frombuffer(struct.pack(">H", depth), dtype=np.uint8)
        node_rows.extend(zip(numbers[lv].tolist(), [b.tobytes() for b in blobs]))
        if lv > 0:
            parent_rows.extend(zip(cell_ids.tolist(), numbers[lv][node_of].tolist()))
        else:
            leaf = np.argsort(entries, kind="stable")
            rowids = [entries[leaf].tolist(), numbers[0][node_of[leaf]].tolist()]
    con.execute(f"DELETE FROM {quote(rtree + '_node')}")
    node_rows.sort()
    parent_rows.sort()
    _insert_rows(con, rtree + "_node", ["nodeno", "data"], [list(c) for c in zip(*node_rows)], len(node_rows))
    if parent_rows:
        _insert_rows(con, rtree + "_parent", ["nodeno", "parentnode"], [list(c) for c in zip(*parent_rows)],
                     len(parent_rows))
    _insert_rows(con, rtree + "_rowid", ["rowid", "nodeno"], rowids, n)


def read_rtree(con: sqlite3.Connection, schema: str, rtree: str) -> tuple:
    """(ids, float32 boxes) of every entry of the R-tree ``schema.rtree``, read from its leaf nodes."""
    leaves = con.execute(f"SELECT data FROM {schema}.{quote(rtree + '_node')} WHERE nodeno IN "
                         f"(SELECT DISTINCT nodeno FROM {schema}.{quote(rtree + '_rowid')})").fetchall()
    if not leaves:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 4), dtype=np.float32)
    size = len(leaves[0][0])
    per = (size - 4) // _CELL.itemsize
    raw = np.frombuffer(b"".join(d for (d,) in leaves), dtype=np.uint8).reshape(len(leaves), size)
    counts = raw[:, 2].astype(np.int64) * 256 + raw[:, 3]
    cells = raw[:, 4:4 + per * _CELL.itemsize].copy().view(_CELL).reshape(len(leaves), per)
    used = np.arange(per)[None, :] < counts[:, None]
    cells = cells[used]
    return cells["id"].astype(np.int64), cells["box"].astype(np.float32)


def _str_order(boxes: np.ndarray, per: int) -> np.ndarray:
    """Sort-tile-recursive order of ``boxes`` (n, 4) for nodes of ``per`` entries.

    Two single-key sorts: by x centre (then slabs of ``slices * per`` entries),
    then by one float key, slab-major and y centre within the slab.
    """
    n = len(boxes)
    cx = boxes[:, 0].astype(np.float64) + boxes[:, 1]            # twice the centres: the order is the same
    cy = boxes[:, 2].astype(np.float64) + boxes[:, 3]
    leaves = -(-n // per)
    slices = max(1, int(np.ceil(np.sqrt(leaves))))
    slab = np.empty(n, dtype=np.float64)
    slab[np.argsort(cx, kind="stable")] = np.arange(n) // (slices * per)
    lo, span = cy.min(), cy.max() - cy.min()
    key = slab * (2.0 * span + 1.0) + (cy - lo)                   # exact enough: slabs apart by > span
    return np.argsort(key, kind="stable")


# --------------------------------------------------------------------------- styles

_STYLE_FIELDS = (("f_table_catalog", "s", 256), ("f_table_schema", "s", 256), ("f_table_name", "s", 256),
                 ("f_geometry_column", "s", 256), ("styleName", "s", 30), ("styleQML", "s", 0),
                 ("styleSLD", "s", 0), ("useAsDefault", "b", 0), ("description", "s", 0), ("owner", "s", 30),
                 ("ui", "s", 30), ("update_time", "t", 0))


def _style_text(style) -> str:
    path = Path(style)
    if not path.is_absolute() and not path.exists():
        path = STYLES / style
    try:
        return path.read_text(encoding="utf-8")
    except OSError as exc:
        raise SylvaError(f"style {style}: cannot be read ({exc.strerror})") from None


def write_styles(con: sqlite3.Connection, styles: Dict[str, str]) -> None:
    """QGIS's ``layer_styles`` rows (one default style per layer) from .qml files; replaces earlier ones.

    The table has QGIS's schema (QgsOgrProvider's saveStyle) and is registered
    as an attributes table, as QGIS registers it.
    """
    if not styles:
        return
    exists = con.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'layer_styles'").fetchone()
    if not exists:
        con.execute(
            "CREATE TABLE layer_styles (id INTEGER PRIMARY KEY AUTOINCREMENT, f_table_catalog TEXT(256), "
            "f_table_schema TEXT(256), f_table_name TEXT(256), f_geometry_column TEXT(256), styleName TEXT(30), "
            "styleQML TEXT, styleSLD TEXT, useAsDefault BOOLEAN, description TEXT, owner TEXT(30), ui TEXT(30), "
            "update_time DATETIME DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ','now')))")
        con.execute("INSERT OR REPLACE INTO gpkg_contents (table_name, data_type, identifier, description, srs_id) "
                    "VALUES ('layer_styles', 'attributes', 'layer_styles', '', 0)")
        con.execute("INSERT OR REPLACE INTO gpkg_ogr_contents (table_name, feature_count) "
                    "VALUES ('layer_styles', NULL)")
    geometry = dict(con.execute("SELECT table_name, column_name FROM gpkg_geometry_columns").fetchall())
    for layer, style in styles.items():
        qml = _style_text(style)
        con.execute("DELETE FROM layer_styles WHERE f_table_name = ?", (layer,))
        con.execute("INSERT INTO layer_styles (f_table_catalog, f_table_schema, f_table_name, f_geometry_column, "
                    "styleName, styleQML, styleSLD, useAsDefault, description, owner, ui) "
                    "VALUES ('', '', ?, ?, ?, ?, '', 1, ?, '', '')",
                    (layer, geometry.get(layer, ""), layer, qml, f"Sylva style {Path(style).name}"))
    con.execute("UPDATE gpkg_ogr_contents SET feature_count = (SELECT count(*) FROM layer_styles) "
                "WHERE table_name = 'layer_styles'")


def default_styles(layers: Iterable[str]) -> Dict[str, str]:
    """{layer: "<layer>.qml"} for the layers with a style of that name in :data:`STYLES`."""
    return {name: f"{name}.qml" for name in layers if (STYLES / f"{name}.qml").is_file()}


# --------------------------------------------------------------------------- merging

class GpkgMerge:
    """Appends GeoPackages written by :func:`write_gpkg` (the pipeline's tile parts) into one new file.

    Rows are copied table by table in SQL (``INSERT ... SELECT`` from the
    attached part, memory-mapped), so memory holds only the R-tree boxes
    (24 bytes a feature, read from each part's R-tree: the workers built them);
    extents are the union of the parts'.  :meth:`add` returns the fid range
    each table's new rows got, which :meth:`remap` takes to rewrite their
    ``tree_id`` values.  :meth:`close` builds the R-trees, writes the styles
    and the feature counts; :meth:`abort` only closes.  The connection may be
    handed from one thread to another (never used by two at once).
    """

    def __init__(self, path, styles: Optional[Dict[str, str]] = None, spatial_index: bool = True):
        self.path = Path(path)
        self.con = sqlite3.connect(self.path, check_same_thread=False)
        # a temporary file renamed at the end: no journal, no fsync per part, larger pages
        self.con.execute(f"PRAGMA page_size = {PAGE_SIZE}")
        self.con.execute("PRAGMA journal_mode = OFF")
        self.con.execute("PRAGMA synchronous = OFF")
        self.con.execute(f"PRAGMA mmap_size = {MERGE_MMAP_BYTES}")   # parts attached later are read mapped too
        self.styles = styles
        self.spatial_index = spatial_index
        self.created: Dict[str, Dict[str, str]] = {}     # table -> {column: declared type}
        self.triggers: Dict[str, str] = {}
        self.geometry: Dict[str, str] = {}               # table -> geometry column
        self.bounds: Dict[str, List[tuple]] = {}         # table -> [(first fid, (k, 4) bounds)]
        self.parts = 0

    def add(self, part) -> Dict[str, tuple]:
        """Append the layers of the GeoPackage ``part``; returns {table: (first fid - 1, last fid)}."""
        con = self.con
        ranges = {}
        con.execute("ATTACH DATABASE ? AS part", (str(part),))
        try:
            if self.parts == 0:
                con.execute("PRAGMA application_id = 1196444487")
                (version,) = con.execute("PRAGMA part.user_version").fetchone()
                con.execute(f"PRAGMA user_version = {int(version)}")
            meta = [r[0] for r in con.execute(
                "SELECT name FROM part.sqlite_master WHERE type = 'table' AND name LIKE 'gpkg%' ORDER BY rootpage")]
            for t in meta:
                if con.execute("SELECT 1 FROM main.sqlite_master WHERE name = ?", (t,)).fetchone() is None:
                    (sql,) = con.execute("SELECT sql FROM part.sqlite_master WHERE name = ?", (t,)).fetchone()
                    con.execute(sql)
                where = {"gpkg_contents": "table_name != 'layer_styles'",
                         "gpkg_ogr_contents": "table_name != 'layer_styles'",
                         "gpkg_extensions": "extension_name != 'gpkg_rtree_index'"}.get(t, "1")
                con.execute(f"INSERT OR IGNORE INTO main.{quote(t)} SELECT * FROM part.{quote(t)} WHERE {where}")
            self._union_extents()
            for name, sql in con.execute("SELECT name, sql FROM part.sqlite_master WHERE type = 'trigger' "
                                         "AND name NOT LIKE 'rtree_%'"):
                self.triggers.setdefault(name, sql)
            self.geometry.update(con.execute("SELECT table_name, column_name FROM part.gpkg_geometry_columns"))
            tables = [r[0] for r in con.execute(
                "SELECT table_name FROM part.gpkg_contents WHERE data_type IN ('features', 'attributes') "
                "AND table_name != 'layer_styles' ORDER BY rowid")]
            for t in tables:
                ranges.update(self._append(t))
            con.commit()
        finally:
            con.execute("DETACH DATABASE part")
        self.parts += 1
        return ranges

    def _union_extents(self) -> None:
        sides = (("min_x", "min"), ("min_y", "min"), ("max_x", "max"), ("max_y", "max"))
        sets = ", ".join(
            f"{c} = {f}(coalesce({c}, (SELECT p.{c} FROM part.gpkg_contents p WHERE p.table_name = "
            f"gpkg_contents.table_name)), coalesce((SELECT p.{c} FROM part.gpkg_contents p WHERE p.table_name = "
            f"gpkg_contents.table_name), {c}))" for c, f in sides)
        self.con.execute(f"UPDATE main.gpkg_contents SET {sets}")

    def _append(self, t: str) -> Dict[str, tuple]:
        con = self.con
        info = [(r[1], r[2]) for r in con.execute(f"PRAGMA part.table_info({quote(t)})") if r[1] != "fid"]
        if t not in self.created:
            (sql,) = con.execute("SELECT sql FROM part.sqlite_master WHERE type = 'table' AND name = ?",
                                 (t,)).fetchone()
            con.execute(sql)
            self.created[t] = {r[1]: r[2] for r in con.execute(f"PRAGMA main.table_info({quote(t)})")}
        for c, kind in info:
            if c not in self.created[t]:
                con.execute(f"ALTER TABLE main.{quote(t)} ADD COLUMN {quote(c)} {kind or 'TEXT'}")
                self.created[t][c] = kind
        cols = ",".join(quote(c) for c, _ in info)
        (before,) = con.execute(f"SELECT coalesce(max(fid), 0) FROM main.{quote(t)}").fetchone()
        if cols:
            con.execute(f"INSERT INTO main.{quote(t)} ({cols}) SELECT {cols} FROM part.{quote(t)} ORDER BY fid")
        else:
            con.execute(f"INSERT INTO main.{quote(t)} (fid) SELECT NULL FROM part.{quote(t)} ORDER BY fid")
        (after,) = con.execute(f"SELECT coalesce(max(fid), 0) FROM main.{quote(t)}").fetchone()
        geom = self.geometry.get(t)
        if geom and self.spatial_index and after > before:
            self.bounds.setdefault(t, []).append(self._part_boxes(t, geom, before))
        return {t: (before, after)} if "tree_id" in self.created[t] else {}

    def _part_boxes(self, t: str, geom: str, before: int) -> tuple:
        """(new fids, float32 boxes) of the part's rows of ``t`` just appended after fid ``before``.

        From the part's own R-tree when it has one and its fids are 1..n (as
        :func:`write_gpkg` writes them: the new fid is then ``before + fid``),
        else from its geometry blobs (:func:`blob_bounds`).
        """
        con = self.con
        rtree = f"rtree_{t}_{geom}"
        lo, hi, n = con.execute(f"SELECT min(fid), max(fid), count(*) FROM part.{quote(t)}").fetchone()
        indexed = con.execute("SELECT 1 FROM part.gpkg_extensions WHERE table_name = ? AND column_name = ? AND "
                              "extension_name = 'gpkg_rtree_index'", (t, geom)).fetchone() if con.execute(
            "SELECT 1 FROM part.sqlite_master WHERE name = 'gpkg_extensions'").fetchone() else None
        if indexed and lo == 1 and hi == n:
            ids, boxes = read_rtree(con, "part", rtree)
            return ids + before, boxes
        blobs = [b for (b,) in con.execute(f"SELECT {quote(geom)} FROM part.{quote(t)} ORDER BY fid")]
        bounds = blob_bounds(blobs)
        keep = np.isfinite(bounds).all(axis=1)
        return np.arange(before + 1, before + 1 + len(blobs), dtype=np.int64)[keep], outward_float32(bounds[keep])

    def remap(self, ranges: Dict[str, tuple], mapping: dict) -> None:
        """Rewrite ``tree_id`` {old: new} in the rows ``ranges`` (what :meth:`add` returned for a part)."""
        if not mapping or not ranges:
            return
        con = self.con
        con.execute("CREATE TEMP TABLE IF NOT EXISTS idmap (old INTEGER PRIMARY KEY, new INTEGER)")
        con.execute("DELETE FROM idmap")
        con.executemany("INSERT INTO idmap VALUES (?,?)", list(mapping.items()))
        for t, (lo, hi) in ranges.items():
            con.execute(f"UPDATE main.{quote(t)} SET tree_id = (SELECT new FROM idmap WHERE old = tree_id) "
                        f"WHERE fid > ? AND fid <= ? AND tree_id IN (SELECT old FROM idmap)", (lo, hi))
        con.commit()

    def close(self) -> None:
        """Finish the file: feature counts, R-trees, triggers, styles; then close."""
        con = self.con
        try:
            for t in self.created:
                con.execute("UPDATE gpkg_ogr_contents SET feature_count = (SELECT count(*) FROM main."
                            f"{quote(t)}) WHERE lower(table_name) = lower(?)", (t,))
            if self.spatial_index:
                for t, geom in self.geometry.items():
                    if t not in self.created:
                        continue
                    chunks = self.bounds.pop(t, [])
                    ids = np.concatenate([i for i, _ in chunks] or [np.zeros(0, dtype=np.int64)])
                    boxes = np.concatenate([b for _, b in chunks] or [np.zeros((0, 4), dtype=np.float32)])
                    add_rtree(con, t, geom, ids, boxes)
            for sql in self.triggers.values():
                con.execute(sql)
            if self.styles:
                write_styles(con, {k: v for k, v in self.styles.items() if k in self.created})
            con.commit()
        finally:
            con.close()

    def abort(self) -> None:
        """Close without finishing (the file is about to be removed)."""
        self.con.close()


# --------------------------------------------------------------------------- reading

def split_source(source: str) -> tuple:
    """(path, layer name or None) of a QGIS-style source ``file.gpkg`` or ``file.gpkg|layername=NAME``."""
    path, _, options = str(source).partition("|")
    layer = None
    for option in filter(None, options.split("|")):
        key, _, value = option.partition("=")
        if key.strip().lower() == "layername":
            layer = value.strip()
    return path, layer


def _open(path) -> object:
    gdal, ogr, _ = _ogr()
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: file not found")
    with _GdalErrors() as err:
        ds = gdal.OpenEx(str(path), gdal.OF_VECTOR | gdal.OF_READONLY, allowed_drivers=["GPKG"])
        if ds is None:
            raise InputError(f"{path}: not a GeoPackage ({err.message()})")
    return ds


def layer_names(path) -> List[str]:
    """The names of the feature and attribute layers of a GeoPackage (not ``layer_styles``), in file order."""
    ds = _open(path)
    return [ds.GetLayer(i).GetName() for i in range(ds.GetLayerCount())
            if ds.GetLayer(i).GetName() != "layer_styles"]


def read_gpkg(path, layer: str) -> VectorTable:
    """Read one layer of a GeoPackage through OGR (any GeoPackage layer, not only Sylva's)."""
    import pyproj

    _, ogr, osr = _ogr()
    path = Path(path)
    ds = _open(path)
    lay = ds.GetLayerByName(layer)
    if lay is None or lay.GetName() != layer:
        raise InputError(f"{path}: no layer named {layer!r}")
    defn = lay.GetLayerDefn()
    gtype = lay.GetGeomType()
    kind = "none" if gtype == ogr.wkbNone else _geometry_kind(ogr.GeometryTypeToName(gtype))
    has_z, has_m = bool(ogr.GT_HasZ(gtype)), bool(ogr.GT_HasM(gtype))
    crs = None
    srs = lay.GetSpatialRef()
    if srs is not None:
        code = srs.GetAuthorityCode(None) if srs.GetAuthorityName(None) == "EPSG" else None
        crs = pyproj.CRS.from_epsg(int(code)) if code else pyproj.CRS.from_wkt(srs.ExportToWkt(["FORMAT=WKT2_2018"]))
    fields = [defn.GetFieldDefn(i) for i in range(defn.GetFieldCount())]
    values = [[] for _ in fields]
    wkb = []
    with _GdalErrors() as err:
        lay.ResetReading()
        for feature in lay:
            for i, column in enumerate(values):
                column.append(feature.GetField(i) if feature.IsFieldSetAndNotNull(i) else None)
            if kind != "none":
                g = feature.GetGeometryRef()
                wkb.append(None if g is None else bytes(g.ExportToIsoWkb()))
        if err.gdal.GetLastErrorType() >= 3:
            raise InputError(f"{path}: cannot read layer {layer!r} ({err.message()})")
    columns = {}
    for f, column in zip(fields, values):
        columns[f.GetName()] = _column(column, f.GetType(), ogr)
    geoms = None
    if kind != "none":
        if has_m:
            geoms = np.array(wkb, dtype=object)
        else:
            geoms = shapely.from_wkb(np.array(wkb, dtype=object))
    return VectorTable(layer, kind, geoms, columns, crs, has_z=has_z or kind == "none", has_m=has_m,
                       wkb=has_m)


def _geometry_kind(name: str) -> str:
    """"point" | "line" | "polygon" for an OGR geometry type name (Multi- and Z/M forms too)."""
    name = name.upper()
    for word, kind in (("POINT", "point"), ("LINE", "line"), ("CURVE", "line"), ("POLYGON", "polygon"),
                       ("SURFACE", "polygon")):
        if word in name:
            return kind
    return "polygon"


def _column(vals: list, ftype: int, ogr) -> np.ndarray:
    if ftype in (ogr.OFTInteger, ogr.OFTInteger64) and all(v is not None for v in vals):
        return np.array(vals, dtype=np.int64)
    if ftype in (ogr.OFTInteger, ogr.OFTInteger64, ogr.OFTReal):
        return np.array([np.nan if v is None else v for v in vals], dtype=np.float64)
    return np.array(vals, dtype=object)


def read_layer(source: str) -> VectorTable:
    """A vector layer named as QGIS names it: ``file.gpkg`` (its only layer) or ``file.gpkg|layername=NAME``."""
    path, layer = split_source(source)
    if layer is None:
        names = layer_names(path)
        if len(names) != 1:
            raise InputError(f"{path}: holds {len(names)} layers ({', '.join(names) or 'none'}); "
                             f"name one as {path}|layername=NAME")
        layer = names[0]
    return read_gpkg(path, layer)
