"""sylva:exportmodels: a Sylva GLB read back, written as GLB/3D Tiles/CityGML/OBJ and as a QGIS 3D layer."""
import json
import subprocess
import sys

import numpy as np
import pytest
import shapely
from scipy.spatial import cKDTree

from sylva.algorithms import get
from sylva.algorithms.spec import Feedback
from sylva.core.errors import CRSError, EmptyInputError, InputError
from sylva.core.export.gltf import _pack_glb, read_glb, write_glb
from sylva.core.export.gpkg3d import MIN_TRIANGLE_AREA_M2, attribute_columns, models_table
from sylva.core.export.model import ExportFrame, TreeModel
from sylva.core.export.read import read_models
from sylva.core.io import read_cloud
from sylva.core.io.gpkg import read_gpkg, write_gpkg


def _args(alg, **values):
    args = {p.name: p.default for p in alg.params}
    for p in alg.outputs:
        args[p.name] = None
    args.update(values)
    return args


@pytest.fixture(scope="module")
def modelled(sample_laz, tmp_path_factory):
    """A 30 m x 30 m corner of the sample: segmented, reconstructed (LOD 0) and written as a GLB.

    Returns (glb path, the TreeModels that were written, their frame).
    """
    from sylva.core.forest import ModelOptions, model_trees
    from sylva.core.measure import tree_metrics
    from sylva.core.segment import segment_trees
    from sylva.core.terrain import normalize

    cloud = read_cloud(sample_laz)
    x0, y0 = cloud.xyz[:, 0].min(), cloud.xyz[:, 1].min()
    corner = normalize(cloud.subset((cloud.xyz[:, 0] < x0 + 30) & (cloud.xyz[:, 1] < y0 + 30)))
    labels = segment_trees(corner)
    metrics = tree_metrics(corner, labels)
    trees = model_trees(corner, labels, metrics, ModelOptions(lod=0))
    models = [TreeModel(t.tree_id, [t.record["base_x"], t.record["base_y"], t.record["base_z"]], t.wood, t.leaves,
                        {**t.record, "height": float(metrics.height[k]), "species": None if k % 3 else "Picea"})
              for k, t in enumerate(trees)]
    frame = ExportFrame.from_cloud(corner)
    glb = tmp_path_factory.mktemp("models") / "trees.glb"
    write_glb(models, glb, frame)
    return glb, models, frame


def test_read_models_round_trip(modelled):
    glb, models, frame = modelled
    back, back_frame = read_models(glb)
    assert back_frame.pyproj_crs().to_epsg() == frame.pyproj_crs().to_epsg() == 32632
    assert back_frame.resolved_units() == frame.resolved_units()
    assert [m.tree_id for m in back] == [m.tree_id for m in models]
    for m, b in zip(models, back):
        np.testing.assert_allclose(b.base, m.base, atol=1e-6)       # source CRS, metres
        wv, wf = m.wood_arrays()
        used = np.unique(wf)                                         # the writer drops unused vertices
        bv, bf = b.wood_arrays()
        np.testing.assert_allclose(bv, wv[used], atol=2e-5)          # float32 in the GLB
        np.testing.assert_array_equal(bf, np.searchsorted(used, wf))
        lv, lf, luv = m.leaf_arrays()
        blv, blf, bluv = b.leaf_arrays()
        assert len(blf) == len(lf) > 0
        np.testing.assert_allclose(blv, lv[np.unique(lf)], atol=2e-5)
        np.testing.assert_allclose(bluv, luv[np.unique(lf)], atol=1e-6)
        assert b.leaves.texture == m.leaves.texture
        assert b.attributes["dbh"] == pytest.approx(m.attributes["dbh"])
        assert b.attributes["species"] == m.attributes["species"]
        assert b.attributes["method"] == m.attributes["method"]


