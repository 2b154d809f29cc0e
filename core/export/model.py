"""What the exporters take: :class:`TreeModel` (one reconstructed tree) and :class:`ExportFrame` (its CRS).

A tree model is in METRES in a local frame whose origin is the tree's base:
``x`` = grid east, ``y`` = grid north, ``z`` = up (the frame reconstruction
works in: the source CRS's grid axes scaled to metres, ARCHITECTURE.md
"Coordinates stay in the source CRS in files; computation happens in a local
metric frame").  ``base`` places that frame in the source CRS: x, y in the
CRS's horizontal unit and z (the ground elevation under the stem) in its
vertical unit.  So a model vertex ``v`` (metres) lies at
``base + v / (h, h, v_unit)`` in source CRS coordinates.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Dict, Optional

import numpy as np

from ..cloud import METRES, Units
from ..atomic import atomic_open, atomic_write_bytes  # noqa: F401 (re-exported to the writers)
from ..errors import CRSError, InputError

__all__ = ["TreeModel", "ExportFrame", "check_models", "json_scalar", "cached", "mesh_arrays",
           "cached_attributes"]


_PLAIN = frozenset([bool, int, str, type(None)])
#: ``value.item()`` of the common numpy scalars, done faster by their Python type.
_UNWRAP = {**{t: float for t in (np.float64, np.float32, np.float16)},
           **{t: int for t in (np.int64, np.int32, np.int16, np.int8, np.uint64, np.uint32, np.uint16, np.uint8)},
           np.bool_: bool, np.str_: str}


def json_scalar(value):
    """A JSON-serialisable scalar for an attribute value (numpy scalars unwrapped, NaN -> None)."""
    unwrap = _UNWRAP.get(type(value))
    if unwrap is not None:
        value = unwrap(value)
    elif isinstance(value, np.generic):
        value = value.item()
    kind = type(value)
    if kind is float:
        return value if math.isfinite(value) else None
    if kind in _PLAIN:
        return value
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return str(value)


@dataclass
class TreeModel:
    """One tree ready for export.

    ``tree_id`` stable tree id (as in the ``trees`` layer and the LAS ``treeID``);
    ``base`` (3,) the stem base in SOURCE CRS coordinates (ground z);
    ``wood`` a :class:`trimesh.Trimesh` in local metres (origin = base, x grid
    east, y grid north, z up); ``leaves`` a :class:`sylva.core.leaves.LeafMesh`
    in the same frame, or None; ``attributes`` JSON scalars (tree_id, height,
    crown_diameter, crown_base_height, dbh, dbh_source, species, method, ...);
    ``lods`` optional coarser wood meshes by level (0 = coarsest), same frame;
    ``billboard`` optional :class:`sylva.core.reconstruct.billboard.BillboardMesh`
    in the same frame (Zhou et al. 2013: textured quads, the far level of
    detail; a tree may have only a billboard, no wood and no leaves).
    """

    tree_id: int
    base: np.ndarray
    wood: Any
    leaves: Any = None
    attributes: Dict[str, Any] = field(default_factory=dict)
    lods: Dict[int, Any] = field(default_factory=dict)
    billboard: Any = None

    def __post_init__(self):
        self.tree_id = int(self.tree_id)
        self.base = np.asarray(self.base, dtype=np.float64).reshape(-1)
        if self.base.shape != (3,) or not np.all(np.isfinite(self.base)):
            raise InputError(f"tree {self.tree_id}: base must be three finite coordinates "
                             f"(x, y, ground z in the source CRS), got {self.base.tolist()}")

    @property
    def name(self) -> str:
        return f"tree_{self.tree_id}"

    def json_attributes(self) -> Dict[str, Any]:
        """``attributes`` as JSON scalars, with ``tree_id`` always present and first."""
        out = {"tree_id": self.tree_id}
        for k in sorted(self.attributes):
            if k != "tree_id":
                out[str(k)] = json_scalar(self.attributes[k])
        return out

    def wood_arrays(self, lod: Optional[int] = None):
        """(vertices (v, 3) float64, faces (f, 3) int64) of the wood, or of ``lods[lod]``."""
        mesh = self.wood if lod is None else self.lods[lod]
        return _mesh_arrays(mesh, f"tree {self.tree_id}" + ("" if lod is None else f" lod {lod}"))

    def leaf_arrays(self):
        """(vertices, faces, uvs) of the leaves (empty arrays when there are none)."""
        lv = self.leaves
        if lv is None or len(np.asarray(lv.faces)) == 0:
            return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 2))
        v = np.asarray(lv.vertices, dtype=np.float64).reshape(-1, 3)
        f = np.asarray(lv.faces, dtype=np.int64).reshape(-1, 3)
        uv = np.asarray(lv.uvs, dtype=np.float64).reshape(-1, 2)
        if len(uv) != len(v) or _bad_index(f, len(v)) or not np.isfinite(v).all():
            raise InputError(f"tree {self.tree_id}: leaf mesh is inconsistent "
                             f"({len(v)} vertices, {len(uv)} uvs, faces index up to {f.max() if len(f) else -1})")
        return v, f, uv

    def billboard_arrays(self):
        """(vertices, faces, uvs) of the billboard quads (empty arrays when there is none)."""
        bb = self.billboard
        if bb is None or len(np.asarray(bb.faces)) == 0:
            return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 2))
        v = np.asarray(bb.vertices, dtype=np.float64).reshape(-1, 3)
        f = np.asarray(bb.faces, dtype=np.int64).reshape(-1, 3)
        uv = np.asarray(bb.uvs, dtype=np.float64).reshape(-1, 2)
        tex = np.asarray(bb.texture)
        if (len(uv) != len(v) or (len(f) and (f.min() < 0 or f.max() >= len(v))) or not np.all(np.isfinite(v))
                or tex.ndim != 3 or tex.shape[2] != 4 or tex.dtype != np.uint8):
            raise InputError(f"tree {self.tree_id}: billboard is inconsistent ({len(v)} vertices, {len(uv)} uvs, "
                             f"texture {tex.shape} {tex.dtype})")
        return v, f, uv

    def has_mesh(self) -> bool:
        """True when the tree has wood or leaf faces (the full model)."""
        return len(self.wood_arrays()[1]) > 0 or len(self.leaf_arrays()[1]) > 0

    def all_local_vertices(self) -> np.ndarray:
        parts = [self.wood_arrays()[0], self.leaf_arrays()[0]]
        parts += [self.wood_arrays(k)[0] for k in sorted(self.lods)]
        parts.append(self.billboard_arrays()[0])
        return np.concatenate(parts)


def _mesh_arrays(mesh, where):
    if mesh is None:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    v = np.asarray(mesh.vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
    if not np.isfinite(v).all():
        raise InputError(f"{where}: the mesh has non-finite vertex coordinates")
    if _bad_index(f, len(v)):
        raise InputError(f"{where}: mesh faces index vertices that do not exist")
    return v, f


def _bad_index(faces: np.ndarray, n_vertices: int) -> bool:
    """Whether int64 ``faces`` index outside 0 .. n_vertices - 1 (one pass: negatives wrap to huge unsigned)."""
    return bool(len(faces)) and int(np.maximum.reduce(faces.view(np.uint64), axis=None)) >= n_vertices


def check_models(models, what: str = "export", cache: Optional[dict] = None):
    """A list of TreeModel; raises InputError for an empty list, duplicates or a tree without geometry.

    ``cache``: see :func:`cached`; the checked arrays are kept in it (:func:`mesh_arrays`).
    """
    models = list(models)
    if not models:
        raise InputError(f"{what}: no trees to write")
    cache = {} if cache is None else cache
    seen = set()
    for m in models:
        if not isinstance(m, TreeModel):
            raise InputError(f"{what}: expected TreeModel objects, got {type(m).__name__}")
        if m.tree_id in seen:
            raise InputError(f"{what}: tree id {m.tree_id} occurs twice")
        seen.add(m.tree_id)
        wv, wf = mesh_arrays(m, "wood", cache)
        _, lf, _ = mesh_arrays(m, "leaves", cache)
        if len(wf) == 0 and len(lf) == 0 and len(mesh_arrays(m, "billboard", cache)[1]) == 0:
            raise InputError(f"{what}: tree {m.tree_id} has an empty mesh (no wood and no leaf faces); "
                             f"leave it out or rebuild its geometry")
    return models


def cached(cache: dict, model: TreeModel, what, compute):
    """``compute(model)``, kept in ``cache`` under ``what`` for this very model.

    ``cache`` is a dict shared by the exports of the same, unchanged models (a tile's GLB, its
    tileset: see :func:`~.gltf.glb_bytes`); a hit must hold the model itself, as ids are reused
    once an object is gone.  Sylva, not in the paper.
    """
    key = (id(model), what)
    hit = cache.get(key)
    if hit is not None and hit[0] is model:
        return hit[1]
    value = compute(model)
    cache[key] = (model, value)
    return value


def mesh_arrays(model: TreeModel, what: str, cache: dict, lod: Optional[int] = None):
    """``model.wood_arrays(lod)``, ``model.leaf_arrays()`` or ``model.billboard_arrays()`` (``what``
    "wood", "leaves" or "billboard"), checked once per ``cache`` (:func:`cached`)."""
    if what == "wood":
        return cached(cache, model, ("wood", lod), lambda m: m.wood_arrays(lod))
    if what == "leaves":
        return cached(cache, model, "leaves", lambda m: m.leaf_arrays())
    return cached(cache, model, "billboard", lambda m: m.billboard_arrays())


def cached_attributes(model: TreeModel, cache: dict) -> Dict[str, Any]:
    """``model.json_attributes()``, computed once per ``cache`` (:func:`cached`)."""
    return cached(cache, model, "attributes", lambda m: m.json_attributes())


@dataclass(frozen=True)
class ExportFrame:
    """The source CRS of the models' ``base`` coordinates.

    ``crs`` a :class:`pyproj.CRS` or anything pyproj accepts (``"EPSG:32632"``,
    an EPSG integer, WKT); None for a purely local engineering frame.
    ``units`` metres per unit of the horizontal and vertical axes (default:
    from the CRS as :func:`sylva.core.io.las.units_of` reads them, vertical =
    horizontal unless the CRS has a vertical axis — the LAS convention).
    """

    crs: Any = None
    units: Optional[Units] = None

    def pyproj_crs(self):
        if self.crs is None:
            return None
        from pyproj import CRS
        from pyproj.exceptions import CRSError as ProjCRSError

        if isinstance(self.crs, CRS):
            return self.crs
        try:
            return CRS.from_user_input(self.crs)
        except ProjCRSError as exc:
            raise CRSError(f"export: the CRS {str(self.crs)[:80]!r} is not understood by PROJ: {exc}")

    def resolved_units(self) -> Units:
        if self.units is not None:
            return self.units
        crs = self.pyproj_crs()
        if crs is None:
            return METRES
        from ..io.las import units_of

        units = units_of(crs)
        if math.isnan(units.horizontal_m):
            raise CRSError(f"export: the CRS {crs.name!r} is geographic (degrees); tree bases "
                           f"must be in a projected CRS — reproject the point cloud first")
        return units

    @classmethod
    def from_cloud(cls, cloud) -> "ExportFrame":
        """The frame of a :class:`sylva.core.cloud.PointCloud` (its CRS and units)."""
        return cls(crs=cloud.crs, units=cloud.units)
