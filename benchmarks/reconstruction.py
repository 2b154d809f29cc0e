"""Speed and quality of tree reconstruction: greedy skeleton (Hu et al. 2017), guided growth
(Guo et al. 2018) and the hybrid of Hu §6.2, side by side; then whole models against truth.

    python benchmarks/reconstruction.py [--seed 1] [--size 100] [--k 16] [--per-tree]
                                        [--methods greedy,guided,hybrid]
    python benchmarks/reconstruction.py --kernels [--seed 1] [--size 100]

Data sets, each tree reconstructed from its own points with
``reconstruct_tree(TreePoints(...), GreedySkeleton(...))``:

* a synthetic stand (testing/synth, "medium" mix of conifers, broadleaves and
  multi-stem trees, ``--size`` metres square) scanned at 10 and 20 pulses/m2;
  segmentation = the simulator's truth (``truth_tree``), ground_z = the
  true terrain height at the stem;
* ../shared/data/als/MixedConifer.laz (lidR's sample tile, ~4.7 pts/m2) with
  lidR's ``treeID`` as segmentation, without the ground points (class 2,
  which lidR labels with the tree above them); Z is already height above
  ground, so ground_z = 0.  Skipped when the file is absent.

Printed per data set: trees, points per tree (median), wall time per tree
(median, p95) and CPU time per tree (median; the machine may be shared),
milliseconds per 1,000 points, median time of each step, median visited
fraction, share of trees with a connected graph, share connected *and*
visited >= 85 % (the paper's hybrid threshold, §6.2: the rest go to the
fallback), coverage (share of a tree's points within 0.5 m of its skeleton
segments, median over trees) and, for synthetic trees, the horizontal
distance from the skeleton root to the true stem base (median; share
< 0.5 m; single-stem trees).

``--kernels`` instead times the compiled kernels (core/jit.py, numba):
the cold compile (first call in a fresh process with an empty cache) and
the cached load (first call in a fresh process with the cache written),
each in its own subprocess; then, on every tree of the synthetic stand (20
pulses/m2) and of the bundled sample, CPU time per tree (process_time) of
thin_voxels, build_graph and greedy_skeleton.  (The numpy/heapq/cKDTree
implementations the kernels replaced, and this benchmark's side-by-side
timing of them, are in git history (commit 3818fe1: 29 -> 7 ms CPU per
tree for the five GreedySkeleton steps when they moved).)
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from sylva.core.reconstruct import GreedySkeleton, GuidedGrowth, Hybrid, TreePoints, reconstruct_tree

HERE = Path(__file__).resolve()

STEPS = ("trunk", "thinning", "graph", "direction", "skeleton")
DATA = HERE.parents[1].parent / "shared" / "data"


def run_trees(trees, method, bases=None, species=None):
    """Reconstruct every tree; collect figures."""
    rows = []
    for i, tree in enumerate(trees):
        c0 = time.process_time()
        t0 = time.perf_counter()
        rec = reconstruct_tree(tree, method)
        wall = time.perf_counter() - t0
        cpu = time.process_time() - c0
        cover = float((rec.skeleton.distance(tree.xyz) < 0.5).mean())
        row = dict(tree=tree.tree_id, n=len(tree), wall=wall, cpu=cpu, visited=rec.visited_fraction,
                   connected=rec.connected, cover=cover, flags=",".join(rec.flags),
                   rule=rec.stats.get("trunk_rule", "-"), nodes=len(rec.skeleton),
                   cand=rec.stats.get("n_candidates", 0))
        for s in STEPS:
            row[s] = rec.stats.get(f"t_{s}_s", np.nan)
        row["visited_all"] = rec.stats.get("visited_fraction_all", np.nan)
        if bases is not None:
            row["root_err"] = float(np.hypot(*(rec.skeleton.nodes[0, :2] - bases[i])))
            row["species"] = species[i][0]
            row["interior"] = species[i][1]
        rows.append(row)
    return rows


def summarise(name, rows, per_tree=False):
    col = lambda k: np.array([r[k] for r in rows], dtype=float)  # noqa: E731
    n, wall, cpu, vis = col("n"), col("wall"), col("cpu"), col("visited")
    conn = col("connected").astype(bool)
    print(f"\n== {name}: {len(rows)} trees, median {np.median(n):.0f} points/tree "
          f"(p5 {np.percentile(n, 5):.0f}, p95 {np.percentile(n, 95):.0f})")
    print(f"   time per tree   wall median {np.median(wall) * 1e3:6.2f} ms   p95 {np.percentile(wall, 95) * 1e3:6.2f} ms"
          f"   cpu median {np.median(cpu) * 1e3:6.2f} ms")
    print(f"   per 1000 points wall {wall.sum() / n.sum() * 1e6:6.2f} ms   cpu {cpu.sum() / n.sum() * 1e6:6.2f} ms")
    print("   per step (median ms): " + "  ".join(f"{s} {np.nanmedian(col(s)) * 1e3:.2f}" for s in STEPS))
    print(f"   visited fraction median {np.median(vis):.3f} (incl. added trunk candidates "
          f"{np.nanmedian(col('visited_all')):.3f})   connected {conn.mean():.1%}   "
          f"connected & visited>=85% {(conn & (vis >= 0.85)).mean():.1%}")
    print(f"   coverage (points within 0.5 m of the skeleton) median {np.median(col('cover')):.3f}   "
          f"mean {np.mean(col('cover')):.3f}")
    flags = [f for r in rows for f in r["flags"].split(",") if f]
    if flags:
        print("   flags: " + ", ".join(f"{f} {flags.count(f)}" for f in sorted(set(flags))))
    if "root_err" in rows[0]:
        single = np.array([r["species"] != "multistem" for r in rows])
        inner = single & np.array([r["interior"] for r in rows])
        eq3 = np.array([r["rule"] == "eq3" for r in rows])
        err = col("root_err")
        print(f"   root to true stem base, single-stem trees ({single.sum()}): median {np.median(err[single]):.2f} m, "
              f"< 0.5 m {(err[single] < 0.5).mean():.1%};  of them with the crown inside the stand "
              f"({inner.sum()}): median {np.median(err[inner]):.2f} m, < 0.5 m {(err[inner] < 0.5).mean():.1%} "
              f"(Eq. 3 trees {(inner & eq3).sum()}: median {np.median(err[inner & eq3]) if (inner & eq3).any() else np.nan:.2f} m; "
              f"Eq. 4 trees {(inner & ~eq3).sum()}: < 0.5 m {(err[inner & ~eq3] < 0.5).mean():.1%})")
        if (~single).any():
            print(f"   multi-stem trees ({(~single).sum()}): root to common stem base median {np.median(err[~single]):.2f} m")
    if per_tree:
        for r in rows:
            extra = f" {r['species']:9s} root_err {r['root_err']:.2f}" if "root_err" in r else ""
            print(f"     tree {r['tree']:4d} n {r['n']:5d} cand {r['cand']:5d} nodes {r['nodes']:5d} "
                  f"vis {r['visited']:.2f} conn {int(r['connected'])} cover {r['cover']:.2f} "
                  f"{r['wall'] * 1e3:6.1f} ms {r['rule']}{extra} {r['flags']}")


def synthetic(density, seed, size):
    from sylva.testing import synth
    stand_spec, scan_spec = synth.preset("medium", pulse_density=density, seed=seed)
    from dataclasses import replace
    stand_spec = replace(stand_spec, width_m=size, depth_m=size)
    stand = synth.make_stand(stand_spec)
    scan = synth.simulate_scan(stand, scan_spec)
    origin = np.array([*stand.spec.origin, 0.0])
    xyz = scan.cloud.xyz - origin
    order = np.argsort(scan.truth_tree, kind="stable")
    ids, start = np.unique(scan.truth_tree[order], return_index=True)
    groups = dict(zip(ids.tolist(), np.split(order, start[1:])))
    trees, bases, species = [], [], []
    for t in stand.trees:
        idx = groups.get(t.tree_id)
        if idx is None or t.tree_id == 0:
            continue
        trees.append(TreePoints(t.tree_id, xyz[idx], t.ground_z))
        base = np.array([t.x, t.y]) - origin[:2]
        bases.append(base)
        inside = bool((base > t.crown_radius_m).all() and (base < np.array([size, size]) - t.crown_radius_m).all())
        species.append((t.species, inside))
    return trees, bases, species


def sample_tile():
    """The bundled sample (resources/sample): its own truth segmentation and terrain."""
    import laspy

    from sylva.testing.synth import read_truth

    las = laspy.read(str(HERE.parents[1] / "resources" / "sample" / "sample.laz"))
    truth = {t.tree_id: t for t in read_truth(HERE.parents[1] / "resources" / "sample" / "sample_trees.csv")}
    xyz = np.c_[np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)]
    origin = np.array([xyz[:, 0].min(), xyz[:, 1].min(), 0.0])
    xyz -= origin
    tid = np.where(np.asarray(las["true_kind"]) <= 2, np.asarray(las["true_tree"]), 0).astype(np.int64)
    order = np.argsort(tid, kind="stable")
    ids, start = np.unique(tid[order], return_index=True)
    return [TreePoints(int(i), xyz[g], truth[int(i)].ground_z) for i, g in zip(ids, np.split(order, start[1:]))
            if i > 0]


def model_errors(density, seed, size):
    """Whole models (core.forest.model_trees) of a synthetic stand against its truth."""
    from dataclasses import replace

    from sylva.testing import synth
    from sylva.core.forest import model_trees
    from sylva.core.measure import tree_metrics
    from sylva.core.terrain import normalize

    stand_spec, scan_spec = synth.preset("medium", pulse_density=density, seed=seed)
    stand = synth.make_stand(replace(stand_spec, width_m=size, depth_m=size))
    scan = synth.simulate_scan(stand, scan_spec)
    labels = np.where(scan.truth_kind <= synth.CROWN, scan.truth_tree, 0).astype(np.int64)
    cloud = normalize(scan.cloud)
    metrics = tree_metrics(cloud, labels)
    t0 = time.perf_counter()
    trees = model_trees(cloud, labels, metrics)
    dt = time.perf_counter() - t0
    truth = {t.tree_id: t for t in stand.trees}
    rec = {t.tree_id: t for t in trees}
    ids = metrics.tree_id
    noise = np.array([rec[i].record["quality"] == "noise" for i in ids])
    modelled = np.array([len(rec[i].wood.faces) > 0 for i in ids])
    th = np.array([truth[i].height for i in ids])
    tcd = np.array([2 * truth[i].crown_radius_m for i in ids])
    tdbh = np.array([truth[i].dbh_m for i in ids])
    dbh = np.array([rec[i].record["dbh"] for i in ids])
    ok = ~noise
    rel = lambda a, b: np.abs(a - b) / b  # noqa: E731
    print(f"\n== whole models, synthetic 'medium' {size:.0f} m at {density:g} pulses/m2: {len(ids)} trees "
          f"({noise.sum()} noise), {dt / len(ids) * 1e3:.1f} ms per tree (reconstruction + mesh + leaves)")
    print(f"   non-noise trees with a model: {modelled[ok].mean():.1%}   methods: "
          + ", ".join(f"{m} {sum(t.record['method'] == m for t in trees)}" for m in sorted({t.record['method'] for t in trees})))
    print(f"   height error: median {np.median(metrics.height[ok] - th[ok]):+.2f} m, "
          f"MAE {np.mean(np.abs(metrics.height[ok] - th[ok])):.2f} m")
    print(f"   crown diameter error: median {np.median(metrics.crown_diameter[ok] - tcd[ok]):+.2f} m, "
          f"median relative {np.median(rel(metrics.crown_diameter[ok], tcd[ok])):.1%}")
    print(f"   DBH error ({', '.join(sorted({t.record['dbh_source'] for t in trees}))}): "
          f"median {np.median(dbh[ok] - tdbh[ok]) * 100:+.1f} cm, median relative {np.median(rel(dbh[ok], tdbh[ok])):.1%}")


def mixed_conifer():
    path = DATA / "als" / "MixedConifer.laz"
    if not path.exists():
        return None
    import laspy
    las = laspy.read(str(path))
    xyz = np.c_[np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)]
    xyz[:, :2] -= xyz[:, :2].min(axis=0)
    tid = np.asarray(las.treeID, dtype=np.float64)
    ok = np.isfinite(tid) & (tid > 0) & (tid < 1e9)        # 0 / huge = no tree
    ok &= np.asarray(las.classification) != 2               # lidR gives ground points a treeID too
    tid = np.where(ok, tid, 0).astype(np.int64)
    order = np.argsort(tid, kind="stable")
    ids, start = np.unique(tid[order], return_index=True)
    return [TreePoints(int(i), xyz[g], 0.0) for i, g in zip(ids, np.split(order, start[1:])) if i > 0]


_COLD_SCRIPT = """
import time
t0 = time.perf_counter()
import numpy as np
from sylva.core.reconstruct import GreedySkeleton, TreePoints
t1 = time.perf_counter()
rng = np.random.default_rng(0)
tree = TreePoints(0, rng.random((300, 3)) * [4, 4, 10] + [0, 0, 5], 0.0)
c = time.process_time(); t2 = time.perf_counter()
GreedySkeleton().reconstruct(tree)
t3 = time.perf_counter(); c3 = time.process_time()
GreedySkeleton().reconstruct(tree)
t4 = time.perf_counter()
print(t1 - t0, t3 - t2, c3 - c, t4 - t3)
"""


def jit_start_up():
    """Cold compile and cached load of the kernels, each in a fresh process."""
    import os
    import subprocess
    import sys
    import tempfile

    from sylva.core.jit import jit_status
    print(f"\n== compiled kernels: {jit_status()}")
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        for label in ("cold (empty cache)", "cached", "cached"):
            out = subprocess.run([sys.executable, "-c", _COLD_SCRIPT], env=env, capture_output=True, text=True,
                                 check=True).stdout.split()
            imp, first, first_cpu, second = map(float, out)
            print(f"   {label:19s} import sylva {imp:5.2f} s   first tree (numba import + kernels) "
                  f"{first:6.2f} s wall, {first_cpu:6.2f} s cpu   next tree {second * 1e3:6.1f} ms")


def kernel_times(name, trees):
    """CPU ms per tree of the compiled steps thin_voxels, build_graph and greedy_skeleton."""
    from sylva.core.reconstruct.direction import direction_field
    from sylva.core.reconstruct.graph import build_graph
    from sylva.core.reconstruct.model import screen
    from sylva.core.reconstruct.skeleton import choose_end, greedy_skeleton
    from sylva.core.reconstruct.thinning import thin_voxels
    from sylva.core.reconstruct.trunk import add_trunk_points

    m = GreedySkeleton()
    cpu = {"thin": 0.0, "graph": 0.0, "greedy": 0.0}
    count = 0
    T = time.process_time
    for tree in trees:
        if screen(tree, m.min_points, m.name, None)[2] is not None:
            continue
        count += 1
        trunk = add_trunk_points(tree.xyz, tree.ground_z, m.trunk_radius_m, m.trunk_spacing_m)
        added = trunk.points[1:]
        all_xyz = np.concatenate([tree.xyz, added])
        keep = np.r_[np.zeros(len(tree.xyz), bool), np.ones(len(added), bool)]
        t = T()
        th = thin_voxels(all_xyz, m.voxel_m, keep=keep)
        cpu["thin"] += T() - t
        cand = np.concatenate([trunk.root[None, :], th.points])
        t = T()
        g = build_graph(cand, m.radius_m, m.k)
        cpu["graph"] += T() - t
        u = direction_field(cand)
        end = choose_end(cand, g.adjacency, 0, trunk.direction, m.alpha_max_deg)
        t = T()
        greedy_skeleton(cand, g.adjacency, u, 0, end, m.alpha_max_deg, m.beta_max_deg, m.phi_max_deg,
                        m.regrow_pruned)
        cpu["greedy"] += T() - t
    print(f"\n== {name}: {count} trees, CPU ms per tree (process_time) of the compiled steps")
    for step, label in (("thin", "thin_voxels (§5.1)"), ("graph", "build_graph (§5.2)"),
                        ("greedy", "greedy_skeleton (§5.4)")):
        print(f"   {label:24s} {cpu[step] / count * 1e3:6.2f} ms")
    print(f"   {'the three steps':24s} {sum(cpu.values()) / count * 1e3:6.2f} ms")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--size", type=float, default=100.0, help="synthetic stand side in metres")
    ap.add_argument("--k", type=int, default=None, help="override GreedySkeleton.k")
    ap.add_argument("--densities", default="10,20")
    ap.add_argument("--per-tree", action="store_true")
    ap.add_argument("--verbatim", action="store_true", help="Algorithm 2 verbatim (regrow_pruned=False)")
    ap.add_argument("--methods", default="greedy,guided,hybrid")
    ap.add_argument("--kernels", action="store_true",
                    help="time the compiled kernels (cold/cached start-up, CPU per tree of each step)")
    args = ap.parse_args(argv)
    if args.kernels:
        jit_start_up()
        reconstruct_tree(TreePoints(0, np.random.default_rng(0).random((300, 3)) * [4, 4, 10] + [0, 0, 5], 0.0),
                         GreedySkeleton())                              # load the kernels once
        trees, _, _ = synthetic(20.0, args.seed, args.size)
        kernel_times(f"synthetic 'medium' stand {args.size:.0f} m, 20 pulses/m2", trees)
        kernel_times("bundled sample (resources/sample)", sample_tile())
        return
    kw = {}
    if args.k is not None:
        kw["k"] = args.k
    if args.verbatim:
        kw["regrow_pruned"] = False
    greedy = GreedySkeleton(**kw)
    methods = {"greedy": greedy, "guided": GuidedGrowth(), "hybrid": Hybrid(primary=greedy)}
    chosen = [m for m in args.methods.split(",") if m]
    print("methods: " + "; ".join(f"{m} = {methods[m]}" for m in chosen))

    # warm-up (imports, the thinning memo) on a throwaway tree
    rng = np.random.default_rng(0)
    for m in chosen:
        reconstruct_tree(TreePoints(0, rng.random((300, 3)) * [4, 4, 10] + [0, 0, 5], 0.0), methods[m])

    datasets = []
    for density in [float(d) for d in args.densities.split(",") if d]:
        t0 = time.perf_counter()
        trees, bases, species = synthetic(density, args.seed, args.size)
        datasets.append((f"synthetic 'medium' stand {args.size:.0f} m, {density:g} pulses/m2 "
                         f"(simulated in {time.perf_counter() - t0:.1f} s)", trees, bases, species))
    datasets.append(("bundled sample (resources/sample, truth segmentation)", sample_tile(), None, None))
    mc = mixed_conifer()
    if mc is None:
        print("\n== MixedConifer.laz: skipped (../shared/data/als/MixedConifer.laz not found)")
    else:
        datasets.append(("MixedConifer.laz (lidR treeID segmentation, ground_z = 0)", mc, None, None))
    for name, trees, bases, species in datasets:
        for m in chosen:
            rows = run_trees(trees, methods[m], bases, species)
            summarise(f"{name} [{m}]", rows, args.per_tree)
    for density in [float(d) for d in args.densities.split(",") if d]:
        model_errors(density, args.seed, args.size)


if __name__ == "__main__":
    main()
