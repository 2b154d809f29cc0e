"""Georeferenced single-band rasters (CHM, DTM) and a GDAL-free GeoTIFF writer.

A :class:`Raster` is a float32 grid, row 0 at the north edge, NaN where there
is no data, placed by the west edge ``x0``, the north edge ``y0`` and a square
pixel size, all in the units of its CRS (a north-up, pixel-is-area grid; GDAL
geotransform ``(x0, pixel, 0, y0, 0, -pixel)``).

:func:`write_geotiff` writes it with :mod:`tifffile` only, so that the command
line runs without GDAL or QGIS.  The georeferencing follows the GeoTIFF 1.0
specification (OGC 19-008r4): ``ModelPixelScaleTag`` (33550),
``ModelTiepointTag`` (33922) and ``GeoKeyDirectoryTag`` (34735) with
``ProjectedCSTypeGeoKey`` (3072) or ``GeographicTypeGeoKey`` (2048) holding the
EPSG code when pyproj finds one.  A CRS without an EPSG code is written as WKT
into a GDAL PAM sidecar ``<file>.aux.xml``, which GDAL and QGIS read.  The no
data value goes into GDAL's ``GDAL_NODATA`` tag (42113).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional, Tuple
from xml.sax.saxutils import escape

import numpy as np

from .errors import InputError

# TIFF / GeoTIFF tag numbers and GeoKey ids (GeoTIFF 1.0, OGC 19-008r4 §7).
TAG_MODEL_PIXEL_SCALE = 33550
TAG_MODEL_TIEPOINT = 33922
TAG_GEOKEY_DIRECTORY = 34735
TAG_GEO_DOUBLE_PARAMS = 34736
TAG_GEO_ASCII_PARAMS = 34737
TAG_GDAL_NODATA = 42113

GT_MODEL_TYPE = 1024          # 1 projected, 2 geographic, 32767 user-defined
GT_RASTER_TYPE = 1025         # 1 PixelIsArea
GT_CITATION = 1026
GEOGRAPHIC_TYPE = 2048
PROJECTED_CS_TYPE = 3072
PROJ_LINEAR_UNITS = 3076
USER_DEFINED = 32767


@dataclass(eq=False)
class Raster:
    """A north-up single-band grid.

    ``data``: float32 (rows, cols), NaN = no data, row 0 = north edge;
    ``x0``: west edge, ``y0``: north edge, ``pixel``: pixel size, all in CRS
    units; ``crs``: :class:`pyproj.CRS` or None.
    """

    data: np.ndarray
    x0: float
    y0: float
    pixel: float
    crs: Any = None

    def __post_init__(self):
        self.data = np.asarray(self.data, dtype=np.float32)
        if self.data.ndim != 2:
            raise ValueError(f"raster data must be 2-D, got shape {self.data.shape}")
        self.x0 = float(self.x0)
        self.y0 = float(self.y0)
        self.pixel = float(self.pixel)
        if not self.pixel > 0:
            raise ValueError(f"pixel size must be positive, got {self.pixel}")

    @property
    def shape(self) -> Tuple[int, int]:
        return self.data.shape

    @property
    def rows(self) -> int:
        return self.data.shape[0]

    @property
    def cols(self) -> int:
        return self.data.shape[1]

    @property
    def geotransform(self) -> Tuple[float, float, float, float, float, float]:
        """GDAL geotransform ``(x0, pixel, 0, y0, 0, -pixel)``."""
        return (self.x0, self.pixel, 0.0, self.y0, 0.0, -self.pixel)

    def bounds(self) -> Tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of the grid's outer edges, CRS units."""
        return (self.x0, self.y0 - self.rows * self.pixel,
                self.x0 + self.cols * self.pixel, self.y0)

    def col_centres(self) -> np.ndarray:
        """x of each column's centre (cols,)."""
        return self.x0 + (np.arange(self.cols) + 0.5) * self.pixel

    def row_centres(self) -> np.ndarray:
        """y of each row's centre (rows,), decreasing southwards."""
        return self.y0 - (np.arange(self.rows) + 0.5) * self.pixel

    def cell_centres(self) -> Tuple[np.ndarray, np.ndarray]:
        """(x, y) of every cell centre, each shaped like ``data``."""
        return np.meshgrid(self.col_centres(), self.row_centres())

    def xy_of(self, row, col) -> Tuple[np.ndarray, np.ndarray]:
        """Centre coordinates of cells (row, col)."""
        row = np.asarray(row)
        col = np.asarray(col)
        return self.x0 + (col + 0.5) * self.pixel, self.y0 - (row + 0.5) * self.pixel

    def index_of(self, x, y) -> Tuple[np.ndarray, np.ndarray]:
        """(row, col) int64 of the cells holding points (x, y); may be outside the grid."""
        col = np.floor((np.asarray(x, dtype=np.float64) - self.x0) / self.pixel).astype(np.int64)
        row = np.floor((self.y0 - np.asarray(y, dtype=np.float64)) / self.pixel).astype(np.int64)
        return row, col

    def inside(self, row, col) -> np.ndarray:
        row = np.asarray(row)
        col = np.asarray(col)
        return (row >= 0) & (row < self.rows) & (col >= 0) & (col < self.cols)

    def sample(self, x, y) -> np.ndarray:
        """Value of the cell under each (x, y); NaN outside the grid."""
        row, col = self.index_of(x, y)
        ok = self.inside(row, col)
        out = np.full(np.shape(row), np.nan, dtype=np.float32)
        out[ok] = self.data[row[ok], col[ok]]
        return out


