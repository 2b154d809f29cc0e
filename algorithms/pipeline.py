"""A whole survey in one go: sylva:pipeline (tiles with buffers -> trees, models, one GeoPackage)."""
from __future__ import annotations

from ..core.segment import ChmRegionGrowing, NormalizedCut
from .common import (buffer_param, crs_override, growth_param, leaves_param, lod_param, min_height_param,
                     scheduler_of, scheduler_param, tiles_and_folder, tiles_input, top_window_param, workers_param)
from .segment import SEGMENTATION_LABELS
from .spec import (BOOLEAN, ENUM, FOLDER_OUT, NUMBER, NUMBER_RESULT,
                   STRING_RESULT, Algorithm, Feedback, Param, Result)

SEGMENTATION = {"ncut": NormalizedCut, "chm": ChmRegionGrowing}


def run(args: dict, feedback: Feedback) -> Result:
    from pathlib import Path

    from ..core.catalog import run_catalog
    from ..core.errors import InputError
    from ..core.pipeline import PipelineOptions

    inputs, out = tiles_and_folder(args)
    from .segment import segmentation_method, warn_unused_growth

    options = PipelineOptions(
        buffer_m=float(args["BUFFER_M"]), segmentation=segmentation_method(args),
        reconstruct=bool(args["RECONSTRUCT"]), lod=int(args["LOD"]), leaves=args["LEAVES"],
        billboards=bool(args["BILLBOARDS"]), chunk_size_m=float(args["CHUNK_SIZE_M"]),
        crs=args.get("CRS") or None)
    warn_unused_growth(args, feedback, options.segmentation)
    scheduler = scheduler_of(args)
    report = run_catalog(inputs, out, options, workers=max(1, int(args["WORKERS"])), scheduler=scheduler,
                         resume=bool(args["RESUME"]), progress=feedback.progress, cancelled=feedback.cancelled)
    for line in report.summary().splitlines():
        if line.startswith(("FAILED", "WARNING ")):
            feedback.warn(line.removeprefix("WARNING "))
        else:
            feedback.info(line)
    if not report.tiles:
        first = report.failures[0] if report.failures else {"name": "?", "reason": "no tile"}
        raise InputError(f"every tile failed ({len(report.failures)} of {len(report.failures)}; "
                         f"see {Path(out) / 'report.txt'}): first {first['name']}: {first['reason']}")
    result = Result(values={"TREE_COUNT": report.trees, "TILE_COUNT": len(report.tiles),
                            "FAILED_TILES": len(report.failures)})
    result.files["OUTPUT_FOLDER"] = str(out)
    if report.gpkg:
        result.values["GEOPACKAGE"] = report.gpkg
    for name, path in (("DTM", report.dtm), ("CHM", report.chm)):   # dtm.vrt (the 3D view's terrain), chm.vrt
        if path:
            result.files[name] = path
    return result


PIPELINE = Algorithm(
    id="pipeline",
    name="Forest from tiles (pipeline)",
    group="Individual trees",
    group_id="trees",
    summary=(
        "Runs the whole chain — noise filter, height normalisation, tree tops, tree segmentation, "
        "tree measurements and (optionally) 3D reconstruction — over every tile of a survey, each "
        "tile with a buffer of its neighbours' points so that no tree is lost, split or counted twice "
        "at a tile border: a tree belongs to the tile that holds its top, and its ID is derived from "
        "the top's position, so it is the same whatever the tiling or the number of workers (where "
        "crowns are wider than the buffer allows for, two tiles can cut a tree at their border "
        "differently so that neither owns it: its points then carry no tree ID, and the log warns and "
        "counts them; a wider BUFFER_M prevents it). Writes "
        "into the output folder: forest.gpkg (trees, tree_tops, crowns, crown_points, stem_points, "
        "skeletons, models_3d: the wood for QGIS's 3D view, crowns_3d: a closed crown envelope per tree "
        "for it), tiles/ (every tile with an int32 treeID), models/ (a GLB per tile and one 3D Tiles "
        "tileset.json) and report.json/report.txt (tiles, trees, failures with reasons, time, points/s, "
        "peak memory). A rerun skips the tiles already complete for the same inputs and parameters; a "
        "tile that fails is retried once and reported without stopping the run."
    ),
    params=(
        tiles_input(),
        buffer_param(),
        Param("CHUNK_SIZE_M", NUMBER, "Chunk size (m)", default=0.0, minimum=0.0, maximum=100000.0, advanced=True,
              help="Cut files wider than this into square chunks of this size, each processed as a tile with "
                   "its buffer (as lidR's opt_chunk_size): a large merged block or a dense flight in one file "
                   "then needs the memory of one chunk and keeps every worker busy. The trees and their IDs "
                   "are the same; the segmented points are written per chunk (tiles/<file>_<i>_<j>.laz). "
                   "0: one tile per file. About 250 m suits 20 points/m²."),
        Param("METHOD", ENUM, "Segmentation method", options=tuple(SEGMENTATION), default="ncut",
              labels=SEGMENTATION_LABELS[:2],
              help="ncut: normalised cut on a voxel graph (Hu et al. 2017); chm: region growing on the "
                   "canopy height model (Dalponte & Coomes 2016)."),
        top_window_param(),
        min_height_param(),
        growth_param(),
        Param("RECONSTRUCT", BOOLEAN, "Reconstruct 3D models", default=True,
              help="Model every tree (hybrid greedy skeleton / guided growth) and write GLB and 3D Tiles; "
                   "off: segmentation and measurements only (much faster)."),
        lod_param(advanced=True),
        leaves_param(advanced=True),
        Param("BILLBOARDS", BOOLEAN, "Billboards as the far level of detail", default=False, advanced=True,
              help="Also build each tree's textured billboard (Zhou et al. 2013: six quads, textured from the "
                   "points' RGB when the tiles have colour) and draw it in the 3D Tiles tileset's far tile "
                   "instead of the coarse wood; about 0.07 s per tree."),
        workers_param(),
        scheduler_param(),
        Param("RESUME", BOOLEAN, "Skip completed tiles", default=True,
              help="Reuse tiles whose outputs are complete for the same input files and parameters."),
        crs_override(),
        Param("OUTPUT_FOLDER", FOLDER_OUT, "Output folder",
              help="Receives forest.gpkg, tiles/, models/, parts/ and report.json/report.txt."),
    ),
    run=run,
    results=(
        Param("TREE_COUNT", NUMBER_RESULT, "Number of trees", help="Trees of the whole run."),
        Param("TILE_COUNT", NUMBER_RESULT, "Number of tiles", help="Tiles of the run."),
        Param("FAILED_TILES", NUMBER_RESULT, "Failed tiles", help="Tiles that failed (see report.txt)."),
        Param("GEOPACKAGE", STRING_RESULT, "Forest GeoPackage", help="The path of forest.gpkg."),
        Param("DTM", STRING_RESULT, "Terrain model (dtm.vrt)",
              help="The path of dtm.vrt: the tiles' 1 m terrain (CRS elevations), a DEM for the 3D view."),
        Param("CHM", STRING_RESULT, "Canopy height model (chm.vrt)",
              help="The path of chm.vrt: the tiles' 0.5 m canopy heights (m)."),
    ),
)

ALGORITHMS = (PIPELINE,)
