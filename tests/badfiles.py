"""Broken inputs every front end must answer with one clear message (used by several tests)."""
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


def slow_name(seconds, job):
    """A catalog worker function that takes ``seconds`` and returns the tile's name."""
    import time

    time.sleep(seconds)
    return job.name
