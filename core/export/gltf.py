"""glTF 2.0 binary (GLB) writer for tree models: numpy + json + struct, no other dependency.

Layout of a Sylva GLB (one file per tile, or one per tree):

* node 0 ``sylva_root``: ``matrix`` = :data:`~.georef.Z_UP_TO_Y_UP` (z-up ENU
  -> glTF's y-up, x = east, y = up, z = south); ``extras`` = the
  georeferencing block (:meth:`Georef.describe`: CRS WKT / EPSG, origin in
  the source CRS and as lon/lat/h, ENU->ECEF matrix).  The same block is in
  ``asset.extras.georeference``.
* one child node per tree, named ``tree_<id>``, ``translation`` = the tree
  base in ENU metres at the file origin, ``extras`` = the tree's attributes;
  its mesh holds the vertices relative to the base (ENU axes, float32).
* materials ``bark`` (PBR, brown, rough) and ``leaves_<shape>`` (the leaf
  texture as an embedded PNG, alphaMode MASK, doubleSided).
* billboards (``content="billboard"``, Zhou et al. 2013): each tree's quads
  are one primitive with its own material ``billboard_<id>`` (the tree's
  texture atlas as an embedded palette PNG with a transparent index,
  alphaMode MASK, doubleSided); trees without a billboard are written as
  the ``lod``/``leaves`` arguments say.  A tree with a billboard but no
  wood and no leaves is written as its billboard in either content.
* 3D Tiles 1.1 metadata: every primitive has a ``_FEATURE_ID_0`` attribute
  (the tree's row in the property table) and ``EXT_mesh_features``; the
  root ``EXT_structural_metadata`` holds a schema (class ``tree``) and one
  property table with every attribute.

This is the convention 3D Tiles expects: a client turns glTF y-up into z-up
(+90 degrees about x, 3D Tiles 1.1 "glTF transforms") which undoes the root
matrix, and the tileset's root ``transform`` (ENU -> ECEF at the origin)
places the content on the globe.  Texture v is flipped (glTF has v = 0 at
the top of the image; :mod:`sylva.core.leaves` uses the OpenGL convention).

Bytes are deterministic: no time stamps, fixed ordering, JSON with fixed
separators.  Buffer views are aligned to 8 bytes (EXT_structural_metadata
requires 8 for its tables; glTF needs 4).
"""
from __future__ import annotations

import functools
import json
import re
import struct
from pathlib import Path
from typing import List, Optional, Sequence

import numpy as np

from ..errors import InputError
from ..progress import check, report
from .georef import Georef, Z_UP_TO_Y_UP, default_origin, write_sidecars
from .model import ExportFrame, TreeModel, atomic_write_bytes, check_models

__all__ = ["write_glb", "glb_bytes", "read_glb", "node_world_positions", "uses_billboard", "BARK_RGBA",
           "SYLVA_GENERATOR"]

SYLVA_GENERATOR = "Sylva (QGIS plugin) glTF writer"
#: Bark base colour (linear RGBA): a mid brown.
BARK_RGBA = (0.30, 0.20, 0.13, 1.0)

_FLOAT, _UINT, _USHORT = 5126, 5125, 5123
_BILLBOARD = object()  # part kind of billboard quads (a sentinel: leaf kinds are shape names)
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963


@functools.lru_cache(maxsize=32)
def leaf_png(shape: str, size: int = 256) -> bytes:
    """The PNG bytes of a leaf texture (cached: drawing and compressing it takes ~0.3 s)."""
    from ..textures import _png_bytes, leaf_texture

    return _png_bytes(np.ascontiguousarray(leaf_texture(shape, size), dtype=np.uint8))


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


def _property_name(key: str) -> str:
    name = re.sub(r"[^A-Za-z0-9_]", "_", str(key))
    return name if re.match(r"[A-Za-z_]", name) else "_" + name


#: noData value of numeric properties whose value is missing (None/NaN) for some trees.
NO_DATA = -9999


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


def _pick_lod(model: TreeModel, lod):
    if lod == "coarsest":
        return min(model.lods) if model.lods else None
    return lod if (lod is not None and lod in model.lods) else None


CONTENTS = ("model", "billboard")


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


def read_glb(path_or_bytes):
    """(json dict, binary chunk bytes) of a GLB file (for checks and round trips)."""
    data = path_or_bytes if isinstance(path_or_bytes, (bytes, bytearray)) else Path(path_or_bytes).read_bytes()
    magic, version, total = struct.unpack_from("<4sII", data, 0)
    if magic != b"glTF" or version != 2 or total != len(data):
        raise InputError(f"{path_or_bytes if not isinstance(path_or_bytes, (bytes, bytearray)) else 'GLB'}: "
                         f"not a glTF 2.0 binary file")
    jlen, jtype = struct.unpack_from("<I4s", data, 12)
    doc = json.loads(data[20:20 + jlen].decode("utf-8"))
    off = 20 + jlen
    binary = b""
    if off < len(data):
        blen, _ = struct.unpack_from("<I4s", data, off)
        binary = bytes(data[off + 8:off + 8 + blen])
    return doc, binary


def accessor_array(doc: dict, binary: bytes, index: int) -> np.ndarray:
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    dtype = {_FLOAT: np.float32, _UINT: np.uint32, _USHORT: np.uint16}[acc["componentType"]]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[acc["type"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    a = np.frombuffer(binary, dtype=dtype, count=acc["count"] * width, offset=start)
    return a.reshape(acc["count"], width) if width > 1 else a


def _node_matrix(node: dict) -> np.ndarray:
    if "matrix" in node:
        return np.array(node["matrix"], dtype=np.float64).reshape(4, 4).T
    m = np.eye(4)
    if "translation" in node:
        m[:3, 3] = node["translation"]
    if "rotation" in node or "scale" in node:
        raise NotImplementedError("rotation/scale nodes are not written by Sylva")
    return m


def node_world_positions(doc: dict, binary: bytes, name: str, z_up: bool = True) -> np.ndarray:
    """All POSITION vertices of node ``name`` in scene coordinates (float64).

    With ``z_up`` the y-up -> z-up rotation of 3D Tiles is applied, giving the
    ENU frame of the file's origin.
    """
    nodes = doc["nodes"]
    parent = {c: i for i, n in enumerate(nodes) for c in n.get("children", [])}
    idx = next(i for i, n in enumerate(nodes) if n.get("name") == name)
    m = np.eye(4)
    j = idx
    while j is not None:
        m = _node_matrix(nodes[j]) @ m
        j = parent.get(j)
    if z_up:
        from .georef import Y_UP_TO_Z_UP

        m = Y_UP_TO_Z_UP @ m
    pts = [accessor_array(doc, binary, p["attributes"]["POSITION"]).astype(np.float64)
           for p in doc["meshes"][nodes[idx]["mesh"]]["primitives"]]
    p = np.concatenate(pts)
    return p @ m[:3, :3].T + m[:3, 3]


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
