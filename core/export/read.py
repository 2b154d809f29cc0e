"""Read a Sylva GLB back into :class:`~.model.TreeModel` objects (the inverse of :func:`.gltf.write_glb`).

    models, frame = read_models("trees.glb")

What :mod:`.gltf` writes, and how each piece is undone here:

* the georeferencing block (:meth:`.georef.Georef.describe`) in
  ``asset.extras.georeference`` (also on the root node's ``extras``, and in the
  ``<name>.origin.json`` sidecar, read when the GLB itself lacks it): the
  source CRS (``crs_wkt``), its ``units`` and ``origin_source`` rebuild the
  :class:`ExportFrame` and the :class:`Georef` of the file;
* one node ``tree_<id>`` per tree, ``translation`` = the base in ENU metres at
  the origin -> ``base = Georef.enu_to_source(translation)`` (source CRS);
* its mesh: vertices ``J v`` in ENU axes (``J`` the per-tree Jacobian of
  :meth:`Georef.tree_frames`, float32) -> ``v = J^-1 p`` in tree-local metres
  (x grid east, y grid north, z up, origin at the base, the frame
  :mod:`.model` defines), to float32 precision (~1 um at 30 m);
* primitives with material ``bark`` -> the wood :class:`trimesh.Trimesh`;
  material ``leaves_<shape>`` (textured) -> a :class:`sylva.core.leaves.LeafMesh`
  with the UVs flipped back to the OpenGL convention (glTF's v = 1 - v).
  The per-leaf bookkeeping of LeafMesh (tip, base, axis, ...) is not stored in
  a GLB and comes back empty;
* node ``extras`` -> ``TreeModel.attributes``.

A GLB that was not written by Sylva (no georeferencing block) raises
:class:`~sylva.core.errors.InputError` "... has no Sylva georeferencing".
"""
from __future__ import annotations

import json
import re
import struct
from pathlib import Path
from typing import List, Tuple

import numpy as np

from ..cloud import Units
from ..errors import CRSError, EmptyInputError, InputError
from .georef import Georef
from .gltf import accessor_array, read_glb
from .model import ExportFrame, TreeModel

__all__ = ["read_models", "frame_of"]

_TREE_NODE = re.compile(r"^tree_(-?\d+)$")


def _georeference(doc: dict, path: Path) -> dict:
    geo = (doc.get("asset", {}).get("extras") or {}).get("georeference")
    if not isinstance(geo, dict):
        for node in doc.get("nodes", []):
            if node.get("name") == "sylva_root":
                geo = (node.get("extras") or {}).get("georeference")
    if not isinstance(geo, dict):
        sidecar = path.with_name(path.with_suffix("").name + ".origin.json")
        if sidecar.is_file():
            try:
                geo = json.loads(sidecar.read_text(encoding="utf-8"))
            except (ValueError, OSError):
                geo = None
    if not isinstance(geo, dict) or "origin_source" not in geo or "units" not in geo:
        raise InputError(f"{path}: has no Sylva georeferencing (no asset.extras.georeference block and no "
                         f"{path.with_suffix('').name}.origin.json sidecar); export trees with "
                         f"'Reconstruct trees' (sylva:reconstructtrees, MODELS output) first")
    return geo


