"""Writing a point cloud to LAS/LAZ (:func:`write_las`): its template's header and records kept, what
the cloud changed written over them, new attributes as extra dimensions, the CRS as VLRs; atomically.
"""
from __future__ import annotations

import copy
import os
import uuid
from pathlib import Path
from typing import Optional

import numpy as np

from ...cloud import PointCloud
from ...errors import CRSError, InputError, SylvaError
from ...progress import CancelCheck, Progress, check, report
from .crs import as_crs
from .reading import field, parallel_laz_used
from .template import XYZ, LasTemplate, load_laspy

_CRS_VLR_CLASSES = ("WktCoordinateSystemVlr", "GeoKeyDirectoryVlr", "GeoAsciiParamsVlr",
                    "GeoDoubleParamsVlr")


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
    dims = load_laspy().point.dims
    names = set()
    for fmt_id in dims.POINT_FORMAT_DIMENSIONS:
        names.update(load_laspy().PointFormat(fmt_id).dimension_names)
    return names


def _format_for(header, wanted_std: set) -> Optional[int]:
    """Smallest point format (version-compatible if possible) holding all ``wanted_std``."""
    laspy = load_laspy()
    current = set(header.point_format.standard_dimension_names)
    need = current | wanted_std
    for fmt_id in sorted(laspy.point.dims.POINT_FORMAT_DIMENSIONS):
        if need <= set(laspy.PointFormat(fmt_id).standard_dimension_names):
            return fmt_id
    return None


def _new_header(cloud: PointCloud, names: set, where: str):
    """LAS 1.4 header for a cloud without template: format 6/7/8, 0.001-unit scale."""
    laspy = load_laspy()
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
    laspy = load_laspy()
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
    laspy = load_laspy()
    n = len(cloud)
    values = {k: np.asarray(v) for k, v in cloud.attrs.items() if k not in ("x", "y", "z")}
    for k, v in (extra or {}).items():
        v = np.asarray(v)
        if v.ndim == 0 or len(v) != n:
            raise InputError(f"{where}: extra dimension {k!r} has "
                             f"{v.size if v.ndim == 0 else len(v)} values for {n} points")
        values[k] = v
    for k in list(values):
        if k in XYZ:
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
    standard = _standard_names() - set(XYZ)
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
               if not _same(field(las.points.array, fmt, k, packed, sub_fields), v)]
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
    laspy = load_laspy()
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
                parallel_laz_used()
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
            from ...errors import disk_error

            raise disk_error(where, err) from None
        if isinstance(err, laspy.errors.LaspyException):
            raise InputError(f"{where}: cannot write the file ({err})") from None
        raise
    report(progress, 1.0, f"wrote {len(cloud)} points to {path.name}")
    return path
