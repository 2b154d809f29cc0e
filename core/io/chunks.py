"""Cut a large LAS/LAZ file into square chunks, so that a run holds one chunk (with its buffer) at a time.

    chunk_tiles(tiles, "out/parts/chunks", chunk_m=250.0)   # the tiles, big files replaced by their chunks

A survey delivered as one merged block or one dense drone flight (50–200 M points) would otherwise be
one job held whole in one worker (about 230 MB per million points) while the others wait.  The file is
streamed once; every point record is copied unchanged (same point format, scales, offsets, VLRs and
CRS) into the chunk of the square grid cell that holds it.  The grid is anchored on multiples of
``chunk_m`` in the file's CRS, and cells are half-open (a point on an edge belongs to the cell east /
north of it), so chunks never overlap and a chunk's points do not depend on which other files a run
has.  The chunks are then ordinary tiles: buffers, the one-owner rule and the position-derived tree
IDs make the trees the same as without chunks (the role of lidR's ``opt_chunk_size`` /
``opt_chunk_buffer``; Sylva, not in the papers).
"""
from __future__ import annotations

import copy
import math
import shutil
from pathlib import Path
from typing import Dict, List, Sequence, Tuple

import numpy as np

from ..atomic import move_into_place, temporary_beside
from ..errors import InputError, ParameterError
from ..progress import CancelCheck
from .tiles import Tile, file_checksum

#: Points read from the source at a time while cutting it (bounds the memory of the cut).
READ_POINTS = 1_000_000
#: At most this many chunks a file (each is an open file while the source is read once).
MAX_CHUNKS = 400


def needs_chunks(tile: Tile, chunk_m: float) -> bool:
    """True when ``chunk_m`` > 0 and the tile spans more than one chunk in x or y."""
    if not chunk_m or chunk_m <= 0:
        return False
    size = chunk_m / tile.metres_per_unit
    xmin, ymin, xmax, ymax = tile.bounds
    return math.floor(xmin / size) != math.floor(xmax / size) or math.floor(ymin / size) != math.floor(ymax / size)


def cut_into_chunks(tile: Tile, folder, chunk_m: float, crs=None, cancelled: CancelCheck = None) -> List[Tile]:
    """Write ``<name>_<i>_<j>.las`` (uncompressed: they are scratch) for every grid cell of ``chunk_m``
    metres that holds points of ``tile``, in a folder of ``folder`` named for the file's checksum and
    the chunk size; returns them as tiles, sorted by name.

    A cut that finished before (its list of chunks is written last) is reused, not repeated.
    """
    import laspy

    from .las import checked_records

    size = chunk_m / tile.metres_per_unit
    xmin, ymin, xmax, ymax = tile.bounds
    cells = (math.floor(xmax / size) - math.floor(xmin / size) + 1) * (math.floor(ymax / size) - math.floor(ymin / size) + 1)
    if cells > MAX_CHUNKS:
        raise ParameterError(f"CHUNK_SIZE_M={chunk_m:g}: {tile.path} would be cut into {cells} chunks (at most "
                         f"{MAX_CHUNKS}); choose larger chunks")
    folder = Path(folder) / f"{tile.name}-{file_checksum(tile.path)[:16]}-{chunk_m:g}m"
    folder.mkdir(parents=True, exist_ok=True)
    done = folder / "chunks.txt"
    if done.is_file():
        paths = [folder / f"{n}.las" for n in done.read_text("utf-8").split()]
        if paths and all(p.is_file() for p in paths):
            return _as_tiles(paths, tile, crs)
    writers: Dict[Tuple[int, int], object] = {}   # one open writer per chunk: the file is read once
    temporary: Dict[Tuple[int, int], Path] = {}
    try:
        # a damaged file fails here; decoded on this thread: the run forks its workers after the cut
        header, records = checked_records(tile.path, READ_POINTS, cancelled, parallel=False)
        for points in records:
            ix = np.floor(np.asarray(points.x) / size).astype(np.int64)
            iy = np.floor(np.asarray(points.y) / size).astype(np.int64)
            keys = np.stack([ix, iy], axis=1)
            cells, inverse = np.unique(keys, axis=0, return_inverse=True)
            inverse = inverse.reshape(-1)
            order = np.argsort(inverse, kind="stable")
            starts = np.searchsorted(inverse[order], np.arange(len(cells) + 1))
            for c, (i, j) in enumerate(cells.tolist()):
                key = (int(i), int(j))
                if key not in writers:
                    temporary[key] = temporary_beside(folder / f"{tile.name}_{i}_{j}.las")
                    chunk_header = copy.deepcopy(header)
                    chunk_header.point_count = 0
                    writers[key] = laspy.open(temporary[key], mode="w", header=chunk_header, do_compress=False)
                writers[key].write_points(points[order[starts[c]:starts[c + 1]]])
    except BaseException:
        for w in writers.values():
            w.close()
        for t in temporary.values():
            t.unlink(missing_ok=True)
        shutil.rmtree(folder, ignore_errors=True)      # nothing of a failed cut stays
        raise
    for w in writers.values():
        w.close()
    if not writers:
        raise InputError(f"{tile.path}: the file holds no points to cut into chunks")
    paths = []
    for key in sorted(writers):
        final = folder / f"{tile.name}_{key[0]}_{key[1]}.las"
        move_into_place(temporary[key], final)
        paths.append(final)
    done.write_text("\n".join(p.stem for p in paths) + "\n", "utf-8")
    return _as_tiles(paths, tile, crs)


def _as_tiles(paths: Sequence[Path], source: Tile, crs) -> List[Tile]:
    from .las import las_info

    tiles = []
    for p in sorted(paths, key=lambda q: q.stem):
        info = las_info(p, crs=crs)
        b = info.bounds
        tiles.append(Tile(str(p.resolve()), p.stem, (b[0], b[1], b[3], b[4]), info.point_count, source.metres_per_unit))
    return tiles


def chunk_tiles(tiles: Sequence[Tile], folder, chunk_m: float, crs=None,
                cancelled: CancelCheck = None) -> Tuple[List[Tile], List[dict]]:
    """``(tiles, failures)``: ``tiles`` with every tile wider than one chunk replaced by its chunks (see
    :func:`cut_into_chunks`); a file that cannot be cut (damaged, unreadable) is a failure of its own, as
    a tile that fails is, and the other files go on."""
    out, failures = [], []
    for t in tiles:
        if not needs_chunks(t, chunk_m):
            out.append(t)
            continue
        try:
            out.extend(cut_into_chunks(t, folder, chunk_m, crs, cancelled))
        except ParameterError:                  # the chunk size, not the file: the run stops
            raise
        except InputError as err:
            failures.append({"name": t.name, "path": t.path, "status": "failed", "reason": str(err), "attempts": 1})
    return out, failures
