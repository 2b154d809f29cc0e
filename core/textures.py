"""Leaf textures drawn by Sylva itself: RGBA arrays with an alpha mask, no copied images.

Hu et al. 2017 §5.6 texture leaf cards with scanned apple, cherry, maple and
poplar leaves; Guo et al. 2018 §5.2 use "quads with alpha textures".  Sylva
draws comparable shapes procedurally with numpy (supersampled for smooth
edges):

* ``"ovate"``       apple / cherry: widest below the middle, finely serrate;
* ``"lobed"``       oak: obovate outline with rounded lobes;
* ``"palmate"``     maple: five pointed lobes around the petiole;
* ``"lanceolate"``  willow: long and narrow;
* ``"deltoid"``     poplar: broad triangular base, pointed tip;
* ``"needle_spray"`` conifer: a twig with needles on both sides.

Layout of every texture: the petiole (or twig base) at the bottom centre of
the image, the leaf tip at the top; texture coordinates in
:mod:`sylva.core.leaves` follow the OBJ/OpenGL convention (v = 0 at the
bottom row of the image).  Pixels outside the leaf have alpha 0 (and a leaf
colour, so mipmapped edges do not darken).  :func:`write_png` writes an image
through Pillow when it is installed, else through a minimal zlib PNG writer.
"""
from __future__ import annotations

import struct
import zlib
from pathlib import Path
from typing import Dict, Tuple

import numpy as np

from .atomic import atomic_open
from .errors import InputError

__all__ = ["LEAF_SHAPES", "SPECIES_SHAPES", "leaf_texture", "leaf_aspect", "write_png", "read_png_size",
           "foliage_texture", "bark_texture", "png_bytes_indexed"]

LEAF_SHAPES = ("ovate", "lobed", "palmate", "lanceolate", "deltoid", "needle_spray")

#: Hu et al.'s leaf species (and a few more) mapped to the drawn shapes.
SPECIES_SHAPES: Dict[str, str] = {
    "apple": "ovate", "cherry": "ovate", "beech": "ovate", "birch": "deltoid",
    "poplar": "deltoid", "maple": "palmate", "oak": "lobed", "willow": "lanceolate",
    "pine": "needle_spray", "spruce": "needle_spray", "fir": "needle_spray",
}

# width / length of the drawn leaf (used by leaves.py to size cards)
_ASPECT = {"ovate": 0.62, "lobed": 0.62, "palmate": 1.0, "lanceolate": 0.3,
           "deltoid": 0.85, "needle_spray": 0.55}

_PETIOLE_V = 0.12  # the blade starts here (v from 0 at the bottom to 1 at the top)


def leaf_shape_name(shape: str) -> str:
    """The leaf shape a shape or species name stands for (one line naming the choices if unknown)."""
    name = SPECIES_SHAPES.get(str(shape).lower(), str(shape).lower())
    if name not in LEAF_SHAPES:
        raise InputError(f"unknown leaf shape {shape!r}: use one of {', '.join(LEAF_SHAPES)} "
                         f"or a species ({', '.join(sorted(SPECIES_SHAPES))})")
    return name


def leaf_aspect(shape: str) -> float:
    """Width / length of the drawn leaf (cards of this aspect show it undistorted)."""
    return _ASPECT[leaf_shape_name(shape)]


def _blade_halfwidth(name: str, t: np.ndarray) -> np.ndarray:
    """Half width (in units of the image half width) along the blade, t in [0, 1]."""
    t = np.clip(t, 0.0, 1.0)
    if name == "ovate":
        hw = 0.95 * np.sin(np.pi * t ** 0.85) ** 0.8 * (1.0 - 0.25 * t ** 3)
        return hw * (1.0 + 0.035 * np.abs(np.sin(44 * np.pi * t)))          # serrate margin
    if name == "lanceolate":
        return 0.95 * np.sin(np.pi * t ** 0.9) ** 1.1
    if name == "deltoid":
        hw = 0.97 * np.sin(np.pi * t ** 0.55) ** 0.8
        return hw * (1.0 + 0.03 * np.abs(np.sin(36 * np.pi * t)))
    if name == "lobed":
        base = 0.98 * np.sin(np.pi * t ** 1.25) ** 0.7
        lobes = 0.62 + 0.38 * (0.5 - 0.5 * np.cos(2.0 * np.pi * 4.0 * t ** 1.1)) ** 0.5
        return base * lobes
    raise AssertionError(name)


