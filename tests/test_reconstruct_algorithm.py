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


@pytest.fixture(scope="module")
def segmented_corner(sample_laz, tmp_path_factory):
    """A 40 m x 40 m corner of the sample, segmented, written with a treeID dimension."""
    from conftest import segmented_corner_of

    return segmented_corner_of(sample_laz, tmp_path_factory.mktemp("seg"), 40.0)


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
    assert set(trees.columns["quality"]) <= {"ok", "fallback", "sparse", "noise"}
    n_points = np.bincount(labels[labels > 0])[trees.columns["tree_id"]]
    assert np.array_equal(trees.columns["quality"] == "sparse", (n_points >= 10) & (n_points < 20))
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


# --------------------------------------------------------------------------- QSM outputs (dense trees)

PSI = [  # trunk 30 cm at the base tapering to 16 cm at 4 m, two side branches
    dict(start=(0, 0, 0), direction=(0, 0, 1), length=4.0, radius=(0.15, 0.08), parent=-1, n=8),
    dict(start=(0, 0, 2.0), direction=(1, 0, 0.8), length=1.6, radius=(0.05, 0.03), parent=0, n=4),
    dict(start=(0, 0, 2.6), direction=(-0.7, 0.5, 0.8), length=1.4, radius=(0.05, 0.03), parent=0, n=4),
]
OFFSET = np.array([500000.0, 5500000.0, 100.0])


@pytest.fixture(scope="module")
def dense_and_sparse(tmp_path_factory):
    """A LAS with treeID: tree 1 a densely scanned cylinder tree (known truth), tree 2 a sparse
    airborne-like crown, and class-2 ground at z = 100 m (UTM 32N)."""
    from pyproj import CRS

    from sylva.core.cloud import PointCloud
    from sylva.testing.cylinders import cylinder_tree, sample_cylinder_surfaces

    truth = cylinder_tree(PSI)
    pts = sample_cylinder_surfaces(truth, spacing_m=0.02, noise_m=0.002, seed=3)
    rng = np.random.default_rng(1)
    u = rng.uniform(size=(800, 3))
    r, a = 2.0 * np.sqrt(u[:, 0]) * (1 - u[:, 2]), 2 * np.pi * u[:, 1]
    crown = np.c_[10 + r * np.cos(a), r * np.sin(a), 4 + 6 * u[:, 2]]
    g = np.stack(np.meshgrid(np.arange(-3, 14, 0.5), np.arange(-4, 4, 0.5)), -1).reshape(-1, 2)
    ground = np.c_[g, np.zeros(len(g))]
    xyz = np.vstack([pts, crown, ground]) + OFFSET
    tid = np.r_[np.full(len(pts), 1), np.full(len(crown), 2), np.zeros(len(ground))].astype(np.int32)
    cls = np.r_[np.ones(len(pts) + len(crown)), np.full(len(ground), 2)].astype(np.uint8)
    path = tmp_path_factory.mktemp("dense") / "dense.las"
    write_las(path, PointCloud(xyz, {"classification": cls}, CRS.from_epsg(32632)), extra={"treeID": tid})
    vol = np.pi * truth["radius"] ** 2 * truth["length"]
    trunk = truth["branch"] == 0
    i = np.flatnonzero(trunk & (truth["start"][:, 2] <= 1.3))[-1]
    return path, dict(dbh=2 * truth["radius"][i], total=vol.sum(), trunk=vol[trunk].sum(), height=4.0)


def _check_qsm_outputs(trees, cyl, br, tcsv, ccsv, bcsv, truth):
    t1 = {k: trees.columns[k][list(trees.columns["tree_id"]).index(1)] for k in trees.columns}
    t2 = {k: trees.columns[k][list(trees.columns["tree_id"]).index(2)] for k in trees.columns}
    assert t1["method"] == "level_set_qsm" and t1["qsm_method"] == "fitted_cylinders"
    assert t2["method"] in ("greedy_skeleton", "guided_growth") and t2["qsm_method"] == "skeleton_edges"
    assert t1["dbh_source"] == "measured" and abs(t1["dbh"] - truth["dbh"]) < 0.01     # within 1 cm
    assert t1["total_volume"] == pytest.approx(truth["total"], rel=0.05)      # within 5 %
    assert t1["trunk_volume"] == pytest.approx(truth["trunk"], rel=0.05)
    assert t1["n_branches_order_1"] == 2 and t1["n_branches_order_2"] == 0
    assert t2["total_volume"] > 0 and t2["n_cylinders"] > 10
    # cylinders: 3-D lines in the CRS, start at the stated coordinates, the fields of the issue
    for name in ("tree_id", "id", "parent", "branch", "order", "start_x", "start_y", "start_z",
                 "axis_x", "axis_y", "axis_z", "length", "radius"):
        assert name in cyl.columns, name
    c = cyl.columns
    one = c["tree_id"] == 1
    assert set(np.unique(c["tree_id"])) == {1, 2}
    g = cyl.geometries[np.flatnonzero(one)[0]]
    start = np.asarray(g.geoms[0].coords[0] if hasattr(g, "geoms") else g.coords[0])
    assert start == pytest.approx([c["start_x"][one][0], c["start_y"][one][0], c["start_z"][one][0]], abs=1e-3)
    assert abs(start[0] - OFFSET[0]) < 0.2 and abs(start[2] - OFFSET[2]) < 0.3
    vol = np.pi * c["radius"][one] ** 2 * c["length"][one]
    assert vol.sum() == pytest.approx(t1["total_volume"], rel=1e-3)   # layers keep 4 significant digits
    stem = one & (c["branch"] == 0)
    assert c["length"][stem].sum() == pytest.approx(truth["height"], abs=0.3)
    assert np.all(c["parent"][one][1:] >= 0) and c["parent"][one][0] == -1
    b = br.columns
    assert sorted(b["order"][b["tree_id"] == 1].tolist()) == [0, 1, 1]
    # CSVs: same rows as the layers
    import csv
    rows = list(csv.DictReader(open(tcsv)))
    r1 = next(r for r in rows if r["tree_id"] == "1")
    assert float(r1["dbh_m"]) == pytest.approx(t1["dbh"], rel=1e-3)   # layer: 4 digits
    assert float(r1["total_volume_m3"]) == pytest.approx(t1["total_volume"], rel=1e-3)   # layer: 4 digits
    assert r1["qsm_method"] == "fitted_cylinders" and r1["dbh_source"] == "measured"
    crow = list(csv.DictReader(open(ccsv)))
    assert len(crow) == len(cyl)
    assert sum(float(r["radius"]) ** 2 * float(r["length"]) * np.pi for r in crow
               if r["tree_id"] == "1") == pytest.approx(t1["total_volume"], rel=1e-3)
    assert len(list(csv.DictReader(open(bcsv)))) == len(br)


