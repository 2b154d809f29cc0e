"""From a folder of tiles to a forest: tiles + buffers, tree ownership, stable IDs, parallel runs.

    report = run_catalog(["tiles/"], "out/", PipelineOptions(), workers=2)

Inputs: LAS/LAZ files, folders of them, or QGIS virtual point clouds (``.vpc``),
listed by :mod:`sylva.core.io.tiles`.  Each tile is processed by
:func:`sylva.core.pipeline.process_tile` with its neighbours' points within
``buffer_m`` (see that module for the ownership and ID rules), run by
:func:`sylva.core.engine.apply` here, in a local process pool (``workers``) or
on a ``dask.distributed`` scheduler (``scheduler`` address); the tiles'
layers are merged by :mod:`sylva.core.io.gpkg_merge` while they run.  A tile that fails is retried once, then reported;
the run goes on.  A rerun skips every tile whose manifest matches its inputs
(checksums of the tile and its neighbours) and the parameters.

Output folder::

    forest.gpkg            trees, tree_tops, crowns, crown_points, stem_points, skeletons, models_3d, crowns_3d
    tiles/<tile>.laz       every input tile with an int32 treeID (0 = no tree)
    models/<tile>.glb      the tile's owned trees, a node per tree
    models/tileset.json    one 3D Tiles 1.1 tileset for the run (external tilesets per tile)
    report.json, report.txt
    parts/                 per-tile parts and manifests (what a resumed run reuses)

Tree-ID collisions: IDs are 31-bit hashes of the top's position
(:func:`sylva.core.treeids.tree_ids`); each tile resolves the collisions among
the tops it sees, and :func:`run_catalog` re-runs the same deterministic rule
over the whole run's trees and rewrites the ``treeID`` of any tile (and the
merged layers) whose local choice differs — so IDs depend only on the set of
trees, never on tiling, order or workers.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import sqlite3
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

import numpy as np

from .atomic import atomic_save_npz, atomic_write_bytes
from .engine import apply
from .errors import Cancelled, InputError, OutputError, ParameterError, SylvaError, disk_error
from .export.tiles3d import write_root_tileset
from .io.gpkg_merge import OrderedMerge
from .io.chunks import chunk_tiles
from .io.tiles import Tile, file_checksum, list_tiles
from .pipeline import PipelineOptions, TileJob, is_complete, part_paths, process_tile
from .progress import CancelCheck, Progress, check, report
from .treeids import run_wide_remaps, unowned_trees


def make_jobs(tiles: Sequence[Tile], out_dir, options: PipelineOptions) -> List[TileJob]:
    """One :class:`TileJob` per tile, with its neighbours (bounds within ``buffer_m``) and resume checksum."""
    sums = {t.path: file_checksum(t.path) for t in tiles}
    jobs = []
    for i, t in enumerate(tiles):
        pad = options.buffer_m / t.metres_per_unit
        box = (t.bounds[0] - pad, t.bounds[1] - pad, t.bounds[2] + pad, t.bounds[3] + pad)
        neighbours = tuple((j, u.path, u.bounds, sums[u.path]) for j, u in enumerate(tiles)
                           if j != i and not (u.bounds[2] < box[0] or u.bounds[0] > box[2]
                                              or u.bounds[3] < box[1] or u.bounds[1] > box[3]))
        key = hashlib.sha256("|".join([options.key(), sums[t.path]] +
                                      [f"{Path(p).name}:{sums[p]}" for _, p, _, _ in neighbours]).encode()).hexdigest()[:24]
        jobs.append(TileJob(i, t.name, t.path, t.bounds, neighbours, str(out_dir), options, key,
                            file_checksum=sums[t.path]))
    return jobs


#: Free bytes below which a tile's write error is put down to a full disk (SQLite, for one, reports a
#: full disk met half-way through a page as "database disk image is malformed").
FULL_DISK_BYTES = 16 * 2**20


def failure_record(job: TileJob, err: BaseException, out: Path) -> dict:
    """A failed job's report row: name, path, status, a one-line reason (a full disk named as such), attempts."""
    if isinstance(err, SylvaError):
        reason = str(err)
    elif isinstance(err, OSError) and err.errno is not None:
        reason = str(disk_error(err.filename or out, err))
    else:
        reason = f"{type(err).__name__}: {err}"
        try:
            if shutil.disk_usage(out).free < FULL_DISK_BYTES:
                reason = f"{out}: cannot write (the disk is full): {reason}"
        except OSError:
            pass
    return {"name": job.name, "path": job.path, "status": "failed", "reason": reason, "attempts": job.attempt}


