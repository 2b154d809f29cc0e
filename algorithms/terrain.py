"""Canopy height model: sylva:canopyheightmodel."""
from __future__ import annotations

from ..core.progress import scaled
from .common import crs_override, drop_noise, input_cloud, load_cloud
from .spec import BOOLEAN, NUMBER, RASTER_OUT, Algorithm, Feedback, Param, Result


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
        Param("RESOLUTION_M", NUMBER, "Cell size (m)", default=0.5, minimum=0.05, maximum=100.0,
              help="Size of a CHM cell in metres. About half the typical point spacing or finer "
                   "gives sharp crowns; 0.5 m suits 5–20 points/m².",),
        Param("PIT_FREE", BOOLEAN, "Pit-free CHM", default=True,
              help="Build the CHM from stacked partial triangulations of first returns above "
                   "increasing heights (Khosravipour et al. 2014) instead of the highest point per cell."),
        crs_override(),
        Param("OUTPUT", RASTER_OUT, "Canopy height model", file_filter="GeoTIFF (*.tif *.tiff)",
              help="GeoTIFF of heights above ground in metres, in the tile's CRS; no-data outside the data."),
    ),
    run=run,
)
ALGORITHMS = (CANOPY_HEIGHT_MODEL,)
