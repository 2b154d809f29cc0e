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


def _enu_vertices(model: TreeModel, base_enu, jac, coarse: bool) -> np.ndarray:
    """The ENU positions (float32 rounding applied as in the GLB) of what a tile draws of ``model``."""
    if uses_billboard(model, "billboard" if coarse else "model"):
        parts = [model.billboard_arrays()[:2]]
    elif coarse:
        lod = min(model.lods) if model.lods else None
        parts = [model.wood_arrays(lod)]
    else:
        parts = [model.wood_arrays(), model.leaf_arrays()[:2]]
    pts = []
    for v, f in parts:
        if len(f):
            v = v[np.unique(f)]
            pts.append((v @ jac.T).astype(np.float32).astype(np.float64) + base_enu)
    return np.concatenate(pts) if pts else np.zeros((0, 3))


def tile_box(points: np.ndarray, pad_m: float = _PAD_M) -> List[float]:
    """An axis-aligned 3D Tiles ``box`` (centre + three half-axes) holding ``points``, padded."""
    lo, hi = points.min(axis=0) - pad_m, points.max(axis=0) + pad_m
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

        fv = np.concatenate([model.wood_arrays()[0], model.leaf_arrays()[0]])
        d, _ = cKDTree(opaque_points(model.billboard)).query(fv)
        return float(d.max())
    lod = min(model.lods) if model.lods else None
    cv, cf = model.wood_arrays(lod)
    fv = np.concatenate([model.wood_arrays()[0], model.leaf_arrays()[0]])
    if len(fv) == 0:
        return 0.0
    if len(cf) == 0:
        return float(np.linalg.norm(fv - fv.mean(axis=0), axis=1).max() * 2.0)
    d, _ = cKDTree(cv[np.unique(cf)]).query(fv)
    return float(d.max())


def write_tileset(models: Sequence[TreeModel], folder, frame: ExportFrame, origin=None, tile_size_m: float = 50.0,
                  texture_size: int = 256, progress=None, cancelled=None) -> List[Path]:
    """Write a 3D Tiles 1.1 tileset of ``models`` into ``folder`` (created if missing); returns the files.

    ``origin`` source CRS coordinates of the ENU frame (default: centre of the
    bases at the lowest ground); ``tile_size_m`` edge of the square grid cells
    that group trees into child tiles.
    """
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
    all_pts = []
    for k, key in enumerate(keys):
        check(cancelled)
        idx = [i for i in range(len(models)) if tuple(cell[i]) == key]
        group = [models[i] for i in idx]
        pts = np.concatenate([_enu_vertices(models[i], bases_enu[i], jac[i], False) for i in idx])
        all_pts.append(pts)
        name = f"content/tile_{key[0]}_{key[1]}.glb"
        written.append(atomic_write_bytes(folder / name, glb_bytes(group, georef, None, True, texture_size)))
        children.append({"boundingVolume": {"box": tile_box(pts)}, "geometricError": 0.0,
                         "content": {"uri": name}})
        report(progress, 0.9 * (k + 1) / len(keys), f"tile {key[0]} {key[1]}: {len(group)} trees")
    coarse_pts = np.concatenate([_enu_vertices(m, bases_enu[i], jac[i], True) for i, m in enumerate(models)])
    root_pts = np.concatenate(all_pts + [coarse_pts])
    root_error = max(coarse_error(m) for m in models)
    root_content = "billboard" if any(m.billboard is not None for m in models) else "model"
    written.append(atomic_write_bytes(folder / "content/root.glb",
                                      glb_bytes(models, georef, lod="coarsest", leaves=False, texture_size=texture_size,
                                                content=root_content)))
    box = tile_box(root_pts)
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
