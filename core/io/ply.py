"""PLY point clouds (ASCII or binary, as scanners and CloudCompare write them), read with trimesh.

Only the vertices are read (a mesh's faces are ignored): x y z, and red / green / blue when present
(8-bit values scaled to LAS's 16 bits, × 257).  PLY carries no CRS: the cloud has none unless given.
"""
from __future__ import annotations

from typing import Optional, Union

import numpy as np

from ..cloud import PointCloud, Units
from ..errors import EmptyInputError, InputError
from ..progress import CancelCheck, Progress, report
from .xyz import open_point_file

__all__ = ["read_ply"]


def read_ply(path, crs=None, units: Optional[Union[Units, float]] = None, *, allow_empty: bool = False,
             progress: Progress = None, cancelled: CancelCheck = None) -> PointCloud:
    """Read the vertices of a PLY file into a :class:`PointCloud` (see the module docstring)."""
    import trimesh

    path, where, crs, units = open_point_file(path, "PLY point cloud", crs, units, progress, cancelled)
    try:
        with open(path, "rb") as f:
            if f.read(3) != b"ply":
                raise InputError(f"{where}: not a PLY file (it does not start with 'ply')")
        geom = trimesh.load(str(path), file_type="ply", process=False)
    except InputError:
        raise
    except Exception as exc:       # trimesh raises many kinds on damaged files
        raise InputError(f"{where}: cannot read this PLY file ({str(exc)[:120]})") from None
    xyz = np.ascontiguousarray(np.asarray(getattr(geom, "vertices", np.zeros((0, 3))), dtype=np.float64)
                               .reshape(-1, 3))
    if len(xyz) == 0 and not allow_empty:
        raise EmptyInputError(f"{where}: the file holds no points")
    if not np.all(np.isfinite(xyz)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(xyz), axis=1))[0])
        raise InputError(f"{where}: point {bad + 1} has a non-finite coordinate")
    attrs = {}
    colors = getattr(geom, "colors", None)
    if colors is None and hasattr(geom, "visual") and getattr(geom.visual, "kind", None) == "vertex":
        colors = geom.visual.vertex_colors
    colors = None if colors is None else np.asarray(colors)
    if colors is not None and colors.shape[:1] == (len(xyz),) and colors.ndim == 2 and colors.shape[1] >= 3 \
            and len(xyz) and np.ptp(colors[:, :3]) > 0:
        for i, name in enumerate(("red", "green", "blue")):
            attrs[name] = (colors[:, i].astype(np.uint16) * 257).astype(np.uint16)
    cloud = PointCloud(xyz=xyz, attrs=attrs, crs=crs, units=units, source=where)
    report(progress, 1.0, f"read {len(cloud)} points from {path.name}")
    return cloud
