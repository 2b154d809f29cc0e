"""Height normalisation and individual-tree segmentation: sylva:normalizeheight, sylva:segmenttrees."""
from __future__ import annotations

import numpy as np

from ..core.progress import scaled
from ..core.segment import ChmRegionGrowing, NormalizedCut
from ..core.segment.stems import AutoSegmentation, StemSegmentation
from ..core.table import VectorTable
from .common import (build_method, crs_override, drop_noise, input_cloud, load_cloud, method_params, min_height_param,
                     top_window_param, growth_param)
from .spec import (BOOLEAN, ENUM, FILE_OUT, LINE, NO_GEOMETRY, NUMBER, NUMBER_RESULT, POINT, POLYGON, VECTOR_OUT,  # noqa: F401
                   Algorithm, Feedback, Param, Result)

LAS_FILTER = "LAZ (*.laz);;LAS (*.las)"
GROUND = ("auto", "never", "always")


# --------------------------------------------------------------------------- normalizeheight

def run_normalize(args: dict, feedback: Feedback) -> Result:
    from ..core.io.las import write_las
    from ..core.terrain import CSF, SMRF, height_as_z, normalize

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
        out, extra = height_as_z(out, height, cloud.xyz[:, 2])
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
              labels=("Triangulation (TIN)", "Inverse distance, 10 nearest (k-NN IDW)"),
              help="tin: linear in the triangulation of ground points (exact on planar ground); "
                   "knnidw: inverse-distance weighting of the 10 nearest ground points."),
        Param("CLASSIFY_GROUND", ENUM, "Classify ground points", options=GROUND, default="auto",
              labels=("Only when the tile has none", "Never (use class 2)", "Always (reclassify)"),
              help="auto: only when the tile has no ground class 2; never: fail without ground "
                   "points; always: reclassify, ignoring the file's ground class."),
        Param("GROUND_METHOD", ENUM, "Ground filter", options=("smrf", "csf"), default="smrf",
              labels=("Morphological filter (SMRF)", "Cloth simulation (CSF)"),
              help="smrf: simple morphological filter (Pingel et al. 2013); csf: cloth simulation "
                   "filter (Zhang et al. 2016)."),
        Param("REPLACE_Z", BOOLEAN, "Write height above ground as Z", default=True,
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
    "voxel_m": ("voxel size (m)", "Pitch of the voxel graph, d_s in Hu et al. 2017 (§4.1, §6.1: 0.7 m for tens "
                "of thousands of points, 0.9 m for millions)."),
    "radius_m": ("link radius (m)", "Voxels farther apart horizontally than this are not linked: the cylinder "
                 "radius r_xz of Hu et al. 2017, Eq. 2."),
    "sigma_h_m": ("horizontal distance scale (m)", "Weight exp(-H/σ_h) of the horizontal distance between "
                  "voxels (Hu et al. 2017, Eq. 2)."),
    "sigma_v_m": ("vertical distance scale (m)", "Weight exp(-V/σ_v) of the vertical distance (Hu et al. "
                  "2017, Eq. 2)."),
    "sigma_intensity": ("intensity scale", "Scale σ_I of intensity differences, in natural-log units: 1 means "
                        "a ratio of e ≈ 2.7 between two voxels' intensities costs as much as σ_h of horizontal "
                        "distance (Hu et al. 2017, Eq. 2)."),
    "sigma_colour": ("colour scale", "Weight of RGB differences (0–1 colour units; Hu et al. 2017, Eq. 2); "
                     "ignored without RGB."),
    "top_window_points": ("canopy points per tree-top window", "On sparse clouds the tree-top window is widened "
                          "until it holds at least this many canopy first returns (2.7 m at 4.3 points/m²); 0, "
                          "or a tree-top window you set, turns this off (Sylva, not in the paper)."),
    "top_window_crown": ("tree-top window, share of crown width", "The tree-top window is at least this share of "
                         "the crown width Popescu & Wynne (2004) give a tree that high (CW = 2.51503 + 0.00901 h², "
                         "at most 12 m; metres: 2.4 m at 20 m, 4.2 m at 30 m, 4.8 m above 32.4 m); 0, or a tree-top window you set, turns this off "
                         "(Sylva, not in Hu et al.)."),
    "closed_window": ("tree-top window in a closed canopy, factor", "Where the canopy around a top is closed (crowns "
                      "reaching half its height cover at least 75 % of the ground within two crown radii), "
                      "neighbours have narrowed the crowns: the maxima of a window whose share of the crown width "
                      "(TOP_WINDOW_CROWN) shrinks by this factor are tree tops too; 1, or a tree-top window you "
                      "set, turns this off, as does GROWTH open-grown (Sylva, not in Hu et al.)."),
    "apex_window_m": ("steep-apex window (m)", "Maxima of this narrow window also count as tree tops when the "
                      "canopy falls away steeply from them (conifer tips overtopped on one side by a taller "
                      "neighbour; Sylva, not in the paper); 0 turns this off."),
    "apex_slope": ("steep-apex drop (m/m)", "The drop around such a tip, metres per metre."),
    "apex_sectors": ("steep-apex directions (of 8)", "In how many of 8 compass directions the canopy must "
                     "drop that steeply."),
    "understory_points": ("points of a suppressed tree", "A crown under the canopy that no tree top reaches "
                          "(more than 2 m below the crowns above it) is a tree of its own when it holds at "
                          "least this many points and spans 2.5 m; smaller pieces join the nearest tree "
                          "(Sylva, not in the paper; after Hamraz et al. 2017); 0 turns this off."),
}, advanced=("voxel_m", "radius_m", "sigma_h_m", "sigma_v_m", "sigma_intensity", "sigma_colour",
             "top_window_points", "top_window_crown", "closed_window", "apex_window_m", "apex_slope",
             "apex_sectors", "understory_points"),
   ranges={"voxel_m": (0.05, 10.0), "radius_m": (0.05, 50.0), "sigma_h_m": (0.01, 100.0),
           "sigma_v_m": (0.01, 100.0), "sigma_intensity": (0.001, 100.0), "sigma_colour": (0.001, 10.0),
           "top_window_points": (0.0, 10000.0), "top_window_crown": (0.0, 2.0), "closed_window": (0.0, 1.0),
           "apex_window_m": (0.0, 20.0),
           "apex_slope": (0.01, 100.0), "apex_sectors": (1, 8), "understory_points": (0, 1000000)},
   prefix="Normalised cut: ", optional=("understory_points", "top_window_crown", "closed_window"))



