"""The export writers (GLB, 3D Tiles, the models_3d layer) against the code they replaced.

The numpy / cKDTree / per-tree implementations that ``core/export/gltf.py``, ``tiles3d.py``,
``gpkg3d.py`` and ``model.py`` had before the speed-up are kept below verbatim (only the import of
``opaque_points`` is absolute) under their old names; the tests write the same synthetic forests
with both and compare the files byte for byte and the tables array for array, on inputs that reach
every branch: lods or none, leaf cards / needles / none, wood-only and leaves-only trees,
unreferenced vertices and degenerate triangles, billboards (alone or with a mesh), a mesh of more
than 65535 vertices (uint32 indices), attributes of every type (bool, int, big int, float, NaN,
missing, text, numpy scalars, clashing names), a geodetic and a local frame.  The compiled kernels
are also run as plain Python (``SYLVA_NO_JIT``) on small inputs.
"""
from __future__ import annotations

import importlib.util
import json
import math
import struct
import warnings
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from sylva.core.errors import InputError
from sylva.core.export import georef as georef_mod
from sylva.core.export import gltf, gpkg3d, tiles3d
from sylva.core.export.georef import Georef, Z_UP_TO_Y_UP, default_origin, write_sidecars
from sylva.core.export.gltf import (_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER, _FLOAT, _UINT, _USHORT, BARK_RGBA,
                                    CONTENTS, NO_DATA, SYLVA_GENERATOR, _pick_lod, _property_name, leaf_png)
from sylva.core.export import model as model_mod
from sylva.core.export.gpkg3d import MIN_TRIANGLE_AREA_M2
from sylva.core.export.model import ExportFrame, TreeModel, atomic_write_bytes, check_models
from sylva.core.export.tiles3d import _box
from sylva.core.progress import check, report
from sylva.core.reconstruct.billboard import BillboardMesh
from sylva.core.table import VectorTable

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("_sylva_bench_export", ROOT / "benchmarks" / "export.py")
_bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_bench)

_BILLBOARD = object()


# =========================================================================== references (the replaced code)

def _unit_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals, unit length (up for isolated/degenerate vertices)."""
    v = vertices.astype(np.float64)
    fn = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    # sum of the face normals at each corner, corner 0 of all faces first (as np.add.at per corner)
    corner = faces.T.ravel()
    n = np.empty_like(v)
    for c in range(3):
        n[:, c] = np.bincount(corner, weights=np.tile(fn[:, c], 3), minlength=len(v))
    length = np.linalg.norm(n, axis=1)
    bad = length < 1e-12
    n[bad] = (0.0, 0.0, 1.0)
    length[bad] = 1.0
    return (n / length[:, None]).astype(np.float32)


def _compact(faces: np.ndarray, n_vertices: int):
    """(used, faces') with ``used`` the sorted referenced vertex indices and ``faces'`` indexing them:
    ``np.unique(faces, return_inverse=True)`` without the sort (a mask and a cumulative sum)."""
    mask = np.zeros(n_vertices, dtype=bool)
    mask[faces.ravel()] = True
    used = np.flatnonzero(mask)
    if len(used) == n_vertices:
        return used, faces.reshape(-1, 3)
    new = np.cumsum(mask) - 1
    return used, new[faces].reshape(-1, 3)


#: Vertex normals are computed for batches of meshes of about this many vertices.
_BATCH_VERTICES = 1_000_000


def _normals_and_bounds(positions: List[np.ndarray], faces: List[np.ndarray]):
    """:func:`_unit_normals` and per-axis (min, max) of many float32 meshes in one vectorised pass.

    The same numbers as one call per mesh: the face normals are summed per vertex in the same
    order (corner 0 of every face of a mesh, then corner 1, then corner 2).
    """
    if not positions:
        return [], [], []
    nv = np.array([len(p) for p in positions], dtype=np.int64)
    # bounded temporaries: batches of meshes of about _BATCH_VERTICES vertices
    cuts = np.r_[0, np.flatnonzero(np.diff(np.cumsum(nv) // _BATCH_VERTICES)) + 1, len(positions)].tolist()
    if len(cuts) == 2:
        return _normals_and_bounds_batch(positions, faces, nv)
    parts = [_normals_and_bounds_batch(positions[a:b], faces[a:b], nv[a:b]) for a, b in zip(cuts[:-1], cuts[1:])]
    return ([n for p in parts for n in p[0]], np.concatenate([p[1] for p in parts]),
            np.concatenate([p[2] for p in parts]))


def _normals_and_bounds_batch(positions: List[np.ndarray], faces: List[np.ndarray], nv: np.ndarray):
    """One batch of :func:`_normals_and_bounds` (``nv`` the vertex count of every mesh)."""
    nf = np.array([len(f) for f in faces], dtype=np.int64)
    voff = np.r_[0, np.cumsum(nv)]
    pos = np.concatenate(positions)
    f = np.concatenate(faces) + np.repeat(voff[:-1], nf)[:, None]
    normals = _unit_normals(pos, f)
    starts = voff[:-1]
    ok = nv > 0
    lo = np.zeros((len(nv), 3), dtype=pos.dtype)
    hi = np.zeros((len(nv), 3), dtype=pos.dtype)
    if ok.any():
        lo[ok] = np.minimum.reduceat(pos, starts[ok], axis=0)
        hi[ok] = np.maximum.reduceat(pos, starts[ok], axis=0)
    bounds = voff.tolist()
    return [normals[a:b] for a, b in zip(bounds[:-1], bounds[1:])], lo, hi


class _Builder:
    """Accumulates the glTF JSON and the binary chunk."""

    def __init__(self):
        self.bin = bytearray()
        self.views: list = []
        self.accessors: list = []

    def view(self, data: bytes, target: Optional[int] = None) -> int:
        pad = (-len(self.bin)) % 8
        self.bin.extend(b"\0" * pad)
        data = data or b"\0"   # glTF: byteLength >= 1 (the fix of issue 17, made in the reference too)
        v = {"buffer": 0, "byteOffset": len(self.bin), "byteLength": len(data)}
        if target is not None:
            v["target"] = target
        self.bin.extend(data)
        self.views.append(v)
        return len(self.views) - 1

    def accessor(self, array: np.ndarray, kind: str, target: Optional[int], minmax: bool = False,
                 bounds=None) -> int:
        """An accessor + view of ``array``; with ``minmax`` its min/max, or ``bounds`` (min, max) given."""
        array = np.ascontiguousarray(array)
        ctype = {np.dtype(np.float32): _FLOAT, np.dtype(np.uint32): _UINT,
                 np.dtype(np.uint16): _USHORT}[array.dtype]
        count = len(array) if kind != "SCALAR" or array.ndim == 1 else array.size
        acc = {"bufferView": self.view(array.tobytes(), target), "componentType": ctype,
               "count": int(count), "type": kind}
        if minmax and bounds is None:
            a = array.reshape(count, -1)
            bounds = (a.min(axis=0), a.max(axis=0))
        if bounds is not None:
            acc["min"] = [float(x) for x in bounds[0]]
            acc["max"] = [float(x) for x in bounds[1]]
        self.accessors.append(acc)
        return len(self.accessors) - 1

    def indices(self, faces: np.ndarray, n_vertices: int) -> int:
        dtype = np.uint16 if n_vertices < 65535 else np.uint32
        return self.accessor(faces.astype(dtype).ravel(), "SCALAR", _ELEMENT_ARRAY_BUFFER)


def _metadata(builder: _Builder, rows: List[dict]):
    """EXT_structural_metadata schema + one property table built from the trees' attributes."""
    keys: List[str] = []
    for r in rows:
        keys.extend(k for k in r if k not in keys)
    props, table = {}, {}
    used = set()
    for key in keys:
        name = _property_name(key)
        while name in used:
            name += "_"
        used.add(name)
        values = [r.get(key) for r in rows]
        present = [v for v in values if v is not None]
        missing = len(present) < len(values)
        if present and all(isinstance(v, bool) for v in present) and not missing:
            bits = np.packbits(np.array(values, dtype=bool), bitorder="little")
            props[name] = {"type": "BOOLEAN"}
            table[name] = {"values": builder.view(bits.tobytes())}
        elif present and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in present):
            ints = all(isinstance(v, int) for v in present)
            if ints and all(-2**31 < v < 2**31 for v in present):
                arr = np.array([NO_DATA if v is None else v for v in values], dtype="<i4")
                props[name] = {"type": "SCALAR", "componentType": "INT32"}
            else:
                arr = np.array([NO_DATA if v is None else v for v in values], dtype="<f8")
                props[name] = {"type": "SCALAR", "componentType": "FLOAT64"}
            if missing:
                props[name]["noData"] = NO_DATA
            table[name] = {"values": builder.view(arr.tobytes())}
        else:
            text = ["" if v is None else str(v) for v in values]
            enc = [t.encode("utf-8") for t in text]
            offsets = np.r_[0, np.cumsum([len(e) for e in enc])].astype("<u4")
            props[name] = {"type": "STRING"}
            if missing:
                props[name]["noData"] = ""
            table[name] = {"values": builder.view(b"".join(enc)),
                           "stringOffsets": builder.view(offsets.tobytes()),
                           "stringOffsetType": "UINT32"}
        props[name]["name"] = str(key)
    return {"schema": {"id": "sylva_trees", "name": "Sylva tree attributes",
                       "classes": {"tree": {"name": "Tree", "properties": props}}},
            "propertyTables": [{"name": "trees", "class": "tree", "count": len(rows), "properties": table}]}


