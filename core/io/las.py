"""LAS/LAZ point clouds: read (whole or in chunks), inspect, write losslessly.

Reading uses laspy (LAS 1.0–1.4, point formats 0–10) with lazrs for LAZ; COPC
files are valid LAZ 1.4 and read as such.  A cloud read here keeps, in
:attr:`PointCloud.template`, the file's header and its raw point records
(:class:`LasTemplate`), so that :func:`write_las` writes back every source
dimension, VLR, EVLR and the CRS bit for bit, changing only what the cloud's
attributes changed and adding extra-bytes dimensions (such as ``treeID``,
int32, 0 = no tree, as lidR writes it; ARCHITECTURE.md, conventions).

The CRS comes from the WKT or GeoTIFF VLRs (``LasHeader.parse_crs``, WKT
preferred) unless the caller passes one; a GeoTIFF vertical CRS key (4096) is
added as the vertical part of a compound CRS.  Units (metres, international
feet, US survey feet) are read from the CRS: horizontal from the horizontal
part, vertical from the vertical part of a compound CRS (or the third axis of
a 3D CRS), else assumed equal to the horizontal one.  Without any CRS the
GeoTIFF unit keys (3076, 4099) are used when present, else metres.
"""
from __future__ import annotations

import copy
import math
import os
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Optional, Tuple

import numpy as np

from ..cloud import INTERNATIONAL_FOOT, METRE, METRES, US_SURVEY_FOOT, PointCloud, Units
from ..errors import CRSError, DamagedInputError, EmptyInputError, InputError, SylvaError
from ..progress import CancelCheck, Progress, check, report

__all__ = [
    "LasTemplate",
    "LasInfo",
    "read_las",
    "read_las_chunks",
    "checked_records",
    "las_info",
    "write_las",
    "require_crs",
    "units_of",
    "parse_crs",
    "tree_labels",
]

_XYZ = ("X", "Y", "Z")
# EPSG unit-of-measure codes used by the GeoTIFF keys, as metres per unit.
_EPSG_LINEAR_UNITS = {9001: METRE, 9002: INTERNATIONAL_FOOT, 9003: US_SURVEY_FOOT}
_GEOKEY_PROJ_LINEAR_UNITS = 3076
_GEOKEY_VERTICAL_CS = 4096
_GEOKEY_VERTICAL_UNITS = 4099
_CRS_VLR_CLASSES = ("WktCoordinateSystemVlr", "GeoKeyDirectoryVlr", "GeoAsciiParamsVlr",
                    "GeoDoubleParamsVlr")


def _laspy():
    import laspy  # imported lazily: `import sylva.core` must not need laspy

    return laspy


# --------------------------------------------------------------------------- template


@dataclass(eq=False)
class LasTemplate:
    """What a lossless write needs: the source header and raw point records.

    ``header`` is the laspy :class:`~laspy.LasHeader` of the source file (never
    modified; :func:`write_las` works on a copy), ``array`` the raw structured
    numpy record array (integer X/Y/Z, packed bit fields, extra bytes) of the
    points the cloud holds, and ``crs`` the CRS parsed from the header (so a
    writer can tell whether the cloud's CRS was overridden).
    """

    header: Any
    array: np.ndarray
    crs: Any = None

    def subset(self, index) -> "LasTemplate":
        """The records of the selected points (boolean mask or index array)."""
        return LasTemplate(self.header, self.array[np.asarray(index)], self.crs)

    def __len__(self) -> int:
        return len(self.array)

    def record(self):
        """The records as a laspy ScaleAwarePointRecord (shares memory)."""
        laspy = _laspy()
        h = self.header
        return laspy.ScaleAwarePointRecord(self.array, h.point_format, h.scales, h.offsets)


# --------------------------------------------------------------------------- CRS and units


def _snap_unit(factor: float) -> float:
    for known in (METRE, INTERNATIONAL_FOOT, US_SURVEY_FOOT):
        if abs(factor - known) <= 1e-12 * known:
            return known
    return float(factor)