def test_dense_tree_qsm_outputs_from_the_cli(dense_and_sparse, tmp_path):
    path, truth = dense_and_sparse
    out = tmp_path / "qsm"
    run = subprocess.run([sys.executable, "-m", "sylva.cli", "--quiet", "reconstructtrees", f"--INPUT={path}",
                          "--METHOD=auto", f"--TREES={tmp_path / 'trees.gpkg'}",
                          f"--SKELETONS={tmp_path / 'sk.gpkg'}", f"--CYLINDERS={tmp_path / 'cyl.gpkg'}",
                          f"--BRANCHES={tmp_path / 'br.gpkg'}", f"--QSM_FOLDER={out}"],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    trees = read_gpkg(tmp_path / "trees.gpkg", "trees")
    cyl = read_gpkg(tmp_path / "cyl.gpkg", "cylinders")
    br = read_gpkg(tmp_path / "br.gpkg", "branches")
    assert cyl.crs is not None and cyl.crs.to_epsg() == 32632
    _check_qsm_outputs(trees, cyl, br, out / "trees.csv", out / "cylinders.csv", out / "branches.csv", truth)


@pytest.mark.qgis
def test_dense_tree_qsm_layers_in_qgis(sylva_provider, dense_and_sparse, tmp_path):
    import processing
    from qgis.core import QgsVectorLayer, QgsWkbTypes

    path, truth = dense_and_sparse
    result = processing.run("sylva:reconstructtrees", {
        "INPUT": str(path), "METHOD": 4, "SKELETONS": str(tmp_path / "sk.gpkg"),
        "TREES": str(tmp_path / "trees.gpkg"), "CYLINDERS": str(tmp_path / "cyl.gpkg"),
        "BRANCHES": str(tmp_path / "br.gpkg"), "QSM_FOLDER": str(tmp_path / "qsm")})
    layer = QgsVectorLayer(result["CYLINDERS"], "cyl", "ogr")
    assert layer.isValid() and QgsWkbTypes.hasZ(layer.wkbType())
    assert QgsWkbTypes.geometryType(layer.wkbType()) == QgsWkbTypes.LineGeometry
    feats = list(layer.getFeatures())
    r1 = [f for f in feats if f["tree_id"] == 1]
    vol = sum(np.pi * f["radius"] ** 2 * f["length"] for f in r1)
    assert vol == pytest.approx(truth["total"], rel=0.05)
    v = next(r1[0].geometry().vertices())
    assert v.x() == pytest.approx(r1[0]["start_x"], abs=1e-3) and v.z() == pytest.approx(r1[0]["start_z"], abs=1e-3)
    branches = QgsVectorLayer(result["BRANCHES"], "br", "ogr")
    assert branches.isValid() and branches.featureCount() == sum(1 for _ in open(tmp_path / "qsm" / "branches.csv")) - 1
    trees = {f["tree_id"]: f for f in QgsVectorLayer(result["TREES"], "trees", "ogr").getFeatures()}
    assert trees[1]["dbh_source"] == "measured" and abs(trees[1]["dbh"] - truth["dbh"]) < 0.01
    assert (tmp_path / "qsm" / "cylinders.csv").exists() and (tmp_path / "qsm" / "trees.csv").exists()


def test_completed_crowns_add_small_branches_inside_the_crown(segmented_corner, tmp_path):
    """METHOD completed: the hybrid skeleton plus the sketch paper's self-similar small branches."""
    path, labels = segmented_corner
    out = {}
    for method in ("hybrid", "completed"):
        run = subprocess.run([sys.executable, "-m", "sylva.cli", "--quiet", "reconstructtrees", f"--INPUT={path}",
                              f"--METHOD={method}", f"--TREES={tmp_path / f'{method}.gpkg'}"],
                             capture_output=True, text=True)
        assert run.returncode == 0, run.stderr
        out[method] = read_gpkg(tmp_path / f"{method}.gpkg", "trees").columns
    plain, full = out["hybrid"], out["completed"]
    assert np.array_equal(plain["tree_id"], full["tree_id"])
    ok = plain["quality"] != "noise"
    more = full["total_branch_length"][ok] > plain["total_branch_length"][ok] + 1e-9
    assert more.mean() > 0.5                     # most trees gain small branches
    assert np.all(full["total_branch_length"][ok] >= plain["total_branch_length"][ok] - 1e-9)
    completed = full["method"] == "sketch_completion"   # the others were too small to complete
    assert completed[ok].mean() > 0.5 and set(full["method"][~completed]) <= {"greedy_skeleton", "guided_growth"}
