"""From a folder of tiles to a forest: tiles + buffers, tree ownership, stable IDs, parallel runs.

    report = run_catalog(["tiles/"], "out/", PipelineOptions(), workers=2)

Inputs: LAS/LAZ files, folders of them, or QGIS virtual point clouds (``.vpc``:
a STAC ItemCollection whose features give ``assets.data.href`` and
``proj:bbox``/``bbox``).  Each tile is processed by
:func:`sylva.core.pipeline.process_tile` with its neighbours' points within
``buffer_m`` (see that module for the ownership and ID rules) in a local
process pool (``workers``) or on a ``dask.distributed`` scheduler
(``scheduler`` address).  A tile that fails is retried once, then reported;
the run goes on.  A rerun skips every tile whose manifest matches its inputs
(checksums of the tile and its neighbours) and the parameters.

Output folder::

    forest.gpkg            trees, tree_tops, crowns, crown_points, stem_points, skeletons, models_3d
    tiles/<tile>.laz       every input tile with an int32 treeID (0 = no tree)
    models/<tile>.glb      the tile's owned trees, a node per tree
    models/tileset.json    one 3D Tiles 1.1 tileset for the run (external tilesets per tile)
    report.json, report.txt
    parts/                 per-tile parts and manifests (what a resumed run reuses)

Tree-ID collisions: IDs are 31-bit hashes of the top's position
(:func:`sylva.core.pipeline.tree_ids`); each tile resolves the collisions among
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
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

import numpy as np

from .atomic import atomic_path, atomic_write_bytes, move_into_place, temporary_beside
from .errors import Cancelled, InputError, OutputError, ParameterError, SylvaError, disk_error
from .io.gpkg import GpkgMerge, default_styles
from .pipeline import PipelineOptions, TileJob, is_complete, part_paths, process_tile, tree_ids
from .progress import CancelCheck, Progress, check, report

LAYERS = ("trees", "tree_tops", "crowns", "crown_points", "stem_points", "skeletons", "models_3d")
LAS_SUFFIXES = (".las", ".laz")


@dataclass(frozen=True)
class Tile:
    """One input tile: its path, a unique name, and its (xmin, ymin, xmax, ymax) in CRS units."""

    path: str
    name: str
    bounds: tuple
    points: int = -1
    metres_per_unit: float = 1.0


# --------------------------------------------------------------------------- inputs

def read_vpc(path) -> List[tuple]:
    """(file path, bounds or None) of every feature of a QGIS virtual point cloud (.vpc)."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text("utf-8"))
    except (OSError, ValueError) as err:
        raise InputError(f"{path}: not a readable virtual point cloud ({err})") from None
    if doc.get("type") != "FeatureCollection" or not isinstance(doc.get("features"), list):
        raise InputError(f"{path}: not a virtual point cloud (a STAC FeatureCollection with features)")
    out = []
    for i, feature in enumerate(doc["features"]):
        try:
            href = feature["assets"]["data"]["href"]
        except (KeyError, TypeError):
            raise InputError(f"{path}: feature {i} has no assets.data.href") from None
        p = Path(href[7:] if href.startswith("file://") else href)
        p = p if p.is_absolute() else (path.parent / p)
        props = feature.get("properties") or {}
        bbox = props.get("proj:bbox") or feature.get("bbox")
        bounds = None
        if bbox and len(bbox) in (4, 6):
            b = [float(v) for v in bbox]
            bounds = (b[0], b[1], b[2], b[3]) if len(b) == 4 else (b[0], b[1], b[3], b[4])
        out.append((str(p.resolve()), bounds))
    return out


def write_vpc(path, tiles: Sequence[Tile], crs=None) -> Path:
    """Write a minimal QGIS virtual point cloud listing ``tiles`` (paths relative to the .vpc)."""
    path = Path(path)
    features = []
    epsg = crs.to_epsg() if crs is not None and hasattr(crs, "to_epsg") else None
    for t in tiles:
        xmin, ymin, xmax, ymax = t.bounds
        props = {"datetime": "2024-01-01T00:00:00Z", "pc:count": int(t.points), "proj:bbox": [xmin, ymin, xmax, ymax]}
        if epsg:
            props["proj:epsg"] = epsg
        features.append({
            "type": "Feature", "stac_version": "1.0.0",
            "stac_extensions": ["https://stac-extensions.github.io/pointcloud/v1.0.0/schema.json",
                                "https://stac-extensions.github.io/projection/v1.1.0/schema.json"],
            "id": t.name, "geometry": None, "bbox": [xmin, ymin, xmax, ymax], "properties": props,
            "links": [], "assets": {"data": {"href": "./" + os.path.relpath(t.path, path.parent),
                                             "roles": ["data"]}},
        })
    doc = {"type": "FeatureCollection", "features": features}
    return atomic_write_bytes(path, (json.dumps(doc, indent=1) + "\n").encode("utf-8"))


