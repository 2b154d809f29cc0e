"""Tree models in other formats, and as a QGIS 3D layer: sylva:exportmodels."""
from __future__ import annotations

from pathlib import Path

from ..core.progress import check, scaled
from .spec import BOOLEAN, ENUM, FILE, FILE_OUT, FOLDER_OUT, NUMBER_RESULT, POLYGON, VECTOR_OUT, Algorithm, Feedback, Param, Result

CITYGML_VERSIONS = ("2.0", "3.0")


def _folder(path: str, what: str) -> Path:
    """An output folder, created when missing (its parent must exist)."""
    from ..core.errors import InputError

    folder = Path(path)
    if folder.exists() and not folder.is_dir():
        raise InputError(f"{folder}: {what} must be a folder, but a file has that name")
    if not folder.parent.is_dir():
        raise InputError(f"{folder}: the parent folder of the {what} does not exist")
    folder.mkdir(exist_ok=True)
    return folder


def run(args: dict, feedback: Feedback) -> Result:
    from ..core.export import write_citygml, write_glb, write_obj, write_tileset
    from ..core.export.georef import Georef, default_origin
    from ..core.export.gpkg3d import models_table
    from ..core.export.read import read_models
    from ..core.errors import InputError

    source = args["INPUT"]
    if not source or not Path(source).is_file():
        raise InputError(f"{source}: file not found")
    feedback.progress(0.0, "reading the models")
    models, frame = read_models(source)
    crs = frame.pyproj_crs()
    feedback.info(f"{Path(source).name}: {len(models)} trees, CRS "
                  f"{crs.name if crs is not None else 'none (local frame)'}")
    if args.get("TILES"):  # fail before writing anything else
        Georef(frame, default_origin(models)).require_geodetic(f"3D Tiles export to {args['TILES']}")
    leaves = bool(args.get("INCLUDE_LEAVES", True))
    result = Result(values={"TREE_COUNT": len(models)})
    steps = [(name, args.get(name)) for name in ("GLB_FOLDER", "TILES", "CITYGML", "OBJ") if args.get(name)]
    for k, (name, target) in enumerate(steps):
        check(feedback.cancelled)
        progress = scaled(feedback.progress, 0.05 + 0.85 * k / len(steps), 0.05 + 0.85 * (k + 1) / len(steps))
        common = dict(progress=progress, cancelled=feedback.cancelled)
        if name == "GLB_FOLDER":
            write_glb(models, _folder(target, "GLB folder"), frame, per_tree=True, leaves=leaves, **common)
        elif name == "TILES":
            write_tileset(models, _folder(target, "3D Tiles folder"), frame, **common)
        elif name == "CITYGML":
            write_citygml(models, target, frame, leaves=leaves, implicit=bool(args.get("IMPLICIT")),
                          version=args.get("VERSION") or "2.0", **common)
        else:
            write_obj(models, target, frame, leaves=leaves, **common)
        result.files[name] = str(target)
        feedback.info(f"{name}: {target}")
    feedback.progress(0.92, "3D layer")
    result.vectors["MODELS_3D"] = models_table(models, frame, leaves=bool(args.get("INCLUDE_LEAVES_3D")))
    feedback.progress(0.96, "3D crowns")
    result.vectors["CROWNS_3D"] = model_crowns(models, frame)
    feedback.progress(1.0, "done")
    return result


def model_crowns(models, frame):
    """The crowns_3d layer of ``models``: each one's crown envelope (core/export/crowns3d.py) from its leaves,
    else from its wood above the crown base, standing on its base like models_3d."""
    import numpy as np

    from ..core.export.crowns3d import crown_hull, crowns_table, model_crown_points

    units = frame.resolved_units()
    scale = np.array([units.horizontal_m, units.horizontal_m, units.vertical_m])
    cache, hulls = {}, []
    for m in models:
        points, top = model_crown_points(m, cache)
        hulls.append(crown_hull(points, keep=top))
    height = np.array([np.nan if m.attributes.get("height") is None else float(m.attributes["height"])
                       for m in models])
    return crowns_table([m.tree_id for m in models], hulls, np.array([m.base for m in models]), scale,
                        np.array([m.base[2] for m in models]), frame.pyproj_crs(), height=height)