CHM_PARAMS = method_params(ChmRegionGrowing, {
    "resolution_m": ("cell size (m)", "Cell size of the canopy height model the crowns grow on."),
    "th_seed": ("seed threshold (share of top)", "A cell joins a tree when higher than this fraction of "
                "the tree's top (th_seed of Dalponte & Coomes 2016)."),
    "th_cr": ("crown threshold (share of mean)", "... and higher than this fraction of the mean height of "
              "the crown grown so far (th_cr of Dalponte & Coomes 2016)."),
    "max_crown_diameter_m": ("maximum crown diameter (m)", "No crown grows wider."),
}, advanced=("resolution_m", "th_seed", "th_cr", "max_crown_diameter_m"),
   ranges={"resolution_m": (0.05, 10.0), "th_seed": (0.0, 1.0), "th_cr": (0.0, 1.0),
           "max_crown_diameter_m": (0.5, 100.0)},
   prefix="CHM region growing: ")

STEMS_PARAMS = method_params(StemSegmentation, {
    "slice_low_m": ("stripe bottom (m)", "Lowest height above ground of the stripe in which stems are sought "
                    "(Laino et al. 2024's stripe)."),
    "slice_high_m": ("stripe top (m)", "Highest height above ground of that stripe."),
    "section_m": ("section thickness (m)", "The stripe is cut into sections this thick, one centred at 1.3 m; "
                  "every section's clusters get a circle fit (Cabo et al. 2018 §2.3)."),
    "cluster_m": ("cluster distance (m)", "Points of a section closer than this are one cluster (DBSCAN)."),
    "min_dbh_m": ("smallest stem diameter (m)", "Thinner circles are not stems."),
    "max_dbh_m": ("largest stem diameter (m)", "Wider circles are not stems."),
    "bridge_m": ("occlusion bridge (m)", "Pieces of a crown cut off from every stem by occlusion join the tree of "
                 "the nearest assigned point within this distance (Sylva, not in the papers); 0 turns this off."),
}, advanced=("slice_low_m", "slice_high_m", "section_m", "cluster_m", "min_dbh_m", "max_dbh_m", "bridge_m"),
   ranges={"slice_low_m": (0.0, 10.0), "slice_high_m": (0.1, 20.0), "section_m": (0.02, 2.0),
           "cluster_m": (0.005, 2.0), "min_dbh_m": (0.0, 5.0), "max_dbh_m": (0.01, 10.0), "bridge_m": (0.0, 20.0)},
   prefix="Stems: ")

