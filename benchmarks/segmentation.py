"""Individual-tree segmentation: accuracy, agreement with lidR, throughput and memory.

    python benchmarks/segmentation.py            # everything (1, 5 and 20 M points)
    python benchmarks/segmentation.py --quick    # throughput at 1 M points only
    python benchmarks/segmentation.py --stands dense --densities 20 --sizes 0
                                                 # one setting of the table, no throughput

Prints, for every method side by side:

1. detection precision / recall / F1 and point-level accuracy against the
   synthetic truth of core/synth, on open / medium / dense stands scanned at
   5, 20 and 50 pulses/m2 (matching rule in benchmarks/metrics.py: tops
   within 0.5 x the true crown radius, heights within 15 %, one-to-one by a
   Hungarian assignment; a segmented tree's top is its highest point);
   each method finds its own tree tops with its default window;
2. on ../shared/data/als/MixedConifer.laz (heights already normalised): the
   number of trees and, for trees matched one-to-one to lidR's own treeID
   labels, the median 2-D convex-hull crown IoU (skipped when absent);
   and the same detection scores as in 1. on the plugin's shipped sample
   (resources/sample/sample.laz against sample_trees.csv);
3. throughput (points/s through the whole segment_trees verb: tops,
   voxels, graph, cuts, labels) and the verb's peak memory (tracemalloc
   peak of a second run; numpy reports its buffers to tracemalloc) and the
   process's ru_maxrss, one fresh subprocess per size.
"""
import argparse
import dataclasses
import importlib.util
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
DATA = REPO.parent / "shared" / "data"


def _metrics():
    name = "sylva_bench_metrics"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, HERE / "metrics.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]


def _methods():
    from sylva.core.segment import ChmRegionGrowing, NormalizedCut

    return [("NormalizedCut", NormalizedCut()), ("ChmRegionGrowing", ChmRegionGrowing())]


def accuracy_table(stands=("open", "medium", "dense"), densities=(5, 20, 50)):
    from sylva.core import synth
    from sylva.core.segment import segment_trees
    from sylva.core.terrain import normalize

    M = _metrics()
    print("1. Detection and point accuracy on synthetic stands (100 m x 100 m, core/synth presets)")
    head = f"{'stand':7s} {'pulses/m2':>9s} {'points':>8s} {'trees':>5s}  "
    names = [n for n, _ in _methods()]
    for n in names:
        head += f"| {n[:16]:16s} P     R     F1    ptacc  kpt/s "
    print(head)
    for stand_name in stands:
        for density in densities:
            stand_spec, scan_spec = synth.preset(stand_name, pulse_density=density)
            stand = synth.make_stand(stand_spec)
            scan = synth.simulate_scan(stand, scan_spec)
            cloud = normalize(scan.cloud)
            row = f"{stand_name:7s} {density:9d} {len(cloud):8d} {len(stand.trees):5d}  "
            for _, method in _methods():
                t0 = time.perf_counter()
                labels = segment_trees(cloud, method)
                dt = time.perf_counter() - t0
                r = M.evaluate(cloud.xyz, cloud.attrs["height"], labels, scan.truth_tree,
                               stand.trees)
                row += (f"| {'':16s} {r['precision']:.3f} {r['recall']:.3f} {r['f1']:.3f} "
                        f"{r['point_accuracy']:.3f}  {len(cloud) / dt / 1e3:5.0f} ")
            print(row, flush=True)
    print()


def mixed_conifer():
    path = DATA / "als" / "MixedConifer.laz"
    print("2. MixedConifer.laz (lidR sample, EPSG:26912, heights normalised) vs lidR's treeID")
    if not path.exists():
        print(f"   skipped: {path} not found\n")
        return
    import laspy

    from sylva.core.cloud import PointCloud
    from sylva.core.segment import segment_trees

    las = laspy.read(str(path))
    xyz = np.column_stack([las.x, las.y, las.z])
    attrs = {"height": np.asarray(las.z, dtype=np.float64),
             "classification": np.asarray(las.classification),
             "intensity": np.asarray(las.intensity)}
    cloud = PointCloud(xyz, attrs=attrs, source=str(path))
    ref = np.asarray(las["treeID"])
    print(f"   {len(cloud)} points; lidR treeID: {len(np.unique(ref[ref > 0]))} trees")
    for name, method in _methods():
        t0 = time.perf_counter()
        labels = segment_trees(cloud, method)
        dt = time.perf_counter() - t0
        n_ours, n_ref, ious = _metrics().crown_iou(xyz[:, :2], labels, ref)
        print(f"   {name:16s} trees {len(np.unique(labels[labels > 0])):4d}   matched to lidR "
              f"{len(ious):4d} of {n_ref}   median crown IoU {np.median(ious):.3f}   "
              f"({dt:.1f} s)")
    print()


def shipped_sample():
    """Detection scores on resources/sample/sample.laz against sample_trees.csv."""
    import laspy

    from sylva.core.io.las import read_las
    from sylva.core.segment import segment_trees
    from sylva.core.synth import read_truth
    from sylva.core.terrain import normalize

    laz = REPO / "resources" / "sample" / "sample.laz"
    print("   shipped sample (resources/sample/sample.laz vs sample_trees.csv):")
    if not laz.exists():
        print(f"   skipped: {laz} not found\n")
        return
    cloud = normalize(read_las(str(laz)))
    truth = np.asarray(laspy.read(str(laz)).true_tree)
    trees = read_truth(laz.with_name("sample_trees.csv"))
    for name, method in _methods():
        labels = segment_trees(cloud, method)
        r = _metrics().evaluate(cloud.xyz, cloud.attrs["height"], labels, truth, trees)
        print(f"   {name:16s} trees {r['n_detected']:4d} of {r['n_true']}   P {r['precision']:.3f} "
              f"R {r['recall']:.3f} F1 {r['f1']:.3f} ptacc {r['point_accuracy']:.3f}")
    print()


