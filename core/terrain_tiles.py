"""Terrain and canopy rasters over a folder of tiles: each tile with a buffer, one DTM and CHM per tile.

    run = run_terrain_tiles(["tiles/"], "out/", TerrainOptions(chm_pixel_m=0.5), workers=2)

The same engine as the forest run (:func:`sylva.core.engine.apply`, in this
process, a process pool or on dask) and the same buffered reading
(:func:`sylva.core.pipeline.read_buffered`: the neighbours' points within
``buffer_m``), so heights near a tile's edge are those of the whole survey, not
of a triangulation cut at the edge.  Each tile is noise-filtered and
height-normalised as the forest run does (SMRF ground where the file has none,
the TIN of the lowest ground point per ``ground_cell_m``, triangles no longer
than half the buffer), and its rasters cover its own bounds on a grid aligned on
multiples of the pixel, so neighbouring tiles abut
(:func:`sylva.core.pipeline.write_tile_rasters`).  lidR's LAScatalog runs
``rasterize_terrain`` / ``rasterize_canopy`` the same way (chunks with a buffer,
one raster each, a virtual mosaic).  Sylva, not in a paper.

Output folder::

    dtm/<tile>.tif, chm/<tile>.tif   per tile (DTM in the CRS's vertical units, CHM in metres)
    dtm.vrt, chm.vrt                 GDAL virtual mosaics of them
    normalized/<tile>.laz            with ``normalized``: the tile's points, z = height above ground
                                     (extra dimension ``elevation``: the source z), as sylva:normalizeheight
                                     and lidR's normalize_height write a file, here with the buffer's ground
"""
from __future__ import annotations

import hashlib
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional

from .engine import apply
from .errors import Cancelled, InputError
from .progress import CancelCheck, Progress, check, report


@dataclass(frozen=True)
class TerrainOptions:
    """``buffer_m`` neighbours' ring read around each tile; ``ground_cell_m`` ground points are thinned
    to the lowest per cell of this size before the TIN; ``dtm_pixel_m`` / ``chm_pixel_m`` the rasters'
    pixels (metres); ``pit_free`` the Khosravipour et al. (2014) CHM instead of the highest first return
    per cell; ``normalized`` also writes each tile's points with z = height above ground; ``crs``
    overrides the files' CRS; ``chunk_size`` points read at a time from a neighbour."""

    buffer_m: float = 15.0
    ground_cell_m: float = 0.5
    dtm_pixel_m: float = 1.0
    chm_pixel_m: float = 0.5
    pit_free: bool = True
    normalized: bool = False
    crs: Optional[str] = None
    chunk_size: int = 1_000_000

    def key(self) -> str:
        return hashlib.sha256(repr(self).encode("utf-8")).hexdigest()[:16]


@dataclass
class TerrainRun:
    """What :func:`run_terrain_tiles` made: per-tile records, failures (name, path, reason) and mosaics."""

    tiles: List[dict] = field(default_factory=list)
    failures: List[dict] = field(default_factory=list)
    dtm: Optional[str] = None
    chm: Optional[str] = None


def terrain_tile(job, progress: Progress = None, cancelled: CancelCheck = None) -> dict:
    """One tile's DTM and CHM GeoTIFFs from its buffered, normalised points; its record."""
    from .noise import noise_mask
    from .pipeline import part_paths, read_buffered, write_tile_rasters
    from .terrain import SMRF, normalize

    opts = job.options
    report(progress, 0.0, f"{job.name}: reading with a {opts.buffer_m:g} m buffer")
    own, cloud, warnings = read_buffered(job, progress, cancelled)
    check(cancelled)
    report(progress, 0.4, f"{job.name}: height above ground")
    noise = noise_mask(cloud)
    work = normalize(cloud.subset(~noise), classify=SMRF(), cell_m=opts.ground_cell_m,
                     tin_radius_m=opts.buffer_m / 2)
    check(cancelled)
    report(progress, 0.7, f"{job.name}: rasters")
    files = write_tile_rasters(work, job, part_paths(job.out_dir, job.name), dtm_pixel_m=opts.dtm_pixel_m,
                               chm_pixel_m=opts.chm_pixel_m, pit_free=opts.pit_free)
    if opts.normalized:
        check(cancelled)
        report(progress, 0.85, f"{job.name}: normalised points")
        files["normalized"] = str(_write_normalized(own, cloud, noise, work, job))
    return {"name": job.name, "points": int(len(own)), "buffer_points": int(len(cloud) - len(own)),
            "warnings": warnings, "files": files}


