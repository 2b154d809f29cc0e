"""QSM tables: cylinders (3-D lines or no geometry), branches and trees as
:class:`~sylva.core.table.VectorTable`, and CSV files written atomically."""
from __future__ import annotations

import csv
import io

import numpy as np

from ..atomic import atomic_open
from ..table import VectorTable
from .cylinders import cylinders_from_curves
from .measure import BRANCH_FIELDS, QSM, branch_table_arrays

__all__ = ["cylinders_table", "branches_table", "trees_table", "write_table_csv", "write_cylinders_csv",
           "write_branches_csv", "write_trees_csv"]


def _cyl_columns(q: QSM) -> dict:
    c = q.cylinders
    n = len(c["id"])
    return {"tree_id": np.full(n, q.tree_id, dtype=np.int64), "id": c["id"], "parent": c["parent"],
            "branch": c["branch"], "order": c["order"],
            "start_x": c["start"][:, 0], "start_y": c["start"][:, 1], "start_z": c["start"][:, 2],
            "axis_x": c["axis"][:, 0], "axis_y": c["axis"][:, 1], "axis_z": c["axis"][:, 2],
            "length": c["length"], "radius": c["radius"]}


def cylinders_table(qsms, crs=None, geometry: bool = True, origin=(0.0, 0.0, 0.0)) -> VectorTable:
    """Cylinders of one or more QSMs as a VectorTable: 3-D lines start -> end (``geometry``)
    or a no-geometry table.  ``origin`` is added to the local coordinates of the lines."""
    from shapely import linestrings
    qs = [qsms] if isinstance(qsms, QSM) else list(qsms)
    cols = [_cyl_columns(q) for q in qs]
    names = cols[0].keys() if cols else _cyl_columns(QSM(-1, cylinders_from_curves([], [], []),
                                                         branch_table_arrays(cylinders_from_curves([], [], []), []),
                                                         0, "none", 0, 0, 0, 0)).keys()
    merged = {k: np.concatenate([c[k] for c in cols]) if cols else np.zeros(0) for k in names}
    if not geometry:
        return VectorTable("cylinders", "none", None, merged, crs)
    o = np.asarray(origin, dtype=float)
    s = np.stack([merged["start_x"], merged["start_y"], merged["start_z"]], axis=1).reshape(-1, 3) + o
    a = np.stack([merged["axis_x"], merged["axis_y"], merged["axis_z"]], axis=1).reshape(-1, 3)
    e = s + a * np.asarray(merged["length"]).reshape(-1, 1)
    geoms = linestrings(np.stack([s, e], axis=1)) if len(s) else np.zeros(0, dtype=object)
    return VectorTable("cylinders", "line", np.asarray(geoms, dtype=object), merged, crs)


def branches_table(qsms, crs=None) -> VectorTable:
    """Branches of one or more QSMs as a no-geometry VectorTable (:data:`BRANCH_FIELDS` + tree_id)."""
    qs = [qsms] if isinstance(qsms, QSM) else list(qsms)
    cols = []
    for q in qs:
        b = dict(q.branches)
        cols.append({"tree_id": np.full(len(b["id"]), q.tree_id, dtype=np.int64), **b})
    keys = ("tree_id",) + BRANCH_FIELDS
    merged = {k: np.concatenate([c[k] for c in cols]) if cols else np.zeros(0) for k in keys}
    return VectorTable("branches", "none", None, merged, crs)


def trees_table(qsms, crs=None) -> VectorTable:
    """One row per QSM with the tree measurements (no geometry)."""
    qs = [qsms] if isinstance(qsms, QSM) else list(qsms)
    max_o = max([max(q.branch_counts, default=0) for q in qs], default=0)
    cols = {
        "tree_id": np.array([q.tree_id for q in qs], dtype=np.int64),
        "dbh_m": np.array([q.dbh_m for q in qs], dtype=float),
        "dbh_source": np.array([q.dbh_source for q in qs], dtype=object),
        "height_m": np.array([q.height_m for q in qs], dtype=float),
        "trunk_volume_m3": np.array([q.trunk_volume_m3 for q in qs], dtype=float),
        "total_volume_m3": np.array([q.total_volume_m3 for q in qs], dtype=float),
        "n_cylinders": np.array([len(q.cylinders["id"]) for q in qs], dtype=np.int64),
    }
    for o in range(1, max_o + 1):
        cols[f"branches_order{o}"] = np.array([q.branch_counts.get(o, 0) for q in qs], dtype=np.int64)
    return VectorTable("trees", "none", None, cols, crs)


def _write_csv(path, table: VectorTable) -> None:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    names = list(table.columns)
    w.writerow(names)
    kinds = table.field_types()
    cols = [np.asarray(table.columns[k]) for k in names]
    for i in range(len(table)):
        row = []
        for k, c in zip(names, cols):
            v = c[i]
            if kinds[k] == "real":
                row.append("" if not np.isfinite(v) else repr(float(v)))
            elif kinds[k] == "integer":
                row.append(int(v))
            else:
                row.append("" if v is None else str(v))
        w.writerow(row)
    with atomic_open(path, "w") as fh:
        fh.write(buf.getvalue())


def write_table_csv(path, table: VectorTable) -> None:
    """Any no-geometry columns of a VectorTable as CSV (header = column names), written atomically."""
    _write_csv(path, table)


def write_cylinders_csv(path, qsms) -> None:
    """Cylinder table as CSV (tree_id + :data:`CYLINDER_FIELDS`), written atomically."""
    _write_csv(path, cylinders_table(qsms, geometry=False))


def write_branches_csv(path, qsms) -> None:
    """Branch table as CSV (tree_id + :data:`BRANCH_FIELDS`), written atomically."""
    _write_csv(path, branches_table(qsms))


def write_trees_csv(path, qsms) -> None:
    """Tree measurements as CSV, written atomically."""
    _write_csv(path, trees_table(qsms))
