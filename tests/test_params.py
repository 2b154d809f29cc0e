"""Parameter definitions: every number has its real range, refused values give one line naming the parameter.

The ranges live in the Param definitions (algorithms/*.py), so the CLI, qgis_process and the dialog refuse the
same values; these tests check the definitions against the core dataclasses and drive the CLI as a user would.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import shapely

from sylva import cli
from sylva.algorithms import all_algorithms, get
from sylva.algorithms import spec as S
from sylva.algorithms.billboard import BILLBOARD_PARAMS
from sylva.algorithms.reconstruct import GREEDY_PARAMS, GUIDED_PARAMS
from sylva.algorithms.segment import CHM_PARAMS, NCUT_PARAMS
from sylva.algorithms.sketch import SKETCH_PARAMS
from sylva.core.reconstruct import GreedySkeleton, GuidedGrowth
from sylva.core.reconstruct.billboard import Billboard
from sylva.core.reconstruct.sketch import SketchTree
from sylva.core.segment import ChmRegionGrowing, NormalizedCut

NUMERIC = [(a.id, p) for a in all_algorithms().values() for p in a.params if p.kind in (S.NUMBER, S.INTEGER)]


@pytest.mark.parametrize("alg_id,p", NUMERIC, ids=[f"{a}.{p.name}" for a, p in NUMERIC])
def test_every_number_has_a_finite_range_that_holds_its_default(alg_id, p):
    assert math.isfinite(p.minimum) and math.isfinite(p.maximum) and p.minimum <= p.maximum
    if p.kind == S.INTEGER:
        assert -2 ** 31 <= p.minimum and p.maximum <= 2 ** 31 - 1   # a QGIS spin box holds it
    if p.default is not None:
        assert p.minimum <= p.default <= p.maximum
    assert p.problem(float("nan")) and p.problem(float("inf")) and p.problem(-float("inf"))
    assert p.problem(p.maximum + 1) and p.problem(p.minimum - 1)
    assert p.problem(p.minimum) is None and p.problem(p.maximum) is None


METHODS = [(NormalizedCut, NCUT_PARAMS, {}), (ChmRegionGrowing, CHM_PARAMS, {}), (GreedySkeleton, GREEDY_PARAMS, {}),
           (GuidedGrowth, GUIDED_PARAMS, {}), (Billboard, BILLBOARD_PARAMS, {}),
           (SketchTree, SKETCH_PARAMS, {"cos_theta1": -1.0, "cos_phi1": -1.0})]


@pytest.mark.parametrize("cls,params,base", METHODS, ids=[m[0].__name__ for m in METHODS])
def test_the_ranges_are_accepted_by_the_core_method(cls, params, base):
    """Each end of every exposed range builds the dataclass (so the front ends refuse only what it refuses)."""
    fields = {f.name for f in dataclasses.fields(cls)}
    for p in params:
        if p.kind not in (S.NUMBER, S.INTEGER):
            continue
        name = p.name.lower()
        assert name in fields
        for value in (p.minimum, p.maximum):
            kw = dict(base)
            if cls is SketchTree and name.startswith("cos_"):   # keep cos_x1 <= cos_x2
                kw = {"cos_theta1": -1.0, "cos_theta2": 1.0, "cos_phi1": -1.0, "cos_phi2": 1.0}
            kw[name] = type(p.default)(value)
            cls(**kw)


# The values issue 17 found giving tracebacks (or, for MIN_HEIGHT_M=nan, 0 trees and exit 0).
REFUSED = [("segmenttrees", "VOXEL_M", v) for v in ("0", "nan", "inf", "-1")] + [
    ("segmenttrees", "RADIUS_M", "0"), ("segmenttrees", "SIGMA_H_M", "0"), ("segmenttrees", "SIGMA_V_M", "nan"),
    ("segmenttrees", "SIGMA_INTENSITY", "0"), ("segmenttrees", "SIGMA_COLOUR", "-inf"),
    ("segmenttrees", "APEX_SLOPE", "0"), ("segmenttrees", "APEX_SECTORS", "0"), ("segmenttrees", "APEX_SECTORS", "9"),
    ("segmenttrees", "APEX_SECTORS", "2.5"), ("segmenttrees", "TOP_WINDOW_M", "nan"),
    ("segmenttrees", "MIN_HEIGHT_M", "nan"), ("treetops", "MIN_HEIGHT_M", "nan"),
    ("reconstructtrees", "STEP_M", "0"), ("reconstructtrees", "K", "0"), ("reconstructtrees", "VOXEL_M", "inf"),
    ("billboards", "TEXTURE_PX", "4"), ("billboards", "SEED", "-1"), ("pipeline", "BUFFER_M", "nan"),
    ("pipeline", "WORKERS", "0"), ("canopyheightmodel", "RESOLUTION_M", "0"),
    ("treefromsketch", "HEIGHT_M", "1e308"), ("treefromsketch", "HEIGHT_M", "0"), ("treefromsketch", "LEVELS", "-1"),
]


@pytest.fixture(scope="module")
def sketch_layers(tmp_path_factory):
    """Small line layers and a location, as a user digitises them (GeoPackage)."""
    import pyproj

    from sylva.core.io.gpkg import write_gpkg
    from sylva.core.table import VectorTable

    folder = tmp_path_factory.mktemp("sketch")
    front = [shapely.LineString([(100, 0), (100, 300), (102, 500)]), shapely.LineString([(101, 250), (60, 330)])]
    side = [shapely.LineString([(0, 0), (5, 250), (10, 520)]), shapely.LineString([(4, 200), (60, 300)])]
    paths = {}
    for name, geoms, kind, crs in (("front", front, "line", None), ("side", side, "line", None),
                                   ("location", [shapely.Point(500123.0, 5700456.0, 80.0)], "point",
                                    pyproj.CRS.from_epsg(25832))):
        path = folder / f"{name}.gpkg"
        write_gpkg(path, [VectorTable(name, kind, np.array(geoms, dtype=object),
                                      {"id": np.arange(len(geoms))}, crs, has_z=kind == "point")])
        paths[name.upper()] = str(path)
    return paths


@pytest.mark.parametrize("alg_id,name,value", REFUSED, ids=[f"{a}.{n}={v}" for a, n, v in REFUSED])
def test_the_cli_refuses_with_one_line_naming_the_parameter(alg_id, name, value, sample_laz, sketch_layers,
                                                             tmp_path, capsys):
    given = {"treefromsketch": [f"--{k}={v}" for k, v in sketch_layers.items()],
             "pipeline": [f"--INPUT={sample_laz}", f"--OUTPUT_FOLDER={tmp_path / 'out'}"]}.get(
        alg_id, [f"--INPUT={sample_laz}"])
    code = cli.main(["--quiet", alg_id, *given, f"--{name}={value}"])
    err = capsys.readouterr().err.strip()
    assert code == 1
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert f"--{name}" in err and get(alg_id).param(name).description in err
    assert not (tmp_path / "out").exists()      # refused before anything is written


def test_enums_take_the_id_the_label_or_the_index():
    p = get("segmenttrees").param("METHOD")
    assert p.option("chm") == p.option("1") == p.option(1) == p.option(p.labels[1]) == "chm"
    assert p.option_labels[0].startswith("Normalised cut")
    for bad in ("4", "-1", "bogus", True):
        with pytest.raises(ValueError):
            p.option(bad)


def test_cross_field_refusals_are_one_line(sample_laz, sketch_layers, capsys):
    """A combination the core dataclass refuses (cos θ1 > cos θ2) is an InputError, not a traceback."""
    code = cli.main(["--quiet", "treefromsketch", *[f"--{k}={v}" for k, v in sketch_layers.items()],
                     "--COS_THETA1=0.9", "--COS_THETA2=0.1"])
    err = capsys.readouterr().err.strip()
    assert code == 1 and len(err.splitlines()) == 1 and "cos_theta1" in err and "Traceback" not in err


def test_labels_are_plain_words_with_units():
    """No paper symbol in a label (they are in the help); lengths say (m)."""
    for alg in all_algorithms().values():
        for p in alg.params:
            assert not any(sym in p.description for sym in ("σ", "θ", "φ", "α", "β", "d_s", "r_xz", "d_l")), p
            if p.name.endswith("_M") and p.kind == S.NUMBER:
                assert "(m)" in p.description, p
            if p.kind == S.ENUM:
                assert p.labels, f"{alg.id}.{p.name} has no readable labels"


def test_results_are_declared():
    assert [r.name for r in get("pipeline").results][:3] == ["TREE_COUNT", "TILE_COUNT", "FAILED_TILES"]
    for alg in all_algorithms().values():
        if alg.id not in ("canopyheightmodel", "normalizeheight", "terraintiles"):   # rasters, no trees: no tree count
            assert "TREE_COUNT" in [r.name for r in alg.results], alg.id


def test_display_round():
    v = S.display_round(np.array([12.3456789123, 482345.1234567, 0.000412345678, -0.5, np.nan, 0.0]))
    assert v[0] == 12.346 and v[1] == 482345.123 and v[2] == 0.0004123 and v[3] == -0.5
    assert np.isnan(v[4]) and v[5] == 0.0


def test_the_shipped_help_pages_are_current(tmp_path):
    from sylva.algorithms.helppages import HELP_DIR, write_pages

    for page in write_pages(tmp_path):
        shipped = HELP_DIR / page.name
        assert shipped.is_file(), f"{shipped} missing: run python -m sylva.algorithms.helppages"
        assert shipped.read_text(encoding="utf-8") == page.read_text(encoding="utf-8"), \
            f"{shipped} is stale: run python -m sylva.algorithms.helppages"
