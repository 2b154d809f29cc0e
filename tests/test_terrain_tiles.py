"""sylva:terraintiles: the DTM and CHM of a survey's tiles, each read with its neighbours' buffer."""
import subprocess
import sys

import numpy as np
import pytest

from badfiles import corner_tiles
from sylva.core.terrain_tiles import TerrainOptions, run_terrain_tiles


def _grid(path):
    from osgeo import gdal

    ds = gdal.Open(str(path))
    return ds.GetGeoTransform(), ds.ReadAsArray().astype(np.float64), ds.GetSpatialRef().GetAuthorityCode(None)


@pytest.fixture(scope="module")
def runs(sample_laz, tmp_path_factory):
    """The sample's 80 m corner as 2 x 2 tiles of 40 m and as one tile, each run through run_terrain_tiles
    (normalised tiles too)."""
    root = tmp_path_factory.mktemp("terrain")
    corner_tiles(root / "tiles", sample_laz, size_m=40.0, n=2)
    corner_tiles(root / "whole", sample_laz, size_m=80.0, n=1)
    out = {}
    for name, workers in (("tiles", 2), ("whole", 1)):
        out[name] = run_terrain_tiles([str(root / name)], root / f"out_{name}", TerrainOptions(normalized=True),
                                      workers=workers)
    return root, out


@pytest.mark.parametrize("kind", ["dtm", "chm"])
def test_tiles_give_the_rasters_of_the_whole(runs, kind):
    root, out = runs
    assert len(out["tiles"].tiles) == 4 and not out["tiles"].failures
    assert sorted(p.name for p in (root / "out_tiles" / kind).glob("*.tif")) == [
        "c_0_0.tif", "c_0_1.tif", "c_1_0.tif", "c_1_1.tif"]
    ga, a, epsg = _grid(getattr(out["tiles"], kind))
    gb, b, _ = _grid(getattr(out["whole"], kind))
    assert epsg == "32632" and ga == gb and a.shape == b.shape
    assert ga[1] == {"dtm": 1.0, "chm": 0.5}[kind]
    both = np.isfinite(a) & np.isfinite(b)
    assert both.mean() > 0.95
    # no seam: every cell both have is the same (buffered reads, grids aligned on the pixel)
    np.testing.assert_allclose(a[both], b[both], atol=1e-3)
    if kind == "chm":
        assert 10.0 < np.nanmax(a) < 60.0                      # metres above ground, not elevations
    assert not (root / "out_tiles" / "parts").exists()        # the halos were scratch


def test_normalised_tiles_are_the_whole_normalised(runs):
    """Every point of every tile, z = its height above the ground: the same as the untiled run's (the
    ground triangulated with the buffer), the source elevation kept as 'elevation'."""
    import laspy

    root, _ = runs

    def points(folder):
        las = [laspy.read(str(p)) for p in sorted((root / folder / "normalized").glob("*.laz"))]
        return np.concatenate([np.column_stack([f.x, f.y, f["elevation"], f.z]) for f in las])

    source = [laspy.read(str(p)) for p in sorted((root / "tiles").glob("*.laz"))]
    tiled, whole = points("out_tiles"), points("out_whole")
    assert len(tiled) == len(whole) == sum(len(f.points) for f in source)
    src = np.concatenate([np.column_stack([f.x, f.y, f.z]) for f in source])
    order = lambda a: a[np.lexsort((a[:, 2], a[:, 1], a[:, 0]))]
    np.testing.assert_array_equal(order(tiled)[:, :3], order(src))          # every point, elevation kept
    np.testing.assert_allclose(order(tiled)[:, 3], order(whole)[:, 3], atol=1e-3)
    assert np.percentile(tiled[:, 3], 99) > 10.0 and abs(np.median(tiled[tiled[:, 3] < 0.5, 3])) < 0.2


def test_a_folder_without_tiles_is_one_line(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    run = subprocess.run([sys.executable, "-m", "sylva.cli", "terraintiles", f"--INPUT={empty}",
                          f"--OUTPUT_FOLDER={tmp_path / 'out'}"], capture_output=True, text=True)
    assert run.returncode != 0
    assert "Traceback" not in run.stderr and str(empty) in run.stderr
    assert not list((tmp_path / "out").glob("*.vrt"))