def list_tiles(inputs, crs=None) -> tuple:
    """(tiles, failures): every LAS/LAZ of ``inputs`` (files, folders, .vpc) with its bounds.

    A file whose header cannot be read is a failure (path, reason), not an error.
    Tiles are sorted by path; names are the file stems, made unique.
    """
    from .io.las import las_info

    if isinstance(inputs, (str, os.PathLike)):
        inputs = [inputs]
    found = {}
    for item in inputs:
        p = Path(item)
        if p.is_dir():
            for f in sorted(p.iterdir()):
                if f.suffix.lower() in LAS_SUFFIXES and f.is_file():
                    found[str(f.resolve())] = None
        elif p.suffix.lower() == ".vpc":
            for f, bounds in read_vpc(p):
                found[f] = bounds
        elif p.suffix.lower() in LAS_SUFFIXES:
            if not p.exists():
                raise InputError(f"{p}: file not found")
            found[str(p.resolve())] = None
        else:
            raise InputError(f"{p}: not a LAS/LAZ file, a folder or a .vpc virtual point cloud")
    if not found:
        raise InputError(f"no LAS/LAZ tiles in {', '.join(map(str, inputs))}")
    tiles, failures, names, infos = [], [], set(), {}
    for path in sorted(found):
        try:
            info = las_info(path, crs=crs)
            b = info.bounds
            bounds = (b[0], b[1], b[3], b[4])
            points = info.point_count
            mpu = float(info.units.horizontal_m)
        except SylvaError as err:
            failures.append({"name": Path(path).stem, "path": path, "status": "failed", "reason": str(err),
                             "attempts": 1})   # a header that cannot be read is not retried
            continue
        infos[path] = info
        name = Path(path).stem
        k = 2
        while name in names:
            name = f"{Path(path).stem}_{k}"
            k += 1
        names.add(name)
        tiles.append(Tile(path, name, bounds, points, mpu))
    if crs is None:
        require_one_crs({t.path: infos[t.path].crs for t in tiles})
    return tiles, failures


def require_one_crs(crs_of: Dict[str, object]) -> None:
    """Refuse tiles in different CRSs (:class:`CRSError` naming the odd ones) — Sylva, not in the papers.

    CRSs are compared as pyproj objects (``equals`` ignoring axis order), not by name: a
    WKT and an EPSG code of one CRS are equal; UTM 12N, UTM 17N and a state plane in feet
    are not.  The largest group of equal CRSs is the run's; tiles without a CRS are odd too
    when others have one.  The CRS parameter reads every tile in one CRS instead.
    """
    from .errors import CRSError

    groups: List[list] = []   # [crs, [paths]]
    for path, crs in crs_of.items():
        for group in groups:
            a, b = group[0], crs
            if (a is None and b is None) or (a is not None and b is not None
                                             and (a == b or a.equals(b, ignore_axis_order=True))):
                group[1].append(path)
                break
        else:
            groups.append([crs, [path]])
    if len(groups) <= 1:
        return
    groups.sort(key=lambda g: (-len(g[1]), g[0] is None))
    main = groups[0][0]
    odd = "; ".join(f"{Path(p).name} ({'no CRS' if g[0] is None else g[0].name})"
                    for g in groups[1:] for p in g[1])
    raise CRSError(f"the tiles of a run must share one CRS: {len(groups[0][1])} tile(s) are in "
                   f"{'no CRS' if main is None else main.name}, but {odd}; reproject those tiles, or set "
                   "the CRS parameter to read every tile in one CRS")


def file_checksum(path, block: int = 1 << 22) -> str:
    """BLAKE2b (16 bytes) of a file's bytes."""
    h = hashlib.blake2b(digest_size=16)
    with open(path, "rb") as fh:
        while True:
            data = fh.read(block)
            if not data:
                break
            h.update(data)
    return h.hexdigest()


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


# --------------------------------------------------------------------------- execution

