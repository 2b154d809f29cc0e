"""Lightweight billboard trees: Zhou et al. 2013, "Automatic reconstruction of lightweight trees" §IV–§VI.

A tree becomes six textured quads with alpha (§IV): three around the axis of
the main trunk (which may lean) and three around a vertical crown axis,
60 degrees apart.  Trees without a single main trunk get the three crown
quads only (§VI-A, Fig. 5).

    bb = billboard_tree(xyz, Billboard(), rgb=colours, ground_z=0.0, tree_id=7)
    bb.vertices, bb.faces, bb.uvs, bb.texture        # metres, origin at the stem base, z up

Steps (one pure function each):

* :func:`shape_mask` — §V/§VI-A: the tree's points projected onto a
  vertical plane and rasterised (``pixel_m`` is the paper's scale factor
  ``s = (z_max - z_min) / img_height``: sizes come out in metres), holes
  closed and filled, noisy specks removed ("morphology operations to fill
  holes and remove noisy points").  The paper projects onto one camera
  image; Sylva projects onto ``planes`` vertical planes (0, 60, 120 degrees),
  one per quad, so that each quad shows its own silhouette.
* :func:`width_function` — §VI-A: ``f(y) = x_max - x_min`` of the edge pixels
  of each row (for a hole-free mask the outermost edge pixels are the
  mask's extremes).  :func:`first_change` finds the first non-zero
  ``∂f/∂y`` going up from the stem base, i.e. the first row where the width
  grows by more than ``width_jump_m`` over the mean width below it on two
  consecutive rows (the discrete, noise-proof reading of "non-zero").
* :func:`ransac_line` — §VI-A (RANSAC, Fischler & Bolles): the left and the
  right trunk edge lines in the approximate trunk area (seeded).  Their
  middle line is the trunk's rotation axis; the width is then re-measured
  between the edge points nearest the axis (Fig. 4c) and the trunk top found
  again: the accurate trunk box.  The crown box starts at the approximate
  trunk height (Fig. 4d); the crown axis is vertical, at the centre of the
  crown's extent (Fig. 4b).  :func:`fit_plane` does all this on one mask;
  :func:`shape_fit` combines the planes into a 3D trunk axis and a crown
  axis by least squares (a single trunk needs edge lines in at least two
  planes: "a tree with a single main trunk is determined only if it has two
  edge lines of the main trunk").
* Textures (§VI-B): point colours (LAS RGB, or sampled from an orthophoto
  :func:`sample_orthophoto` or a pinhole camera image :func:`sample_camera`,
  §V's ``P = K M``) splatted into the mask; :func:`gmm_clean` clusters the
  crown's pixels with a Gaussian mixture in HSV (scikit-learn, EM) and keeps
  the cluster nearest the mean HSV; :func:`complete_blocks` fills removed
  and unknown pixels block by block (Algorithm 1, cost Eq. 2 with the
  Bhattacharyya histogram distance Eq. 3 and the boundary SSD).  Without
  any colour a procedural foliage / bark texture is drawn
  (:func:`sylva.core.textures.foliage_texture`).
* :func:`quads` — the six (or three) quads, one texture atlas per tree
  (one material per tree in glTF).

Sylva departures from the paper, stated where they happen: several planes
instead of one image; the colours come from the points (the paper's image
is replaced by per-point colours); hue enters the GMM as a point on the HSV
cone (``s cos h, s sin h, v``) so that red hues do not wrap; the GMM only
cleans the crown (bark is a legitimately different colour); the boundary
SSD uses RGB in [0, 1] so that Eq. 2's two terms have comparable scales.

Sylva, not in the paper (speed; at most 0.1 s a tree for 100k points, the
paper's own figure being 0.37–1.32 s): the point spacing that sets the
closing radius is bounded on a subset of the points first (:func:`_close_px`);
the closing uses exact discs without distance transforms (:func:`_disc_dilate`;
the disc stamped on each point when there are few); holes and specks are
found in the mask's bounding box; the plane's pixel rows are computed once
for every plane; the GMM's EM runs as scikit-learn's algorithm in a few
vectorised lines (:func:`_gmm_diag`); block completion works in the mask's
bounding box and updates its neighbour counts incrementally; no BLAS call
touches all the points (its threads spin on a busy machine).  Each gives the
same masks, axes, boxes and opaque texels as the straightforward version.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from ..errors import EmptyInputError, InputError
from ..textures import bark_texture

__all__ = ["Billboard", "BillboardMesh", "PlaneFit", "Orthophoto", "PinholeCamera", "billboard_tree",
           "shape_mask", "width_function", "first_change", "ransac_line", "fit_plane", "shape_fit",
           "point_rgb", "read_orthophoto", "sample_orthophoto", "read_camera", "sample_camera", "gmm_clean",
           "complete_blocks", "bhattacharyya", "opaque_points"]


@dataclass(frozen=True)
class Billboard:
    """Parameters of the billboard method (Zhou et al. 2013 §VI); lengths in metres.

    The paper states no numeric value for these (it works in camera pixels);
    the defaults were chosen for airborne and terrestrial scans of forest trees.

    ``planes`` quads per part (§IV: three for the trunk, three for the crown,
    evenly spread over 180 degrees); ``pixel_m`` shape-mask pixel (the scale
    factor s of §VI-A); ``close_m`` smallest radius of the morphological
    closing that joins the points into a silhouette (the median point spacing
    is used when larger; at most ``max_close_m``); ``min_blob_fraction``
    specks smaller than this fraction of the largest blob are noise;
    ``width_jump_m`` smallest growth of f(y) counted as ∂f/∂y ≠ 0;
    ``min_trunk_m`` a shorter trunk area is no trunk; ``ransac_iterations``,
    ``ransac_tolerance_m``, ``min_inlier_fraction`` the RANSAC edge-line fit;
    ``texture_px`` texels along the tree's longest side (64–128 keep a tree
    near the paper's 40 kB); ``gmm_components`` Gaussian mixture clusters in
    HSV (0: no cleaning); ``block_px`` initial block size s of Algorithm 1;
    ``hist_bins`` histogram bins per channel in Eq. 3; ``max_candidates``
    candidate blocks T_j kept (evenly spaced); ``max_bad_fraction`` a block
    with more wrong pixels than this share is replaced (L = 0); ``palette_colours`` PNG
    palette size; ``seed`` the random generator's seed (RANSAC, GMM).
    """

    planes: int = 3
    pixel_m: float = 0.05
    close_m: float = 0.15
    max_close_m: float = 1.0
    min_blob_fraction: float = 0.05
    width_jump_m: float = 0.15
    min_trunk_m: float = 0.5
    ransac_iterations: int = 100
    ransac_tolerance_m: float = 0.05
    min_inlier_fraction: float = 0.5
    texture_px: int = 128
    gmm_components: int = 2
    block_px: int = 8
    hist_bins: int = 8
    max_candidates: int = 256
    max_bad_fraction: float = 0.5
    palette_colours: int = 64
    seed: int = 0

    def __post_init__(self):
        if int(self.planes) < 1:
            raise InputError(f"billboards: planes must be at least 1, got {self.planes}")
        for name in ("pixel_m", "close_m", "ransac_tolerance_m"):
            if not getattr(self, name) > 0:
                raise InputError(f"billboards: {name} must be positive, got {getattr(self, name)}")
        if int(self.texture_px) < 8:
            raise InputError(f"billboards: texture_px must be at least 8, got {self.texture_px}")
        if int(self.block_px) < 1 or int(self.hist_bins) < 2:
            raise InputError("billboards: block_px must be >= 1 and hist_bins >= 2")

    def build(self, xyz, **kwargs) -> "BillboardMesh":
        """:func:`billboard_tree` with these parameters."""
        return billboard_tree(xyz, self, **kwargs)


@dataclass(eq=False)
class BillboardMesh:
    """Textured quads of one tree: metres, origin at the stem base, x east, y north, z up.

    ``vertices`` (4q, 3) float64; ``faces`` (2q, 3) int64; ``uvs`` (4q, 2)
    OpenGL convention (v = 0 at the bottom row of ``texture``, as
    :mod:`sylva.core.leaves`); ``texture`` (h, w, 4) uint8 RGBA atlas, alpha
    0 or 255; ``quad_kind`` per quad "crown" or "trunk"; ``has_trunk``;
    ``trunk_axis`` (2, 3) bottom and top of the trunk axis (or None);
    ``trunk_width_m``, ``trunk_height_m`` (0 without trunk); ``crown_axis``
    (2,) x, y of the vertical crown axis; ``crown_boxes`` (planes, 4) s_min,
    s_max (along the quad, from the crown axis), z_min, z_max;
    ``texture_source`` "points", "image" or "procedural"; ``origin`` (3,) the stem
    base in the input points' frame (vertices are relative to it); ``timings`` seconds
    per step (not part of the result's identity).
    """

    vertices: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray
    texture: np.ndarray
    quad_kind: Tuple[str, ...]
    has_trunk: bool
    trunk_axis: Optional[np.ndarray]
    trunk_width_m: float
    trunk_height_m: float
    crown_axis: np.ndarray
    crown_boxes: np.ndarray
    texture_source: str
    origin: Optional[np.ndarray] = None
    palette_colours: int = 64
    timings: Dict[str, float] = field(default_factory=dict)

    def png(self) -> bytes:
        """The atlas as a palette PNG with a transparent index (:func:`~sylva.core.textures.png_bytes_indexed`)."""
        from ..textures import png_bytes_indexed

        return png_bytes_indexed(self.texture, self.palette_colours)

    def summary(self) -> Dict[str, Any]:
        """Per-tree attributes: has_trunk, trunk height/width, crown width/height (m), texture source."""
        b = self.crown_boxes
        return {"bb_has_trunk": bool(self.has_trunk), "bb_trunk_height_m": float(self.trunk_height_m),
                "bb_trunk_width_m": float(self.trunk_width_m),
                "bb_crown_width_m": float(np.median(b[:, 1] - b[:, 0])) if len(b) else 0.0,
                "bb_crown_base_m": float(np.median(b[:, 2])) if len(b) else 0.0,
                "bb_texture": self.texture_source}


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


def fit_plane(mask: np.ndarray, s0: float, z0: float, method: Billboard, rng: np.random.Generator) -> PlaneFit:
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


def shape_fit(local: np.ndarray, method: Billboard, rng: np.random.Generator):
    """§VI-A on ``planes`` vertical planes: masks, per-plane fits, 3D trunk axis and crown axis (least squares).

    ``local``: points relative to the reference (x, y about the tree, z above ground), metres.
    Returns (shape, closing radius in pixels).
    """
    shape, close_px, _ = _shape_fit(np.asarray(local, dtype=np.float64), method, rng)
    return shape, close_px


def _shape_fit(local: np.ndarray, method: Billboard, rng: np.random.Generator):
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


# --------------------------------------------------------------------------- colours (§V)

def point_rgb(rgb) -> Optional[np.ndarray]:
    """Point colours as float (n, 3) in [0, 1] (NaN rows = unknown): uint8, LAS 16-bit or floats in [0, 1]."""
    if rgb is None:
        return None
    a = np.asarray(rgb)
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputError(f"billboards: colours must be (n, 3), got shape {a.shape}")
    if a.dtype.kind == "f":
        out = a.astype(np.float64)
        finite = np.isfinite(out)
        if finite.any() and np.nanmax(out) > 1.0:
            out = out / (65535.0 if np.nanmax(out) > 255.0 else 255.0)
        return out
    top = a.max() if a.size else 0
    return a.astype(np.float64) / (65535.0 if (a.dtype.itemsize > 1 and top > 255) else 255.0)


@dataclass(eq=False)
class Orthophoto:
    """An RGB north-up image: ``rgb`` (rows, cols, 3) uint8, row 0 at the north edge; ``x0``/``y0``
    west/north edges and ``pixel`` size in CRS units; ``valid`` (rows, cols) bool; ``crs``."""

    rgb: np.ndarray
    x0: float
    y0: float
    pixel: float
    crs: Any = None
    valid: Optional[np.ndarray] = None

    @classmethod
    def from_raster(cls, raster) -> "Orthophoto":
        """A grey image from a single-band :class:`sylva.core.raster.Raster` (stretched to 0..255, NaN invalid)."""
        data = np.asarray(raster.data, dtype=np.float64)
        ok = np.isfinite(data)
        lo, hi = (np.nanmin(data), np.nanmax(data)) if ok.any() else (0.0, 1.0)
        scale = 255.0 / (hi - lo) if hi > lo else 1.0
        g = np.clip(np.rint((np.where(ok, data, lo) - lo) * scale), 0, 255).astype(np.uint8)
        return cls(np.repeat(g[..., None], 3, axis=2), raster.x0, raster.y0, raster.pixel, raster.crs, ok)


def read_orthophoto(path) -> Orthophoto:
    """Read a north-up GeoTIFF orthophoto: RGB(A) 8/16-bit, or one band (grey) via :func:`read_geotiff`."""
    import tifffile

    from ..raster import (GEOGRAPHIC_TYPE, PROJECTED_CS_TYPE, TAG_GEOKEY_DIRECTORY, TAG_MODEL_PIXEL_SCALE,
                          TAG_MODEL_TIEPOINT, USER_DEFINED, read_geotiff)

    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: image file not found")
    try:
        with tifffile.TiffFile(str(path)) as tif:
            page = tif.pages[0]
            data = page.asarray()
            tags = page.tags
            if TAG_MODEL_PIXEL_SCALE not in tags or TAG_MODEL_TIEPOINT not in tags:
                raise InputError(f"{path}: not a GeoTIFF (no pixel scale / tiepoint tags): the image must be "
                                 f"georeferenced, north-up")
            scale = tags[TAG_MODEL_PIXEL_SCALE].value
            tie = tags[TAG_MODEL_TIEPOINT].value
            keys = tags[TAG_GEOKEY_DIRECTORY].value if TAG_GEOKEY_DIRECTORY in tags else ()
    except InputError:
        raise
    except Exception as exc:  # tifffile raises its own errors for damaged files
        raise InputError(f"{path}: cannot read the image: {exc}")
    if data.ndim == 2:
        return Orthophoto.from_raster(read_geotiff(path))
    if data.ndim == 3 and data.shape[0] in (3, 4) and data.shape[2] not in (3, 4):
        data = np.moveaxis(data, 0, -1)
    if data.ndim != 3 or data.shape[2] < 3:
        raise InputError(f"{path}: expected an RGB image (3 or 4 bands), got shape {data.shape}")
    rgb = data[..., :3]
    if rgb.dtype != np.uint8:
        top = float(rgb.max()) if rgb.size else 1.0
        rgb = np.clip(np.rint(rgb.astype(np.float64) * (255.0 / (65535.0 if top > 255 else 255.0))), 0, 255)
    valid = data[..., 3] > 0 if data.shape[2] >= 4 else None
    pixel = float(scale[0])
    crs = None
    for i in range(keys[3] if len(keys) >= 4 else 0):
        key, loc, _count, value = keys[4 + 4 * i: 8 + 4 * i]
        if key in (PROJECTED_CS_TYPE, GEOGRAPHIC_TYPE) and loc == 0 and value != USER_DEFINED:
            import pyproj

            crs = pyproj.CRS.from_epsg(int(value))
            break
    return Orthophoto(np.asarray(rgb, dtype=np.uint8), tie[3] - tie[0] * pixel, tie[4] + tie[1] * pixel, pixel,
                      crs, valid)


def sample_orthophoto(ortho: Orthophoto, x, y) -> np.ndarray:
    """Colour (n, 3) float in [0, 1] of the image pixel above each point (x, y in the image's CRS); NaN outside."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    col = np.floor((x - ortho.x0) / ortho.pixel).astype(np.int64)
    row = np.floor((ortho.y0 - y) / ortho.pixel).astype(np.int64)
    rows, cols = ortho.rgb.shape[:2]
    ok = (row >= 0) & (row < rows) & (col >= 0) & (col < cols)
    if ortho.valid is not None:
        ok[ok] = ortho.valid[row[ok], col[ok]]
    out = np.full((len(x), 3), np.nan)
    out[ok] = ortho.rgb[row[ok], col[ok]] / 255.0
    return out


@dataclass(frozen=True)
class PinholeCamera:
    """A street-level image with its camera (§V): ``K`` (3, 3) intrinsics, ``R`` (3, 3) and ``t`` (3,)
    world -> camera (X_c = R X + t, i.e. M = [R | t], the paper's M_lc M_wl composed), ``image``
    (h, w, 3) uint8; the camera looks along +z of its frame."""

    K: Any
    R: Any
    t: Any
    image: Any


def read_camera(camera_path, image_path) -> PinholeCamera:
    """A street-level photo (any format Pillow or tifffile reads) and its camera from a JSON file.

    The JSON holds ``K`` (3 x 3 intrinsics, pixels), ``R`` (3 x 3) and ``t`` (3) taking
    world coordinates — the point cloud's CRS coordinates — to the camera frame
    (X_c = R X + t, +z forward, image rows down), as in Zhou et al. §V.
    """
    import json

    camera_path, image_path = Path(camera_path), Path(image_path)
    try:
        doc = json.loads(camera_path.read_text("utf-8"))
        K, R, t = (np.asarray(doc[k], dtype=np.float64) for k in ("K", "R", "t"))
    except FileNotFoundError:
        raise InputError(f"{camera_path}: camera file not found") from None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"{camera_path}: not a camera file (JSON with K 3x3, R 3x3 and t 3): {exc}") from None
    if K.shape != (3, 3) or R.shape != (3, 3) or t.shape != (3,) or not np.all(np.isfinite(np.r_[K.ravel(), R.ravel(), t])):
        raise InputError(f"{camera_path}: K and R must be 3 x 3 and t 3 finite numbers, got shapes "
                         f"{K.shape}, {R.shape}, {t.shape}")
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6):
        raise InputError(f"{camera_path}: R is not a rotation matrix (R Rᵀ ≠ I)")
    if not image_path.exists():
        raise InputError(f"{image_path}: image file not found")
    try:
        if image_path.suffix.lower() in (".tif", ".tiff"):
            import tifffile

            image = tifffile.imread(str(image_path))
        else:
            from PIL import Image

            with Image.open(image_path) as im:
                image = np.asarray(im.convert("RGB"))
    except Exception as exc:  # decoders raise their own errors for damaged files
        raise InputError(f"{image_path}: cannot read the image: {exc}") from None
    image = np.asarray(image)
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    if image.ndim != 3 or image.shape[2] < 3:
        raise InputError(f"{image_path}: expected an RGB or grey image, got shape {image.shape}")
    if image.dtype != np.uint8:
        top = 65535.0 if image.max() > 255 else 255.0
        image = np.clip(np.rint(image.astype(np.float64) * (255.0 / top)), 0, 255).astype(np.uint8)
    return PinholeCamera(K, R, t, image[..., :3])