# --------------------------------------------------------------------------- tree IDs of the run

def _resolve_ids(records, out_dir, bits, complete: bool) -> Dict[str, dict]:
    """Per tile, the {old ID: new ID} its files need after run-wide collision resolution
    (``complete``: every tile of the run is done, see :func:`run_wide_remaps`)."""
    tiles = {}
    for r in records:
        z = np.load(part_paths(out_dir, r["name"])["ids"])
        tiles[r["name"]] = (z["owned_keys"], z["seen_keys"], z["seen_ids"])
    return run_wide_remaps(tiles, bits, complete)


def _remap_las(path, mapping: dict) -> int:
    """Rewrite the tile's ``treeID`` {old: new}; return how many points it left with no tree (new 0:
    their tree is owned by no tile, see :func:`run_wide_remaps`)."""
    from .io.las import read_las, tree_labels, write_las

    cloud = read_las(path)
    tid = tree_labels(cloud.attrs["treeID"])
    old = np.array(list(mapping), dtype=np.int64)
    new = np.array([mapping[k] for k in mapping], dtype=np.int64)
    order = np.argsort(old)
    pos = np.clip(np.searchsorted(old[order], tid), 0, len(old) - 1)
    hit = old[order][pos] == tid
    tid[hit] = new[order][pos[hit]]
    write_las(path, cloud.with_attrs(treeID=tid.astype(np.int32)))
    return int((hit & (tid == 0)).sum())



# --------------------------------------------------------------------------- the run

@dataclass
class RunReport:
    """What a run did: per-tile records, failures, totals (also written as report.json/.txt)."""

    tiles: List[dict]
    failures: List[dict]
    skipped: List[str]
    trees: int
    points: int
    seconds: float
    workers: int
    scheduler: Optional[str]
    peak_rss_mb_per_worker: Dict[str, float]
    id_collisions_rewritten: int
    gpkg: Optional[str]
    tileset: Optional[str]
    compile_seconds: float = 0.0   # of ``seconds``: compiling the numba kernels (a first run after installing)
    dtm: Optional[str] = None        # dtm.vrt: the tiles' terrain (CRS vertical units), QGIS's 3D terrain
    chm: Optional[str] = None        # chm.vrt: the tiles' canopy height model (m)
    unowned_edge_trees: int = 0    # segments across tile edges owned by no tile (treeids.run_wide_remaps)
    unowned_edge_points: int = 0   # their points in the tiles' LAS files, which carry no tree ID

    @property
    def points_per_s(self) -> float:
        return self.points / max(self.seconds, 1e-9)

    @property
    def work_seconds(self) -> float:
        """``seconds`` without the kernels' compilation: what later runs take."""
        return max(self.seconds - self.compile_seconds, 0.0)

    def as_dict(self) -> dict:
        d = dict(self.__dict__)
        d["points_per_s"] = round(self.points_per_s, 1)
        d["work_seconds"] = round(self.work_seconds, 3)
        d["work_points_per_s"] = round(self.points / max(self.work_seconds, 1e-9), 1)
        return d

    def summary(self) -> str:
        lines = [f"Sylva catalog run: {len(self.tiles)} tiles processed ({len(self.skipped)} reused from a "
                 f"previous run), {len(self.failures)} failed",
                 f"{self.trees:,} trees, {self.points:,} points in {self.seconds:.1f} s "
                 f"({self.points_per_s:,.0f} points/s) with "
                 + (f"dask scheduler {self.scheduler}" if self.scheduler else f"{self.workers} worker(s)"),
                 "peak memory per worker (MB): " + ", ".join(f"{k}: {v:.0f}" for k, v in
                                                           sorted(self.peak_rss_mb_per_worker.items()))]
        if self.compile_seconds >= 0.05:
            lines.insert(2, f"of which {self.compile_seconds:.1f} s compiling the numba kernels (once after installing "
                            f"or updating; cached for later runs): {self.work_seconds:.1f} s of work, "
                            f"{self.points / max(self.work_seconds, 1e-9):,.0f} points/s")
        if self.id_collisions_rewritten:
            lines.append(f"{self.id_collisions_rewritten} tile(s) rewritten to resolve tree-ID collisions")
        if self.unowned_edge_trees:
            lines.append(f"WARNING {self.unowned_edge_trees} segment(s) across tile edges owned by no tile (the "
                         f"neighbouring tiles segmented the edge differently): their {self.unowned_edge_points:,} "
                         f"points carry no tree ID (a wider BUFFER_M makes the tiles agree)")
        for f in self.failures:
            lines.append(f"FAILED {f['name']} ({f.get('attempts', 0)} attempt(s)): {f['reason']}")
        return "\n".join(lines) + "\n"


