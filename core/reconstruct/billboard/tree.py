"""The billboard tree: Zhou et al. 2013, "Automatic reconstruction of lightweight trees" §IV, §VI.

The method's parameters (:class:`Billboard`), its result (:class:`BillboardMesh`) and
:func:`billboard_tree`, which runs the steps of :mod:`.shape`, :mod:`.colour` and :mod:`.texture` on one
tree: the point colours splatted into each plane's frame, the six (or three) quads and their texture
atlas packed into one image (one material per tree in glTF); :func:`opaque_points` samples the quads'
opaque texels (the far tile's geometric error).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from ...errors import EmptyInputError, InputError
from ...textures import bark_texture
from .colour import point_rgb
from .shape import PlaneFit, shape_fit_along
from .texture import complete_blocks, gmm_clean


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
        from ...textures import png_bytes_indexed

        return png_bytes_indexed(self.texture, self.palette_colours)

    def summary(self) -> Dict[str, Any]:
        """Per-tree attributes: has_trunk, trunk height/width, crown width/height (m), texture source."""
        b = self.crown_boxes
        return {"bb_has_trunk": bool(self.has_trunk), "bb_trunk_height_m": float(self.trunk_height_m),
                "bb_trunk_width_m": float(self.trunk_width_m),
                "bb_crown_width_m": float(np.median(b[:, 1] - b[:, 0])) if len(b) else 0.0,
                "bb_crown_base_m": float(np.median(b[:, 2])) if len(b) else 0.0,
                "bb_texture": self.texture_source}


# --------------------------------------------------------------------------- point colours in the planes' frames

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
    shape, close_px, along = shape_fit_along(local, method, rng)
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
    from ...textures import bark_texture, foliage_texture

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
