"""OGC 3D Tiles 1.1 tilesets of tree models: a two-level tree of GLB content placed on the globe.

Layout written into ``folder``::

    tileset.json              asset.version "1.1"; extras.georeference (CRS, origin)
    content/root.glb          parent tile: every tree, coarse (its billboard when it has one, Zhou et al.
                              2013; else TreeModel.lods[min], no leaves)
    content/tile_<i>_<j>.glb  children: the full models (wood + leaf cards) of one grid cell

* The root tile's ``transform`` is the ENU -> ECEF matrix at the origin
  (:meth:`Georef.enu_to_ecef`, column-major); the GLB content is in that ENU
  frame, y-up as glTF requires (3D Tiles 1.1 "glTF transforms": the client
  rotates y-up to z-up, undoing the GLB's root matrix, see :mod:`.gltf`).
* Bounding volumes are ``box`` es in that ENU frame computed from the very
  vertex positions written (float32, as the GLB stores them), padded by 1 cm.
* Geometric error (metres): a leaf tile 0 (the full model); the parent tile
  the largest distance from any full-model vertex (wood and leaves) to the
  nearest coarse vertex of the same tree (a one-sided Hausdorff distance on
  vertices, exact, one early-break search over all trees) — for a billboard, to the nearest
  opaque texel centre of its quads (what a viewer sees of it); the tileset the diagonal of the
  root box (the error of drawing nothing).  ``refine`` is REPLACE: close up, children replace the parent.
* Per-tree attributes: EXT_mesh_features (feature ID per vertex) and
  EXT_structural_metadata (one property table per GLB), plus node extras.

A frame without a geodetic datum (local engineering CRS, or no CRS) cannot
be placed in ECEF: :class:`~sylva.core.errors.CRSError`.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import List, Optional, Sequence

import numpy as np

from ..errors import InputError
from ..jit import njit
from ..progress import check, report
from .georef import Georef, default_origin, write_sidecars
from .gltf import SYLVA_GENERATOR, glb_bytes, uses_billboard
from .model import ExportFrame, TreeModel, atomic_write_bytes, check_models, mesh_arrays

__all__ = ["write_tileset", "tile_box", "coarse_error", "max_coarse_error"]

_PAD_M = 0.01


def _enu_bounds(models, idx, bases_enu, jac, coarse: bool, cache: dict):
    """Per-axis (min, max) (3,) of the ENU positions (float32 rounding applied as in the GLB) of what a
    tile draws of the models ``idx``, or None when it draws nothing.

    From the float32 bounds :func:`~.gltf.glb_bytes` put in ``cache`` when it has them, else from the
    vertices; adding the base is monotonic, so ``min(p + b) == min(p) + b`` exactly.
    """
    lo, hi, owner = [], [], []
    for i in idx:
        model = models[i]
        for tag, v, f in _drawn_parts(model, coarse, cache):
            if len(f):
                hit = cache.get((id(model), tag, jac[i].tobytes()))
                if hit is not None and hit[0] is model:
                    lo.append(hit[1].lo)
                    hi.append(hit[1].hi)
                else:
                    pos = (v[_used(f, len(v))] @ jac[i].T).astype(np.float32)
                    lo.append(pos.min(axis=0))
                    hi.append(pos.max(axis=0))
                owner.append(i)
    if not lo:
        return None
    base = bases_enu[owner]
    return ((np.array(lo).astype(np.float64) + base).min(axis=0),
            (np.array(hi).astype(np.float64) + base).max(axis=0))


def _drawn_parts(model: TreeModel, coarse: bool, cache: dict):
    """(cache tag, vertices, faces) of what a tile draws of ``model`` (tags as :func:`~.gltf.glb_bytes`)."""
    if uses_billboard(model, "billboard" if coarse else "model", cache):
        return [("billboard",) + mesh_arrays(model, "billboard", cache)[:2]]
    if coarse:
        lod = min(model.lods) if model.lods else None
        return [(("bark", lod),) + mesh_arrays(model, "wood", cache, lod)]
    return [(("bark", None),) + mesh_arrays(model, "wood", cache),
            ("leaves",) + mesh_arrays(model, "leaves", cache)[:2]]


def tile_box(points: np.ndarray, pad_m: float = _PAD_M) -> List[float]:
    """An axis-aligned 3D Tiles ``box`` (centre + three half-axes) holding ``points``, padded."""
    return _box(points.min(axis=0), points.max(axis=0), pad_m)


def _box(lo: np.ndarray, hi: np.ndarray, pad_m: float = _PAD_M) -> List[float]:
    """:func:`tile_box` of points whose per-axis min and max are ``lo`` and ``hi``."""
    lo, hi = lo - pad_m, hi + pad_m
    c, h = (lo + hi) / 2.0, (hi - lo) / 2.0
    return [float(c[0]), float(c[1]), float(c[2]), float(h[0]), 0.0, 0.0, 0.0, float(h[1]), 0.0, 0.0, 0.0,
            float(h[2])]


def coarse_error(model: TreeModel) -> float:
    """Largest distance (m) from a full-model vertex to the nearest vertex of its coarse version."""
    return max_coarse_error([model])


def max_coarse_error(models: Sequence[TreeModel], cache: Optional[dict] = None) -> float:
    """``max(coarse_error(m) for m in models)``: the root tile's geometric error, in one kernel call.

    Only the largest distance matters, so a full-model vertex is dropped as soon as some coarse
    vertex lies within the largest distance found so far (:func:`_max_nearest_sq`).
    ``cache``: see :func:`~.model.cached`.
    """
    cache = {} if cache is None else cache
    best, queries, targets = 0.0, [], []
    for m in models:
        value, q, t = _coarse_sets(m, cache)
        best = max(best, value)
        if q is not None:
            queries.append(q)
            targets.append(t)
    if not queries:
        return best
    qoff = np.r_[0, np.cumsum([len(q) for q in queries])].astype(np.int64)
    toff = np.r_[0, np.cumsum([len(t) for t in targets])].astype(np.int64)
    far = _max_nearest_sq(np.concatenate(queries), qoff, np.concatenate(targets), toff, _SAMPLE_STRIDE)
    return max(best, float(np.sqrt(far)))


def _coarse_sets(model: TreeModel, cache: dict):
    """What :func:`coarse_error` measures of ``model``: (error, None, None) when no search is needed,
    else (0, full-model points, coarse points) for the largest distance from a full-model point to
    the nearest coarse point (the coarse level's drawn vertices, or the opaque texel centres of
    its billboard)."""
    if uses_billboard(model, "billboard", cache):
        wv, wf = mesh_arrays(model, "wood", cache)
        lv, lf, _ = mesh_arrays(model, "leaves", cache)
        if len(wf) == 0 and len(lf) == 0:
            return 0.0, None, None  # the billboard is the full model too
        from ..reconstruct.billboard import opaque_points

        return 0.0, np.concatenate([lv, wv]), np.asarray(opaque_points(model.billboard), dtype=np.float64)
    lod = min(model.lods) if model.lods else None
    cv, cf = mesh_arrays(model, "wood", cache, lod)
    wv, wf = mesh_arrays(model, "wood", cache)
    lv = mesh_arrays(model, "leaves", cache)[0]
    if len(wv) + len(lv) == 0:
        return 0.0, None, None
    if len(cf) == 0:
        fv = np.concatenate([wv, lv])
        return float(np.linalg.norm(fv - fv.mean(axis=0), axis=1).max() * 2.0), None, None
    drawn = np.zeros(len(cv), dtype=bool)
    drawn[cf.ravel()] = True
    every = bool(drawn.all())
    if lod is None:
        # the coarse level is the full wood: its drawn vertices are at distance 0, only the others are queried
        wv = wv[:0] if every else wv[~drawn]
        if len(wv) + len(lv) == 0:
            return 0.0, None, None
    return 0.0, lv if len(wv) == 0 else np.concatenate([lv, wv]), cv if every else cv[drawn]


#: Every this many-th full-model point is searched first (see :func:`_max_nearest_sq`).
_SAMPLE_STRIDE = 64


@njit
def _max_nearest_sq(queries, qoff, targets, toff, stride):
    """``max`` over sets ``s`` and points ``q`` of set ``s`` of the squared distance from ``q`` to the
    nearest target of set ``s`` (queries ``qoff[s]:qoff[s+1]``, targets ``toff[s]:toff[s+1]``).

    Exact, and the squared distance as ``cKDTree`` computes it (``(dx^2 + dy^2) + dz^2``), so its
    square root is the ``max`` of ``cKDTree.query`` distances to the last bit; inf when a set with
    queries has no target.  The early break of Taha & Hanbury (2015, "An efficient algorithm for
    calculating the exact Hausdorff distance"): a point is dropped as soon as a target lies within
    the largest distance found so far, trying the targets from the previous point's nearest one on
    (consecutive points are near each other).  Every ``stride``-th point of every set is searched
    first, so that the largest distance is nearly known before the other points are (any order
    gives the same result).  Sylva, not in the paper.
    """
    best = 0.0
    for phase in range(2):
        for s in range(len(qoff) - 1):
            t0, t1 = toff[s], toff[s + 1]
            nt = t1 - t0
            if nt == 0:
                if qoff[s + 1] > qoff[s]:
                    return np.inf
                continue
            start = t0
            for i in range(qoff[s], qoff[s + 1], stride if phase == 0 else 1):
                x, y, z = queries[i, 0], queries[i, 1], queries[i, 2]
                near = np.inf
                nearest = start
                for step in range(nt):
                    j = start + step
                    if j >= t1:
                        j -= nt
                    dx, dy, dz = x - targets[j, 0], y - targets[j, 1], z - targets[j, 2]
                    d = (dx * dx + dy * dy) + dz * dz
                    if d < near:
                        near = d
                        nearest = j
                        if near <= best:
                            break
                if near > best:
                    best = near
                start = nearest
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
    models = check_models(models, f"3D Tiles export to {folder}", cache)
    if not tile_size_m > 0:
        raise InputError(f"3D Tiles export: tile_size_m must be positive, got {tile_size_m}")
    georef = Georef(frame, default_origin(models) if origin is None else origin)
    georef.require_geodetic(f"3D Tiles export to {folder}")
    if not folder.parent.exists():
        raise InputError(f"3D Tiles export: the parent folder of {folder} does not exist")
    (folder / "content").mkdir(parents=True, exist_ok=True)
    bases_enu, jac = georef.tree_frames([m.base for m in models])
    cell = np.floor(bases_enu[:, :2] / tile_size_m).astype(np.int64)
    tiles = {}          # grid cell -> its trees, in model order
    for i, key in enumerate(map(tuple, cell.tolist())):
        tiles.setdefault(key, []).append(i)
    keys = sorted(tiles)
    written: List[Path] = []
    children = []
    bounds = []         # (min, max) of what each child tile draws, then of the coarse models
    for k, key in enumerate(keys):
        check(cancelled)
        idx = tiles[key]
        group = [models[i] for i in idx]
        name = f"content/tile_{key[0]}_{key[1]}.glb"
        written.append(atomic_write_bytes(folder / name, glb_bytes(group, georef, None, True, texture_size,
                                                                   cache=cache)))
        bounds.append(_enu_bounds(models, idx, bases_enu, jac, False, cache))
        children.append({"boundingVolume": {"box": _box(*bounds[-1])}, "geometricError": 0.0,
                         "content": {"uri": name}})
        report(progress, 0.9 * (k + 1) / len(keys), f"tile {key[0]} {key[1]}: {len(group)} trees")
    root_content = "billboard" if any(m.billboard is not None for m in models) else "model"
    written.append(atomic_write_bytes(folder / "content/root.glb",
                                      glb_bytes(models, georef, lod="coarsest", leaves=False, texture_size=texture_size,
                                                content=root_content, cache=cache)))
    coarse = _enu_bounds(models, range(len(models)), bases_enu, jac, True, cache)
    if coarse is not None:
        bounds.append(coarse)
    root_error = max_coarse_error(models, cache)
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


def write_root_tileset(folder, tilesets: Sequence[Path]) -> Optional[Path]:
    """``folder/tileset.json`` whose children are the per-tile tilesets (external tileset content).

    Each child's bounding volume is its tileset's root box carried into ECEF
    (an oriented box: centre ``M c``, half-axes ``R h``), so it is as tight as
    the tile's own; the root is the box, in the first tile's east-north-up
    axes, around every child box's corners.  Children refine by REPLACE: a
    client (QGIS's tiled scene layer merges an external tileset's root into
    the tile that points to it) then swaps a tile's coarse content for its
    full models instead of drawing both.
    """
    children, corners, axes, errors = [], [], None, []
    folder = Path(folder)
    signs = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], dtype=np.float64)
    for ts in tilesets:
        doc = json.loads(Path(ts).read_text("utf-8"))
        root = doc["root"]
        M = np.array(root.get("transform", np.eye(4).ravel().tolist()), dtype=np.float64).reshape(4, 4).T
        box = np.array(root["boundingVolume"]["box"], dtype=np.float64)
        centre = (M @ np.r_[box[:3], 1.0])[:3]
        half = (M[:3, :3] @ box[3:].reshape(3, 3).T).T           # rows: the three half-axes in ECEF
        if axes is None:
            axes = M[:3, :3] / np.linalg.norm(M[:3, :3], axis=0)  # columns: east, north, up at the first tile
        corners.append(centre + signs @ half)
        errors.append(float(doc.get("geometricError", root.get("geometricError", 0.0))))
        children.append({"boundingVolume": {"box": [*centre.tolist(), *half.ravel().tolist()]},
                         "geometricError": errors[-1], "refine": "REPLACE",
                         "content": {"uri": Path(os.path.relpath(ts, folder)).as_posix()}})
    if not children:
        return None
    local = np.concatenate(corners) @ axes                        # corners in the first tile's ENU axes
    lo, hi = local.min(axis=0), local.max(axis=0)
    centre = axes @ ((lo + hi) / 2.0)
    half = (axes * ((hi - lo) / 2.0)).T
    diagonal = 2.0 * float(np.linalg.norm((hi - lo) / 2.0))
    doc = {"asset": {"version": "1.1", "extras": {"generator": "Sylva catalog"}},
           "geometricError": diagonal,
           "root": {"boundingVolume": {"box": [*centre.tolist(), *half.ravel().tolist()]},
                    "geometricError": max(errors) * 2 + 1.0, "refine": "REPLACE", "children": children}}
    return atomic_write_bytes(folder / "tileset.json", (json.dumps(doc, indent=1) + "\n").encode("utf-8"))
