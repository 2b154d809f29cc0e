"""Height normalisation and individual-tree segmentation: sylva:normalizeheight, sylva:segmenttrees."""
from __future__ import annotations

import numpy as np

from ..core.progress import scaled
from ..core.segment import ChmRegionGrowing, NormalizedCut
from ..core.table import VectorTable
from .common import build_method, crs_override, drop_noise, input_cloud, load_cloud, method_params
from .spec import (BOOLEAN, ENUM, FILE_OUT, LINE, NO_GEOMETRY, NUMBER, POINT, POLYGON, VECTOR_OUT,  # noqa: F401
                   Algorithm, Feedback, Param, Result)

LAS_FILTER = "LAZ (*.laz);;LAS (*.las)"
GROUND = ("auto", "never", "always")


# --------------------------------------------------------------------------- normalizeheight

def run_normalize(args: dict, feedback: Feedback) -> Result:
    from ..core.io.las import write_las
    from ..core.terrain import CSF, SMRF, normalize

    cloud = load_cloud(args, feedback)
    method = SMRF() if args["GROUND_METHOD"] == "smrf" else CSF()
    if args["CLASSIFY_GROUND"] == "always":
        cloud = cloud.with_attrs(classification=np.where(
            np.asarray(cloud.attrs.get("classification", np.ones(len(cloud)))) == 2, 1,
            cloud.attrs.get("classification", np.ones(len(cloud)))).astype(np.uint8))
    classify = None if args["CLASSIFY_GROUND"] == "never" else method
    feedback.progress(0.1, "height above ground")
    out = normalize(cloud, method=args["INTERPOLATION"], classify=classify)
    feedback.progress(0.8, "writing")
    height = out.attrs["height"]
    if args["REPLACE_Z"]:
        xyz = out.xyz.copy()
        xyz[:, 2] = height / out.units.vertical_m
        attrs = {k: v for k, v in out.attrs.items() if k != "height"}
        from dataclasses import replace

        out = replace(out, xyz=xyz, attrs=attrs)
        extra = {"elevation": cloud.xyz[:, 2].astype(np.float64)}
    else:
        extra = {}
    write_las(args["OUTPUT"], out, extra=extra, cancelled=feedback.cancelled)
    feedback.progress(1.0, "done")
    return Result(files={"OUTPUT": args["OUTPUT"]})


NORMALIZE_HEIGHT = Algorithm(
    id="normalizeheight",
    name="Normalise heights",
    group="Terrain and canopy",
    group_id="terrain",
    summary=(
        "Turns elevations into heights above the ground. The ground is the tile's class-2 points "
        "(classified first with SMRF or a cloth simulation filter when the tile has none), "
        "interpolated by a Delaunay triangulation (TIN) or by inverse-distance weighting of the "
        "nearest ground points. Writes a LAS/LAZ with every source dimension kept."
    ),
    params=(
        input_cloud(),
        Param("INTERPOLATION", ENUM, "Ground interpolation", options=("tin", "knnidw"), default="tin",
              help="tin: linear in the triangulation of ground points (exact on planar ground); "
                   "knnidw: inverse-distance weighting of the 10 nearest ground points."),
        Param("CLASSIFY_GROUND", ENUM, "Classify ground", options=GROUND, default="auto",
              help="auto: only when the tile has no ground class 2; never: fail without ground "
                   "points; always: reclassify, ignoring the file's ground class."),
        Param("GROUND_METHOD", ENUM, "Ground filter", options=("smrf", "csf"), default="smrf",
              help="smrf: simple morphological filter (Pingel et al. 2013); csf: cloth simulation "
                   "filter (Zhang et al. 2016)."),
        Param("REPLACE_Z", BOOLEAN, "Replace Z by height", default=True,
              help="Write the height above ground as Z (as lidR's normalize_height does) and keep "
                   "the elevation in an extra dimension 'elevation'; otherwise keep Z and add the "
                   "extra dimension 'height' (metres)."),
        crs_override(),
        Param("OUTPUT", FILE_OUT, "Normalised point cloud", file_filter=LAS_FILTER,
              help="LAS or LAZ (by the extension) with heights above ground."),
    ),
    run=run_normalize,
)


# --------------------------------------------------------------------------- segmenttrees