def units_of(crs) -> Units:
    """Metres per unit of the horizontal and vertical axes of a pyproj CRS.

    Horizontal: the unit of the horizontal (projected) part.  Vertical: the
    unit of the vertical part of a compound CRS, or of the third axis of a 3D
    CRS, else the horizontal unit.  A geographic horizontal CRS has no linear
    unit: its horizontal factor is NaN (and its vertical unit metres unless
    the CRS says otherwise).  ``None`` gives metres.
    """
    if crs is None:
        return METRES
    if getattr(crs, "is_bound", False):
        crs = crs.source_crs
    horizontal, vertical = crs, None
    if crs.is_compound:
        horizontal = None
        for sub in crs.sub_crs_list:
            if sub.is_bound:
                sub = sub.source_crs
            if sub.is_vertical:
                vertical = vertical or sub
            elif horizontal is None:
                horizontal = sub
    elif crs.is_vertical:
        horizontal, vertical = None, crs

    h_m = METRE
    axes = list(horizontal.axis_info) if horizontal is not None else []
    if horizontal is not None and horizontal.is_geographic:
        h_m = math.nan
    elif axes:
        h_m = _snap_unit(axes[0].unit_conversion_factor)

    if vertical is not None and vertical.axis_info:
        v_m = _snap_unit(vertical.axis_info[0].unit_conversion_factor)
    elif len(axes) >= 3 and axes[2].direction.lower() in ("up", "down"):
        v_m = _snap_unit(axes[2].unit_conversion_factor)
    elif math.isnan(h_m):
        v_m = METRE
    else:
        v_m = h_m
    return Units(horizontal_m=h_m, vertical_m=v_m)


def as_crs(crs, where: str):
    """A pyproj CRS from anything pyproj accepts ("EPSG:2994", 26912, WKT, CRS)."""
    if crs is None:
        return None
    import pyproj

    if isinstance(crs, pyproj.CRS):
        return crs
    try:
        return pyproj.CRS.from_user_input(crs)
    except Exception as err:  # pyproj.exceptions.CRSError and friends
        raise CRSError(f"{where}: the CRS {crs!r} given is not understood ({err})") from None


def _geokeys(header) -> dict:
    """GeoTIFF keys stored inline (tiff_tag_location 0) as {key id: value}."""
    try:
        vlr = header.vlrs.get("GeoKeyDirectoryVlr")
    except Exception:
        return {}
    keys = {}
    for v in vlr:
        for k in getattr(v, "geo_keys", []):
            if k.tiff_tag_location == 0 and k.id:
                keys[int(k.id)] = int(k.value_offset)
    return keys


def parse_crs(header, where: str = "the LAS file"):
    """The CRS of a laspy header (WKT preferred over GeoTIFF keys) or None.

    A GeoTIFF vertical CRS key (VerticalCSTypeGeoKey, an EPSG code) is joined
    to the horizontal CRS as a compound CRS.  A CRS record that exists but
    cannot be understood raises :class:`CRSError`.
    """
    import pyproj

    has_wkt = bool(header.vlrs.get("WktCoordinateSystemVlr"))
    try:
        crs = header.parse_crs()
    except Exception as err:
        raise CRSError(
            f"{where}: its CRS record cannot be understood ({err}); "
            "pass a CRS with the CRS parameter"
        ) from None
    if crs is not None and not has_wkt and not crs.is_compound:
        code = _geokeys(header).get(_GEOKEY_VERTICAL_CS)
        if code is not None and 1024 <= code <= 32766:
            try:
                vertical = pyproj.CRS.from_epsg(code)
                crs = pyproj.CRS.from_user_input(
                    pyproj.crs.CompoundCRS(f"{crs.name} + {vertical.name}", [crs, vertical])
                )
            except Exception:
                pass  # an unknown vertical code: keep the horizontal CRS
    return crs