def test_models_3d_layer_is_the_wood_in_source_crs(modelled, tmp_path):
    glb, models, frame = modelled
    back, back_frame = read_models(glb)
    table = models_table(back, back_frame)
    assert table.geometry_type == "polygon" and table.has_z and len(table) == len(models)
    assert list(table.columns)[0] == "tree_id"
    np.testing.assert_array_equal(table.columns["tree_id"], [m.tree_id for m in models])
    assert table.wkb and table.extent is not None
    for k, m in enumerate(models):
        g = shapely.from_wkb(table.geometries[k])
        assert g.geom_type == "MultiPolygon" and g.has_z
        wv, wf = m.wood_arrays()
        tri = wv[wf]
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        assert table.columns["n_triangles"][k] == len(g.geoms) == int((area >= MIN_TRIANGLE_AREA_M2).sum()) > 0
        coords = shapely.get_coordinates(g, include_z=True)
        expected = m.base + wv[np.unique(wf)]                         # metres: the CRS is in metres
        # every corner is a vertex of the wood mesh placed at the base, to float32 precision
        d, _ = cKDTree(expected).query(coords)
        assert d.max() < 1e-4
        assert coords[:, 2].min() == pytest.approx(m.base[2] + wv[:, 2].min(), abs=1e-4)
    assert table.columns["dbh"].dtype == np.float64 and table.columns["species"].dtype == object
    path = write_gpkg(tmp_path / "m.gpkg", [table])
    again = read_gpkg(path, "models_3d")
    assert len(again) == len(models)
    assert shapely.equals_exact(again.geometries[0], shapely.from_wkb(table.geometries[0]), tolerance=1e-9)
    whole = shapely.total_bounds(shapely.from_wkb(table.geometries))
    np.testing.assert_allclose(table.extent, whole, atol=1e-9)


def test_leaves_option_adds_the_cards(modelled):
    glb, models, frame = modelled
    back, fr = read_models(glb)
    wood_only = models_table(back[:2], fr).columns["n_triangles"]
    with_leaves = models_table(back[:2], fr, leaves=True).columns["n_triangles"]
    assert np.all(with_leaves - wood_only == [len(m.leaf_arrays()[1]) for m in back[:2]])


def test_attribute_columns_types():
    cols = attribute_columns([{"a": 1, "b": 2.5, "c": "x", "d": True},
                              {"a": 3, "b": None, "c": None, "d": False, "e": 7}])
    assert cols["a"].dtype == np.int64 and cols["d"].dtype == np.int64
    assert cols["b"].dtype == np.float64 and np.isnan(cols["b"][1])
    assert list(cols["c"]) == ["x", None]
    assert cols["e"].dtype == np.float64 and np.isnan(cols["e"][0])   # missing int -> real with NaN