NCUT_PARAMS = method_params(NormalizedCut, {
    "voxel_m": ("Voxel size d_s (m)", "Normalised cut: pitch of the voxel graph (Hu et al. §4.1, §6.1: "
                "0.7 m for tens of thousands of points, 0.9 m for millions)."),
    "radius_m": ("Cylinder radius r_xz (m)", "Normalised cut: voxels farther apart horizontally than this "
                 "are not linked (Eq. 2)."),
    "sigma_h_m": ("Horizontal distance scale (m)", "Normalised cut: weight exp(-H/σ_h) of the horizontal "
                  "distance between voxels (Eq. 2)."),
    "sigma_v_m": ("Vertical distance scale (m)", "Normalised cut: weight exp(-V/σ_v) of the vertical "
                  "distance (Eq. 2)."),
    "sigma_intensity": ("Intensity scale", "Normalised cut: scale of intensity differences, in natural-log "
                        "units: 1 means a ratio of e ≈ 2.7 between two voxels' intensities costs as much as "
                        "σ_h of horizontal distance (Eq. 2)."),
    "sigma_colour": ("Colour scale", "Normalised cut: weight of RGB differences (0–1 colour units, Eq. 2); "
                     "ignored without RGB."),
    "top_window_points": ("Tree-top window: canopy points", "Normalised cut: on sparse clouds the tree-top "
                          "window is widened until it holds at least this many canopy first returns (2.7 m at "
                          "4.3 points/m²); 0, or a TOP_WINDOW_M you set, keeps the window fixed."),
    "apex_window_m": ("Steep-apex window (m)", "Normalised cut: maxima of this narrow window also count as tree "
                      "tops when the canopy falls away steeply from them (conifer tips overtopped on one side "
                      "by a taller neighbour; Sylva's rule, not the paper's); 0 turns this off."),
    "apex_slope": ("Steep-apex drop (m/m)", "Normalised cut: the drop around such a tip, metres per metre."),
    "apex_sectors": ("Steep-apex directions", "Normalised cut: in how many of 8 compass directions the canopy "
                     "must drop that steeply."),
}, advanced=("sigma_h_m", "sigma_v_m", "sigma_intensity", "sigma_colour", "top_window_points", "apex_window_m",
             "apex_slope", "apex_sectors"))



CHM_PARAMS = method_params(ChmRegionGrowing, {
    "resolution_m": ("CHM cell size (m)", "Region growing: cell size of the canopy height model."),
    "th_seed": ("Seed threshold", "Region growing: a cell joins a tree when higher than this fraction of "
                "the tree's top (Dalponte & Coomes 2016)."),
    "th_cr": ("Crown threshold", "Region growing: ... and higher than this fraction of the mean height of "
              "the crown grown so far."),
    "max_crown_diameter_m": ("Maximum crown diameter (m)", "Region growing: no crown grows wider."),
}, advanced=("th_seed", "th_cr"))

METHODS = {"ncut": NormalizedCut, "chm": ChmRegionGrowing}


def segmentation_method(args: dict):
    """The segmentation method value of METHOD and its parameters (segmenttrees and pipeline)."""
    cls = METHODS[args["METHOD"]]
    fixed = {"min_height_m": args["MIN_HEIGHT_M"]}
    if args.get("TOP_WINDOW_M"):
        fixed["top_window_m"] = args["TOP_WINDOW_M"]
        if cls is NormalizedCut:
            fixed["top_window_points"] = 0.0   # the user's window, exactly
    return build_method(cls, args, **fixed)


def run_segment(args: dict, feedback: Feedback) -> Result:
    import shapely

    from ..core.io.las import write_las
    from ..core.measure import CrownBase, tree_metrics
    from ..core.segment.tile import segment_tile

    source = load_cloud(args, feedback)
    seg = segment_tile(source, segmentation_method(args), progress=scaled(feedback.progress, 0.02, 0.8),
                       cancelled=feedback.cancelled)
    cloud, keep, labels = seg.cloud, seg.keep, seg.labels
    if not keep.all():
        feedback.info(f"{int((~keep).sum()):,} noise points left out (classes 7/18, withheld, isolated)")
    feedback.progress(0.8, "measuring trees")
    m = tree_metrics(cloud, labels, hull=args["HULL"], concavity=args["CONCAVITY"],
                     crown_base=CrownBase(gap_m=args["CROWN_BASE_GAP_M"]))
    feedback.info(f"{len(m)} trees, {int((labels > 0).sum()):,} tree points")
    crs = cloud.crs
    result = Result(values={"TREE_COUNT": len(m)})
    result.vectors["TREES"] = VectorTable("trees", NO_GEOMETRY, None, m.columns(), crs)
    result.vectors["TREE_TOPS"] = VectorTable(
        "tree_tops", POINT, shapely.points(np.column_stack([m.x, m.y, m.top_z])),
        {"tree_id": m.tree_id, "height": m.height}, crs)
    result.vectors["CROWNS"] = VectorTable(
        "crowns", POLYGON, m.crowns,
        {"tree_id": m.tree_id, "height": m.height, "top_z": m.top_z, "crown_area": m.crown_area,
         "crown_diameter": m.crown_diameter}, crs, has_z=False)
    height = cloud.attrs["height"]
    for name, layer, mask in (("CROWN_POINTS", "crown_points", (labels > 0) & ~m.is_stem),
                              ("STEM_POINTS", "stem_points", m.is_stem)):
        idx = np.flatnonzero(mask)
        result.vectors[name] = VectorTable(
            layer, POINT, shapely.points(cloud.xyz[idx]),
            {"tree_id": labels[idx].astype(np.int64), "height": height[idx]}, crs)
    if args.get("OUTPUT"):
        feedback.progress(0.9, "writing the segmented point cloud")
        tree_id = np.zeros(len(source), dtype=np.int32)
        tree_id[keep] = labels
        write_las(args["OUTPUT"], source, extra={"treeID": tree_id}, cancelled=feedback.cancelled)
        result.files["OUTPUT"] = args["OUTPUT"]
    feedback.progress(1.0, "done")
    return result


