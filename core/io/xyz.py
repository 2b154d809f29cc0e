"""Text point clouds: ``x y z [more columns]`` per line.

Columns are separated by whitespace, commas or semicolons (with semicolons a
comma is read as a decimal comma, as European spreadsheets write it).  ``#``
starts a comment.  An optional first line names the columns (``x y z
intensity r g b classification ...``; also ``//X Y Z`` as CloudCompare
writes it, or a ``#`` comment line naming x, y and z); a leading single
integer line (the point count of a ``.pts`` file) is skipped.  Without names
the columns are x y z, then: 1 more -> intensity, 3 more -> red green blue,
4 more -> intensity red green blue (the PTS layout), otherwise ``col4``,
``col5``... (1-based).

Parsing is one :func:`numpy.loadtxt` call (numpy's C parser; measured as
fast as or faster than ``numpy.fromstring`` on the whole text, and it checks
every line has the same columns); only when it fails is the text walked line
by line to name the bad line.
Text has no CRS: ``crs`` is None unless given.
"""
from __future__ import annotations

import io
import re
from pathlib import Path
from typing import Optional, Union

import numpy as np

from ..cloud import PointCloud, Units
from ..errors import EmptyInputError, InputError
from ..progress import CancelCheck, Progress, check, report
from .las import as_crs, require_linear, units_of

__all__ = ["read_xyz", "COLUMN_ALIASES"]

# Column names as written in text headers -> Sylva/LAS attribute names.
COLUMN_ALIASES = {
    "x": "x", "y": "y", "z": "z",
    "i": "intensity", "int": "intensity", "intensity": "intensity",
    "r": "red", "red": "red", "g": "green", "green": "green", "b": "blue", "blue": "blue",
    "nir": "nir",
    "c": "classification", "class": "classification", "cls": "classification",
    "classification": "classification",
    "rn": "return_number", "return": "return_number", "returnnumber": "return_number",
    "return_number": "return_number",
    "nr": "number_of_returns", "numberofreturns": "number_of_returns",
    "number_of_returns": "number_of_returns", "returns": "number_of_returns",
    "t": "gps_time", "time": "gps_time", "gpstime": "gps_time", "gps_time": "gps_time",
    "psid": "point_source_id", "point_source_id": "point_source_id",
    "pointsourceid": "point_source_id",
    "user_data": "user_data", "userdata": "user_data",
    "scan_angle": "scan_angle", "scanangle": "scan_angle",
    "scan_angle_rank": "scan_angle_rank", "scananglerank": "scan_angle_rank",
    "treeid": "treeID", "tree_id": "treeID",
}

# LAS dimensions stored as integers: a column holding only integers in range
# is given this dtype, so that writing it to LAS is lossless.
_INTEGER_DIMS = {
    "intensity": np.uint16, "red": np.uint16, "green": np.uint16, "blue": np.uint16,
    "nir": np.uint16, "classification": np.uint8, "return_number": np.uint8,
    "number_of_returns": np.uint8, "point_source_id": np.uint16, "user_data": np.uint8,
    "scan_angle_rank": np.int8, "scan_angle": np.int16, "treeID": np.int32,
}

_COMMENT = re.compile(r"#[^\n]*")


def _is_number(token: str) -> bool:
    try:
        float(token)
        return True
    except ValueError:
        return False


def _split(line: str):
    return [t for t in re.split(r"[\s]+", line.strip()) if t]


def _column_names(tokens, where):
    names = []
    for t in tokens:
        key = t.strip().strip("\"'").lstrip("/").strip()
        names.append(COLUMN_ALIASES.get(key.lower(), key))
    if not {"x", "y", "z"} <= set(names):
        raise InputError(f"{where}: the header line names the columns {', '.join(tokens)} "
                         "but not all of x, y and z")
    if len(set(names)) != len(names):
        raise InputError(f"{where}: the header line names a column twice ({' '.join(tokens)})")
    return names


