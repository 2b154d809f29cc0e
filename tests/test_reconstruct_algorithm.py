"""sylva:reconstructtrees end to end: every segmented tree gets a model, in QGIS and from the CLI."""
import json
import subprocess
import sys

import numpy as np
import pytest

from sylva.core.export.georef import Georef
from sylva.core.export.gltf import node_world_positions, read_glb
from sylva.core.export.model import ExportFrame
from sylva.core.io import read_cloud
from sylva.core.io.gpkg import read_gpkg
from sylva.core.io.las import write_las
from sylva.core.segment import segment_trees
from sylva.core.terrain import normalize


@pytest.fixture(scope="module")
def segmented_corner(sample_laz, tmp_path_factory):
    """A 40 m x 40 m corner of the sample, segmented, written with a treeID dimension."""
    cloud = read_cloud(sample_laz)
    x0, y0 = cloud.xyz[:, 0].min(), cloud.xyz[:, 1].min()
    corner = cloud.subset((cloud.xyz[:, 0] < x0 + 40) & (cloud.xyz[:, 1] < y0 + 40))
    labels = segment_trees(normalize(corner))
    path = tmp_path_factory.mktemp("seg") / "corner.laz"
    write_las(path, corner, extra={"treeID": labels})
    return path, labels


def test_every_tree_gets_a_model(segmented_corner, tmp_path):
    path, labels = segmented_corner
    glb = tmp_path / "trees.glb"
    run = subprocess.run([sys.executable, "-m", "sylva.cli", "--quiet", "reconstructtrees", f"--INPUT={path}",
                          f"--MODELS={glb}", f"--TREES={tmp_path / 'trees.gpkg'}",
                          f"--SKELETONS={tmp_path / 'sk.gpkg'}"], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    trees = read_gpkg(tmp_path / "trees.gpkg", "trees")
    ids = set(np.unique(labels[labels > 0]))
    assert set(trees.columns["tree_id"]) == ids  # none dropped
    assert set(trees.columns["method"]) <= {"greedy_skeleton", "guided_growth"}
    assert set(trees.columns["quality"]) <= {"ok", "fallback", "noise"}
    ok = trees.columns["quality"] != "noise"
    assert np.all(trees.columns["wood_volume"][ok] > 0) and np.all(trees.columns["dbh"][ok] > 0.02)
    assert set(trees.columns["dbh_source"]) <= {"measured", "allometric"}
    # the GLB holds one named node per tree, whose lowest vertex is the tree's base in the table
    doc, binary = read_glb(glb)
    names = {n.get("name") for n in doc["nodes"]}
    assert {f"tree_{i}" for i in ids} <= names
    origin = json.loads(glb.with_name("trees.origin.json").read_text())
    cloud = read_cloud(path)
    georef = Georef(ExportFrame.from_cloud(cloud), origin["origin_source"])
    for k in range(len(trees)):
        enu = node_world_positions(doc, binary, f"tree_{trees.columns['tree_id'][k]}")
        src = georef.enu_to_source(enu)
        base = np.array([trees.columns[c][k] for c in ("base_x", "base_y", "base_z")])
        nearest = np.abs(src - base).max(axis=1).min()
        assert nearest < 0.05  # the stem's first ring surrounds the base within its radius
    sk = read_gpkg(tmp_path / "sk.gpkg", "skeletons")
    assert len(sk) == len(trees)


@pytest.mark.qgis
def test_skeletons_open_in_qgis_with_radius_as_m(sylva_provider, segmented_corner, tmp_path):
    import processing
    from qgis.core import QgsVectorLayer, QgsWkbTypes

    path, labels = segmented_corner
    result = processing.run("sylva:reconstructtrees", {
        "INPUT": str(path), "METHOD": 0, "SKELETONS": str(tmp_path / "sk.gpkg"),
        "TREES": str(tmp_path / "trees.gpkg")})
    layer = QgsVectorLayer(result["SKELETONS"], "sk", "ogr")
    assert layer.isValid() and layer.wkbType() == QgsWkbTypes.MultiLineStringZM
    radii = [v.m() for f in layer.getFeatures() for v in f.geometry().vertices()]
    assert len(radii) > 100 and min(radii) > 0 and max(radii) < 1.0
    trees = QgsVectorLayer(result["TREES"], "trees", "ogr")
    assert trees.featureCount() == len(np.unique(labels[labels > 0]))


def test_untagged_tile_is_refused(sample_laz, tmp_path):
    run = subprocess.run([sys.executable, "-m", "sylva.cli", "reconstructtrees", f"--INPUT={sample_laz}",
                          f"--TREES={tmp_path / 't.gpkg'}"], capture_output=True, text=True)
    assert run.returncode == 1 and "treeID" in run.stderr and "Traceback" not in run.stderr


def test_a_tree_cut_by_the_tile_edge_still_gets_a_model():
    """Half a crown (the other half beyond the tile edge) and no stem points: a model, not a crash."""
    from sylva.core.reconstruct import TreePoints, reconstruct_tree

    rng = np.random.default_rng(5)
    u = rng.uniform(size=(600, 3))
    r = 3.0 * np.sqrt(u[:, 0]) * (1 - u[:, 2])
    a = np.pi * u[:, 1] - np.pi / 2          # only the half with x >= 0
    crown = np.column_stack([r * np.cos(a), r * np.sin(a), 8 + 10 * u[:, 2]])
    rec = reconstruct_tree(TreePoints(9, crown, 0.0))
    sk = rec.skeleton
    assert len(sk) > 5 and sk.nodes[sk.root, 2] == pytest.approx(0.0, abs=0.3)
    assert sk.nodes[:, 2].max() > 15
    assert (sk.distance(crown) < 0.5).mean() > 0.8
