"""Headless `qgis_process`, as users run batches: the provider loads, algorithms run, errors are clear."""
import os
import subprocess
from pathlib import Path

import pytest

from conftest import ROOT, qgis_process_binary
from badfiles import make_bad_inputs

pytestmark = pytest.mark.qgis


def qgis_process(*args):
    env = dict(os.environ)
    profile = ROOT / ".qgis-profile"
    if not profile.exists():
        pytest.skip("run scripts/setup.sh first: it enables the plugin in .qgis-profile")
    env.update(QT_QPA_PLATFORM="offscreen", QGIS_PLUGINPATH=str(ROOT / ".qgis-plugins"),
               QGIS_CUSTOM_CONFIG_PATH=str(profile))
    return subprocess.run([qgis_process_binary(), *args], capture_output=True, text=True, env=env, timeout=300)


def test_list_shows_sylva_algorithms():
    out = qgis_process("list")
    assert out.returncode == 0, out.stderr
    assert "sylva:canopyheightmodel" in out.stdout
    assert "sylva:treetops" in out.stdout


def test_run_treetops_writes_a_layer_qgis_opens(sample_laz, tmp_path, qgis_app):
    from qgis.core import QgsVectorLayer

    target = tmp_path / "tops.gpkg"
    out = qgis_process("run", "sylva:treetops", f"--INPUT={sample_laz}", "--WINDOW=0", f"--OUTPUT={target}")
    assert out.returncode == 0, out.stdout + out.stderr
    layer = QgsVectorLayer(str(target), "tops", "ogr")
    assert layer.isValid() and layer.featureCount() > 20


def test_bad_input_message_without_traceback(sample_laz, tmp_path):
    path, words = make_bad_inputs(tmp_path / "bad", sample_laz)["no_crs"]
    out = qgis_process("run", "sylva:treetops", f"--INPUT={path}", f"--OUTPUT={tmp_path / 'x.gpkg'}")
    assert out.returncode != 0
    text = out.stdout + out.stderr
    assert path.name in text and words in text
    assert "Traceback" not in text
    assert not (tmp_path / "x.gpkg").exists()
