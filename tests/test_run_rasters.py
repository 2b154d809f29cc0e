"""The pipeline's terrain and canopy rasters: dtm/<tile>.tif, chm/<tile>.tif joined by dtm.vrt and chm.vrt.

Opened with GDAL (what QGIS reads them with): the mosaic of 2 x 2 tiles is the raster of the whole stand
in one tile, the DTM matches the simulator's ground, the CHM the trees' heights.
"""
from pathlib import Path

import numpy as np
import pytest

from sylva.core.catalog import run_catalog
from sylva.core.pipeline import PipelineOptions
from sylva.core.raster import Raster, aligned_raster, paste, write_geotiff, write_vrt
from sylva.testing.synth import ScanSpec, StandSpec, make_stand, simulate_scan

from .test_catalog import cut

gdal = pytest.importorskip("osgeo.gdal")
FAST = PipelineOptions(reconstruct=False)


def _read(path: Path):
    ds = gdal.Open(str(path))
    assert ds is not None, f"GDAL cannot open {path}"
    return ds.GetRasterBand(1).ReadAsArray().astype(np.float64), ds.GetGeoTransform(), ds.GetProjection()


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("rasters")
    stand = make_stand(StandSpec(width_m=40.0, depth_m=40.0, stems_per_ha=250, crown_overlap=0.5, seed=5))
    scan = simulate_scan(stand, ScanSpec(pulse_density=5.0, seed=5))
    cut(scan.cloud, scan.truth_tree, root / "one", 1)
    cut(scan.cloud, scan.truth_tree, root / "four", 2)
    one = run_catalog([root / "one"], root / "out_one", FAST)
    four = run_catalog([root / "four"], root / "out_four", FAST)
    return scan, one, four


def test_run_writes_a_dtm_and_chm_mosaic_gdal_opens(runs):
    scan, one, four = runs
    assert Path(four.dtm).name == "dtm.vrt" and Path(four.chm).name == "chm.vrt"
    assert len(list((Path(four.dtm).parent / "dtm").glob("*.tif"))) == 4
    dtm, gt, wkt = _read(Path(four.dtm))
    assert "UTM" in wkt or "PROJCS" in wkt or "PROJCRS" in wkt
    assert gt[1] == 1.0 and gt[5] == -1.0
    xmin, ymin, _, xmax, ymax, _ = scan.cloud.bounds()
    # the mosaic covers the stand, and no more than a pixel beyond it
    assert gt[0] <= xmin < gt[0] + 1 and gt[3] >= ymax > gt[3] - 1
    assert xmax <= gt[0] + dtm.shape[1] and ymin >= gt[3] - dtm.shape[0]
    assert np.isfinite(dtm).all()
    # the ground under every simulated ground point, within 15 cm
    pts = scan.cloud.xyz[scan.cloud.attrs["classification"] == 2]
    assert len(pts) > 1000
    col = np.floor(pts[:, 0] - gt[0]).astype(int)
    row = np.floor(gt[3] - pts[:, 1]).astype(int)
    assert np.median(np.abs(dtm[row, col] - pts[:, 2])) < 0.15


def test_mosaic_of_tiles_is_the_raster_of_one_tile(runs):
    _, one, four = runs
    for kind, tol in (("dtm", 0.02), ("chm", 0.05)):
        a, gta, _ = _read(Path(getattr(one, kind)))
        b, gtb, _ = _read(Path(getattr(four, kind)))
        # both on the same grid (multiples of the pixel); compare where both have data
        dc, dr = int(round((gtb[0] - gta[0]) / gta[1])), int(round((gta[3] - gtb[3]) / gta[1]))
        h, w = min(a.shape[0] - dr, b.shape[0]), min(a.shape[1] - dc, b.shape[1])
        a, b = a[dr:dr + h, dc:dc + w], b[:h, :w]
        both = np.isfinite(a) & np.isfinite(b)
        assert both.mean() > 0.9, kind
        assert np.quantile(np.abs(a[both] - b[both]), 0.99) < tol, kind


def test_chm_holds_the_trees_heights(runs):
    scan, one, _ = runs
    chm, gt, _ = _read(Path(one.chm))
    assert gt[1] == 0.5
    tallest = max(t.height for t in scan.stand.trees)
    assert np.nanmax(chm) == pytest.approx(tallest, abs=1.0)       # the simulator's tallest tree
    assert np.nanmax(chm) > 10 and np.nanmin(chm) < 1      # trees and open ground
    assert np.isfinite(chm).mean() > 0.97                   # scan-line gaps filled


def test_vrt_joins_rasters_and_leaves_nan_to_the_other_source(tmp_path):
    a = aligned_raster((0.0, 0.0, 4.0, 2.0), 1.0)
    a.data[:] = 1.0
    a.data[0, 3] = np.nan
    b = Raster(np.full((2, 3), 2.0, np.float32), 3.0, 2.0, 1.0)   # overlaps a's last column
    write_geotiff(tmp_path / "a.tif", a)
    write_geotiff(tmp_path / "b.tif", b)
    data, gt, _ = _read(write_vrt(tmp_path / "m.vrt", [tmp_path / "a.tif", tmp_path / "b.tif"]))
    assert data.shape == (2, 6) and gt[0] == 0.0 and gt[3] == 2.0
    assert data[0, 3] == 2.0 and data[1, 0] == 1.0 and data[0, 5] == 2.0
    target = aligned_raster((0.0, 0.0, 6.0, 2.0), 1.0)
    paste(target, b)
    assert np.isnan(target.data[:, :3]).all() and (target.data[:, 3:] == 2.0).all()


@pytest.mark.parametrize("qml, renderer", [("dtm.qml", "hillshade"), ("chm.qml", "singlebandpseudocolor")])
def test_raster_styles_load(qgis_app, runs, qml, renderer):
    from qgis.core import QgsRasterLayer

    from sylva.processing.outputs import StyledOutput

    _, one, _ = runs
    layer = QgsRasterLayer(one.dtm if qml == "dtm.qml" else one.chm, qml)
    assert layer.isValid()
    StyledOutput.get(qml).postProcessLayer(layer, _NoProject(), None)
    assert layer.renderer().type() == renderer


class _NoProject:
    @staticmethod
    def project():
        return None