EXPORT_MODELS = Algorithm(
    id="exportmodels",
    name="Export tree models",
    group="Individual trees",
    group_id="trees",
    summary=(
        "Turns the 3D models of 'Reconstruct trees' (its MODELS GLB: a node tree_<id> per tree, "
        "georeferenced) into other formats, each optional: one GLB per tree, an OGC 3D Tiles 1.1 "
        "tileset (Cesium, CesiumJS, QGIS 3.34+), CityGML 2.0 or 3.0 SolitaryVegetationObjects, and "
        "Wavefront OBJ (Blender, MeshLab). MODELS_3D is a layer QGIS draws in its own 3D map view: "
        "one MultiPolygonZ of triangles per tree (the coarsest wood mesh, in the source CRS, with the "
        "trees' attributes), loaded with a 3D style (polygon symbol, standing on the terrain, no extrusion); "
        "CROWNS_3D adds a closed low-poly crown envelope per tree, drawn green. "
        "Every file keeps the source CRS: a .prj and an .origin.json are written next to it."
    ),
    params=(
        Param("INPUT", FILE, "Tree models (GLB)", file_filter="glTF binary (*.glb);;All files (*)",
              help="The MODELS output of 'Reconstruct trees' (or a per-tree GLB of this algorithm)."),
        Param("INCLUDE_LEAVES", BOOLEAN, "Include leaves", default=True, aliases=("LEAVES",),
              help="The models' leaves (cards or needle clusters, as 'Reconstruct trees' grew them) in the "
                   "per-tree GLBs, the CityGML (lod2) and the OBJ; 3D Tiles always have them. (LEAVES "
                   "elsewhere chooses which leaves to grow.)"),
        Param("VERSION", ENUM, "CityGML version", options=CITYGML_VERSIONS, default="2.0",
              labels=("CityGML 2.0", "CityGML 3.0"),
              help="2.0: lod2Geometry (widest support); 3.0: lod2MultiSurface."),
        Param("IMPLICIT", BOOLEAN, "CityGML implicit geometry", default=False, advanced=True,
              help="Write lod2ImplicitRepresentation (a prototype in local metres, a reference point and a "
                   "transformation matrix) instead of explicit coordinates."),
        Param("INCLUDE_LEAVES_3D", BOOLEAN, "Leaves in the 3D layer", default=False, advanced=True,
              aliases=("LEAVES_3D",),
              help="Add the leaf cards to MODELS_3D as further triangles (many more faces)."),
        Param("GLB_FOLDER", FOLDER_OUT, "One GLB per tree (folder)", optional=True,
              help="tree_<id>.glb for every tree, its origin at the tree's base, with .prj and .origin.json."),
        Param("TILES", FOLDER_OUT, "3D Tiles tileset (folder)", optional=True,
              help="tileset.json with a coarse root tile and full child tiles; needs a CRS with a datum."),
        Param("CITYGML", FILE_OUT, "CityGML", file_filter="CityGML (*.gml)", optional=True,
              help="One CityModel of SolitaryVegetationObjects in the source CRS."),
        Param("OBJ", FILE_OUT, "Wavefront OBJ", file_filter="Wavefront OBJ (*.obj)", optional=True,
              help="OBJ + MTL + leaf textures, vertices relative to the origin in .offset.txt."),
        Param("MODELS_3D", VECTOR_OUT, "3D models layer", geometry=POLYGON, optional=True, style="models_3d.qml",
              help="MultiPolygonZ of triangles per tree in the source CRS with the trees' attributes and "
                   "n_triangles; shown by QGIS's 3D map view."),
        Param("CROWNS_3D", VECTOR_OUT, "3D crowns layer", geometry=POLYGON, optional=True, style="crowns_3d.qml",
              help="One closed low-poly crown envelope per tree (at most 82 triangles: the convex hull of its "
                   "leaves, else of its wood above the crown base) as a MultiPolygonZ in the source CRS with "
                   "tree_id, base_z, height and n_triangles; drawn green over the wood in QGIS's 3D map view."),
    ),
    run=run,
    results=(Param("TREE_COUNT", NUMBER_RESULT, "Number of trees", help="Trees exported."),),
)

ALGORITHMS = (EXPORT_MODELS,)