METHODS = {"ncut": NormalizedCut, "chm": ChmRegionGrowing, "stems": StemSegmentation, "auto": AutoSegmentation}
SEGMENTATION_LABELS = ("Normalised cut on a voxel graph (airborne scans)", "Region growing on the canopy height model",
                       "Stems (terrestrial or mobile plot scans)",
                       "Automatic: stems for plot scans, normalised cut otherwise")


def segmentation_method(args: dict):
    """The segmentation method value of METHOD and its parameters (segmenttrees and pipeline)."""
    # the stems' own parameters only (its voxel_m is not the normalised cut's VOXEL_M)
    stems = {p.name: args.get(p.name) for p in STEMS_PARAMS}
    if args["METHOD"] == "stems":
        return build_method(StemSegmentation, stems)
    if args["METHOD"] == "auto":
        return AutoSegmentation(plot=build_method(StemSegmentation, stems),
                                other=segmentation_method({**args, "METHOD": "ncut"}))
    cls = METHODS[args["METHOD"]]
    fixed = {"min_height_m": args["MIN_HEIGHT_M"]}
    window = args.get("TOP_WINDOW_M")
    if window is not None and window == window and window > 0:   # empty (None or NaN from QGIS): the method's own
        fixed["top_window_m"] = window
        if cls is NormalizedCut:
            fixed["top_window_points"] = fixed["top_window_crown"] = 0.0   # the user's window, exactly
    if cls is NormalizedCut:
        fixed["growth"] = args.get("GROWTH") or "forest"
    return build_method(cls, args, **fixed)


def warn_unused_growth(args: dict, feedback: Feedback, method) -> None:
    """GROWTH shapes the normalised cut only: say so when another method runs with a preset chosen."""
    growth = args.get("GROWTH") or "forest"
    if growth != "forest" and not isinstance(method, NormalizedCut):
        used = next((k for k, cls in METHODS.items() if type(method) is cls), type(method).__name__)
        feedback.warn(f"GROWTH {growth} shapes the normalised cut (METHOD ncut) only; METHOD {used} ignores it")