def _default_names(ncols, where):
    if ncols < 3:
        raise InputError(f"{where}: a line has {ncols} column(s); x y z need at least 3")
    more = {0: [], 1: ["intensity"], 3: ["red", "green", "blue"],
            4: ["intensity", "red", "green", "blue"]}.get(ncols - 3)
    if more is None:
        more = [f"col{i + 1}" for i in range(3, ncols)]
    return ["x", "y", "z"] + more


def _find_bad_line(lines, ncols, where, first_lineno):
    for k, line in enumerate(lines):
        tokens = _split(line)
        if not tokens:
            continue
        if len(tokens) != ncols or not all(_is_number(t) for t in tokens):
            raise InputError(f"{where}: line {first_lineno + k} ({line.strip()[:60]!r}) does "
                             f"not hold {ncols} numbers like the first data line")
    raise InputError(f"{where}: the numbers cannot be read")


_HEAD_BYTES = 1 << 16


def _scan(text: str, path: Path, where: str):
    """Header names, (line number, tokens, separator) of the first data line, and
    the names of a ``# x y z ...`` comment line, from the start of the text."""
    names = None
    comment_header = None
    for lineno, line in enumerate(text.split("\n"), start=1):
        stripped = line.strip()
        if stripped.startswith("#") and comment_header is None:
            tokens = _split(stripped.lstrip("#").replace(",", " ").replace(";", " "))
            keys = {COLUMN_ALIASES.get(t.strip("\"'").lower()) for t in tokens}
            if {"x", "y", "z"} <= keys:
                comment_header = tokens
        body = stripped.split("#", 1)[0].strip()
        if not body:
            continue
        if ";" in body:
            separator = ";,"  if "," in body else ";"  # ";," : decimal commas
            tokens = _split(body.replace(",", ".").replace(";", " "))
        elif "," in body:
            separator, tokens = ",", _split(body.replace(",", " "))
        else:
            separator, tokens = None, _split(body)
        if names is None and not all(_is_number(t) for t in tokens):
            names = _column_names(tokens, where)
        elif (names is None and len(tokens) == 1 and tokens[0].isdigit()
              and path.suffix.lower() == ".pts"):
            continue  # the point count line of a PTS file
        else:
            return names, (lineno, tokens, separator), comment_header
    return names, None, comment_header


def _parse(path: Path, where: str, encoding: str, first_lineno: int, separator, ncols):
    """The numbers from ``first_lineno`` on, by numpy's C parser straight from the file;
    decimal commas (or mixed separators) go through a cleaned copy of the text."""
    if separator != ";,":
        try:
            return np.loadtxt(path, dtype=np.float64, delimiter=separator, comments="#",
                              skiprows=first_lineno - 1, ndmin=2, encoding=encoding)
        except ValueError:
            pass  # mixed separators, a bad line: the slow path below says which
    text = path.read_bytes().decode(encoding, "replace")
    body = text.split("\n", first_lineno - 1)[-1] if first_lineno > 1 else text
    del text
    body = body.replace(",", ".").replace(";", " ") if separator == ";," \
        else body.replace(";", " ").replace(",", " ")
    lines = _COMMENT.sub("", body).split("\n")
    try:
        data = np.loadtxt(io.StringIO(body), dtype=np.float64, comments="#", ndmin=2)
    except ValueError:
        _find_bad_line(lines, ncols, where, first_lineno)
        raise  # not reached: _find_bad_line raises
    if data.shape[1] != ncols:
        _find_bad_line(lines, ncols, where, first_lineno)
    return data


def _typed(name, values):
    dtype = _INTEGER_DIMS.get(name)
    if dtype is None or len(values) == 0:
        return values
    info = np.iinfo(dtype)
    if values.min() < info.min or values.max() > info.max or not np.array_equal(
            values, np.round(values)):
        return values
    return values.astype(dtype)


