"""Terrain benchmark: ground filters, normalisation speed, CHM speed, tree-top accuracy.

Run: ``PROJ_DATA=/usr/share/proj .venv/bin/python benchmarks/terrain.py [--quick]``

Prints
1. ground classification, SMRF vs CSF (Sylva's vectorised one and, when the
   ``cloth-simulation-filter`` package is installed, its reference C++ one):
   precision and recall of ground points, RMSE of the 1 m DTM against the true
   terrain, time; on synthetic medium stands (testing.synth) on 0, 15, 30 degree slopes;
2. normalisation throughput (points/s) for TIN and kNN-IDW at about 1 M points;
3. CHM time, plain vs pit-free, on the same cloud;
4. tree-top precision / recall / F1 for FixedWindow 2, 3, 4, 5 m and
   VariableWindow on open, medium and dense stands at 5 and 20 pulses/m2, on
   points and on the pit-free CHM.  A detected top matches a true tree when it is
   within 0.5 x its crown radius and within 15 % of its height (one-to-one, tallest
   true tree first).
"""
from __future__ import annotations

import argparse
import contextlib
import io
import os
import time
from dataclasses import replace

import numpy as np

from sylva.testing import synth
from sylva.core.terrain import (
    CSF, SMRF, canopy_height_model, classify_ground, digital_terrain_model, height_above_ground,
    normalize,
)
from sylva.core.tops import FixedWindow, VariableWindow, find_tree_tops


def match(tops, stand):
    xy = np.array([[t.x, t.y] for t in stand.trees])
    h = np.array([t.height for t in stand.trees])
    r = np.array([t.crown_radius_m for t in stand.trees])
    used = np.zeros(len(tops), dtype=bool)
    hits = 0
    for i in np.argsort(-h):
        d = np.hypot(*(tops.xyz[:, :2] - xy[i]).T)
        ok = ~used & (d <= 0.5 * r[i]) & (np.abs(tops.height - h[i]) <= 0.15 * h[i])
        if ok.any():
            used[np.argmin(np.where(ok, d, np.inf))] = True
            hits += 1
    p = hits / max(len(tops), 1)
    rc = hits / max(len(h), 1)
    return p, rc, 2 * p * rc / max(p + rc, 1e-12)


class PackageCSF:
    """The reference implementation (PyPI ``cloth-simulation-filter``), for comparison only."""

    def __init__(self, rigidness=2, cloth_resolution=0.5, slope_smooth=False):
        import importlib

        importlib.import_module("CSF")  # ImportError when the package is absent
        self.rigidness = rigidness
        self.cloth_resolution = cloth_resolution
        self.slope_smooth = slope_smooth

    def classify(self, cloud):
        import CSF as csf_module

        csf = csf_module.CSF()
        csf.params.bSloopSmooth = self.slope_smooth
        csf.params.cloth_resolution = self.cloth_resolution
        csf.params.rigidness = self.rigidness
        csf.params.time_step = 0.65
        csf.params.class_threshold = 0.5
        csf.params.interations = 500
        csf.setPointCloud(cloud.local_xyz())
        ground, off = csf_module.VecInt(), csf_module.VecInt()
        with open(os.devnull, "w") as devnull, contextlib.redirect_stdout(io.StringIO()):
            fd = os.dup(1)
            os.dup2(devnull.fileno(), 1)  # the C++ code prints progress on stdout
            try:
                csf.do_filtering(ground, off, False)  # False: no cloth_nodes.txt in the cwd
            finally:
                os.dup2(fd, 1)
                os.close(fd)
        mask = np.zeros(len(cloud), dtype=bool)
        mask[np.asarray(ground, dtype=np.int64)] = True
        return mask


def ground_comparison(seeds):
    print("\n== 1. Ground classification on synthetic medium stands (100 m x 100 m, 10 pulses/m2) ==")
    methods = [("SMRF()", SMRF()), ("CSF(rigidness=1)", CSF(rigidness=1)),
               ("CSF(rigidness=2)", CSF(rigidness=2)), ("CSF() [rigidness=3]", CSF())]
    try:
        methods += [("cloth-simulation-filter pkg, rigidness=2", PackageCSF(2)),
                    ("cloth-simulation-filter pkg, rigidness=1, slope smooth", PackageCSF(1, slope_smooth=True))]
    except ImportError:
        print("(cloth-simulation-filter is not installed: reference CSF not compared)")
    print(f"{'slope':>5}  {'method':<48}{'precision':>10}{'recall':>8}{'DTM RMSE m':>12}{'time s':>8}")
    summary = {}
    for slope in (0.0, 15.0, 30.0):
        for seed in seeds:
            stand_spec, scan_spec = synth.preset("medium", pulse_density=10.0, seed=seed)
            stand = synth.make_stand(replace(stand_spec, slope_deg=slope, undulation_m=1.0))
            scan = synth.simulate_scan(stand, replace(scan_spec, classify_ground=False))
            cloud = scan.cloud
            truth = scan.truth_kind == synth.GROUND
            for name, method in methods:
                t0 = time.perf_counter()
                g = classify_ground(cloud, method)
                dt = time.perf_counter() - t0
                tp = np.sum(g & truth)
                precision, recall = tp / max(g.sum(), 1), tp / truth.sum()
                dtm = digital_terrain_model(cloud, resolution_m=1.0, ground=g)
                cx, cy = dtm.cell_centres()
                x0, y0, x1, y1 = stand.extent
                inside = (cx > x0 + 2) & (cx < x1 - 2) & (cy > y0 + 2) & (cy < y1 - 2)
                err = dtm.data[inside] - stand.ground_z(cx[inside], cy[inside])
                rmse = float(np.sqrt(np.mean(err ** 2)))
                summary.setdefault(name, []).append((precision, recall, rmse, dt))
                print(f"{slope:5.0f}  {name:<48}{precision:10.4f}{recall:8.4f}{rmse:12.3f}{dt:8.2f}")
    print("mean over slopes and seeds:")
    for name, rows in summary.items():
        p, r, e, t = np.mean(rows, axis=0)
        print(f"       {name:<48}{p:10.4f}{r:8.4f}{e:12.3f}{t:8.2f}")


