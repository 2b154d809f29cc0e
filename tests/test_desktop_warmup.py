"""The plugin's first load in the QGIS desktop (Xvfb), as a user meets it after installing: it says it prepares
Sylva's compiled routines, compiles them in a separate Python process while the interface stays usable (a new
3D view opens meanwhile; a warm-up thread inside QGIS froze 3.22's 3D view), and says when Sylva is ready."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "tests" / "desktop" / "first_load.py"

pytestmark = [pytest.mark.qgis, pytest.mark.slow]


def test_first_load_compiles_in_another_process_and_says_so(tmp_path):
    qgis = shutil.which("qgis")
    if qgis is None or shutil.which("xvfb-run") is None:
        pytest.skip("the QGIS desktop or xvfb-run is not installed")
    if not (ROOT / ".qgis-profile").is_dir():
        pytest.skip("run scripts/setup.sh first: it makes the QGIS profile with the plugin enabled")
    profiles = tmp_path / "profiles"
    shutil.copytree(ROOT / ".qgis-profile", profiles)
    cache = tmp_path / "numba-cache"          # empty: the kernels are not compiled yet for this QGIS
    cache.mkdir()
    report = tmp_path / "report.json"
    env = {k: v for k, v in os.environ.items() if k != "QT_QPA_PLATFORM"}
    env.update(SYLVA_DESKTOP_REPORT=str(report), QGIS_PLUGINPATH=str(ROOT / ".qgis-plugins"),
               NUMBA_CACHE_DIR=str(cache))
    done = subprocess.run(["xvfb-run", "-a", "-s", "-screen 0 1600x1000x24", qgis, "--profiles-path", str(profiles),
                           "--nologo", "--noversioncheck", "--code", str(SCRIPT)],
                          capture_output=True, text=True, env=env, timeout=600)
    assert report.is_file(), f"QGIS wrote no report (exit {done.returncode}): {done.stderr[-2000:]}"
    data = json.loads(report.read_text())
    assert data["error"] is None, data["error"]
    steps = [s for _, s in data["steps"]]
    assert steps[-1] == "done", steps              # the interface stayed alive through the 3D view
    assert any("Preparing Sylva's compiled routines" in t for t in data["bar_at_start"]), data["bar_at_start"]
    assert any("sylva.plugin.warmup" in p for p in data["processes_at_start"]), data["processes_at_start"]
    assert data["python_threads"] == 0             # no QgsTask: nothing of it runs in QGIS's thread pool
    assert any("Sylva is ready" in t for t in data["bar_at_end"]), data["bar_at_end"]
    assert list(cache.glob("sylva-warm-*.json")), sorted(p.name for p in cache.iterdir())[:5]