# --------------------------------------------------------------------------- throughput

def _make_input(n_points: int, path: str) -> None:
    """Child: a medium synthetic stand at 20 pulses/m2 with ~n_points points, saved as .npz."""
    from sylva.core import synth
    from sylva.core.terrain import normalize

    per_m2 = 31.0   # points/m2 of the medium preset at 20 pulses/m2 (multiple returns)
    side = float(np.sqrt(n_points / per_m2))
    stand_spec, scan_spec = synth.preset("medium", pulse_density=20.0)
    stand_spec = dataclasses.replace(stand_spec, width_m=side, depth_m=side)
    stand = synth.make_stand(stand_spec)
    scan = synth.simulate_scan(stand, scan_spec)
    cloud = normalize(scan.cloud)
    np.savez(path, xyz=cloud.xyz, height=cloud.attrs["height"],
             classification=cloud.attrs["classification"], intensity=cloud.attrs["intensity"],
             crs=str(cloud.crs.to_string()) if cloud.crs is not None else "")


def _run_verb(path: str) -> dict:
    """Child: load the input, then time segment_trees and measure its peak memory."""
    from sylva.core.cloud import PointCloud
    from sylva.core.segment import segment_trees

    data = np.load(path)
    cloud = PointCloud(data["xyz"], attrs={"height": data["height"],
                                           "classification": data["classification"],
                                           "intensity": data["intensity"]})
    t0 = time.perf_counter()
    c0 = time.process_time()
    labels = segment_trees(cloud)
    dt = time.perf_counter() - t0
    cpu = time.process_time() - c0
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    # a second run under tracemalloc (numpy reports its buffers to it): the verb's own peak
    tracemalloc.start()
    segment_trees(cloud)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return {"points": len(cloud), "seconds": dt, "cpu_seconds": cpu, "trees": int(len(np.unique(labels[labels > 0]))),
            "rss_mb": rss, "extra_mb": peak / 2 ** 20}


def throughput(sizes):
    print("3. Throughput of segment_trees(cloud) (NormalizedCut, tops found), one core,"
          " medium stand at 20 pulses/m2\n   (points/s on the wall clock; points per CPU"
          " second is robust to other jobs sharing the machine)")
    print(f"   {'points':>10s} {'trees':>7s} {'seconds':>8s} {'points/s':>10s} "
          f"{'CPU s':>7s} {'points/CPU s':>12s} "
          f"{'verb peak MB':>13s} {'MB/Mpt':>7s} {'process maxrss MB':>18s}")
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    for n in sizes:
        with tempfile.TemporaryDirectory() as tmp:
            path = os.path.join(tmp, "input.npz")
            subprocess.run([sys.executable, __file__, "--child-make", str(n), path], check=True,
                           env=env)
            out = subprocess.run([sys.executable, __file__, "--child-run", path], check=True,
                                 env=env, capture_output=True, text=True).stdout
            r = json.loads(out.strip().splitlines()[-1])
        mpts = r["points"] / 1e6
        print(f"   {r['points']:10d} {r['trees']:7d} {r['seconds']:8.1f} "
              f"{r['points'] / r['seconds']:10.0f} {r['cpu_seconds']:7.1f} "
              f"{r['points'] / r['cpu_seconds']:12.0f} {r['extra_mb']:13.0f} "
              f"{r['extra_mb'] / mpts:7.0f} {r['rss_mb']:18.0f}", flush=True)
    print()


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="throughput at 1 M points only")
    parser.add_argument("--stands", default="open,medium,dense",
                        help="comma-separated stands of the accuracy table (open, medium, dense)")
    parser.add_argument("--densities", default="5,20,50",
                        help="comma-separated pulse densities of the accuracy table")
    parser.add_argument("--sizes", default=None,
                        help="comma-separated throughput sizes in points (0: no throughput)")
    parser.add_argument("--no-real", action="store_true",
                        help="skip MixedConifer and the shipped sample")
    parser.add_argument("--child-make", nargs=2, help=argparse.SUPPRESS)
    parser.add_argument("--child-run", nargs=1, help=argparse.SUPPRESS)
    parser.add_argument("--skip-accuracy", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child_make:
        _make_input(int(args.child_make[0]), args.child_make[1])
        return
    if args.child_run:
        print(json.dumps(_run_verb(args.child_run[0])))
        return
    if not args.skip_accuracy:
        stands = tuple(s for s in args.stands.split(",") if s)
        densities = tuple(float(d) if "." in d else int(d) for d in args.densities.split(",") if d)
        if stands and densities:
            accuracy_table(stands, densities)
        if not args.no_real:
            mixed_conifer()
            shipped_sample()
    if args.sizes is not None:
        sizes = [int(float(n)) for n in args.sizes.split(",") if float(n) > 0]
    else:
        sizes = [1_000_000] if args.quick else [1_000_000, 5_000_000, 20_000_000]
    if sizes:
        throughput(sizes)


if __name__ == "__main__":
    main()