def _failure(job: TileJob, err: BaseException) -> dict:
    reason = str(err) if isinstance(err, SylvaError) else f"{type(err).__name__}: {err}"
    return {"name": job.name, "path": job.path, "status": "failed", "reason": reason, "attempts": job.attempt}


def _run_serial(jobs, on_done, cancelled, tile_progress=lambda job: None):
    for job in jobs:
        check(cancelled)
        try:
            on_done(job, process_tile(job, progress=tile_progress(job), cancelled=cancelled), None)
        except Cancelled:
            raise
        except Exception as err:  # noqa: BLE001 — a tile's failure is reported, never fatal
            on_done(job, None, err)


def _pool_context():
    import multiprocessing as mp

    # fork is fast, but not safe once QGIS (Qt threads) is running in this process: spawn then
    if sys.platform.startswith("linux") and "qgis.core" not in sys.modules:
        return mp.get_context("fork")
    ctx = mp.get_context("spawn")
    exe = Path(sys.exec_prefix) / ("python.exe" if os.name == "nt" else "bin/python3")
    if exe.exists() and not Path(sys.executable).name.lower().startswith("python"):
        ctx.set_executable(str(exe))   # inside QGIS sys.executable is QGIS itself
    return ctx


class WorkerDied(SylvaError):
    """The process working on a tile died (killed for memory, or a crash in native code)."""


def _run_pool(jobs, workers, on_done, cancelled, work=process_tile, idle=lambda: False):
    """Run ``work(job)`` in a process pool, at most ``workers`` tiles in flight.

    A worker that dies breaks the whole pool (``BrokenProcessPool`` for every
    tile in flight): those tiles are then rerun one at a time in a pool of
    their own, which finds the culprit — reported as :class:`WorkerDied`, not
    retried — and clears the innocent; the other tiles go on in a new pool.
    ``idle()`` is called while no tile has finished (it returns False when it had nothing to do).
    """
    from collections import deque
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from concurrent.futures.process import BrokenProcessPool

    queue, suspects = deque(jobs), deque()
    while queue or suspects:
        alone = bool(suspects)
        source, size = (suspects, 1) if alone else (queue, workers)
        pending = {}
        with ProcessPoolExecutor(max_workers=size, mp_context=_pool_context()) as pool:
            try:
                broken = False
                while pending or (source and not broken):
                    while source and not broken and len(pending) < size:
                        job = source.popleft()
                        pending[pool.submit(work, job)] = job
                    done, _ = wait(list(pending), timeout=0 if idle() else 0.5, return_when=FIRST_COMPLETED)
                    check(cancelled)
                    for fut in done:
                        job = pending.pop(fut)
                        err = fut.exception()
                        if isinstance(err, BrokenProcessPool):
                            broken = True
                            if alone:
                                on_done(replace(job, attempt=max(job.attempt, 2)), None, WorkerDied(
                                    f"{job.path}: the process working on this tile died (out of memory, "
                                    "or a crash in a native library)"))
                            else:
                                suspects.append(job)
                            continue
                        retry = on_done(job, None if err else fut.result(), err)
                        if retry is not None:
                            source.appendleft(retry)
            except BaseException:
                for fut in pending:
                    fut.cancel()
                _terminate(pool)   # a cancel (Ctrl-C, SIGTERM) must not wait for the tiles in flight
                raise


def _terminate(pool) -> None:
    """Stop a ProcessPoolExecutor's workers now (their .part files are removed by the run)."""
    processes = dict(getattr(pool, "_processes", None) or {})
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in processes.values():
        try:
            proc.terminate()
        except Exception:  # noqa: BLE001 — already gone
            pass
    for proc in processes.values():
        try:
            proc.join(5)
            if proc.is_alive():
                proc.kill()
                proc.join(5)
        except Exception:  # noqa: BLE001
            pass


#: The address schemes a SCHEDULER may use: given explicitly, over the network only.
SCHEDULER_SCHEMES = ("tcp://", "tls://")


