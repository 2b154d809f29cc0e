"""Billboard colours: Zhou et al. 2013, "Automatic reconstruction of lightweight trees" §V.

Per-point colours (LAS RGB in any of its scales), and colours sampled from an orthophoto (GeoTIFF) or from a
pinhole camera image (§V's ``P = K M``), with the readers of both.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import numpy as np

from ...errors import InputError


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

    from ...raster import (GEOGRAPHIC_TYPE, PROJECTED_CS_TYPE, TAG_GEOKEY_DIRECTORY, TAG_MODEL_PIXEL_SCALE,
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