def run_segment(args: dict, feedback: Feedback) -> Result:
    import shapely

    from ..core.io.las import write_las
    from ..core.measure import CrownBase, tree_metrics
    from ..core.segment.tile import segment_tile

    from ..core.errors import CRSError

    # a terrestrial plot scan may come in a local engineering frame; airborne methods need the CRS
    source = load_cloud(args, feedback, require_crs=args["METHOD"] not in ("stems", "auto"))
    seg = segment_tile(source, segmentation_method(args), progress=scaled(feedback.progress, 0.02, 0.8),
                       cancelled=feedback.cancelled)
    cloud, keep, labels = seg.cloud, seg.keep, seg.labels
    stems = isinstance(seg.method, StemSegmentation)
    if source.crs is None and not stems:
        # airborne tiles need their CRS; a terrestrial plot scan may be in a local engineering frame
        raise CRSError(f"{args['INPUT']}: the file has no coordinate reference system; "
                       "set the CRS parameter (for example EPSG:32632)")
    warn_unused_growth(args, feedback, seg.method)
    if args["METHOD"] == "auto":
        feedback.info("a terrestrial plot scan: trees segmented by their stems (METHOD stems)" if stems else
                      "trees segmented by the normalised cut (METHOD ncut; not a terrestrial plot scan)")
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
        "noise left out, points of classes that are never a tree (buildings, water, rail, roads, wires, "
        "towers, bridge decks: ASPRS 6, 9-11, 13-17) kept out of every tree, tree tops found by a local-maximum filter, and the canopy is cut into trees by the "
        "normalised cut of Hu et al. (2017, §4.1) on a voxel graph whose links weigh horizontal and "
        "vertical distance, intensity and colour (METHOD ncut), or by seeded region growing on a "
        "canopy height model (Dalponte & Coomes 2016; METHOD chm), the classic baseline. Terrestrial and "
        "mobile plot scans (stems seen from below; no CRS needed: a local engineering frame) are segmented by "
        "their stems (METHOD stems, chosen by METHOD auto): stems found by circle fits in sections of a "
        "0.3–2.5 m stripe (Cabo et al. 2018; Laino et al. 2024), every other point given to the stem it "
        "is connected to. "
        "Outputs: the tile with a treeID dimension (0 = no tree), tree tops, crown polygons, crown "
        "and stem points, and a trees table. A tree's crown base is where its vertical point profile, "
        "read from the top down, first has a gap wider than CROWN_BASE_GAP_M; its points below "
        "that are stem points."
    ),
    params=(
        input_cloud(),
        Param("METHOD", ENUM, "Segmentation method", options=tuple(METHODS), default="auto",
              labels=SEGMENTATION_LABELS,
              help="auto (default): stems for terrestrial or mobile plot scans (at least 3 % of the points "
                   "above ground lie below 2 m, densely: 8th neighbour within 0.25 m, and stems are found "
                   "there), ncut otherwise; ncut: normalised cut on a voxel graph (Hu et al. 2017); chm: "
                   "region growing on the canopy height model (Dalponte & Coomes 2016); stems: stems found "
                   "in sections of a 0.3–2.5 m stripe by circle fits and every other point given to the stem "
                   "it is connected to (Cabo et al. 2018; Laino et al. 2024, 3DFin), with the ground "
                   "classified under the canopy from the lowest points. Each method's own settings are "
                   "under Advanced parameters, named after it."),
        top_window_param(),
        min_height_param(),
        growth_param(),
        *NCUT_PARAMS,
        *CHM_PARAMS,
        *STEMS_PARAMS,
        Param("HULL", ENUM, "Crown outline", options=("convex", "concave"), default="convex",
              labels=("Convex hull", "Concave hull (tighter)"),
              help="convex: convex hull of the crown points; concave: a tighter outline (CONCAVITY)."),
        Param("CONCAVITY", NUMBER, "Concave hull: concavity (0–1)", default=0.3, minimum=0.0, maximum=1.0, advanced=True,
              help="For concave outlines: 1 = convex hull, smaller values hug the points more tightly."),
        Param("CROWN_BASE_GAP_M", NUMBER, "Crown base gap (m)", default=1.5, minimum=0.1, maximum=20.0,
              advanced=True, help="An empty height interval at least this tall separates crown and stem."),
        crs_override(),
        Param("OUTPUT", FILE_OUT, "Segmented point cloud", file_filter=LAS_FILTER, optional=True,
              help="The tile with every source dimension and an int32 treeID (0 = no tree), as lidR writes."),
        Param("TREE_TOPS", VECTOR_OUT, "Tree tops", geometry=POINT, style="tree_tops.qml",
              help="PointZ at each tree's apex (its highest point in elevation): tree_id, height."),
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
    results=(Param("TREE_COUNT", NUMBER_RESULT, "Number of trees", help="Trees found in the tile."),),
)
ALGORITHMS = (NORMALIZE_HEIGHT, SEGMENT_TREES)
