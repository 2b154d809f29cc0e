"""One tile of a catalog run: read it with a buffer, segment, keep the trees it owns, write its parts.

:func:`process_tile` is the unit of work that :mod:`sylva.core.catalog` hands to
a process pool or a ``dask.distributed`` cluster.  It takes a picklable
:class:`TileJob` and returns a JSON-able dict; everything it writes goes into
the run's output folder under names derived from the tile, each file written
atomically, and the tile's manifest (``parts/<tile>.done.json``) last, so a
tile is either complete or redone.

Rules (the design of ARCHITECTURE.md, catalog.py; lidR's catalog engine):

* The tile is read whole; every neighbour whose header bounds meet the
  buffered box (tile bounds grown by ``buffer_m``) gives its points inside the
  box: memory is one tile plus its buffer.  They come from the neighbour's
  *halo* (``parts/halo/``: its points within ``buffer_m`` of its own edges,
  uncompressed, written by the first job that reads the neighbour's file — its
  own or another's) or, while no halo exists yet, from the neighbour's file
  streamed chunk by chunk (:func:`sylva.core.io.las.read_las_chunks`).  So a
  LAZ tile is decompressed about twice in a run, not once per neighbour
  (nine times on a grid).  Halos are keyed by the file's checksum, the buffer
  and the CRS, and are used only between tiles whose bounds do not overlap
  (only then is the part of a neighbour inside a buffer within its edge ring).
* Computation happens in a local frame whose origin is *snapped to a global
  grid* (:data:`ANCHOR_GRID_M`, a common multiple of the voxel, cell and window
  pitches used downstream), not at the tile's lower-left corner: voxels and
  grid cells then fall on the same places whatever the tiling, which is what
  makes the segmentation of a tree the same in a 3 x 3, a 6 x 6 and a single
  tile run.
* A tree belongs to the one tile whose *file* holds the point that is its top
  (tops are points of the cloud, :func:`sylva.core.tops.find_tree_tops`); an
  exactly duplicated top point in two files goes to the tile listed first.
  Tiles thus need not be a regular grid; overlaps and gaps are fine.
* Tree IDs come from the top's position (:func:`sylva.core.treeids.tree_ids`), so the same tree
  gets the same ID in any tiling, run order or worker count.
* Per-point ``treeID`` of a tile's own points is the label its buffered
  segmentation gives them, owned tree or not (IDs are global, so a border
  tree's points in two files carry one ID); per-tree outputs (trees, tops,
  crowns, crown/stem points, skeletons, models) are written by the owner tile
  from all the points its buffered segmentation gives the tree, wherever they lie.
"""
from __future__ import annotations

import hashlib
import json
import os
try:
    import resource
except ImportError:  # Windows
    resource = None
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Optional, Tuple

import numpy as np

from .cloud import ANCHOR_GRID_M, AnchoredCloud, PointCloud
from .errors import EmptyInputError, InputError, SylvaError
from .geometry import DEFAULT_LOD
from .segment import NormalizedCut
from .treeids import grid_keys, tree_ids

