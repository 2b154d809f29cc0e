"""Tree tops: sylva:treetops."""
from __future__ import annotations

import shapely

from ..core.progress import scaled
from ..core.table import VectorTable
from .common import crs_override, drop_noise, is_raster, load_cloud, min_height_param, require_existing
from .spec import ENUM, FILE, NUMBER, NUMBER_RESULT, POINT, VECTOR_OUT, Algorithm, Feedback, Param, Result

WINDOWS = ("fixed", "variable")


def run(args: dict, feedback: Feedback) -> Result:
    from ..core.raster import read_geotiff
    from ..core.terrain import normalize
    from ..core.tops import FixedWindow, VariableWindow, find_tree_tops

    source = require_existing(args["INPUT"])
    if is_raster(source):
        target = read_geotiff(source)
        crs = target.crs
        feedback.info(f"{source}: canopy height model, {target.data.shape[1]} x {target.data.shape[0]} cells")
    else:
        cloud, _ = drop_noise(load_cloud(args, feedback), feedback)
        feedback.progress(0.05, "height above ground")
        target = normalize(cloud)
        crs = cloud.crs
    window = FixedWindow(diameter_m=args["TOP_WINDOW_M"]) if args["WINDOW"] == "fixed" else VariableWindow()
    tops = find_tree_tops(
        target, window=window, min_height_m=args["MIN_HEIGHT_M"],
        progress=scaled(feedback.progress, 0.3, 1.0), cancelled=feedback.cancelled,
    )
    feedback.info(f"{len(tops.height)} tree tops found")
    table = VectorTable(
        "tree_tops", POINT, shapely.points(tops.xyz),
        {"tree_id": tops.tree_id, "height": tops.height}, crs,
    )
    return Result(vectors={"OUTPUT": table}, values={"TREE_COUNT": len(tops.height)})


TREE_TOPS = Algorithm(
    id="treetops",
    name="Tree tops",
    group="Individual trees",
    group_id="trees",
    summary=(
        "Finds tree tops as local maxima of canopy height (as lidR's lmf): a point, or CHM cell, "
        "is a top when nothing within the search window around it is higher. Input is a LiDAR "
        "tile (heights are normalised first) or a canopy height model GeoTIFF from "
        "'Canopy height model'. Output: one PointZ per tree with tree_id and height (m above ground)."
    ),
    params=(
        Param("INPUT", FILE, "Point cloud (LAS/LAZ) or canopy height model (GeoTIFF)",
              file_filter="LAS/LAZ or GeoTIFF (*.las *.laz *.tif *.tiff);;All files (*)",
              help="A LiDAR tile, or a CHM raster of heights above ground in metres."),
        Param("WINDOW", ENUM, "Search window", options=WINDOWS, default="variable",
              labels=("Fixed diameter", "Grows with tree height"),
              help="variable (default): the window grows with height (1.5 m + 0.1 x height, 2–8 m), as "
                   "crowns of taller trees are wider; measured best on mixed stands (benchmarks/terrain.py). "
                   "fixed: one circular window of TOP_WINDOW_M for every tree."),
        Param("TOP_WINDOW_M", NUMBER, "Tree-top window (m)", default=3.0, minimum=0.5, maximum=50.0,
              aliases=("WINDOW_DIAMETER_M",),
              help="Diameter of the circular search window in metres; about the crown radius of "
                   "the smallest trees you want to find."),
        min_height_param(),
        crs_override(),
        Param("OUTPUT", VECTOR_OUT, "Tree tops", geometry=POINT, style="tree_tops.qml",
              help="Point layer (PointZ, z = elevation of the top) with tree_id and height."),
    ),
    run=run,
    results=(Param("TREE_COUNT", NUMBER_RESULT, "Number of trees", help="Tree tops found."),),
)
ALGORITHMS = (TREE_TOPS,)