def connect_scheduler(address: str, timeout_s: Optional[float] = None):
    """A dask.distributed Client for ``address`` (tcp:// or tls:// only), or one line why not.

    A scheduler is trusted code execution: dask sends tasks and results pickled both ways, so a
    scheduler (or a worker) one does not control can run any code in this process.  Only
    addresses written out with an explicit tcp:// or tls:// scheme are accepted (no inproc://,
    ucx:// or a bare host name that dask would complete), and the connection times out instead
    of hanging (Sylva, not in the papers).
    """
    try:
        from distributed import Client
    except ImportError:
        raise InputError("the SCHEDULER option needs dask.distributed: pip install 'dask[distributed]'") from None
    if timeout_s is None:   # SYLVA_SCHEDULER_TIMEOUT_S: seconds to wait for the scheduler (default 20)
        try:
            timeout_s = float(os.environ.get("SYLVA_SCHEDULER_TIMEOUT_S", "20"))
        except ValueError:
            timeout_s = 20.0
    text = str(address).strip()
    if not text.lower().startswith(SCHEDULER_SCHEMES) or len(text) <= 6:
        raise InputError(f"SCHEDULER={text!r}: give the scheduler's address with its scheme, "
                         "tcp://HOST:PORT or tls://HOST:PORT")
    try:
        return Client(text, timeout=timeout_s, set_as_default=False)
    except (OSError, TimeoutError) as err:
        raise InputError(f"SCHEDULER={text}: cannot reach the dask scheduler within {timeout_s:g} s "
                         f"({type(err).__name__}: {' '.join(str(err).split())[:200]})") from None
    except ValueError as err:
        raise InputError(f"SCHEDULER={text}: not a usable scheduler address ({err})") from None


def _run_dask(jobs, scheduler, on_done, cancelled, idle=lambda: False):
    client = scheduler if hasattr(scheduler, "submit") else connect_scheduler(scheduler)
    from distributed import wait
    pending = {}
    try:
        pending = {client.submit(process_tile, job, pure=False, key=f"sylva-{job.name}-{job.attempt}-{job.checksum}"): job
                   for job in jobs}
        while pending:
            try:
                done = wait(list(pending), timeout=0 if idle() else 0.5, return_when="FIRST_COMPLETED").done
            except TimeoutError:
                done = ()
            check(cancelled)
            for fut in done:
                job = pending.pop(fut)
                if fut.status == "error":
                    retry = on_done(job, None, fut.exception())
                else:
                    retry = on_done(job, fut.result(), None)
                if retry is not None:
                    pending[client.submit(process_tile, retry, pure=False,
                                          key=f"sylva-{retry.name}-{retry.attempt}-{retry.checksum}")] = retry
    except BaseException:
        client.cancel(list(pending))
        raise
    finally:
        if client is not scheduler:
            client.close()


# --------------------------------------------------------------------------- merging

def _resolve_ids(records, out_dir, bits) -> Dict[str, dict]:
    """Per tile, the {old ID: new ID} its files need after run-wide collision resolution."""
    keys, ids = [], []
    for r in records:
        z = np.load(part_paths(out_dir, r["name"])["ids"])
        keys.append(z["owned_keys"].reshape(-1, 2))
        ids.append(z["owned_ids"])
    if not keys:
        return {}
    allk = np.concatenate(keys)
    final = tree_ids(allk, bits)
    lookup = {tuple(k): int(v) for k, v in zip(allk.tolist(), final.tolist())}
    maps = {}
    for r in records:
        z = np.load(part_paths(out_dir, r["name"])["ids"])
        m = {}
        for k, v in zip(z["seen_keys"].reshape(-1, 2).tolist(), z["seen_ids"].tolist()):
            new = lookup.get(tuple(k))
            if new is not None and new != v:
                m[int(v)] = new
        if m:
            maps[r["name"]] = m
    return maps


def _remap_las(path, mapping: dict) -> None:
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


def merge_gpkg(parts: Sequence[Path], path, id_maps: Optional[Sequence[dict]] = None) -> Path:
    """Concatenate the layers of per-tile GeoPackages into one at ``path`` (:class:`~.io.gpkg.GpkgMerge`).

    The result conforms to GeoPackage 1.2 (GDAL's ``validate_gpkg.py``), has an
    R-tree per geometry column and carries Sylva's QGIS styles in ``layer_styles``.

    ``id_maps`` (one {old: new} per part) rewrites ``tree_id`` values on the way.
    The 3D layer (``models_3d``, core/export/gpkg3d.py) is written per tile by the
    pipeline and merged here like the others.
    """
    parts = [Path(p) for p in parts]
    id_maps = list(id_maps or [{}] * len(parts))
    with atomic_path(path) as tmp:
        merge = GpkgMerge(tmp, styles=default_styles(LAYERS))
        try:
            for part, mapping in zip(parts, id_maps):
                merge.remap(merge.add(part), mapping)
        except BaseException:
            merge.abort()
            raise
        merge.close()
    return Path(path)