@dataclass(frozen=True)
class PipelineOptions:
    """Parameters of the per-tile job (one value per run; part of the resume key).

    ``buffer_m``: width of the neighbours' ring read around each tile (wider than
    the widest crown).  ``segmentation``: a method value of
    :func:`sylva.core.segment.segment_trees` (default Hu et al. 2017 §4.1
    normalised cut); its tree-top search (window, window points, apex rule,
    minimum height) is a field of the method, as in ``sylva:segmenttrees``:
    both run :func:`sylva.core.segment.tile.segment_tile`.  ``ground_cell_m``: ground points are reduced to the lowest
    per cell of this size before the TIN of heights (a fine DTM; 0 keeps all).  ``reconstruct``: model every owned tree (skeletons, GLB, 3D
    Tiles) with ``reconstruction`` (default :class:`sylva.core.reconstruct.Hybrid`),
    ``lod`` and ``leaves``; ``billboards`` also builds each tree's billboard (Zhou et al.,
    :mod:`sylva.core.reconstruct.billboard`), the tileset's far level of detail.  ``id_bits``: bits of the position-derived tree ID
    (31 for the int32 ``treeID``; smaller only to test collision handling).  ``chunk_size_m``: files
    wider than this are cut into square chunks of this size, each a tile of the run
    (:mod:`sylva.core.io.chunks`; 0: one tile per file).
    """

    buffer_m: float = 15.0
    segmentation: Any = NormalizedCut()
    ground_cell_m: float = 0.5
    hull: str = "convex"
    crown_base_gap_m: float = 1.5
    reconstruct: bool = True
    reconstruction: Any = None
    lod: int = DEFAULT_LOD
    leaves: str = "auto"
    billboards: bool = False
    chunk_size: int = 1_000_000
    id_bits: int = 31
    crs: Optional[str] = None
    chunk_size_m: float = 0.0

    def key(self) -> str:
        """A digest of every parameter (what a resumed run must match)."""
        return hashlib.sha256(repr(self).encode("utf-8")).hexdigest()[:16]


@dataclass(frozen=True)
class TileJob:
    """Everything one tile's job needs; plain data, cheap to pickle."""

    index: int
    name: str
    path: str
    bounds: Tuple[float, float, float, float]            # xmin, ymin, xmax, ymax (CRS units)
    neighbours: Tuple[Tuple[int, str, Tuple[float, float, float, float], str], ...]  # index, path, bounds, checksum
    out_dir: str
    options: PipelineOptions = field(default_factory=PipelineOptions)
    checksum: str = ""                                   # of this tile + neighbours + options
    attempt: int = 1
    file_checksum: str = ""                              # of this tile's file alone (names its halo)


# --------------------------------------------------------------------------- reading

def _box_hits(bounds, box) -> bool:
    return not (bounds[2] < box[0] or bounds[0] > box[2] or bounds[3] < box[1] or bounds[1] > box[3])


def _concat(clouds, anchor) -> AnchoredCloud:
    names = set(clouds[0].attrs)
    for c in clouds[1:]:
        names &= set(c.attrs)
    first = clouds[0]
    attrs = {n: np.concatenate([np.asarray(c.attrs[n]) for c in clouds]) for n in first.attrs if n in names}
    return AnchoredCloud(xyz=np.concatenate([c.xyz for c in clouds]), attrs=attrs, crs=first.crs,
                         units=first.units, source=first.source, template=None, anchor=anchor)


def _overlap(a, b) -> bool:
    """True when two bounds share interior area (touching edges do not count)."""
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def halo_path(out_dir, file_checksum: str, options) -> Path:
    """Where the halo of the tile whose file has ``file_checksum`` is kept for ``options``."""
    key = hashlib.sha256(f"{file_checksum}|{options.buffer_m!r}|{options.crs!r}".encode()).hexdigest()[:20]
    return Path(out_dir) / "parts" / "halo" / f"{key}.npz"


def _halo_mask(cloud: PointCloud, bounds, pad: float) -> np.ndarray:
    x, y = cloud.xyz[:, 0], cloud.xyz[:, 1]
    return ~((x > bounds[0] + pad) & (x < bounds[2] - pad) & (y > bounds[1] + pad) & (y < bounds[3] - pad))


def write_halo(path: Path, clouds) -> None:
    """Save the edge-ring points ``clouds`` (PointClouds of one file) atomically as an uncompressed .npz."""
    from .atomic import atomic_save_npz

    clouds = [c for c in clouds if len(c)]
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {"xyz": np.concatenate([c.xyz for c in clouds]) if clouds else np.zeros((0, 3))}
    for name in (clouds[0].attrs if clouds else ()):
        arrays[f"attr:{name}"] = np.concatenate([np.asarray(c.attrs[name]) for c in clouds])
    atomic_save_npz(path, **arrays)


