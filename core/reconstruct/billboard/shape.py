"""Billboard shapes: Zhou et al. 2013, "Automatic reconstruction of lightweight trees" §V/§VI-A.

The tree's points projected onto vertical planes and rasterised into shape masks (closed, hole-filled,
specks removed), the width function f(y) and its first change, the RANSAC trunk edge lines, the trunk and
crown boxes of one plane (:func:`fit_plane`) and their least-squares combination into a 3D trunk axis and a
vertical crown axis (:func:`shape_fit`).  ``method`` is a :class:`~.tree.Billboard`.  The speed-ups
(subset-bounded spacing, exact-disc closing, bounding-box hole filling) are Sylva's, not in the paper; see
:mod:`sylva.core.reconstruct.billboard`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Optional, Tuple

import numpy as np


# --------------------------------------------------------------------------- §V/§VI-A masks

def _spacing(xyz: np.ndarray) -> float:
    """Median distance to the nearest other point (m), over up to 2000 evenly spaced points."""
    from scipy.spatial import cKDTree

    if len(xyz) < 2:
        return 0.0
    query = xyz if len(xyz) <= 2000 else xyz[np.linspace(0, len(xyz) - 1, 2000).astype(np.int64)]
    d, _ = cKDTree(xyz, balanced_tree=False, compact_nodes=False).query(query, k=2)
    d = d[:, 1]
    d = d[d > 0]
    return float(np.median(d)) if len(d) else 0.0


_SPACING_SUBSET = 8000


def _close_px(xyz: np.ndarray, method: "Billboard") -> int:
    """Closing radius in pixels: ``close_m`` or the median point spacing (:func:`_spacing`), at most ``max_close_m``.

    Sylva, not in the paper (speed, same result): a dense tree does not need a
    k-d tree of all its points.  The same query points searched among a subset
    of the points that contains them have nearest-neighbour distances at least
    as large, so the subset's median is an upper bound of :func:`_spacing`;
    when that bound already gives the smallest radius (``close_m``) it is the
    exact answer, otherwise all points are searched.
    """
    p = method.pixel_m

    def radius(spacing):
        return int(np.ceil(min(max(method.close_m, spacing), method.max_close_m) / p))

    n = len(xyz)
    floor_px = radius(0.0)
    if n > _SPACING_SUBSET:
        from scipy.spatial import cKDTree

        query = np.linspace(0, n - 1, 2000).astype(np.int64)
        sub = np.union1d(np.linspace(0, n - 1, _SPACING_SUBSET).astype(np.int64), query)
        d, _ = cKDTree(xyz[sub], balanced_tree=False, compact_nodes=False).query(xyz[query], k=2)
        d = d[:, 1]
        d = d[d > 0]
        if len(d) and radius(float(np.median(d))) == floor_px:
            return floor_px
    return radius(_spacing(xyz))


def _disc_dilate(img: np.ndarray, r: int) -> np.ndarray:
    """Binary dilation by the disc {dx² + dy² <= r²}, outside the array False: exactly
    ``distance_transform_edt(~img) <= r`` (when img has a True pixel).

    A pixel is reached when, for some row offset |dy| <= r, the row dy away has a True pixel within
    the disc's chord half-width floor(sqrt(r² - dy²)): one horizontal gap image, then one comparison
    and one OR per row offset.
    """
    h, w = img.shape
    j = np.arange(w, dtype=np.int32)
    far = np.int32(w + r + 2)                                               # gap > r in a row with none
    left = np.maximum.accumulate(np.where(img, j, -far), axis=1)          # nearest True at or left of j
    right = np.minimum.accumulate(np.where(img, j, far)[:, ::-1], axis=1)[:, ::-1]
    gap = np.minimum(j - left, right - j)                                  # horizontal distance to it
    out = np.zeros_like(img)
    within: Dict[int, np.ndarray] = {}
    for dy in range(-min(r, h - 1), min(r, h - 1) + 1):
        half = int(np.floor(np.sqrt(r * r - dy * dy)))
        while (half + 1) ** 2 + dy * dy <= r * r:   # guard the float square root
            half += 1
        while half * half + dy * dy > r * r:
            half -= 1
        if half not in within:
            within[half] = gap <= half
        row = within[half]
        if dy >= 0:
            out[dy:] |= row[:h - dy]
        else:
            out[:h + dy] |= row[-dy:]
    return out


def _fill_holes(mask: np.ndarray) -> np.ndarray:
    """``scipy.ndimage.binary_fill_holes``: background (4-connected) not reaching the border becomes foreground."""
    from scipy import ndimage

    bg, n = ndimage.label(~mask)
    if n == 0:
        return mask.copy()
    outside = np.zeros(n + 1, dtype=bool)
    for edge in (bg[0], bg[-1], bg[:, 0], bg[:, -1]):
        outside[edge] = True
    outside[0] = True
    return mask | ~outside[bg]


def _disc_offsets(r: int, width: int) -> np.ndarray:
    """Flat index offsets of the disc {dx² + dy² <= r²} in an array ``width`` pixels wide."""
    dy, dx = np.mgrid[-r:r + 1, -r:r + 1]
    inside = dx * dx + dy * dy <= r * r
    return (dy[inside] * width + dx[inside]).astype(np.int64)


def _mask_pixels(row: np.ndarray, col: np.ndarray, shape, close_px: int, min_blob_fraction: float) -> np.ndarray:
    """The shape mask from the pixel indices of the points (see :func:`shape_mask`); the points must lie at
    least ``close_px`` pixels inside the array (as :func:`shape_mask`'s padding makes them)."""
    from scipy import ndimage

    h, w = shape
    flat = row * w + col
    occ = np.zeros(shape, dtype=bool)
    occ.ravel()[flat] = True
    r = int(close_px)
    if r > 0:           # closing: dilation, then erosion as the complement's dilation (exact discs)
        disc = _disc_offsets(r, w)
        if len(flat) * len(disc) <= 2 * (2 * r + 1) * h * w:
            dil = np.zeros(shape, dtype=bool)           # few points: stamp the disc on each
            dil.ravel()[(flat[:, None] + disc[None, :]).ravel()] = True
        else:
            dil = _disc_dilate(occ, r)
        mask = ~_disc_dilate(~dil, r)
        mask |= occ
    else:
        mask = occ
    # holes and specks inside the mask's bounding box plus a background ring (the same components)
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    r0, r1 = max(0, int(rows[0]) - 1), min(h, int(rows[-1]) + 2)
    c0, c1 = max(0, int(cols[0]) - 1), min(w, int(cols[-1]) + 2)
    box = _fill_holes(mask[r0:r1, c0:c1])
    lab, n = ndimage.label(box, structure=np.ones((3, 3), bool))
    if n > 1:
        sizes = np.bincount(lab.ravel())[1:]
        keep = np.r_[False, sizes >= min_blob_fraction * sizes.max()]
        box = keep[lab]
    mask = np.zeros(shape, dtype=bool)
    mask[r0:r1, c0:c1] = box
    return mask


def _origin(v_min: float, pixel_m: float, pad: int) -> float:
    return float(np.floor(v_min / pixel_m) * pixel_m - pad * pixel_m)


def shape_mask(s: np.ndarray, z: np.ndarray, pixel_m: float, close_px: int, min_blob_fraction: float = 0.05):
    """The shape mask of points (s along the plane, z up) — §V, §VI-A.

    Returns (mask (rows, cols) bool with row 0 at the bottom, s0, z0): pixel
    (r, c) covers s in [s0 + c p, s0 + (c+1) p) and z likewise.  Points are
    rasterised, closed with a disc of ``close_px`` (dilation then erosion by
    the disc, exact: silhouettes are not inflated), holes filled, and blobs
    smaller than ``min_blob_fraction`` of the largest removed.
    """
    pad = int(close_px) + 2
    s0, z0 = _origin(s.min(), pixel_m, pad), _origin(z.min(), pixel_m, pad)
    col = np.floor((s - s0) / pixel_m).astype(np.int64)
    row = np.floor((z - z0) / pixel_m).astype(np.int64)
    shape = (int(row.max()) + pad + 1, int(col.max()) + pad + 1)
    return _mask_pixels(row, col, shape, close_px, min_blob_fraction), s0, z0


def width_function(mask: np.ndarray):
    """(f, first, last): f(y) = x_max - x_min + 1 per row (0 on empty rows), §VI-A; first/last edge columns."""
    any_ = mask.any(axis=1)
    first = np.argmax(mask, axis=1)
    last = mask.shape[1] - 1 - np.argmax(mask[:, ::-1], axis=1)
    f = np.where(any_, last - first + 1, 0)
    return f, first, last


def first_change(f: np.ndarray, r0: int, jump_px: float) -> int:
    """The first row above ``r0`` where ∂f/∂y becomes non-zero (§VI-A): f exceeds the mean of f below by ``jump_px``.

    Two consecutive rows must exceed it (one noisy row does not end a trunk).
    Returns the row index (len(f) when the width never grows).
    """
    seg = f[r0:].astype(np.float64)
    if len(seg) < 3:
        return len(f)
    mean_below = np.cumsum(seg) / np.arange(1, len(seg) + 1)
    grow = seg[1:] - mean_below[:-1] > jump_px
    both = grow[:-1] & grow[1:]
    hit = np.flatnonzero(both)
    return int(r0 + 1 + hit[0]) if len(hit) else len(f)


def ransac_line(y: np.ndarray, x: np.ndarray, iterations: int, tolerance: float, rng: np.random.Generator):
    """RANSAC (Fischler & Bolles 1981) line x = a y + b: (a, b, inlier fraction) or None; least-squares refit on inliers."""
    n = len(y)
    if n < 2:
        return None
    pick = rng.integers(0, n, size=(int(iterations), 2))
    y0, y1 = y[pick[:, 0]], y[pick[:, 1]]
    ok = y1 != y0
    if not ok.any():
        return None
    a = np.where(ok, (x[pick[:, 1]] - x[pick[:, 0]]) / np.where(ok, y1 - y0, 1.0), 0.0)
    b = x[pick[:, 0]] - a * y0
    inl = np.abs(x[None, :] - (a[:, None] * y[None, :] + b[:, None])) <= tolerance
    count = np.where(ok, inl.sum(axis=1), -1)
    best = inl[int(np.argmax(count))]
    if best.sum() < 2 or np.ptp(y[best]) == 0:
        return None
    A = np.column_stack([y[best], np.ones(int(best.sum()))])
    (a1, b1), *_ = np.linalg.lstsq(A, x[best], rcond=None)
    frac = float((np.abs(x - (a1 * y + b1)) <= tolerance).mean())
    return float(a1), float(b1), frac


@dataclass
class PlaneFit:
    """§VI-A on one plane, metres (s along the plane from the reference, z above ground).

    ``single`` a single trunk was found; ``axis`` (a, b): trunk axis s = a z + b;
    ``z_bottom`` lowest mask z; ``top_approx_z`` / ``top_z`` approximate (Fig. 4a) and
    accurate (Fig. 4c) trunk top; ``width_m`` trunk width; ``crown`` (s_min, s_max, z_min, z_max);
    ``crown_centre`` s of the vertical crown axis; ``multiple`` the trunk area shows
    several separate stems (Fig. 5).
    """

    mask: np.ndarray
    s0: float
    z0: float
    single: bool
    axis: Optional[Tuple[float, float]]
    z_bottom: float
    top_approx_z: float
    top_z: float
    width_m: float
    crown: Tuple[float, float, float, float]
    crown_centre: float
    multiple: bool = False


def _run_width_at(mask: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Per row, width of the mask run containing column cols[r] (0 when that pixel is background) — Fig. 4c."""
    rows, w = mask.shape
    j = np.arange(w)
    left_bg = np.maximum.accumulate(np.where(~mask, j[None, :], -1), axis=1)
    right_bg = np.minimum.accumulate(np.where(~mask, j[None, :], w)[:, ::-1], axis=1)[:, ::-1]
    c = np.clip(cols, 0, w - 1)
    r = np.arange(rows)
    width = right_bg[r, c] - left_bg[r, c] - 1
    return np.where(mask[r, c], width, 0)


def fit_plane(mask: np.ndarray, s0: float, z0: float, method: "Billboard", rng: np.random.Generator) -> PlaneFit:
    """Shape fitting on one mask (§VI-A, Fig. 4): trunk area, RANSAC edge lines, axes and boxes."""
    p = method.pixel_m
    f, first, last = width_function(mask)
    rows = np.flatnonzero(f > 0)
    r0, rtop = int(rows[0]), int(rows[-1])
    jump = method.width_jump_m / p
    rt = min(first_change(f, r0, jump), rtop + 1)
    zc = z0 + (np.arange(mask.shape[0]) + 0.5) * p
    z_bottom = z0 + r0 * p
    top_approx = z0 + rt * p
    single, axis, width, top, multiple = False, None, 0.0, z_bottom, False
    trunk_rows = np.arange(r0, rt)
    trunk_rows = trunk_rows[f[trunk_rows] > 0]
    if (rt - r0) * p >= method.min_trunk_m and len(trunk_rows) >= 3:
        seg = mask[trunk_rows]
        runs = (seg[:, 1:] & ~seg[:, :-1]).sum(axis=1) + seg[:, 0]
        multiple = bool(np.median(runs) > 1)
        y = zc[trunk_rows]
        left = ransac_line(y, s0 + first[trunk_rows] * p, method.ransac_iterations, method.ransac_tolerance_m, rng)
        right = ransac_line(y, s0 + (last[trunk_rows] + 1) * p, method.ransac_iterations,
                            method.ransac_tolerance_m, rng)
        if (left is not None and right is not None and np.median(runs) == 1
                and min(left[2], right[2]) >= method.min_inlier_fraction):
            wl = (right[0] - left[0]) * y + (right[1] - left[1])
            if wl.min() > 0:
                a, b = (left[0] + right[0]) / 2.0, (left[1] + right[1]) / 2.0
                # Fig. 4c: f restricted to the edge points nearest the axis, then the trunk area again
                cols = np.floor((a * zc + b - s0) / p).astype(np.int64)
                f2 = _run_width_at(mask, cols)
                rt2 = min(first_change(f2, r0, jump), rtop + 1)
                top = z0 + max(rt2, rt) * p
                single, axis, width = True, (float(a), float(b)), float(np.median(wl))
    fit = PlaneFit(mask, s0, z0, single, axis, float(z_bottom), float(top_approx), float(top), width,
                   (0.0, 0.0, 0.0, 0.0), 0.0, multiple)
    return crown_box(fit, f, first, last, p, rt if single else r0)


def crown_box(fit: PlaneFit, f, first, last, p: float, start_row: int) -> PlaneFit:
    """Set the crown box (blue box of Fig. 4d: from ``start_row`` to the top) and the crown centre (Fig. 4b)."""
    rows = np.flatnonzero(f > 0)
    crown_rows = rows[rows >= start_row]
    if len(crown_rows) == 0:
        crown_rows = rows
    smin = fit.s0 + first[crown_rows].min() * p
    smax = fit.s0 + (last[crown_rows].max() + 1) * p
    fit.crown = (float(smin), float(smax), float(fit.z0 + crown_rows[0] * p), float(fit.z0 + (crown_rows[-1] + 1) * p))
    fit.crown_centre = float((smin + smax) / 2.0)
    return fit


def _directions(planes: int) -> np.ndarray:
    ang = np.pi * np.arange(planes) / planes
    return np.column_stack([np.cos(ang), np.sin(ang)])


@dataclass
class _Shape:
    fits: List[PlaneFit]
    u: np.ndarray
    has_trunk: bool
    trunk_p0: np.ndarray       # (2,) axis x, y at z = 0 (reference frame)
    trunk_dir: np.ndarray      # (2,) dx/dz, dy/dz
    trunk_z: Tuple[float, float]
    trunk_width: float
    crown_c: np.ndarray        # (2,)


def shape_fit(local: np.ndarray, method: "Billboard", rng: np.random.Generator):
    """§VI-A on ``planes`` vertical planes: masks, per-plane fits, 3D trunk axis and crown axis (least squares).

    ``local``: points relative to the reference (x, y about the tree, z above ground), metres.
    Returns (shape, closing radius in pixels).
    """
    shape, close_px, _ = shape_fit_along(np.asarray(local, dtype=np.float64), method, rng)
    return shape, close_px


def shape_fit_along(local: np.ndarray, method: "Billboard", rng: np.random.Generator):
    """:func:`shape_fit`, also returning the points' coordinate along each plane (reused by the textures)."""
    u = _directions(int(method.planes))
    close_px = _close_px(local, method)
    p = method.pixel_m
    pad = close_px + 2
    z = local[:, 2]
    z0 = _origin(z.min(), p, pad)                 # the same rows in every plane
    row = np.floor((z - z0) / p).astype(np.int64)
    rows = int(row.max()) + pad + 1
    fits, along = [], []
    for k in range(len(u)):
        s = local[:, 0] * u[k, 0] + local[:, 1] * u[k, 1]     # no BLAS call: its threads spin on a busy machine
        s0 = _origin(s.min(), p, pad)
        col = np.floor((s - s0) / p).astype(np.int64)
        mask = _mask_pixels(row, col, (rows, int(col.max()) + pad + 1), close_px, method.min_blob_fraction)
        fits.append(fit_plane(mask, s0, z0, method, rng))
        along.append(s)
    good = [k for k, fp in enumerate(fits) if fp.single]
    need = 1 if len(u) == 1 else max(2, (len(u) + 1) // 2)
    # several stems seen in any plane (Fig. 5) -> no single main trunk
    has_trunk = len(good) >= need and not any(fp.multiple for fp in fits)
    p0, d = np.zeros(2), np.zeros(2)
    tz, tw = (0.0, 0.0), 0.0
    if has_trunk:
        U = u[good]
        a = np.array([fits[k].axis[0] for k in good])
        b = np.array([fits[k].axis[1] for k in good])
        if len(good) == 1:
            d, p0 = U[0] * a[0], U[0] * b[0]
        else:
            d = np.linalg.lstsq(U, a, rcond=None)[0]
            p0 = np.linalg.lstsq(U, b, rcond=None)[0]
        tz = (float(min(fits[k].z_bottom for k in good)), float(np.median([fits[k].top_z for k in good])))
        tw = float(np.median([fits[k].width_m for k in good]))
        if tz[1] - tz[0] < method.min_trunk_m:
            has_trunk = False
    if not has_trunk:
        # no single main trunk: the whole silhouette is crown (§VI-A, Fig. 5), three quads only
        for fp in fits:
            fp.single = False
            f, first, last = width_function(fp.mask)
            crown_box(fp, f, first, last, method.pixel_m, 0)
    centres = np.array([fp.crown_centre for fp in fits])
    c = np.linalg.lstsq(u, centres, rcond=None)[0] if len(u) > 1 else u[0] * centres[0]
    return _Shape(fits, u, has_trunk, p0, d, tz, tw, c), close_px, along
