"""Individual-tree segmentation: accuracy, agreement with lidR, throughput and memory.

    python benchmarks/segmentation.py            # everything (1, 5 and 20 M points)
    python benchmarks/segmentation.py --quick    # throughput at 1 M points only
    python benchmarks/segmentation.py --stands dense --densities 20 --sizes 0
                                                 # one setting of the table, no throughput
    python benchmarks/segmentation.py --variants '[{}, {"top_window_points": 50}]'
                                                 # what changing a default trades (table 4 only)
    python benchmarks/segmentation.py --pairs    # what tells one tree's two tops from two trees (5 only)
    python benchmarks/segmentation.py --slope 30 --sizes 0 --no-real
                                                 # the table on ground sloping 30 degrees

Prints, for every method side by side:

1. detection precision / recall / F1 and point-level accuracy against the
   synthetic truth of testing/synth (conifers) and sylva/testing/crowns.py
   (broadleaf, mixed, open-grown parkland, and tall mixed stands of 30-60 m),
   on open / medium / dense stands scanned at 2, 5, 20
   and 50 pulses/m2 (matching rule in benchmarks/metrics.py: tops
   within 0.5 x the true crown radius, heights within 15 %, one-to-one by a
   Hungarian assignment; a segmented tree's top is its apex, its highest
   point in elevation);
   every method segments the cloud segmenttrees and the pipeline segment
   (sylva.core.segment.tile.prepare_tile: noise left out, heights from the
   ground the chain classifies), so the figures are what a user gets;
   each method finds its own tree tops with its default window; then, for
   the default method, where the F1 is lost (metrics.losses: false positives
   that are pieces of a matched crown or crowns whose top the matching
   misses; misses inside another tree's segment, and misses whose apex is
   under a neighbour's crown), and the F1 and median crown IoU it reaches
   given each true tree's apex as its top, beside the IoU of
   ChmRegionGrowing's crowns from the same tops (the crown boundaries alone),
   and how many true trees have their apex under a neighbour's crown (what
   tops searched on the canopy surface cannot see);
   each method's median 2-D crown IoU with the true trees (the measure of 2.);
2. on ../shared/data/als/MixedConifer.laz (heights already normalised): the
   number of trees and, for trees matched one-to-one to lidR's own treeID
   labels, the median 2-D convex-hull crown IoU (skipped when absent), and a
   picture of Sylva's crowns beside lidR's over the CHM; a row 'ncut+chm'
   grows Dalponte's CHM regions from the tops NormalizedCut keeps (which
   part of the disagreement is crown boundaries, which is tops), a row
   'chm 4 m' is ChmRegionGrowing with a 4 m top window (what lidR's labels
   look like: a CHM method); rows 'ncut@lidR' and 'chm@lidR' give both
   methods lidR's own tops (each lidR tree's apex), so their IoU
   measures the crown boundaries alone (how alike the two partitions are,
   not the tops);
   and the same detection scores as in 1. on the plugin's shipped sample
   (resources/sample/sample.laz against sample_trees.csv);
3. throughput (points/s through the whole segment_trees verb: tops,
   voxels, graph, cuts, labels) and the verb's peak memory (tracemalloc
   peak of a second run; numpy reports its buffers to tracemalloc) and the
   process's ru_maxrss, one fresh subprocess per size;
4. with ``--variants``, only: NormalizedCut with given field overrides side
   by side on a panel of the suite, the sample and MixedConifer.laz;
5. with ``--pairs``, only: for every pair of touching regions of the
   candidate tops (all merges off), the features a merge rule could use
   (height ratio, gap and reach in allometric crown radii, prominence above
   the saddle, elongation), pairs of one reference tree beside pairs of two,
   on the same panel and MixedConifer.laz (lidR's trees as the reference).
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


def _methods(growth="forest"):
    from sylva.core.segment import ChmRegionGrowing, NormalizedCut

    return [("ncut", NormalizedCut(growth=growth)), ("chm", ChmRegionGrowing())]


def _suite_scan(kind, structure, density, seed=0, slope_deg=0.0):
    """(stand, scan) of the extended suite: kind conifer (testing/synth presets), broadleaf, mixed,
    parkland or tall (sylva/testing/crowns.py), on ground sloping ``slope_deg`` degrees."""
    from sylva.testing import synth
    from sylva.testing import crowns

    if kind == "conifer":
        stand_spec, scan_spec = synth.preset(structure, pulse_density=density, seed=seed)
        stand = synth.make_stand(dataclasses.replace(stand_spec, slope_deg=slope_deg))
    else:
        stand, scan_spec = crowns.suite_preset(kind, structure, density, seed=seed, slope_deg=slope_deg)
    return stand, synth.simulate_scan(stand, scan_spec)


def _chain_cloud(cloud):
    """(the cloud every method of segmenttrees and the pipeline segments: without noise, with heights;
    the mask of its points in ``cloud``): :func:`sylva.core.segment.tile.prepare_tile`."""
    from sylva.core.segment.tile import prepare_tile

    return prepare_tile(cloud)


def _pipeline_labels(scan, tmp, growth="forest"):
    """treeID of every point of the scan through sylva:pipeline's run_catalog (one tile, no models)."""
    import laspy

    from sylva.testing import synth
    from sylva.core.catalog import run_catalog
    from sylva.core.pipeline import PipelineOptions
    from sylva.core.segment import NormalizedCut

    laz, _ = synth.write_scan(scan, tmp, "stand")
    options = PipelineOptions(reconstruct=False, segmentation=NormalizedCut(growth=growth))
    run_catalog([str(laz)], str(Path(tmp) / "out"), options, resume=False)
    return np.asarray(laspy.read(str(Path(tmp) / "out" / "tiles" / "stand.laz"))["treeID"])