# --------------------------------------------------------------------------- writing

def _horizontal_crs(crs):
    """The horizontal part of a (possibly compound) pyproj CRS."""
    if crs is None:
        return None
    if getattr(crs, "is_compound", False):
        for sub in crs.sub_crs_list:
            if sub.is_projected or sub.is_geographic:
                return sub
    return crs


def _geokeys(crs) -> Tuple[list, Optional[str], Optional[int]]:
    """GeoKeyDirectory shorts, ascii params and the EPSG code (None if none)."""
    keys = [(GT_RASTER_TYPE, 0, 1, 1)]
    ascii_params = None
    horizontal = _horizontal_crs(crs)
    epsg = None
    if horizontal is not None:
        try:
            epsg = horizontal.to_epsg()
        except Exception:  # pragma: no cover - pyproj edge cases
            epsg = None
    if horizontal is None:
        pass
    elif epsg is not None and horizontal.is_projected:
        keys += [(GT_MODEL_TYPE, 0, 1, 1), (PROJECTED_CS_TYPE, 0, 1, int(epsg))]
    elif epsg is not None and horizontal.is_geographic:
        keys += [(GT_MODEL_TYPE, 0, 1, 2), (GEOGRAPHIC_TYPE, 0, 1, int(epsg))]
    else:
        citation = (horizontal.name or "user-defined")[:200] + "|"
        ascii_params = citation
        model = 1 if horizontal.is_projected else (2 if horizontal.is_geographic else USER_DEFINED)
        keys += [(GT_MODEL_TYPE, 0, 1, model),
                 (GT_CITATION, TAG_GEO_ASCII_PARAMS, len(citation), 0)]
        if horizontal.is_projected:
            keys.append((PROJECTED_CS_TYPE, 0, 1, USER_DEFINED))
    keys.sort()
    directory = [1, 1, 0, len(keys)]
    for key in keys:
        directory.extend(key)
    return directory, ascii_params, epsg


def _deflate_available() -> bool:
    """tifffile encodes 'zlib' (deflate) with the standard library when imagecodecs is absent."""
    try:
        import io

        import tifffile

        buf = io.BytesIO()
        tifffile.imwrite(buf, np.zeros((2, 2), np.float32), compression="zlib")
        return True
    except Exception:
        return False


_DEFLATE: Optional[bool] = None


def _pam_xml(wkt: str) -> str:
    return ("<PAMDataset>\n  <SRS dataAxisToSRSAxisMapping=\"1,2\">"
            f"{escape(wkt)}</SRS>\n</PAMDataset>\n")


def _atomic_write_bytes(path: Path, payload: bytes) -> None:
    from .atomic import atomic_write_bytes   # the umask's permissions, not mkstemp's 0600

    atomic_write_bytes(path, payload)


