"""The parameter definitions as QGIS Processing sees them (pytest-qgis): bounds, refusals, enum labels, outputs."""
from __future__ import annotations

from pathlib import Path

import pytest

from sylva.algorithms import all_algorithms
from sylva.algorithms import spec as S

pytestmark = pytest.mark.qgis


def _alg(alg_id):
    from qgis.core import QgsApplication

    return QgsApplication.processingRegistry().algorithmById(f"sylva:{alg_id}")


def test_every_number_has_the_definition_s_bounds(sylva_provider):
    from qgis.core import QgsProcessingParameterNumber

    for spec in all_algorithms().values():
        alg = _alg(spec.id)
        for p in spec.params:
            if p.kind not in (S.NUMBER, S.INTEGER):
                continue
            q = alg.parameterDefinition(p.name)
            assert isinstance(q, QgsProcessingParameterNumber)
            assert (q.minimum(), q.maximum()) == (p.minimum, p.maximum), (spec.id, p.name)
            if p.default is not None:
                assert q.checkValueIsAcceptable(q.defaultValue()), (spec.id, p.name)


@pytest.mark.parametrize("alg_id,name,value", [
    ("segmenttrees", "MIN_HEIGHT_M", "nan"), ("segmenttrees", "VOXEL_M", float("nan")),
    ("segmenttrees", "APEX_SECTORS", 0), ("segmenttrees", "APEX_SLOPE", 0.0), ("segmenttrees", "RADIUS_M", "inf"),
    ("reconstructtrees", "STEP_M", 0.0), ("treefromsketch", "HEIGHT_M", 1e308), ("pipeline", "BUFFER_M", "nan"),
])
def test_check_parameter_values_names_the_parameter(sylva_provider, sample_laz, alg_id, name, value):
    from qgis.core import QgsProcessingContext

    alg = _alg(alg_id)
    ok, message = alg.checkParameterValues({"INPUT": str(sample_laz), name: value}, QgsProcessingContext())
    assert not ok
    assert message.startswith(name) and all_algorithms()[alg_id].param(name).description in message
    assert "\n" not in message


def test_enums_show_labels_and_take_ids(sylva_provider, sample_laz, tmp_path):
    import processing

    method = _alg("segmenttrees").parameterDefinition("METHOD")
    assert method.options()[0].startswith("Normalised cut")
    out = processing.run("sylva:treetops", {"INPUT": str(sample_laz), "WINDOW": "fixed", "WINDOW_DIAMETER_M": 3.0,
                                            "OUTPUT": str(tmp_path / "tops.gpkg")})
    by_index = processing.run("sylva:treetops", {"INPUT": str(sample_laz), "WINDOW": 0, "WINDOW_DIAMETER_M": 3.0,
                                                 "OUTPUT": str(tmp_path / "tops0.gpkg")})
    assert out["TREE_COUNT"] == by_index["TREE_COUNT"] > 0


def test_results_help_and_advanced(sylva_provider):
    from qgis.core import QgsProcessingOutputNumber, QgsProcessingParameterDefinition

    alg = _alg("pipeline")
    assert isinstance(alg.outputDefinition("TREE_COUNT"), QgsProcessingOutputNumber)
    assert alg.outputDefinition("GEOPACKAGE") is not None
    for spec in all_algorithms().values():
        url = _alg(spec.id).helpUrl()
        assert url.startswith("file://") and Path(url[len("file://"):]).is_file()
        assert "<dl>" in _alg(spec.id).shortHelpString()
    seg = _alg("segmenttrees")
    for name in ("VOXEL_M", "TH_SEED", "RESOLUTION_M"):   # each method's own settings are Advanced
        assert seg.parameterDefinition(name).flags() & QgsProcessingParameterDefinition.FlagAdvanced