def accuracy_table(kinds=("conifer", "broadleaf", "mixed"), stands=("open", "medium", "dense"),
                   densities=(2, 5, 20, 50), seed=0, growth="forest", slope_deg=0.0):
    from sylva.core.segment import ChmRegionGrowing, segment_trees

    M = _metrics()
    print("1. Detection and point accuracy on the extended synthetic suite (100 m x 100 m; conifer: "
          "testing/synth presets, broadleaf / mixed / parkland / tall: sylva/testing/crowns.py), seed", seed, "; ncut and pipeline "
          "with the growth preset", repr(growth), f"; ground sloping {slope_deg:g} degrees" if slope_deg else "")
    names = [n for n, _ in _methods()] + ["pipeline"]
    head = f"{'kind':9s} {'stand':6s} {'p/m2':>4s} {'points':>7s} {'trees':>5s} "
    for n in names:
        head += f"| {n:8s} {'n':>4s} {'P':>5s} {'R':>5s} {'F1':>5s} {'ptacc':>5s} {'IoU':>5s} {'<20':>4s} "
    print(head)
    f1s = {n: [] for n in names}
    loss_rows = []
    for kind in kinds:
        for stand_name in stands:
            for density in densities:
                stand, scan = _suite_scan(kind, stand_name, density, seed, slope_deg)
                cloud, keep = _chain_cloud(scan.cloud)
                truth = scan.truth_tree[keep]
                row = f"{kind:9s} {stand_name:6s} {density:4g} {len(cloud):7d} {len(stand.trees):5d} "
                runs = [(n, lambda m=m: segment_trees(cloud, m)) for n, m in _methods(growth)]
                with tempfile.TemporaryDirectory() as tmp:
                    runs.append(("pipeline", lambda: _pipeline_labels(scan, tmp, growth)[keep]))
                    for name, run in runs:
                        labels = run()
                        r = M.evaluate(cloud.xyz, cloud.attrs["height"], labels, truth,
                                       stand.trees)
                        _, counts = np.unique(labels[labels > 0], return_counts=True)
                        small = float((counts < 20).mean()) if len(counts) else 0.0
                        _, _, ious = M.crown_iou(cloud.xyz[:, :2], labels, truth)
                        iou = float(np.median(ious)) if len(ious) else 0.0
                        f1s[name].append((density, r["f1"]))
                        row += (f"| {'':8s} {r['n_detected']:4d} {r['precision']:.3f} {r['recall']:.3f} "
                                f"{r['f1']:.3f} {r['point_accuracy']:.3f} {iou:.3f} {small:4.2f} ")
                        if name == names[0]:
                            # the same method given the true apexes as tops: what the cut and merges lose;
                            # Dalponte's CHM regions from the same tops: the crown boundaries alone
                            apexes = _apex_tops(cloud, truth, keep_ids=True)
                            given = segment_trees(cloud, _methods(growth)[0][1], tops=apexes)
                            g = M.evaluate(cloud.xyz, cloud.attrs["height"], given, truth, stand.trees)
                            given_iou = {n: np.median(M.crown_iou(cloud.xyz[:, :2], lab, truth)[2])
                                         for n, lab in ((names[0], given), ("chm", segment_trees(
                                             cloud, ChmRegionGrowing(), tops=apexes)))}
                            loss_rows.append(f"   {kind:9s} {stand_name:6s} {density:4g} | FP {r['n_detected'] - round(r['precision'] * r['n_detected']):4d}: "
                                             f"split {r['fp_split']:4d} offset {r['fp_offset']:4d} | FN {r['fn']:4d}: merged "
                                             f"{r['fn_merged']:4d} overtopped {r['fn_overtopped']:4d} | F1 {r['f1']:.3f}, "
                                             f"{g['f1']:.3f} from the true apexes | crown IoU from them "
                                             f"{given_iou[names[0]]:.3f} ({names[0]}), {given_iou['chm']:.3f} (chm) | "
                                             f"overtopped {r['overtopped']:3d} ({r['tp_overtopped']:2d} found), surface "
                                             f"F1 {_surface_f1(r['overtopped'], r['n_true']):.3f}")
                print(row, flush=True)
    print("   IoU: median 2-D convex-hull crown IoU with the true trees (the measure MixedConifer's agreement "
          "with lidR uses)")
    print(f"   where {names[0]} loses F1 (benchmarks/metrics.py losses: split = a piece of a matched crown, offset ="
          " its crown's top missed by the matching, merged = inside another tree's segment, overtopped ="
          " its apex under a neighbour's crown; 'from the true apexes': the same method given each true tree's"
          " apex (its highest point in elevation) as its top, so the F1 it lacks is lost by the cut and merges, the rest by the top search;"
          " the crown IoU from them is that of its crowns and of chm's grown from the same tops: the crown"
          " boundaries alone; overtopped: true trees whose apex is under a neighbour's crown, a point of"
          " another tree 0.5 m higher within 1 m, and how many of them are found all the same; surface F1:"
          " the F1 of finding every other tree and nothing else, what tops on the canopy surface reach at"
          " best)")
    for line in loss_rows:
        print(line)
    for name, vals in f1s.items():
        lo = [f for d, f in vals if d < 5]
        hi = [f for d, f in vals if d >= 5]
        print(f"   {name:8s} min F1 at >= 5 p/m2: {min(hi) if hi else float('nan'):.3f} "
              f"(mean {np.mean(hi) if hi else float('nan'):.3f});  at 2 p/m2: "
              f"{min(lo) if lo else float('nan'):.3f} (mean {np.mean(lo) if lo else float('nan'):.3f})")
    print()


