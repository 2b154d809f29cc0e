"""Lightweight billboard trees (Zhou et al. 2013): sylva:billboards."""
from __future__ import annotations

import numpy as np

from ..core.reconstruct.billboard import Billboard
from .common import build_method, crs_override, input_cloud, load_segmented, method_params
from .spec import FILE, FILE_OUT, FOLDER_OUT, NUMBER_RESULT, RASTER, Algorithm, Feedback, Param, Result

BILLBOARD_PARAMS = method_params(Billboard, {
    "pixel_m": ("Mask pixel (m)", "Pixel size of the shape masks: the scale factor s of Zhou et al. 2013 §VI-A, so "
                                  "sizes come out in metres. Smaller finds thinner trunks, costs more time."),
    "close_m": ("Closing radius (m)", "Smallest radius of the morphological closing that joins the points into a "
                                      "silhouette (Zhou et al. 2013 §VI-A); the median point spacing is used when "
                                      "larger."),
    "width_jump_m": ("Trunk end: width jump (m)", "Growth of the width function f(y) that ends the trunk going up "
                                                  "(the first non-zero ∂f/∂y of Zhou et al. 2013 §VI-A)."),
    "min_trunk_m": ("Shortest trunk (m)", "A trunk area shorter than this is no trunk: the tree gets the three "
                                          "crown quads only (Zhou et al. 2013 §VI-A, Fig. 5)."),
    "ransac_tolerance_m": ("Trunk edge tolerance (m)", "Largest distance of an edge point to a trunk edge line "
                                                       "found by RANSAC (Zhou et al. 2013 §VI-A)."),
    "texture_px": ("Texture size (pixels)", "Texels along the tree's longest side; 64–128 keep a tree near the "
                                            "paper's 40 kB (Zhou et al. 2013, Table I)."),
    "gmm_components": ("Colour clusters", "Clusters of the Gaussian mixture in HSV that removes wrong colours "
                                          "(Zhou et al. 2013 §VI-B); 0 keeps every colour."),
    "block_px": ("Texture completion block (pixels)", "Initial block size s of the texture completion (Zhou et "
                                                      "al. 2013 §VI-B, Algorithm 1)."),
    "palette_colours": ("Palette colours", "Colours of the PNG palette of each tree's texture."),
    "seed": ("Random seed", "Seed of RANSAC and of the Gaussian mixture: same seed, same result."),
}, advanced=("close_m", "width_jump_m", "ransac_tolerance_m", "gmm_components", "block_px", "palette_colours",
             "seed"),
   ranges={"pixel_m": (0.005, 1.0), "close_m": (0.005, 10.0), "width_jump_m": (0.0, 10.0),
           "min_trunk_m": (0.0, 100.0), "ransac_tolerance_m": (0.001, 1.0), "texture_px": (8, 4096),
           "gmm_components": (0, 16), "block_px": (1, 256), "palette_colours": (2, 256),
           "seed": (0, 2 ** 31 - 1)})


def point_colours(cloud, image_path, feedback: Feedback, camera_path=None):
    """(colours (n, 3) float in [0, 1] with NaN rows, source name) or (None, "procedural")."""
    from ..core.errors import InputError

    if camera_path and not image_path:
        raise InputError(f"CAMERA {camera_path}: give the street-level photo it belongs to as IMAGE")
    if image_path and camera_path:
        from ..core.reconstruct.billboard import read_camera, sample_camera

        rgb = sample_camera(read_camera(camera_path, image_path), cloud.xyz)
        seen = np.isfinite(rgb[:, 0])
        feedback.info(f"{int(seen.sum()):,} of {len(seen):,} points project into the photo")
        if not seen.any():
            raise InputError(f"{image_path}: no point of the cloud projects into the photo "
                             f"(check the camera {camera_path} and the CRS)")
        return rgb, "camera"
    if image_path:
        from ..core.reconstruct.billboard import read_orthophoto, sample_orthophoto

        ortho = read_orthophoto(image_path)
        x, y = cloud.xyz[:, 0], cloud.xyz[:, 1]
        if ortho.crs is not None and cloud.crs is not None and not ortho.crs.equals(cloud.crs):
            from pyproj import Transformer

            x, y = Transformer.from_crs(cloud.crs, ortho.crs, always_xy=True).transform(x, y)
        rgb = sample_orthophoto(ortho, x, y)
        inside = np.isfinite(rgb[:, 0])
        feedback.info(f"{int(inside.sum()):,} of {len(inside):,} points lie on the image")
        if not inside.any():
            raise InputError(f"{image_path}: no point of the cloud lies on the image (check its extent and CRS)")
        return rgb, "image"
    names = ("red", "green", "blue")
    if all(cloud.attr(n) is not None for n in names):
        rgb = np.column_stack([np.asarray(cloud.attrs[n]) for n in names])
        if rgb.any():
            return rgb, "points"
    feedback.info("no colours in the points and no image: procedural bark and foliage textures")
    return None, "procedural"