SEGMENT_TREES = Algorithm(
    id="segmenttrees",
    name="Segment trees",
    group="Individual trees",
    group_id="trees",
    summary=(
        "Finds every tree of a LiDAR tile and the points that belong to it. Heights are normalised, "
        "noise left out, tree tops found by a local-maximum filter, and the canopy is cut into trees by the "
        "normalised cut of Hu et al. (2017, §4.1) on a voxel graph whose links weigh horizontal and "
        "vertical distance, intensity and colour (METHOD ncut), or by seeded region growing on a "
        "canopy height model (Dalponte & Coomes 2016; METHOD chm), the classic baseline. "
        "Outputs: the tile with a treeID dimension (0 = no tree), tree tops, crown polygons, crown "
        "and stem points, and a trees table. A tree's crown base is where its vertical point profile, "
        "read from the top down, first has a gap wider than CROWN_BASE_GAP_M; its points below "
        "that are stem points."
    ),
    params=(
        input_cloud(),
        Param("METHOD", ENUM, "Segmentation method", options=tuple(METHODS), default="ncut",
              help="ncut: normalised cut on a voxel graph (Hu et al. 2017); chm: region growing on "
                   "the canopy height model (Dalponte & Coomes 2016)."),
        Param("TOP_WINDOW_M", NUMBER, "Tree-top window (m)", optional=True, minimum=0.0, maximum=50.0,
              help="Diameter of the local-maximum window that finds the tree tops guiding the "
                   "segmentation; left empty, each method uses its own measured default."),
        Param("MIN_HEIGHT_M", NUMBER, "Minimum tree height (m)", default=2.0, minimum=0.0, maximum=200.0,
              help="Lower tops are not trees; lower points belong to a tree only under its crown."),
        *NCUT_PARAMS,
        *CHM_PARAMS,
        Param("HULL", ENUM, "Crown outline", options=("convex", "concave"), default="convex",
              help="convex: convex hull of the crown points; concave: a tighter outline (CONCAVITY)."),
        Param("CONCAVITY", NUMBER, "Concavity", default=0.3, minimum=0.0, maximum=1.0, advanced=True,
              help="For concave outlines: 1 = convex hull, smaller values hug the points more tightly."),
        Param("CROWN_BASE_GAP_M", NUMBER, "Crown base gap (m)", default=1.5, minimum=0.1, maximum=20.0,
              advanced=True, help="An empty height interval at least this tall separates crown and stem."),
        crs_override(),
        Param("OUTPUT", FILE_OUT, "Segmented point cloud", file_filter=LAS_FILTER, optional=True,
              help="The tile with every source dimension and an int32 treeID (0 = no tree), as lidR writes."),
        Param("TREE_TOPS", VECTOR_OUT, "Tree tops", geometry=POINT, style="tree_tops.qml",
              help="PointZ at each tree's highest point: tree_id, height."),
        Param("CROWNS", VECTOR_OUT, "Crowns", geometry=POLYGON, style="crowns.qml",
              help="Crown outlines: tree_id, height, top_z, crown_area, crown_diameter."),
        Param("CROWN_POINTS", VECTOR_OUT, "Crown points", geometry=POINT, optional=True, style="crown_points.qml",
              help="PointZ of every crown point: tree_id, height."),
        Param("STEM_POINTS", VECTOR_OUT, "Stem points", geometry=POINT, optional=True, style="stem_points.qml",
              help="PointZ of every point below its tree's crown base: tree_id, height."),
        Param("TREES", VECTOR_OUT, "Trees table", geometry=NO_GEOMETRY,
              help="One row per tree; the fields are documented in the README."),
    ),
    run=run_segment,
)
ALGORITHMS = (NORMALIZE_HEIGHT, SEGMENT_TREES)