def test_cli_writes_every_format(modelled, tmp_path):
    glb, models, _ = modelled
    out = tmp_path
    run = subprocess.run(
        [sys.executable, "-m", "sylva.cli", "--quiet", "exportmodels", f"--INPUT={glb}",
         f"--GLB_FOLDER={out / 'glbs'}", f"--TILES={out / 'tiles'}", f"--CITYGML={out / 'trees.gml'}",
         "--VERSION=3.0", "--IMPLICIT=true", f"--OBJ={out / 'trees.obj'}", f"--MODELS_3D={out / 'm3d.gpkg'}"],
        capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    ids = [m.tree_id for m in models]
    assert sorted(p.name for p in (out / "glbs").glob("*.glb")) == sorted(f"tree_{i}.glb" for i in ids)
    # a per-tree GLB reads back as that one tree, its origin at the base
    one, _ = read_models(out / "glbs" / f"tree_{ids[0]}.glb")
    assert [m.tree_id for m in one] == [ids[0]]
    np.testing.assert_allclose(one[0].base, models[0].base, atol=1e-6)
    tileset = json.loads((out / "tiles" / "tileset.json").read_text())
    assert tileset["asset"]["version"] == "1.1" and tileset["extras"]["trees"] == len(models)
    gml = (out / "trees.gml").read_text()
    assert "http://www.opengis.net/citygml/3.0" in gml and "ImplicitGeometry" in gml
    assert gml.count("<veg:SolitaryVegetationObject") == len(models)
    obj = (out / "trees.obj").read_text()
    assert sorted(int(line.split("_")[1]) for line in obj.splitlines() if line.startswith("o ")) == sorted(ids)
    layer = read_gpkg(out / "m3d.gpkg", "models_3d")
    np.testing.assert_array_equal(layer.columns["tree_id"], ids)
    assert "TREE_COUNT: %d" % len(models) in run.stdout


def test_deterministic(modelled):
    glb, _, _ = modelled
    alg = get("exportmodels")
    a = alg.run(_args(alg, INPUT=str(glb)), Feedback()).vectors["MODELS_3D"]
    b = alg.run(_args(alg, INPUT=str(glb)), Feedback()).vectors["MODELS_3D"]
    assert a.wkb and list(a.geometries) == list(b.geometries)


def test_not_a_sylva_glb(tmp_path):
    path = tmp_path / "other.glb"
    path.write_bytes(_pack_glb({"asset": {"version": "2.0"}, "nodes": [{"name": "tree_1", "mesh": 0}]}, b""))
    with pytest.raises(InputError, match="has no Sylva georeferencing"):
        read_models(path)
    alg = get("exportmodels")
    with pytest.raises(InputError, match="has no Sylva georeferencing"):
        alg.run(_args(alg, INPUT=str(path)), Feedback())
    (tmp_path / "text.glb").write_text("hello")
    with pytest.raises(InputError, match="not a glTF 2.0 binary"):
        read_models(tmp_path / "text.glb")
    with pytest.raises(InputError, match="file not found"):
        read_models(tmp_path / "missing.glb")


def test_no_trees(modelled, tmp_path):
    glb, _, _ = modelled
    doc, _ = read_glb(glb)
    empty = tmp_path / "empty.glb"
    empty.write_bytes(_pack_glb({"asset": doc["asset"], "nodes": [{"name": "sylva_root"}]}, b""))
    with pytest.raises(EmptyInputError, match="holds no tree models"):
        read_models(empty)
    with pytest.raises(InputError, match="no trees to write"):
        models_table([], ExportFrame("EPSG:32632"))


def test_local_crs_refuses_3d_tiles_and_writes_nothing(modelled, tmp_path):
    _, models, _ = modelled
    local = tmp_path / "local.glb"
    write_glb(models[:3], local, ExportFrame(crs=None))
    back, frame = read_models(local)
    assert frame.crs is None and len(back) == 3
    np.testing.assert_allclose(back[0].base, models[0].base, atol=1e-9)
    alg = get("exportmodels")
    with pytest.raises(CRSError, match="no geodetic datum"):
        alg.run(_args(alg, INPUT=str(local), TILES=str(tmp_path / "tiles"), OBJ=str(tmp_path / "t.obj")),
                Feedback())
    assert not (tmp_path / "tiles").exists() and not (tmp_path / "t.obj").exists()
    # without the tileset the local frame is fine
    result = alg.run(_args(alg, INPUT=str(local), OBJ=str(tmp_path / "t.obj")), Feedback())
    assert (tmp_path / "t.obj").exists() and len(result.vectors["MODELS_3D"]) == 3


# ---------------------------------------------------------------------------- QGIS

def _init_3d():  # QGIS desktop registers the 3D renderers at start; a bare QgsApplication does not
    from qgis.core import QgsApplication

    if QgsApplication.renderer3DRegistry().rendererMetadata("vector") is None:
        from qgis._3d import Qgs3D

        Qgs3D.initialize()


def test_qgis_output_loads_with_its_3d_style(sylva_provider, modelled):
    """Run as the QGIS GUI does (output to load into the project), then apply the post-processor it finds."""
    from qgis._3d import Qgs3DTypes
    from qgis.core import (QgsApplication, QgsProcessingContext, QgsProcessingFeedback,
                           QgsProcessingOutputLayerDefinition, QgsProcessingUtils, QgsProject, QgsWkbTypes)

    from sylva.processing.outputs import StyledOutput

    _init_3d()
    glb, models, _ = modelled
    project = QgsProject.instance()
    context = QgsProcessingContext()
    context.setProject(project)
    feedback = QgsProcessingFeedback()
    alg = QgsApplication.processingRegistry().createAlgorithmById("sylva:exportmodels")
    params = {"INPUT": str(glb), "MODELS_3D": QgsProcessingOutputLayerDefinition("TEMPORARY_OUTPUT", project)}
    result, ok = alg.run(params, context, feedback)
    assert ok and result["TREE_COUNT"] == len(models)
    dest = result["MODELS_3D"]
    assert context.willLoadLayerOnCompletion(dest)
    details = context.layerToLoadOnCompletionDetails(dest)
    processor = details.postProcessor()
    assert isinstance(processor, StyledOutput) and processor.qml.endswith("models_3d.qml")
    layer = QgsProcessingUtils.mapLayerFromString(dest, context)
    assert layer.featureCount() == len(models) and layer.wkbType() == QgsWkbTypes.MultiPolygonZ
    assert layer.crs().authid() == "EPSG:32632"
    assert layer.renderer3D() is None
    processor.postProcessLayer(layer, context, feedback)
    renderer = layer.renderer3D()
    assert renderer is not None and renderer.type() == "vector"
    from qgis._3d import QgsPolygon3DSymbol, QgsVectorLayer3DRenderer
    from qgis.PyQt import sip

    symbol = sip.cast(sip.cast(renderer, QgsVectorLayer3DRenderer).symbol(), QgsPolygon3DSymbol)
    assert symbol.type() == "polygon"
    # each tree stands on the terrain (QGIS 3.22's new 3D view: flat at 0 m; or a DEM): z + terrain - base_z
    assert symbol.altitudeClamping() == Qgs3DTypes.AltClampRelative
    assert symbol.altitudeBinding() == Qgs3DTypes.AltBindCentroid
    assert symbol.extrusionHeight() == 0.0
    from qgis.core import QgsExpressionContext, QgsExpressionContextUtils

    height = symbol.dataDefinedProperties().property(QgsPolygon3DSymbol.PropertyHeight)
    assert height.isActive()
    feature = next(layer.getFeatures())
    expression_context = QgsExpressionContext(QgsExpressionContextUtils.globalProjectLayerScopes(layer))
    expression_context.setFeature(feature)
    offset, ok = height.valueAsDouble(expression_context, 0.0)
    assert ok and offset == pytest.approx(-models[0].base[2], abs=1e-3)   # base_z is kept to the mm
    # the feature's z values are the trees' own heights; with the offset the tree's base is at the terrain
    z = [v.z() for v in feature.geometry().vertices()]
    assert min(z) == pytest.approx(models[0].base[2] + models[0].wood_arrays()[0][:, 2].min(), abs=1e-3)
    assert min(z) + offset == pytest.approx(models[0].wood_arrays()[0][:, 2].min(), abs=1e-3)
    assert abs(min(z) + offset) < 1.0


@pytest.mark.parametrize("qml, uri", [
    ("crowns.qml", "MultiPolygon?crs=EPSG:32632&field=tree_id:integer&field=height:double"),
    ("tree_tops.qml", "PointZ?crs=EPSG:32632&field=tree_id:integer&field=height:double"),
    ("stem_points.qml", "PointZ?crs=EPSG:32632&field=tree_id:integer&field=height:double"),
    ("crown_points.qml", "PointZ?crs=EPSG:32632&field=tree_id:integer&field=height:double"),
])
def test_shipped_styles(qgis_app, qml, uri):
    from qgis.core import QgsExpression, QgsExpressionContext, QgsFeature, QgsGeometry, QgsVectorLayer

    from sylva.processing.outputs import StyledOutput

    layer = QgsVectorLayer(uri, qml, "memory")
    StyledOutput.get(qml).postProcessLayer(layer, None, None)
    renderer = layer.renderer()
    if qml == "crowns.qml":
        assert renderer.type() == "graduatedSymbol" and renderer.classAttribute() == "height"
        ranges = renderer.ranges()
        assert len(ranges) == 5 and ranges[0].lowerValue() == 0 and ranges[-1].upperValue() >= 100
        colours = [r.symbol().color() for r in ranges]
        assert colours[0].green() > colours[0].blue() and colours[-1].green() > colours[-1].red()
        assert colours[-1].lightness() < colours[0].lightness()       # taller = darker green
        return
    assert renderer.type() == "singleSymbol"
    symbol = renderer.symbol()
    if qml == "tree_tops.qml":
        size = symbol.dataDefinedSize()
        assert size.isActive() and "height" in size.expressionString()
        f = QgsFeature(layer.fields())
        f.setAttributes([1, 40.0])
        f.setGeometry(QgsGeometry.fromWkt("PointZ (0 0 40)"))
        ctx = QgsExpressionContext()
        ctx.setFeature(f)
        tall = QgsExpression(size.expressionString()).evaluate(ctx)
        f.setAttributes([2, 5.0])
        ctx.setFeature(f)
        assert tall > QgsExpression(size.expressionString()).evaluate(ctx)
    else:
        c = symbol.color()
        if qml == "stem_points.qml":                                   # brown
            assert c.red() > c.green() > c.blue()
        else:                                                          # green
            assert c.green() > c.red() and c.green() > c.blue()


def _closed_outward_containing(vertices, faces, point):
    """Whether a triangle mesh is closed (every edge in two faces, in opposite directions), bounds a positive
    volume (faces outward) and holds ``point`` (inside or on it, 1 mm)."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    directed = {tuple(e) for e in edges.tolist()}
    closed = len(directed) == len(edges) and all((b, a) in directed for a, b in directed)
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    volume = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0
    normals = np.cross(b - a, c - a)
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    inside = (np.einsum("ij,ij->i", normals, point - a) <= 1e-3).all()
    return closed and volume > 0 and inside


def test_crowns_3d_layer_closes_each_crown_over_its_top(modelled, tmp_path):
    """CROWNS_3D: one closed, outward, low-poly hull a tree from its leaves, holding the model's top, in the
    source CRS, with base_z (the clamping of crowns_3d.qml); written to one GeoPackage with MODELS_3D, valid."""
    from test_gpkg import validate

    glb, models, frame = modelled
    out = tmp_path / "m3d.gpkg"
    run = subprocess.run([sys.executable, "-m", "sylva.cli", "--quiet", "exportmodels", f"--INPUT={glb}",
                          f"--MODELS_3D={out}", f"--CROWNS_3D={out}"], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert validate(out) == ""
    layer = read_gpkg(out, "crowns_3d")
    np.testing.assert_array_equal(layer.columns["tree_id"], [m.tree_id for m in models])
    np.testing.assert_allclose(layer.columns["base_z"], [m.base[2] for m in models], atol=1e-3)
    assert len(read_gpkg(out, "models_3d")) == len(models)
    for k, m in enumerate(models):
        g = layer.geometries[k]
        assert g.geom_type == "MultiPolygon" and g.has_z
        assert layer.columns["n_triangles"][k] == len(g.geoms) <= 82
        tri = np.array([shapely.get_coordinates(p, include_z=True)[:3] for p in g.geoms])
        vertices, faces = np.unique(tri.reshape(-1, 3), axis=0, return_inverse=True)
        faces = faces.reshape(-1, 3)
        local = m.all_local_vertices()
        top = m.base + local[np.argmax(local[:, 2])]
        assert _closed_outward_containing(vertices, faces, top)
        # the envelope of the leaves: its corners are leaf vertices (or the top), it spans the leaves' height
        leaves = m.base + m.leaf_arrays()[0]
        d, _ = cKDTree(np.vstack([leaves, top])).query(vertices)
        assert d.max() < 1e-3
        assert vertices[:, 2].max() == pytest.approx(top[2], abs=1e-3)


def test_crown_hull_is_bounded_closed_and_keeps_the_top():
    """core/export/crowns3d.py on random crowns: <= 2 (k + 2 + 1) - 4 faces, closed, outward, top held; None
    for a flat or tiny crown; point_crowns groups by label and places each hull at its origin."""
    from sylva.core.export.crowns3d import N_DIRECTIONS, crown_hull, crowns_table, point_crowns

    rng = np.random.default_rng(3)
    for _ in range(50):
        pts = rng.normal(size=(int(rng.integers(5, 4000)), 3)) * [3.0, 2.0, 5.0] + [0, 0, 15]
        top = pts[[np.argmax(pts[:, 2])]] + [0.5, 0.0, 1.0]          # a top above every point
        v, f = crown_hull(pts, keep=top)
        assert len(f) <= 2 * (N_DIRECTIONS + 3) - 4 and len(f) == 2 * len(v) - 4
        assert _closed_outward_containing(v, f, top[0])
        assert v[:, 2].max() == pytest.approx(top[0, 2])
    assert crown_hull(np.zeros((3, 3))) is None
    assert crown_hull(np.column_stack([rng.random(50), rng.random(50), np.zeros(50)])) is None
    # two trees, labels interleaved, in a CRS of feet on all axes
    xyz = np.vstack([rng.normal(size=(200, 3)) + [100, 200, 30], rng.normal(size=(300, 3)) + [110, 200, 40]])
    labels = np.repeat([7, 9], [200, 300])
    perm = rng.permutation(len(xyz))
    origins = np.array([[100.0, 200.0, 0.0], [110.0, 200.0, 0.0]])
    tops = np.array([xyz[:200][np.argmax(xyz[:200, 2])], xyz[200:][np.argmax(xyz[200:, 2])]])
    feet = np.full(3, 0.3048)
    hulls = point_crowns(xyz[perm], labels[perm], np.array([7, 9]), origins, feet, tops)
    table = crowns_table([7, 9, 11], hulls + [None], np.vstack([origins, origins[:1]]), feet, [0.0] * 3, None)
    assert table.geometries[2] is None and list(table.columns["n_triangles"][:2]) == [len(h[1]) for h in hulls]
    table = crowns_table([7, 9], hulls, origins, feet, [0.0, 0.0], None)
    for k, g in enumerate(shapely.from_wkb(table.geometries)):
        coords = shapely.get_coordinates(g, include_z=True)
        d, _ = cKDTree(xyz[labels == [7, 9][k]]).query(coords)
        assert d.max() < 1e-9                                          # corners are the tree's own points
    np.testing.assert_allclose(table.extent, shapely.total_bounds(shapely.from_wkb(table.geometries)))


def test_include_leaves_keeps_its_earlier_name(modelled, tmp_path):
    """exportmodels' INCLUDE_LEAVES was LEAVES (a yes/no here, the leaf kind elsewhere): scripts written with
    the earlier name still write the same files."""
    glb, _, _ = modelled
    objs = {}
    for key, flag in (("new", "--INCLUDE_LEAVES=false"), ("old", "--LEAVES=false"), ("default", None)):
        obj = tmp_path / key / "trees.obj"
        obj.parent.mkdir()
        run = subprocess.run([sys.executable, "-m", "sylva.cli", "--quiet", "exportmodels", f"--INPUT={glb}",
                              f"--OBJ={obj}", *([flag] if flag else [])], capture_output=True, text=True)
        assert run.returncode == 0, run.stderr
        objs[key] = obj.read_text()
    assert objs["old"] == objs["new"]
    assert len(objs["new"].splitlines()) < len(objs["default"].splitlines())