def _compile_seconds(done, skipped, c0: float) -> float:
    """Kernel compilation of the run: this process's (serial tiles, merge, tileset), plus the worker processes'
    as their tile records report it (the serial tiles' are already in this process's count)."""
    from .jit import compile_seconds

    here = compile_seconds() - c0
    pid = os.getpid()
    per_worker: Dict[Any, float] = {}
    for r in done:
        if r["name"] not in skipped and r.get("pid") != pid:
            per_worker[r.get("pid")] = per_worker.get(r.get("pid"), 0.0) + float(r.get("compile_seconds", 0.0))
    return here + max(per_worker.values(), default=0.0)   # workers compile side by side: the longest one


def _write_mosaics(out: Path, records) -> Dict[str, Optional[str]]:
    """dtm.vrt and chm.vrt of the tiles' rasters (tiles of a run made before Sylva wrote them have none)."""
    from .raster import write_vrt

    found = {}
    for kind in ("dtm", "chm"):
        tiffs = [r["files"][kind] for r in records if Path(r.get("files", {}).get(kind, "")).is_file()]
        found[kind] = str(write_vrt(out / f"{kind}.vrt", tiffs)) if tiffs else None
    return found


def run_catalog(inputs, out_dir, options: PipelineOptions = PipelineOptions(), workers: int = 1,
                scheduler=None, resume: bool = True, progress: Progress = None,
                cancelled: CancelCheck = None) -> RunReport:
    """Process every tile of ``inputs`` into ``out_dir`` (see the module docstring); returns the report.

    ``workers`` local processes (1 = in this process); ``scheduler`` a
    ``dask.distributed`` address (or Client), which then replaces the pool.
    ``resume`` skips tiles whose manifest matches.  Failed tiles are retried
    once and listed in the report; :class:`Cancelled` stops the run.
    """
    from .jit import compile_seconds

    t0 = time.perf_counter()
    c0 = compile_seconds()
    out = Path(out_dir)
    check_options(options)
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out}: the output folder is a file")
    if not out.parent.is_dir():
        raise InputError(f"{out}: the parent folder does not exist")
    try:
        out.mkdir(exist_ok=True)
        lock = RunLock(out)
    except OSError as err:
        raise disk_error(out, err) from None
    with lock:
        removed = remove_part_files(out)   # left by a killed run: we hold the folder now
        try:
            return _run(inputs, out, options, workers, scheduler, resume, progress, cancelled, t0, removed, c0)
        except OSError as err:
            raise disk_error(err.filename or out, err) from None
        except sqlite3.Error as err:
            raise OutputError(f"{out / 'forest.gpkg'}: merging the tiles' layers failed ({err})") from None
        finally:
            remove_part_files(out)   # a cancel or an error: what this run was writing


def check_options(options: PipelineOptions) -> None:
    """Refuse NaN, infinite or negative run parameters before any tile is read (:class:`ParameterError`)."""
    import math

    for name in ("buffer_m", "ground_cell_m", "crown_base_gap_m", "chunk_size_m"):
        value = getattr(options, name)
        try:
            ok = math.isfinite(float(value)) and float(value) >= 0
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise ParameterError(f"{name.upper()}={value}: must be a finite number of metres, 0 or more")


def remove_part_files(out: Path) -> int:
    """Remove every ``.part`` (temporary file of an atomic write) under the run folder ``out``."""
    n = 0
    for sub in (out, out / "tiles", out / "parts", out / "models"):
        if not sub.is_dir():
            continue
        for f in sub.rglob(".*.part") if sub != out else sub.glob(".*.part"):
            try:
                if f.is_file():
                    f.unlink()
                    n += 1
            except OSError:
                pass
    return n


