"""sylva:pipeline as an algorithm, and the single-tile Graphical Modeler model run by qgis_process."""
import json
import os
from pathlib import Path

import numpy as np
import pytest
import shapely

from conftest import ROOT, qgis_process

MODEL = ROOT / "resources" / "models" / "sylva_single_tile.model3"
CHAIN = ["normalise", "segment", "reconstruct", "export"]


def small_tiles(sample: Path, folder: Path, size_m=36.0, n=2) -> Path:
    """An n x n tiling of a size_m square cut out of the bundled sample (a handful of trees per tile)."""
    from sylva.core.io.las import read_las, write_las

    folder.mkdir(parents=True, exist_ok=True)
    cloud = read_las(sample)
    x0, y0 = cloud.xyz[:, 0].min() + 30.0, cloud.xyz[:, 1].min() + 30.0
    step = size_m / n
    for i in range(n):
        for j in range(n):
            x, y = cloud.xyz[:, 0], cloud.xyz[:, 1]
            m = (x >= x0 + i * step) & (x < x0 + (i + 1) * step) & (y >= y0 + j * step) & (y < y0 + (j + 1) * step)
            write_las(folder / f"s_{i}_{j}.laz", cloud.subset(m))
    return folder


def test_pipeline_algorithm_writes_the_whole_forest(sample_laz, tmp_path):
    from sylva.algorithms import get
    from sylva.algorithms.spec import Feedback
    from sylva.core.export.gltf import read_glb
    from sylva.core.io.gpkg import read_gpkg

    tiles = small_tiles(sample_laz, tmp_path / "tiles")
    alg = get("sylva:pipeline")
    args = {p.name: p.default for p in alg.params}
    messages = []

    class Fb(Feedback):
        def info(self, message):
            messages.append(message)

    args.update(INPUT=str(tiles), OUTPUT_FOLDER=str(tmp_path / "out"), WORKERS=2)
    result = alg.run(args, Fb())
    out = tmp_path / "out"
    n = result.values["TREE_COUNT"]
    assert result.values["TILE_COUNT"] == 4 and result.values["FAILED_TILES"] == 0 and n >= 5
    trees = read_gpkg(out / "forest.gpkg", "trees")
    assert len(trees) == n and len(np.unique(trees.columns["tree_id"])) == n
    assert {"dbh", "method", "model_file", "tile"} <= set(trees.columns)
    assert len(read_gpkg(out / "forest.gpkg", "skeletons")) == n
    assert len(read_gpkg(out / "forest.gpkg", "crowns")) == n
    assert len(read_gpkg(out / "forest.gpkg", "models_3d")) == n
    crowns = read_gpkg(out / "forest.gpkg", "crowns_3d")      # one crown envelope a tree, across the tiles
    assert sorted(crowns.columns["tree_id"]) == sorted(trees.columns["tree_id"])
    assert all(g is not None for g in crowns.geometries) and crowns.columns["n_triangles"].max() <= 82
    from test_export_algorithm import _closed_outward_containing

    tops = read_gpkg(out / "forest.gpkg", "tree_tops")
    top_of = dict(zip(tops.columns["tree_id"].tolist(), shapely.get_coordinates(tops.geometries, include_z=True)))
    for tree_id, g in zip(crowns.columns["tree_id"].tolist(), crowns.geometries):   # closed, over the tree's top
        tri = np.array([shapely.get_coordinates(p, include_z=True)[:3] for p in g.geoms])
        vertices, faces = np.unique(tri.reshape(-1, 3), axis=0, return_inverse=True)
        assert _closed_outward_containing(vertices, faces.reshape(-1, 3), top_of[tree_id])
    # per-tile GLBs hold every owned tree once; the run's tileset points at every tile's tileset
    names = []
    for glb in sorted((out / "models").glob("*.glb")):
        doc, _ = read_glb(glb)
        names += [nd["name"] for nd in doc["nodes"] if nd.get("name", "").startswith("tree_")]
    assert sorted(names) == sorted(f"tree_{t}" for t in trees.columns["tree_id"])
    root = json.loads((out / "models" / "tileset.json").read_text())
    kids = [c["content"]["uri"] for c in root["root"]["children"]]
    assert len(kids) == len(list((out / "models").glob("*.glb")))
    assert all((out / "models" / k).exists() for k in kids)
    assert any("trees" in m and "points/s" in m for m in messages)