def sample_camera(camera: PinholeCamera, xyz) -> np.ndarray:
    """Colour (n, 3) in [0, 1] of each point's projection P = K [R | t] X (§V); NaN behind or outside the image.

    Occlusion is not tested: the paper's GMM cleaning and block completion
    (§VI-B) are what remove wrong colours.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    cam = xyz @ np.asarray(camera.R, dtype=np.float64).T + np.asarray(camera.t, dtype=np.float64)
    img = np.asarray(camera.image)
    h, w = img.shape[:2]
    out = np.full((len(xyz), 3), np.nan)
    front = cam[:, 2] > 1e-6
    pix = cam[front] @ np.asarray(camera.K, dtype=np.float64).T
    u = np.floor(pix[:, 0] / pix[:, 2]).astype(np.int64)
    v = np.floor(pix[:, 1] / pix[:, 2]).astype(np.int64)
    ok = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    idx = np.flatnonzero(front)[ok]
    out[idx] = img[v[ok], u[ok], :3] / 255.0
    return out


# --------------------------------------------------------------------------- §VI-B textures

def _hsv_cone(rgb: np.ndarray) -> np.ndarray:
    """RGB [0, 1] (n, 3) -> HSV as points on the cone (s cos 2πh, s sin 2πh, v), (n, 3)."""
    return _hsv_cone_rows(rgb).T


def _hsv_cone_rows(rgb: np.ndarray) -> np.ndarray:
    """:func:`_hsv_cone` as (3, n) rows (contiguous: fast elementwise work)."""
    r, g, b = np.array(rgb, dtype=np.float64).T.copy()
    mx = np.maximum(np.maximum(r, g), b)
    d = mx - np.minimum(np.minimum(r, g), b)
    is_r, is_g = mx == r, mx == g
    safe = np.where(d > 0, d, 1.0)
    h = np.where(is_r, g - b, np.where(is_g, b - r, r - g)) / safe
    h = np.where(is_r, h % 6.0, h + np.where(is_g, 2.0, 4.0))
    h = np.where(d > 0, h / 6.0, 0.0)
    s = np.where(mx > 0, d / np.where(mx > 0, mx, 1.0), 0.0)
    angle = 2 * np.pi * h
    out = np.empty((3, len(r)))
    out[0], out[1], out[2] = s * np.cos(angle), s * np.sin(angle), mx
    return out


def _gmm_diag(xt: np.ndarray, components: int, seed: int, max_iter: int = 50, tol: float = 1e-3,
              reg_covar: float = 1e-4):
    """EM for a Gaussian mixture with diagonal covariances on the samples ``xt`` (d, n): (weights, means, variances).

    The EM of scikit-learn's ``GaussianMixture(covariance_type="diag", init_params="k-means++")``
    step for step (its k-means++ seeds, E-step then M-step, stop when the mean log-likelihood
    changes by less than ``tol``), without its per-iteration overhead.
    """
    from sklearn.cluster import kmeans_plusplus

    n = xt.shape[1]
    k = int(components)
    tiny = 10 * np.finfo(np.float64).eps
    x2 = xt * xt
    _, seeds = kmeans_plusplus(np.ascontiguousarray(xt.T), k, random_state=int(seed) % (2**31))
    means = xt[:, seeds].T                     # one-hot responsibilities on the seeds
    var = x2[:, seeds].T - means * means + reg_covar
    weights = np.full(k, (1.0 + tiny) / n)
    bound = -np.inf
    for _ in range(int(max_iter)):
        log_p = _gmm_log_prob(xt, weights, means, var)                         # E-step, (k, n)
        top = log_p.max(axis=0)
        log_norm = top + np.log(np.exp(log_p - top).sum(axis=0))
        resp = np.exp(log_p - log_norm)
        nk = resp.sum(axis=1) + tiny                                           # M-step
        weights = nk / nk.sum()
        means = np.einsum("kn,dn->kd", resp, xt) / nk[:, None]
        var = np.einsum("kn,dn->kd", resp, x2) / nk[:, None] - means * means + reg_covar
        new_bound = float(log_norm.mean())
        if abs(new_bound - bound) < tol:
            break
        bound = new_bound
    return weights, means, var


def _gmm_log_prob(xt: np.ndarray, weights: np.ndarray, means: np.ndarray, var: np.ndarray) -> np.ndarray:
    """(k, n) log(w_k N(x | mean_k, diag var_k)) of the samples ``xt`` (d, n)."""
    const = np.log(weights) - 0.5 * (len(xt) * np.log(2 * np.pi) + np.log(var).sum(axis=1))
    inv = 1.0 / var
    diff = xt[None, :, :] - means[:, :, None]          # (k, d, n): elementwise, not BLAS (its threads spin)
    diff *= diff
    diff *= inv[:, :, None]
    return const[:, None] - 0.5 * diff.sum(axis=1)


def gmm_clean(rgb: np.ndarray, components: int, seed: int, max_samples: int = 1500) -> np.ndarray:
    """§VI-B: True for colours of the right cluster (GMM + EM in HSV; the cluster nearest the mean HSV).

    The mixture is fitted on at most ``max_samples`` colours (a seeded random sample) and predicted on all.
    Sylva, not in the paper (speed): EM is :func:`_gmm_diag`, scikit-learn's ``GaussianMixture``
    algorithm in a few vectorised lines (the class spends ~0.6 ms an iteration in overhead).
    """
    n = len(rgb)
    if components < 2 or n < 10 * components:
        return np.ones(n, dtype=bool)
    feats = _hsv_cone_rows(rgb)                                                   # (3, n)
    rng = np.random.default_rng(seed)
    train = feats if n <= max_samples else feats[:, np.sort(rng.choice(n, max_samples, replace=False))]
    weights, means, var = _gmm_diag(train, int(components), seed)
    labels = np.argmax(_gmm_log_prob(feats, weights, means, var), axis=0)
    right = int(np.argmin(np.linalg.norm(means - feats.mean(axis=1), axis=1)))
    return labels == right


def bhattacharyya(h1: np.ndarray, h2: np.ndarray) -> np.ndarray:
    """Eq. 3: d(H1, H2) = sqrt(1 - Σ sqrt(H1 H2) / sqrt(mean(H1) mean(H2) N²)), broadcast over leading axes."""
    n = h1.shape[-1]
    norm = np.sqrt(h1.mean(axis=-1) * h2.mean(axis=-1) * n * n)
    bc = np.sqrt(h1 * h2).sum(axis=-1) / np.where(norm > 0, norm, 1.0)
    return np.sqrt(np.clip(1.0 - bc, 0.0, 1.0))


def _hist(pixels: np.ndarray, bins: int) -> np.ndarray:
    """Per-channel histograms of (..., m, 3) colours in [0, 1], concatenated: (..., 3 bins)."""
    q = np.clip((pixels * bins).astype(np.int64), 0, bins - 1) + np.arange(3) * bins
    lead = q.shape[:-2]
    flat = q.reshape(-1, q.shape[-2] * 3)
    k = flat.shape[0]
    idx = (flat + (np.arange(k) * (3 * bins))[:, None]).ravel()
    out = np.bincount(idx, minlength=k * 3 * bins).astype(np.float64)
    return out.reshape(*lead, 3 * bins)


def complete_blocks(image: np.ndarray, mask: np.ndarray, good: np.ndarray, method: Billboard,
                    rng: Optional[np.random.Generator] = None) -> Tuple[np.ndarray, int]:
    """Algorithm 1 (§VI-B): fill the mask pixels that are not ``good`` block by block.

    Tiling blocks of size s get L = 2 (no mask pixel), 0 (to replace: more
    than ``max_bad_fraction`` of its mask pixels are wrong or unknown) or 1;
    the few wrong pixels of an L = 1 block take the colour of the nearest
    correct pixel (Sylva's reading of "the texture is correct": point colours
    cleaned by the GMM leave scattered holes, not only whole wrong regions).
    Candidate blocks T_j are s x s windows (stride s/2) inside the mask with
    at most half that share of wrong pixels; s starts at ``block_px`` and
    halves until there is one.  While a block has L = 0, the one with most
    L = 1 4-neighbours is replaced by the candidate minimising Eq. 2:
    Σ_neighbours Bhattacharyya (Eq. 3) of the RGB histograms + the SSD of
    RGB (0..1) across the shared boundary (with no L = 1 neighbour: the
    candidate nearest the mean histogram).  Returns (completed image, s);
    s = 0 when no pixel is correct (the caller draws a procedural texture).

    Sylva, not in the paper (speed, same result inside the mask): the work is done in the mask's bounding
    box plus one pixel, its corner on the block grid; pixels outside it keep their colour.
    """
    h, w, _ = image.shape
    good = good & mask
    need = mask & ~good
    if not need.any():
        return image, int(method.block_px)
    if not good.any():
        return image, 0
    align, s = 1, int(method.block_px)
    while s >= 1:                                  # every block size and candidate stride tried below
        align = math.lcm(align, s, max(1, s // 2))
        s //= 2
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    r0, c0 = max(0, int(rows[0]) - 1) // align * align, max(0, int(cols[0]) - 1) // align * align
    r1 = min(h, r0 + -(-(int(rows[-1]) + 2 - r0) // align) * align)
    c1 = min(w, c0 + -(-(int(cols[-1]) + 2 - c0) // align) * align)
    if (r0, c0, r1, c1) == (0, 0, h, w):
        return _complete_window(image, mask, good, need, method)
    sub, s = _complete_window(image[r0:r1, c0:c1], mask[r0:r1, c0:c1], good[r0:r1, c0:c1], need[r0:r1, c0:c1],
                              method)
    out = image.copy()
    out[r0:r1, c0:c1] = sub
    return out, s


def _complete_window(image: np.ndarray, mask: np.ndarray, good: np.ndarray, need: np.ndarray, method: Billboard):
    """:func:`complete_blocks` on a window holding the whole mask."""
    from scipy import ndimage

    h, w, _ = image.shape
    ri, ci = ndimage.distance_transform_edt(~good, return_distances=False, return_indices=True)
    img = np.take(image.reshape(h * w, 3), (ri * w + ci).ravel(), axis=0).reshape(h, w, 3)  # wrong: nearest correct
    limit = float(method.max_bad_fraction)
    s = int(method.block_px)
    cand = None
    while s >= 1:
        if h >= s and w >= s:
            win_m = _window_sum(mask, s) == s * s
            win_bad = _window_sum(need, s) / float(s * s)
            step = max(1, s // 2)
            ok = (win_m & (win_bad <= limit / 2.0))[::step, ::step]
            ii, jj = np.nonzero(ok)
            if len(ii):
                ii, jj = ii * step, jj * step
                if len(ii) > method.max_candidates:
                    pick = np.linspace(0, len(ii) - 1, method.max_candidates).round().astype(int)
                    ii, jj = ii[pick], jj[pick]
                cand = (ii, jj)
                break
        s //= 2
    if cand is None:
        return img, 0
    H, W = -(-h // s), -(-w // s)
    padded = np.zeros((H * s, W * s, 3))
    padded[:h, :w] = img
    pm = np.zeros((H * s, W * s), bool)
    pm[:h, :w] = mask
    pn = np.zeros((H * s, W * s), bool)
    pn[:h, :w] = need
    n_mask = pm.reshape(H, s, W, s).sum(axis=(1, 3))
    n_bad = pn.reshape(H, s, W, s).sum(axis=(1, 3))
    L = np.where(n_mask == 0, 2, np.where(n_bad > limit * np.maximum(n_mask, 1), 0, 1))
    if not (L == 0).any():
        return img, s
    ci_, cj_ = cand
    windows = np.lib.stride_tricks.sliding_window_view(img, (s, s), axis=(0, 1))  # (h-s+1, w-s+1, 3, s, s)
    tiles = windows[ci_, cj_].transpose(0, 2, 3, 1)                                 # (n, s, s, 3)
    bins = int(method.hist_bins)
    # Eq. 3 on histograms normalised to sum 1: the normaliser is 1 and d = sqrt(1 - Σ sqrt(h1 h2))
    t_hist = _hist(tiles.reshape(len(ci_), s * s, 3), bins)
    t_root = np.sqrt(t_hist / t_hist.sum(axis=1, keepdims=True))
    blk = padded.reshape(H, s, W, s, 3).transpose(0, 2, 1, 3, 4).copy()          # (H, W, s, s, 3)
    # histograms of the L = 1 blocks next to an L = 0 block (the only ones Eq. 2 reads; replaced blocks take
    # their candidate's)
    zero = L == 0
    near = np.zeros_like(zero)
    near[1:] |= zero[:-1]
    near[:-1] |= zero[1:]
    near[:, 1:] |= zero[:, :-1]
    near[:, :-1] |= zero[:, 1:]
    bi_, bj_ = np.nonzero(near & (L == 1))
    b_root = np.zeros((H, W, 3 * bins))
    if len(bi_):
        b_hist = _hist(blk[bi_, bj_].reshape(len(bi_), s * s, 3), bins)
        b_root[bi_, bj_] = np.sqrt(b_hist / np.maximum(b_hist.sum(axis=1, keepdims=True), 1e-12))
    g_root = np.sqrt(t_hist.sum(axis=0) / t_hist.sum())
    n_cand = len(ci_)
    # Eq. 2's boundary SSD with each side's L = 1 neighbour: Σ (t - b)² = Σ t² - 2 Σ t b + Σ b², the candidates'
    # sides side by side so that one product serves all neighbours
    sides = ((-1, 0, tiles[:, 0], lambda b: b[-1]), (1, 0, tiles[:, -1], lambda b: b[0]),
             (0, -1, tiles[:, :, 0], lambda b: b[:, -1]), (0, 1, tiles[:, :, -1], lambda b: b[:, 0]))
    t_side = np.concatenate([t.reshape(n_cand, 3 * s) for _, _, t, _ in sides], axis=1)     # (n, 4 * 3s)
    t_side_sq = (t_side * t_side).reshape(n_cand, 4, 3 * s).sum(axis=2)                      # (n, 4)
    ones = (L == 1).astype(np.int64)
    deg = np.zeros_like(ones)                 # L = 1 4-neighbours of every L = 0 block (-1: not to replace)
    deg[1:] += ones[:-1]
    deg[:-1] += ones[1:]
    deg[:, 1:] += ones[:, :-1]
    deg[:, :-1] += ones[:, 1:]
    deg = np.where(L == 0, deg, -1)
    flat_deg = deg.ravel()
    g_cost = None
    todo = int((L == 0).sum())
    for _ in range(todo):
        bi, bj = divmod(int(np.argmax(flat_deg)), W)
        present, vec, b_sq = [], np.zeros(4 * 3 * s), 0.0
        for e, (di, dj, _, b_edge) in enumerate(sides):
            ni, nj = bi + di, bj + dj
            if 0 <= ni < H and 0 <= nj < W and L[ni, nj] == 1:
                b = b_edge(blk[ni, nj]).ravel()
                vec[e * 3 * s:(e + 1) * 3 * s] = b
                b_sq += float(b @ b)
                present.append((e, ni, nj))
        if present:
            e_, ni_, nj_ = (list(v) for v in zip(*present))
            cost = np.sqrt(np.clip(1.0 - t_root @ b_root[ni_, nj_].T, 0.0, 1.0)).sum(axis=1)    # Eq. 3
            cost += t_side_sq[:, e_].sum(axis=1) - 2.0 * (t_side @ vec) + b_sq
        else:                                  # no L = 1 neighbour: nearest the mean histogram
            if g_cost is None:
                g_cost = np.sqrt(np.clip(1.0 - t_root @ g_root, 0.0, 1.0))
            cost = g_cost
        best = int(np.argmin(cost))
        blk[bi, bj] = tiles[best]
        b_root[bi, bj] = t_root[best]
        L[bi, bj] = 1
        deg[bi, bj] = -1
        for di, dj in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            ni, nj = bi + di, bj + dj
            if 0 <= ni < H and 0 <= nj < W and L[ni, nj] == 0:
                deg[ni, nj] += 1
    out = blk.transpose(0, 2, 1, 3, 4).reshape(H * s, W * s, 3)[:h, :w]
    return _paste(img, out, need, n_bad, n_mask, limit, s, h, w), s


def _window_sum(a: np.ndarray, s: int) -> np.ndarray:
    """Sums of every s x s window of a 2D array (summed-area table), shape (h - s + 1, w - s + 1)."""
    c = np.zeros((a.shape[0] + 1, a.shape[1] + 1))
    c[1:, 1:] = np.cumsum(np.cumsum(a, axis=0, dtype=np.float64), axis=1)
    return c[s:, s:] - c[:-s, s:] - c[s:, :-s] + c[:-s, :-s]


def _paste(img, out, need, n_bad, n_mask, limit, s, h, w):
    """Copy the replaced blocks (those that had L = 0) of ``out`` into ``img`` inside the mask."""
    was0 = n_bad > limit * np.maximum(n_mask, 1)
    sel = np.repeat(np.repeat(was0, s, axis=0), s, axis=1)[:h, :w]
    res = img.copy()
    res[sel] = out[sel]
    return res


def _splat_pixels(row: np.ndarray, col: np.ndarray, rgb: np.ndarray, shape, radius_px: float):
    """Mean point colour per pixel from the points' pixel indices (points outside the image are ignored), spread to
    pixels within ``radius_px`` of a coloured one: (image, known)."""
    from scipy import ndimage

    h, w = shape
    if len(row) and (row.min() < 0 or row.max() >= h or col.min() < 0 or col.max() >= w):
        ok = (row >= 0) & (row < h) & (col >= 0) & (col < w)
        row, col, rgb = row[ok], col[ok], rgb[ok]
    flat = row * w + col
    n = np.bincount(flat, minlength=h * w)
    img = np.zeros((h * w, 3))
    for c in range(3):
        img[:, c] = np.bincount(flat, weights=rgb[:, c], minlength=h * w)
    has = n > 0
    img[has] /= n[has, None]
    img = img.reshape(h, w, 3)
    has = has.reshape(h, w)
    if not has.any():
        return img, has
    dist, (ri, cj) = ndimage.distance_transform_edt(~has, return_indices=True)
    img = img[ri, cj]
    return img, dist <= radius_px


def _sample(image: np.ndarray, s0: float, z0: float, p: float, s: np.ndarray, z: np.ndarray):
    """Nearest-pixel lookup of image (rows bottom-up) at plane coordinates; out-of-range pixels -> zeros/False.

    ``s`` and ``z`` broadcast against each other (a row of columns and a column of rows make a grid).
    """
    h, w = image.shape[:2]
    col = np.floor((s - s0) / p).astype(np.int64)
    row = np.floor((z - z0) / p).astype(np.int64)
    ok = ((row >= 0) & (row < h)) & ((col >= 0) & (col < w))
    out = image[np.clip(row, 0, h - 1), np.clip(col, 0, w - 1)]
    if not ok.all():
        out[~np.broadcast_to(ok, out.shape[:ok.ndim])] = 0
    return out


# --------------------------------------------------------------------------- the tree

def _frame(fit: PlaneFit, fine_p: float, p: float):
    """Texture-resolution grid (s0, z0, shape) covering a plane's fine mask."""
    h = max(1, int(np.ceil(fit.mask.shape[0] * fine_p / p)))
    w = max(1, int(np.ceil(fit.mask.shape[1] * fine_p / p)))
    return fit.s0, fit.z0, (h, w)