def read_halo(path: Path, like: PointCloud) -> Optional[PointCloud]:
    """The halo at ``path`` as a PointCloud in ``like``'s CRS and units, or None if it is absent or unreadable."""
    try:
        with np.load(path) as z:
            xyz = z["xyz"]
            attrs = {k[5:]: z[k] for k in z.files if k.startswith("attr:")}
    except (OSError, ValueError, KeyError):
        return None
    return PointCloud(xyz=xyz, attrs=attrs, crs=like.crs, units=like.units, source=str(path))


def read_buffered(job: TileJob, progress=None, cancelled=None):
    """(own cloud as read, buffered AnchoredCloud with int32 attr ``_tile``, warnings).

    The buffered cloud starts with the tile's own points, in file order.
    Unreadable neighbours are left out with a warning (their own job reports them).
    Writes the halos of the files it reads whole (see the module docstring).
    """
    from .io.las import read_las, read_las_chunks
    from .progress import check

    opts = job.options
    own = read_las(job.path, crs=opts.crs)
    if own.crs is None:
        raise InputError(f"{job.path}: the file has no coordinate reference system; set the CRS parameter")
    pad = opts.buffer_m / own.units.horizontal_m
    xmin, ymin, xmax, ymax = job.bounds
    box = (xmin - pad, ymin - pad, xmax + pad, ymax + pad)
    grid = ANCHOR_GRID_M / own.units.horizontal_m
    anchor = np.array([np.floor(box[0] / grid) * grid, np.floor(box[1] / grid) * grid, 0.0])
    if job.file_checksum:
        mine = halo_path(job.out_dir, job.file_checksum, opts)
        if not mine.exists():
            write_halo(mine, [own.subset(_halo_mask(own, job.bounds, pad))])
    parts = [own]
    tiles = [np.full(len(own), job.index, dtype=np.int32)]
    warnings = []

    def keep(chunk, index):
        x, y = chunk.xyz[:, 0], chunk.xyz[:, 1]
        inside = (x >= box[0]) & (x <= box[2]) & (y >= box[1]) & (y <= box[3])
        if inside.any():
            sub = chunk.subset(inside)
            parts.append(replace(sub, template=None))
            tiles.append(np.full(len(sub), index, dtype=np.int32))

    for index, path, bounds, checksum in job.neighbours:
        check(cancelled)
        if not _box_hits(bounds, box):
            continue
        halo = halo_path(job.out_dir, checksum, opts) if checksum and not _overlap(bounds, job.bounds) else None
        cached = read_halo(halo, own) if halo is not None and halo.exists() else None
        if cached is not None:
            keep(cached, index)
            continue
        try:
            ring = []
            for chunk in read_las_chunks(path, opts.chunk_size, crs=opts.crs or own.crs):
                keep(chunk, index)
                if halo is not None:
                    ring.append(replace(chunk.subset(_halo_mask(chunk, bounds, pad)), template=None))
            if halo is not None:
                write_halo(halo, ring)
            del ring
        except SylvaError as err:
            warnings.append(f"neighbour {Path(path).name} left out of the buffer: {err}")
    cloud = _concat(parts, anchor)
    cloud = cloud.with_attrs(_tile=np.concatenate(tiles))
    return own, cloud, warnings


# --------------------------------------------------------------------------- the job

