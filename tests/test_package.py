"""The plugin ZIP (scripts/package.sh) installs into a fresh QGIS profile and its provider loads there."""
from __future__ import annotations

import os
import shutil
import subprocess
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def build_zip(tmp_path) -> Path:
    out = tmp_path / "sylva.zip"
    done = subprocess.run(["bash", str(ROOT / "scripts" / "package.sh"), str(out)], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    return out


def test_the_zip_holds_only_the_plugin(tmp_path):
    names = zipfile.ZipFile(build_zip(tmp_path)).namelist()
    assert all(n.startswith("sylva/") for n in names)
    for needed in ("sylva/__init__.py", "sylva/metadata.txt", "sylva/LICENSE", "sylva/processing/provider.py",
                   "sylva/resources/help/pipeline.html", "sylva/resources/styles/crowns.qml"):
        assert needed in names
    for banned in ("tests/", "benchmarks/", ".venv/", "scripts/", "tools/", "__pycache__", ".qgis-"):
        assert not any(banned in n for n in names), banned
    assert "GNU GENERAL PUBLIC LICENSE" in zipfile.ZipFile(tmp_path / "sylva.zip").read("sylva/LICENSE").decode()


@pytest.mark.qgis
def test_the_zip_installs_into_a_fresh_profile(tmp_path):
    binary = shutil.which("qgis_process.bin") or shutil.which("qgis_process")
    if binary is None:
        pytest.skip("qgis_process is not installed")
    profile = tmp_path / "profile"
    plugins = profile / "profiles" / "default" / "python" / "plugins"
    plugins.mkdir(parents=True)
    zipfile.ZipFile(build_zip(tmp_path)).extractall(plugins)       # what "Install from ZIP" does
    env = {k: v for k, v in os.environ.items() if k not in ("QGIS_PLUGINPATH", "PYTHONDONTWRITEBYTECODE")}
    env.update(QT_QPA_PLATFORM="offscreen", QGIS_CUSTOM_CONFIG_PATH=str(profile))

    def qp(*args):
        return subprocess.run([binary, *args], capture_output=True, text=True, env=env, timeout=300)

    enabled = qp("plugins", "enable", "sylva")
    assert enabled.returncode == 0, enabled.stdout + enabled.stderr
    listed = qp("list")
    ids = {line.strip().split()[0] for line in listed.stdout.splitlines() if line.strip().startswith("sylva:")}
    assert {"sylva:segmenttrees", "sylva:pipeline", "sylva:treefromsketch"} <= ids, listed.stdout[-2000:]
    # The provider QGIS loaded is the unzipped copy (its modules were compiled there), not this checkout.
    assert list((plugins / "sylva" / "processing").glob("__pycache__/provider*.pyc"))
    assert list((plugins / "sylva" / "algorithms").glob("__pycache__/segment*.pyc"))


def test_missing_packages_message_names_the_python_qgis_runs(monkeypatch):
    """Inside QGIS sys.executable is the qgis binary: the hint must name a real Python of the same version."""
    import sys

    from sylva.plugin import deps

    monkeypatch.setattr(sys, "executable", shutil.which("qgis") or "/usr/bin/qgis")
    python = deps.interpreter()
    assert "qgis" not in Path(python).name
    ran = subprocess.run([python, "-c", "import sys; print(sys.version_info[0], sys.version_info[1])"],
                         capture_output=True, text=True, timeout=60)
    assert ran.stdout.split() == [str(v) for v in sys.version_info[:2]]
    hint = deps.install_hint(["laspy", "numpy<2"])
    assert f"{python} -m pip install" in hint and '"numpy<2"' in hint and "laspy" in hint


def test_pyproject_lists_every_package():
    """A non-editable install (``pip install .``) takes only the listed packages: every folder of the plugin
    with an ``__init__.py`` must be there (core/kernels was missing, so such an install could not import)."""
    import tomllib

    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {"sylva"} | {"sylva." + ".".join(p.parent.relative_to(ROOT).parts)
                         for folder in ("algorithms", "core", "plugin", "processing", "testing")
                         for p in (ROOT / folder).rglob("__init__.py")}
    assert found == listed, (sorted(found - listed), sorted(listed - found))
