"""Envelopes and R-trees: geometry blobs' bounds, the GeoPackage R-tree extension bulk-loaded, and read back."""
from __future__ import annotations

import sqlite3
import struct
from typing import Sequence

import numpy as np

from ...errors import SylvaError
from ...jit import njit
from .sqlite import insert_rows, quote

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
    insert_rows(con, rtree + "_node", ["nodeno", "data"], [list(c) for c in zip(*node_rows)], len(node_rows))
    if parent_rows:
        insert_rows(con, rtree + "_parent", ["nodeno", "parentnode"], [list(c) for c in zip(*parent_rows)],
                     len(parent_rows))
    insert_rows(con, rtree + "_rowid", ["rowid", "nodeno"], rowids, n)


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