def _surface_f1(overtopped: int, n_true: int) -> float:
    """The F1 of a segmentation that finds every tree whose apex is on the canopy surface, and nothing
    else (metrics.overtopped: apexes under a neighbour's crown are not): what tops searched on the
    canopy surface reach at best, unless a tree's visible flank passes for its top."""
    recall = 1.0 - overtopped / n_true if n_true else 0.0
    return 2 * recall / (1 + recall) if recall > 0 else 0.0


def _draw(ax, xy, h, labels, title, cell=0.5):
    """The CHM (``cell`` m, highest point per cell) in grey, each tree's crown outline and top in colour."""
    from shapely import MultiPoint

    ij = np.floor(xy / cell).astype(int)
    chm = np.zeros(tuple(ij.max(axis=0) + 1))
    np.maximum.at(chm, (ij[:, 0], ij[:, 1]), np.maximum(h, 0))
    ax.imshow(chm.T, origin="lower", cmap="gray", extent=(0, chm.shape[0] * cell, 0, chm.shape[1] * cell))
    rng = np.random.default_rng(0)
    ids = np.unique(labels[labels > 0])
    for t in ids:
        pts = xy[labels == t]
        if len(pts) < 3:
            continue
        hull = MultiPoint(pts).convex_hull
        if hull.geom_type != "Polygon":
            continue
        c = rng.uniform(0.2, 1.0, 3)
        ax.plot(*hull.exterior.xy, color=c, lw=1.2)
        top = np.argmax(np.where(labels == t, h, -np.inf))
        ax.plot(xy[top, 0], xy[top, 1], "+", color=c, ms=6)
    ax.set_title(f"{title}: {len(ids)} trees over the CHM (m)")


