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
2. **Stem detection** (Cabo et al. 2018 §2.2–2.3; Laino et al. 2024's stripe and sections): the stripe
   between ``slice_low_m`` and ``slice_high_m`` above ground is cut into sections ``section_m`` thick, one
   of them centred at ``breast_height_m``; every section's points are clustered (DBSCAN, ``cluster_m``)
   and every cluster of at least ``min_section_points`` gets a least-squares circle (Kåsa's algebraic
   fit refined by Gauss-Newton, refitted once without the points farther than 2.5 RMS or 1 cm from it:
   a branch's base or a twig across the stem).  A circle counts when its RMS residual is under
   ``max_rms_rel`` of the radius + 1 cm over at least ``min_arc_deg``, with a diameter between
   ``min_dbh_m`` and ``max_dbh_m``.  Circles of different sections whose centres lie within the larger
   radius of each other, at most one section apart and of radii within a factor of 2, are one stem
   (a fork's two circles join the one below); a stem needs circles in
   ``min_sections`` sections, the lowest at most ``stem_base_max_m`` up (Sylva: branches and shrubs
   high in the stripe are not stems), and a piece that starts higher than a stem whose circles it
   overlaps belongs to that stem (a fork, a branch).  DBH and position: the stem's single circle at breast height;
   where the stem forks below breast height or a branch spoils the circle there, the nearest section
   below with a single circle, else the nearest above (Sylva, not in the papers; the height is
   reported as :attr:`Stems.dbh_height_m`).  The sections let small trees whose crowns start near
   breast height (the TLS trees of ../shared/data/tls fork or branch at 1.0–1.4 m) be found by their
   lower stem (Sylva: the single breast-height slice of Cabo et al. found none of them,
   ``benchmarks/stems.py``).
3. **Stems followed upward and the rest assigned** (Sylva, after Laino et al.'s assignment of points to
   the stem they are connected to): the points above ground are voxelised (``voxel_m``), voxels linked
   to their neighbours within ``link_m``, and every voxel takes the stem from which its shortest path
   through the voxels is shortest (one multi-source Dijkstra from the voxels of the stems' circles); voxels no stem
   reaches take the tree of the nearest labelled voxel within ``bridge_m`` (a crown above a stretch of
   stem hidden from every scanner; Sylva), the others (isolated shrubs, noise) stay 0, as do ground
   points.

Tree IDs are 1..k in order of the stems' positions (x, then y): deterministic.  :attr:`stems` of
:func:`detect_stems` gives the stems' positions and DBHs.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from ..circles import fit_circles
from ..cloud import PointCloud
from ..errors import InputError
from ..progress import CancelCheck, Progress, check, report

__all__ = ["AutoSegmentation", "StemSegmentation", "Stems", "detect_stems", "ground_under_canopy",
           "is_plot_scan"]


@dataclass(frozen=True)
class Stems:
    """Stems found in the lower stripe: ``xy`` (k, 2) local metres (the centre of the circle the DBH comes
    from), ``dbh_m`` (k,), ``n_points`` (points of the stem's circles), ``dbh_height_m`` (k,) the height
    of the section the DBH was measured in (breast height unless the stem forks or is hidden there)."""

    xy: np.ndarray
    dbh_m: np.ndarray
    n_points: np.ndarray
    dbh_height_m: np.ndarray

    def __len__(self) -> int:
        return len(self.dbh_m)


@dataclass(frozen=True)
class StemSegmentation:
    """Stem-based segmentation of plot scans (see the module docstring for each parameter)."""

    slice_low_m: float = 0.3
    slice_high_m: float = 2.5
    section_m: float = 0.2
    breast_height_m: float = 1.3
    cluster_m: float = 0.08
    min_section_points: int = 10
    min_sections: int = 2
    stem_base_max_m: float = 1.3
    min_dbh_m: float = 0.05
    max_dbh_m: float = 2.0
    min_arc_deg: float = 90.0
    max_rms_rel: float = 0.15
    voxel_m: float = 0.1
    link_m: float = 0.25
    bridge_m: float = 1.0
    ground_m: float = 0.15
    ground_cell_m: float = 0.5
    ground_step_m: float = 0.3

    name = "stems"
    #: the chain (core/segment/tile.py) classifies the ground even of a cloud whose z looks normalised
    exact_ground = True

    def __post_init__(self):
        if not (0 <= self.slice_low_m < self.slice_high_m):
            raise InputError("stems: the slice must have 0 <= slice_low_m < slice_high_m")
        if self.slice_high_m - self.slice_low_m < self.section_m:
            raise InputError("stems: the slice must hold at least one section (slice_high_m - slice_low_m >= section_m)")
        for k in ("cluster_m", "voxel_m", "link_m", "ground_cell_m", "section_m"):
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
            return out, Stems(np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int64), np.zeros(0))
        h = cloud.attr("height")
        if h is None:
            cls = cloud.attr("classification")
            if cls is not None and (np.asarray(cls) == 2).any():
                from ..terrain import normalize

                h = normalize(cloud).attrs["height"]
            else:
                h = xyz[:, 2] - ground_under_canopy(xyz, self.ground_cell_m, self.ground_step_m)
        h = np.asarray(h, dtype=np.float64)
        report(progress, 0.2, "stems in the lower stripe")
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
        vlab = _bridge_pieces(cen, g, vlab, self.bridge_m)
        out[above] = vlab[inv].astype(np.int32)
        report(progress, 1.0, f"{len(stems)} stems")
        return out, stems


def _bridge_pieces(cen: np.ndarray, g, vlab: np.ndarray, bridge_m: float, passes: int = 3) -> np.ndarray:
    """Voxel pieces no stem reaches (a crown above an occluded stretch of stem) take the tree of the
    labelled voxel nearest to them when it is within ``bridge_m`` (Sylva, as levelset's bridges across
    occlusion gaps); nearest pieces first, a few passes."""
    if bridge_m <= 0 or not (vlab > 0).any():
        return vlab
    _, comp = csgraph.connected_components(g, directed=False)
    vlab = vlab.copy()
    for _ in range(passes):
        lab_idx = np.flatnonzero(vlab > 0)
        free = np.flatnonzero(vlab == 0)
        if not len(free) or not len(lab_idx):
            break
        d, j = cKDTree(cen[lab_idx]).query(cen[free], distance_upper_bound=bridge_m, workers=-1)
        hit = np.isfinite(d)
        if not hit.any():
            break
        # per piece its voxel nearest to a tree: the whole piece takes that tree
        fc = comp[free[hit]]
        order = np.lexsort((d[hit], fc))
        fc_o = fc[order]
        firsts = order[np.r_[True, fc_o[1:] != fc_o[:-1]]]
        piece_lab = np.zeros(comp.max() + 1, dtype=vlab.dtype)
        piece_lab[fc[firsts]] = vlab[lab_idx[j[hit][firsts]]]
        # only pieces with no labelled voxel of their own
        has = np.zeros(comp.max() + 1, bool)
        has[comp[lab_idx]] = True
        piece_lab[has] = 0
        take = (vlab == 0) & (piece_lab[comp] > 0)
        if not take.any():
            break
        vlab[take] = piece_lab[comp[take]]
    return vlab


def detect_stems(xyz: np.ndarray, height: np.ndarray, opt: StemSegmentation = StemSegmentation()):
    """Stems crossing the lower stripe (Cabo et al. 2018 §2.2–2.3, as sections): (Stems in ID order, indices
    of the section points that belong to a stem, their tree IDs).  See the module docstring, step 2."""
    from sklearn.cluster import DBSCAN

    empty = (Stems(np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int64), np.zeros(0)),
             np.zeros(0, np.int64), np.zeros(0, np.int32))
    s, bh = opt.section_m, opt.breast_height_m
    k_lo = int(np.ceil((opt.slice_low_m + s / 2 - bh) / s - 1e-9))
    k_hi = int(np.floor((opt.slice_high_m - s / 2 - bh) / s + 1e-9))
    centres = bh + s * np.arange(k_lo, k_hi + 1)
    if not len(centres):
        return empty
    sec = np.floor((height - (centres[0] - s / 2)) / s).astype(np.int64)
    sl = np.flatnonzero((sec >= 0) & (sec < len(centres)) & np.isfinite(height))
    if len(sl) < opt.min_section_points:
        return empty
    sec = sec[sl]
    # clusters of every section at once: the sections lie 1 km apart in a third coordinate
    key = np.c_[xyz[sl, :2], sec * 1000.0]
    lab = DBSCAN(eps=opt.cluster_m, min_samples=5).fit_predict(key)
    ok = lab >= 0
    sl, sec, lab = sl[ok], sec[ok], lab[ok]
    if not len(sl):
        return empty
    _, grp = np.unique(lab, return_inverse=True)
    grp = grp.reshape(-1)
    m = int(grp.max()) + 1
    x, y = xyz[sl, 0], xyz[sl, 1]
    live = np.bincount(grp, minlength=m) >= opt.min_section_points
    use = live[grp]
    cx, cy, r, rms, arc = fit_circles(x[use], y[use], grp[use], m)
    # one trimmed refit: points off the circle (a branch's base, a twig across the stem) are left out
    dev = np.abs(np.hypot(x - cx[grp], y - cy[grp]) - r[grp])
    inl = use & (dev <= np.maximum(2.5 * rms[grp], 0.01))
    cx, cy, r, rms, arc = fit_circles(x[inl], y[inl], grp[inl], m)
    n_in = np.bincount(grp[inl], minlength=m)
    # a stem is hollow in its slice (the scanner sees its bark): points well inside the circle are twigs
    # or leaves around which a circle was fitted (Laino et al. 2024 / dendromatics' check of the points
    # inside the circle; 0.7 r and 5 %: Sylva, measured on benchmarks/stems.py's real plot)
    inside = use & (np.hypot(x - cx[grp], y - cy[grp]) < 0.7 * r[grp])
    hollow = np.bincount(grp[inside], minlength=m) <= 0.05 * np.bincount(grp[use], minlength=m)
    good = (live & hollow & (n_in >= opt.min_section_points) & np.isfinite(r) & (2 * r >= opt.min_dbh_m)
            & (2 * r <= opt.max_dbh_m) & (rms <= opt.max_rms_rel * r + 0.01) & (arc >= opt.min_arc_deg))
    gi = np.flatnonzero(good)
    if not len(gi):
        return empty
    gsec = np.zeros(m, np.int64)
    gsec[grp] = sec
    # circles of one stem: centres within the larger radius of each other, in different sections
    c_xy = np.c_[cx[gi], cy[gi]]
    pairs = cKDTree(c_xy).query_pairs(opt.max_dbh_m / 2, output_type="ndarray")
    if len(pairs):
        d = np.linalg.norm(c_xy[pairs[:, 0]] - c_xy[pairs[:, 1]], axis=1)
        ra, rb = r[gi][pairs[:, 0]], r[gi][pairs[:, 1]]
        gap = np.abs(gsec[gi][pairs[:, 0]] - gsec[gi][pairs[:, 1]])
        keep = (d <= np.maximum(ra, rb)) & (gap >= 1) & (gap <= 2) & (np.minimum(ra, rb) >= 0.5 * np.maximum(ra, rb))
        pairs = pairs[keep]
    g = sparse.csr_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(gi), len(gi)))
    _, comp = csgraph.connected_components(g, directed=False)
    # a piece that starts higher than a stem it overlaps (circles closer than their radii' sum) is a fork or
    # a branch of that stem, not another tree (Sylva)
    low = np.full(comp.max() + 1, np.iinfo(np.int64).max)
    np.minimum.at(low, comp, gsec[gi])
    cp = cKDTree(c_xy).query_pairs(opt.max_dbh_m, output_type="ndarray")
    if len(cp):
        a, b = comp[cp[:, 0]], comp[cp[:, 1]]
        touch = (np.linalg.norm(c_xy[cp[:, 0]] - c_xy[cp[:, 1]], axis=1) < r[gi][cp[:, 0]] + r[gi][cp[:, 1]])
        touch &= (a != b) & (low[a] != low[b])
        if touch.any():
            ug = sparse.csr_matrix((np.ones(touch.sum()), (a[touch], b[touch])), shape=(len(low), len(low)))
            _, cmap = csgraph.connected_components(ug, directed=False)
            comp0, comp = comp, cmap[comp]
        else:
            comp0 = comp
    else:
        comp0 = comp
    found = []
    bh_sec = int(round((bh - centres[0]) / s))
    for c in np.unique(comp):
        mem = gi[comp == c]
        secs = gsec[mem]
        if len(np.unique(secs)) < opt.min_sections or centres[secs.min()] > opt.stem_base_max_m:
            continue                  # a branch, a shrub, or a stem seen in too few sections
        # DBH: on the trunk (the piece that reaches lowest), the single circle of the breast-height
        # section; else (a fork or a branch there) the nearest section below with a single circle, else
        # the nearest above (Sylva; the height is reported)
        pieces = comp0[comp == c]
        trunk = min(np.unique(pieces), key=lambda p: (low[p], -int((pieces == p).sum()), p))
        tsecs = secs[pieces == trunk]
        single = [q for q in np.unique(tsecs) if (tsecs == q).sum() == 1]
        if not single:
            continue
        below = [q for q in single if q <= bh_sec]
        q = max(below) if below else min(single)
        j = mem[(secs == q) & (pieces == trunk)][0]
        pts = sl[inl & np.isin(grp, mem)]
        found.append((float(cx[j]), float(cy[j]), float(2 * r[j]), float(centres[q]), pts))
    if not found:
        return empty
    found.sort(key=lambda f: (round(f[0], 3), round(f[1], 3)))
    stems = Stems(np.array([[f[0], f[1]] for f in found]), np.array([f[2] for f in found]),
                  np.array([len(f[4]) for f in found], dtype=np.int64), np.array([f[3] for f in found]))
    idx = np.concatenate([f[4] for f in found])
    tid = np.concatenate([np.full(len(f[4]), i + 1, dtype=np.int32) for i, f in enumerate(found)])
    return stems, idx, tid