class _OrderedMerge:
    """Merges the tiles' GeoPackages into ``forest.gpkg`` while the tiles are processed.

    Parts are appended in ``order`` (the run's deterministic processing order,
    so the merged rows do not depend on which worker finished first) as each
    becomes :meth:`ready`; :meth:`step` appends the next one when the main
    process has nothing else to do (the pool runners call it while they wait),
    so the merge of the first parts overlaps the work on the last ones.  No
    thread: the pools fork their workers from this process (Sylva, not in a
    paper).  :meth:`finish` appends the rest; :meth:`remap` rewrites IDs;
    :meth:`commit` moves the file into place; leaving the ``with`` block on an
    exception (an error or a cancel) removes it.
    """

    def __init__(self, path: Path, order: Sequence[str]):
        self.path = Path(path)
        self.tmp = temporary_beside(self.path)
        self.merge = GpkgMerge(self.tmp, styles=default_styles(LAYERS))
        self.order = list(order)
        self.next = 0
        self.parts: Dict[str, Optional[Path]] = {}
        self.ranges: Dict[str, Dict[str, tuple]] = {}

    def __enter__(self):
        return self

    def __exit__(self, kind, value, tb):
        if kind is not None:
            self.merge.abort()
            self.tmp.unlink(missing_ok=True)
        return False

    def ready(self, name: str, part: Optional[Path]) -> None:
        """Tile ``name`` is final: its GeoPackage ``part``, or None when it failed."""
        self.parts[name] = part

    def step(self) -> bool:
        """Append the next part in order if it is ready; False when there was none to append."""
        if self.next >= len(self.order) or self.order[self.next] not in self.parts:
            return False
        name = self.order[self.next]
        self.next += 1
        if self.parts[name] is not None:
            self.ranges[name] = self.merge.add(self.parts[name])
        return True

    def finish(self) -> None:
        while self.step():
            pass

    def remap(self, name: str, mapping: dict) -> None:
        self.merge.remap(self.ranges.get(name, {}), mapping)

    def commit(self) -> Optional[Path]:
        """The merged file in place (None, and nothing written, when no part was merged)."""
        self.merge.close()
        if self.merge.parts == 0:
            self.tmp.unlink()
            return None
        move_into_place(self.tmp, self.path)
        return self.path


