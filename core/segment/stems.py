"""Trees of terrestrial / mobile plot scans segmented by their stems (3DFin / dendromatics' approach).

    labels = segment_trees(cloud, StemSegmentation())

Cabo, Ordóñez, López-Sánchez & Armesto (2018), "Automatic dendrometry: tree detection, tree height and
diameter estimation using terrestrial laser scanning", Int. J. Appl. Earth Obs. Geoinf. 69:164–174, and
Laino, Cabo, Prendes, Janvier, Ordóñez, Nikonovas, Doerr & Santin (2024), "3DFin: a software for automated
3D forest inventories from terrestrial point clouds", Forestry 97(4):479–496 (the dendromatics package):
under a canopy the stems are what a terrestrial scan sees best, so trees are found where stems cross a
slice at breast height and every other point follows its stem.  This module does, in that spirit:

1. **Ground under canopy** (:func:`ground_under_canopy`, used when the cloud has neither heights nor a
   ground class): the lowest point of every ``ground_cell_m`` cell, cells higher than ``ground_step_m``
   above the median of their 5 × 5 neighbourhood dropped (stems, low branches), the rest interpolated
   (linear in their triangulation, nearest outside it).  Crowns above do not matter: only the lowest
   returns are used, which a terrestrial scan has under any canopy.
2. **Stem detection** (Cabo et al. 2018 §2.2–2.3): the points between ``slice_low_m`` and
   ``slice_high_m`` above ground are clustered (DBSCAN, ``cluster_m``); a cluster is a stem when it
   spans most of the slice's height and in at least two of three sub-slices its points fit a circle
   (algebraic fit refined by Gauss-Newton) with an RMS residual under ``max_rms_rel`` of the radius + 1 cm
   over at least ``min_arc_deg``, of a diameter between ``min_dbh_m`` and ``max_dbh_m`` (Sylva: sub-slices
   for leaning stems).  The median of those circles is the stem's position and DBH.
3. **Stems followed upward and the rest assigned** (Sylva, after Laino et al.'s assignment of points to
   the stem they are connected to): the points above ground are voxelised (``voxel_m``), voxels linked
   to their neighbours within ``link_m``, and every voxel takes the stem from which its shortest path
   through the voxels is shortest (one multi-source Dijkstra from the stems' slice voxels); voxels no stem
   reaches (isolated shrubs, noise) stay 0, as do ground points.

Tree IDs are 1..k in order of the stems' positions (x, then y): deterministic.  :attr:`stems` of
:func:`detect_stems` gives the stems' positions and DBHs.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from ..cloud import PointCloud
from ..errors import InputError
from ..progress import CancelCheck, Progress, check, report

__all__ = ["StemSegmentation", "Stems", "detect_stems", "ground_under_canopy"]


@dataclass(frozen=True)
class Stems:
    """Stems found in the breast-height slice: ``xy`` (k, 2) local metres, ``dbh_m`` (k,), ``n_points``."""

    xy: np.ndarray
    dbh_m: np.ndarray
    n_points: np.ndarray

    def __len__(self) -> int:
        return len(self.dbh_m)


@dataclass(frozen=True)
class StemSegmentation:
    """Stem-based segmentation of plot scans (see the module docstring for each parameter)."""

    slice_low_m: float = 1.0
    slice_high_m: float = 1.6
    cluster_m: float = 0.08
    min_cluster_points: int = 15
    min_dbh_m: float = 0.05
    max_dbh_m: float = 2.0
    min_arc_deg: float = 90.0
    max_rms_rel: float = 0.15
    voxel_m: float = 0.1
    link_m: float = 0.25
    ground_m: float = 0.15
    ground_cell_m: float = 0.5
    ground_step_m: float = 0.3

    name = "stems"

    def __post_init__(self):
        if not (0 <= self.slice_low_m < self.slice_high_m):
            raise InputError("stems: the slice must have 0 <= slice_low_m < slice_high_m")
        for k in ("cluster_m", "voxel_m", "link_m", "ground_cell_m"):
            if not getattr(self, k) > 0:
                raise InputError(f"stems: {k} must be > 0 m, got {getattr(self, k)!r}")

    def segment(self, cloud: PointCloud, tops=None, progress: Progress = None,
                cancelled: CancelCheck = None) -> np.ndarray:
        labels, _ = self.segment_with_stems(cloud, progress, cancelled)
        return labels

    def segment_with_stems(self, cloud: PointCloud, progress: Progress = None, cancelled: CancelCheck = None):
        """(int32 tree ID per point, :class:`Stems` in ID order)."""
        xyz = cloud.local_xyz()
        n = len(xyz)
        out = np.zeros(n, dtype=np.int32)
        if n == 0:
            return out, Stems(np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int64))
        h = cloud.attr("height")
        if h is None:
            cls = cloud.attr("classification")
            if cls is not None and (np.asarray(cls) == 2).any():
                from ..terrain import normalize

                h = normalize(cloud).attrs["height"]
            else:
                h = xyz[:, 2] - ground_under_canopy(xyz, self.ground_cell_m, self.ground_step_m)
        h = np.asarray(h, dtype=np.float64)
        report(progress, 0.2, "stems at breast height")
        stems, slice_idx, slice_lab = detect_stems(xyz, h, self)
        check(cancelled)
        if not len(stems):
            return out, stems
        report(progress, 0.5, "points to their stems")
        above = np.flatnonzero(h >= self.ground_m)
        key = np.floor(xyz[above] / self.voxel_m).astype(np.int64)
        _, vox, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
        inv = inv.reshape(-1)
        nv = len(vox)
        cnt = np.bincount(inv, minlength=nv).astype(float)
        cen = np.stack([np.bincount(inv, weights=xyz[above, c], minlength=nv) for c in range(3)], 1) / cnt[:, None]
        pairs = cKDTree(cen).query_pairs(self.link_m, output_type="ndarray")
        w = np.linalg.norm(cen[pairs[:, 0]] - cen[pairs[:, 1]], axis=1) + 1e-6
        g = sparse.csr_matrix((np.r_[w, w], (np.r_[pairs[:, 0], pairs[:, 1]], np.r_[pairs[:, 1], pairs[:, 0]])),
                              shape=(nv, nv))
        pos = np.full(n, -1, dtype=np.int64)
        pos[above] = np.arange(len(above))
        sv = inv[pos[slice_idx]]
        ok = pos[slice_idx] >= 0
        src_vox, src_lab = sv[ok], slice_lab[ok]
        uniq, first = np.unique(src_vox, return_index=True)
        check(cancelled)
        _, _, source = csgraph.dijkstra(g, directed=False, indices=uniq, min_only=True, return_predecessors=True)
        vlab = np.where(source >= 0, src_lab[first][np.searchsorted(uniq, np.maximum(source, 0))], 0)
        out[above] = vlab[inv].astype(np.int32)
        report(progress, 1.0, f"{len(stems)} stems")
        return out, stems


def detect_stems(xyz: np.ndarray, height: np.ndarray, opt: StemSegmentation = StemSegmentation()):
    """Stems crossing the breast-height slice (Cabo et al. 2018 §2.2–2.3): (Stems in ID order, indices of
    the slice points that belong to a stem, their tree IDs)."""
    from sklearn.cluster import DBSCAN

    sl = np.flatnonzero((height >= opt.slice_low_m) & (height <= opt.slice_high_m))
    empty = Stems(np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int64))
    if len(sl) < opt.min_cluster_points:
        return empty, np.zeros(0, np.int64), np.zeros(0, np.int32)
    lab = DBSCAN(eps=opt.cluster_m, min_samples=5).fit_predict(xyz[sl])
    found = []
    for c in range(lab.max() + 1):
        idx = sl[lab == c]
        if len(idx) < opt.min_cluster_points:
            continue
        hz = height[idx]
        if np.ptp(hz) < 0.6 * (opt.slice_high_m - opt.slice_low_m):
            continue                      # does not cross the slice: a branch or a shrub
        # circles in three sub-slices (a leaning or crooked stem smears one circle over the whole slice);
        # a stem needs two that pass, its DBH and position are their medians
        edges = np.linspace(opt.slice_low_m, opt.slice_high_m, 4)
        good = []
        for lo, hi in zip(edges[:-1], edges[1:]):
            sub = idx[(hz >= lo) & (hz <= hi)]
            fit = _circle(xyz[sub, :2]) if len(sub) >= 6 else None
            if fit is None:
                continue
            cx, cy, r, rms, arc = fit
            if opt.min_dbh_m <= 2 * r <= opt.max_dbh_m and rms <= opt.max_rms_rel * r + 0.01 and arc >= opt.min_arc_deg:
                good.append((cx, cy, 2 * r))
        if len(good) < 2:
            continue
        g = np.median(np.array(good), axis=0)
        found.append((float(g[0]), float(g[1]), float(g[2]), idx))
    if not found:
        return empty, np.zeros(0, np.int64), np.zeros(0, np.int32)
    found.sort(key=lambda f: (round(f[0], 3), round(f[1], 3)))
    stems = Stems(np.array([[f[0], f[1]] for f in found]), np.array([f[2] for f in found]),
                  np.array([len(f[3]) for f in found], dtype=np.int64))
    idx = np.concatenate([f[3] for f in found])
    tid = np.concatenate([np.full(len(f[3]), i + 1, dtype=np.int32) for i, f in enumerate(found)])
    return stems, idx, tid


def _circle(p: np.ndarray, iterations: int = 8):
    """(cx, cy, r, rms, arc in degrees covered, 30° sectors) of the best circle through 2-D points, or None."""
    x, y = p[:, 0] - p[:, 0].mean(), p[:, 1] - p[:, 1].mean()
    a = np.c_[x, y, np.ones_like(x)]
    try:
        sol = np.linalg.lstsq(a, x * x + y * y, rcond=None)[0]
    except np.linalg.LinAlgError:
        return None
    cx, cy = sol[0] / 2, sol[1] / 2
    r = np.sqrt(max(sol[2] + cx * cx + cy * cy, 0.0))
    for _ in range(iterations):
        dx, dy = x - cx, y - cy
        d = np.maximum(np.hypot(dx, dy), 1e-12)
        j = np.c_[-dx / d, -dy / d, -np.ones_like(d)]
        try:
            step = np.linalg.lstsq(j, -(d - r), rcond=None)[0]
        except np.linalg.LinAlgError:
            return None
        cx, cy, r = cx + step[0], cy + step[1], r + step[2]
    if not (np.isfinite(r) and r > 0):
        return None
    dx, dy = x - cx, y - cy
    rms = float(np.sqrt(np.mean((np.hypot(dx, dy) - r) ** 2)))
    sec = (np.floor((np.arctan2(dy, dx) + np.pi) / (np.pi / 6)).astype(int)) % 12
    arc = 30.0 * len(np.unique(sec))
    return cx + p[:, 0].mean(), cy + p[:, 1].mean(), float(r), rms, arc


def ground_under_canopy(xyz: np.ndarray, cell_m: float = 0.5, step_m: float = 0.3) -> np.ndarray:
    """Ground elevation under every point from the lowest returns (see the module docstring, step 1)."""
    from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator
    from scipy.ndimage import median_filter

    xy0 = xyz[:, :2].min(axis=0)
    ij = np.floor((xyz[:, :2] - xy0) / cell_m).astype(np.int64)
    shape = ij.max(axis=0) + 1
    flat = ij[:, 0] * shape[1] + ij[:, 1]
    low = np.full(shape[0] * shape[1], np.inf)
    np.minimum.at(low, flat, xyz[:, 2])
    grid = low.reshape(shape)
    filled = np.where(np.isfinite(grid), grid, np.nan)
    ref = median_filter(np.where(np.isfinite(filled), filled, np.nanmax(filled)), size=5, mode="nearest")
    good = np.isfinite(filled) & (filled <= ref + step_m)
    gi, gj = np.nonzero(good)
    pts = np.c_[xy0[0] + (gi + 0.5) * cell_m, xy0[1] + (gj + 0.5) * cell_m]
    val = filled[gi, gj]
    if len(val) < 3:
        return np.full(len(xyz), float(np.min(xyz[:, 2])))
    z = LinearNDInterpolator(pts, val)(xyz[:, :2])
    miss = ~np.isfinite(z)
    if miss.any():
        z[miss] = NearestNDInterpolator(pts, val)(xyz[miss, :2])
    return z
