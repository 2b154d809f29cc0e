"""Broken inputs every front end must answer with one clear message (used by several tests)."""
from dataclasses import dataclass
from pathlib import Path

import laspy
import numpy as np


def make_bad_inputs(folder: Path, sample: Path) -> dict:
    """name -> (path, words the error message must contain besides the file name)."""
    folder.mkdir(parents=True, exist_ok=True)
    bad = {}
    bad["missing"] = (folder / "does_not_exist.laz", "not found")
    text = folder / "not_a_las.las"
    text.write_text("this is not a point cloud\n" * 20)
    bad["not_las"] = (text, "")
    data = sample.read_bytes()
    truncated = folder / "truncated.laz"
    truncated.write_bytes(data[: len(data) // 2])
    bad["truncated"] = (truncated, "")
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales = np.array([0.01, 0.01, 0.01])
    empty = folder / "empty.las"
    laspy.LasData(header).write(empty)
    bad["empty"] = (empty, "no points")
    las = laspy.read(sample)
    nocrs = laspy.LasData(laspy.LasHeader(point_format=las.header.point_format.id, version="1.4"))
    nocrs.header.offsets = las.header.offsets
    nocrs.header.scales = las.header.scales
    nocrs.x, nocrs.y, nocrs.z = las.x[:2000], las.y[:2000], las.z[:2000]
    nocrs.classification = las.classification[:2000]
    path = folder / "no_crs.las"
    nocrs.write(path)
    bad["no_crs"] = (path, "CRS")
    return bad


def die_on(name, job):
    """A catalog worker function that kills its process on the tile called ``name`` (as an OOM kill would)."""
    import os

    from sylva.core.pipeline import process_tile

    if job.name == name:
        os._exit(9)
    return process_tile(job)


def slow_name(seconds, job, **_):
    """A catalog worker function that takes ``seconds`` and returns the tile's name."""
    import time

    time.sleep(seconds)
    return job.name


@dataclass(frozen=True)
class Job:
    """The smallest job the engine (core/engine.py) can run: a name and an attempt."""

    name: str
    attempt: int = 1


def fail_first(job, **_):
    """A worker function that fails on a job's first attempt and returns (name, attempt) after."""
    if job.attempt == 1 and job.name.startswith("flaky"):
        raise RuntimeError(f"{job.name} failed once")
    return job.name, job.attempt


# --------------------------------------------------------------------------- damaged files (issue 17)

def _patched_count(data: bytes, n: int) -> bytes:
    """A LAS/LAZ file's bytes with its header's point count replaced by ``n`` (legacy and 1.4 fields)."""
    import struct

    b = bytearray(data)
    minor = b[25]
    struct.pack_into("<I", b, 107, n if minor < 4 else 0)
    if minor >= 4:
        struct.pack_into("<Q", b, 247, n)
    return bytes(b)


def _patched_max_z(data: bytes, z: float) -> bytes:
    """The header's maximum z replaced by ``z`` (a header whose bounds lie about its points)."""
    import struct

    b = bytearray(data)
    struct.pack_into("<d", b, 179 + 32, z)
    return bytes(b)


def make_damaged_files(folder: Path, sample: Path) -> dict:
    """name -> (path, words the one-line message must contain): every damage Sylva must detect.

    From the bundled sample (LAZ 1.4, three chunks of 50,000 points) and a LAS copy of it:
    truncations at several places, zeroed blocks, header counts smaller and larger than the
    data, header bounds that the points exceed.
    """
    folder.mkdir(parents=True, exist_ok=True)
    laz = sample.read_bytes()
    las_path = folder / "plain.las"
    laspy.read(sample).write(las_path)
    las = las_path.read_bytes()
    out = {}

    def put(name, data, words):
        path = folder / name
        path.write_bytes(data)
        out[path.stem] = (path, words)

    for frac in (0.1, 0.5, 0.9, 0.999):
        put(f"laz_truncated_{int(frac * 1000)}.laz", laz[: int(len(laz) * frac)], "")
        put(f"las_truncated_{int(frac * 1000)}.las", las[: int(len(las) * frac)], "truncated")
    # (a block zeroed in a LAZ 1.4 chunk's colour layer decodes to other colours: no check can tell, LAZ has no checksums)
    for frac, size in ((0.5, 20_000), (0.2, 20_000), (0.8, 20_000)):
        at = int(len(laz) * frac)
        put(f"laz_zeroed_{int(frac * 100)}.laz", laz[:at] + bytes(size) + laz[at + size:], "damaged")
    n = laspy.open(sample).header.point_count
    put("laz_count_half.laz", _patched_count(laz, n // 2), "damaged")
    put("laz_count_slightly_low.laz", _patched_count(laz, n - 300), "damaged")
    put("laz_count_high.laz", _patched_count(laz, n * 2), "damaged")
    put("laz_count_slightly_high.laz", _patched_count(laz, n + 100), "")
    put("las_count_low.las", _patched_count(las, n - 1), "damaged")
    put("las_count_high.las", _patched_count(las, n + 1), "truncated")
    put("laz_bounds_lie.laz", _patched_max_z(laz, 300.0), "outside the header's bounds")
    las_path.unlink()
    return out


def corner_tiles(folder: Path, sample: Path, size_m: float = 30.0, n: int = 2) -> list:
    """``n`` x ``n`` LAZ tiles of ``size_m`` from the sample's corner (small and fast)."""
    from sylva.core.io import read_cloud
    from sylva.core.io.las import write_las

    folder.mkdir(parents=True, exist_ok=True)
    cloud = read_cloud(sample)
    x0, y0 = cloud.xyz[:, 0].min(), cloud.xyz[:, 1].min()
    paths = []
    for i in range(n):
        for j in range(n):
            m = ((cloud.xyz[:, 0] >= x0 + i * size_m) & (cloud.xyz[:, 0] < x0 + (i + 1) * size_m)
                 & (cloud.xyz[:, 1] >= y0 + j * size_m) & (cloud.xyz[:, 1] < y0 + (j + 1) * size_m))
            path = folder / f"c_{i}_{j}.laz"
            write_las(path, cloud.subset(m))
            paths.append(path)
    return paths


def mixed_crs_tiles(folder: Path, sample: Path) -> list:
    """Three small tiles tagged UTM 12N, UTM 17N and New York Long Island state plane (US feet)."""
    folder.mkdir(parents=True, exist_ok=True)
    las = laspy.read(sample)
    paths = []
    for code in (26912, 26917, 2263):
        import pyproj

        sub = laspy.LasData(laspy.LasHeader(point_format=las.header.point_format.id, version="1.4"))
        sub.header.offsets, sub.header.scales = las.header.offsets, las.header.scales
        sub.header.add_crs(pyproj.CRS.from_epsg(code))
        sub.x, sub.y, sub.z = las.x[:3000], las.y[:3000], las.z[:3000]
        sub.classification = las.classification[:3000]
        path = folder / f"epsg{code}.las"
        sub.write(path)
        paths.append(path)
    return paths
