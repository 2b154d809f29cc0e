"""Sylva's Processing provider in real QGIS (pytest-qgis): toolbox algorithms, modeler, errors, cancel."""
from pathlib import Path

import pytest

from badfiles import make_bad_inputs

pytestmark = pytest.mark.qgis


def run(alg_id, params, feedback=None):
    import processing

    return processing.run(alg_id, params, feedback=feedback)


def test_provider_lists_the_algorithms(sylva_provider):
    from qgis.core import QgsApplication

    ids = {a.id() for a in QgsApplication.processingRegistry().providerById("sylva").algorithms()}
    assert {"sylva:canopyheightmodel", "sylva:terraintiles", "sylva:treetops"} <= ids
    alg = QgsApplication.processingRegistry().algorithmById("sylva:treetops")
    assert "TOP_WINDOW_M" in alg.shortHelpString()
    # the earlier name is a hidden parameter, so graphs and scripts saved with it keep their value
    from qgis.core import QgsProcessingParameterDefinition as Def
    assert alg.parameterDefinition("WINDOW_DIAMETER_M").flags() & Def.FlagHidden
    assert alg.parameterDefinition("MIN_HEIGHT_M").defaultValue() == 2.0


def test_chm_opens_as_a_raster_layer(sylva_provider, sample_laz, tmp_path):
    from qgis.core import QgsRasterLayer

    result = run("sylva:canopyheightmodel", {"INPUT": str(sample_laz), "RESOLUTION_M": 1.0,
                                             "PIT_FREE": True, "OUTPUT": str(tmp_path / "chm.tif")})
    layer = QgsRasterLayer(result["OUTPUT"], "chm")
    assert layer.isValid()
    assert layer.crs().authid() == "EPSG:32632"
    stats = layer.dataProvider().bandStatistics(1)
    assert 5.0 < stats.maximumValue < 60.0  # metres above ground, not elevations
    assert abs(layer.rasterUnitsPerPixelX() - 1.0) < 1e-9


def test_treetops_layer_opens_with_fields(sylva_provider, sample_laz, tmp_path):
    from qgis.core import QgsVectorLayer, QgsWkbTypes

    out = str(tmp_path / "tops.gpkg")
    result = run("sylva:treetops", {"INPUT": str(sample_laz), "WINDOW": 0, "TOP_WINDOW_M": 3.0,
                                    "MIN_HEIGHT_M": 2.0, "OUTPUT": out})
    layer = QgsVectorLayer(result["OUTPUT"], "tops", "ogr")
    assert layer.isValid()
    assert layer.wkbType() == QgsWkbTypes.PointZ
    assert layer.crs().authid() == "EPSG:32632"
    assert [f.name() for f in layer.fields()][-2:] == ["tree_id", "height"]
    assert layer.featureCount() == result["TREE_COUNT"] > 20
    heights = [f["height"] for f in layer.getFeatures()]
    assert min(heights) >= 2.0