def write_geotiff(path, raster: Raster, compress: bool = True) -> Path:
    """Write ``raster`` as a float32 GeoTIFF at ``path`` (atomically) and return the path.

    Deflate compression is used when tifffile can encode it (it can without
    imagecodecs, through :mod:`zlib`); otherwise the file is uncompressed.
    When the CRS has no EPSG code, the WKT goes to ``<path>.aux.xml``.
    """
    global _DEFLATE
    import tifffile

    path = Path(path)
    if not path.parent.exists():
        raise InputError(f"cannot write {path}: folder {path.parent} does not exist")
    directory, ascii_params, epsg = _geokeys(raster.crs)
    extratags = [
        (TAG_MODEL_PIXEL_SCALE, "d", 3, (raster.pixel, raster.pixel, 0.0), True),
        (TAG_MODEL_TIEPOINT, "d", 6, (0.0, 0.0, 0.0, raster.x0, raster.y0, 0.0), True),
        (TAG_GEOKEY_DIRECTORY, "H", len(directory), tuple(directory), True),
        (TAG_GDAL_NODATA, "s", 0, "nan", True),
    ]
    if ascii_params is not None:
        extratags.append((TAG_GEO_ASCII_PARAMS, "s", 0, ascii_params, True))
    if _DEFLATE is None:
        _DEFLATE = _deflate_available()
    compression = "zlib" if (compress and _DEFLATE) else None

    from .atomic import atomic_path   # the umask's permissions (0666 minus it), not mkstemp's 0600

    with atomic_path(path) as tmp:
        tifffile.imwrite(
            str(tmp), np.ascontiguousarray(raster.data, dtype=np.float32),
            compression=compression, photometric="minisblack",
            metadata=None, extratags=extratags,
        )
    aux = Path(str(path) + ".aux.xml")
    horizontal = _horizontal_crs(raster.crs)
    if horizontal is not None and epsg is None:
        _atomic_write_bytes(aux, _pam_xml(raster.crs.to_wkt()).encode("utf-8"))
    elif aux.exists():
        aux.unlink()  # a stale sidecar would override the GeoKeys in GDAL
    return path


# --------------------------------------------------------------------------- reading

def read_geotiff(path) -> Raster:
    """Read a single-band GeoTIFF written by :func:`write_geotiff` (or a simple north-up one)."""
    import tifffile

    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: file not found")
    with tifffile.TiffFile(str(path)) as tif:
        page = tif.pages[0]
        data = page.asarray().astype(np.float32)
        tags = page.tags
        if TAG_MODEL_PIXEL_SCALE not in tags or TAG_MODEL_TIEPOINT not in tags:
            raise InputError(f"{path}: not a GeoTIFF (no pixel scale / tiepoint tags)")
        scale = tags[TAG_MODEL_PIXEL_SCALE].value
        tie = tags[TAG_MODEL_TIEPOINT].value
        nodata = tags[TAG_GDAL_NODATA].value if TAG_GDAL_NODATA in tags else None
        keys = tags[TAG_GEOKEY_DIRECTORY].value if TAG_GEOKEY_DIRECTORY in tags else ()
    if data.ndim != 2:
        raise InputError(f"{path}: expected one band, got shape {data.shape}")
    if abs(scale[0] - scale[1]) > 1e-12 * max(1.0, abs(scale[0])):
        raise InputError(f"{path}: non-square pixels ({scale[0]} x {scale[1]}) are not supported")
    pixel = float(scale[0])
    x0 = tie[3] - tie[0] * pixel
    y0 = tie[4] + tie[1] * pixel
    if nodata is not None:
        text = nodata.strip("\x00 ").lower()
        if text not in ("nan", "-nan", ""):
            data[data == np.float32(float(text))] = np.nan
    crs = None
    aux = Path(str(path) + ".aux.xml")
    if aux.exists():
        import re
        from xml.sax.saxutils import unescape

        import pyproj

        match = re.search(r"<SRS[^>]*>(.*?)</SRS>", aux.read_text("utf-8"), re.S)
        if match:
            crs = pyproj.CRS.from_wkt(unescape(match.group(1)))
    if crs is None and len(keys) >= 4:
        import pyproj

        for i in range(keys[3]):
            key, loc, _count, value = keys[4 + 4 * i: 8 + 4 * i]
            if key in (PROJECTED_CS_TYPE, GEOGRAPHIC_TYPE) and loc == 0 and value != USER_DEFINED:
                crs = pyproj.CRS.from_epsg(int(value))
                break
    return Raster(data=data, x0=x0, y0=y0, pixel=pixel, crs=crs)


# --------------------------------------------------------------------------- tile grids and mosaics

