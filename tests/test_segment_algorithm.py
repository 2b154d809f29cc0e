"""sylva:segmenttrees and sylva:normalizeheight end to end, in real QGIS and from the CLI."""
import subprocess
import sys

import laspy
import numpy as np
import pytest

from sylva.core.io.gpkg import read_gpkg

TREE_FIELDS = ["tree_id", "x", "y", "ground_z", "height", "crown_area", "crown_diameter",
               "crown_base_height", "n_points", "quality"]


@pytest.mark.qgis
@pytest.mark.parametrize("method", [0, 1])
def test_segmenttrees_outputs_open_in_qgis(sylva_provider, sample_laz, tmp_path, method):
    import processing
    from qgis.core import QgsVectorLayer, QgsWkbTypes

    out = {name: str(tmp_path / f"{name.lower()}.gpkg")
           for name in ("TREE_TOPS", "CROWNS", "CROWN_POINTS", "STEM_POINTS", "TREES")}
    result = processing.run("sylva:segmenttrees", {"INPUT": str(sample_laz), "METHOD": method,
                                                   "OUTPUT": str(tmp_path / "seg.laz"), **out})
    layers = {name: QgsVectorLayer(result[name], name, "ogr") for name in out}
    assert all(layer.isValid() for layer in layers.values())
    assert layers["TREE_TOPS"].wkbType() == QgsWkbTypes.PointZ
    assert QgsWkbTypes.geometryType(layers["CROWNS"].wkbType()) == QgsWkbTypes.PolygonGeometry
    assert layers["TREES"].wkbType() == QgsWkbTypes.NoGeometry
    assert [f.name() for f in layers["TREES"].fields()][1:] == TREE_FIELDS  # after the fid
    n = layers["TREES"].featureCount()
    assert n == result["TREE_COUNT"] > 20
    assert layers["TREE_TOPS"].featureCount() == layers["CROWNS"].featureCount() == n
    tree_ids = {f["tree_id"] for f in layers["TREES"].getFeatures()}
    las = laspy.read(result["OUTPUT"])
    labels = np.asarray(las["treeID"])
    assert set(np.unique(labels[labels > 0])) == tree_ids
    assert {f["tree_id"] for f in layers["CROWN_POINTS"].getFeatures()} <= tree_ids
    counts = np.bincount(labels)
    real = []
    for f in layers["TREES"].getFeatures():
        assert f["n_points"] == counts[f["tree_id"]]
        assert f["quality"] == ("sparse" if f["n_points"] < 20 else "ok")   # a small tree is flagged
        assert 0 <= f["crown_base_height"] <= f["height"]
        if f["n_points"] >= 10:  # tiny segments are kept (flagged), but real trees have crowns
            real.append(f["crown_diameter"] > 0 and f["crown_base_height"] < f["height"])
    assert np.mean(real) >= 0.95
    assert layers["CROWN_POINTS"].featureCount() + layers["STEM_POINTS"].featureCount() == int((labels > 0).sum())
    src = laspy.read(sample_laz)
    assert len(las.points) == len(src.points)
    np.testing.assert_array_equal(las.x, src.x)
    assert las.header.parse_crs() == src.header.parse_crs()


def test_normalizeheight_cli(tmp_path, sample_laz):
    out = tmp_path / "norm.laz"
    run = subprocess.run([sys.executable, "-m", "sylva.cli", "normalizeheight", f"--INPUT={sample_laz}",
                          f"--OUTPUT={out}"], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    src, las = laspy.read(sample_laz), laspy.read(out)
    ground = np.asarray(src.classification) == 2
    assert np.abs(np.asarray(las.z)[ground]).max() < 0.05  # ground is at height 0
    np.testing.assert_allclose(np.asarray(las["elevation"]), np.asarray(src.z), atol=1e-6)
    assert np.percentile(np.asarray(las.z)[~ground], 99.9) < 60  # heights, not elevations (noise kept)


def test_segmenttrees_cli_is_deterministic(tmp_path, sample_laz):
    tables = []
    for i in range(2):
        target = tmp_path / f"trees{i}.gpkg"
        run = subprocess.run([sys.executable, "-m", "sylva.cli", "--quiet", "segmenttrees",
                              f"--INPUT={sample_laz}", f"--TREES={target}"], capture_output=True, text=True)
        assert run.returncode == 0, run.stderr
        tables.append(read_gpkg(target, "trees"))
    for name in TREE_FIELDS:
        np.testing.assert_array_equal(tables[0].columns[name], tables[1].columns[name])


@pytest.mark.parametrize("growth", ["forest", "open-grown"])
def test_pipeline_and_segmenttrees_give_the_same_trees(tmp_path, sample_laz, growth):
    """One chain (issue 16): sylva:pipeline and sylva:segmenttrees run segment_tile on the same tile
    and give the same partition of its points into trees (IDs differ: the pipeline's come from
    the tops' positions), with either GROWTH preset."""
    cli = [sys.executable, "-m", "sylva.cli", "--quiet"]
    run = subprocess.run(cli + ["pipeline", f"--INPUT={sample_laz}", f"--OUTPUT_FOLDER={tmp_path / 'pipe'}",
                                "--RECONSTRUCT=false", f"--GROWTH={growth}"], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    seg = tmp_path / "seg.laz"
    run = subprocess.run(cli + ["segmenttrees", f"--INPUT={sample_laz}", f"--OUTPUT={seg}", f"--GROWTH={growth}"],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    a = np.asarray(laspy.read(str(tmp_path / "pipe" / "tiles" / "sample.laz"))["treeID"])
    b = np.asarray(laspy.read(str(seg))["treeID"])
    pairs = np.unique(np.column_stack([a, b]), axis=0)
    assert len(np.unique(a)) == len(np.unique(b)) == len(pairs)   # a bijection of the labels
    # the sample is a forest: the open-grown preset joins its crowns into fewer, wider trees
    assert len(pairs) > 200 if growth == "forest" else 50 < len(pairs) < 200
    assert ((a == 0) == (b == 0)).all()


def test_growth_with_another_method_says_it_is_ignored(tmp_path, sample_laz):
    """GROWTH shapes the normalised cut only: a run of METHOD chm with GROWTH open-grown says so in one line,
    a run of the normalised cut does not."""
    said = []
    for method in ("chm", "ncut"):
        run = subprocess.run([sys.executable, "-m", "sylva.cli", "segmenttrees", f"--INPUT={sample_laz}",
                              f"--METHOD={method}", "--GROWTH=open-grown", f"--TREES={tmp_path / method}.gpkg"],
                             capture_output=True, text=True)
        assert run.returncode == 0, run.stderr
        said.append([line for line in (run.stdout + run.stderr).splitlines() if "GROWTH" in line])
    assert said[0] == ["GROWTH open-grown shapes the normalised cut (METHOD ncut) only; METHOD chm ignores it"]
    assert said[1] == []