def billboard_tree(xyz, method: Billboard = Billboard(), rgb=None, base=None, ground_z: Optional[float] = None,
                   tree_id: int = 0, texture_source: Optional[str] = None,
                   stem_diameter_m: Optional[float] = None) -> BillboardMesh:
    """The billboard model of one tree (Zhou et al. 2013 §IV, §VI).

    ``xyz`` (n, 3) the tree's points in a metric frame, z up (e.g. the tile's
    local frame); ``rgb`` optional (n, 3) colours (uint8, LAS 16-bit or floats
    in [0, 1]; NaN rows unknown — e.g. from :func:`sample_orthophoto`);
    ``ground_z`` the ground under the tree (default the lowest point);
    ``base`` (3,) the origin of the returned vertices (default: the trunk
    axis, or the crown axis, at ``ground_z``); ``tree_id`` names the tree in
    messages and seeds its random generator with ``method.seed``;
    ``texture_source`` labels the colours ("points" / "image").

    ``stem_diameter_m`` (Sylva, not in the paper): airborne scans rarely see a
    stem, so a crown with no trunk found would float above the ground.  When
    given, and no plane saw several stems rising from the ground (Zhou's
    multi-stem case keeps its crown quads only), a stem of this diameter is drawn from the ground into
    the lowest tenth of the crown, on the crown axis, with a bark texture
    (``quad_kind`` "stem").
    """
    t_start = time.perf_counter()
    timings: Dict[str, float] = {}
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or len(xyz) == 0:
        raise EmptyInputError(f"tree {tree_id}: no points to build a billboard from")
    colours = point_rgb(rgb)
    if colours is not None and len(colours) != len(xyz):
        raise InputError(f"tree {tree_id}: {len(colours)} colours for {len(xyz)} points")
    if not np.isfinite(xyz).all():
        finite = np.all(np.isfinite(xyz), axis=1)
        xyz = xyz[finite]
        if colours is not None:
            colours = colours[finite]
    if len(xyz) == 0:
        raise EmptyInputError(f"tree {tree_id}: no finite point to build a billboard from")
    x, y = xyz[:, 0].copy(), xyz[:, 1].copy()          # contiguous: fast reductions
    gz = float(xyz[:, 2].min()) if ground_z is None else float(ground_z)
    ref = np.array([(x.min() + x.max()) / 2.0, (y.min() + y.max()) / 2.0, gz])
    local = xyz - ref
    rng = np.random.default_rng([int(method.seed) & 0xFFFFFFFF, int(tree_id) & 0xFFFFFFFF])
    shape, close_px, along = _shape_fit(local, method, rng)
    timings["shape"] = time.perf_counter() - t_start

    # ---- textures: one colour image per plane at the texture resolution
    t0 = time.perf_counter()
    fine_p = method.pixel_m
    # texels along the longest quad side (the crown boxes, the trunk): texture_px
    extent = max([fp.crown[1] - fp.crown[0] for fp in shape.fits] + [fp.crown[3] - fp.crown[2] for fp in shape.fits]
                 + [shape.trunk_z[1] - shape.trunk_z[0] if shape.has_trunk else 0.0, fine_p])
    p = max(fine_p, extent / int(method.texture_px))
    coloured = None                                      # points with a colour (None: all of them)
    if colours is not None and not np.isfinite(colours).all():
        coloured = np.flatnonzero(np.all(np.isfinite(colours), axis=1))
    has_colour = colours is not None and (coloured is None or len(coloured) > 0)
    if has_colour:
        zc = local[:, 2] if coloured is None else local[coloured, 2]
        pc = colours if coloured is None else colours[coloured]
        # texture rows: every plane's frame starts at the same z0
        row_c = np.floor((zc - shape.fits[0].z0) / p).astype(np.int64)
    source = (texture_source or "points") if has_colour else "procedural"
    seed_int = int(rng.integers(0, 2**31 - 1))
    trunk_top = shape.trunk_z[1] if shape.has_trunk else -np.inf
    planes = []
    for k, fp in enumerate(shape.fits):
        s0, z0, (h, w) = _frame(fp, fine_p, p)
        zr = (z0 + (np.arange(h) + 0.5) * p)[:, None]
        rr = np.broadcast_to(zr, (h, w))
        m = _sample(fp.mask, s0, z0, fine_p, (s0 + (np.arange(w) + 0.5) * p)[None, :], zr)
        img, good = None, None
        if has_colour:
            s = along[k] if coloured is None else along[k][coloured]
            col_c = np.floor((s - s0) / p).astype(np.int64)
            img, known = _splat_pixels(row_c, col_c, pc, (h, w), max(1.0, close_px * fine_p / p))
            good = known & m
        planes.append((rr, m, img, good))
    if has_colour and method.gmm_components >= 2:
        # §VI-B: one mixture per tree over the crown pixels of every plane
        crown = [good & (rr >= (fp.top_approx_z if fp.single else -np.inf))
                 for (rr, m, img, good), fp in zip(planes, shape.fits)]
        pix = np.concatenate([img[sel] for (rr, m, img, good), sel in zip(planes, crown)])
        if len(pix):
            keep = gmm_clean(pix, method.gmm_components, seed_int)
            start = 0
            for (rr, m, img, good), sel in zip(planes, crown):
                n = int(sel.sum())
                good[sel] = keep[start:start + n]
                start += n
    images, masks = [], []
    for k, (rr, m, img, good) in enumerate(planes):
        h, w = m.shape
        used = 0
        if img is not None and good.any():
            img, used = complete_blocks(img, m, good, method, rng)
        if used == 0:
            img = _procedural(h, w, rr, trunk_top, seed_int + k)
        images.append(img)
        masks.append(m)
    timings["texture"] = time.perf_counter() - t0

    # ---- quads and atlas
    t0 = time.perf_counter()
    origin = np.array([*ref[:2], gz]) if base is None else np.asarray(base, dtype=np.float64).reshape(3)
    if base is None:
        origin[:2] += shape.trunk_p0 if shape.has_trunk else shape.crown_c
    shift = ref - origin        # reference frame -> output frame
    quads, tex, kinds = [], [], []
    c = shape.crown_c
    boxes = []
    for k, fp in enumerate(shape.fits):
        uk = shape.u[k]
        smin, smax, zmin, zmax = fp.crown
        off = float(uk @ c)
        cperp = c - uk * off
        corners = np.array([[*(cperp + uk * smin), zmin], [*(cperp + uk * smax), zmin],
                            [*(cperp + uk * smax), zmax], [*(cperp + uk * smin), zmax]])
        hh = max(2, min(int(method.texture_px), int(round((zmax - zmin) / p))))
        ww = max(2, min(int(method.texture_px), int(round((smax - smin) / p))))
        zz = zmin + (np.arange(hh) + 0.5) * (zmax - zmin) / hh
        ss = smin + (np.arange(ww) + 0.5) * (smax - smin) / ww
        tex.append(_rgba(images[k], fp, p, fine_p, ss[None, :], zz[:, None]))
        quads.append(corners)
        kinds.append("crown")
        boxes.append((smin - off, smax - off, zmin, zmax))
    trunk_axis = None
    if shape.has_trunk:
        z_lo, z_hi = shape.trunk_z
        half = shape.trunk_width / 2.0
        a0 = np.array([*(shape.trunk_p0 + shape.trunk_dir * z_lo), z_lo])
        a1 = np.array([*(shape.trunk_p0 + shape.trunk_dir * z_hi), z_hi])
        trunk_axis = np.vstack([a0, a1]) + shift
        for k, fp in enumerate(shape.fits):
            uk = np.array([*shape.u[k], 0.0])
            quads.append(np.array([a0 - uk * half, a0 + uk * half, a1 + uk * half, a1 - uk * half]))
            hh = max(2, min(int(method.texture_px), int(round((z_hi - z_lo) / p))))
            ww = max(4, int(round(2 * half / p)))
            zz = z_lo + (np.arange(hh) + 0.5) * (z_hi - z_lo) / hh
            tt = -half + (np.arange(ww) + 0.5) * (2 * half) / ww
            Z = zz[:, None]
            axis_s = (shape.trunk_p0 @ shape.u[k]) + (shape.trunk_dir @ shape.u[k]) * Z
            tex.append(_rgba(images[k], fp, p, fine_p, axis_s + tt[None, :], Z))
            kinds.append("trunk")
    z_crown = min(fp.crown[2] for fp in shape.fits)
    stems_seen = any(fp.multiple and fp.z_bottom <= 1.0 for fp in shape.fits)  # several stems from the ground
    if not shape.has_trunk and stem_diameter_m and stem_diameter_m > 0 and z_crown > 0 and not stems_seen:
        half = float(stem_diameter_m) / 2.0
        top = z_crown + 0.1 * (max(fp.crown[3] for fp in shape.fits) - z_crown)
        a0, a1 = np.array([*c, 0.0]), np.array([*c, top])
        hh = max(2, min(int(method.texture_px), int(round(top / p))))
        bark = bark_texture(hh, max(4, int(round(2 * half / p))), seed_int)
        for k in range(len(shape.fits)):
            uk = np.array([*shape.u[k], 0.0])
            quads.append(np.array([a0 - uk * half, a0 + uk * half, a1 + uk * half, a1 - uk * half]))
            tex.append(np.concatenate([bark, np.full(bark.shape[:2] + (1,), 255, np.uint8)], axis=2))
            kinds.append("stem")
    atlas, rects = _pack(tex)
    verts, faces, uvs = [], [], []
    for q, (quad, (u0, v0, u1, v1)) in enumerate(zip(quads, rects)):
        verts.append(quad + shift)
        uvs.append([[u0, v0], [u1, v0], [u1, v1], [u0, v1]])
        faces.append([[4 * q, 4 * q + 1, 4 * q + 2], [4 * q, 4 * q + 2, 4 * q + 3]])
    timings["quads"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_start
    return BillboardMesh(
        vertices=np.concatenate(verts).astype(np.float64), faces=np.concatenate(faces).astype(np.int64),
        uvs=np.concatenate(uvs).astype(np.float64).reshape(-1, 2), texture=atlas, quad_kind=tuple(kinds),
        has_trunk=bool(shape.has_trunk), trunk_axis=trunk_axis,
        trunk_width_m=float(shape.trunk_width) if shape.has_trunk else 0.0,
        trunk_height_m=float(shape.trunk_z[1] - shape.trunk_z[0]) if shape.has_trunk else 0.0,
        crown_axis=(c + shift[:2]).astype(np.float64), crown_boxes=np.array(boxes, dtype=np.float64),
        texture_source=source, origin=origin.copy(), palette_colours=int(method.palette_colours), timings=timings)


def _procedural(h, w, rows_z, trunk_top, seed):
    from ..textures import bark_texture, foliage_texture

    img = foliage_texture(h, w, seed).astype(np.float64) / 255.0
    bark = rows_z < trunk_top
    if bark.any():
        img[bark] = (bark_texture(h, w, seed + 1).astype(np.float64) / 255.0)[bark]
    return img


def _rgba(image, fit: PlaneFit, p, fine_p, S, Z) -> np.ndarray:
    """RGBA uint8 texture (rows bottom-up) at plane coordinates (S, Z): colour from the texture-resolution
    image, alpha from the fine shape mask."""
    s0, z0 = fit.s0, fit.z0
    rgb = _sample(image, s0, z0, p, S, Z)
    a = _sample(fit.mask, s0, z0, fine_p, S, Z)
    out = np.zeros(a.shape + (4,), dtype=np.uint8)
    out[..., :3] = np.clip(np.rint(rgb * 255.0), 0, 255).astype(np.uint8)
    out[..., 3] = np.where(a, 255, 0)
    return out


def _pack(textures: List[np.ndarray]):
    """One atlas (rows top-down, glTF/PNG order) with the textures side by side and a 1-texel gutter;
    returns (atlas, [(u0, v0, u1, v1)] in the OpenGL convention, v up)."""
    H = max(t.shape[0] for t in textures) + 2
    W = sum(t.shape[1] + 2 for t in textures)
    atlas = np.zeros((H, W, 4), dtype=np.uint8)
    rects = []
    c = 0
    for t in textures:
        h, w = t.shape[:2]
        atlas[1:1 + h, c + 1:c + 1 + w] = t[::-1]
        rects.append(((c + 1) / W, 1.0 - (1 + h) / H, (c + 1 + w) / W, 1.0 - 1.0 / H))
        c += w + 2
    opaque = atlas[..., 3] > 0
    if opaque.any():
        atlas[~opaque, :3] = np.rint(atlas[opaque, :3].mean(axis=0)).astype(np.uint8)
    return atlas, rects


def opaque_points(bb: BillboardMesh, step: int = 1) -> np.ndarray:
    """3D centres (metres, the mesh's frame) of the opaque texels of every quad: the surface a viewer sees.

    Used for honest geometric errors (:func:`sylva.core.export.tiles3d.coarse_error`).
    """
    H, W = bb.texture.shape[:2]
    out = []
    for q in range(len(bb.faces) // 2):
        v = bb.vertices[4 * q:4 * q + 4]
        uv = bb.uvs[4 * q:4 * q + 4]
        u0, v0, u1, v1 = uv[0, 0], uv[0, 1], uv[2, 0], uv[2, 1]
        c0, c1 = int(round(u0 * W)), int(round(u1 * W))
        r0, r1 = int(round((1.0 - v1) * H)), int(round((1.0 - v0) * H))
        alpha = bb.texture[r0:r1:step, c0:c1:step, 3] > 0
        ri, cj = np.nonzero(alpha)
        if not len(ri):
            continue
        h, w = r1 - r0, c1 - c0
        fu = (cj * step + 0.5) / w
        fv = 1.0 - (ri * step + 0.5) / h          # 0 at the bottom edge
        bottom = v[0][None] + (v[1] - v[0])[None] * fu[:, None]
        top = v[3][None] + (v[2] - v[3])[None] * fu[:, None]
        out.append(bottom + (top - bottom) * fv[:, None])
    return np.concatenate(out) if out else bb.vertices.copy()
