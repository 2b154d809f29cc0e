"""Stem segmentation of terrestrial plot scans (sylva.core.segment.stems), against synthetic truth.

    python benchmarks/stems.py
    python benchmarks/stems.py --dendromatics=PYTHON   # also dendromatics (3DFin's engine), side by side,
                                                       # run by PYTHON (a Python with dendromatics installed)

* synthetic plots (sylva.testing.plots: stems with known positions, DBH and heights, seen from five
  scanner positions with occlusion by the other stems, crowns, rough sloping ground): stem detection
  recall and precision (a detected stem matches a true one within 30 cm), DBH RMSE, position error,
  share of each matched tree's points labelled with its ID, time;
* a plot built from the shared single-tree scans (../shared/data/tls tree1, tree7, tree13 placed 6 m
  apart on a 20 m plot with a synthetic ground): the trees found, the DBH of each and the share of each
  source tree's points given to it.

dendromatics runs in its own process (benchmarks/dendromatics_run.py: 3DFin's processing order and
default parameters); its time includes its own ground model, as Sylva's includes its ground.
"""
from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from sylva.core.cloud import PointCloud
from sylva.core.segment.stems import StemSegmentation
from sylva.testing.plots import plot_scan

HERE = Path(__file__).resolve()

TLS = HERE.parents[1].parent / "shared" / "data" / "tls"


def sylva_run(pts):
    cloud = PointCloud(pts, {})
    t0 = time.perf_counter()
    labels, stems = StemSegmentation().segment_with_stems(cloud)
    dt = time.perf_counter() - t0
    return stems.xy + cloud.origin[:2], stems.dbh_m, labels, dt, stems.dbh_height_m


def dendromatics_run(pts, python):
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "pts.npy", Path(tmp) / "out.npz"
        np.save(src, pts)
        proc = subprocess.run([python, str(HERE.parent / "dendromatics_run.py"), str(src), str(dst)],
                              capture_output=True, text=True)
        if proc.returncode != 0:
            return proc.stderr.strip().splitlines()[-1]        # its error message
        r = np.load(dst)
        return r["xy"], r["dbh"], r["tree_id"], float(r["seconds"]), np.full(len(r["dbh"]), 1.3)


def scores(xy, dbh, labels, truth_xy, truth_dbh, point_tree):
    n = len(truth_xy)
    d = np.linalg.norm(xy[:, None] - truth_xy[None], axis=2) if len(xy) else np.zeros((0, n))
    j = d.argmin(axis=1) if len(xy) else np.zeros(0, int)
    ok = d[np.arange(len(j)), j] < 0.3 if len(xy) else np.zeros(0, bool)
    recall = len(set(j[ok])) / n
    precision = ok.mean() if len(ok) else 0.0
    good = ok & (dbh > 0)                    # dendromatics gives 0 where its DBH is not reliable
    rmse = np.sqrt(np.mean((dbh[good] - truth_dbh[j[good]]) ** 2)) * 100 if good.any() else np.nan
    pos = d[np.arange(len(j)), j][ok].mean() * 100 if ok.any() else np.nan
    if labels is not None and (labels >= 0).all() and ok.any():
        # the ID most of the true tree's points carry, when it is the matched stem's; the share carrying it
        share = []
        for k, jj in zip(np.flatnonzero(ok), j[ok]):
            mine = labels[point_tree == jj + 1]
            ids, cnt = np.unique(mine[mine > 0], return_counts=True)
            share.append(cnt.max() / len(mine) if len(ids) else 0.0)
        share = 100 * float(np.mean(share))
    else:
        share = np.nan
    return recall, precision, rmse, pos, share


def synthetic(runners):
    print(f"{'plot':<24}{'method':<13}{'points':>9}{'trees':>6}{'found':>6}{'recall':>8}{'precision':>10}"
          f"{'DBH RMSE cm':>12}{'pos err cm':>11}{'pts ok %':>9}{'s':>7}")
    for n, size, seed in ((8, 16, 1), (15, 20, 2), (25, 25, 3), (40, 30, 4)):
        pts, truth = plot_scan(n_trees=n, size_m=size, seed=seed)
        t = np.c_[truth["x"], truth["y"]]
        for name, run in runners:
            out = run(pts)
            if isinstance(out, str):
                print(f"{f'{n} trees, {size} m, seed {seed}':<24}{name:<13}failed: {out}")
                continue
            xy, dbh, labels, dt, _ = out
            recall, precision, rmse, pos, share = scores(xy, dbh, labels, t, truth["dbh"], truth["tree"])
            print(f"{f'{n} trees, {size} m, seed {seed}':<24}{name:<13}{len(pts):>9}{n:>6}{len(xy):>6}{recall:>8.2f}"
                  f"{precision:>10.2f}{rmse:>12.2f}{pos:>11.2f}{share:>9.1f}{dt:>7.2f}")


def real_plot(runners):
    files = [TLS / f"tree{i}.xyz" for i in (1, 7, 13)]
    if not all(f.exists() for f in files):
        print(f"(no TLS trees at {TLS})")
        return
    rng = np.random.default_rng(0)
    parts, src = [], []
    for k, f in enumerate(files):
        x = np.loadtxt(f)
        low = x[x[:, 2] < x[:, 2].min() + 0.3]
        x = x - np.r_[low[:, :2].mean(axis=0), x[:, 2].min()] + np.r_[4 + 6 * k, 10, 0]
        parts.append(x)
        src.append(np.full(len(x), k + 1))
    g = rng.uniform(0, 20, (16000, 2))
    parts.append(np.c_[g, rng.normal(0, 0.02, len(g))])
    src.append(np.zeros(len(g), int))
    pts = np.vstack(parts)
    src = np.concatenate(src)
    for name, run in runners:
        out = run(pts)
        if isinstance(out, str):
            print(f"\nreal plot ({name}): failed: {out}")
            continue
        xy, dbh, labels, dt, dbh_h = out
        print(f"\nreal plot ({name}): tree1, tree7, tree13 at x = 4, 10, 16 m, y = 10 m (stem bases), "
              f"{len(pts):,} points, {dt:.2f} s: {len(xy)} stems found")
        for k in range(len(xy)):
            near = int(np.argmin(np.abs(xy[k, 0] - np.array([4, 10, 16]))))
            share = (labels[src == near + 1] == (k + 1 if name == "sylva" else labels[src == near + 1])).mean() \
                if labels is not None and (labels >= 0).all() else np.nan
            print(f"  stem {k + 1}: x {xy[k, 0]:.2f} y {xy[k, 1]:.2f} DBH {100 * dbh[k]:.1f} cm at {dbh_h[k]:.1f} m"
                  f" (nearest source tree{(1, 7, 13)[near]})" +
                  (f", {100 * share:.1f} % of its points" if name == "sylva" else ""))


if __name__ == "__main__":
    runners = [("sylva", sylva_run)]
    for a in sys.argv[1:]:
        if a.startswith("--dendromatics"):
            python = a.split("=", 1)[1] if "=" in a else sys.executable
            runners.append(("dendromatics", lambda p, py=python: dendromatics_run(p, py)))
    synthetic(runners)
    real_plot(runners)
