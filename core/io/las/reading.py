"""Reading LAS/LAZ points: whole (:func:`read_las`), in chunks (:func:`read_las_chunks`), as raw records
(:func:`checked_records`); the header alone (:func:`las_info`); tree IDs of any type (:func:`tree_labels`).

:data:`PARALLEL_LAZ_USED` says whether this process has used lazrs's thread pool (read it here, as
``reading.PARALLEL_LAZ_USED``: a copy imported elsewhere would not see it change).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Optional, Tuple

import numpy as np

from ...cloud import PointCloud, Units
from ...errors import EmptyInputError, InputError
from ...progress import CancelCheck, Progress, check, report
from .checks import bad_file, check_bounds, check_file, check_no_more_points, check_size
from .crs import crs_and_units, require_linear
from .template import XYZ, LasTemplate, load_laspy


def tree_labels(values, where: str = "treeID") -> np.ndarray:
    """int64 tree IDs (0 = no tree) of a ``treeID`` dimension of any type.

    lidR writes "no tree" in a floating-point treeID as NA, which in a LAS file is the
    largest double: NaN, infinite, negative or out-of-int32 values are read as 0 (no
    tree), without a RuntimeWarning from the cast (Sylva, not in the papers).
    """
    v = np.asarray(values)
    if v.dtype.kind in "iub":
        return v.astype(np.int64)
    v = v.astype(np.float64, copy=False)
    ok = np.isfinite(v) & (v > 0) & (v <= np.iinfo(np.int32).max)
    out = np.zeros(len(v), dtype=np.int64)
    out[ok] = np.rint(v[ok]).astype(np.int64)
    return out


#: True once this process decoded LAZ with lazrs's multi-threaded backend (laspy's default): its thread pool
#: (rayon) does not survive a fork, and a forked child that compresses or decompresses LAZ then waits for
#: those threads forever (seen: a pipeline's pool workers after the parent cut a file into chunks).
PARALLEL_LAZ_USED = False


def parallel_laz_used() -> None:
    global PARALLEL_LAZ_USED
    PARALLEL_LAZ_USED = True


def _decoding(reader) -> None:
    """Note that points of ``reader`` are about to be decoded (see PARALLEL_LAZ_USED)."""
    if getattr(reader, "sylva_parallel", False):
        parallel_laz_used()


def _open(path: Path, parallel: bool = True):
    laspy = load_laspy()
    reader = None
    try:
        backend = None if parallel else laspy.LazBackend.Lazrs
        reader = laspy.open(str(path), laz_backend=backend) if backend is not None else laspy.open(str(path))
        reader.sylva_parallel = parallel and reader.header.are_points_compressed
        check_size(path, reader.header)
    except Exception as err:
        if reader is not None:
            reader.close()
        raise bad_file(path, err) from None
    return reader


def field(array: np.ndarray, fmt, name: str, packed: dict, sub_fields: dict) -> np.ndarray:
    """The values of one dimension, as laspy gives them, decoded from the raw records.

    Bit fields are unpacked from one contiguous copy of their byte per composed
    field (``packed`` caches it), several times faster than masking the strided
    field once per flag.  Scaled extra dimensions come back scaled (float64).
    """
    if name in sub_fields:
        composed, sub = sub_fields[name]
        if composed not in packed:
            packed[composed] = np.ascontiguousarray(array[composed])
        bits = packed[composed]
        lsb = (sub.mask & -sub.mask).bit_length() - 1
        return (bits & bits.dtype.type(sub.mask)) >> bits.dtype.type(lsb)
    dim = fmt.dimension_by_name(name)
    if not dim.is_standard and dim.is_scaled:
        return np.asarray(array[name]) * dim.scales + dim.offsets
    return array[name]


def _cloud_from_array(array, header, crs, units, source, parsed_crs) -> PointCloud:
    """Scaled xyz + one copied attribute array per dimension + template."""
    laspy = load_laspy()
    fmt = header.point_format
    n = len(array)
    xyz = np.empty((n, 3), dtype=np.float64)
    for i, name in enumerate(XYZ):
        # X * scale + offset, as laspy computes it, so values match laspy.read exactly
        column = xyz[:, i]
        np.multiply(array[name], header.scales[i], out=column)
        column += header.offsets[i]
    sub_fields = laspy.point.dims.get_sub_fields_dict(fmt.id)
    packed = {}
    attrs = {}
    for name in fmt.dimension_names:
        if name in XYZ:
            continue
        values = field(array, fmt, name, packed, sub_fields)
        # a copy of its own, never a view into the records
        attrs[name] = values if values.base is None else np.array(values)
    template = LasTemplate(header, array, parsed_crs)
    return PointCloud(xyz=xyz, attrs=attrs, crs=crs, units=units, source=source,
                      template=template)


def read_las(path, crs=None, *, units: Optional[Units] = None, allow_empty: bool = False,
             progress: Progress = None, cancelled: CancelCheck = None) -> PointCloud:
    """Read a LAS/LAZ (or COPC) file into a :class:`PointCloud`.

    ``xyz`` are the scaled coordinates (float64, file units); ``attrs`` holds
    every dimension but X/Y/Z under laspy's names (``intensity``,
    ``return_number``, ``classification``, ``scan_angle_rank`` or
    ``scan_angle``, ``gps_time``, ``red``..., flags, extra bytes such as
    ``treeID``); ``crs`` is the file's CRS, or ``crs`` when given (anything
    pyproj accepts), or None; ``units`` its units (or ``units``, a
    :class:`Units` or metres per unit, when given); ``template`` a
    :class:`LasTemplate` for lossless writing.  A file without points raises
    :class:`EmptyInputError` unless ``allow_empty``; a geographic (degree)
    CRS raises :class:`CRSError` (Sylva does not reproject).
    """
    path = check_file(path)
    check(cancelled)
    report(progress, 0.0, f"reading {path.name}")
    with _open(path) as reader:
        header = reader.header
        crs, units, parsed = crs_and_units(header, crs, str(path), units)
        require_linear(units, crs, str(path))
        if header.point_count == 0 and not allow_empty:
            raise EmptyInputError(f"{path}: the file holds no points")
        try:
            _decoding(reader)
            las = reader.read()
        except Exception as err:
            raise bad_file(path, err) from None
        check_no_more_points(reader, path, header)
    if len(las.points) != header.point_count:
        raise InputError(f"{path}: the file is truncated ({len(las.points)} of "
                         f"{header.point_count} points could be read)")
    check_bounds(path, las.points.array, header)
    cloud = _cloud_from_array(las.points.array, las.header, crs, units, str(path), parsed)
    report(progress, 1.0, f"read {len(cloud)} points from {path.name}")
    return cloud


def read_las_chunks(path, chunk_size: int = 1_000_000, crs=None, *,
                    units: Optional[Units] = None, allow_empty: bool = False,
                    progress: Progress = None,
                    cancelled: CancelCheck = None) -> Iterator[PointCloud]:
    """Stream a LAS/LAZ file as clouds of at most ``chunk_size`` points.

    The file is opened and checked (existence, format, CRS, emptiness) when
    this is called; the returned iterator reads one chunk at a time, so files
    larger than memory can be processed.  Each chunk is a full
    :class:`PointCloud` (same CRS, units, attribute names) whose template
    allows writing it back.  Concatenating the chunks gives :func:`read_las`.
    """
    if int(chunk_size) < 1:
        raise InputError(f"{path}: chunk_size must be at least 1 point, not {chunk_size}")
    path = check_file(path)
    reader = _open(path)
    try:
        header = reader.header
        crs, units, parsed = crs_and_units(header, crs, str(path), units)
        require_linear(units, crs, str(path))
        if header.point_count == 0 and not allow_empty:
            raise EmptyInputError(f"{path}: the file holds no points")
    except BaseException:
        reader.close()
        raise
    return _chunks(reader, path, int(chunk_size), crs, units, parsed, progress, cancelled)


def _chunks(reader, path, chunk_size, crs, units, parsed, progress, cancelled):
    header = reader.header
    total = max(1, header.point_count)
    done = 0
    for record in _checked_records(reader, path, chunk_size, cancelled):
        done += len(record)
        yield _cloud_from_array(record.array, header, crs, units, str(path), parsed)
        report(progress, done / total, f"read {done} of {header.point_count} points")


def checked_records(path, chunk_size: int = 1_000_000, cancelled: CancelCheck = None, parallel: bool = True):
    """``(header, records)``: the file's laspy header and an iterator over its point records (laspy's
    ``ScaleAwarePointRecord``, at most ``chunk_size`` at a time), with every check :func:`read_las` makes
    (truncation, chunk table, bounds, point count, decode errors: one :class:`InputError` naming the
    file).  For code that copies records unchanged (``sylva.core.io.chunks``).  ``parallel`` False decodes
    on this thread only (lazrs without its thread pool: safe in a process that forks afterwards)."""
    path = check_file(path)
    reader = _open(path, parallel)
    return reader.header, _checked_records(reader, path, int(chunk_size), cancelled)


def _checked_records(reader, path, chunk_size, cancelled):
    with reader:
        header = reader.header
        done = 0
        _decoding(reader)
        iterator = reader.chunk_iterator(chunk_size)
        while True:
            check(cancelled)
            try:
                record = next(iterator)
            except StopIteration:
                break
            except Exception as err:
                raise bad_file(path, err) from None
            if len(record) == 0:
                break
            done += len(record)
            check_bounds(path, record.array, header)
            if done >= header.point_count:
                check_no_more_points(reader, path, header)
            yield record
        if done != header.point_count:
            raise InputError(f"{path}: the file is truncated ({done} of "
                             f"{header.point_count} points could be read)")


@dataclass(frozen=True)
class LasInfo:
    """What the header of a LAS/LAZ file says, without reading the points.

    ``bounds`` is (xmin, ymin, zmin, xmax, ymax, zmax) in file units.
    ``has_classification`` says whether the point format has a classification
    field (every LAS format does); whether ground (class 2) points exist
    needs the points and is deliberately not read here.
    """

    path: str
    point_count: int
    bounds: Tuple[float, float, float, float, float, float]
    crs: Any
    units: Units
    version: str
    point_format: int
    has_classification: bool
    file_size: int
    compressed: bool
    dimensions: Tuple[str, ...]
    extra_dimensions: Tuple[str, ...]


def las_info(path, crs=None) -> LasInfo:
    """Header facts of a LAS/LAZ file (count, bounds, CRS, units, version, format)."""
    path = check_file(path)
    with _open(path) as reader:
        h = reader.header
        crs, units, _ = crs_and_units(h, crs, str(path))
        fmt = h.point_format
        return LasInfo(
            path=str(path),
            point_count=int(h.point_count),
            bounds=tuple(float(v) for v in (*h.mins, *h.maxs)),
            crs=crs,
            units=units,
            version=str(h.version),
            point_format=int(fmt.id),
            has_classification="classification" in fmt.dimension_names,
            file_size=path.stat().st_size,
            compressed=bool(h.are_points_compressed),
            dimensions=tuple(fmt.dimension_names),
            extra_dimensions=tuple(fmt.extra_dimension_names),
        )