def aligned_raster(bounds, pixel: float, crs=None) -> Raster:
    """An all-NaN raster covering ``bounds`` (xmin, ymin, xmax, ymax), its edges snapped outwards to
    multiples of ``pixel`` (Sylva, not in a paper).

    Rasters of abutting tiles made this way share one grid and do not overlap
    when the tile edges fall on multiples of ``pixel``, so a VRT
    (:func:`write_vrt`) joins them without resampling.
    """
    xmin, ymin, xmax, ymax = (float(v) for v in bounds)
    x0 = np.floor(xmin / pixel) * pixel
    y0 = np.ceil(ymax / pixel) * pixel
    cols = max(1, int(np.ceil((xmax - x0) / pixel - 1e-9)))
    rows = max(1, int(np.ceil((y0 - ymin) / pixel - 1e-9)))
    return Raster(np.full((rows, cols), np.nan, np.float32), x0, y0, pixel, crs)


def paste(target: Raster, source: Raster) -> Raster:
    """Copy ``source``'s cells into ``target`` where they overlap (same pixel, grids offset by whole
    pixels, as :func:`aligned_raster` and the CHM grid make them); returns ``target``."""
    if abs(target.pixel - source.pixel) > 1e-9 * target.pixel:
        raise ValueError(f"pixel sizes differ: {target.pixel} and {source.pixel}")
    dc = int(round((source.x0 - target.x0) / target.pixel))
    dr = int(round((target.y0 - source.y0) / target.pixel))
    r0, c0 = max(dr, 0), max(dc, 0)
    r1, c1 = min(dr + source.rows, target.rows), min(dc + source.cols, target.cols)
    if r1 > r0 and c1 > c0:
        target.data[r0:r1, c0:c1] = source.data[r0 - dr:r1 - dr, c0 - dc:c1 - dc]
    return target


def write_vrt(path, tiffs, crs=None) -> Path:
    """A GDAL virtual raster (VRT XML) mosaicking single-band float32 GeoTIFFs of one pixel size.

    Sources are referenced relative to the VRT; NaN is no data (a NaN cell of
    one source does not hide another's value).  Written atomically.  GDAL's
    VRT format: https://gdal.org/drivers/raster/vrt.html (Sylva, not in a paper).
    """
    from .atomic import atomic_write_bytes

    path = Path(path)
    heads = [(Path(t), read_geotiff(t)) for t in tiffs]
    if not heads:
        raise InputError(f"{path}: no raster to mosaic")
    pixel = heads[0][1].pixel
    for t, r in heads:
        if abs(r.pixel - pixel) > 1e-9 * pixel:
            raise InputError(f"{t}: pixel {r.pixel} differs from {pixel} of {heads[0][0]}")
    crs = crs if crs is not None else heads[0][1].crs
    x0 = min(r.x0 for _, r in heads)
    y0 = max(r.y0 for _, r in heads)
    x1 = max(r.bounds()[2] for _, r in heads)
    y1 = min(r.bounds()[1] for _, r in heads)
    cols, rows = int(round((x1 - x0) / pixel)), int(round((y0 - y1) / pixel))
    lines = [f'<VRTDataset rasterXSize="{cols}" rasterYSize="{rows}">']
    if crs is not None:
        lines.append(f'  <SRS dataAxisToSRSAxisMapping="1,2">{escape(crs.to_wkt())}</SRS>')
    lines += [f"  <GeoTransform>{x0!r}, {pixel!r}, 0.0, {y0!r}, 0.0, {-pixel!r}</GeoTransform>",
              '  <VRTRasterBand dataType="Float32" band="1">', "    <NoDataValue>nan</NoDataValue>"]
    for t, r in sorted(heads, key=lambda h: (-h[1].y0, h[1].x0, str(h[0]))):
        try:
            rel = os.path.relpath(t.resolve(), path.resolve().parent)
        except ValueError:  # another drive (Windows)
            rel = None
        name = escape(rel if rel is not None else str(t.resolve()))
        xo, yo = int(round((r.x0 - x0) / pixel)), int(round((y0 - r.y0) / pixel))
        lines += ["    <ComplexSource>",
                  f'      <SourceFilename relativeToVRT="{0 if rel is None else 1}">{name}</SourceFilename>',
                  "      <SourceBand>1</SourceBand>",
                  f'      <SourceProperties RasterXSize="{r.cols}" RasterYSize="{r.rows}" DataType="Float32"/>',
                  f'      <SrcRect xOff="0" yOff="0" xSize="{r.cols}" ySize="{r.rows}"/>',
                  f'      <DstRect xOff="{xo}" yOff="{yo}" xSize="{r.cols}" ySize="{r.rows}"/>',
                  "      <NODATA>nan</NODATA>",
                  "    </ComplexSource>"]
    lines += ["  </VRTRasterBand>", "</VRTDataset>", ""]
    atomic_write_bytes(path, "\n".join(lines).encode("utf-8"))
    return path
