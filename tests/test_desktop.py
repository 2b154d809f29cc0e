"""Every sylva algorithm from its dialog in the real QGIS desktop (Xvfb), as a forester meets it.

``tests/desktop/run_dialogs.py`` runs inside ``qgis --code``: it opens each dialog with only its required inputs,
reads back every widget, checks the algorithm accepts the values, presses Run and records the layers that
appear in the project. Screenshots of the dialogs, their logs and the main window go to tests/artefacts/desktop/
(git-ignored). QGIS_SETUP.md items 13-14 explain the set-up.

Two lanes: Debian 12's QGIS 3.22 on the host, and Debian 13's QGIS 3.40 desktop inside the root ``.qgis-trixie``
(``scripts/setup_qgis_trixie.sh`` installs it with Sylva's dependencies and warmed kernels; the script runs there
under the root's own xvfb-run, screenshots in tests/artefacts/desktop-3.40/). The 3.40 lane skips, saying why,
when the root, its desktop stage or root rights are missing.
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
    "sylva:terraintiles": ["DTM (terrain)", "CHM (canopy height)"],
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


TRIXIE = ROOT / ".qgis-trixie"
TRIXIE_SETUP = ROOT / "scripts" / "setup_qgis_trixie.sh"
#: the lanes: Debian 12's QGIS 3.22 on the host, Debian 13's QGIS 3.40 in the root .qgis-trixie
LANES = ("3.22", "3.40")


@pytest.fixture(scope="module")
def desktop_inputs(tmp_path_factory, sample_laz):
    """The dialogs' required inputs (shared by both lanes): the sample, a segmented corner, a GLB, sketches."""
    from conftest import segmented_corner_of

    from sylva import cli

    work = tmp_path_factory.mktemp("desktop")
    corner, _ = segmented_corner_of(sample_laz, work, 30.0)       # a segmented tile for reconstruct/billboards
    glb = work / "models.glb"                                     # exportmodels reads a GLB made first
    assert cli.main(["--quiet", "reconstructtrees", f"--INPUT={corner}", f"--MODELS={glb}",
                     f"--SKELETONS={work / 's.gpkg'}", f"--TREES={work / 't.gpkg'}"]) == 0
    inputs = {f"sylva:{a}": {"INPUT": str(sample_laz)}
              for a in ("canopyheightmodel", "treetops", "normalizeheight", "segmenttrees", "pipeline",
                        "terraintiles")}
    inputs.update({"sylva:reconstructtrees": {"INPUT": str(corner)}, "sylva:billboards": {"INPUT": str(corner)},
                   "sylva:exportmodels": {"INPUT": str(glb)}, "sylva:treefromsketch": _sketch_layers(work)})
    return work, inputs


def _desktop_env(report: Path, artefacts: Path, inputs: dict) -> dict:
    return {"SYLVA_DESKTOP_REPORT": str(report), "SYLVA_DESKTOP_ARTEFACTS": str(artefacts),
            "SYLVA_DESKTOP_INPUTS": json.dumps(inputs), "SYLVA_DESKTOP_ORDER": "sylva:segmenttrees"}


def _trixie_desktop_or_skip():
    """Skip (saying why) unless the QGIS 3.40 desktop is installed in .qgis-trixie and root can enter it."""
    if not (TRIXIE / ".sylva-installed").exists():
        pytest.skip("QGIS 3.40 is not installed in .qgis-trixie: bash scripts/setup_qgis_trixie.sh installs it "
                    "(needs root; scripts/test.sh runs it)")
    if not (TRIXIE / ".sylva-desktop-installed").exists():
        failed = TRIXIE / ".sylva-desktop-failed"
        why = failed.read_text().strip()[-600:] if failed.exists() else "its desktop stage has not run"
        pytest.skip(f"the QGIS 3.40 desktop is not installed in .qgis-trixie: {why}")
    if os.geteuid() != 0:
        pytest.skip("entering the .qgis-trixie root needs root (unshare + chroot)")
    probe = subprocess.run(["bash", str(TRIXIE_SETUP), "--run", "/bin/sh", "-c",
                            "for c in qgis xvfb-run xauth; do command -v $c >/dev/null || { echo \"no $c in the root "
                            "(rerun scripts/setup_qgis_trixie.sh after deleting .qgis-trixie/.sylva-desktop-installed)\"; "
                            "exit 1; }; done"], capture_output=True, text=True, timeout=60)
    if probe.returncode != 0:
        pytest.skip(f"cannot run the QGIS 3.40 desktop in .qgis-trixie: {(probe.stdout + probe.stderr).strip()[-300:]}")


