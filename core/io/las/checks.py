"""Damage checks of a LAS/LAZ file before and while its points are decoded (issue 17).

A missing file or a folder (:func:`check_file`), a file shorter or longer than its header says or a LAZ
chunk table that does not hold its count (:func:`check_size`), points outside the header's bounds
(:func:`check_bounds`), LAZ data past the header's count (:func:`check_no_more_points`); a laspy or
lazrs error becomes one :class:`InputError` naming the file (:func:`bad_file`).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ...errors import DamagedInputError, InputError, SylvaError
from .template import XYZ


def check_file(path) -> Path:
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: file not found")
    if path.is_dir():
        raise InputError(f"{path}: is a folder, not a LAS/LAZ file")
    return path


def bad_file(path, err) -> InputError:
    if isinstance(err, SylvaError):
        return err
    text = str(err) or type(err).__name__
    if "fill whole buffer" in text or "unexpected end" in text.lower() or "truncat" in text.lower():
        return InputError(f"{path}: the file is truncated or damaged ({text})")
    return InputError(f"{path}: not a readable LAS/LAZ file ({text})")


def check_size(path: Path, header) -> None:
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


def check_bounds(path, array: np.ndarray, header) -> None:
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
    for i, name in enumerate(XYZ):
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


def check_no_more_points(reader, path, header) -> None:
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
