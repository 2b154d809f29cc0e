"""Size and speed of billboard trees (Zhou et al. 2013), side by side with the paper's figures.

    python benchmarks/billboard.py [--size 60] [--density 20] [--skip-sample]

Zhou et al. report (Table I, Table II; Intel i5-2300 2.8 GHz): 7,792–95,529
points a tree, model 208–416 B + texture 15–47 kB ("around 40 kB" a tree),
0.37–1.32 s a tree for the whole pipeline without segmentation.  Sylva's
targets: at most 40 kB a tree with its texture, at most 0.1 s a tree.

Data sets:

* the bundled sample tile (resources/sample/sample.laz, airborne, RGB),
  segmented with Sylva's default ``segment_trees``;
* a synthetic stand (testing/synth "medium" mix, ``--size`` m square, scanned
  at ``--density`` pulses/m2 with RGB), segmented by the simulator's truth;
  accuracy against the true crown base / crown diameter / stem count;
* three dense single trees like the paper's (8k, 46k, 96k points: a stem
  cylinder under an ellipsoidal crown, terrestrial-like), with known trunk.

Printed: trees, points per tree (median), the share with a single trunk,
seconds per tree for each step (median; shape fitting §VI-A, textures
§VI-B, quads/atlas, PNG encoding), the total (median, p95), kB a tree
(GLB of all trees / trees, and the texture PNG alone, median and max).
Times are wall-clock (and CPU time of the process, which counts the
threads of numpy/scikit-learn too) on a machine that may be shared.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from sylva.core.export import ExportFrame
from sylva.core.export.georef import Georef, default_origin
from sylva.core.export.gltf import glb_bytes
from sylva.core.export.model import TreeModel
from sylva.core.reconstruct.billboard import Billboard, billboard_tree

HERE = Path(__file__).resolve()
SAMPLE = HERE.parents[1] / "resources" / "sample" / "sample.laz"
PAPER = "paper: ~40 kB a tree (15.2–46.6 kB texture + 208–416 B model), 0.37–1.32 s a tree"


def _groups(labels):
    idx = np.flatnonzero(labels > 0)
    order = idx[np.argsort(labels[idx], kind="stable")]
    lab = labels[order]
    cuts = np.flatnonzero(np.diff(lab)) + 1
    return (lab[np.concatenate([[0], cuts])] if len(lab) else np.zeros(0, int)), np.split(order, cuts)


def run_trees(name, trees, crs, method=Billboard()):
    """trees: list of (tree_id, xyz local metres, rgb or None, ground_z, base_crs (3,))."""
    import sklearn.cluster  # noqa: F401  (import once, outside the timings: the GMM seeds with k-means++)

    rows, models, bbs = [], [], []
    for tree_id, xyz, rgb, ground_z, to_crs in trees:
        t0, c0 = time.perf_counter(), time.process_time()
        bb = billboard_tree(xyz, method, rgb=rgb, ground_z=ground_z, tree_id=tree_id)
        t1 = time.perf_counter()
        png = bb.png()
        t2, c2 = time.perf_counter(), time.process_time()
        rows.append(dict(points=len(xyz), shape=bb.timings["shape"], texture=bb.timings["texture"],
                         quads=bb.timings["quads"], png=t2 - t1, total=t2 - t0, cpu=c2 - c0, png_kb=len(png) / 1000.0,
                         trunk=bb.has_trunk))
        bbs.append(bb)
        models.append(TreeModel(tree_id, to_crs(bb.origin), None, attributes=bb.summary(), billboard=bb))
    frame = ExportFrame(crs)
    georef = Georef(frame, default_origin(models))
    t0 = time.perf_counter()
    glb = glb_bytes(models, georef, content="billboard")
    t_glb = time.perf_counter() - t0
    col = {k: np.array([r[k] for r in rows]) for k in rows[0]}
    n = len(rows)
    print(f"\n== {name}: {n} trees, {int(np.median(col['points'])):,} points a tree (median), "
          f"{col['trunk'].mean():.0%} with a single trunk")
    print("  seconds a tree (median): " + ", ".join(f"{k} {np.median(col[k]):.3f}"
                                                   for k in ("shape", "texture", "quads", "png")))
    print(f"  total a tree: mean {col['total'].mean():.3f} s, median {np.median(col['total']):.3f} s, p95 {np.percentile(col['total'], 95):.3f} s, "
          f"max {col['total'].max():.3f} s; CPU median {np.median(col['cpu']):.3f} s; "
          f"GLB writing {t_glb / n:.3f} s a tree")
    print(f"  size a tree: GLB {len(glb) / n / 1000:.1f} kB (all trees / trees); texture PNG median "
          f"{np.median(col['png_kb']):.1f} kB, max {col['png_kb'].max():.1f} kB")
    print(f"  targets: <= 40 kB and <= 0.1 s a tree; {PAPER}")
    return bbs, col


def sample_trees():
    from sylva.core.io import read_cloud
    from sylva.core.segment import segment_trees
    from sylva.core.terrain import normalize

    cloud = normalize(read_cloud(SAMPLE))
    labels = segment_trees(cloud)
    local = cloud.local_xyz()
    rgb = np.column_stack([cloud.attrs[c] for c in ("red", "green", "blue")])
    h = np.asarray(cloud.attrs["height"])
    ids, groups = _groups(labels)
    out = []
    for tid, idx in zip(ids, groups):
        gz = float(np.median(local[idx, 2] - h[idx]))
        out.append((int(tid), local[idx], rgb[idx], gz, lambda o, c=cloud: c.from_local(o[None, :])[0]))
    return out, cloud.crs


def synthetic_trees(size, density):
    from sylva.testing.synth import ScanSpec, StandSpec, make_stand, simulate_scan

    stand = make_stand(StandSpec(width_m=size, depth_m=size, stems_per_ha=250, crown_overlap=0.5, seed=1))
    scan = simulate_scan(stand, ScanSpec(pulse_density=density, rgb=True, seed=1))
    cloud = scan.cloud
    local = cloud.local_xyz()
    rgb = np.column_stack([cloud.attrs[c] for c in ("red", "green", "blue")])
    truth = {t.tree_id: t for t in stand.trees}
    ids, groups = _groups(np.asarray(scan.truth_tree).astype(np.int64))
    out = []
    vm = cloud.units.vertical_m
    for tid, idx in zip(ids, groups):
        t = truth[int(tid)]
        gz = float(np.median(local[idx, 2] - (cloud.xyz[idx, 2] - t.ground_z) * vm))
        out.append((int(tid), local[idx], rgb[idx], gz, lambda o, c=cloud: c.from_local(o[None, :])[0]))
    return out, cloud.crs, truth


def dense_tree(n_points, seed):
    rng = np.random.default_rng(seed)
    n_trunk = n_points // 4
    z = rng.uniform(0, 6.0, n_trunk)
    a = rng.uniform(0, 2 * np.pi, n_trunk)
    trunk = np.column_stack([0.03 * z + 0.2 * np.cos(a), 0.2 * np.sin(a), z])
    u = rng.normal(size=(n_points - n_trunk, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    u *= rng.uniform(0.6, 1.0, len(u))[:, None]
    crown = np.column_stack([0.17 + 3.5 * u[:, 0], 3.5 * u[:, 1], 10.0 + 5.0 * u[:, 2]])
    xyz = np.vstack([trunk, crown])
    rgb = np.vstack([np.tile((110, 80, 50), (len(trunk), 1)), np.tile((50, 120, 40), (len(crown), 1))])
    rgb = np.clip(rgb + rng.normal(0, 10, rgb.shape), 0, 255).astype(np.uint8)
    return xyz, rgb


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=float, default=60.0, help="synthetic stand edge (m)")
    ap.add_argument("--density", type=float, default=20.0, help="synthetic pulses per m2")
    ap.add_argument("--skip-sample", action="store_true")
    args = ap.parse_args()

    if not args.skip_sample and SAMPLE.exists():
        trees, crs = sample_trees()
        run_trees(f"bundled sample ({SAMPLE.name}, airborne, segment_trees)", trees, crs)

    trees, crs, truth = synthetic_trees(args.size, args.density)
    bbs, col = run_trees(f"synthetic stand ({args.size:.0f} m, {args.density:.0f} pulses/m2, truth segmentation)",
                         trees, crs)
    single = np.array([truth[t[0]].n_stems == 1 for t in trees])
    found = col["trunk"]
    width = np.array([np.median(b.crown_boxes[:, 1] - b.crown_boxes[:, 0]) for b in bbs])
    true_d = np.array([2 * truth[t[0]].crown_radius_m for t in trees])
    print(f"  accuracy: crown width / true crown diameter median {np.median(width / true_d):.2f}; "
          f"single trunk found in {found[single].mean():.0%} of single-stem trees, "
          f"{found[~single].mean() if (~single).any() else 0:.0%} of multi-stem trees")
    if found.any():
        cbh = np.array([truth[t[0]].crown_base_height_m for t in trees])
        th = np.array([b.trunk_height_m for b in bbs])
        print(f"  trunk height - true crown base height (trees with a trunk): median "
              f"{np.median(th[found] - cbh[found]):+.2f} m, |error| p90 "
              f"{np.percentile(np.abs(th[found] - cbh[found]), 90):.2f} m")

    dense = []
    for k, n in enumerate((7_792, 45_936, 95_529)):   # the point counts of the paper's Table I
        xyz, rgb = dense_tree(n, k)
        dense.append((k + 1, xyz, rgb, 0.0, lambda o: np.array([500000.0, 5400000.0, 300.0]) + o))
    bbs, col = run_trees("dense single trees with the paper's point counts (7,792 / 45,936 / 95,529)", dense,
                         "EPSG:32632")
    for (tid, xyz, *_), b, t, cpu in zip(dense, bbs, col["total"], col["cpu"]):
        lean = (b.trunk_axis[1] - b.trunk_axis[0]) if b.has_trunk else None
        print(f"  {len(xyz):>6,} points: {t:.3f} s (CPU {cpu:.3f} s), texture {len(b.png()) / 1000:.1f} kB, trunk "
              f"{'yes' if b.has_trunk else 'no'}, trunk height {b.trunk_height_m:.2f} m (truth: crown "
              f"base 5.0), lean {lean[0] / lean[2] if lean is not None else float('nan'):.3f} (truth 0.030), "
              f"width {b.trunk_width_m:.2f} m (truth 0.40)")


if __name__ == "__main__":
    main()