def _units_from_header(header, crs, from_file: bool) -> Units:
    units = units_of(crs)
    if not from_file:
        return units
    keys = _geokeys(header)
    if crs is None:
        h = _EPSG_LINEAR_UNITS.get(keys.get(_GEOKEY_PROJ_LINEAR_UNITS), METRE)
        v = _EPSG_LINEAR_UNITS.get(keys.get(_GEOKEY_VERTICAL_UNITS), h)
        return Units(horizontal_m=h, vertical_m=v)
    if not crs.is_compound and _GEOKEY_VERTICAL_UNITS in keys:
        v = _EPSG_LINEAR_UNITS.get(keys[_GEOKEY_VERTICAL_UNITS])
        if v is not None:
            return Units(horizontal_m=units.horizontal_m, vertical_m=v)
    return units


def _crs_and_units(header, crs, where, units=None):
    """(crs, units, parsed-from-file crs) for a header and optional overrides."""
    if crs is not None:
        crs = as_crs(crs, where)
        parsed = None
    else:
        crs = parsed = parse_crs(header, where)
    if units is not None:
        if not isinstance(units, Units):
            units = Units(horizontal_m=float(units), vertical_m=float(units))
        return crs, units, parsed
    if crs is not None and parsed is None:  # an override: its own units
        return crs, units_of(crs), None
    return crs, _units_from_header(header, parsed, True), parsed


def require_linear(units: Units, crs, where: str) -> None:
    """Refuse a geographic (degree) CRS: Sylva computes in metres from x/y in
    metres or feet, and does not reproject."""
    if math.isnan(units.horizontal_m):
        name = crs.name if crs is not None else "geographic"
        raise CRSError(
            f"{where}: its CRS ({name}) is geographic, in degrees; Sylva needs projected "
            "coordinates in metres or feet: reproject the file first, or pass the right "
            "CRS with the CRS parameter"
        )


def require_crs(cloud: PointCloud) -> PointCloud:
    """Return ``cloud`` if it has a CRS, else raise :class:`CRSError` naming its file."""
    if cloud.crs is None:
        raise CRSError(f"{cloud.name} has no CRS; pass one with the CRS parameter")
    return cloud


# --------------------------------------------------------------------------- reading


def _check_file(path) -> Path:
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: file not found")
    if path.is_dir():
        raise InputError(f"{path}: is a folder, not a LAS/LAZ file")
    return path


def _bad_file(path, err) -> InputError:
    if isinstance(err, SylvaError):
        return err
    text = str(err) or type(err).__name__
    if "fill whole buffer" in text or "unexpected end" in text.lower() or "truncat" in text.lower():
        return InputError(f"{path}: the file is truncated or damaged ({text})")
    return InputError(f"{path}: not a readable LAS/LAZ file ({text})")


def _check_size(path: Path, header) -> None:
    """Reject a file shorter than its header says (truncated), before decoding.

    LAS: the header's point count times the record length must fit.  LAZ: the
    first 8 bytes of the point data give the offset of the chunk table, which
    a complete file holds (-1 means a streaming writer put the offset at the
    end of the file; that case is left to the decoder).
    """
    size = path.stat().st_size
    if header.are_points_compressed:
        with open(path, "rb") as f:
            f.seek(header.offset_to_point_data)
            head = f.read(8)
        table = int.from_bytes(head, "little", signed=True) if len(head) == 8 else None
        if table is None or (table != -1 and not (0 < table <= size - 8)):
            raise InputError(
                f"{path}: the file is truncated or damaged ({size} bytes; its LAZ chunk "
                "table is missing)"
            )
        if table != -1:
            _check_chunk_table(path, header)
        return
    need = header.offset_to_point_data + header.point_count * header.point_format.size
    if size < need:
        raise InputError(
            f"{path}: the file is truncated ({size} bytes, its header announces "
            f"{header.point_count} points needing {need} bytes)"
        )
    # more whole records than the header counts: a lying header would hide points (Sylva, not in the papers)
    end = size
    evlr = int(getattr(header, "start_of_first_evlr", 0) or 0)
    if getattr(header, "number_of_evlrs", 0) and header.offset_to_point_data <= evlr <= size:
        end = evlr
    held = (end - header.offset_to_point_data) // header.point_format.size
    if held > header.point_count:
        raise DamagedInputError(
            f"{path}: the file is damaged: its header counts {header.point_count} points but the "
            f"file holds {held} point records"
        )


