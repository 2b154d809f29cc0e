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

Modules: :mod:`.template` (:class:`LasTemplate`, laspy imported lazily), :mod:`.crs` (CRS and units of a
header), :mod:`.checks` (the damage checks), :mod:`.reading` (read, inspect, ``PARALLEL_LAZ_USED``: read
it there) and :mod:`.writing` (:func:`write_las`); the public names are re-exported here.
"""
from __future__ import annotations

from .checks import bad_file, check_bounds, check_file, check_no_more_points, check_size
from .crs import as_crs, crs_and_units, parse_crs, require_crs, require_linear, units_of
from .reading import (LasInfo, checked_records, field, las_info, parallel_laz_used, read_las, read_las_chunks,
                      tree_labels)
from .template import XYZ, LasTemplate, load_laspy
from .writing import write_las

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
