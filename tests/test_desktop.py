"""Every sylva algorithm from its dialog in the real QGIS desktop (Xvfb), as a forester meets it.

``tests/desktop/run_dialogs.py`` runs inside ``qgis --code``: it opens each dialog with only its required inputs,
reads back every widget, checks the algorithm accepts the values, presses Run and records the layers that
appear in the project. Screenshots of the dialogs, their logs and the main window go to tests/artefacts/desktop/
(git-ignored). QGIS_SETUP.md items 13-14 explain the set-up.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import shapely

ROOT = Path(__file__).resolve().parents[1]
ARTEFACTS = ROOT / "tests" / "artefacts" / "desktop"
SCRIPT = ROOT / "tests" / "desktop" / "run_dialogs.py"

pytestmark = [pytest.mark.qgis, pytest.mark.slow]

#: What each run must give: layers added to the project (name prefixes) and results.
EXPECTED_LAYERS = {
    "sylva:canopyheightmodel": ["Canopy height model"],
    "sylva:treetops": ["Tree tops"],
    "sylva:segmenttrees": ["Crowns", "Tree tops", "Trees table"],
    "sylva:reconstructtrees": ["Skeletons", "Trees table"],
    "sylva:treefromsketch": ["Skeleton", "Tree"],
    "sylva:exportmodels": ["3D models layer"],
}


def _sketch_layers(folder: Path) -> dict:
    import pyproj

    from sylva.core.io.gpkg import write_gpkg
    from sylva.core.table import VectorTable

    front = [shapely.LineString([(100, 0), (100, 300), (102, 500)]), shapely.LineString([(101, 250), (60, 330)]),
             shapely.LineString([(90, 380), (160, 460)])]
    side = [shapely.LineString([(0, 0), (5, 250), (10, 520)]), shapely.LineString([(4, 200), (60, 300)])]
    paths = {}
    for name, geoms, kind, crs in (("front", front, "line", None), ("side", side, "line", None),
                                   ("location", [shapely.Point(500123.0, 5700456.0, 80.0)], "point",
                                    pyproj.CRS.from_epsg(25832))):
        path = folder / f"{name}.gpkg"
        write_gpkg(path, [VectorTable(name, kind, np.array(geoms, dtype=object), {"id": np.arange(len(geoms))},
                                      crs, has_z=kind == "point")])
        paths[name.upper()] = str(path)
    return paths


@pytest.fixture(scope="module")
def desktop_report(tmp_path_factory, sample_laz):
    qgis = shutil.which("qgis")
    if qgis is None or shutil.which("xvfb-run") is None:
        pytest.skip("the QGIS desktop or xvfb-run is not installed")
    if not (ROOT / ".qgis-profile").is_dir():
        pytest.skip("run scripts/setup.sh first: it makes the QGIS profile with the plugin enabled")
    from conftest import segmented_corner_of

    from sylva import cli

    work = tmp_path_factory.mktemp("desktop")
    corner, _ = segmented_corner_of(sample_laz, work, 30.0)       # a segmented tile for reconstruct/billboards
    glb = work / "models.glb"                                     # exportmodels reads a GLB made first
    assert cli.main(["--quiet", "reconstructtrees", f"--INPUT={corner}", f"--MODELS={glb}",
                     f"--SKELETONS={work / 's.gpkg'}", f"--TREES={work / 't.gpkg'}"]) == 0
    inputs = {f"sylva:{a}": {"INPUT": str(sample_laz)}
              for a in ("canopyheightmodel", "treetops", "normalizeheight", "segmenttrees", "pipeline")}
    inputs.update({"sylva:reconstructtrees": {"INPUT": str(corner)}, "sylva:billboards": {"INPUT": str(corner)},
                   "sylva:exportmodels": {"INPUT": str(glb)}, "sylva:treefromsketch": _sketch_layers(work)})
    if ARTEFACTS.exists():
        shutil.rmtree(ARTEFACTS)
    ARTEFACTS.mkdir(parents=True)
    report = work / "report.json"
    env = {k: v for k, v in os.environ.items() if k != "QT_QPA_PLATFORM"}
    env.update(SYLVA_DESKTOP_REPORT=str(report), SYLVA_DESKTOP_ARTEFACTS=str(ARTEFACTS),
               SYLVA_DESKTOP_INPUTS=json.dumps(inputs), QGIS_PLUGINPATH=str(ROOT / ".qgis-plugins"),
               SYLVA_DESKTOP_ORDER="sylva:segmenttrees")
    profiles = work / "profiles"           # a copy: the desktop writes its settings into the profile
    shutil.copytree(ROOT / ".qgis-profile", profiles)
    done = subprocess.run(["xvfb-run", "-a", "-s", "-screen 0 1600x1000x24", qgis, "--profiles-path", str(profiles),
                           "--nologo", "--noversioncheck", "--code", str(SCRIPT)],
                          capture_output=True, text=True, env=env, timeout=600)
    assert report.is_file(), f"QGIS wrote no report (exit {done.returncode}): {done.stderr[-2000:]}"
    data = json.loads(report.read_text())
    (ARTEFACTS / "report.json").write_text(json.dumps(data, indent=1))
    assert data["error"] is None, data["error"]
    return data


ALGORITHMS = ("canopyheightmodel", "treetops", "normalizeheight", "segmenttrees", "reconstructtrees",
              "exportmodels", "pipeline", "treefromsketch", "billboards")


@pytest.mark.parametrize("name", ALGORITHMS)
def test_the_dialog_runs_with_its_defaults(desktop_report, name):
    entry = desktop_report["algorithms"][f"sylva:{name}"]
    assert "error" not in entry, entry.get("error")
    assert entry["refused_widgets"] == [], {n: entry["widgets"][n] for n in entry["refused_widgets"]}
    assert entry["accepted"], entry["check_message"]
    assert "-2147483648" not in entry["widgets"].values()
    assert entry["help_url"].startswith("file://") and entry["help_url"].endswith(f"{name}.html")
    assert Path(entry["dialog_png"]).stat().st_size > 10_000
    assert entry["successful"], entry.get("log_tail")
    for prefix in EXPECTED_LAYERS.get(f"sylva:{name}", []):
        layers = [layer for layer in entry["layers"] if layer[0].startswith(prefix)]
        assert layers and all(valid for _, valid, _ in layers), (prefix, entry["layers"])


def test_counts_are_declared_outputs_and_returned(desktop_report):
    for name in ("segmenttrees", "treetops", "reconstructtrees", "pipeline", "billboards", "exportmodels"):
        entry = desktop_report["algorithms"][f"sylva:{name}"]
        assert "TREE_COUNT" in entry["outputs_declared"]
        assert int(float(entry["results"]["TREE_COUNT"])) > 0, name
    seg = desktop_report["algorithms"]["sylva:segmenttrees"]
    trees = [n for n in seg["layers"] if n[0].startswith("Tree tops")]
    assert trees[0][2] == int(float(seg["results"]["TREE_COUNT"]))


def test_the_trees_table_shows_rounded_values(desktop_report):
    row = desktop_report["trees_row"]
    for name, value in row.items():
        if isinstance(value, float) and abs(value) >= 1:
            assert round(value, 3) == value, (name, value)
    assert row["height"] > 2.0 and row["n_points"] > 0


def test_the_missing_packages_hint_names_a_python_inside_qgis(desktop_report):
    assert "python3" in Path(desktop_report["interpreter"]).name