def _picture(cloud, labels, path, title, reference=None, reference_title="reference"):
    """PNG of the crowns over the CHM; with ``reference`` labels (per point of ``cloud``), the
    reference's crowns in a second panel beside them."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    xy = cloud.local_xyz()[:, :2]
    h = np.asarray(cloud.attrs["height"])
    panels = [(labels, title)] + ([] if reference is None else [(reference, reference_title)])
    fig, axes = plt.subplots(1, len(panels), figsize=(9 * len(panels), 9), squeeze=False)
    for ax, (lab, name) in zip(axes[0], panels):
        _draw(ax, xy, h, np.asarray(lab), name)
    fig.savefig(path, dpi=90, bbox_inches="tight")
    plt.close(fig)


def _mixed_conifer():
    """(cloud, lidR treeID per point, 0 = none) of ../shared/data/als/MixedConifer.laz, whose z is
    already height above ground."""
    import laspy

    from sylva.core.cloud import PointCloud

    path = DATA / "als" / "MixedConifer.laz"
    las = laspy.read(str(path))
    xyz = np.column_stack([las.x, las.y, las.z])
    attrs = {"height": np.asarray(las.z, dtype=np.float64),
             "classification": np.asarray(las.classification),
             "intensity": np.asarray(las.intensity),
             "return_number": np.asarray(las.return_number)}
    ref = np.asarray(las["treeID"], dtype=np.float64)
    # lidR writes "no tree" (NA) as the extra-bytes no-data value (the largest double): not a tree
    ref = np.where(np.isfinite(ref) & (ref > 0) & (ref < 2 ** 31), ref, 0).astype(np.int64)
    return PointCloud(xyz, attrs=attrs, source=str(path)), ref


#: The panel of --variants: (kind, stand, pulses/m2) of the suite, open to dense, 2 to 20 pulses/m2.
VARIANT_PANEL = (("broadleaf", "open", 20), ("broadleaf", "medium", 5), ("broadleaf", "dense", 20),
                 ("mixed", "open", 5), ("mixed", "dense", 20), ("conifer", "dense", 20),
                 ("conifer", "open", 5), ("conifer", "medium", 2))


def variant_table(variants, seed=0):
    """NormalizedCut with each dict of field overrides in ``variants`` ({} = the defaults) side by
    side: detection F1 on :data:`VARIANT_PANEL`, the shipped sample, and on MixedConifer.laz the
    number of trees and the median crown IoU with lidR's (what a change of a default trades)."""
    from sylva.core.segment import NormalizedCut, segment_trees

    M = _metrics()
    panel = []
    for kind, stand_name, density in VARIANT_PANEL:
        stand, scan = _suite_scan(kind, stand_name, density, seed)
        cloud, keep = _chain_cloud(scan.cloud)
        panel.append((f"{kind[:5]}-{stand_name[:3]}-{density}", cloud, scan.truth_tree[keep], stand.trees))
    panel.append(("sample", *_sample()))
    mixed = _mixed_conifer() if (DATA / "als" / "MixedConifer.laz").exists() else None
    print("4. NormalizedCut variants (detection F1 per stand; MixedConifer: trees vs lidR's 205, median IoU)")
    print("   " + " ".join(f"{name:>13s}" for name, *_ in panel) + "   MC trees   IoU   variant")
    for overrides in variants:
        method = NormalizedCut(**overrides)
        row = []
        for _, cloud, truth, trees in panel:
            r = M.evaluate(cloud.xyz, cloud.attrs["height"], segment_trees(cloud, method), truth, trees)
            row.append(f"{r['f1']:13.3f}")
        mc = "      -      -"
        if mixed is not None:
            cloud, ref = mixed
            labels = segment_trees(cloud, method)
            _, _, ious = M.crown_iou(cloud.xyz[:, :2], labels, ref)
            mc = f"{len(np.unique(labels[labels > 0])):11d} {np.median(ious):5.3f}"
        print("   " + " ".join(row) + f"{mc}   {json.dumps(overrides)}", flush=True)
    print()


#: NormalizedCut with every merge off: the regions of all its candidate tops (table 5).
UNMERGED = dict(merge_ncut=1e9, always_merge_ncut=1e9, merge_reach=0.0, merge_plateau=0.0, min_tree_points=1)