def frame_of(geo: dict, where: str = "GLB") -> Tuple[ExportFrame, np.ndarray]:
    """(ExportFrame, origin in source CRS) from a Sylva georeferencing block."""
    crs = None
    if geo.get("crs_wkt") or geo.get("crs_epsg"):
        from pyproj import CRS
        from pyproj.exceptions import CRSError as ProjCRSError

        try:  # the EPSG code is only written when PROJ identified the CRS with full confidence
            crs = CRS.from_epsg(int(geo["crs_epsg"])) if geo.get("crs_epsg") else CRS.from_wkt(geo["crs_wkt"])
        except (ProjCRSError, TypeError, ValueError) as exc:
            raise CRSError(f"{where}: the CRS in its georeferencing block is not understood by PROJ: {exc}")
    try:
        units = Units(float(geo["units"]["horizontal_m"]), float(geo["units"]["vertical_m"]))
        origin = np.array([float(c) for c in geo["origin_source"]], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        raise InputError(f"{where}: its Sylva georeferencing block is damaged (units or origin_source)")
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise InputError(f"{where}: its Sylva georeferencing block has no valid origin_source")
    return ExportFrame(crs=crs, units=units), origin


def _material_kind(doc: dict, prim: dict) -> str:
    """"bark", or the leaf shape of a ``leaves_<shape>`` material."""
    mats = doc.get("materials", [])
    idx = prim.get("material")
    name = mats[idx].get("name", "") if idx is not None and 0 <= idx < len(mats) else ""
    if name.startswith("leaves_") or "TEXCOORD_0" in prim.get("attributes", {}):
        return name[len("leaves_"):] if name.startswith("leaves_") else (name or "ovate")
    return "bark"


def _leaf_mesh(vertices, faces, uvs, shape):
    from ..leaves import LeafMesh

    z3 = np.zeros((0, 3))
    needles = "needle" in shape
    return LeafMesh(vertices, faces, uvs, shape, f"sylva_{'needles' if needles else 'leaf'}_{shape}",
                    np.zeros(0, dtype=np.int64), z3, z3, z3, np.zeros(0), np.zeros(0, dtype=np.int64),
                    {"source": "glb"})


def _merge(parts):
    vs, fs, n = [], [], 0
    for v, f in parts:
        vs.append(v)
        fs.append(f + n)
        n += len(v)
    return np.concatenate(vs), np.concatenate(fs)


def read_models(path) -> Tuple[List[TreeModel], ExportFrame]:
    """(models in file order, frame) of a GLB written by :func:`.gltf.write_glb` (a tile or one tree)."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    try:
        doc, binary = read_glb(path)
    except (struct.error, UnicodeDecodeError, ValueError) as exc:  # truncated, or not JSON inside
        raise InputError(f"{path}: not a glTF 2.0 binary file, or a damaged one ({exc})") from None
    if not isinstance(doc, dict):
        raise InputError(f"{path}: not a glTF 2.0 binary file (its JSON chunk is not an object)")
    geo = _georeference(doc, path)
    frame, origin = frame_of(geo, str(path))
    try:
        georef = Georef(frame, origin)
    except CRSError as exc:
        raise CRSError(f"{path}: {exc}") from None
    nodes = doc.get("nodes", [])
    picked = []
    for node in nodes:
        match = _TREE_NODE.match(str(node.get("name", "")))
        if match and "mesh" in node:
            if "rotation" in node or "scale" in node or "matrix" in node:
                raise InputError(f"{path}: node {node['name']} has a rotation/scale/matrix; "
                                 f"Sylva writes tree nodes with a translation only")
            picked.append((int(match.group(1)), node))
    if not picked:
        raise EmptyInputError(f"{path}: holds no tree models (no node named tree_<id> with a mesh); "
                              f"there is nothing to export")
    translations = np.array([n.get("translation", [0.0, 0.0, 0.0]) for _, n in picked], dtype=np.float64)
    bases = georef.enu_to_source(translations)
    _, jac = georef.tree_frames(bases)
    models = []
    for k, (tree_id, node) in enumerate(picked):
        wood_parts, leaf_parts, shape = [], [], None
        try:
            mesh = doc["meshes"][node["mesh"]]
            for prim in mesh.get("primitives", []):
                if prim.get("mode", 4) != 4:
                    raise InputError(f"{path}: tree {tree_id} has a primitive that is not triangles")
                pos = accessor_array(doc, binary, prim["attributes"]["POSITION"]).astype(np.float64)
                faces = accessor_array(doc, binary, prim["indices"]).astype(np.int64).reshape(-1, 3)
                local = np.linalg.solve(jac[k], pos.T).T
                kind = _material_kind(doc, prim)
                if kind == "bark":
                    wood_parts.append((local, faces))
                else:
                    tex = accessor_array(doc, binary, prim["attributes"]["TEXCOORD_0"]).astype(np.float64)
                    uv = np.column_stack([tex[:, 0], 1.0 - tex[:, 1]])
                    leaf_parts.append((local, faces, uv))
                    shape = shape or kind
        except (KeyError, IndexError, TypeError, ValueError) as exc:
            if isinstance(exc, InputError):
                raise
            raise InputError(f"{path}: the mesh of tree {tree_id} is damaged ({type(exc).__name__}: {exc})")
        wood = None
        if wood_parts:
            v, f = _merge(wood_parts)
            wood = trimesh.Trimesh(v, f, process=False)
        leaves = None
        if leaf_parts:
            v, f = _merge([(lv, lf) for lv, lf, _ in leaf_parts])
            uv = np.concatenate([luv for _, _, luv in leaf_parts])
            leaves = _leaf_mesh(v, f, uv, shape)
        attributes = dict(node.get("extras") or {})
        attributes["tree_id"] = tree_id
        models.append(TreeModel(tree_id, bases[k], wood, leaves, attributes))
    return models, frame
