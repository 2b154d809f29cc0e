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
  vertices, cKDTree) — for a billboard, to the nearest opaque texel centre of
  its quads (what a viewer sees of it); the tileset the diagonal of the root box (the error of
  drawing nothing).  ``refine`` is REPLACE: close up, children replace the parent.
* Per-tree attributes: EXT_mesh_features (feature ID per vertex) and
  EXT_structural_metadata (one property table per GLB), plus node extras.

A frame without a geodetic datum (local engineering CRS, or no CRS) cannot
be placed in ECEF: :class:`~sylva.core.errors.CRSError`.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import List, Sequence

import numpy as np

from ..errors import InputError
from ..progress import check, report
from .georef import Georef, default_origin, write_sidecars
from .gltf import SYLVA_GENERATOR, glb_bytes, uses_billboard
from .model import ExportFrame, TreeModel, atomic_write_bytes, check_models

__all__ = ["write_tileset", "tile_box", "coarse_error"]

_PAD_M = 0.01


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
    from scipy.spatial import cKDTree

    if uses_billboard(model, "billboard"):
        if not model.has_mesh():
            return 0.0  # the billboard is the full model too
        from ..reconstruct.billboard import opaque_points

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