def touching_pairs(cloud, labels, reference):
    """Features of every pair of touching regions (points of the two within 1 m), the higher top first,
    and whether the reference holds both in one tree (each region's majority reference tree).

    Returns (same (k,) bool, features (k, 5)): the lower top's height / the higher's; the distance of
    the tops / the higher top's allometric crown radius (:func:`crown_radius_m`); the lower top's rise
    above the saddle (the highest of the lower points of the touching pairs) / its height; the
    elongation sqrt(l1 / l2) of the two upper crowns' points (above half the lower top) in plan; the
    90th percentile of their distance to the higher top / its crown radius. Sylva benchmark measure."""
    from scipy.spatial import cKDTree

    from sylva.core.segment.ncut import crown_radius_m

    h, xy = cloud.attrs["height"], cloud.xyz[:, :2]
    sel = np.flatnonzero(labels > 0)
    order = sel[np.lexsort((-h[sel], labels[sel]))]
    starts = np.flatnonzero(np.r_[True, labels[order][1:] != labels[order][:-1]])
    ids = labels[order[starts]]
    top = np.zeros(int(labels.max()) + 1, dtype=np.int64)
    top[ids] = order[starts]
    members = dict(zip(ids, np.split(order, starts[1:])))
    majority = np.zeros(len(top), dtype=np.int64)
    for t, m in members.items():
        r = reference[m][reference[m] > 0]
        majority[t] = np.bincount(r).argmax() if len(r) else 0
    pp = cKDTree(cloud.xyz).query_pairs(1.0, output_type="ndarray")
    la, lb = labels[pp[:, 0]], labels[pp[:, 1]]
    keep = (la > 0) & (lb > 0) & (la != lb)
    la, lb, low = la[keep], lb[keep], np.minimum(h[pp[keep, 0]], h[pp[keep, 1]])
    key = np.minimum(la, lb).astype(np.int64) * len(top) + np.maximum(la, lb)
    o = np.lexsort((-low, key))
    first = o[np.r_[True, key[o][1:] != key[o][:-1]]]
    same, rows = [], []
    for k, saddle in zip(key[first], low[first]):
        a, b = divmod(int(k), len(top))
        if h[top[a]] < h[top[b]]:
            a, b = b, a
        ha, hb, radius = h[top[a]], h[top[b]], crown_radius_m(h[top[a]])
        union = np.r_[members[a], members[b]]
        union = union[h[union] > 0.5 * hb]
        ev = np.linalg.eigvalsh(np.cov(xy[union].T)) if len(union) > 3 else np.ones(2)
        rows.append((hb / ha, np.hypot(*(xy[top[a]] - xy[top[b]])) / radius, (hb - saddle) / hb,
                     np.sqrt(ev[1] / max(ev[0], 1e-9)),
                     np.percentile(np.hypot(*(xy[union] - xy[top[a]]).T), 90) / radius))
        same.append(majority[a] == majority[b] and majority[a] > 0)
    return np.array(same, dtype=bool), np.array(rows).reshape(-1, 5)


def pair_table(seed=0):
    """What tells one tree's two tops from two trees: the features of :func:`touching_pairs` over the
    regions of every candidate top (:data:`UNMERGED`), same-tree pairs beside two-tree pairs, on the
    panel of --variants and on MixedConifer.laz (lidR's trees as the reference), and how many of
    each today's crown-reach rule (``merge_reach``, ``merge_prominence``) would merge."""
    from sylva.core.segment import NormalizedCut, segment_trees

    d = NormalizedCut()
    cases = []
    for kind, stand_name, density in VARIANT_PANEL:
        stand, scan = _suite_scan(kind, stand_name, density, seed)
        cloud, keep = _chain_cloud(scan.cloud)
        cases.append((f"{kind[:5]}-{stand_name[:3]}-{density}", cloud, scan.truth_tree[keep]))
    if (DATA / "als" / "MixedConifer.laz").exists():
        cases.append(("MixedConifer (lidR)", *_mixed_conifer()))
    names = ("height ratio", "gap / radius", "prominence", "elongation", "reach / radius")
    print("5. Touching candidate regions (every merge off): 10th / 50th / 90th percentile of each feature, "
          "pairs of one reference tree | pairs of two; 'rule': pairs today's crown-reach rule merges")
    print(f"   {'stand':19s} {'pairs':>11s} " + " ".join(f"{n:>29s}" for n in names) + "   rule one|two")
    for name, cloud, reference in cases:
        same, f = touching_pairs(cloud, segment_trees(cloud, NormalizedCut(**UNMERGED)), reference)
        cells = []
        for j in range(f.shape[1]):
            a, b = (np.percentile(f[m, j], [10, 50, 90]) if m.any() else np.full(3, np.nan)
                    for m in (same, ~same))
            cells.append(f"{a[0]:4.2f} {a[1]:4.2f} {a[2]:4.2f}|{b[0]:4.2f} {b[1]:4.2f} {b[2]:4.2f}")
        rule = (f[:, 1] < d.merge_reach) & (f[:, 2] < d.merge_prominence)
        print(f"   {name:19s} {same.sum():5d}|{(~same).sum():<5d} " + " ".join(f"{c:>29s}" for c in cells)
              + f"   {(rule & same).sum():5d}|{(rule & ~same).sum():<5d}", flush=True)
    print()