def open_point_file(path, kind: str, crs, units, progress: Progress = None, cancelled: CancelCheck = None):
    """The checks every point-file reader starts with: ``(path, where, crs, units)``.

    Refuses a missing file or a folder (naming ``kind``, e.g. "text point cloud"),
    reports progress, and resolves ``crs`` and ``units`` (a :class:`Units`, metres per
    unit, or None for the CRS's units, which must be linear)."""
    path = Path(path)
    where = str(path)
    if not path.exists():
        raise InputError(f"{where}: file not found")
    if path.is_dir():
        raise InputError(f"{where}: is a folder, not a {kind}")
    check(cancelled)
    report(progress, 0.0, f"reading {path.name}")
    crs = as_crs(crs, where)
    if units is None:
        units = units_of(crs)
        require_linear(units, crs, where)
    elif not isinstance(units, Units):
        units = Units(horizontal_m=float(units), vertical_m=float(units))
    return path, where, crs, units


def read_xyz(path, crs=None, units: Optional[Union[Units, float]] = None, *,
             allow_empty: bool = False, progress: Progress = None,
             cancelled: CancelCheck = None) -> PointCloud:
    """Read a text point cloud (``.xyz .txt .csv .pts``) into a :class:`PointCloud`.

    ``crs`` is anything pyproj accepts (text carries none, so the cloud's
    CRS is None unless given).  ``units`` is a :class:`Units` or metres per
    unit; by default the CRS's units, or metres.  Attributes other than x y z
    are named after the header (see :data:`COLUMN_ALIASES`); LAS integer
    dimensions holding only in-range integers get their LAS dtype, others
    stay float64.  A file without points raises :class:`EmptyInputError`
    unless ``allow_empty``.
    """
    path, where, crs, units = open_point_file(path, "text point cloud", crs, units, progress, cancelled)

    with open(path, "rb") as f:
        head = f.read(_HEAD_BYTES)
        more = bool(f.read(1))
    if b"\0" in head[:4096]:
        raise InputError(f"{where}: not a text point cloud (binary data)")
    encoding = "utf-8-sig"
    try:
        head.decode(encoding)
    except UnicodeDecodeError as err:
        if not (more and err.start >= len(head) - 4):  # not just a cut multi-byte char
            encoding = "latin-1"
    if more:
        head = head[: head.rfind(b"\n") + 1]  # complete lines only
    names, first, comment_header = _scan(head.decode(encoding, "replace"), path, where)
    if first is None and more:  # a header longer than the first block: scan everything
        names, first, comment_header = _scan(path.read_bytes().decode(encoding, "replace"),
                                             path, where)

    if first is None:
        if not allow_empty:
            raise EmptyInputError(f"{where}: the file holds no points")
        names = names or ["x", "y", "z"]
        data = np.empty((0, len(names)))
    else:
        first_lineno, tokens, separator = first
        ncols = len(tokens)
        if names is None and comment_header is not None:
            try:
                names = _column_names(comment_header, where)
            except InputError:
                names = None
            if names is not None and len(names) != ncols:
                names = None
        if names is None:
            names = _default_names(ncols, where)
        if len(names) != ncols:
            raise InputError(f"{where}: the header names {len(names)} columns but line "
                             f"{first_lineno} has {ncols}")
        check(cancelled)
        data = _parse(path, where, encoding, first_lineno, separator, ncols)

    index = {n: i for i, n in enumerate(names)}
    xyz = np.ascontiguousarray(data[:, [index["x"], index["y"], index["z"]]])
    if not np.all(np.isfinite(xyz)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(xyz), axis=1))[0])
        raise InputError(f"{where}: point {bad + 1} has a non-finite coordinate")
    attrs = {n: _typed(n, np.ascontiguousarray(data[:, i]))
             for n, i in index.items() if n not in ("x", "y", "z")}
    cloud = PointCloud(xyz=xyz, attrs=attrs, crs=crs, units=units, source=where)
    report(progress, 1.0, f"read {len(cloud)} points from {path.name}")
    return cloud