def _write_normalized(own, cloud, noise, work, job) -> Path:
    """normalized/<tile>.laz: the tile's own points (file order, noise too) with z = height above the ground
    of its buffered cloud (the ground points ``work`` found, noise never among them)."""
    import numpy as np

    from .io.las import write_las
    from .terrain import GROUND_CLASS, ground_mask, height_above_ground, height_as_z

    opts, n = job.options, len(own)
    ground = np.zeros(len(cloud), dtype=bool)
    ground[np.flatnonzero(~noise)[ground_mask(work)]] = True
    if ground.any():
        height = height_above_ground(cloud, ground=ground, cell_m=opts.ground_cell_m,
                                     tin_radius_m=opts.buffer_m / 2)[:n]
    else:                                   # an already normalised tile: its z is the height
        height = own.xyz[:, 2] * own.units.vertical_m
    cls = own.attr("classification")
    cls = np.ones(n, dtype=np.uint8) if cls is None else np.array(cls, copy=True)
    cls[ground[:n]] = GROUND_CLASS
    out, extra = height_as_z(own.with_attrs(classification=cls), height, own.xyz[:, 2])
    path = Path(job.out_dir) / "normalized" / f"{job.name}.laz"
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_las(path, out, extra=extra)


def run_terrain_tiles(inputs, out_dir, options: TerrainOptions = TerrainOptions(), workers: int = 1,
                      scheduler=None, progress: Progress = None, cancelled: CancelCheck = None) -> TerrainRun:
    """DTM and CHM of every tile of ``inputs`` (LAS/LAZ files, folders of them, ``.vpc``) into ``out_dir``.

    A tile that fails is reported (name and reason) and the run goes on; a tile's rasters are written
    under temporary names and renamed, so none is ever half-written."""
    from .catalog import failure_record, make_jobs
    from .io.tiles import list_tiles
    from .raster import write_vrt

    out = Path(out_dir)
    report(progress, 0.0, "reading tile headers")
    tiles, failures = list_tiles(inputs, crs=options.crs)
    if not tiles:
        raise InputError("no readable tile: " + "; ".join(f["reason"] for f in failures))
    jobs = make_jobs(tiles, out, options)
    run = TerrainRun(failures=list(failures))
    done = {}

    def on_done(job, record, err):
        if err is not None:
            if isinstance(err, Cancelled):
                raise err
            run.failures.append(failure_record(job, err, out))
        else:
            done[job.name] = record
        report(progress, 0.95 * (len(done) + len(run.failures) - len(failures)) / len(jobs),
               f"{len(done)} of {len(jobs)} tiles")
        return None

    try:
        apply(jobs, terrain_tile, on_done, workers=workers, scheduler=scheduler, cancelled=cancelled,
              progress_of=lambda job: (lambda f, m="": report(progress, 0.95 * (len(done) + f) / len(jobs), m)))
    finally:
        shutil.rmtree(out / "parts", ignore_errors=True)   # the halos: scratch of the buffered reads
    check(cancelled)
    run.tiles = [done[j.name] for j in jobs if j.name in done]
    for kind in ("dtm", "chm"):
        tiffs = [r["files"][kind] for r in run.tiles]
        if tiffs:
            setattr(run, kind, str(write_vrt(out / f"{kind}.vrt", tiffs)))
    report(progress, 1.0, f"{len(run.tiles)} tiles")
    return run


__all__ = ["TerrainOptions", "TerrainRun", "run_terrain_tiles", "terrain_tile"]