def uses_billboard(model: TreeModel, content: str = "model") -> bool:
    """Whether ``model`` is drawn as its billboard for ``content`` (see the module docstring)."""
    if model.billboard is None or len(model.billboard_arrays()[1]) == 0:
        return False
    return content == "billboard" or not model.has_mesh()


def glb_bytes(models: Sequence[TreeModel], georef: Georef, lod: Optional[int] = None,
              leaves: bool = True, texture_size: int = 256, metadata: bool = True,
              extras: Optional[dict] = None, content: str = "model", cache: Optional[dict] = None) -> bytes:
    """The GLB of ``models`` in the ENU frame of ``georef`` (see the module docstring).

    ``lod`` None writes the full wood; an int writes ``model.lods[lod]`` when the
    model has it (else the full wood); ``"coarsest"`` the lowest level it has.  ``leaves`` False leaves the leaf cards out.
    ``content`` "model" (default) or "billboard": the trees' billboards where they have one.
    ``cache``: a dict shared by several calls on the same, unchanged models (a tile's GLB and its
    tileset, :func:`write_glb` / :func:`~.tiles3d.write_tileset`): each tree's primitives (float32
    positions, normals, bounds, indices) are then computed once per frame; the bytes are the same.
    The dict keeps the models and these arrays alive: drop it after the exports.
    """
    if content not in CONTENTS:
        raise InputError(f"glTF export: content must be one of {', '.join(CONTENTS)}, got {content!r}")
    models = check_models(models, "glTF export")
    b = _Builder()
    bases_enu, jac = georef.tree_frames([m.base for m in models])
    rows = [m.json_attributes() for m in models]
    materials = [{"name": "bark", "pbrMetallicRoughness": {
        "baseColorFactor": list(BARK_RGBA), "metallicFactor": 0.0, "roughnessFactor": 0.9}}]
    textures, images, leaf_material = [], [], {}
    meshes, nodes = [], [None]
    # pass 1: every primitive's arrays; normals and bounds of all of them in one vectorised call
    prim_parts = []
    cached, todo = [], []
    for i, m in enumerate(models):
        parts = []
        if uses_billboard(m, content):
            bv, bf, buv = m.billboard_arrays()
            parts.append((_BILLBOARD, "billboard", bv, bf, buv))
        else:
            wood_lod = _pick_lod(m, lod)
            wv, wf = m.wood_arrays(wood_lod)
            if len(wf):
                parts.append(("bark", ("bark", wood_lod), wv, wf, None))
            if leaves:
                lv, lf, luv = m.leaf_arrays()
                if len(lf):
                    parts.append((m.leaves.texture, "leaves", lv, lf, luv))
        for kind, tag, v, f, uv in parts:
            key = (id(m), tag, jac[i].tobytes())
            hit = cache.get(key) if cache is not None else None
            if hit is not None and hit[0] is m:       # the very model (ids are reused once it is gone)
                prim_parts.append((i, kind) + hit[1][:3])
                cached.append(hit[1][3:])
                continue
            # drop unreferenced vertices so min/max and counts describe what is drawn
            used, f = _compact(f, len(v))
            pos = (v[used] @ jac[i].T).astype(np.float32)
            prim_parts.append((i, kind, pos, f, None if uv is None else uv[used]))
            cached.append(None)
            todo.append((len(prim_parts) - 1, key, m))
    new = _normals_and_bounds([prim_parts[k][2] for k, _, _ in todo], [prim_parts[k][3] for k, _, _ in todo])
    for (k, key, m), normal, lo_k, hi_k in zip(todo, *new):
        cached[k] = (normal, lo_k, hi_k)
        if cache is not None:
            cache[key] = (m, prim_parts[k][2:] + cached[k])
    normals = [c[0] for c in cached]
    lo = [c[1] for c in cached]
    hi = [c[2] for c in cached]
    # pass 2: buffer views and accessors, in file order
    prims_of = [[] for _ in models]
    for k, (i, kind, pos, f, uv) in enumerate(prim_parts):
        m = models[i]
        attrs = {"POSITION": b.accessor(pos, "VEC3", _ARRAY_BUFFER, bounds=(lo[k], hi[k])),
                 "NORMAL": b.accessor(normals[k], "VEC3", _ARRAY_BUFFER)}
        if uv is not None:
            tex = np.column_stack([uv[:, 0], 1.0 - uv[:, 1]]).astype(np.float32)
            attrs["TEXCOORD_0"] = b.accessor(tex, "VEC2", _ARRAY_BUFFER)
            if kind is _BILLBOARD:
                images.append({"name": f"billboard_{m.tree_id}", "mimeType": "image/png",
                               "bufferView": b.view(m.billboard.png())})
                textures.append({"sampler": 0, "source": len(images) - 1})
                materials.append({"name": f"billboard_{m.tree_id}", "alphaMode": "MASK", "alphaCutoff": 0.5,
                                  "doubleSided": True, "pbrMetallicRoughness": {
                                      "baseColorTexture": {"index": len(textures) - 1},
                                      "metallicFactor": 0.0, "roughnessFactor": 0.9}})
                material = len(materials) - 1
            elif kind not in leaf_material:
                png = leaf_png(kind, texture_size)
                images.append({"name": f"leaf_{kind}", "mimeType": "image/png", "bufferView": b.view(png)})
                textures.append({"sampler": 0, "source": len(images) - 1})
                materials.append({"name": f"leaves_{kind}", "alphaMode": "MASK", "alphaCutoff": 0.5,
                                  "doubleSided": True, "pbrMetallicRoughness": {
                                      "baseColorTexture": {"index": len(textures) - 1},
                                      "metallicFactor": 0.0, "roughnessFactor": 0.8}})
                leaf_material[kind] = len(materials) - 1
            if kind is not _BILLBOARD:
                material = leaf_material[kind]
        else:
            material = 0
        prim = {"attributes": attrs, "indices": b.indices(f, len(pos)), "material": material, "mode": 4}
        if metadata:
            attrs["_FEATURE_ID_0"] = b.accessor(np.full(len(pos), i, np.float32), "SCALAR", _ARRAY_BUFFER)
            prim["extensions"] = {"EXT_mesh_features": {"featureIds": [
                {"featureCount": len(models), "attribute": 0, "propertyTable": 0}]}}
        prims_of[i].append(prim)
    for i, m in enumerate(models):
        meshes.append({"name": m.name, "primitives": prims_of[i]})
        nodes.append({"name": m.name, "mesh": len(meshes) - 1,
                      "translation": [float(c) for c in bases_enu[i]], "extras": rows[i]})
    geo = georef.describe()
    if extras:
        geo.update(extras)
    nodes[0] = {"name": "sylva_root", "matrix": [float(c) for c in Z_UP_TO_Y_UP.T.ravel()],
                "children": list(range(1, len(nodes))), "extras": {"georeference": geo}}
    doc = {"asset": {"version": "2.0", "generator": SYLVA_GENERATOR, "extras": {"georeference": geo}},
           "scene": 0, "scenes": [{"name": "trees", "nodes": [0]}], "nodes": nodes, "meshes": meshes,
           "materials": materials}
    if textures:
        doc["textures"] = textures
        doc["images"] = images
        doc["samplers"] = [{"magFilter": 9729, "minFilter": 9987, "wrapS": 33071, "wrapT": 33071}]
    if metadata:
        ext = _metadata(b, rows)
        doc["extensionsUsed"] = ["EXT_mesh_features", "EXT_structural_metadata"]
        doc["extensions"] = {"EXT_structural_metadata": ext}
    doc["accessors"] = b.accessors
    doc["bufferViews"] = b.views
    b.bin.extend(b"\0" * ((-len(b.bin)) % 4))
    doc["buffers"] = [{"byteLength": len(b.bin)}]
    return _pack_glb(doc, bytes(b.bin))