def _leaf_mask(name: str, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Boolean coverage at normalised coordinates u in [-1, 1] (across), v in [0, 1] (up)."""
    petiole = (np.abs(u) < 0.035) & (v >= 0.0) & (v <= _PETIOLE_V + 0.05)
    if name == "palmate":
        cy, radius = 0.42, 0.98
        du, dv = u, (v - cy) * 2.0  # u spans 2 units and v 1 unit on a square card
        rr = np.hypot(du, dv)
        theta = np.arctan2(du, dv)  # 0 = up
        period = np.deg2rad(54.0)
        lobe = (0.5 + 0.5 * np.cos(2.0 * np.pi * theta / period)) ** 2.5
        env = np.clip(1.0 - 0.33 * np.abs(theta) / np.deg2rad(108.0), 0.0, 1.0)
        rmax = radius * (0.45 + 0.55 * lobe * env) * np.where(np.abs(theta) > np.deg2rad(135), 0.45, 1.0)
        rmax = rmax * (1.0 + 0.04 * np.abs(np.sin(5 * 2.0 * np.pi * theta / period)))
        blade = rr <= rmax * 1.0
        petiole = (np.abs(u) < 0.035) & (v >= 0.0) & (v <= cy)
        return blade | petiole
    if name == "needle_spray":
        vv = 2.0 * v                                    # isotropic: both in image half widths
        out = (np.abs(u) < 0.035) & (vv >= 0.0) & (vv <= 1.94)      # the twig
        spacing, width = 0.07, 0.02
        tilt = np.deg2rad(50.0)  # needle angle from the twig axis, pointing to the tip
        for sgn, shift in ((1.0, 0.0), (-1.0, 0.5)):
            du, dv = sgn * np.sin(tilt), np.cos(tilt)   # needle direction
            v0 = 0.08 + shift * spacing
            cross0 = u * dv - vv * du                   # cross((u, V) - (0, V_k), d) = cross0 + V_k du
            kmax = int((1.86 - v0) / spacing)
            k = np.clip(np.rint(-(cross0 + v0 * du) / (spacing * du)), 0, kmax)
            vk = v0 + k * spacing
            perp = np.abs(cross0 + vk * du)
            along = u * du + (vv - vk) * dv
            frac = np.clip((vk - v0) / (1.86 - v0), 0.0, 1.0)
            length = 1.25 * (0.35 + 0.65 * np.sin(np.pi * (0.15 + 0.75 * frac)))
            taper = width * np.clip(1.0 - along / length, 0.25, 1.0)
            out |= (sgn * u > 0) & (perp < taper) & (along > 0) & (along < length) & (vv < 2.0)
        return out
    t = (v - _PETIOLE_V) / (1.0 - _PETIOLE_V - 0.02)
    blade = (t >= 0) & (t <= 1) & (np.abs(u) <= _blade_halfwidth(name, t))
    return blade | petiole


_COLOURS = {
    "ovate": ((64, 128, 38), (38, 90, 24)),
    "lobed": ((82, 120, 40), (52, 86, 26)),
    "palmate": ((96, 140, 42), (60, 100, 28)),
    "lanceolate": ((104, 140, 66), (66, 102, 44)),
    "deltoid": ((74, 136, 52), (44, 96, 34)),
    "needle_spray": ((46, 92, 52), (30, 66, 38)),
}


def leaf_texture(shape: str = "ovate", size: int = 256, supersample: int = 3) -> np.ndarray:
    """An RGBA leaf image (size, size, 4) uint8 drawn procedurally (no image files).

    ``shape`` is one of :data:`LEAF_SHAPES` or a species of
    :data:`SPECIES_SHAPES` (Hu et al. 2017 §5.6 use apple, cherry, maple and
    poplar).  The petiole is at the bottom centre, the tip at the top; alpha
    is 255 inside the leaf, 0 outside, antialiased over ``supersample``²
    subpixels.  The blade is shaded from the midrib outwards with a darker
    midrib and lateral veins.  Deterministic.
    """
    name = leaf_shape_name(shape)
    size = int(size)
    if size < 8:
        raise InputError(f"leaf texture size must be at least 8 pixels, got {size}")
    ss = max(1, int(supersample))
    n = size * ss
    c = (np.arange(n) + 0.5) / n
    u = (c * 2.0 - 1.0)[None, :]            # across, -1 .. 1
    v = (1.0 - c)[:, None]                  # up: row 0 is the top of the image
    uu = np.broadcast_to(u, (n, n))
    vv = np.broadcast_to(v, (n, n))
    mask = _leaf_mask(name, uu, vv)
    cover = mask.reshape(size, ss, size, ss).mean(axis=(1, 3))
    # colours at pixel centres
    pc = (np.arange(size) + 0.5) / size
    pu = (pc * 2.0 - 1.0)[None, :]
    pv = (1.0 - pc)[:, None]
    light, dark = (np.array(x, dtype=np.float64) for x in _COLOURS[name])
    shade = np.clip(0.25 + 0.75 * np.abs(pu) ** 0.7 + 0.15 * (1 - pv), 0.0, 1.0)
    rgb = light[None, None, :] * (1 - 0.35 * shade[..., None]) + dark[None, None, :] * 0.35 * shade[..., None]
    if name == "needle_spray":
        twig = np.abs(pu) < 0.045
        rgb = np.where(twig[..., None], np.array([96.0, 72.0, 46.0]), rgb)
    else:
        midrib = np.abs(pu) < 0.025
        veins = (np.abs(((pv - 1.1 * np.abs(pu)) * 9.0) % 1.0 - 0.5) < 0.06) & (np.abs(pu) < 0.85)
        if name == "palmate":
            th = np.arctan2(pu, (pv - 0.42) * 2.0)
            midrib = (np.abs(((th / np.deg2rad(54.0)) + 0.5) % 1.0 - 0.5) * np.deg2rad(54.0)
                      * np.hypot(pu, (pv - 0.42) * 2) < 0.025) & (np.abs(th) < np.deg2rad(115))
            veins = np.zeros_like(midrib)
        rgb = np.where(midrib[..., None], rgb * 0.72 + 40.0, rgb)
        rgb = np.where(veins[..., None], rgb * 0.85 + 12.0, rgb)
    out = np.empty((size, size, 4), dtype=np.uint8)
    out[..., :3] = np.clip(np.rint(rgb), 0, 255).astype(np.uint8)
    out[..., 3] = np.clip(np.rint(cover * 255.0), 0, 255).astype(np.uint8)
    return out


# --------------------------------------------------------------------------- PNG

def png_bytes(rgba: np.ndarray) -> bytes:
    """A minimal PNG (8-bit RGBA, filter 0 rows, one zlib IDAT chunk)."""
    h, w = rgba.shape[:2]
    raw = np.zeros((h, w * 4 + 1), dtype=np.uint8)
    raw[:, 1:] = rgba.reshape(h, w * 4)

    def chunk(tag: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + tag + data
                + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF))

    return (b"\x89PNG\r\n\x1a\n"
            + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 6, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw.tobytes(), 9))
            + chunk(b"IEND", b""))


def write_png(path, rgba: np.ndarray) -> Path:
    """Write an (h, w, 4) uint8 image as PNG, atomically."""
    rgba = np.asarray(rgba)
    if rgba.ndim != 3 or rgba.shape[2] != 4 or rgba.dtype != np.uint8:
        raise InputError(f"{path}: expected an (h, w, 4) uint8 RGBA image, got {rgba.shape} {rgba.dtype}")
    with atomic_open(path) as fh:
        try:
            from PIL import Image
            Image.fromarray(np.ascontiguousarray(rgba), "RGBA").save(fh, format="PNG", optimize=True)
        except ImportError:
            fh.write(png_bytes(rgba))
    return Path(path)


def read_png_size(path) -> Tuple[int, int]:
    """(width, height) from a PNG header (for checks without an image library)."""
    with open(path, "rb") as fh:
        head = fh.read(24)
    if head[:8] != b"\x89PNG\r\n\x1a\n":
        raise InputError(f"{path}: not a PNG file")
    return struct.unpack(">II", head[16:24])


# --------------------------------------------------------------------------- billboard fallbacks

def _value_noise(h: int, w: int, rng: np.random.Generator, cell_px: float) -> np.ndarray:
    """Smooth noise in [0, 1], (h, w): a coarse random grid bilinearly upsampled."""
    gh, gw = int(np.ceil(h / cell_px)) + 2, int(np.ceil(w / cell_px)) + 2
    grid = rng.uniform(0.0, 1.0, (gh, gw))
    y = (np.arange(h) + 0.5) / cell_px
    x = (np.arange(w) + 0.5) / cell_px
    y0, x0 = np.floor(y).astype(int), np.floor(x).astype(int)
    fy, fx = (y - y0)[:, None], (x - x0)[None, :]
    g00, g01 = grid[y0][:, x0], grid[y0][:, x0 + 1]
    g10, g11 = grid[y0 + 1][:, x0], grid[y0 + 1][:, x0 + 1]
    return (g00 * (1 - fy) * (1 - fx) + g01 * (1 - fy) * fx + g10 * fy * (1 - fx) + g11 * fy * fx)


def foliage_texture(height: int, width: int, seed: int = 0, rgb=(0.22, 0.36, 0.14)) -> np.ndarray:
    """A procedural foliage colour image (height, width, 3) uint8: clumps of light and shade.

    The fallback texture of billboard crowns (Zhou et al. 2013 §VI-B needs an
    image; without one and without point colours Sylva draws this): two
    octaves of value noise modulate the brightness of ``rgb`` (linear 0..1).
    """
    rng = np.random.default_rng(seed)
    h, w = max(int(height), 1), max(int(width), 1)
    n = 0.65 * _value_noise(h, w, rng, 6.0) + 0.35 * _value_noise(h, w, rng, 2.0)
    shade = 0.55 + 0.9 * n
    hue = 1.0 + 0.12 * (_value_noise(h, w, rng, 12.0) - 0.5)
    out = np.asarray(rgb, dtype=np.float64)[None, None, :] * shade[..., None]
    out[..., 0] *= hue
    return np.clip(np.rint(out * 255.0), 0, 255).astype(np.uint8)


def bark_texture(height: int, width: int, seed: int = 0, rgb=(0.30, 0.20, 0.13)) -> np.ndarray:
    """A procedural bark colour image (height, width, 3) uint8: vertical furrows (the trunk quads' fallback)."""
    rng = np.random.default_rng(seed)
    h, w = max(int(height), 1), max(int(width), 1)
    cols = rng.uniform(0.0, 1.0, w)
    furrow = 0.75 + 0.35 * np.convolve(np.r_[cols[-1:], cols, cols[:1]], np.ones(3) / 3.0, "valid")
    n = _value_noise(h, w, rng, 3.0)
    shade = furrow[None, :] * (0.85 + 0.3 * n)
    out = np.asarray(rgb, dtype=np.float64)[None, None, :] * shade[..., None]
    return np.clip(np.rint(out * 255.0), 0, 255).astype(np.uint8)


def png_bytes_indexed(rgba: np.ndarray, max_colours: int = 64) -> bytes:
    """A palette PNG (colour type 3, 8-bit indices, ``tRNS``) of an RGBA image with a binary alpha.

    Pixels with alpha < 128 become index 0 (fully transparent); the opaque
    colours are reduced to at most ``max_colours - 1`` entries: colours are
    binned to 5 bits a channel, the most frequent bins kept (ties by bin
    value: deterministic) and every other bin mapped to its nearest kept one;
    each entry is the mean of the colours it stands for.  Much smaller than
    RGBA for the billboard atlases (Zhou et al. 2013 Table I: ~40 kB a tree).
    """
    from scipy.spatial import cKDTree

    rgba = np.ascontiguousarray(rgba, dtype=np.uint8)
    h, w = rgba.shape[:2]
    max_colours = int(min(max(max_colours, 2), 256))
    flat = rgba.reshape(-1, 4)
    opaque = flat[:, 3] >= 128
    rgb = flat[opaque, :3].astype(np.int64)
    index = np.zeros(h * w, dtype=np.uint8)
    palette = np.zeros((1, 3))
    if len(rgb):
        palette[0] = rgb.mean(axis=0)  # the transparent entry: a mean colour, so filtered edges do not darken
        key = ((rgb[:, 0] >> 3) << 10) | ((rgb[:, 1] >> 3) << 5) | (rgb[:, 2] >> 3)
        bins, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
        keep = np.lexsort((bins, -counts))[:max_colours - 1]
        centres = np.column_stack([(bins >> 10) & 31, (bins >> 5) & 31, bins & 31]).astype(np.float64)
        _, nearest = cKDTree(centres[keep]).query(centres)
        entry = nearest[inverse]
        sums = np.stack([np.bincount(entry, weights=rgb[:, c], minlength=len(keep)) for c in range(3)], axis=1)
        n = np.bincount(entry, minlength=len(keep))[:, None]
        palette = np.vstack([palette, sums / np.maximum(n, 1)])
        index[opaque] = (entry + 1).astype(np.uint8)
    plte = np.clip(np.rint(palette), 0, 255).astype(np.uint8)
    raw = np.zeros((h, w + 1), dtype=np.uint8)
    raw[:, 1:] = index.reshape(h, w)

    def chunk(tag: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + tag + data
                + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF))

    return (b"\x89PNG\r\n\x1a\n"
            + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 3, 0, 0, 0))
            + chunk(b"PLTE", plte.tobytes())
            + chunk(b"tRNS", b"\x00")
            + chunk(b"IDAT", zlib.compress(raw.tobytes(), 9))
            + chunk(b"IEND", b""))
