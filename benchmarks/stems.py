"""Stem segmentation of terrestrial plot scans (sylva.core.segment.stems), against synthetic truth.

    python benchmarks/stems.py

* synthetic plots (tests/sylva.testing.plots.py: stems with known positions, DBH and heights, seen from five
  scanner positions with occlusion by the other stems, crowns, rough sloping ground): stem detection
  recall and precision (a detected stem matches a true one within 30 cm), DBH RMSE, position error,
  share of each matched tree's points labelled with its ID, time;
* a plot built from the shared single-tree scans (../shared/data/tls tree1, tree7, tree13 placed 6 m
  apart on a 20 m plot with a synthetic ground): the trees found and the DBH of each.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from sylva.core.cloud import PointCloud
from sylva.core.segment.stems import StemSegmentation
from sylva.testing.plots import plot_scan

HERE = Path(__file__).resolve()

TLS = HERE.parents[1].parent / "shared" / "data" / "tls"


def synthetic():
    print(f"{'plot':<22}{'points':>9}{'trees':>6}{'found':>6}{'recall':>8}{'precision':>10}{'DBH RMSE cm':>12}"
          f"{'pos err cm':>11}{'pts ok %':>9}{'s':>7}")
    for n, size, seed in ((8, 16, 1), (15, 20, 2), (25, 25, 3), (40, 30, 4)):
        pts, truth = plot_scan(n_trees=n, size_m=size, seed=seed)
        cloud = PointCloud(pts, {})
        t0 = time.perf_counter()
        labels, stems = StemSegmentation().segment_with_stems(cloud)
        dt = time.perf_counter() - t0
        t = np.c_[truth["x"], truth["y"]]
        xy = stems.xy + cloud.origin[:2]
        d = np.linalg.norm(xy[:, None] - t[None], axis=2) if len(xy) else np.zeros((0, n))
        j = d.argmin(axis=1) if len(xy) else np.zeros(0, int)
        ok = d[np.arange(len(j)), j] < 0.3 if len(xy) else np.zeros(0, bool)
        recall = len(set(j[ok])) / n
        precision = ok.mean() if len(ok) else 0.0
        rmse = np.sqrt(np.mean((stems.dbh_m[ok] - truth["dbh"][j[ok]]) ** 2)) * 100 if ok.any() else np.nan
        pos = d[np.arange(len(j)), j][ok].mean() * 100 if ok.any() else np.nan
        share = np.mean([(labels[truth["tree"] == jj + 1] == k + 1).mean() for k, jj in zip(np.flatnonzero(ok), j[ok])])
        print(f"{f'{n} trees, {size} m, seed {seed}':<22}{len(pts):>9}{n:>6}{len(stems):>6}{recall:>8.2f}"
              f"{precision:>10.2f}{rmse:>12.2f}{pos:>11.2f}{100 * share:>9.1f}{dt:>7.2f}")


def real_plot():
    files = [TLS / f"tree{i}.xyz" for i in (1, 7, 13)]
    if not all(f.exists() for f in files):
        print(f"(no TLS trees at {TLS})")
        return
    rng = np.random.default_rng(0)
    parts, where, src = [], [], []
    for k, f in enumerate(files):
        x = np.loadtxt(f)
        low = x[x[:, 2] < x[:, 2].min() + 0.3]
        x = x - np.r_[low[:, :2].mean(axis=0), x[:, 2].min()] + np.r_[4 + 6 * k, 10, 0]
        parts.append(x)
        src.append(np.full(len(x), k + 1))
        where.append((4 + 6 * k, 10))
    g = rng.uniform(0, 20, (16000, 2))
    parts.append(np.c_[g, rng.normal(0, 0.02, len(g))])
    src.append(np.zeros(len(g), int))
    pts = np.vstack(parts)
    src = np.concatenate(src)
    cloud = PointCloud(pts, {})
    t0 = time.perf_counter()
    labels, stems = StemSegmentation().segment_with_stems(cloud)
    dt = time.perf_counter() - t0
    print(f"\nreal plot: tree1, tree7, tree13 at x = 4, 10, 16 m, y = 10 m (stem bases), {len(pts):,} points, "
          f"{dt:.2f} s: {len(stems)} stems found")
    for k in range(len(stems)):
        x, y = stems.xy[k] + cloud.origin[:2]
        print(f"  stem {k + 1}: x {x:.2f} y {y:.2f} DBH {100 * stems.dbh_m[k]:.1f} cm at {stems.dbh_height_m[k]:.1f} m, "
              f"{int((labels == k + 1).sum()):,} points, "
              f"{100 * np.mean([(labels[src == t] == k + 1).mean() for t in (1, 2, 3)][k]) if len(stems) == 3 else 0:.1f} % "
              "of its source tree's points")


if __name__ == "__main__":
    synthetic()
    real_plot()