def _apex_tops(cloud, labels, keep_ids=False):
    """TreeTops at the apex of every labelled tree (its highest point in elevation; ids 1..n by
    height, or the labels)."""
    from sylva.core.tops import TreeTops, apex_points

    height = cloud.attrs["height"]
    first = apex_points(cloud.xyz, labels)
    first = first[np.argsort(-height[first], kind="stable")]
    ids = labels[first].astype(np.int64) if keep_ids else np.arange(1, len(first) + 1, dtype=np.int64)
    return TreeTops(cloud.xyz[first], height[first], ids, cloud.crs)


def _chm_from_kept_tops(cloud):
    """Dalponte's CHM region growing from the tops of NormalizedCut's trees (each tree's apex)."""
    from sylva.core.segment import ChmRegionGrowing, NormalizedCut, segment_trees

    return segment_trees(cloud, ChmRegionGrowing(), tops=_apex_tops(cloud, segment_trees(cloud, NormalizedCut())))


def real_files(out_dir):
    """MixedConifer agreement with lidR; share of small trees and a crown picture on every real file."""
    from sylva.core.io.las import read_las
    from sylva.core.segment import ChmRegionGrowing, NormalizedCut, segment_trees
    from sylva.core.segment.tile import segment_tile

    M = _metrics()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    print("2. Real files (the pipeline column is sylva.core.segment.tile.segment_tile, the chain "
          "segmenttrees and the pipeline both run)")
    path = DATA / "als" / "MixedConifer.laz"
    if path.exists():
        cloud, ref = _mixed_conifer()
        xyz = cloud.xyz
        n_lidr = len(np.unique(ref[ref > 0]))
        print(f"   MixedConifer.laz: {len(cloud)} points; lidR treeID: {n_lidr} trees "
              f"(target: within 15 % of 205, median IoU >= 0.7, < 5 % under 20 points)")
        runs = [(n, lambda m=m: segment_trees(cloud, m)) for n, m in _methods()]
        runs.append(("pipeline", lambda: _full(segment_tile(read_las(str(path))), len(cloud))))
        runs.append(("ncut+chm", lambda: _chm_from_kept_tops(cloud)))
        runs.append(("chm 4 m", lambda: segment_trees(cloud, ChmRegionGrowing(top_window_m=4.0))))
        lidr_tops = _apex_tops(cloud, ref, keep_ids=True)
        runs.append(("ncut@lidR", lambda: segment_trees(cloud, NormalizedCut(), tops=lidr_tops)))
        runs.append(("chm@lidR", lambda: segment_trees(cloud, ChmRegionGrowing(), tops=lidr_tops)))
        for name, run in runs:
            t0 = time.perf_counter()
            labels = run()
            dt = time.perf_counter() - t0
            _, n_ref, ious = M.crown_iou(xyz[:, :2], labels, ref)
            _, counts = np.unique(labels[labels > 0], return_counts=True)
            print(f"   {name:9s} trees {len(counts):4d} ({len(counts) / 205 - 1:+.0%} vs 205)   matched "
                  f"{len(ious):4d} of {n_ref}   median crown IoU {np.median(ious):.3f}   under 20 points "
                  f"{(counts < 20).mean():.1%}   smallest {counts.min()}   ({dt:.1f} s)", flush=True)
        tile = segment_tile(read_las(str(path)))
        _picture(tile.cloud, tile.labels, out_dir / "MixedConifer.png", "MixedConifer.laz (Sylva)",
                 reference=ref[tile.keep],
                 reference_title="lidR treeID")
    else:
        print(f"   skipped: {path} not found")

    # autzen_trim.laz is suburban: its park and street trees grew in the open (growth "open-grown")
    for name, growth in (("autzen_trim.laz", "forest"), ("autzen_trim.laz", "open-grown"), ("ahn3_delft.xyz", "forest")):
        path = DATA / "als" / name
        if not path.exists():
            print(f"   {name}: skipped, not found")
            continue
        from sylva.core.io import read_cloud

        t0 = time.perf_counter()
        tile = segment_tile(read_cloud(str(path)), NormalizedCut(growth=growth))
        dt = time.perf_counter() - t0
        _, counts = np.unique(tile.labels[tile.labels > 0], return_counts=True)
        png = out_dir / (Path(name).stem + ("" if growth == "forest" else f"_{growth}") + ".png")
        _picture(tile.cloud, tile.labels, png, f"{name} (growth {growth})")
        print(f"   {name} (growth {growth}): {len(tile.cloud)} points, {len(counts)} trees, under 20 points "
              f"{(counts < 20).mean() if len(counts) else 0:.1%}, smallest {counts.min() if len(counts) else 0} "
              f"({dt:.1f} s); picture {png.name}")
    print(f"   pictures in {out_dir}")
    print()