def _run_desktop_340(work: Path, artefacts: Path, inputs: dict, report: Path):
    """tests/desktop/run_dialogs.py in Debian 13's QGIS 3.40 desktop, inside the root (private mount namespace +
    chroot, scripts/setup_qgis_trixie.sh --run), under the root's own xvfb-run. The checkout is bound at its own
    path (inputs, script, artefacts) and on /sylva (the plugin, QGIS_PLUGINPATH=/opt/sylva-plugins)."""
    profiles = work / "profiles-3.40"        # a fresh profile with the plugin enabled (3.40 writes into it)
    ini = profiles / "profiles" / "default" / "QGIS" / "QGIS3.ini"
    ini.parent.mkdir(parents=True)
    ini.write_text("[PythonPlugins]\nprocessing=true\nsylva=true\n")
    env = [f"{k}={v}" for k, v in _desktop_env(report, artefacts, inputs).items()]
    return subprocess.run(["bash", str(TRIXIE_SETUP), "--run", "--bind", str(ROOT), "--bind", str(work),
                           "/usr/bin/env", "-u", "QT_QPA_PLATFORM", *env, "xvfb-run", "-a", "-s",
                           "-screen 0 1600x1000x24", "qgis", "--profiles-path", str(profiles), "--nologo",
                           "--noversioncheck", "--code", str(SCRIPT)],
                          capture_output=True, text=True, timeout=1200)


@pytest.fixture(scope="module", params=LANES)
def desktop_report(request, desktop_inputs):
    lane = request.param
    if lane == "3.22":
        qgis = shutil.which("qgis")
        if qgis is None or shutil.which("xvfb-run") is None:
            pytest.skip("the QGIS desktop or xvfb-run is not installed")
        if not (ROOT / ".qgis-profile").is_dir():
            pytest.skip("run scripts/setup.sh first: it makes the QGIS profile with the plugin enabled")
    else:
        _trixie_desktop_or_skip()
    base, inputs = desktop_inputs
    work = base / f"qgis-{lane}"
    work.mkdir()
    artefacts = ARTEFACTS if lane == "3.22" else ARTEFACTS.with_name(f"desktop-{lane}")
    if artefacts.exists():
        shutil.rmtree(artefacts)
    artefacts.mkdir(parents=True)
    report = work / "report.json"
    if lane == "3.22":
        env = {k: v for k, v in os.environ.items() if k != "QT_QPA_PLATFORM"}
        env.update(_desktop_env(report, artefacts, inputs), QGIS_PLUGINPATH=str(ROOT / ".qgis-plugins"))
        profiles = work / "profiles"           # a copy: the desktop writes its settings into the profile
        shutil.copytree(ROOT / ".qgis-profile", profiles)
        done = subprocess.run(["xvfb-run", "-a", "-s", "-screen 0 1600x1000x24", qgis, "--profiles-path",
                               str(profiles), "--nologo", "--noversioncheck", "--code", str(SCRIPT)],
                              capture_output=True, text=True, env=env, timeout=600)
    else:
        done = _run_desktop_340(base, artefacts, inputs, report)
    (artefacts / "qgis_stderr.txt").write_text(done.stderr[-20000:])
    assert report.is_file(), f"QGIS {lane} wrote no report (exit {done.returncode}): {done.stderr[-2000:]}"
    data = json.loads(report.read_text())
    (artefacts / "report.json").write_text(json.dumps(data, indent=1))
    assert data["error"] is None, data["error"]
    assert data["qgis"].startswith(lane), (lane, data["qgis"])
    return data


ALGORITHMS = ("canopyheightmodel", "treetops", "normalizeheight", "segmenttrees", "reconstructtrees",
              "exportmodels", "pipeline", "treefromsketch", "billboards", "terraintiles")


@pytest.mark.parametrize("name", ALGORITHMS)
def test_the_dialog_runs_with_its_defaults(desktop_report, name):
    entry = desktop_report["algorithms"][f"sylva:{name}"]
    assert "error" not in entry, entry.get("error")
    assert entry["refused_widgets"] == [], {n: entry["widgets"][n] for n in entry["refused_widgets"]}
    assert entry["accepted"], entry["check_message"]
    assert "-2147483648" not in entry["widgets"].values()
    assert entry["help_url"].startswith("file://") and entry["help_url"].endswith(f"{name}.html")
    # pressing Help opens that page, which ships with the plugin
    assert entry["help_buttons"] == 1 and entry["help_opened"] == [entry["help_url"]], entry["help_opened"]
    assert (ROOT / "resources" / "help" / f"{name}.html").is_file()
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


def test_the_pipeline_sets_the_project_terrain_in_a_newer_qgis(desktop_report):
    """QGIS >= 3.26 has a project terrain (3.22 has none): the pipeline's run makes its DTM the terrain."""
    if "terrain" not in desktop_report:
        pytest.skip(f"QGIS {desktop_report['qgis']} has no project terrain (QgsProjectElevationProperties: 3.26+)")
    assert desktop_report["terrain"] == ["raster", "DTM (terrain)"], desktop_report["terrain"]