def big_cloud(quick):
    stand_spec, scan_spec = synth.preset("medium", pulse_density=10.0, seed=0)
    side = 120.0 if quick else 260.0  # about 1.4 M points at 260 m
    stand = synth.make_stand(replace(stand_spec, width_m=side, depth_m=side, slope_deg=10.0))
    return synth.simulate_scan(stand, scan_spec).cloud


def normalisation_and_chm(quick):
    cloud = big_cloud(quick)
    n = len(cloud)
    print(f"\n== 2. Normalisation throughput ({n:,} points, {np.sum(cloud.attrs['classification'] == 2):,} ground) ==")
    heights = {}
    for method in ("tin", "knnidw"):
        t0 = time.perf_counter()
        heights[method] = height_above_ground(cloud, method=method)
        dt = time.perf_counter() - t0
        print(f"  {method:<7} {dt:6.2f} s  {n / dt:12,.0f} points/s")
    d = heights["knnidw"] - heights["tin"]
    print(f"  IDW - TIN heights: median {np.median(d):+.3f} m, 95th pct |d| {np.percentile(np.abs(d), 95):.3f} m")
    normed = cloud.with_attrs(height=heights["tin"])
    print(f"\n== 3. CHM time, 0.5 m pixels ({n:,} points) ==")
    for pit_free in (False, True):
        t0 = time.perf_counter()
        chm = canopy_height_model(normed, resolution_m=0.5, pit_free=pit_free)
        dt = time.perf_counter() - t0
        print(f"  {'pit-free' if pit_free else 'plain':<9} {dt:6.2f} s  {chm.shape[0]}x{chm.shape[1]} cells, "
              f"{np.isnan(chm.data).mean() * 100:.1f} % empty")


def tops_accuracy(seeds):
    print("\n== 4. Tree tops: precision / recall / F1 (points | pit-free CHM 0.5 m) ==")
    windows = [("Fixed 2 m", FixedWindow(2.0)), ("Fixed 3 m", FixedWindow(3.0)),
               ("Fixed 4 m", FixedWindow(4.0)), ("Fixed 5 m", FixedWindow(5.0)),
               ("Variable() 1.5+0.1h", VariableWindow()),
               ("Variable.pines()", VariableWindow.pines()),
               ("Variable.combined()", VariableWindow.combined())]
    means = {}
    for name in ("open", "medium", "dense"):
        for density in (5.0, 20.0):
            for seed in seeds:
                stand_spec, scan_spec = synth.preset(name, pulse_density=density, seed=seed)
                stand = synth.make_stand(stand_spec)
                cloud = normalize(synth.simulate_scan(stand, scan_spec).cloud)
                chm = canopy_height_model(cloud, resolution_m=0.5)
                print(f"-- {name}, {density:g} pulses/m2, seed {seed}: {len(stand.trees)} trees, {len(cloud):,} points")
                for wname, window in windows:
                    t0 = time.perf_counter()
                    tp = find_tree_tops(cloud, window)
                    dt = time.perf_counter() - t0
                    a = match(tp, stand)
                    b = match(find_tree_tops(chm, window), stand)
                    means.setdefault(wname, []).append((a[2], b[2]))
                    print(f"   {wname:<22} P {a[0]:.2f} R {a[1]:.2f} F1 {a[2]:.2f} ({dt:.2f} s) | "
                          f"P {b[0]:.2f} R {b[1]:.2f} F1 {b[2]:.2f}")
    print("mean F1 over stands, densities and seeds (points | CHM):")
    for wname, rows in means.items():
        a, b = np.mean(rows, axis=0)
        print(f"   {wname:<22} {a:.3f} | {b:.3f}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one seed, a smaller cloud for sections 2-3")
    args = parser.parse_args()
    seeds = (0,) if args.quick else (0, 1)
    ground_comparison(seeds)
    normalisation_and_chm(args.quick)
    tops_accuracy(seeds)


if __name__ == "__main__":
    main()