def run(args: dict, feedback: Feedback) -> Result:
    from ..core.export.gltf import write_glb
    from ..core.export.model import ExportFrame, TreeModel
    from ..core.export.tiles3d import write_tileset
    from ..core.forest import tree_points
    from ..core.measure import estimate_dbh, tree_metrics
    from ..core.progress import check
    from ..core.reconstruct.billboard import billboard_tree, point_rgb

    cloud, labels = load_segmented(args, feedback)
    metrics = tree_metrics(cloud, labels)
    method = build_method(Billboard, args)
    rgb, kind = point_colours(cloud, args.get("IMAGE"), feedback, args.get("CAMERA"))
    colours = point_rgb(rgb) if rgb is not None else None
    local = cloud.local_xyz()
    height = np.asarray(cloud.attrs["height"], dtype=np.float64)
    columns = metrics.columns()
    row_of = {int(t): i for i, t in enumerate(metrics.tree_id)}
    ids, groups = tree_points(labels)
    models = []
    feedback.info(f"{len(ids)} trees")
    for k, (tree_id, idx) in enumerate(zip(ids, groups)):
        check(feedback.cancelled)
        feedback.progress(0.05 + 0.8 * k / max(len(ids), 1), f"tree {k + 1} of {len(ids)}")
        xyz = local[idx]
        ground_z = float(np.median(xyz[:, 2] - height[idx]))
        i = row_of[int(tree_id)]
        dbh, _ = estimate_dbh(xyz, height[idx], float(metrics.height[i]), float(metrics.crown_diameter[i]))
        bb = billboard_tree(xyz, method, rgb=None if colours is None else colours[idx], ground_z=ground_z,
                            tree_id=int(tree_id), texture_source=kind, stem_diameter_m=dbh)
        attributes = {key: columns[key][i] for key in columns}
        attributes.update(bb.summary())
        models.append(TreeModel(int(tree_id), cloud.from_local(bb.origin[None, :])[0], None,
                                attributes=attributes, billboard=bb))
    frame = ExportFrame.from_cloud(cloud)
    feedback.progress(0.88, "writing the GLB")
    result = Result(values={"TREE_COUNT": len(models), "TRUNK_COUNT": sum(m.billboard.has_trunk for m in models)})
    write_glb(models, args["OUTPUT"], frame, content="billboard", cancelled=feedback.cancelled)
    result.files["OUTPUT"] = args["OUTPUT"]
    if args.get("TILESET"):
        feedback.progress(0.94, "writing the 3D Tiles tileset")
        write_tileset(models, args["TILESET"], frame, cancelled=feedback.cancelled)
        result.files["TILESET"] = args["TILESET"]
    feedback.info(f"{len(models)} billboard trees, {result.values['TRUNK_COUNT']} with a single main trunk "
                  f"(six quads), the others crown quads on a stem drawn from their DBH; textures: {kind}")
    feedback.progress(1.0, "done")
    return result


BILLBOARDS = Algorithm(
    id="billboards",
    name="Billboard trees (Zhou et al.)",
    group="Individual trees",
    group_id="trees",
    summary=(
        "Lightweight 3D trees for large scenes (Zhou et al. 2013): every tree of a segmented tile (a treeID "
        "per point, as 'Segment trees' writes it) becomes six textured quads with transparency — three around "
        "the trunk axis, three around a vertical crown axis — or three crown quads when the tree has no "
        "single main trunk. The trunk is found from the width of the tree's silhouette (the first change of "
        "f(y)) and two edge lines fitted by RANSAC (§VI-A); sizes are in metres. Textures come from the "
        "points' RGB, or from an orthophoto, cleaned by a Gaussian mixture in HSV and completed block by "
        "block (§VI-B, Eq. 2–3); procedural bark and foliage when there is no colour. Outputs: one GLB "
        "(a node per tree, georeferenced, its attributes as 3D Tiles metadata) and optionally a 3D Tiles "
        "tileset."
    ),
    params=(
        input_cloud(" It must carry a treeID dimension (0 = no tree)."),
        Param("IMAGE", RASTER, "Image for the textures (orthophoto or photo)", optional=True,
              help="A north-up georeferenced RGB image (GeoTIFF) over the tile, each point taking the colour of "
                   "the pixel above it; or, with CAMERA, a street-level photo (JPEG, PNG, TIFF) each point "
                   "takes the colour it projects to. Leave empty to use the points' own RGB."),
        Param("CAMERA", FILE, "Camera of the photo (JSON)", optional=True, file_filter="JSON (*.json)",
              help="Makes IMAGE a street-level photo (Zhou et al. §V): a JSON file with K (3x3 intrinsics, "
                   "pixels), R (3x3) and t (3) taking the cloud's CRS coordinates to the camera frame "
                   "(X_c = R X + t, z forward, image rows down). Occlusions are not traced: the colour "
                   "cleaning and block completion remove what the camera sees in front of a tree."),
        *BILLBOARD_PARAMS,
        crs_override(),
        Param("OUTPUT", FILE_OUT, "Billboard trees (GLB)", file_filter="glTF binary (*.glb)",
              help="One GLB for the tile: a node per tree named tree_<id> with its quads and its own texture "
                   "(PNG with transparency), a .prj and an origin sidecar."),
        Param("TILESET", FOLDER_OUT, "3D Tiles tileset (folder)", optional=True,
              help="A 3D Tiles 1.1 tileset of the billboards (the tile needs a CRS with a datum)."),
    ),
    run=run,
    results=(Param("TREE_COUNT", NUMBER_RESULT, "Number of trees", help="Billboard trees written."),
             Param("TRUNK_COUNT", NUMBER_RESULT, "Trees with a trunk", help="Trees with a single main trunk "
                   "(six quads)."),),
)

ALGORITHMS = (BILLBOARDS,)
