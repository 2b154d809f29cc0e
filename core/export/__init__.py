"""Georeferenced 3D model export: glTF 2.0 / GLB, OGC 3D Tiles 1.1, CityGML 2.0/3.0, OBJ + MTL.

Every writer takes a list of :class:`TreeModel` (meshes in tree-local metres:
x grid east, y grid north, z up, origin at the stem base; ``base`` in the
source CRS), an output path and an :class:`ExportFrame` (the source CRS and
its units), and returns the paths it wrote.  :mod:`.georef` holds the frames
they share (source CRS -> WGS 84 -> ECEF -> ENU at an origin, GeographicLib
for geodesics).  Files are written to a temporary name and ``os.replace``d,
and are byte-identical for identical input.

* :func:`write_glb`      one GLB per tile (or per tree), ENU frame at the origin, y-up
  below a root matrix, node ``tree_<id>`` with the attributes in ``extras``,
  EXT_mesh_features + EXT_structural_metadata, ``.prj`` + ``.origin.json``;
* :func:`write_tileset`  3D Tiles 1.1: coarse parent tile, full child tiles, ENU->ECEF
  root transform, boxes from the vertices, geometric errors measured;
* :func:`write_citygml`  SolitaryVegetationObjects with lod geometry or implicit prototypes;
* :func:`write_obj`      OBJ + MTL + leaf PNGs, vertices relative to an origin (offset file, ``.prj``).
"""
from .model import ExportFrame, TreeModel
from .georef import Georef
from .gltf import write_glb
from .obj import write_obj
from .citygml import write_citygml
from .tiles3d import write_tileset

__all__ = ["ExportFrame", "TreeModel", "Georef", "write_glb", "write_obj", "write_citygml", "write_tileset"]