class RunLock:
    """``out/.sylva-run.lock`` (pid, host, start time) held for a run's duration (Sylva, not in the papers).

    A second run into the same folder refuses, naming the first; the lock of a process that
    no longer exists (on this host) is stale and taken over.  Removed on release.
    """

    NAME = ".sylva-run.lock"

    def __init__(self, out: Path):
        import socket

        self.path = Path(out) / self.NAME
        self.me = {"pid": os.getpid(), "host": socket.gethostname(),
                   "started": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
        self.held = False

    def _holder(self) -> Optional[dict]:
        try:
            return json.loads(self.path.read_text("utf-8"))
        except (OSError, ValueError):
            return None

    @staticmethod
    def _alive(pid: int) -> bool:
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            return False
        except (PermissionError, ValueError, TypeError, OverflowError):
            return True
        return True

    def __enter__(self):
        import socket

        data = (json.dumps(self.me) + "\n").encode("utf-8")
        for _ in range(3):
            try:
                fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
            except FileExistsError:
                holder = self._holder()
                if holder is None:                      # being written right now, or garbage
                    time.sleep(0.2)
                    holder = self._holder()
                    if holder is None:
                        self.path.unlink(missing_ok=True)
                        continue
                if holder.get("host") == socket.gethostname() and not self._alive(holder.get("pid", -1)):
                    self.path.unlink(missing_ok=True)  # stale: its process is gone
                    continue
                raise OutputError(
                    f"{self.path.parent}: another Sylva run is writing into this folder (pid "
                    f"{holder.get('pid')} on {holder.get('host')}, started {holder.get('started')}); "
                    f"wait for it to end or choose another OUTPUT_FOLDER (if that run is gone, "
                    f"remove {self.path})")
            try:
                with os.fdopen(fd, "wb") as fh:
                    fh.write(data)
            except OSError as err:                      # a full disk: no empty lock stays behind
                self.path.unlink(missing_ok=True)
                raise disk_error(self.path, err) from None
            self.held = True
            return self
        raise OutputError(f"{self.path}: cannot take the run lock of this folder")

    def __exit__(self, *exc):
        if self.held and (self._holder() or {}).get("pid") == self.me["pid"]:
            self.path.unlink(missing_ok=True)
        self.held = False
        return False


def remove_tile_outputs(out: Path, name: str) -> None:
    """Remove a tile's files (LAZ, GLB, tileset, parts): a failed or foreign tile leaves nothing stale."""
    paths = part_paths(out, name)
    for key, path in paths.items():
        try:
            if path.is_dir():
                shutil.rmtree(path, ignore_errors=True)
            else:
                path.unlink(missing_ok=True)
        except OSError:
            pass


def _stale_names(out: Path, names: set) -> set:
    """Names of tiles whose outputs lie in ``out`` but which are not tiles of this run."""
    found = set()
    for folder, pattern in (("tiles", "*.laz"), ("models", "*.glb"), ("parts", "*.done.json")):
        for f in (out / folder).glob(pattern):
            stem = f.name[: -len(".done.json")] if pattern == "*.done.json" else f.stem
            if stem not in names and not f.name.startswith("."):
                found.add(stem)
    return found


def _run(inputs, out, options, workers, scheduler, resume, progress, cancelled, t0, removed_parts,
         c0: float = 0.0) -> RunReport:
    for sub in ("tiles", "parts", "models"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    if removed_parts:
        report(progress, 0.0, f"removed {removed_parts} temporary file(s) left by an interrupted run")
    report(progress, 0.0, "reading tile headers")
    tiles, failures = list_tiles(inputs, crs=options.crs)
    if not tiles:
        raise InputError("no readable tile: " + "; ".join(f["reason"] for f in failures))
    if options.chunk_size_m:
        report(progress, 0.0, f"cutting files wider than {options.chunk_size_m:g} m into chunks")
        tiles, uncut = chunk_tiles(tiles, out / "parts" / "chunks", options.chunk_size_m, options.crs, cancelled)
        failures += uncut
    # two runs into one folder never mix: outputs of tiles that are not this run's go
    for name in sorted(_stale_names(out, {t.name for t in tiles})):
        remove_tile_outputs(out, name)
    jobs = make_jobs(tiles, out, options)
    # Largest tiles first (longest-processing-time order): no big tile is left to run alone at the end.
    # forest.gpkg takes the tiles' rows in this order too (deterministic: sizes, then names).
    points = {t.name: t.points for t in tiles}
    order = sorted(jobs, key=lambda j: -points[j.name])
    with OrderedMerge(out / "forest.gpkg", [j.name for j in order]) as merger:
        records: Dict[str, dict] = {}
        skipped = []
        todo = []
        for job in order:
            rec = is_complete(job) if resume else None
            if rec is not None:
                records[job.name] = rec
                skipped.append(job.name)
                merger.ready(job.name, part_paths(out, job.name)["gpkg"])
            else:
                # an earlier run's manifest must not vouch for files this run is about to rewrite:
                # interrupted half-way, the tile would otherwise be "complete" with mixed files
                part_paths(out, job.name)["manifest"].unlink(missing_ok=True)
                todo.append(job)
        total = max(len(jobs), 1)
        state = {"done": len(skipped)}

        def on_done(job: TileJob, record, err):
            if err is not None:
                if isinstance(err, Cancelled):
                    raise err
                if job.attempt < 2:
                    return replace(job, attempt=job.attempt + 1)
                failures.append(failure_record(job, err, out))
                remove_tile_outputs(out, job.name)   # no stale LAZ/GLB of an earlier run stays beside the report
                merger.ready(job.name, None)
            else:
                records[job.name] = record
                merger.ready(job.name, part_paths(out, job.name)["gpkg"])
            state["done"] += 1
            report(progress, 0.9 * state["done"] / total, f"{state['done']} of {total} tiles")
            return None

        def tile_progress(job):
            return lambda f, message="": report(progress, 0.9 * (state["done"] + f) / total, message)

        apply(todo, process_tile, on_done, workers=workers, scheduler=scheduler, cancelled=cancelled,
              idle=merger.step, progress_of=tile_progress)
        check(cancelled)
        report(progress, 0.9, "merging")
        merger.finish()
        done = [records[j.name] for j in jobs if j.name in records]
        maps = _resolve_ids(done, out, options.id_bits, complete=len(done) == len(jobs))
        unowned_points = 0
        for name, mapping in maps.items():
            merger.remap(name, mapping)
            unowned_points += _remap_las(part_paths(out, name)["las"], mapping)
            ids_path = part_paths(out, name)["ids"]
            z = dict(np.load(ids_path))
            for k in ("owned_ids", "seen_ids"):
                z[k] = np.array([mapping.get(int(v), int(v)) for v in z[k]], dtype=np.int64)
            atomic_save_npz(ids_path, **z)
        gpkg = merger.commit()
    for scratch in ("halo", "chunks"):   # scratch: a rerun makes what it needs (the same bytes)
        shutil.rmtree(out / "parts" / scratch, ignore_errors=True)
    tilesets = [Path(r["files"]["tileset"]) for r in done if "tileset" in r.get("files", {})]
    root = write_root_tileset(out / "models", tilesets) if tilesets else None
    mosaics = _write_mosaics(out, done)
    peaks: Dict[str, float] = {}
    for r in done:
        if r["name"] in skipped:
            continue
        key = f"pid {r['pid']}"
        peaks[key] = max(peaks.get(key, 0.0), float(r["peak_rss_mb"]))
    result = RunReport(
        tiles=done, failures=failures, skipped=skipped, trees=int(sum(r["trees"] for r in done)),
        points=int(sum(r["points"] for r in done)), seconds=round(time.perf_counter() - t0, 3),
        workers=int(workers), scheduler=None if scheduler is None else str(getattr(scheduler, "scheduler", scheduler)),
        peak_rss_mb_per_worker=peaks, unowned_edge_trees=unowned_trees(maps), unowned_edge_points=unowned_points,
        id_collisions_rewritten=sum(any(v for v in m.values()) for m in maps.values()),
        gpkg=None if gpkg is None else str(gpkg), tileset=None if root is None else str(root),
        compile_seconds=round(_compile_seconds(done, skipped, c0), 3), **mosaics)
    atomic_write_bytes(out / "report.json", (json.dumps(result.as_dict(), indent=1, default=str) + "\n").encode())
    atomic_write_bytes(out / "report.txt", result.summary().encode("utf-8"))
    report(progress, 1.0, f"{result.trees} trees")
    return result