def _pack_glb(doc: dict, binary: bytes) -> bytes:
    js = json.dumps(doc, separators=(",", ":"), allow_nan=False, ensure_ascii=False).encode("utf-8")
    js += b" " * ((-len(js)) % 4)
    total = 12 + 8 + len(js) + 8 + len(binary)
    return (struct.pack("<4sII", b"glTF", 2, total) + struct.pack("<I4s", len(js), b"JSON") + js
            + struct.pack("<I4s", len(binary), b"BIN\0") + binary)


def write_glb(models: Sequence[TreeModel], path, frame: ExportFrame, origin=None, per_tree: bool = False,
              lod: Optional[int] = None, leaves: bool = True, texture_size: int = 256,
              metadata: bool = True, sidecars: bool = True, progress=None, cancelled=None,
              content: str = "model", cache: Optional[dict] = None) -> List[Path]:
    """Write GLB file(s); returns the paths written.

    ``per_tree`` False: one file ``path`` (a tile) with its origin at
    ``origin`` (source CRS; default the centre of the bases at the lowest
    ground).  ``per_tree`` True: ``path`` is a folder that receives
    ``tree_<id>.glb`` per tree, each with its origin at the tree base.  With
    ``sidecars`` a ``.prj`` and a ``.origin.json`` are written next to each file.
    ``content`` "billboard" writes the trees' billboards (Zhou et al.) instead of their models.
    ``cache``: see :func:`glb_bytes` (pass the same dict to :func:`~.tiles3d.write_tileset` of these models).
    """
    models = check_models(models, f"glTF export to {path}")
    path = Path(path)
    out: List[Path] = []
    if not per_tree:
        georef = Georef(frame, default_origin(models) if origin is None else origin)
        report(progress, 0.0, f"writing {len(models)} trees to {path.name}")
        out.append(atomic_write_bytes(path, glb_bytes(models, georef, lod, leaves, texture_size, metadata,
                                                         content=content, cache=cache)))
        if sidecars:
            out.extend(write_sidecars(path, georef))
        report(progress, 1.0, "done")
        return out
    if not path.is_dir():
        raise InputError(f"glTF export: {path} must be an existing folder when writing one file per tree")
    for k, m in enumerate(models):
        check(cancelled)
        georef = Georef(frame, m.base)
        target = path / f"{m.name}.glb"
        out.append(atomic_write_bytes(target, glb_bytes([m], georef, lod, leaves, texture_size, metadata,
                                                            content=content)))
        if sidecars:
            out.extend(write_sidecars(target, georef))
        report(progress, (k + 1) / len(models), f"tree {m.tree_id}")
    return out