def test_two_step_model_chm_then_tops(sylva_provider, sample_laz, tmp_path):
    """A Graphical Modeler graph: CHM -> tree tops, linked by the CHM output; saved and reloaded.

    The graph sets the top window by its earlier name, WINDOW_DIAMETER_M, to 6 m (not the default): the
    value must arrive (as many tops as TOP_WINDOW_M=6 gives, fewer than 3 m)."""
    from qgis.core import (QgsProcessingContext, QgsProcessingFeedback, QgsProcessingModelAlgorithm,
                           QgsProcessingModelChildAlgorithm, QgsProcessingModelChildParameterSource as Src,
                           QgsProcessingModelOutput, QgsProcessingModelParameter,
                           QgsProcessingParameterFile, QgsVectorLayer)

    model = QgsProcessingModelAlgorithm("chm_tops", "sylva tests")
    model.addModelParameter(QgsProcessingParameterFile("tile", "LiDAR tile"), QgsProcessingModelParameter("tile"))
    chm = QgsProcessingModelChildAlgorithm("sylva:canopyheightmodel")
    chm.setChildId("chm")
    chm.addParameterSources("INPUT", [Src.fromModelParameter("tile")])
    chm.addParameterSources("RESOLUTION_M", [Src.fromStaticValue(1.0)])
    chm.addParameterSources("PIT_FREE", [Src.fromStaticValue(True)])
    model.addChildAlgorithm(chm)
    tops = QgsProcessingModelChildAlgorithm("sylva:treetops")
    tops.setChildId("tops")
    tops.addParameterSources("INPUT", [Src.fromChildOutput("chm", "OUTPUT")])
    tops.addParameterSources("WINDOW", [Src.fromStaticValue(0)])
    tops.addParameterSources("WINDOW_DIAMETER_M", [Src.fromStaticValue(6.0)])
    tops.addParameterSources("MIN_HEIGHT_M", [Src.fromStaticValue(2.0)])
    output = QgsProcessingModelOutput("tree_tops")
    output.setChildId("tops")
    output.setChildOutputName("OUTPUT")
    tops.setModelOutputs({"tree_tops": output})
    model.addChildAlgorithm(tops)
    model.updateDestinationParameters()
    saved = tmp_path / "chm_tops.model3"
    assert model.toFile(str(saved))
    reloaded = QgsProcessingModelAlgorithm()
    assert reloaded.fromFile(str(saved))
    ok, message = reloaded.checkParameterValues(
        {"tile": str(sample_laz), "tops:tree_tops": str(tmp_path / "model_tops.gpkg")}, QgsProcessingContext())
    assert ok, message
    import processing

    result = processing.run(reloaded, {"tile": str(sample_laz), "tops:tree_tops": str(tmp_path / "model_tops.gpkg")},
                            feedback=QgsProcessingFeedback())
    layer = QgsVectorLayer(result["tops:tree_tops"], "tops", "ogr")
    assert layer.isValid() and layer.featureCount() > 20
    chm = run("sylva:canopyheightmodel", {"INPUT": str(sample_laz), "RESOLUTION_M": 1.0, "PIT_FREE": True,
                                          "OUTPUT": str(tmp_path / "chm.tif")})["OUTPUT"]
    count = {w: run("sylva:treetops", {"INPUT": chm, "WINDOW": 0, "TOP_WINDOW_M": w, "MIN_HEIGHT_M": 2.0,
                                       "OUTPUT": str(tmp_path / f"tops_{w}.gpkg")})["TREE_COUNT"] for w in (3.0, 6.0)}
    assert layer.featureCount() == count[6.0] < count[3.0]


@pytest.mark.parametrize("case", ["missing", "not_las", "truncated", "empty", "no_crs"])
def test_bad_input_raises_a_processing_exception(sylva_provider, sample_laz, tmp_path, case):
    from qgis.core import QgsProcessingException

    path, words = make_bad_inputs(tmp_path / "bad", sample_laz)[case]
    out = tmp_path / "out"
    out.mkdir()
    with pytest.raises(QgsProcessingException) as err:
        run("sylva:treetops", {"INPUT": str(path), "OUTPUT": str(out / "tops.gpkg")})
    assert path.name in str(err.value) and words in str(err.value)
    assert "Traceback" not in str(err.value)
    assert list(out.iterdir()) == []


def test_cancel_stops_the_run(sylva_provider, sample_laz, tmp_path):
    from qgis.core import QgsProcessingException, QgsProcessingFeedback

    feedback = QgsProcessingFeedback()
    feedback.cancel()
    target = tmp_path / "chm.tif"
    with pytest.raises(QgsProcessingException, match="cancel"):
        run("sylva:canopyheightmodel", {"INPUT": str(sample_laz), "OUTPUT": str(target)}, feedback)
    assert not target.exists()


def test_progress_is_reported(sylva_provider, sample_laz, tmp_path):
    from qgis.core import QgsProcessingFeedback

    seen = []
    feedback = QgsProcessingFeedback()
    feedback.progressChanged.connect(seen.append)
    run("sylva:canopyheightmodel", {"INPUT": str(sample_laz), "RESOLUTION_M": 1.0, "OUTPUT": str(tmp_path / "c.tif")},
        feedback)
    assert len(seen) >= 3 and max(seen) == pytest.approx(100.0)


def test_plugin_registers_and_unregisters_its_provider(qgis_processing):
    from qgis.core import QgsApplication

    import sylva

    registry = QgsApplication.processingRegistry()
    existing = registry.providerById("sylva")
    if existing is not None:
        registry.removeProvider(existing)
    plugin = sylva.classFactory(None)  # what qgis_process does
    plugin.initProcessing()
    assert registry.algorithmById("sylva:segmenttrees") is not None
    plugin.unload()
    assert registry.providerById("sylva") is None


def test_missing_package_is_named_instead_of_failing_to_load(qgis_processing, monkeypatch):
    from sylva.plugin import deps
    from sylva.processing.provider import SylvaProvider

    monkeypatch.setattr(deps, "REQUIRED", deps.REQUIRED + (("surely_missing_mod", "surely-missing"),))
    provider = SylvaProvider()
    provider.refreshAlgorithms()
    algorithms = provider.algorithms()
    assert [a.name() for a in algorithms] == ["dependencies"]
    assert "surely-missing" in algorithms[0].shortHelpString()
    assert "pip install" in algorithms[0].shortHelpString()