def _full(tile, n):
    labels = np.zeros(n, dtype=np.int32)
    labels[tile.keep] = tile.labels
    return labels


SAMPLE = REPO / "resources" / "sample" / "sample.laz"


def _sample():
    """(normalised cloud, true tree per point, true trees) of the shipped sample."""
    import laspy

    from sylva.core.io.las import read_las
    from sylva.testing.synth import read_truth

    cloud, keep = _chain_cloud(read_las(str(SAMPLE)))
    return (cloud, np.asarray(laspy.read(str(SAMPLE)).true_tree)[keep],
            read_truth(SAMPLE.with_name("sample_trees.csv")))


def shipped_sample():
    """Detection scores on resources/sample/sample.laz against sample_trees.csv."""
    from sylva.core.io.las import read_las
    from sylva.core.segment import segment_trees
    from sylva.core.segment.tile import segment_tile

    print("   shipped sample (resources/sample/sample.laz vs sample_trees.csv):")
    if not SAMPLE.exists():
        print(f"   skipped: {SAMPLE} not found\n")
        return
    cloud, truth, trees = _sample()
    runs = [(n, lambda m=m: segment_trees(cloud, m)) for n, m in _methods()]
    runs.append(("pipeline", lambda: segment_tile(read_las(str(SAMPLE))).labels))
    for name, run in runs:
        labels = run()
        r = _metrics().evaluate(cloud.xyz, cloud.attrs["height"], labels, truth, trees)
        _, counts = np.unique(labels[labels > 0], return_counts=True)
        print(f"   {name:9s} trees {r['n_detected']:4d} of {r['n_true']}   P {r['precision']:.3f} "
              f"R {r['recall']:.3f} F1 {r['f1']:.3f} ptacc {r['point_accuracy']:.3f}   under 20 points "
              f"{(counts < 20).mean():.1%}")
    print()


# --------------------------------------------------------------------------- throughput

#: The point attributes of the throughput input: those segment_trees reads from a LAS tile.
_THROUGHPUT_ATTRS = ("height", "classification", "intensity", "return_number", "number_of_returns")


def _make_input(n_points: int, path: str) -> None:
    """Child: a medium synthetic stand at 20 pulses/m2 with ~n_points points, saved as .npz."""
    from sylva.testing import synth
    from sylva.core.terrain import normalize

    per_m2 = 31.0   # points/m2 of the medium preset at 20 pulses/m2 (multiple returns)
    side = float(np.sqrt(n_points / per_m2))
    stand_spec, scan_spec = synth.preset("medium", pulse_density=20.0)
    stand_spec = dataclasses.replace(stand_spec, width_m=side, depth_m=side)
    stand = synth.make_stand(stand_spec)
    scan = synth.simulate_scan(stand, scan_spec)
    cloud = normalize(scan.cloud)
    # every attribute the chain reads from a real tile (the returns: the hard-surface test)
    np.savez(path, xyz=cloud.xyz, **{k: cloud.attrs[k] for k in _THROUGHPUT_ATTRS},
             crs=str(cloud.crs.to_string()) if cloud.crs is not None else "")


def _run_verb(path: str) -> dict:
    """Child: load the input, then time segment_trees and measure its peak memory."""
    from sylva.core.cloud import PointCloud
    from sylva.core.jit import compile_seconds
    from sylva.core.segment import segment_trees

    data = np.load(path)
    cloud = PointCloud(data["xyz"], attrs={k: data[k] for k in _THROUGHPUT_ATTRS})
    t0 = time.perf_counter()
    c0 = time.process_time()
    s0 = resource.getrusage(resource.RUSAGE_SELF).ru_stime
    labels = segment_trees(cloud)
    system = resource.getrusage(resource.RUSAGE_SELF).ru_stime - s0
    # numba compilations (a kernel's cache invalidated by an edit of its module) are not the verb's work
    jit = compile_seconds()
    dt = time.perf_counter() - t0 - jit
    cpu = time.process_time() - c0 - jit
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    # a second run under tracemalloc (numpy reports its buffers to it): the verb's own peak
    tracemalloc.start()
    segment_trees(cloud)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return {"points": len(cloud), "seconds": dt, "cpu_seconds": cpu, "trees": int(len(np.unique(labels[labels > 0]))),
            "system_seconds": system, "rss_mb": rss, "extra_mb": peak / 2 ** 20, "compile_s": jit}