def ground_under_canopy(xyz: np.ndarray, cell_m: float = 0.5, step_m: float = 0.3) -> np.ndarray:
    """Ground elevation under every point from the lowest returns (see the module docstring, step 1)."""
    from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator
    from scipy.ndimage import median_filter

    xy0 = np.floor(xyz[:, :2].min(axis=0) / cell_m) * cell_m      # cells on a global grid (tiling-invariant)
    ij = np.floor((xyz[:, :2] - xy0) / cell_m).astype(np.int64)
    shape = ij.max(axis=0) + 1
    flat = ij[:, 0] * shape[1] + ij[:, 1]
    low = np.full(shape[0] * shape[1], np.inf)
    np.minimum.at(low, flat, xyz[:, 2])
    grid = low.reshape(shape)
    filled = np.where(np.isfinite(grid), grid, np.nan)
    ref = median_filter(grid, size=5, mode="nearest")          # empty cells (inf) count as high
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


def is_plot_scan(cloud: PointCloud, opt: StemSegmentation = StemSegmentation()) -> bool:
    """True for a terrestrial / mobile plot scan (a height-normalised cloud): the rule of dense single
    trees (:func:`sylva.core.reconstruct.kmeans.is_dense_scan`) applied to the ground-normalised points
    (Sylva): at least ``DENSE_LOW_SHARE`` of the points above ground lie below ``DENSE_LOW_M`` (stems
    seen from below), those points are dense (median distance to the 8th neighbour at most
    ``DENSE_SPACING_M``), and stems are found in them (:func:`detect_stems`).  Airborne tiles see the
    crowns from above: few points low down, too sparse, no circles."""
    from ..reconstruct.kmeans import DENSE_LOW_M, DENSE_LOW_SHARE, DENSE_MIN_POINTS, DENSE_SPACING_M

    h = cloud.attr("height")
    if h is None or len(cloud) < DENSE_MIN_POINTS:
        return False
    h = np.asarray(h, dtype=np.float64)
    above = h >= opt.ground_m
    low = np.flatnonzero(above & (h < DENSE_LOW_M))
    if len(low) < DENSE_MIN_POINTS or len(low) < DENSE_LOW_SHARE * above.sum():
        return False
    xyz = cloud.local_xyz()
    sub = low if len(low) <= 50_000 else low[np.random.default_rng(0).choice(len(low), 50_000, replace=False)]
    d, _ = cKDTree(xyz[low]).query(xyz[sub], k=9, workers=-1)
    if np.median(d[:, 8]) > DENSE_SPACING_M:
        return False
    stems, _, _ = detect_stems(xyz, h, opt)
    return len(stems) > 0


@dataclass(frozen=True)
class AutoSegmentation:
    """``plot`` (:class:`StemSegmentation`) for terrestrial / mobile plot scans (:func:`is_plot_scan`),
    ``other`` (by default :class:`~sylva.core.segment.NormalizedCut`) for the rest (Sylva)."""

    plot: StemSegmentation = StemSegmentation()
    other: object = None

    name = "auto"

    def resolve(self, cloud: PointCloud):
        """The method for this height-normalised cloud."""
        from . import NormalizedCut

        if is_plot_scan(cloud, self.plot):
            return self.plot
        return NormalizedCut() if self.other is None else self.other

    def segment(self, cloud: PointCloud, tops=None, progress: Progress = None, cancelled: CancelCheck = None):
        return self.resolve(cloud).segment(cloud, tops, progress, cancelled)