def _enu_bounds(model: TreeModel, base_enu, jac, coarse: bool, cache=None):
    """Per-axis (min, max) (3,) of the ENU positions (float32 rounding applied as in the GLB) of what a
    tile draws of ``model``, or None when it draws nothing.

    From the float32 bounds :func:`~.gltf.glb_bytes` put in ``cache`` when it has them (adding the
    base is monotonic, so ``min(p + b) == min(p) + b`` exactly), else from the vertices.
    """
    lo, hi = [], []
    for tag, v, f in _drawn_parts(model, coarse):
        if len(f):
            hit = cache.get((id(model), tag, jac.tobytes())) if cache is not None else None
            if hit is not None and hit[0] is model:
                lo.append(hit[1][4].astype(np.float64) + base_enu)
                hi.append(hit[1][5].astype(np.float64) + base_enu)
            else:
                pts = (v[_used(f, len(v))] @ jac.T).astype(np.float32).astype(np.float64) + base_enu
                lo.append(pts.min(axis=0))
                hi.append(pts.max(axis=0))
    if not lo:
        return None
    return np.min(lo, axis=0), np.max(hi, axis=0)


def _drawn_parts(model: TreeModel, coarse: bool):
    """(cache tag, vertices, faces) of what a tile draws of ``model`` (tags as :func:`~.gltf.glb_bytes`)."""
    if uses_billboard(model, "billboard" if coarse else "model"):
        return [("billboard",) + model.billboard_arrays()[:2]]
    if coarse:
        lod = min(model.lods) if model.lods else None
        return [(("bark", lod),) + model.wood_arrays(lod)]
    return [(("bark", None),) + model.wood_arrays(), ("leaves",) + model.leaf_arrays()[:2]]


def coarse_error(model: TreeModel) -> float:
    """Largest distance (m) from a full-model vertex to the nearest vertex of its coarse version."""
    from scipy.spatial import cKDTree

    if uses_billboard(model, "billboard"):
        if not model.has_mesh():
            return 0.0  # the billboard is the full model too
        from sylva.core.reconstruct.billboard import opaque_points

        fv = np.concatenate([model.leaf_arrays()[0], model.wood_arrays()[0]])
        return _max_nearest(cKDTree(opaque_points(model.billboard)), fv)
    lod = min(model.lods) if model.lods else None
    cv, cf = model.wood_arrays(lod)
    wv, wf = model.wood_arrays()
    lv = model.leaf_arrays()[0]
    fv = np.concatenate([wv, lv])
    if len(fv) == 0:
        return 0.0
    if len(cf) == 0:
        return float(np.linalg.norm(fv - fv.mean(axis=0), axis=1).max() * 2.0)
    used = _used(cf, len(cv))
    if lod is None:
        # the coarse level is the full wood: its drawn vertices are at distance 0, only the others are queried
        drawn = np.zeros(len(wv), dtype=bool)
        drawn[used] = True
        wv = wv[~drawn]
        if len(wv) + len(lv) == 0:
            return 0.0
    return _max_nearest(cKDTree(cv[used]), np.concatenate([lv, wv]))   # leaf quads first: see _max_nearest


def _max_nearest(tree, points: np.ndarray) -> float:
    """``max_i dist(points[i], tree)``, exactly, querying fewer points.

    Vertices come in quads (leaf cards: two corners at the twig, two at the leaf tip); the
    last point of every four is queried first, then the other three only where the triangle
    inequality ``d(p) <= d(q) + |p - q|`` (q that last point) cannot rule out that they beat
    the maximum found so far.  Any order of points gives the exact result (only the number of
    points queried changes).
    """
    n = len(points)
    i = np.arange(n)
    first = (i % 4 == 3) | (i >= n - n % 4)       # one corner of every quad, and a ragged end
    d_first, _ = tree.query(points[first])
    best = float(d_first.max()) if len(d_first) else 0.0
    rest = np.flatnonzero(~first)
    if len(rest) == 0:
        return best
    partner = rest - rest % 4 + 3
    d_of = np.empty(n)
    d_of[first] = d_first
    bound = d_of[partner] + np.linalg.norm(points[rest] - points[partner], axis=1)
    need = rest[bound >= best - 1e-9 * max(1.0, best)]    # margin against rounding of the bound
    if len(need):
        best = max(best, float(tree.query(points[need])[0].max()))
    return best