def throughput(sizes):
    print("3. Throughput of segment_trees(cloud) (NormalizedCut, tops found), one core,"
          " medium stand at 20 pulses/m2\n   (points/s on the wall clock; points per CPU"
          " second is robust to other jobs sharing the machine)")
    print("   (seconds of numba compilation, when a kernel's cache was stale, are left out and shown; of the CPU"
          " seconds,\n   'system' is the kernel's, mostly zeroing the pages of fresh buffers: it varies with the machine)")
    print(f"   {'points':>10s} {'trees':>7s} {'seconds':>8s} {'points/s':>10s} "
          f"{'CPU s':>7s} {'system':>7s} {'points/CPU s':>12s} "
          f"{'verb peak MB':>13s} {'MB/Mpt':>7s} {'process maxrss MB':>18s} {'compile s':>9s}")
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
              f"{r['points'] / r['seconds']:10.0f} {r['cpu_seconds']:7.1f} {r['system_seconds']:7.1f} "
              f"{r['points'] / r['cpu_seconds']:12.0f} {r['extra_mb']:13.0f} "
              f"{r['extra_mb'] / mpts:7.0f} {r['rss_mb']:18.0f} {r['compile_s']:9.1f}", flush=True)
    print()


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="throughput at 1 M points only")
    parser.add_argument("--kinds", default="conifer,broadleaf,mixed,parkland,tall",
                        help="comma-separated crown kinds of the accuracy table (conifer, broadleaf, mixed, parkland, tall)")
    parser.add_argument("--slope", type=float, default=0.0,
                        help="slope of the accuracy table's ground in degrees (0: level, the default)")
    parser.add_argument("--stands", default="open,medium,dense",
                        help="comma-separated stands of the accuracy table (open, medium, dense)")
    parser.add_argument("--densities", default="2,5,20,50",
                        help="comma-separated pulse densities of the accuracy table")
    parser.add_argument("--seed", type=int, default=0, help="seed of the synthetic stands")
    parser.add_argument("--growth", default="forest",
                        help="NormalizedCut's growth preset of the accuracy table's ncut and pipeline columns "
                             "(forest, open-grown)")
    parser.add_argument("--out", default=os.path.join(tempfile.gettempdir(), "sylva-bench-segmentation"),
                        help="folder of the crown pictures")
    parser.add_argument("--sizes", default=None,
                        help="comma-separated throughput sizes in points (0: no throughput)")
    parser.add_argument("--no-real", action="store_true",
                        help="skip MixedConifer and the shipped sample")
    parser.add_argument("--child-make", nargs=2, help=argparse.SUPPRESS)
    parser.add_argument("--child-run", nargs=1, help=argparse.SUPPRESS)
    parser.add_argument("--variants", default=None,
                        help='JSON list of NormalizedCut field overrides to compare, e.g. '
                             '\'[{}, {"top_window_points": 50}]\' (only this table is printed)')
    parser.add_argument("--pairs", action="store_true",
                        help="only table 5: the features of touching candidate regions, one tree or two")
    parser.add_argument("--skip-accuracy", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child_make:
        _make_input(int(args.child_make[0]), args.child_make[1])
        return
    if args.child_run:
        print(json.dumps(_run_verb(args.child_run[0])))
        return
    if args.variants is not None:
        from sylva.core.segment import NormalizedCut

        try:
            variants = json.loads(args.variants)
            for v in variants:
                NormalizedCut(**v)
        except (ValueError, TypeError, AttributeError) as err:
            parser.error(f"--variants: {err}")
        variant_table(variants, args.seed)
        return
    if args.pairs:
        pair_table(args.seed)
        return
    if not args.skip_accuracy:
        stands = tuple(s for s in args.stands.split(",") if s)
        densities = tuple(float(d) if "." in d else int(d) for d in args.densities.split(",") if d)
        kinds = tuple(k for k in args.kinds.split(",") if k)
        if kinds and stands and densities:
            accuracy_table(kinds, stands, densities, args.seed, args.growth, args.slope)
        if not args.no_real:
            real_files(args.out)
            shipped_sample()
    if args.sizes is not None:
        sizes = [int(float(n)) for n in args.sizes.split(",") if float(n) > 0]
    else:
        sizes = [1_000_000] if args.quick else [1_000_000, 5_000_000, 20_000_000]
    if sizes:
        throughput(sizes)


if __name__ == "__main__":
    main()