def write_root_tileset(folder, tilesets: Sequence[Path]) -> Optional[Path]:
    """``folder/tileset.json`` whose children are the per-tile tilesets (external tileset content).

    Each child's bounding volume is its tileset's root box carried into ECEF
    (an oriented box: centre ``M c``, half-axes ``R h``), so it is as tight as
    the tile's own; the root is the box, in the first tile's east-north-up
    axes, around every child box's corners.  Children refine by REPLACE: a
    client (QGIS's tiled scene layer merges an external tileset's root into
    the tile that points to it) then swaps a tile's coarse content for its
    full models instead of drawing both.
    """
    children, corners, axes, errors = [], [], None, []
    folder = Path(folder)
    signs = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], dtype=np.float64)
    for ts in tilesets:
        doc = json.loads(Path(ts).read_text("utf-8"))
        root = doc["root"]
        M = np.array(root.get("transform", np.eye(4).ravel().tolist()), dtype=np.float64).reshape(4, 4).T
        box = np.array(root["boundingVolume"]["box"], dtype=np.float64)
        centre = (M @ np.r_[box[:3], 1.0])[:3]
        half = (M[:3, :3] @ box[3:].reshape(3, 3).T).T           # rows: the three half-axes in ECEF
        if axes is None:
            axes = M[:3, :3] / np.linalg.norm(M[:3, :3], axis=0)  # columns: east, north, up at the first tile
        corners.append(centre + signs @ half)
        errors.append(float(doc.get("geometricError", root.get("geometricError", 0.0))))
        children.append({"boundingVolume": {"box": [*centre.tolist(), *half.ravel().tolist()]},
                         "geometricError": errors[-1], "refine": "REPLACE",
                         "content": {"uri": Path(os.path.relpath(ts, folder)).as_posix()}})
    if not children:
        return None
    local = np.concatenate(corners) @ axes                        # corners in the first tile's ENU axes
    lo, hi = local.min(axis=0), local.max(axis=0)
    centre = axes @ ((lo + hi) / 2.0)
    half = (axes * ((hi - lo) / 2.0)).T
    diagonal = 2.0 * float(np.linalg.norm((hi - lo) / 2.0))
    doc = {"asset": {"version": "1.1", "extras": {"generator": "Sylva catalog"}},
           "geometricError": diagonal,
           "root": {"boundingVolume": {"box": [*centre.tolist(), *half.ravel().tolist()]},
                    "geometricError": max(errors) * 2 + 1.0, "refine": "REPLACE", "children": children}}
    return atomic_write_bytes(folder / "tileset.json", (json.dumps(doc, indent=1) + "\n").encode("utf-8"))


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

    for name in ("buffer_m", "window_diameter_m", "min_height_m", "ground_cell_m", "crown_base_gap_m"):
        value = getattr(options, name)
        try:
            ok = math.isfinite(float(value)) and float(value) >= 0
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise ParameterError(f"{name.upper()}={value}: must be a finite number of metres, 0 or more")
    if not options.window_diameter_m > 0:
        raise ParameterError(f"WINDOW_DIAMETER_M={options.window_diameter_m}: must be more than 0")


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
            with os.fdopen(fd, "wb") as fh:
                fh.write(data)
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
    # two runs into one folder never mix: outputs of tiles that are not this run's go
    for name in sorted(_stale_names(out, {t.name for t in tiles})):
        remove_tile_outputs(out, name)
    jobs = make_jobs(tiles, out, options)
    # Largest tiles first (longest-processing-time order): no big tile is left to run alone at the end.
    # forest.gpkg takes the tiles' rows in this order too (deterministic: sizes, then names).
    points = {t.name: t.points for t in tiles}
    order = sorted(jobs, key=lambda j: -points[j.name])
    with _OrderedMerge(out / "forest.gpkg", [j.name for j in order]) as merger:
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
                    retry = replace(job, attempt=job.attempt + 1)
                    if scheduler is None and workers <= 1:
                        try:
                            on_done(retry, process_tile(retry, cancelled=cancelled), None)
                        except Cancelled:
                            raise
                        except Exception as err2:  # noqa: BLE001
                            on_done(retry, None, err2)
                        return None
                    return retry
                failures.append(_failure(job, err))
                remove_tile_outputs(out, job.name)   # no stale LAZ/GLB of an earlier run stays beside the report
                merger.ready(job.name, None)
            else:
                records[job.name] = record
                merger.ready(job.name, part_paths(out, job.name)["gpkg"])
            state["done"] += 1
            report(progress, 0.9 * state["done"] / total, f"{state['done']} of {total} tiles")
            return None

        if todo:
            if scheduler is not None:
                _run_dask(todo, scheduler, on_done, cancelled, idle=merger.step)
            elif workers > 1:
                _run_pool(todo, workers, on_done, cancelled, idle=merger.step)
            else:
                def tile_progress(job):
                    return lambda f, message="": report(progress, 0.9 * (state["done"] + f) / total, message)

                _run_serial(todo, on_done, cancelled, tile_progress)
        check(cancelled)
        report(progress, 0.9, "merging")
        merger.finish()
        done = [records[j.name] for j in jobs if j.name in records]
        maps = _resolve_ids(done, out, options.id_bits)
        for name, mapping in maps.items():
            merger.remap(name, mapping)
            _remap_las(part_paths(out, name)["las"], mapping)
            ids_path = part_paths(out, name)["ids"]
            z = dict(np.load(ids_path))
            for k in ("owned_ids", "seen_ids"):
                z[k] = np.array([mapping.get(int(v), int(v)) for v in z[k]], dtype=np.int64)
            with atomic_path(ids_path) as tmp:
                with open(tmp, "wb") as fh:
                    np.savez(fh, **z)
        gpkg = merger.commit()
    shutil.rmtree(out / "parts" / "halo", ignore_errors=True)  # scratch: a rerun makes what it needs
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
        peak_rss_mb_per_worker=peaks, id_collisions_rewritten=len(maps),
        gpkg=None if gpkg is None else str(gpkg), tileset=None if root is None else str(root),
        compile_seconds=round(_compile_seconds(done, skipped, c0), 3), **mosaics)
    atomic_write_bytes(out / "report.json", (json.dumps(result.as_dict(), indent=1, default=str) + "\n").encode())
    atomic_write_bytes(out / "report.txt", result.summary().encode("utf-8"))
    report(progress, 1.0, f"{result.trees} trees")
    return result