def _used(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """The sorted vertex indices ``faces`` references (``np.unique(faces)``, by a mask)."""
    mask = np.zeros(n_vertices, dtype=bool)
    mask[faces.ravel()] = True
    return np.flatnonzero(mask)


def write_tileset(models: Sequence[TreeModel], folder, frame: ExportFrame, origin=None, tile_size_m: float = 50.0,
                  texture_size: int = 256, progress=None, cancelled=None, cache=None) -> List[Path]:
    """Write a 3D Tiles 1.1 tileset of ``models`` into ``folder`` (created if missing); returns the files.

    ``origin`` source CRS coordinates of the ENU frame (default: centre of the
    bases at the lowest ground); ``tile_size_m`` edge of the square grid cells
    that group trees into child tiles.  ``cache``: a dict shared with :func:`~.gltf.write_glb` of the
    same models (see :func:`~.gltf.glb_bytes`) so their primitives are encoded once; the child and
    root tiles share one anyway.
    """
    cache = {} if cache is None else cache
    folder = Path(folder)
    models = check_models(models, f"3D Tiles export to {folder}")
    if not tile_size_m > 0:
        raise InputError(f"3D Tiles export: tile_size_m must be positive, got {tile_size_m}")
    georef = Georef(frame, default_origin(models) if origin is None else origin)
    georef.require_geodetic(f"3D Tiles export to {folder}")
    if not folder.parent.exists():
        raise InputError(f"3D Tiles export: the parent folder of {folder} does not exist")
    (folder / "content").mkdir(parents=True, exist_ok=True)
    bases_enu, jac = georef.tree_frames([m.base for m in models])
    cell = np.floor(bases_enu[:, :2] / tile_size_m).astype(np.int64)
    keys = sorted(set(map(tuple, cell.tolist())))
    written: List[Path] = []
    children = []
    bounds = []         # (min, max) of what each child tile draws, then of the coarse models
    for k, key in enumerate(keys):
        check(cancelled)
        idx = [i for i in range(len(models)) if tuple(cell[i]) == key]
        group = [models[i] for i in idx]
        name = f"content/tile_{key[0]}_{key[1]}.glb"
        written.append(atomic_write_bytes(folder / name, glb_bytes(group, georef, None, True, texture_size,
                                                                   cache=cache)))
        tb = [x for x in (_enu_bounds(models[i], bases_enu[i], jac[i], False, cache) for i in idx) if x is not None]
        bounds.append((np.min([x[0] for x in tb], axis=0), np.max([x[1] for x in tb], axis=0)))
        children.append({"boundingVolume": {"box": _box(*bounds[-1])}, "geometricError": 0.0,
                         "content": {"uri": name}})
        report(progress, 0.9 * (k + 1) / len(keys), f"tile {key[0]} {key[1]}: {len(group)} trees")
    root_content = "billboard" if any(m.billboard is not None for m in models) else "model"
    written.append(atomic_write_bytes(folder / "content/root.glb",
                                      glb_bytes(models, georef, lod="coarsest", leaves=False, texture_size=texture_size,
                                                content=root_content, cache=cache)))
    bounds.extend(x for x in (_enu_bounds(m, bases_enu[i], jac[i], True, cache) for i, m in enumerate(models))
                  if x is not None)
    root_error = max(coarse_error(m) for m in models)
    box = _box(np.min([x[0] for x in bounds], axis=0), np.max([x[1] for x in bounds], axis=0))
    diagonal = 2.0 * float(np.linalg.norm([box[3], box[7], box[11]]))
    tileset = {
        "asset": {"version": "1.1", "extras": {"generator": SYLVA_GENERATOR}},
        "geometricError": max(diagonal, root_error),
        "root": {
            "transform": [float(c) for c in georef.enu_to_ecef.T.ravel()],
            "boundingVolume": {"box": box},
            "geometricError": root_error,
            "refine": "REPLACE",
            "content": {"uri": "content/root.glb"},
            "children": children,
        },
        "extras": {"georeference": georef.describe(), "trees": len(models)},
    }
    path = folder / "tileset.json"
    written.append(atomic_write_bytes(path, (json.dumps(tileset, indent=1) + "\n").encode("utf-8")))
    written.extend(write_sidecars(path, georef))
    report(progress, 1.0, "done")
    return written


def attribute_columns(rows: Sequence[dict]) -> Dict[str, np.ndarray]:
    """Columns (key -> array) from per-feature dicts of JSON scalars, typed by their values.

    All ints (bools counted as ints) -> int64 (a missing value makes the column real);
    ints and floats -> float64 with NaN for missing; anything else -> object array of str/None.
    """
    keys: List[str] = []
    for r in rows:
        keys.extend(k for k in r if k not in keys)
    out = {}
    for key in keys:
        values = [r.get(key) for r in rows]
        present = [v for v in values if v is not None]
        numeric = present and all(isinstance(v, (bool, int, float, np.integer, np.floating)) for v in present)
        if numeric and len(present) == len(values) and all(
                isinstance(v, (bool, int, np.integer)) for v in present):
            out[key] = np.array([int(v) for v in values], dtype=np.int64)
        elif numeric:
            out[key] = np.array([np.nan if v is None else float(v) for v in values], dtype=np.float64)
        else:
            out[key] = np.array([None if v is None else str(v) for v in values], dtype=object)
    return out


def _pick(model: TreeModel, coarsest: bool):
    return min(model.lods) if (coarsest and model.lods) else None


#: One triangle as an ISO WKB Polygon Z (little endian): one closed ring of four points.
_TRIANGLE = np.dtype([("order", "u1"), ("type", "<u4"), ("rings", "<u4"), ("points", "<u4"),
                      ("xyz", "<f8", (4, 3))])


def models_table(models: Sequence[TreeModel], frame: ExportFrame, leaves: bool = False, coarsest: bool = True,
                 name: str = "models_3d") -> VectorTable:
    """The 3D layer of ``models`` (see the module docstring); geometry None for a tree with no triangles.

    The MultiPolygon Z geometries are encoded as ISO WKB straight from the
    triangle arrays (``VectorTable.wkb``): a tile's trees hold hundreds of
    thousands of triangles, too many to build as shapely objects."""
    models = check_models(models, "3D layer")
    units = frame.resolved_units()
    scale = np.array([units.horizontal_m, units.horizontal_m, units.vertical_m])
    geometries = np.full(len(models), None, dtype=object)
    counts = np.zeros(len(models), dtype=np.int64)
    lo, hi = np.full(2, np.inf), np.full(2, -np.inf)
    for i, m in enumerate(models):
        parts = [m.wood_arrays(_pick(m, coarsest))]
        if leaves:
            parts.append(m.leaf_arrays()[:2])
        tris = []
        for v, f in parts:
            if len(f):
                tri = v[f]                                               # (k, 3, 3) local metres
                area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
                tris.append(tri[area >= MIN_TRIANGLE_AREA_M2])
        src = m.base + np.concatenate(tris) / scale if tris else np.zeros((0, 3, 3))   # source CRS
        if len(src) == 0:
            continue
        rec = np.empty(len(src), dtype=_TRIANGLE)
        rec["order"], rec["type"], rec["rings"], rec["points"] = 1, 1003, 1, 4
        rec["xyz"][:, :3] = src
        rec["xyz"][:, 3] = src[:, 0]                                     # closed ring
        geometries[i] = struct.pack("<BII", 1, 1006, len(src)) + rec.tobytes()
        counts[i] = len(src)
        lo = np.minimum(lo, src[..., :2].min(axis=(0, 1)))
        hi = np.maximum(hi, src[..., :2].max(axis=(0, 1)))
    columns = attribute_columns([m.json_attributes() for m in models])
    columns["n_triangles"] = counts
    extent = (lo[0], lo[1], hi[0], hi[1]) if counts.any() else None
    return VectorTable(name, "polygon", geometries, columns, frame.pyproj_crs(), has_z=True, wkb=True,
                       extent=extent)


def json_scalar(value):
    """A JSON-serialisable scalar for an attribute value (numpy scalars unwrapped, NaN -> None)."""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return str(value)


# =========================================================================== synthetic forests

UTM = ExportFrame("EPSG:32632")
ORIGIN = np.array([500000.0, 5400000.0, 300.0])


def _billboard(seed: int, quads: int = 3) -> BillboardMesh:
    """``quads`` vertical textured quads around the z axis, a random binary-alpha atlas (one column a quad)."""
    rng = np.random.default_rng(seed)
    h, w = 16, 8 * quads
    tex = np.zeros((h, w, 4), dtype=np.uint8)
    tex[..., :3] = rng.integers(0, 256, (h, w, 3))
    tex[..., 3] = np.where(rng.uniform(size=(h, w)) < 0.6, 255, 0)
    verts, uvs, faces = [], [], []
    for q in range(quads):
        a = math.pi * q / quads
        d = np.array([math.cos(a), math.sin(a), 0.0]) * (1.5 + 0.3 * q)
        verts += [-d, d, d + [0, 0, 6.0], -d + [0, 0, 6.0]]
        u0, u1 = q / quads, (q + 1) / quads
        uvs += [[u0, 0.0], [u1, 0.0], [u1, 1.0], [u0, 1.0]]
        faces += [[4 * q, 4 * q + 1, 4 * q + 2], [4 * q, 4 * q + 2, 4 * q + 3]]
    return BillboardMesh(np.array(verts) + [0, 0, 0.5], np.array(faces), np.array(uvs), tex, ("crown",) * quads,
                         False, None, 0.0, 0.0, np.zeros(2), np.zeros((quads, 4)), "procedural")


def _odd_wood(seed: int):
    """A tube with unreferenced vertices and degenerate (zero-area and sub-mm^2) triangles."""
    rng = np.random.default_rng(seed)
    tube = trimesh.creation.cylinder(radius=0.2, height=6.0, sections=7)
    n = len(tube.vertices)
    v = np.vstack([tube.vertices + [0, 0, 3.0], rng.normal(0, 2, (5, 3)),
                   [[0.0, 0.0, 7.0], [1e-4, 0.0, 7.0], [0.0, 1e-4, 7.0], [3e-3, 0.0, 7.0], [0.0, 3e-3, 7.0]]])
    # a zero-area, a 5e-9 m^2 and a 4.5e-6 m^2 triangle (the layer keeps only the last)
    f = np.vstack([tube.faces, [[n + 5, n + 6, n + 5], [n + 5, n + 6, n + 7], [n + 5, n + 8, n + 9]]])
    return trimesh.Trimesh(v, f, process=False)


def _slivers():
    """A mesh of triangles under 1 mm^2 only."""
    return trimesh.Trimesh([[0.0, 0.0, 0.0], [1e-4, 0.0, 0.0], [0.0, 1e-4, 0.0], [0.0, 0.0, 1e-4]],
                           [[0, 1, 2], [0, 1, 3]], process=False)


def _attributes(k: int) -> dict:
    """Attributes of every kind the property table and the layer columns distinguish."""
    return {"height": 10.0 + k, "flag": k % 2 == 0, "count": k, "big": 2 ** 40 + k if k % 3 else k,
            "maybe": None if k % 4 == 1 else 0.5 * k, "nan": float("nan") if k % 2 else 1.0,
            "missing_int": None if k == 2 else k, "text": f"baum-{k} \u00e9", "mixed": k if k % 2 else "x",
            "np_f": np.float64(0.1 * k), "np_i": np.int64(-k), "np_s": np.str_(f"s{k}"), "np_b": np.bool_(k % 3 == 0),
            "maybe_flag": True if k % 2 else None, "a b": k, "a_b": -k, "1st": "one",
            "int32_edge": 2 ** 31 - 1 - k, "int32_low": 1 + k - 2 ** 31, "int32_over": 2 ** 31 if k == 3 else -k,
            **({"only_some": k} if k % 3 == 0 else {})}


def forest(billboards: bool = True, big: bool = False):
    """Synthetic TreeModels reaching every branch of the writers (see the module docstring)."""
    with_lods = _bench.synthetic_models(4, seed=3, origin=tuple(ORIGIN), nodes=30, unique=2)
    no_lods = _bench.synthetic_models(3, seed=5, origin=tuple(ORIGIN + [3.0, 40.0, 0.0]), nodes=25, unique=3,
                                      lods=False)
    leafy = no_lods[0].leaves
    models = [TreeModel(10 + k, m.base, m.wood, m.leaves, {**m.attributes, **_attributes(k)}, m.lods)
              for k, m in enumerate(with_lods + no_lods)]
    base = ORIGIN + [-30.0, 20.0, 1.0]
    models += [TreeModel(30, base, no_lods[1].wood, None, _attributes(30)),                          # wood only
               TreeModel(31, base + [4.0, 1.0, 0.0], None, leafy, _attributes(31)),                   # leaves only
               TreeModel(32, base + [8.0, 0.0, 0.2], _odd_wood(1), leafy, _attributes(32), {0: _slivers()}),
               TreeModel(34, base + [12.0, 3.0, 0.1], _odd_wood(2), None, _attributes(34), {1: _odd_wood(3)})]
    if big:
        sphere = trimesh.creation.icosphere(subdivisions=7, radius=3.0)                       # 163842 vertices
        models.append(TreeModel(33, base + [0.0, 9.0, 0.0], sphere, None, _attributes(33)))
    if billboards:
        models += [TreeModel(40, base + [20.0, -5.0, 0.0], None, None, _attributes(40), billboard=_billboard(1)),
                   TreeModel(41, base + [24.0, -9.0, 0.0], no_lods[2].wood, no_lods[2].leaves, _attributes(41),
                             {0: with_lods[0].lods[0]}, billboard=_billboard(2, quads=4))]
    return models


@pytest.fixture(scope="module")
def models():
    return forest()


def _same_tree(a: Path, b: Path):
    fa = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    fb = sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    assert fa == fb
    for p in fa:
        assert (a / p).read_bytes() == (b / p).read_bytes(), p


# =========================================================================== GLB

GLB_OPTIONS = [dict(), dict(lod=0), dict(lod="coarsest", leaves=False), dict(metadata=False),
               dict(content="billboard"), dict(lod=5, texture_size=64, extras={"tile": "t_1", "n": 2})]


@pytest.mark.parametrize("frame", [UTM, ExportFrame(None)], ids=["utm", "local"])
@pytest.mark.parametrize("options", GLB_OPTIONS, ids=lambda o: ",".join(o) or "default")
def test_glb_bytes_equal_the_reference(models, frame, options):
    georef = Georef(frame, ORIGIN + [2.0, -3.0, 0.0])
    expected = glb_bytes(models, georef, **options)
    assert gltf.glb_bytes(models, georef, **options) == expected
    cache = {}   # a shared cache: the same bytes on the first and on a cached call
    assert gltf.glb_bytes(models, georef, cache=cache, **options) == expected
    assert gltf.glb_bytes(models, georef, cache=cache, **options) == expected
    assert gltf.glb_bytes(models[::-1], georef, cache=cache, **options) == glb_bytes(models[::-1], georef, **options)


def test_a_mesh_of_more_than_65535_vertices_equals_the_reference(models):
    big = forest(billboards=False, big=True)[-1:] + models[:2]
    assert len(big[0].wood.vertices) >= 65535
    georef = Georef(UTM, ORIGIN)
    assert gltf.glb_bytes(big, georef) == glb_bytes(big, georef)
    expected, got = models_table(big, UTM), gpkg3d.models_table(big, UTM)
    assert list(got.geometries) == list(expected.geometries) and got.extent == expected.extent


def test_glb_bytes_in_batches_equal_the_reference(models, monkeypatch):
    georef = Georef(UTM, ORIGIN)
    monkeypatch.setattr(gltf, "_BATCH_VERTICES", 2000)
    assert gltf.glb_bytes(models, georef) == glb_bytes(models, georef)


def test_write_glb_equals_the_reference(models, tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    write_glb(models, tmp_path / "a" / "tile.glb", UTM)
    gltf.write_glb(models, tmp_path / "b" / "tile.glb", UTM)
    write_glb(models[:6], tmp_path / "a", UTM, per_tree=True, lod="coarsest")
    gltf.write_glb(models[:6], tmp_path / "b", UTM, per_tree=True, lod="coarsest")
    _same_tree(tmp_path / "a", tmp_path / "b")


def test_glb_errors_equal_the_reference(models):
    georef = Georef(UTM, ORIGIN)
    bad = TreeModel(99, ORIGIN, None, None)
    for fn in (glb_bytes, gltf.glb_bytes):
        with pytest.raises(InputError, match="tree 99 has an empty mesh"):
            fn(models[:2] + [bad], georef)
        with pytest.raises(InputError, match="content must be one of"):
            fn(models[:2], georef, content="photo")
    broken = TreeModel(98, ORIGIN, models[0].wood, models[0].leaves, lods={0: trimesh.Trimesh(
        [[0, 0, 0], [1, 0, 0], [0, np.inf, 0]], [[0, 1, 2]], process=False)})
    messages = []
    for fn in (glb_bytes, gltf.glb_bytes):
        with pytest.raises(InputError) as err:
            fn([broken], georef, lod=0)
        messages.append(str(err.value))
    assert messages[0] == messages[1] and "lod 0" in messages[0]


# =========================================================================== 3D Tiles

@pytest.mark.parametrize("billboards", [True, False])
def test_write_tileset_equals_the_reference(tmp_path, billboards):
    models = forest(billboards=billboards, big=False)
    write_tileset(models, tmp_path / "a", UTM, tile_size_m=20.0)
    tiles3d.write_tileset(models, tmp_path / "b", UTM, tile_size_m=20.0)
    _same_tree(tmp_path / "a", tmp_path / "b")
    # the pipeline's order: the tile GLB, then its tileset, sharing one cache
    cache = {}
    write_glb(models, tmp_path / "a.glb", UTM)
    gltf.write_glb(models, tmp_path / "b.glb", UTM, cache=cache)
    tiles3d.write_tileset(models, tmp_path / "c", UTM, tile_size_m=20.0, cache=cache)
    assert (tmp_path / "a.glb").read_bytes() == (tmp_path / "b.glb").read_bytes()
    _same_tree(tmp_path / "a", tmp_path / "c")


def test_coarse_error_equals_the_reference(models):
    errors = [coarse_error(m) for m in models]
    assert [tiles3d.coarse_error(m) for m in models] == errors
    assert tiles3d.max_coarse_error(models) == max(errors)
    assert tiles3d.max_coarse_error(models[::-1], {}) == max(errors)
    assert min(errors) == 0.0 and 0.0 < max(errors) < math.inf   # the billboard-only tree, and real distances


def _sets(seed: int, n_sets: int = 6):
    """Random point sets of very different sizes and spreads (some without queries)."""
    rng = np.random.default_rng(seed)
    qs, ts = [], []
    for s in range(n_sets):
        nq, nt = int(rng.integers(0, 400)) * (s % 4 != 1), int(rng.integers(1, 300))
        scale = 10 ** rng.uniform(-2, 2)
        qs.append(rng.normal(0, scale, (nq, 3)) + rng.normal(0, 50, 3))
        ts.append(rng.normal(0, scale, (nt, 3)) + rng.normal(0, 50, 3))
    return qs, ts


def _kernel_args(qs, ts):
    qoff = np.r_[0, np.cumsum([len(q) for q in qs])].astype(np.int64)
    toff = np.r_[0, np.cumsum([len(t) for t in ts])].astype(np.int64)
    return np.concatenate(qs), qoff, np.concatenate(ts), toff


@pytest.mark.parametrize("seed", range(6))
def test_max_nearest_kernel_equals_ckdtree(seed):
    qs, ts = _sets(seed)
    expected = max([float(cKDTree(t).query(q)[0].max()) for q, t in zip(qs, ts) if len(q)] + [0.0])
    args = _kernel_args(qs, ts)
    for stride in (1, 7, 64, 10 ** 9):
        assert float(np.sqrt(tiles3d._max_nearest_sq(*args, stride))) == expected
    # the old per-model search (cKDTree + quad bound) gives it too
    assert max([_max_nearest(cKDTree(t), q) for q, t in zip(qs, ts)]) == expected
    # a set with queries and no target: cKDTree's inf
    qs.append(np.zeros((2, 3)))
    ts.append(np.zeros((0, 3)))
    assert tiles3d._max_nearest_sq(*_kernel_args(qs, ts), 64) == np.inf
    assert float(cKDTree(ts[-1]).query(qs[-1])[0].max()) == np.inf


# =========================================================================== models_3d layer

@pytest.mark.parametrize("frame,leaves,coarsest", [(UTM, False, True), (UTM, True, True), (UTM, True, False),
                                                    (ExportFrame("EPSG:2994"), True, True),
                                                    (ExportFrame(None), False, True)],
                         ids=["utm", "utm-leaves", "utm-leaves-full", "feet-leaves", "local"])
def test_models_table_equals_the_reference(models, frame, leaves, coarsest):
    expected = models_table(models, frame, leaves=leaves, coarsest=coarsest)
    for got in (gpkg3d.models_table(models, frame, leaves=leaves, coarsest=coarsest),
                gpkg3d.models_table(models, frame, leaves=leaves, coarsest=coarsest, cache={})):
        assert (got.name, got.geometry_type, got.has_z, got.wkb, got.crs) == \
               (expected.name, expected.geometry_type, expected.has_z, expected.wkb, expected.crs)
        assert list(got.geometries) == list(expected.geometries)
        assert list(got.columns) == list(expected.columns)
        for key, values in expected.columns.items():
            assert got.columns[key].dtype == values.dtype, key
            assert np.array_equal(got.columns[key], values, equal_nan=values.dtype.kind == "f"), key
        assert got.extent == expected.extent
        assert [type(x) for x in got.extent] == [type(x) for x in expected.extent]
    slivers = [m.tree_id for m in models].index(32)                            # its coarse wood: slivers only
    assert (expected.geometries[slivers] is None) == (coarsest and not leaves)


def test_attribute_columns_and_json_scalars_equal_the_reference(models):
    values = [None, True, False, 0, -3, 2 ** 70, 1.5, float("nan"), float("inf"), -float("inf"), "x", np.str_("y"),
              np.float64(2.5), np.float64("nan"), np.float32(0.1), np.float16(0.3), np.int64(-7), np.int8(3),
              np.uint64(2 ** 63), np.bool_(True), np.datetime64("2020-01-02"), np.longdouble(0.1), 1j, (1, 2)]
    for v in values:
        got, want = model_mod.json_scalar(v), json_scalar(v)
        assert type(got) is type(want) and (got == want or (got is None and want is None)), v
    rows = [m.json_attributes() for m in models]
    expected, got = attribute_columns(rows), gpkg3d.attribute_columns(rows)
    assert list(got) == list(expected)
    for key in expected:
        assert got[key].dtype == expected[key].dtype and np.array_equal(
            got[key], expected[key], equal_nan=expected[key].dtype.kind == "f"), key


# =========================================================================== kernels and helpers

#: Nearly opposite face normals at vertex 0, met at corners 2, 0 and 1: the sum's order shows in float32.
_CANCELLING = (np.array([[0, 0, 0], [1000, 0, 0], [0, 1000, 0], [0.001, 1000, 0], [1000, 0.002, 0.003],
                         [0.01, 0.003, 0], [0.002, 0.011, 0.004]], dtype=np.float32),
               np.array([[1, 2, 0], [0, 3, 4], [5, 0, 6]]))


def _random_meshes(seed: int):
    """float32 meshes with degenerate faces (repeated and collinear corners), unreferenced vertices,
    tiny triangles (normals under the 1e-12 threshold) and cancelling face normals."""
    rng = np.random.default_rng(seed)
    out = [_CANCELLING, (_CANCELLING[0] * np.float32(1e-7), _CANCELLING[1])]
    for k in range(5):
        nv = int(rng.integers(0, 60)) if k else 0
        pos = (rng.normal(0, 10 ** rng.uniform(-3, 3), (nv, 3))).astype(np.float32)
        if nv > 2:
            pos[1] = pos[0]
            pos[2] = 2 * pos[0] - pos[3 % nv]
        nf = int(rng.integers(0, 80)) if nv else 0
        faces = rng.integers(0, max(nv - 3, 1), (nf, 3)) if nv else np.zeros((0, 3), np.int64)
        if nf and nv > 2:
            faces[0] = [0, 1, 2]
        out.append((pos, faces.astype(np.int64)))
    return out


@pytest.mark.parametrize("seed", range(4))
def test_normals_kernel_equals_numpy(seed):
    meshes = _random_meshes(seed)
    normals, lo, hi = gltf._normals_and_bounds([p for p, _ in meshes], [f for _, f in meshes])
    ref_n, ref_lo, ref_hi = _normals_and_bounds([p for p, _ in meshes], [f for _, f in meshes])
    for a, b, (p, f) in zip(normals, ref_n, meshes):
        assert a.dtype == b.dtype == np.float32 and np.array_equal(a.view(np.uint32), b.view(np.uint32))
        assert np.array_equal(a.view(np.uint32), _unit_normals(p, f).view(np.uint32))
    assert np.array_equal(lo, ref_lo) and np.array_equal(hi, ref_hi)


def test_kernels_as_plain_python_equal_the_compiled_ones(monkeypatch):
    """What ``SYLVA_NO_JIT=1`` runs: the same functions, uncompiled."""
    meshes = _random_meshes(7)
    nv = [len(p) for p, _ in meshes]
    args = (np.concatenate([p for p, _ in meshes]), np.concatenate([f for _, f in meshes]),
            np.r_[0, np.cumsum(nv)].astype(np.int64), np.r_[0, np.cumsum([len(f) for _, f in meshes])].astype(np.int64))
    plain, compiled = gltf._normals_kernel.py_func(*args), gltf._normals_kernel(*args)
    assert np.array_equal(plain.view(np.uint32), compiled.view(np.uint32))
    args = _kernel_args(*_sets(3, 3))
    assert tiles3d._max_nearest_sq.py_func(*args, 5) == tiles3d._max_nearest_sq(*args, 5)
    small = forest(billboards=False, big=False)[-2:]
    table = gpkg3d.models_table(small, UTM, leaves=True)
    monkeypatch.setattr(gpkg3d, "_triangle_rings", gpkg3d._triangle_rings.py_func)
    plain = gpkg3d.models_table(small, UTM, leaves=True)
    assert list(plain.geometries) == list(table.geometries) and plain.extent == table.extent


def test_memoised_pyproj_objects_give_the_same_frames(models, monkeypatch):
    """Georef's thread-local memo of CRSs and transformers changes no number (fresh objects as before)."""
    def outputs(frame):
        g = Georef(frame, ORIGIN)
        frames = g.tree_frames([m.base for m in models])
        enu = g.source_to_enu(np.array([m.base for m in models]))
        return g.describe(), frames[0], frames[1], enu, g.enu_to_source(enu)

    frames = [UTM, ExportFrame("EPSG:2994"), ExportFrame("EPSG:32632+5773")]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")   # no geoid grid installed
        memoised = [outputs(f) for f in frames] + [outputs(frames[0])]
        monkeypatch.setattr(georef_mod, "_memo", lambda key, make: make())
        fresh = [outputs(f) for f in frames] + [outputs(frames[0])]
    for a, b in zip(memoised, fresh):
        assert a[0] == b[0]
        assert all(np.array_equal(x, y) for x, y in zip(a[1:], b[1:]))