def _reset_peak_rss() -> bool:
    """Reset this process's peak-RSS mark (Linux >= 4.0), so that a tile's peak is its own.

    ``ru_maxrss`` would not do: it survives fork and exec, so a worker would report
    the peak of whatever process started it.
    """
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def _peak_rss_mb() -> float:
    """Peak resident memory (MB) since :func:`_reset_peak_rss` (VmHWM), else the process's ru_maxrss."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    if resource is None:
        return float("nan")
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def part_paths(out_dir, name: str) -> dict:
    out = Path(out_dir)
    return {
        "las": out / "tiles" / f"{name}.laz",
        "gpkg": out / "parts" / f"{name}.gpkg",
        "ids": out / "parts" / f"{name}.ids.npz",
        "glb": out / "models" / f"{name}.glb",
        "tileset": out / "models" / "tileset" / name,
        "manifest": out / "parts" / f"{name}.done.json",
        "dtm": out / "dtm" / f"{name}.tif",
        "chm": out / "chm" / f"{name}.tif",
    }


#: Pixel of the run's terrain and canopy rasters (metres): dtm/<tile>.tif and chm/<tile>.tif, joined in
#: dtm.vrt and chm.vrt (the DTM is what QGIS's 3D view can use as its terrain).
DTM_PIXEL_M = 1.0
CHM_PIXEL_M = 0.5
#: Further points (metres) around a tile for a pit-free CHM: twice the freeze distance (max_edge_m 1.5 of
#: :func:`sylva.core.terrain.canopy_height_model`), so the triangles over the tile's cells are those of the
#: whole survey (measured: the sample cut into 2 x 2 tiles gives the CHM of the whole, cell for cell).
PIT_FREE_PAD_M = 3.0


def _fill_gaps(grid: np.ndarray, passes: int = 2) -> np.ndarray:
    """Empty cells (between scan lines) take the highest of their 3 x 3 neighbours, ``passes`` times."""
    from scipy import ndimage

    out = grid.copy()
    for _ in range(passes):
        empty = np.isnan(out)
        if not empty.any():
            break
        high = ndimage.maximum_filter(np.where(empty, -np.inf, out), size=3, mode="nearest")
        fill = empty & np.isfinite(high)
        out[fill] = high[fill]
    return out


def write_tile_rasters(work: PointCloud, job: TileJob, paths: dict, dtm_pixel_m: float = DTM_PIXEL_M,
                       chm_pixel_m: float = CHM_PIXEL_M, pit_free: bool = False) -> dict:
    """The tile's DTM (CRS vertical units, like the models' z) and CHM (metres above ground) GeoTIFFs
    over its own bounds, from its buffered, normalised cloud (Sylva, not in a paper).

    The DTM is the ground surface that gave the heights (the TIN of
    :func:`sylva.core.terrain.normalize`): each point's ``z - height`` averaged
    per cell (the TIN is linear within a cell, so this is its value there to a
    few cm; no second triangulation), cells without points filled from the
    nearest one, on a grid aligned on multiples of the pixel, so neighbouring
    tiles abut; the CHM is the highest first return per cell
    (:func:`sylva.core.terrain.canopy_height_model`; ``pit_free`` False by default: it is cheap)
    pasted on the same kind of grid, its empty cells given the highest of their
    neighbours twice (:func:`_fill_gaps`).  Returns {"dtm": path, "chm": path}.
    """
    from scipy import ndimage

    from .raster import aligned_raster, paste, write_geotiff
    from .terrain import canopy_height_model

    hm, vm = work.units.horizontal_m, work.units.vertical_m
    pad = (2 * max(chm_pixel_m, dtm_pixel_m / 2) + (PIT_FREE_PAD_M if pit_free else 0.0)) / hm
    xmin, ymin, xmax, ymax = job.bounds
    near = ((work.xyz[:, 0] >= xmin - pad) & (work.xyz[:, 0] <= xmax + pad)
            & (work.xyz[:, 1] >= ymin - pad) & (work.xyz[:, 1] <= ymax + pad))
    # DTM: every point's ground elevation (z minus its height: the TIN under it) averaged per cell, which
    # is the TIN at the cell (linear within it); cells without points take their nearest cell's value.
    dtm = aligned_raster(job.bounds, dtm_pixel_m / hm, work.crs)
    xyz = work.xyz[near]
    ground = xyz[:, 2] - np.asarray(work.attrs["height"], dtype=np.float64)[near] / vm
    row, col = dtm.index_of(xyz[:, 0], xyz[:, 1])
    inside = dtm.inside(row, col)
    if inside.any():
        cell = row[inside] * dtm.cols + col[inside]
        total = np.bincount(cell, ground[inside], minlength=dtm.rows * dtm.cols)
        count = np.bincount(cell, minlength=dtm.rows * dtm.cols)
        mean = np.where(count > 0, total / np.maximum(count, 1), np.nan).reshape(dtm.shape)
        empty = np.isnan(mean)
        if empty.any():
            _, (ri, ci) = ndimage.distance_transform_edt(empty, return_indices=True)
            mean = mean[ri, ci]
        dtm.data[:] = mean
    chm = aligned_raster(job.bounds, chm_pixel_m / hm, work.crs)
    if near.any():
        try:
            paste(chm, canopy_height_model(work.subset(near), chm_pixel_m, pit_free=pit_free))
        except EmptyInputError:  # no first return near the tile: its CHM stays no data
            pass
        chm.data[:] = _fill_gaps(chm.data)
    out = {}
    for name, raster in (("dtm", dtm), ("chm", chm)):
        paths[name].parent.mkdir(parents=True, exist_ok=True)
        out[name] = str(write_geotiff(paths[name], raster))
    return out


def _top_tiles(cloud: AnchoredCloud, tops, min_height_m: float) -> np.ndarray:
    """For each top, the index of the tile whose file holds its point (lowest index on exact ties)."""
    from scipy.spatial import cKDTree

    src = np.asarray(cloud.attrs["_tile"])
    high = np.flatnonzero(np.asarray(cloud.attrs["height"]) >= min_height_m - 1e-9)
    tree = cKDTree(tops.xyz)
    d, j = tree.query(cloud.xyz[high], distance_upper_bound=1e-7)
    hit = np.isfinite(d)
    owner = np.full(len(tops), np.iinfo(np.int32).max, dtype=np.int64)
    np.minimum.at(owner, j[hit], src[high[hit]])
    return owner


def process_tile(job: TileJob, progress=None, cancelled=None) -> dict:
    """Segment (and model) one tile with its buffer; write its parts; return its record.

    The record (JSON-able): name, index, status "done", points (own),
    buffer_points, trees (owned), seconds, points_per_s, peak_rss_mb, pid,
    warnings, files.  Raises :class:`SylvaError` (or anything) on failure; the
    catalog retries once and reports.
    """
    from .atomic import atomic_save_npz, atomic_write_bytes
    from .io.gpkg import write_gpkg
    from .io.las import write_las
    from .measure import CrownBase, tree_metrics
    from .progress import check, report, scaled
    from .segment.tile import segment_tile
    from .table import VectorTable, point_layer

    from .jit import compile_seconds

    t0 = time.perf_counter()
    c0 = compile_seconds()
    _reset_peak_rss()
    opts = job.options
    paths = part_paths(job.out_dir, job.name)
    for p in ("las", "gpkg", "glb"):
        paths[p].parent.mkdir(parents=True, exist_ok=True)
    report(progress, 0.0, f"{job.name}: reading with a {opts.buffer_m:g} m buffer")
    own, cloud, warnings = read_buffered(job, progress, cancelled)
    n_own = len(own)
    check(cancelled)
    # the one segmentation chain (segmenttrees runs it too); triangles wider than the
    # buffer allows would make heights depend on the tiling
    report(progress, 0.1, f"{job.name}: segmenting {len(cloud):,} points")
    seg = segment_tile(cloud, opts.segmentation, ground_cell_m=opts.ground_cell_m,
                       tin_radius_m=opts.buffer_m / 2, cancelled=cancelled,
                       progress=scaled(progress, 0.1, 0.55))
    work, tops = seg.cloud, seg.tops
    kept_idx = np.flatnonzero(seg.keep)
    rasters = write_tile_rasters(work, job, paths)
    keys = grid_keys(tops.xyz[:, :2], work.units.horizontal_m)
    gids = tree_ids(keys, opts.id_bits)
    owner = _top_tiles(work, tops, float(tops.height.min(initial=0.0)))
    owned = owner == job.index
    # the method's labels -> 1..k in the order of the tops
    seq = np.zeros(int(seg.labels.max(initial=0)) + 1, dtype=np.int64)
    seq[tops.tree_id] = np.arange(1, len(tops) + 1)
    labels = seq[seg.labels]
    to_gid = np.concatenate([[0], gids]).astype(np.int64)
    glabels = to_gid[labels]
    owned_gid = np.concatenate([[False], owned])
    mine = owned_gid[labels]
    own_labels = np.where(mine, glabels, 0)
    check(cancelled)
    # the tile's own points with the treeID of their buffered segmentation
    tree_id = np.zeros(n_own, dtype=np.int32)
    in_own = kept_idx < n_own
    tree_id[kept_idx[in_own]] = glabels[in_own]
    write_las(paths["las"], own, extra={"treeID": tree_id}, cancelled=cancelled)
    present = np.unique(glabels[in_own])
    present = present[present > 0]
    del own
    report(progress, 0.6, f"{job.name}: measuring {int(owned.sum())} trees")
    m = tree_metrics(work, own_labels, hull=opts.hull, crown_base=CrownBase(gap_m=opts.crown_base_gap_m))
    crs = work.crs
    columns = m.columns()
    columns["tile"] = np.array([job.name] * len(m), dtype=object)
    tables = []
    skeletons = models_3d = None
    files = {"las": str(paths["las"]), "gpkg": str(paths["gpkg"]), **rasters}
    if opts.reconstruct and len(m):
        report(progress, 0.7, f"{job.name}: modelling {len(m)} trees")
        from .export.gltf import write_glb
        from .export.gpkg3d import models_table
        from .export.model import ExportFrame, TreeModel
        from .export.tiles3d import write_tileset
        from .forest import ModelOptions, model_trees, skeleton_table
        from .reconstruct import Hybrid

        method = opts.reconstruction if opts.reconstruction is not None else Hybrid()
        trees = model_trees(work, own_labels, m, ModelOptions(method=method, lod=opts.lod, leaves=opts.leaves),
                            cancelled=cancelled)
        for key in trees[0].record:
            if key != "tree_id":
                columns[key] = np.array([t.record[key] for t in trees])
        columns["model_file"] = np.array([paths["glb"].name] * len(trees), dtype=object)
        boards = _billboards(work, own_labels, trees) if opts.billboards else [None] * len(trees)
        models = [TreeModel(t.tree_id, np.array([t.record["base_x"], t.record["base_y"], t.record["base_z"]]),
                            t.wood, t.leaves, {k: columns[k][i] for k in columns}, billboard=boards[i])
                  for i, t in enumerate(trees)]
        frame = ExportFrame.from_cloud(work)
        encoded = {}   # meshes encoded and checked once for the tile's GLB, its tileset and its 3D layer
        write_glb(models, paths["glb"], frame, cancelled=cancelled, cache=encoded)
        tileset_dir = paths["tileset"]
        tileset_dir.parent.mkdir(parents=True, exist_ok=True)
        write_tileset(models, tileset_dir, frame, cancelled=cancelled, cache=encoded)
        files["glb"] = str(paths["glb"])
        files["tileset"] = str(tileset_dir / "tileset.json")
        skeletons = skeleton_table(trees, work, crs)
        models_3d = models_table(models, frame, cache=encoded)   # the QGIS-native 3D layer
        del models, trees, encoded
    crowns_3d = None
    if len(m):   # the 3D crown envelopes (core/export/crowns3d.py), standing on the models' bases when there are models
        from .export.crowns3d import crowns_table, point_crowns

        base_z = np.asarray(columns.get("base_z", m.ground_z), dtype=np.float64)
        origins = np.column_stack([m.x, m.y, base_z])
        scale = np.array([work.units.horizontal_m, work.units.horizontal_m, work.units.vertical_m])
        crown_idx = np.flatnonzero((own_labels > 0) & ~m.is_stem)
        hulls = point_crowns(work.xyz[crown_idx], own_labels[crown_idx], m.tree_id, origins, scale,
                             np.column_stack([m.x, m.y, m.top_z]))
        crowns_3d = crowns_table(m.tree_id, hulls, origins, scale, base_z, crs, height=m.height)
    tables.append(VectorTable("trees", "none", None, columns, crs))
    tables.append(point_layer("tree_tops", np.column_stack([m.x, m.y, m.top_z]),
                              {"tree_id": m.tree_id, "height": m.height}, crs))
    tables.append(VectorTable("crowns", "polygon", m.crowns,
                              {"tree_id": m.tree_id, "height": m.height, "top_z": m.top_z,
                               "crown_area": m.crown_area, "crown_diameter": m.crown_diameter}, crs, has_z=False))
    height = work.attrs["height"]
    for layer, mask in (("crown_points", (own_labels > 0) & ~m.is_stem), ("stem_points", m.is_stem)):
        idx = np.flatnonzero(mask)
        tables.append(point_layer(layer, work.xyz[idx],
                                  {"tree_id": own_labels[idx].astype(np.int64), "height": height[idx]}, crs))
    if skeletons is not None:
        tables.append(skeletons)
    if models_3d is not None:
        tables.append(models_3d)
    if crowns_3d is not None:
        tables.append(crowns_3d)
    write_gpkg(paths["gpkg"], tables)
    # IDs written (for the run-wide collision check): owned trees and every ID in the LAS
    seen = np.isin(gids, present) | owned
    atomic_save_npz(paths["ids"], owned_keys=keys[owned], owned_ids=gids[owned], seen_keys=keys[seen],
                    seen_ids=gids[seen])
    seconds = time.perf_counter() - t0
    record = {
        "name": job.name, "index": job.index, "path": job.path, "status": "done", "attempts": job.attempt,
        "points": int(n_own), "buffer_points": int(len(cloud) - n_own), "trees": int(len(m)), "tops": int(owned.sum()),
        "seconds": round(seconds, 3), "points_per_s": round(n_own / max(seconds, 1e-9), 1),
        "compile_seconds": round(compile_seconds() - c0, 3),   # numba compilations (first run after install)
        "peak_rss_mb": round(_peak_rss_mb(), 1), "pid": os.getpid(), "warnings": warnings,
        "files": files, "checksum": job.checksum,
    }
    atomic_write_bytes(paths["manifest"], (json.dumps(record, indent=1) + "\n").encode("utf-8"))
    report(progress, 1.0, f"{job.name}: {record['trees']} trees")
    return record


def _billboards(cloud: PointCloud, labels: np.ndarray, trees) -> list:
    """The billboard of every modelled tree, in the frame of its wood mesh (origin at its base)."""
    from .forest import tree_points
    from .reconstruct.billboard import Billboard, billboard_tree

    rgb = None
    if all(cloud.attr(c) is not None for c in ("red", "green", "blue")):
        rgb = np.column_stack([cloud.attrs[c] for c in ("red", "green", "blue")])
    local = cloud.local_xyz()
    height = np.asarray(cloud.attrs["height"], dtype=np.float64)
    ids, groups = tree_points(labels)
    points_of = dict(zip(ids.tolist(), groups))
    out = []
    for t in trees:
        idx = points_of[t.tree_id]
        out.append(billboard_tree(local[idx], Billboard(), rgb=None if rgb is None else rgb[idx], base=t.base_local,
                                  ground_z=float(np.median(local[idx, 2] - height[idx])), tree_id=t.tree_id,
                                  stem_diameter_m=t.record["dbh"]))
    return out


def is_complete(job: TileJob) -> Optional[dict]:
    """The tile's manifest record when its outputs are complete for this job's inputs and options."""
    paths = part_paths(job.out_dir, job.name)
    try:
        record = json.loads(paths["manifest"].read_text("utf-8"))
    except (OSError, ValueError):
        return None
    if record.get("checksum") != job.checksum or record.get("status") != "done":
        return None
    if not all(Path(f).exists() for f in record.get("files", {}).values()) or not paths["ids"].exists():
        return None
    return record