def _check_chunk_table(path: Path, header) -> None:
    """The LAZ chunk table must hold the header's point count (Sylva, not in the papers).

    Variable-size chunks list their point counts (their sum must be the header's count);
    fixed-size chunks all hold ``chunk_size`` points but the last, so the count must need
    exactly that many chunks.  A table that cannot be read means a damaged file.
    """
    try:
        import lazrs
    except ImportError:  # laspy decodes with another backend: leave it to the decoder
        return
    try:
        record = header.vlrs.get("LasZipVlr")[0].record_data
        vlr = lazrs.LazVlr(record)
        with open(path, "rb") as fh:
            fh.seek(header.offset_to_point_data)
            table = lazrs.read_chunk_table(fh, vlr)
    except (IndexError, AttributeError):
        return
    except Exception as err:  # noqa: BLE001 — lazrs.LazrsError, OSError
        raise DamagedInputError(f"{path}: the file is damaged: its LAZ chunk table cannot be read ({err})") from None
    if table is None:
        return
    n = int(header.point_count)
    if vlr.uses_variable_size_chunks():
        held = int(sum(int(c[0]) for c in table))
        if held != n:
            raise DamagedInputError(f"{path}: the file is damaged: its header counts {n} points but its "
                                    f"LAZ chunks hold {held}")
        return
    size = int(vlr.chunk_size())
    if size <= 0 or size >= 2**32 - 1:
        return
    chunks = len(table)
    need = -(-n // size) if n else 0
    if chunks != need:
        raise DamagedInputError(
            f"{path}: the file is damaged: its header counts {n} points, which need {need} LAZ chunk(s) "
            f"of {size}, but the file has {chunks} ({(chunks - 1) * size + 1}–{chunks * size} points)")


def _check_bounds(path, array: np.ndarray, header) -> None:
    """Every point inside the header's bounds, give or take one scale step (Sylva, not in the papers).

    A LAZ chunk with a damaged block decodes without an error into points kilometres away;
    a header that does not match its points is a damaged file too.  Vectorised: the
    integer records' minimum and maximum per axis.  Headers without bounds (all zero)
    are not checked.
    """
    if len(array) == 0:
        return
    mins, maxs = np.asarray(header.mins, dtype=np.float64), np.asarray(header.maxs, dtype=np.float64)
    if not (np.any(mins) or np.any(maxs)) or not (np.all(np.isfinite(mins)) and np.all(np.isfinite(maxs))):
        return
    for i, name in enumerate(_XYZ):
        column = array[name]
        lo = float(column.min()) * header.scales[i] + header.offsets[i]
        hi = float(column.max()) * header.scales[i] + header.offsets[i]
        slack = abs(header.scales[i]) * 1.01 + 1e-9 * max(abs(mins[i]), abs(maxs[i]), 1.0)
        if lo < mins[i] - slack or hi > maxs[i] + slack:
            raw = np.asarray(column, dtype=np.float64) * header.scales[i] + header.offsets[i]
            outside = int(np.count_nonzero((raw < mins[i] - slack) | (raw > maxs[i] + slack)))
            raise DamagedInputError(
                f"{path}: the file is damaged: {outside:,} point(s) have {name.lower()} from {lo:,.3f} to "
                f"{hi:,.3f}, outside the header's bounds {mins[i]:,.3f}–{maxs[i]:,.3f} (a corrupted block, "
                "or a header that does not describe its points)")


def _check_no_more_points(reader, path, header) -> None:
    """After the header's count of points, a LAZ's last chunk must be exhausted.

    lazrs refuses to decode past the last chunk of a complete file; when one more point
    decodes, the header counts fewer points than the file holds (a header smaller than its
    data would silently drop points).  Costs one point's decoding (Sylva, not in the papers).
    """
    decompressor = getattr(getattr(reader, "point_source", None), "decompressor", None)
    if decompressor is None or not header.are_points_compressed:
        return
    buf = bytearray(header.point_format.size)
    try:
        decompressor.decompress_many(buf)
    except Exception:  # noqa: BLE001 — the expected end of the data
        return
    except BaseException as exc:
        # lazrs 0.6 (laspy 2.5's LAZ backend, Debian 13's) panics there instead of raising: a pyo3
        # PanicException, which derives from BaseException; the same end of the data
        if type(exc).__name__ != "PanicException":
            raise
        return
    raise DamagedInputError(f"{path}: the file is damaged: its header counts {header.point_count} points "
                            "but its LAZ data holds more")


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


def _parallel_laz_used() -> None:
    global PARALLEL_LAZ_USED
    PARALLEL_LAZ_USED = True


def _decoding(reader) -> None:
    """Note that points of ``reader`` are about to be decoded (see PARALLEL_LAZ_USED)."""
    if getattr(reader, "sylva_parallel", False):
        _parallel_laz_used()


def _open(path: Path, parallel: bool = True):
    laspy = _laspy()
    reader = None
    try:
        backend = None if parallel else laspy.LazBackend.Lazrs
        reader = laspy.open(str(path), laz_backend=backend) if backend is not None else laspy.open(str(path))
        reader.sylva_parallel = parallel and reader.header.are_points_compressed
        _check_size(path, reader.header)
    except Exception as err:
        if reader is not None:
            reader.close()
        raise _bad_file(path, err) from None
    return reader


def _field(array: np.ndarray, fmt, name: str, packed: dict, sub_fields: dict) -> np.ndarray:
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
    laspy = _laspy()
    fmt = header.point_format
    n = len(array)
    xyz = np.empty((n, 3), dtype=np.float64)
    for i, name in enumerate(_XYZ):
        # X * scale + offset, as laspy computes it, so values match laspy.read exactly
        column = xyz[:, i]
        np.multiply(array[name], header.scales[i], out=column)
        column += header.offsets[i]
    sub_fields = laspy.point.dims.get_sub_fields_dict(fmt.id)
    packed = {}
    attrs = {}
    for name in fmt.dimension_names:
        if name in _XYZ:
            continue
        values = _field(array, fmt, name, packed, sub_fields)
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
    path = _check_file(path)
    check(cancelled)
    report(progress, 0.0, f"reading {path.name}")
    with _open(path) as reader:
        header = reader.header
        crs, units, parsed = _crs_and_units(header, crs, str(path), units)
        require_linear(units, crs, str(path))
        if header.point_count == 0 and not allow_empty:
            raise EmptyInputError(f"{path}: the file holds no points")
        try:
            _decoding(reader)
            las = reader.read()
        except Exception as err:
            raise _bad_file(path, err) from None
        _check_no_more_points(reader, path, header)
    if len(las.points) != header.point_count:
        raise InputError(f"{path}: the file is truncated ({len(las.points)} of "
                         f"{header.point_count} points could be read)")
    _check_bounds(path, las.points.array, header)
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
    path = _check_file(path)
    reader = _open(path)
    try:
        header = reader.header
        crs, units, parsed = _crs_and_units(header, crs, str(path), units)
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
    path = _check_file(path)
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
                raise _bad_file(path, err) from None
            if len(record) == 0:
                break
            done += len(record)
            _check_bounds(path, record.array, header)
            if done >= header.point_count:
                _check_no_more_points(reader, path, header)
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
    path = _check_file(path)
    with _open(path) as reader:
        h = reader.header
        crs, units, _ = _crs_and_units(h, crs, str(path))
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


# --------------------------------------------------------------------------- writing


def _extra_type(name: str, values: np.ndarray, where: str) -> str:
    """Extra-bytes type of an array: its own dtype (bool -> uint8, float16 -> float32)."""
    dt = values.dtype
    if dt == np.bool_:
        dt = np.dtype("u1")
    elif dt == np.float16:
        dt = np.dtype("f4")
    if dt.kind not in "iuf" or dt.itemsize > 8:
        raise InputError(f"{where}: attribute {name!r} of type {values.dtype} cannot be "
                         "written as a LAS extra dimension (numbers only)")
    dt = dt.newbyteorder("<")
    if values.ndim == 1:
        return dt.str
    if values.ndim == 2 and values.shape[1] in (2, 3):
        return f"{values.shape[1]}{dt.str}"
    raise InputError(f"{where}: attribute {name!r} has shape {values.shape}; LAS extra "
                     "dimensions hold 1, 2 or 3 numbers per point")


def _standard_names() -> set:
    dims = _laspy().point.dims
    names = set()
    for fmt_id in dims.POINT_FORMAT_DIMENSIONS:
        names.update(_laspy().PointFormat(fmt_id).dimension_names)
    return names


def _format_for(header, wanted_std: set) -> Optional[int]:
    """Smallest point format (version-compatible if possible) holding all ``wanted_std``."""
    laspy = _laspy()
    current = set(header.point_format.standard_dimension_names)
    need = current | wanted_std
    for fmt_id in sorted(laspy.point.dims.POINT_FORMAT_DIMENSIONS):
        if need <= set(laspy.PointFormat(fmt_id).standard_dimension_names):
            return fmt_id
    return None


def _new_header(cloud: PointCloud, names: set, where: str):
    """LAS 1.4 header for a cloud without template: format 6/7/8, 0.001-unit scale."""
    laspy = _laspy()
    if "nir" in names:
        fmt = 8
    elif names & {"red", "green", "blue"}:
        fmt = 7
    else:
        fmt = 6
    header = laspy.LasHeader(version="1.4", point_format=fmt)
    header.generating_software = "Sylva"
    if len(cloud):
        lo, hi = cloud.xyz.min(axis=0), cloud.xyz.max(axis=0)
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise InputError(f"{where}: the point cloud has non-finite coordinates")
        offsets = np.floor(lo)
        scales = np.full(3, 0.001)
        for i in range(3):
            while (hi[i] - offsets[i]) / scales[i] > 2**31 - 2:
                scales[i] *= 10.0
    else:
        offsets, scales = np.zeros(3), np.full(3, 0.001)
    header.offsets = offsets
    header.scales = scales
    return header


def _set_crs(header, crs) -> None:
    """Replace the header's CRS VLRs: GeoTIFF keys for formats 0-5 when an EPSG
    code exists (older readers expect them), else an OGC WKT VLR (WKT1 when
    expressible, as LAS 1.4 specifies)."""
    laspy = _laspy()
    for name in _CRS_VLR_CLASSES:
        try:
            header.vlrs.extract(name)
        except Exception:
            pass
    if header.point_format.id < 6 and not crs.is_compound and crs.to_epsg() is not None:
        try:
            from laspy.vlrs.geotiff import create_geotiff_projection_vlrs

            keys = create_geotiff_projection_vlrs(crs)
            header.vlrs.extend(keys)
            if header.parse_crs() == crs:
                return
            for name in _CRS_VLR_CLASSES:
                try:
                    header.vlrs.extract(name)
                except Exception:
                    pass
        except Exception:
            pass
    wkt = None
    try:
        wkt = crs.to_wkt("WKT1_GDAL")
    except Exception:
        wkt = None
    if not wkt or laspy.vlrs.known.WktCoordinateSystemVlr(wkt).parse_crs() != crs:
        wkt = crs.to_wkt()
    header.vlrs.append(laspy.vlrs.known.WktCoordinateSystemVlr(wkt))
    if header.version.minor >= 4:
        header.global_encoding.wkt = True


def _strip_copc(header) -> None:
    """A rewritten file is plain LAS/LAZ: drop COPC info/hierarchy records
    (in place, so the other records keep their order)."""
    for records in (header.vlrs, header.evlrs or []):
        for v in [v for v in records if v.user_id == "copc"]:
            records.remove(v)


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal shapes and values (NaN equal to NaN for floats)."""
    if a.shape != b.shape:
        return False
    if np.array_equal(a, b):
        return True
    nan = a.dtype.kind == "f" and b.dtype.kind == "f"
    return nan and bool(np.array_equal(a, b, equal_nan=True))


def _prepare(cloud: PointCloud, extra: Optional[dict], where: str):
    """A laspy LasData holding the cloud, its template's records and ``extra``."""
    laspy = _laspy()
    n = len(cloud)
    values = {k: np.asarray(v) for k, v in cloud.attrs.items() if k not in ("x", "y", "z")}
    for k, v in (extra or {}).items():
        v = np.asarray(v)
        if v.ndim == 0 or len(v) != n:
            raise InputError(f"{where}: extra dimension {k!r} has "
                             f"{v.size if v.ndim == 0 else len(v)} values for {n} points")
        values[k] = v
    for k in list(values):
        if k in _XYZ:
            raise InputError(f"{where}: attribute {k!r} clashes with the X/Y/Z coordinates")
        if values[k].dtype == np.bool_:
            values[k] = values[k].astype(np.uint8)

    template = cloud.template if isinstance(cloud.template, LasTemplate) else None
    shared = False  # the records are the template's: copy before the first change
    if template is not None:
        header = copy.deepcopy(template.header)
        array = template.array if len(template) == n else None
        shared = array is not None
    else:
        header = _new_header(cloud, set(values), where)
        array = None
    _strip_copc(header)
    if str(header.version) == "1.0":
        # laspy writes 1.1 onwards; 1.1 has the same header and record layout
        # (the 1.0 "reserved" field became file source id + global encoding)
        header.version = laspy.header.Version(1, 1)

    # standard dimensions the format lacks: upgrade the format if one holds them all
    standard = _standard_names() - set(_XYZ)
    missing_std = {k for k in values if k in standard} - set(header.point_format.dimension_names)
    if missing_std:
        fmt_id = _format_for(header, missing_std)
        if fmt_id is not None and fmt_id != header.point_format.id:
            if array is None:
                array = laspy.ScaleAwarePointRecord.zeros(n, header=header).array
            las = laspy.LasData(header, laspy.ScaleAwarePointRecord(
                array, header.point_format, header.scales, header.offsets))
            las = laspy.convert(las, point_format_id=fmt_id)
            header, array, shared = las.header, las.points.array, False
    if array is None:
        array = laspy.ScaleAwarePointRecord.zeros(n, header=header).array
    las = laspy.LasData(header, laspy.ScaleAwarePointRecord(
        array, header.point_format, header.scales, header.offsets))

    present = set(header.point_format.dimension_names)
    new_dims = []
    for k, v in values.items():
        if k in present:
            continue
        if len(k.encode("ascii", "replace")) > 32:
            raise InputError(f"{where}: attribute name {k!r} is longer than the 32 "
                             "characters a LAS extra dimension name may have")
        new_dims.append(laspy.ExtraBytesParams(name=k, type=_extra_type(k, v, where)))
    if new_dims:
        las.add_extra_dims(new_dims)  # reallocates the records
        shared = False

    def writable():
        nonlocal shared
        if shared:
            las.points = laspy.ScaleAwarePointRecord(
                las.points.array.copy(), header.point_format, header.scales, header.offsets)
            shared = False

    # coordinates: rewrite only what differs from the records
    for i, axis in enumerate("xyz"):
        current = np.asarray(las.points[axis])
        wanted = cloud.xyz[:, i]
        if _same(current, wanted):
            continue
        if not np.all(np.isfinite(wanted)):
            raise InputError(f"{where}: the point cloud has non-finite {axis} coordinates")
        writable()
        try:
            las.points[axis] = wanted
        except OverflowError:
            raise InputError(
                f"{where}: {axis} coordinates ({wanted.min():g}..{wanted.max():g}) do not fit "
                f"the file's scale {header.scales[i]:g} and offset {header.offsets[i]:g}"
            ) from None

    # attributes: rewrite only what differs, and check the LAS type holds the values
    fmt = las.point_format
    sub_fields = laspy.point.dims.get_sub_fields_dict(fmt.id)
    packed = {}
    changed = [k for k, v in values.items()
               if not _same(_field(las.points.array, fmt, k, packed, sub_fields), v)]
    for k in changed:
        v = values[k]
        current_arr = np.asarray(las.points[k])
        dim = fmt.dimension_by_name(k)
        try:
            if v.dtype.kind == "f" and current_arr.dtype.kind in "iu" and not dim.is_scaled:
                if not np.array_equal(v, np.round(v)):
                    raise ValueError("non-integer values")
            writable()
            las.points[k] = v
        except (OverflowError, ValueError, TypeError) as err:
            raise InputError(f"{where}: attribute {k!r} cannot be stored in the LAS "
                             f"dimension {k!r} of type {dim.dtype} ({err})") from None
        stored = np.asarray(las.points[k])
        if dim.is_scaled:
            ok = np.allclose(stored, v, rtol=0, atol=float(np.max(dim.scales)) / 2 + 1e-12,
                             equal_nan=True)
        else:
            ok = _same(stored, v)
        if not ok:
            raise InputError(f"{where}: attribute {k!r} has values the LAS dimension "
                             f"{k!r} (type {dim.dtype}) cannot hold")

    # CRS: keep the source's records unless the cloud's CRS differs from them
    crs = cloud.crs
    source_crs = template.crs if template is not None else None
    if crs is not None and (source_crs is None or not (crs is source_crs or crs == source_crs)):
        try:
            _set_crs(header, as_crs(crs, where))
        except SylvaError:
            raise
        except Exception as err:
            raise CRSError(f"{where}: the CRS cannot be written to the file ({err})") from None
    return las


def write_las(path, cloud: PointCloud, extra: Optional[dict] = None, *,
              progress: Progress = None, cancelled: CancelCheck = None) -> Path:
    """Write ``cloud`` to a LAS file, or LAZ (lazrs) when the suffix is ``.laz``.

    With a :class:`LasTemplate` (a cloud read by :func:`read_las`, subset or
    not) the source header is kept — version, point format, scales, offsets,
    VLRs/EVLRs incl. CRS, extra dimensions — and so are the raw records;
    coordinates and attributes that the cloud changed are written over them.
    A standard attribute the format lacks (e.g. ``red`` in format 1) upgrades
    the point format to the smallest one that has it.  Without a template the
    header is LAS 1.4, point format 6 (7 with RGB, 8 with NIR), scale 0.001
    file unit, offsets at the floor of the minimum, CRS as an OGC WKT VLR.

    Attributes not in the point format and ``extra`` (name -> array; the
    dtype decides the extra-bytes type, e.g. int32 ``treeID``) become extra
    dimensions; an existing extra dimension keeps its type.  The file is
    written under a temporary name in the same folder and moved into place;
    nothing is left behind on failure.  Returns the path written.
    """
    laspy = _laspy()
    path = Path(path)
    where = str(path)
    check(cancelled)
    report(progress, 0.0, f"writing {path.name}")
    if not path.parent.is_dir():
        raise InputError(f"{where}: the folder {path.parent} does not exist")
    if path.is_dir():
        raise InputError(f"{where}: is a folder")
    las = _prepare(cloud, extra, where)
    compress = path.suffix.lower() == ".laz"
    check(cancelled)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.part")
    try:
        with open(tmp, "xb") as out:
            if compress:          # laspy compresses with lazrs's thread pool
                _parallel_laz_used()
            las.write(out, do_compress=compress)
        check(cancelled)
        os.replace(tmp, path)
    except BaseException as err:
        try:
            os.remove(tmp)
        except OSError:
            pass
        if isinstance(err, (SylvaError, KeyboardInterrupt, SystemExit)):
            raise
        if isinstance(err, OSError):
            from ..errors import disk_error

            raise disk_error(where, err) from None
        if isinstance(err, laspy.errors.LaspyException):
            raise InputError(f"{where}: cannot write the file ({err})") from None
        raise
    report(progress, 1.0, f"wrote {len(cloud)} points to {path.name}")
    return path
