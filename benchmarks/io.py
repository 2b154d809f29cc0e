"""Throughput of sylva.core.io against laspy's own read/write.

Generates a seeded ~2 million point ALS-like cloud (LAS 1.2, point format 3:
returns, classification, GPS time, RGB, plus an int32 treeID extra dimension),
writes it as LAS and LAZ into a temporary folder, and prints points per second
for

* read:  ``read_las`` (xyz + every attribute as arrays + template) vs ``laspy.read``
* write: ``write_las`` of the cloud read back (lossless, template path) vs
  ``LasData.write`` of the laspy data
* chunked read: ``read_las_chunks`` (1 M points per chunk) vs laspy's
  ``chunk_iterator``
* text: ``read_xyz`` vs ``numpy.loadtxt`` on the same cloud as x y z intensity

Best of ``--repeat`` runs each.  Run: ``python benchmarks/io.py [--points N]``.
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

import laspy

from sylva.core.io import read_las, read_las_chunks, read_xyz, write_las


def make_cloud(n: int, seed: int = 0) -> laspy.LasData:
    rng = np.random.default_rng(seed)
    header = laspy.LasHeader(version="1.2", point_format=3)
    header.scales = np.array([0.01, 0.01, 0.01])
    header.offsets = np.array([481000.0, 3812000.0, 0.0])
    header.add_extra_dims([laspy.ExtraBytesParams("treeID", np.int32)])
    import pyproj

    header.add_crs(pyproj.CRS.from_epsg(26912))
    las = laspy.LasData(header, laspy.ScaleAwarePointRecord.zeros(n, header=header))
    las.x = 481000.0 + rng.uniform(0, 1000, n)
    las.y = 3812000.0 + rng.uniform(0, 1000, n)
    las.z = rng.gamma(2.0, 6.0, n)
    las.intensity = rng.integers(0, 4096, n).astype(np.uint16)
    nr = rng.integers(1, 5, n).astype(np.uint8)
    las.number_of_returns = nr
    las.return_number = (rng.random(n) * nr).astype(np.uint8) + 1
    las.classification = rng.choice(np.array([1, 2, 5], np.uint8), n)
    las.scan_angle_rank = rng.integers(-20, 21, n).astype(np.int8)
    las.gps_time = np.sort(rng.uniform(0, 3600, n))
    las.red = rng.integers(0, 65536, n).astype(np.uint16)
    las.green = rng.integers(0, 65536, n).astype(np.uint16)
    las.blue = rng.integers(0, 65536, n).astype(np.uint16)
    las.treeID = rng.integers(0, 500, n).astype(np.int32)
    return las


def best_pair(ours, reference, repeat):
    """Best time of each, the two runs alternating so both see the same machine load."""
    t_ours, t_ref = [], []
    for _ in range(repeat):
        for fn, times in ((ours, t_ours), (reference, t_ref)):
            t = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t)
    return min(t_ours), min(t_ref)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=2_000_000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--text-points", type=int, default=500_000)
    args = ap.parse_args(argv)
    n, r = args.points, args.repeat

    las = make_cloud(n)
    rows = []
    with tempfile.TemporaryDirectory(prefix="sylva-io-bench-") as tmp:
        tmp = Path(tmp)
        for suffix in (".las", ".laz"):
            src = tmp / f"src{suffix}"
            las.write(str(src))
            size_mb = src.stat().st_size / 1e6
            cloud = read_las(src)
            t_ours_r, t_lp_r = best_pair(lambda: read_las(src), lambda: laspy.read(str(src)), r)
            ref = laspy.read(str(src))
            t_ours_w, t_lp_w = best_pair(lambda: write_las(tmp / f"ours{suffix}", cloud),
                                         lambda: ref.write(str(tmp / f"laspy{suffix}")), r)

            def ours_chunks():
                for c in read_las_chunks(src, chunk_size=1_000_000):
                    pass

            def laspy_chunks():
                with laspy.open(str(src)) as reader:
                    for c in reader.chunk_iterator(1_000_000):
                        pass

            t_ours_c, t_lp_c = best_pair(ours_chunks, laspy_chunks, r)
            label = f"{suffix[1:].upper()} ({size_mb:.0f} MB)"
            rows.append((label, "read", t_ours_r, t_lp_r))
            rows.append((label, "write", t_ours_w, t_lp_w))
            rows.append((label, "chunked read", t_ours_c, t_lp_c))

        # text: x y z intensity, the same points (first --text-points)
        m = min(args.text_points, n)
        txt = tmp / "cloud.xyz"
        data = np.column_stack([np.asarray(las.x[:m]), np.asarray(las.y[:m]),
                                np.asarray(las.z[:m]), np.asarray(las.intensity[:m])])
        np.savetxt(txt, data, fmt="%.2f %.2f %.2f %d")
        assert np.allclose(read_xyz(txt).xyz, np.loadtxt(txt)[:, :3])
        t_ours_t, t_np_t = best_pair(lambda: read_xyz(txt), lambda: np.loadtxt(txt), r)
        rows_text = ("text (x y z i)", "read", t_ours_t, t_np_t, m)

    print(f"sylva.core.io vs laspy {laspy.__version__}, {n:,} points, best of {r}, "
          f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}")
    print(f"{'file':<16}{'operation':<14}{'sylva pts/s':>14}{'reference pts/s':>17}"
          f"{'ratio':>8}")
    for label, op, ours, ref in rows:
        print(f"{label:<16}{op:<14}{n / ours:>14,.0f}{n / ref:>17,.0f}{ref / ours:>8.2f}")
    label, op, ours, ref, m = rows_text
    print(f"{label:<16}{op:<14}{m / ours:>14,.0f}{m / ref:>17,.0f}{ref / ours:>8.2f}"
          "   (reference: numpy.loadtxt)")
    print("ratio = sylva throughput / reference throughput (>1: sylva faster)")


if __name__ == "__main__":
    main()
