"""Wavefront OBJ + MTL of tree models, with the origin in an offset file and a ``.prj``.

``trees.obj`` holds one object ``o tree_<id>`` per tree with groups
``tree_<id>_bark`` (material ``bark``) and ``tree_<id>_leaves`` (material
``leaves_<shape>``, texture coordinates ``vt``).  Vertices are in the SOURCE
CRS grid axes and units (x grid east, y grid north, z up), RELATIVE TO THE
ORIGIN, so that 32-bit tools such as Blender keep millimetre precision:
``CRS coordinates = vertex + origin``.  In Blender import with Forward = Y,
Up = Z.  Side files: ``trees.mtl``, ``trees_leaf_<shape>.png`` (RGBA; the MTL
uses it as ``map_Kd`` and ``map_d``; named after the export, so that a second export into
the same folder does not overwrite the first one's textures), ``trees.prj`` (the CRS, ESRI WKT),
``trees.origin.json`` (origin in CRS coordinates, CRS WKT/EPSG, units) and
``trees.offset.txt`` (the origin as one line ``x y z``, the convention of
CloudCompare's and BlenderGIS's shift files).  ``mtllib`` and ``map_Kd`` take
whitespace-separated file names, so the MTL and texture file names have every space
replaced by ``_`` (Sylva, not in the papers): ``my trees.obj`` refers to ``my_trees.mtl``.  Texture v follows OBJ (0 at
the bottom of the image), as :mod:`sylva.core.leaves` already does.
"""
from __future__ import annotations

import io
from pathlib import Path
from typing import List, Optional, Sequence

import numpy as np

from ..errors import InputError
from ..progress import check, report
from .georef import Georef, default_origin, write_sidecars
from .model import ExportFrame, TreeModel, atomic_write_bytes, check_models

__all__ = ["write_obj"]

_BARK_KD = "0.45 0.33 0.22"


def _rows(fmt: str, array: np.ndarray) -> bytes:
    """One formatted line per row (``fmt % row``), as bytes."""
    if len(array) == 0:
        return b""
    fmt += "\n"
    return "".join([fmt % tuple(r) for r in array.tolist()]).encode()


def _safe_name(name: str) -> str:
    """A file name OBJ/MTL statements can hold: whitespace becomes ``_``."""
    return "_".join(name.split())


def write_obj(models: Sequence[TreeModel], path, frame: ExportFrame, origin=None, leaves: bool = True,
              texture_size: int = 256, decimals: Optional[int] = None, progress=None,
              cancelled=None) -> List[Path]:
    """Write ``path`` (.obj) and its MTL, textures, ``.prj``, origin and offset files; returns the paths.

    ``origin`` in source CRS coordinates (default: centre of the bases at the
    lowest ground); ``decimals`` of the coordinates (default 4: 0.1 mm in
    metres, 0.03 mm in feet).
    """
    path = Path(path)
    models = check_models(models, f"OBJ export to {path}")
    if not path.parent.exists():
        raise InputError(f"OBJ export: the output folder {path.parent} does not exist")
    georef = Georef(frame, default_origin(models) if origin is None else origin)
    dec = 4 if decimals is None else int(decimals)
    vfmt = f"v %.{dec}f %.{dec}f %.{dec}f"
    mtl_path = path.with_name(_safe_name(path.with_suffix(".mtl").name))
    mtl_name = mtl_path.name
    out = io.BytesIO()
    out.write(f"# Sylva tree models: {len(models)} trees\n"
              f"# vertices: source CRS grid axes and units, relative to the origin (add it back)\n"
              f"# origin: {georef.origin[0]!r} {georef.origin[1]!r} {georef.origin[2]!r}\n"
              f"# crs: {georef.crs.name if georef.crs is not None else 'none (local frame)'}\n"
              f"mtllib {mtl_name}\n".encode())
    nv = nt = 0
    shapes: List[str] = []
    for k, m in enumerate(models):
        check(cancelled)
        shift = m.base - georef.origin
        out.write(f"o {m.name}\n".encode())
        wv, wf = m.wood_arrays()
        if len(wf):
            out.write(_rows(vfmt, wv / georef.scale + shift))
            out.write(f"g {m.name}_bark\nusemtl bark\n".encode())
            out.write(_rows("f %d %d %d", wf + nv + 1))
            nv += len(wv)
        if leaves:
            lv, lf, luv = m.leaf_arrays()
            if len(lf):
                shape = m.leaves.texture
                if shape not in shapes:
                    shapes.append(shape)
                out.write(_rows(vfmt, lv / georef.scale + shift))
                out.write(_rows("vt %.5f %.5f", luv))
                out.write(f"g {m.name}_leaves\nusemtl leaves_{shape}\n".encode())
                fv, ft = lf + nv + 1, lf + nt + 1
                out.write(_rows("f %d/%d %d/%d %d/%d", np.stack([fv, ft], axis=2).reshape(-1, 6)))
                nv += len(lv)
                nt += len(luv)
        report(progress, 0.9 * (k + 1) / len(models), f"tree {m.tree_id}")
    written = [atomic_write_bytes(path, out.getvalue())]
    mtl = [f"# Sylva materials\nnewmtl bark\nKa 0 0 0\nKd {_BARK_KD}\nKs 0.02 0.02 0.02\nNs 10\nd 1\nillum 2\n"]
    from ..textures import write_png, leaf_texture

    for shape in shapes:
        png = path.parent / _safe_name(f"{path.stem}_leaf_{shape}.png")
        write_png(png, leaf_texture(shape, texture_size))
        written.append(png)
        mtl.append(f"\nnewmtl leaves_{shape}\nKa 0 0 0\nKd 1 1 1\nKs 0 0 0\nNs 1\nd 1\nillum 2\n"
                   f"map_Kd {png.name}\nmap_d {png.name}\n")
    written.append(atomic_write_bytes(mtl_path, "".join(mtl).encode()))
    o = georef.origin
    written.append(atomic_write_bytes(path.with_suffix(".offset.txt"), f"{o[0]!r} {o[1]!r} {o[2]!r}\n".encode()))
    written.extend(write_sidecars(path, georef, {
        "frame": "source CRS grid, relative to origin_source",
        "axes": "x grid east, y grid north, z up, in the CRS units; CRS coordinates = vertex + origin_source"}))
    report(progress, 1.0, "done")
    return written