def build_model(with_export: bool):
    """The shipped model, built with the QGIS API: normalise -> segment -> reconstruct (-> export)."""
    from qgis.core import (QgsProcessingModelAlgorithm, QgsProcessingModelChildAlgorithm,
                           QgsProcessingModelChildParameterSource as Src, QgsProcessingModelOutput,
                           QgsProcessingModelParameter, QgsProcessingParameterFile)

    model = QgsProcessingModelAlgorithm("Single tile: normalise, segment, reconstruct, export", "Sylva",
                                        "sylvamodels")
    model.setHelpContent({"ALG_DESC": "One LiDAR tile through the Sylva chain, one step at a time: "
                                      "normalise heights, segment trees, reconstruct 3D models"
                                      + (" and export them as 3D Tiles." if with_export else ".")
                                      + " Open it in the Graphical Modeler to change any step's parameters."})
    model.addModelParameter(QgsProcessingParameterFile("tile", "LiDAR tile (LAS/LAZ)",
                                                       fileFilter="LAS/LAZ (*.las *.laz)"),
                            QgsProcessingModelParameter("tile"))

    def child(alg_id, child_id, sources, outputs):
        from sylva.algorithms import get

        c = QgsProcessingModelChildAlgorithm(alg_id)
        c.setChildId(child_id)
        c.setDescription(child_id)
        for p in get(alg_id).inputs:                   # every parameter at Sylva's default, editable
            if p.name in sources or p.default is None:
                continue
            value = p.options.index(p.default) if p.kind == "enum" else p.default
            c.addParameterSources(p.name, [Src.fromStaticValue(value)])
        for name, src in sources.items():
            c.addParameterSources(name, [src])
        outs = {}
        for out_name, model_name in outputs.items():
            o = QgsProcessingModelOutput(model_name)
            o.setChildId(child_id)
            o.setChildOutputName(out_name)
            outs[model_name] = o
        c.setModelOutputs(outs)
        model.addChildAlgorithm(c)
        return c

    child("sylva:normalizeheight", "normalise", {"INPUT": Src.fromModelParameter("tile")}, {})
    child("sylva:segmenttrees", "segment", {"INPUT": Src.fromChildOutput("normalise", "OUTPUT")},
          {"OUTPUT": "segmented", "CROWNS": "crowns", "TREE_TOPS": "tree_tops"})
    child("sylva:reconstructtrees", "reconstruct", {"INPUT": Src.fromChildOutput("segment", "OUTPUT")},
          {"MODELS": "models", "TREES": "trees", "SKELETONS": "skeletons"})
    if with_export:
        child("sylva:exportmodels", "export", {"INPUT": Src.fromChildOutput("reconstruct", "MODELS")},
              {"TILES": "tiles_3d"})
    model.updateDestinationParameters()
    return model


@pytest.mark.qgis
def test_shipped_model_is_the_chain(sylva_provider, tmp_path):
    from qgis.core import QgsApplication, QgsProcessingModelAlgorithm

    has_export = QgsApplication.processingRegistry().algorithmById("sylva:exportmodels") is not None
    if os.environ.get("SYLVA_REBUILD_MODEL"):      # regenerate the shipped file from build_model
        assert build_model(has_export).toFile(str(MODEL))
    model = QgsProcessingModelAlgorithm()
    assert model.fromFile(str(MODEL))
    children = model.childAlgorithms()
    chain = CHAIN if "export" in children else CHAIN[:3]
    assert sorted(children) == sorted(chain)
    assert [children[c].algorithmId() for c in chain] == [
        "sylva:normalizeheight", "sylva:segmenttrees", "sylva:reconstructtrees", "sylva:exportmodels"][:len(chain)]
    for up, down in zip(chain, chain[1:]):                 # each step reads the previous one's output
        (src,) = children[down].parameterSources()["INPUT"]
        assert src.outputChildId() == up
    ok, issues = model.validate()
    assert ok, issues


@pytest.mark.qgis
def test_a_graph_saved_before_a_later_parameter_still_validates(sylva_provider, tmp_path):
    """UNDERSTORY_POINTS, TOP_WINDOW_CROWN and CLOSED_WINDOW came after graphs were saved: a graph with no
    value for them validates."""
    import xml.etree.ElementTree as ET

    from qgis.core import QgsProcessingModelAlgorithm

    tree = ET.parse(MODEL)
    for parent in tree.iter():
        later = ("UNDERSTORY_POINTS", "TOP_WINDOW_CROWN", "CLOSED_WINDOW")
        for option in [o for o in parent if o.get("name") in later]:
            parent.remove(option)
    tree.write(tmp_path / "old.model3")
    model = QgsProcessingModelAlgorithm()
    assert model.fromFile(str(tmp_path / "old.model3"))
    assert "segment" in model.childAlgorithms()
    ok, issues = model.validate()
    assert ok, issues


@pytest.mark.qgis
def test_model_runs_with_qgis_process(sample_laz, tmp_path):
    from sylva.core.io.gpkg import read_gpkg
    from sylva.core.io.las import read_las

    tile = sorted(small_tiles(sample_laz, tmp_path / "tiles", size_m=24.0, n=1).glob("*.laz"))[0]
    out = tmp_path / "out"
    out.mkdir()
    args = ["run", str(MODEL), f"--tile={tile}", f"--segment:segmented={out / 'seg.laz'}",
            f"--segment:crowns={out / 'crowns.gpkg'}", f"--segment:tree_tops={out / 'tops.gpkg'}",
            f"--reconstruct:models={out / 'trees.glb'}", f"--reconstruct:trees={out / 'trees.gpkg'}",
            f"--reconstruct:skeletons={out / 'skel.gpkg'}"]
    if "exportmodels" in MODEL.read_text():
        args.append(f"--export:tiles_3d={out / 'tiles3d'}")
    res = qgis_process(*args)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    seg = read_las(out / "seg.laz")
    ids = np.unique(np.asarray(seg.attrs["treeID"]))
    trees = read_gpkg(out / "trees.gpkg", "trees")
    assert len(trees) >= 2 and set(trees.columns["tree_id"]) == set(ids[ids > 0])
    assert (out / "trees.glb").stat().st_size > 1000
    if "exportmodels" in MODEL.read_text():
        assert (out / "tiles3d" / "tileset.json").exists()
