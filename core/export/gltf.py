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
from typing import List, NamedTuple, Optional, Sequence

import numpy as np

from ..errors import InputError
from ..jit import njit
from ..progress import check, report
from .georef import Georef, Z_UP_TO_Y_UP, default_origin, write_sidecars
from .model import (ExportFrame, TreeModel, atomic_write_bytes, cached, cached_attributes, check_models,
                    mesh_arrays)

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
    from ..textures import png_bytes, leaf_texture

    return png_bytes(np.ascontiguousarray(leaf_texture(shape, size), dtype=np.uint8))


@njit
def _normals_kernel(pos, faces, voff, foff):
    """Unit area-weighted vertex normals of the meshes packed in ``pos`` (float32 (V, 3)) and ``faces``.

    Mesh ``k`` owns the vertices ``voff[k]:voff[k+1]`` and the faces ``foff[k]:foff[k+1]`` (indices
    local to the mesh).  The numbers of the numpy formulation: float64 face normals as ``np.cross``,
    summed per vertex over corner 0 of every face of the mesh, then corner 1, then corner 2 (the
    order of ``np.bincount`` over ``faces.T.ravel()``), divided by their length as
    ``np.linalg.norm`` computes it; up for isolated/degenerate vertices.  Sylva, not in the paper.
    """
    out = np.empty((len(pos), 3), dtype=np.float32)
    for k in range(len(voff) - 1):
        v0, f0 = voff[k], foff[k]
        fn = np.empty((foff[k + 1] - f0, 3))
        for j in range(len(fn)):
            a, b, d = faces[f0 + j, 0] + v0, faces[f0 + j, 1] + v0, faces[f0 + j, 2] + v0
            ux = np.float64(pos[b, 0]) - np.float64(pos[a, 0])
            uy = np.float64(pos[b, 1]) - np.float64(pos[a, 1])
            uz = np.float64(pos[b, 2]) - np.float64(pos[a, 2])
            wx = np.float64(pos[d, 0]) - np.float64(pos[a, 0])
            wy = np.float64(pos[d, 1]) - np.float64(pos[a, 1])
            wz = np.float64(pos[d, 2]) - np.float64(pos[a, 2])
            fn[j, 0] = uy * wz - uz * wy
            fn[j, 1] = uz * wx - ux * wz
            fn[j, 2] = ux * wy - uy * wx
        n = np.zeros((voff[k + 1] - v0, 3))
        for c in range(3):
            for j in range(len(fn)):
                t = faces[f0 + j, c]
                n[t, 0] += fn[j, 0]
                n[t, 1] += fn[j, 1]
                n[t, 2] += fn[j, 2]
        for t in range(len(n)):
            x, y, z = n[t, 0], n[t, 1], n[t, 2]
            length = np.sqrt((x * x + y * y) + z * z)
            if length < 1e-12:
                x, y, z, length = 0.0, 0.0, 1.0, 1.0
            out[v0 + t, 0] = x / length
            out[v0 + t, 1] = y / length
            out[v0 + t, 2] = z / length
    return out


def _compact(faces: np.ndarray, n_vertices: int):
    """(used, faces') with ``used`` the sorted referenced vertex indices and ``faces'`` indexing them:
    ``np.unique(faces, return_inverse=True)`` without the sort (a mask and a cumulative sum);
    ``used`` is None when every vertex is referenced."""
    mask = np.zeros(n_vertices, dtype=bool)
    mask[faces.ravel()] = True
    if mask.all():
        return None, faces.reshape(-1, 3)
    new = np.cumsum(mask) - 1
    return np.flatnonzero(mask), new[faces].reshape(-1, 3)


#: Vertex normals are computed for batches of meshes of about this many vertices.
_BATCH_VERTICES = 1_000_000


