"""scripts/render_3d.py: QGIS's own 3D engine draws the exported trees (under Xvfb) into a non-empty PNG."""
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "render_3d.py"
SCREENSHOT = ROOT / "resources" / "screenshots" / "trees_3d.png"


def _pixels(png: Path) -> np.ndarray:
    """(h, w, 3) uint8 RGB of a PNG (QImage: no Pillow needed)."""
    from qgis.PyQt.QtGui import QImage

    image = QImage(str(png)).convertToFormat(QImage.Format_RGB888)
    assert not image.isNull(), f"{png} is not an image"
    h, w = image.height(), image.width()
    ptr = image.constBits()
    ptr.setsize(image.bytesPerLine() * h)
    rows = np.frombuffer(ptr, dtype=np.uint8).reshape(h, image.bytesPerLine())[:, :3 * w]
    return rows.reshape(h, w, 3).copy()


def _tree_pixels(rgb: np.ndarray) -> np.ndarray:
    """Pixels that differ from the background (the most common colour) by more than 12 levels."""
    colours, counts = np.unique(rgb.reshape(-1, 3), axis=0, return_counts=True)
    background = colours[np.argmax(counts)].astype(int)
    return np.abs(rgb.astype(int) - background).max(axis=2) > 12


@pytest.fixture(scope="module")
def models_gpkg(sample_laz, tmp_path_factory):
    """MODELS_3D of a 25 m corner of the sample (reconstructed and exported in-process)."""
    from sylva.algorithms import get
    from sylva.algorithms.spec import Feedback
    from sylva.core.export.gltf import write_glb
    from sylva.core.export.model import ExportFrame, TreeModel
    from sylva.core.forest import ModelOptions, model_trees
    from sylva.core.io import read_cloud
    from sylva.core.io.gpkg import write_gpkg
    from sylva.core.measure import tree_metrics
    from sylva.core.segment import segment_trees
    from sylva.core.terrain import normalize

    cloud = read_cloud(sample_laz)
    x0, y0 = cloud.xyz[:, 0].min(), cloud.xyz[:, 1].min()
    corner = normalize(cloud.subset((cloud.xyz[:, 0] < x0 + 25) & (cloud.xyz[:, 1] < y0 + 25)))
    labels = segment_trees(corner)
    trees = model_trees(corner, labels, tree_metrics(corner, labels), ModelOptions(lod=0, leaves="none"))
    models = [TreeModel(t.tree_id, [t.record["base_x"], t.record["base_y"], t.record["base_z"]], t.wood, None,
                        t.record) for t in trees]
    folder = tmp_path_factory.mktemp("render")
    glb = folder / "trees.glb"
    write_glb(models, glb, ExportFrame.from_cloud(corner))
    alg = get("exportmodels")
    table = alg.run({**{p.name: p.default for p in alg.params}, "INPUT": str(glb)}, Feedback()).vectors["MODELS_3D"]
    assert len(table) == len(models)
    return write_gpkg(folder / "trees_3d.gpkg", [table]), len(models)


def test_qgis_3d_view_draws_the_trees(models_gpkg, tmp_path):
    if shutil.which("xvfb-run") is None:
        pytest.skip("xvfb-run is absent: QGIS's 3D engine needs an X display with OpenGL "
                    "(Debian: apt-get install -y xvfb)")
    gpkg, n_trees = models_gpkg
    out = tmp_path / "trees.png"
    env = dict(os.environ, PROJ_DATA=os.environ.get("PROJ_DATA", "/usr/share/proj"))
    env.setdefault("XDG_RUNTIME_DIR", f"/tmp/runtime-{os.getuid()}")
    Path(env["XDG_RUNTIME_DIR"]).mkdir(mode=0o700, exist_ok=True)
    run = subprocess.run(["xvfb-run", "-a", "-s", "-screen 0 1280x1024x24", sys.executable, str(SCRIPT),
                          f"--models={gpkg}", f"--out={out}", "--width=480", "--height=320"],
                         capture_output=True, text=True, env=env, timeout=180)
    assert run.returncode == 0, run.stdout + run.stderr
    assert f"{n_trees} trees" in run.stdout
    rgb = _pixels(out)
    assert rgb.shape == (320, 480, 3)
    trees = _tree_pixels(rgb)
    assert 0.005 < trees.mean() < 0.5          # the trees are drawn, and they are not everything
    # drawn with the style's bark material (Phong-shaded brown: red > green > blue)
    r, g, b = (rgb[trees].astype(int).mean(axis=0))
    assert r > g > b
    # the trees stand upright: their pixels span much more height than the first and last rows
    rows = np.flatnonzero(trees.any(axis=1))
    assert rows.max() - rows.min() > 0.4 * rgb.shape[0]


def test_readme_picture_is_not_empty(qgis_app):
    assert SCREENSHOT.exists(), "python scripts/render_3d.py (under xvfb-run) writes it"
    rgb = _pixels(SCREENSHOT)
    trees = _tree_pixels(rgb)
    assert trees.mean() > 0.01
    assert "resources/screenshots/trees_3d.png" in (ROOT / "README.md").read_text()
