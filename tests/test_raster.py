"""Raster helpers and the GDAL-free GeoTIFF writer (checked against GDAL itself)."""
import numpy as np
import pyproj
import pytest

from sylva.core.errors import InputError
from sylva.core.raster import Raster, read_geotiff, write_geotiff


def _raster(crs):
    data = np.arange(20, dtype=np.float32).reshape(4, 5) * 1.5
    data[1, 2] = np.nan
    return Raster(data, x0=500_000.0, y0=4_100_000.0, pixel=0.5, crs=crs)


def test_cell_helpers():
    r = _raster(None)
    assert r.geotransform == (500_000.0, 0.5, 0.0, 4_100_000.0, 0.0, -0.5)
    assert r.bounds() == (500_000.0, 4_099_998.0, 500_002.5, 4_100_000.0)
    cx, cy = r.cell_centres()
    assert cx[0, 0] == 500_000.25 and cy[0, 0] == 4_099_999.75
    assert cy[3, 0] == 4_099_998.25 and cx[0, 4] == 500_002.25
    row, col = r.index_of(cx, cy)
    assert np.array_equal(row, np.repeat(np.arange(4)[:, None], 5, 1))
    assert np.array_equal(col, np.repeat(np.arange(5)[None, :], 4, 0))
    # a point on a cell's north-west corner belongs to that cell
    assert r.index_of(500_000.5, 4_100_000.0) == (0, 1)
    s = r.sample(np.array([500_000.1, 499_999.0]), np.array([4_099_999.9, 4_099_999.9]))
    assert s[0] == 0.0 and np.isnan(s[1])


@pytest.mark.parametrize("crs", [
    pyproj.CRS.from_epsg(26912),
    pyproj.CRS.from_epsg(4326),
    pyproj.CRS.from_proj4("+proj=tmerc +lat_0=0 +lon_0=13.3 +k=0.9996 +x_0=500000 +y_0=0 "
                          "+ellps=GRS80 +units=m +no_defs"),
    None,
])
def test_round_trip(tmp_path, crs):
    r = _raster(crs)
    path = write_geotiff(tmp_path / "chm.tif", r)
    assert path.exists()
    assert not list(tmp_path.glob(".*tmp")), "temporary file left behind"
    assert (tmp_path / "chm.tif.aux.xml").exists() == (crs is not None and crs.to_epsg() is None)
    back = read_geotiff(path)
    assert np.array_equal(back.data, r.data, equal_nan=True)
    assert (back.x0, back.y0, back.pixel) == (r.x0, r.y0, r.pixel)
    if crs is None:
        assert back.crs is None
    else:
        assert back.crs.equals(crs, ignore_axis_order=True)


@pytest.mark.parametrize("epsg", [26912, 4326, None])
def test_gdal_reads_what_we_write(tmp_path, epsg):
    gdal = pytest.importorskip("osgeo.gdal")
    gdal.UseExceptions()
    crs = pyproj.CRS.from_epsg(epsg) if epsg else pyproj.CRS.from_proj4(
        "+proj=tmerc +lat_0=0 +lon_0=13.3 +k=0.9996 +x_0=500000 +y_0=0 +ellps=GRS80 +units=m +no_defs")
    r = _raster(crs)
    path = write_geotiff(tmp_path / "chm.tif", r)
    ds = gdal.Open(str(path))
    assert ds.GetGeoTransform() == r.geotransform
    band = ds.GetRasterBand(1)
    assert np.isnan(band.GetNoDataValue())
    assert band.DataType == gdal.GDT_Float32
    assert np.array_equal(band.ReadAsArray(), r.data, equal_nan=True)
    assert ds.GetMetadata("IMAGE_STRUCTURE").get("COMPRESSION") == "DEFLATE"
    srs = ds.GetSpatialRef()
    assert srs is not None
    if epsg:
        assert srs.GetAuthorityCode(None) == str(epsg)
    assert pyproj.CRS.from_wkt(ds.GetProjection()).equals(crs, ignore_axis_order=True)
    ds = None


def test_overwrite_removes_stale_sidecar(tmp_path):
    odd = pyproj.CRS.from_proj4("+proj=tmerc +lon_0=13.3 +ellps=GRS80 +units=m +no_defs")
    path = tmp_path / "a.tif"
    write_geotiff(path, _raster(odd))
    assert (tmp_path / "a.tif.aux.xml").exists()
    write_geotiff(path, _raster(pyproj.CRS.from_epsg(26912)))
    assert not (tmp_path / "a.tif.aux.xml").exists()
    assert read_geotiff(path).crs.to_epsg() == 26912


def test_bad_paths(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        write_geotiff(tmp_path / "missing" / "a.tif", _raster(None))
    with pytest.raises(InputError, match="not found"):
        read_geotiff(tmp_path / "nope.tif")
