"""Canopy height model: sylva:canopyheightmodel; terrain and canopy over a survey's tiles: sylva:terraintiles."""
from __future__ import annotations

from ..core.progress import scaled
from .common import (buffer_param, crs_override, drop_noise, input_cloud, load_cloud, scheduler_of,
                     scheduler_param, tiles_and_folder, tiles_input, workers_param)
from .spec import (BOOLEAN, FOLDER_OUT, NUMBER, NUMBER_RESULT, RASTER_OUT, STRING_RESULT, Algorithm, Feedback,
                   Param, Result)


def run(args: dict, feedback: Feedback) -> Result:
    from ..core.raster import write_geotiff
    from ..core.terrain import canopy_height_model, normalize

    cloud, _ = drop_noise(load_cloud(args, feedback), feedback)
    feedback.progress(0.05, "height above ground")
    cloud = normalize(cloud)
    chm = canopy_height_model(
        cloud,
        resolution_m=args["RESOLUTION_M"],
        pit_free=args["PIT_FREE"],
        progress=scaled(feedback.progress, 0.3, 0.95),
        cancelled=feedback.cancelled,
    )
    write_geotiff(args["OUTPUT"], chm)
    feedback.progress(1.0, "done")
    return Result(files={"OUTPUT": args["OUTPUT"]})


RESOLUTION = Param("RESOLUTION_M", NUMBER, "Cell size (m)", default=0.5, minimum=0.05, maximum=100.0,
                   help="Size of a CHM cell in metres. About half the typical point spacing or finer "
                        "gives sharp crowns; 0.5 m suits 5–20 points/m².")
PIT_FREE = Param("PIT_FREE", BOOLEAN, "Pit-free CHM", default=True,
                 help="Build the CHM from stacked partial triangulations of first returns above "
                      "increasing heights (Khosravipour et al. 2014) instead of the highest point per cell.")


CANOPY_HEIGHT_MODEL = Algorithm(
    id="canopyheightmodel",
    name="Canopy height model",
    group="Terrain and canopy",
    group_id="terrain",
    summary=(
        "Rasterises a LiDAR tile into a canopy height model (CHM): each cell holds the height of "
        "the canopy above the ground, in metres. Heights are normalised first (ground points, "
        "class 2, are triangulated; tiles that are already height-normalised are detected). "
        "The pit-free option (Khosravipour et al. 2014) removes the dark holes that laser pulses "
        "passing between branches leave in a plain CHM, which otherwise split crowns."
    ),
    params=(
        input_cloud(),
        RESOLUTION,
        PIT_FREE,
        crs_override(),
        Param("OUTPUT", RASTER_OUT, "Canopy height model", file_filter="GeoTIFF (*.tif *.tiff)",
              help="GeoTIFF of heights above ground in metres, in the tile's CRS; no-data outside the data."),
    ),
    run=run,
)


def run_tiles(args: dict, feedback: Feedback) -> Result:
    from pathlib import Path

    from ..core.errors import InputError
    from ..core.terrain_tiles import TerrainOptions, run_terrain_tiles

    inputs, out = tiles_and_folder(args)
    options = TerrainOptions(buffer_m=float(args["BUFFER_M"]), dtm_pixel_m=float(args["DTM_RESOLUTION_M"]),
                             chm_pixel_m=float(args["RESOLUTION_M"]), pit_free=bool(args["PIT_FREE"]),
                             normalized=bool(args["NORMALIZED_TILES"]), crs=args.get("CRS") or None)
    run = run_terrain_tiles(inputs, out, options, workers=max(1, int(args["WORKERS"])),
                            scheduler=scheduler_of(args), progress=feedback.progress, cancelled=feedback.cancelled)
    for failure in run.failures:
        feedback.warn(f"FAILED {failure['name']}: {failure['reason']}")
    if not run.tiles:
        raise InputError(f"every tile failed: first {run.failures[0]['name']}: {run.failures[0]['reason']}")
    feedback.info(f"{len(run.tiles)} tiles: {Path(run.dtm).name}, {Path(run.chm).name} in {out}")
    result = Result(values={"TILE_COUNT": len(run.tiles), "FAILED_TILES": len(run.failures)})
    result.files.update(OUTPUT_FOLDER=str(out), DTM=run.dtm, CHM=run.chm)
    return result


TERRAIN_TILES = Algorithm(
    id="terraintiles",
    name="Terrain and canopy over tiles",
    group="Terrain and canopy",
    group_id="terrain",
    summary=(
        "The terrain model (DTM) and canopy height model (CHM) of a whole survey: every tile is read with a "
        "buffer of its neighbours' points, noise-filtered, its ground classified where the file has none "
        "and its heights normalised as 'Forest from tiles' does, so the rasters join without seams at tile "
        "edges. Writes dtm/<tile>.tif and chm/<tile>.tif over each tile's own extent on a grid aligned on "
        "the pixel, and dtm.vrt and chm.vrt, virtual mosaics QGIS opens as one layer (the DTM can be the "
        "3D view's terrain). Tiles run in parallel processes or on a dask cluster; a tile that fails is "
        "reported and the run goes on. Optionally also writes every tile height-normalised."
    ),
    params=(
        tiles_input(),
        buffer_param(),
        RESOLUTION,
        Param("DTM_RESOLUTION_M", NUMBER, "DTM cell size (m)", default=1.0, minimum=0.1, maximum=100.0,
              help="Size of a terrain cell in metres (each cell: the ground triangulation under its points)."),
        PIT_FREE,
        Param("NORMALIZED_TILES", BOOLEAN, "Also write normalised tiles", default=False,
              help="normalized/<tile>.laz: every point of each tile with its height above the ground as Z "
                   "and its elevation in the extra dimension 'elevation' (as 'Normalise heights' writes one "
                   "file and lidR's normalize_height), the ground triangulated with the neighbours' buffer."),
        workers_param(),
        scheduler_param(),
        crs_override(),
        Param("OUTPUT_FOLDER", FOLDER_OUT, "Output folder",
              help="Receives dtm/, chm/, dtm.vrt and chm.vrt (and normalized/)."),
    ),
    run=run_tiles,
    results=(
        Param("TILE_COUNT", NUMBER_RESULT, "Number of tiles", help="Tiles whose rasters were written."),
        Param("FAILED_TILES", NUMBER_RESULT, "Failed tiles", help="Tiles that failed (named in the log)."),
        Param("DTM", STRING_RESULT, "Terrain model (dtm.vrt)", help="The path of dtm.vrt (CRS elevations)."),
        Param("CHM", STRING_RESULT, "Canopy height model (chm.vrt)", help="The path of chm.vrt (m above ground)."),
    ),
)

ALGORITHMS = (CANOPY_HEIGHT_MODEL, TERRAIN_TILES)
