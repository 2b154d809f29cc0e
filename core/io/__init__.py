"""Point-cloud input/output: LAS/LAZ/COPC (:mod:`.las`), text clouds (:mod:`.xyz`) and PLY (:mod:`.ply`).

:func:`read_cloud` picks the reader from the file name's suffix.
"""
from __future__ import annotations

from pathlib import Path

from ..cloud import PointCloud
from ..errors import InputError
from .las import (
    LasInfo,
    LasTemplate,
    las_info,
    parse_crs,
    read_las,
    read_las_chunks,
    require_crs,
    units_of,
    write_las,
)
from .ply import read_ply
from .xyz import read_xyz

__all__ = [
    "read_cloud",
    "read_las",
    "read_las_chunks",
    "las_info",
    "write_las",
    "require_crs",
    "read_xyz",
    "read_ply",
    "units_of",
    "parse_crs",
    "LasInfo",
    "LasTemplate",
    "LAS_SUFFIXES",
    "TEXT_SUFFIXES",
]

LAS_SUFFIXES = (".las", ".laz")  # .copc.laz ends in .laz
TEXT_SUFFIXES = (".xyz", ".txt", ".csv", ".pts")
PLY_SUFFIXES = (".ply",)


def read_cloud(path, crs=None, **kwargs) -> PointCloud:
    """Read a point cloud, LAS/LAZ/COPC (``.las .laz .copc.laz``), text
    (``.xyz .txt .csv .pts``) or PLY (``.ply``), with ``crs`` overriding the file's CRS.

    Further keyword arguments (``allow_empty``, ``progress``, ``cancelled``,
    and ``units`` for text) go to :func:`read_las` or :func:`read_xyz`.
    """
    suffix = Path(path).suffix.lower()
    if suffix in LAS_SUFFIXES:
        return read_las(path, crs=crs, **kwargs)
    if suffix in TEXT_SUFFIXES:
        return read_xyz(path, crs=crs, **kwargs)
    if suffix in PLY_SUFFIXES:
        return read_ply(path, crs=crs, **kwargs)
    raise InputError(
        f"{path}: unknown point-cloud type {suffix or '(no suffix)'!r}; Sylva reads "
        f"{', '.join(LAS_SUFFIXES + ('.copc.laz',) + TEXT_SUFFIXES + PLY_SUFFIXES)}"
    )
