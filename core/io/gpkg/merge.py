"""Merging: :class:`GpkgMerge` appends GeoPackages into one in SQL (:mod:`sylva.core.io.gpkg_merge` builds on it)."""
from __future__ import annotations

import sqlite3
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np

from .rtree import add_rtree, blob_bounds, outward_float32, read_rtree
from .sqlite import PAGE_SIZE, quote
from .styles import write_styles

#: Parts are read through a memory map of up to this many bytes each (SQLite's mmap_size), not read() calls.
MERGE_MMAP_BYTES = 1 << 30


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
