"""Dense-scan benchmark: Yan et al. 2009 variational k-means + TreeQSM-like cylinders.

    python benchmarks/dense.py            # synthetic trees, TLS trees, segmentation timing
    python benchmarks/dense.py --quick    # smaller timing runs
    python benchmarks/dense.py --timing   # segmentation timing only
    python benchmarks/dense.py --only sylva   # one configuration (paper / tls / sylva)

Prints, per method configuration ("paper": Yan's defaults, principal axis +
enclosing circle; "tls": surface-normal axis + least-squares circles, the
first increment's choice; "sylva": what ``sylva:reconstructtrees`` uses now,
"tls" + clusters split down to 30 points + cylinder radii and axes refitted
to the points, inner branches dropped after the refit):

* synthetic dense trees with known cylinders (trunk + branches sampled on
  their surfaces with noise, full or one-sided): mean / 95th percentile
  distance from the points to the model surface (cm), share of points within
  2 cm, DBH / height / volume errors against the truth, time per tree, per
  step and per 1,000 points;
* the TLS trees of ../shared/data/tls (if present): the same surface
  figures and times, and the QSM measurements (no truth for them);
* the segmentation time on 34,542 and 217,187 points (TLS tree 7 resampled
  along its kNN segments), against Yan et al.'s Table 1 (5.94 s and 215.2 s).
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from sylva.core.qsm import cylinder_tree, measure_qsm, sample_cylinder_surfaces, surface_distance
from sylva.core.reconstruct import TreePoints
from sylva.core.reconstruct.kmeans import VariationalKMeans, is_dense_scan, segment

HERE = Path(__file__).resolve()

TLS = HERE.parents[1].parent / "shared" / "data" / "tls"
CONFIGS = {
    "paper": VariationalKMeans(),
    "tls": VariationalKMeans(axis="normals", radius="fit"),
    "sylva": VariationalKMeans(axis="normals", radius="fit", refit=True, min_cluster_points=30),
}


def synthetic_specs(kind: str, seed: int):
    """Known cylinder trees: 'small' (30 cm trunk, 4 branches), 'large' (45 cm, 6 + 12 sub-branches)."""
    rng = np.random.default_rng(seed)
    if kind == "small":
        h, r0, nb, sub = 8.0, 0.15, 4, 0
    else:
        h, r0, nb, sub = 14.0, 0.225, 6, 2
    specs = [dict(start=(0, 0, 0), direction=(0, 0, 1), length=h, radius=(r0, 0.04), parent=-1, n=int(h * 2))]
    for i in range(nb):
        z = h * (0.35 + 0.5 * i / nb)
        az = i * 2.4 + rng.uniform(-0.3, 0.3)
        el = np.radians(rng.uniform(25, 45))
        d = np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
        rt = r0 + (0.04 - r0) * z / h
        length = (0.45 - 0.25 * i / nb) * h * 0.6
        specs.append(dict(start=(0, 0, z), direction=d, length=length, radius=(0.55 * rt, 0.015), parent=0,
                          n=max(3, int(length * 2))))
        b = len(specs) - 1
        for j in range(sub):
            f = 0.4 + 0.3 * j
            start = np.array([0, 0, z]) + d * length * f
            az2 = az + (1 if j % 2 else -1) * rng.uniform(0.6, 1.0)
            d2 = np.array([np.cos(az2) * 0.7, np.sin(az2) * 0.7, 0.7])
            rb = 0.55 * rt + (0.015 - 0.55 * rt) * f
            specs.append(dict(start=start, direction=d2, length=length * 0.35, radius=(0.6 * rb, 0.01),
                              parent=b, n=3))
    return specs


def run_tree(name, pts, ground_z, method, truth=None):
    t0 = time.perf_counter()
    model = method.model(TreePoints(0, pts, ground_z))
    t_model = time.perf_counter() - t0
    t0 = time.perf_counter()
    q = measure_qsm(model.cylinders, model.branch_parent, pts, base_z=ground_z if truth is not None else None)
    t_qsm = time.perf_counter() - t0
    t0 = time.perf_counter()
    model.mesh()
    t_mesh = time.perf_counter() - t0
    d = surface_distance(pts, model.cylinders) * 100     # sylva.core.qsm.surface_distance
    st = model.reconstruction.stats
    row = dict(tree=name, n=len(pts), clusters=st.get("n_clusters", 0), fixed=st.get("n_fixed", 0),
               branches=len(model.curves), mean_cm=d.mean(), p95_cm=np.percentile(d, 95),
               within2=(d <= 2).mean() * 100, t_seg=st.get("t_segmentation_s", 0), t_branch=st.get("t_branching_s", 0),
               t_model=st.get("t_modelling_s", 0), t_qsm=t_qsm, t_mesh=t_mesh, t_total=t_model + t_qsm,
               dbh=q.dbh_m, dbh_src=q.dbh_source, height=q.height_m, vol=q.total_volume_m3,
               trunk_vol=q.trunk_volume_m3, flags=",".join(model.reconstruction.flags))
    if truth is not None:
        row.update(truth)
    return row


def print_rows(rows, with_truth):
    head = (f"{'tree':<16}{'points':>8}{'clus':>6}{'fix':>5}{'br':>4}{'mean cm':>9}{'p95 cm':>8}{'<=2cm %':>9}"
            f"{'seg s':>7}{'branch s':>9}{'model s':>8}{'qsm s':>7}{'mesh s':>7}{'s/1k pts':>9}")
    print(head)
    for r in rows:
        print(f"{r['tree']:<16}{r['n']:>8}{r['clusters']:>6}{r['fixed']:>5}{r['branches']:>4}{r['mean_cm']:>9.2f}"
              f"{r['p95_cm']:>8.2f}{r['within2']:>9.1f}{r['t_seg']:>7.2f}{r['t_branch']:>9.3f}{r['t_model']:>8.3f}"
              f"{r['t_qsm']:>7.3f}{r['t_mesh']:>7.3f}{1000 * r['t_total'] / r['n']:>9.3f}")
    if with_truth:
        print(f"{'tree':<16}{'DBH cm':>8}{'true':>7}{'err':>6}{'src':>10}{'H m':>7}{'err':>6}"
              f"{'vol m3':>8}{'true':>7}{'err %':>7}{'trunk':>7}{'true':>7}{'err %':>7}  flags")
        for r in rows:
            print(f"{r['tree']:<16}{100 * r['dbh']:>8.1f}{100 * r['true_dbh']:>7.1f}{100 * (r['dbh'] - r['true_dbh']):>6.1f}"
                  f"{r['dbh_src']:>10}{r['height']:>7.2f}{r['height'] - r['true_h']:>6.2f}{r['vol']:>8.3f}"
                  f"{r['true_vol']:>7.3f}{100 * (r['vol'] / r['true_vol'] - 1):>7.1f}{r['trunk_vol']:>7.3f}"
                  f"{r['true_trunk']:>7.3f}{100 * (r['trunk_vol'] / r['true_trunk'] - 1):>7.1f}  {r['flags']}")
    else:
        print(f"{'tree':<16}{'DBH cm':>8}{'src':>10}{'H m':>7}{'vol m3':>8}{'trunk':>7}  flags")
        for r in rows:
            print(f"{r['tree']:<16}{100 * r['dbh']:>8.1f}{r['dbh_src']:>10}{r['height']:>7.2f}{r['vol']:>8.3f}"
                  f"{r['trunk_vol']:>7.3f}  {r['flags']}")


def synthetic_trees():
    out = []
    for kind, seed in (("small", 0), ("large", 1)):
        truth = cylinder_tree(synthetic_specs(kind, seed))
        h = float(max((truth["start"] + truth["axis"] * truth["length"][:, None])[:, 2].max(), 0))
        trunk = truth["branch"] == 0
        vol = np.pi * truth["radius"] ** 2 * truth["length"]
        zc = truth["start"][trunk, 2]
        i = np.flatnonzero(trunk)[np.searchsorted(zc, 1.3) - 1]
        tr = dict(true_dbh=2 * truth["radius"][i], true_h=h, true_vol=vol.sum(), true_trunk=vol[trunk].sum())
        for scan, vis in (("full", None), ("1side", (1.0, 0.4, 0.0))):
            pts = sample_cylinder_surfaces(truth, spacing_m=0.015, noise_m=0.003, seed=seed + 10, visible=vis)
            out.append((f"{kind}-{scan}", pts, tr))
    return out


def timing(quick: bool):
    src = TLS / "tree7.xyz"
    if src.exists():
        base = np.loadtxt(src)
        what = "TLS tree7"
    else:
        base = sample_cylinder_surfaces(cylinder_tree(synthetic_specs("large", 1)), 0.015, 0.003, seed=3)
        what = "synthetic large tree"
    rng = np.random.default_rng(0)
    sizes = (34_542,) if quick else (34_542, 217_187)
    paper = {34_542: 5.94, 217_187: 215.2}
    _, nbr = cKDTree(base).query(base, k=9)
    print(f"\nsegmentation time on {what} resampled to n points (random points on the segments "
          f"to a random one of the 8 nearest neighbours, + 2 mm noise), Yan et al. Table 1 for comparison")
    print(f"{'points':>8}{'config':>8}{'clusters':>10}{'fixed':>7}{'rounds':>8}{'best s':>9}{'median s':>9}"
          f"{'paper s':>9}{'x (best)':>10}{'x (med)':>10}")
    for n in sizes:
        i = rng.integers(0, len(base), n)
        j = nbr[i, rng.integers(1, 9, n)]
        pts = base[i] + rng.uniform(0, 1, (n, 1)) * (base[j] - base[i]) + rng.normal(0, 0.002, (n, 3))
        for name, m in CONFIGS.items():
            times = []
            for _ in range(3):     # best and median of 3: the machine is shared
                t0 = time.perf_counter()
                seg = segment(pts, m.k, m.n_seeds, m.delta_m, m.max_clusters, m.min_cluster_points, m.max_iter,
                              m.epsilon_rel, seed=m.seed, metric=m.metric, axis=m.axis,
                              tightness="fit" if m.radius == "fit" else "bounding")
                times.append(time.perf_counter() - t0)
            best, med = min(times), float(np.median(times))
            print(f"{n:>8}{name:>8}{seg.n_clusters:>10}{int(seg.fixed.sum()):>7}{seg.rounds:>8}{best:>9.2f}"
                  f"{med:>9.2f}{paper[n]:>9.2f}{paper[n] / best:>9.1f}x{paper[n] / med:>9.1f}x")


def main():
    quick = "--quick" in sys.argv
    if "--timing" in sys.argv:
        timing(quick)
        return
    if "--only" in sys.argv:     # --only NAME: one configuration
        keep = sys.argv[sys.argv.index("--only") + 1]
        for k in list(CONFIGS):
            if k != keep:
                del CONFIGS[k]
    syn = synthetic_trees()
    for name, method in CONFIGS.items():
        print(f"\n=== synthetic dense trees, config {name!r}: {method}")
        print_rows([run_tree(n, p, 0.0, method, t) for n, p, t in syn], True)
    tls = [p for p in (TLS / f"tree{i}.xyz" for i in (1, 7, 13)) if p.exists()]
    if tls:
        for name, method in CONFIGS.items():
            print(f"\n=== TLS trees ({TLS}), config {name!r}")
            rows = []
            for p in tls:
                xyz = np.loadtxt(p)
                rows.append(run_tree(f"{p.stem} d={int(is_dense_scan(xyz))}", xyz, float(xyz[:, 2].min()), method))
            print_rows(rows, False)
    else:
        print(f"\n(no TLS trees at {TLS})")
    timing(quick)


if __name__ == "__main__":
    main()
