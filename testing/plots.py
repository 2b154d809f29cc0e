"""Synthetic terrestrial plot scans with known stems (issue 18): tests and benchmarks of stem segmentation.

    pts, truth = plot_scan(n_trees=12, size_m=20, seed=0)

Stems are tapered vertical cylinders (position, DBH, height drawn at random, at least 2 m apart), sampled
on their surface every ``spacing_m`` and kept where a scanner sees them: the surface faces one of the
``scanners`` (positions on the plot) and no other stem crosses the line of sight.  Each tree also gets a
crown (points in an ellipsoid over its upper half, 5 % of a stem's points per m³, thinned by the height
as canopy hides the top from the ground) and the plot a gently sloping, rough ground.  ``truth``: per tree
``x``, ``y``, ``dbh``, ``height`` and per point ``tree`` (0 ground).
"""
from __future__ import annotations

import numpy as np


def plot_scan(n_trees: int = 12, size_m: float = 20.0, seed: int = 0, spacing_m: float = 0.02,
              scanners=None, noise_m: float = 0.003):
    rng = np.random.default_rng(seed)
    xy, dbh, height = [], [], []
    while len(xy) < n_trees:
        p = rng.uniform(1.5, size_m - 1.5, 2)
        if all(np.hypot(*(p - q)) > 2.0 for q in xy):
            xy.append(p)
            dbh.append(rng.uniform(0.12, 0.6))
            height.append(rng.uniform(10, 22))
    xy, dbh, height = np.array(xy), np.array(dbh), np.array(height)
    if scanners is None:
        c = size_m / 2
        scanners = np.array([[c, c], [c * 0.4, c * 0.4], [c * 1.6, c * 0.5], [c * 0.5, c * 1.6], [c * 1.6, c * 1.6]])
    scanners = np.asarray(scanners, dtype=float)
    slope = rng.uniform(-0.05, 0.05, 2)
    ground_z = lambda q: q @ slope   # noqa: E731
    pts, tree = [], []
    for t in range(n_trees):
        stem_h = 0.6 * height[t]
        r0 = dbh[t] / 2 / (1 - 0.7 * 1.3 / stem_h)       # the taper below gives DBH at 1.3 m
        nz = int(stem_h / spacing_m)
        na = max(12, int(2 * np.pi * r0 / spacing_m))
        z, a = np.meshgrid(np.arange(nz) * spacing_m, np.arange(na) * 2 * np.pi / na, indexing="ij")
        z, a = z.ravel() + rng.uniform(0, spacing_m, z.size), a.ravel() + rng.uniform(0, 2 * np.pi / na, a.size)
        r = r0 - (r0 - 0.3 * r0) * z / stem_h
        s = np.c_[xy[t, 0] + r * np.cos(a), xy[t, 1] + r * np.sin(a)]
        normal = np.c_[np.cos(a), np.sin(a)]
        seen = np.zeros(len(s), bool)
        for sc in scanners:
            v = sc - s
            facing = (v * normal).sum(1) > 0
            blocked = np.zeros(len(s), bool)
            for u in range(n_trees):
                if u == t:
                    continue
                # distance from stem u's axis to the segment point -> scanner
                w = xy[u] - s
                L = np.linalg.norm(v, axis=1)
                tt = np.clip((w * v).sum(1) / L ** 2, 0, 1)
                d = np.linalg.norm(s + tt[:, None] * v - xy[u], axis=1)
                blocked |= d < dbh[u] / 2
            seen |= facing & ~blocked
        s, z = s[seen], z[seen]
        p = np.c_[s, z + ground_z(s)] + rng.normal(0, noise_m, (len(s), 3))
        pts.append(p)
        tree.append(np.full(len(p), t + 1))
        # crown: an ellipsoid over the upper half, fewer points higher up (occluded from below)
        cr = 0.12 * height[t] + 1.0
        nc = int(150 * cr ** 2)
        u = rng.normal(size=(nc, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        u *= rng.uniform(0, 1, (nc, 1)) ** (1 / 3)
        c = np.c_[xy[t, 0] + cr * u[:, 0], xy[t, 1] + cr * u[:, 1], 0.75 * height[t] + 0.25 * height[t] * u[:, 2]]
        keep = rng.uniform(size=nc) < np.clip(1.2 - (c[:, 2] / height[t]), 0.1, 1)
        c = c[keep]
        c[:, 2] += ground_z(c[:, :2])
        pts.append(c)
        tree.append(np.full(len(c), t + 1))
    g = rng.uniform(0, size_m, (int(size_m ** 2 * 40), 2))
    gz = ground_z(g) + rng.normal(0, 0.02, len(g))
    pts.append(np.c_[g, gz])
    tree.append(np.zeros(len(g), int))
    truth = dict(x=xy[:, 0], y=xy[:, 1], dbh=dbh, height=height, tree=np.concatenate(tree))
    return np.vstack(pts), truth