def _normals_and_bounds(positions: List[np.ndarray], faces: List[np.ndarray]):
    """Unit vertex normals (:func:`_normals_kernel`) and per-axis (min, max) of many float32 meshes.

    The same numbers as one mesh at a time: the meshes are independent (batches of about
    ``_BATCH_VERTICES`` vertices bound the temporaries).
    """
    if not positions:
        return [], [], []
    nv = np.array([len(p) for p in positions], dtype=np.int64)
    cuts = np.r_[0, np.flatnonzero(np.diff(np.cumsum(nv) // _BATCH_VERTICES)) + 1, len(positions)].tolist()
    if len(cuts) == 2:
        return _normals_and_bounds_batch(positions, faces, nv)
    parts = [_normals_and_bounds_batch(positions[a:b], faces[a:b], nv[a:b]) for a, b in zip(cuts[:-1], cuts[1:])]
    return ([n for p in parts for n in p[0]], np.concatenate([p[1] for p in parts]),
            np.concatenate([p[2] for p in parts]))


def _normals_and_bounds_batch(positions: List[np.ndarray], faces: List[np.ndarray], nv: np.ndarray):
    """One batch of :func:`_normals_and_bounds` (``nv`` the vertex count of every mesh)."""
    voff = np.r_[0, np.cumsum(nv)]
    foff = np.r_[0, np.cumsum([len(f) for f in faces])].astype(np.int64)
    pos = np.concatenate(positions)
    normals = _normals_kernel(pos, np.concatenate(faces).astype(np.int64, copy=False), voff, foff)
    starts = voff[:-1]
    ok = nv > 0
    lo = np.zeros((len(nv), 3), dtype=pos.dtype)
    hi = np.zeros((len(nv), 3), dtype=pos.dtype)
    if ok.any():
        lo[ok] = np.minimum.reduceat(pos, starts[ok], axis=0)
        hi[ok] = np.maximum.reduceat(pos, starts[ok], axis=0)
    bounds = voff.tolist()
    return [normals[a:b] for a, b in zip(bounds[:-1], bounds[1:])], lo, hi


#: JSON text of an object, exactly as ``json.dumps`` with the GLB's settings writes it.
_json = json.JSONEncoder(separators=(",", ":"), allow_nan=False, ensure_ascii=False).encode


def _json_floats(values: np.ndarray) -> List[str]:
    """The JSON texts of an array's values as floats (``repr``, as :data:`_json` writes them), flattened."""
    values = np.asarray(values, dtype=np.float64)
    if not np.isfinite(values).all():
        raise ValueError("Out of range float values are not JSON compliant")
    return [repr(x) for x in values.ravel().tolist()]


class _Primitive(NamedTuple):
    """One primitive's arrays as a GLB stores them (what ``cache`` keeps, see :func:`glb_bytes`)."""

    positions: np.ndarray       # (n, 3) float32, ENU axes, relative to the tree base
    normals: np.ndarray         # (n, 3) float32 unit vectors
    indices: np.ndarray         # (3 f,) uint16 (n < 65535) or uint32
    texcoords: Optional[np.ndarray]   # (n, 2) float32, v flipped; None for bark
    lo: np.ndarray              # (3,) float32 per-axis min of positions
    hi: np.ndarray              # (3,) float32 per-axis max
    bounds_json: str            # ',"min":[...],"max":[...]' of the POSITION accessor


class _Builder:
    """The binary chunk (a list of buffers, joined once) and the JSON of its buffer views and accessors."""

    def __init__(self):
        self.parts: list = []
        self.size = 0
        self.views: List[str] = []
        self.accessors: List[str] = []

    def view(self, data, target: Optional[int] = None) -> int:
        """A buffer view of ``data`` (bytes or a C-contiguous array), 8-byte aligned.

        glTF requires ``byteLength >= 1``: empty data (a string column that is empty for
        every tree, such as ``flags``) becomes one zero byte, which its string offsets
        (all 0) never reach (Sylva, not in the papers).
        """
        pad = (-self.size) % 8
        if pad:
            self.parts.append(bytes(pad))
            self.size += pad
        n = data.nbytes if isinstance(data, np.ndarray) else len(data)
        if n == 0:
            data, n = b"\0", 1
        self.views.append('{"buffer":0,"byteOffset":%d,"byteLength":%d%s}'
                          % (self.size, n, "" if target is None else ',"target":%d' % target))
        self.parts.append(data)
        self.size += n
        return len(self.views) - 1

    def accessor(self, array: np.ndarray, ctype: int, kind: str, target: Optional[int], extra: str = "") -> int:
        """An accessor + view of the C-contiguous ``array`` (count = its length); ``extra`` more JSON members."""
        view = self.view(array, target)
        self.accessors.append('{"bufferView":%d,"componentType":%d,"count":%d,"type":"%s"%s}'
                              % (view, ctype, len(array), kind, extra))
        return len(self.accessors) - 1


def _property_name(key: str) -> str:
    name = re.sub(r"[^A-Za-z0-9_]", "_", str(key))
    return name if re.match(r"[A-Za-z_]", name) else "_" + name


#: noData value of numeric properties whose value is missing (None/NaN) for some trees.
NO_DATA = -9999


def _metadata(builder: _Builder, rows: List[dict]):
    """EXT_structural_metadata schema + one property table built from the trees' attributes."""
    keys = list(dict.fromkeys(k for r in rows for k in r))     # in first-seen order
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
        types = set(map(type, present))                        # (bool has no subclasses)
        if types == {bool} and not missing:
            bits = np.packbits(np.array(values, dtype=bool), bitorder="little")
            props[name] = {"type": "BOOLEAN"}
            table[name] = {"values": builder.view(bits.tobytes())}
        elif types and all(issubclass(t, (int, float)) and t is not bool for t in types):
            ints = all(issubclass(t, int) for t in types)
            if ints and -2**31 < min(present) and max(present) < 2**31:
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


def uses_billboard(model: TreeModel, content: str = "model", cache: Optional[dict] = None) -> bool:
    """Whether ``model`` is drawn as its billboard for ``content`` (see the module docstring).

    ``cache``: see :func:`~.model.cached` (the arrays are then checked once)."""
    cache = {} if cache is None else cache
    if model.billboard is None or len(mesh_arrays(model, "billboard", cache)[1]) == 0:
        return False
    return content == "billboard" or not (len(mesh_arrays(model, "wood", cache)[1]) > 0
                                          or len(mesh_arrays(model, "leaves", cache)[1]) > 0)


def glb_bytes(models: Sequence[TreeModel], georef: Georef, lod: Optional[int] = None,
              leaves: bool = True, texture_size: int = 256, metadata: bool = True,
              extras: Optional[dict] = None, content: str = "model", cache: Optional[dict] = None) -> bytes:
    """The GLB of ``models`` in the ENU frame of ``georef`` (see the module docstring).

    ``lod`` None writes the full wood; an int writes ``model.lods[lod]`` when the
    model has it (else the full wood); ``"coarsest"`` the lowest level it has.  ``leaves`` False leaves the leaf cards out.
    ``content`` "model" (default) or "billboard": the trees' billboards where they have one.
    ``cache``: a dict shared by several calls on the same, unchanged models (a tile's GLB and its
    tileset, :func:`write_glb` / :func:`~.tiles3d.write_tileset`): each tree's primitives (float32
    positions, normals, bounds, indices, texture coordinates), attributes and billboard PNG are then
    computed once per frame; the bytes are the same.
    The dict keeps the models and these arrays alive: drop it after the exports.
    """
    if content not in CONTENTS:
        raise InputError(f"glTF export: content must be one of {', '.join(CONTENTS)}, got {content!r}")
    cache = {} if cache is None else cache
    models = check_models(models, "glTF export", cache)
    bases_enu, jac = georef.tree_frames([m.base for m in models])
    prims = _primitives(models, jac, lod, leaves, content, cache)
    rows = [_attributes(m, cache) for m in models]
    b = _Builder()
    meshes, materials, textures, images = _meshes(b, models, prims, metadata, texture_size, cache)
    geo = georef.describe()
    if extras:
        geo.update(extras)
    geo = _json(geo)
    names = [_json(m.name) for m in models]
    nodes = ['{"name":"sylva_root","matrix":[%s],"children":[%s],"extras":{"georeference":%s}}'
             % (",".join(_json_floats(Z_UP_TO_Y_UP.T)), ",".join(map(str, range(1, len(models) + 1))), geo)]
    xyz = _json_floats(bases_enu)
    nodes += ['{"name":%s,"mesh":%d,"translation":[%s,%s,%s],"extras":%s}'
              % (names[i], i, *xyz[3 * i:3 * i + 3], rows[i][1]) for i in range(len(models))]
    # the JSON chunk, as json.dumps of the document (same key order) writes it
    doc = ['"asset":{"version":"2.0","generator":%s,"extras":{"georeference":%s}}' % (_json(SYLVA_GENERATOR), geo),
           '"scene":0', '"scenes":[{"name":"trees","nodes":[0]}]', '"nodes":[%s]' % ",".join(nodes),
           '"meshes":[%s]' % ",".join('{"name":%s,"primitives":[%s]}' % (names[i], ",".join(prims_i))
                                      for i, prims_i in enumerate(meshes)),
           '"materials":' + _json(materials)]
    if textures:
        doc += ['"textures":' + _json(textures), '"images":' + _json(images),
                '"samplers":[{"magFilter":9729,"minFilter":9987,"wrapS":33071,"wrapT":33071}]']
    if metadata:
        ext = _metadata(b, [r[0] for r in rows])
        doc += ['"extensionsUsed":["EXT_mesh_features","EXT_structural_metadata"]',
                '"extensions":{"EXT_structural_metadata":%s}' % _json(ext)]
    b.parts.append(bytes((-b.size) % 4))
    size = b.size + len(b.parts[-1])
    doc += ['"accessors":[%s]' % ",".join(b.accessors), '"bufferViews":[%s]' % ",".join(b.views),
            '"buffers":[{"byteLength":%d}]' % size]
    return _glb_container(("{" + ",".join(doc) + "}").encode("utf-8"), b.parts, size)


def _meshes(b: _Builder, models, prims, metadata: bool, texture_size: int, cache: dict):
    """(every model's primitives as JSON, materials, textures, images): the views and accessors of
    ``prims`` (:func:`_primitives`) written to ``b`` in file order."""
    materials = [{"name": "bark", "pbrMetallicRoughness": {
        "baseColorFactor": list(BARK_RGBA), "metallicFactor": 0.0, "roughnessFactor": 0.9}}]
    textures, images, leaf_material = [], [], {}
    meshes = [[] for _ in models]
    feature, features = "", None
    if metadata:  # every vertex's feature ID (its tree's row in the property table), one array for the file
        feature = (',"extensions":{"EXT_mesh_features":{"featureIds":[{"featureCount":%d,"attribute":0,'
                   '"propertyTable":0}]}}' % len(models))
        features = np.repeat(np.array([i for i, _, _ in prims], dtype=np.float32),
                             [len(p.positions) for _, _, p in prims])
    start = 0
    for i, kind, p in prims:
        m = models[i]
        n = len(p.positions)
        attrs = '"POSITION":%d' % b.accessor(p.positions, _FLOAT, "VEC3", _ARRAY_BUFFER, p.bounds_json)
        attrs += ',"NORMAL":%d' % b.accessor(p.normals, _FLOAT, "VEC3", _ARRAY_BUFFER)
        material = 0
        if p.texcoords is not None:
            attrs += ',"TEXCOORD_0":%d' % b.accessor(p.texcoords, _FLOAT, "VEC2", _ARRAY_BUFFER)
            if kind is _BILLBOARD:
                png = cached(cache, m, "billboard_png", lambda m: m.billboard.png())
                images.append({"name": f"billboard_{m.tree_id}", "mimeType": "image/png",
                               "bufferView": b.view(png)})
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
        indices = b.accessor(p.indices, _UINT if p.indices.dtype == np.uint32 else _USHORT, "SCALAR",
                             _ELEMENT_ARRAY_BUFFER)
        if metadata:
            attrs += ',"_FEATURE_ID_0":%d' % b.accessor(features[start:start + n], _FLOAT, "SCALAR", _ARRAY_BUFFER)
            start += n
        meshes[i].append('{"attributes":{%s},"indices":%d,"material":%d,"mode":4%s}'
                         % (attrs, indices, material, feature))
    return meshes, materials, textures, images


def _attributes(m: TreeModel, cache: dict):
    """(``m.json_attributes()``, their JSON text), computed once per ``cache``."""
    row = cached_attributes(m, cache)
    return row, cached(cache, m, "attributes_json", lambda m: _json(row))


def _parts(m: TreeModel, lod, leaves: bool, content: str, cache: dict):
    """(kind, cache tag, vertices, faces, uvs or None) of every primitive of ``m`` (see :func:`glb_bytes`)."""
    if uses_billboard(m, content, cache):
        bv, bf, buv = mesh_arrays(m, "billboard", cache)
        return [(_BILLBOARD, "billboard", bv, bf, buv)]
    parts = []
    wood_lod = _pick_lod(m, lod)
    wv, wf = mesh_arrays(m, "wood", cache, wood_lod)
    if len(wf):
        parts.append(("bark", ("bark", wood_lod), wv, wf, None))
    if leaves:
        lv, lf, luv = mesh_arrays(m, "leaves", cache)
        if len(lf):
            parts.append((m.leaves.texture, "leaves", lv, lf, luv))
    return parts


def _primitives(models, jac, lod, leaves: bool, content: str, cache: dict):
    """(model index, kind, :class:`_Primitive`) of every primitive in file order, from ``cache`` or
    encoded (normals and bounds of all new ones in one vectorised call) and put in it."""
    out, todo = [], []
    for i, m in enumerate(models):
        for kind, tag, v, f, uv in _parts(m, lod, leaves, content, cache):
            key = (id(m), tag, jac[i].tobytes())
            hit = cache.get(key)
            if hit is not None and hit[0] is m:       # the very model (ids are reused once it is gone)
                out.append((i, kind, hit[1]))
                continue
            # drop unreferenced vertices so min/max and counts describe what is drawn
            used, f = _compact(f, len(v))
            if used is not None:
                v = v[used]
                uv = None if uv is None else uv[used]
            pos = (np.ascontiguousarray(v) @ jac[i].T).astype(np.float32)
            tex = None
            if uv is not None:
                tex = np.empty((len(uv), 2), dtype=np.float32)
                tex[:, 0] = uv[:, 0]
                tex[:, 1] = 1.0 - uv[:, 1]
            out.append((i, kind, None))
            todo.append((len(out) - 1, key, m, pos, f, tex))
    normals, lo, hi = _normals_and_bounds([t[3] for t in todo], [t[4] for t in todo])
    text = _json_floats(np.hstack([lo, hi])) if todo else []
    for j, ((k, key, m, pos, f, tex), n) in enumerate(zip(todo, normals)):
        indices = f.astype(np.uint16 if len(pos) < 65535 else np.uint32).ravel()
        bounds = ',"min":[%s,%s,%s],"max":[%s,%s,%s]' % tuple(text[6 * j:6 * j + 6])
        cache[key] = (m, _Primitive(pos, n, indices, tex, lo[j], hi[j], bounds))
        out[k] = out[k][:2] + (cache[key][1],)
    return out


def _glb_container(js: bytes, binary_parts: list, binary_size: int) -> bytes:
    """The GLB file: header, JSON chunk (space-padded to 4 bytes) and binary chunk (already padded)."""
    js += b" " * ((-len(js)) % 4)
    total = 12 + 8 + len(js) + 8 + binary_size
    return b"".join([struct.pack("<4sII", b"glTF", 2, total), struct.pack("<I4s", len(js), b"JSON"), js,
                     struct.pack("<I4s", binary_size, b"BIN\0"), *binary_parts])


def _pack_glb(doc: dict, binary: bytes) -> bytes:
    return _glb_container(_json(doc).encode("utf-8"), [binary], len(binary))


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
    cache = {} if cache is None else cache
    models = check_models(models, f"glTF export to {path}", cache)
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
                                                            content=content, cache=cache)))
        if sidecars:
            out.extend(write_sidecars(target, georef))
        report(progress, (k + 1) / len(models), f"tree {m.tree_id}")
    return out
