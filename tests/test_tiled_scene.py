"""Sylva's 3D Tiles open in QGIS's tiled scene layer (QGIS >= 3.34), as the issue asks.

Debian 12's QGIS 3.22 has no tiled scene layer, so the check runs Debian 13's QGIS in the separate
root file system ``.qgis-trixie`` that ``scripts/setup_qgis_trixie.sh`` installs (``scripts/test.sh``
does): ``scripts/qgis_tiled_scene_check.py`` opens a tileset as
``QgsTiledSceneLayer(uri, "trees", "cesiumtiles")``, walks its whole tile index, fetches every
content and renders the layer in 2D in the source CRS. The tilesets are made from the bundled
sample as users get them: ``sylva:pipeline`` (run-level tileset.json with one external tileset per
tile) and ``sylva:exportmodels`` (a tileset from the pipeline's GLB); the truth is the pipeline's
trees table (forest.gpkg).
"""
import json
import os
import subprocess
from pathlib import Path
from urllib.parse import unquote, urlparse

import numpy as np
import pytest
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[1]
TRIXIE = ROOT / ".qgis-trixie"
SETUP = ROOT / "scripts" / "setup_qgis_trixie.sh"


@pytest.fixture(scope="module")
def trixie():
    if not (TRIXIE / ".sylva-installed").exists():
        pytest.skip("QGIS >= 3.34 is not installed in .qgis-trixie (Debian 12's QGIS 3.22 has no tiled scene "
                    "layer): bash scripts/setup_qgis_trixie.sh installs it, scripts/test.sh does")
    if os.geteuid() != 0:
        pytest.skip("entering the .qgis-trixie root needs root (unshare + chroot)")
    probe = subprocess.run(["bash", str(ROOT / "scripts" / "setup_qgis_trixie.sh"), "--run", "/bin/true"],
                           capture_output=True, text=True, timeout=60)
    if probe.returncode != 0:
        pytest.skip(f"this sandbox does not let root enter .qgis-trixie (mount namespace + chroot): "
                    f"{probe.stderr.strip()[-300:]}")
    return TRIXIE


@pytest.fixture(scope="module")
def forest(sample_laz, tmp_path_factory):
    """sylva:pipeline on a 60 m x 60 m corner of the sample, then sylva:exportmodels on its GLB.

    Returns (folder, trees table columns, EPSG code)."""
    from sylva.algorithms import get
    from sylva.algorithms.spec import Feedback
    from sylva.core.io import read_cloud, write_las
    from sylva.core.io.gpkg import read_gpkg

    base = tmp_path_factory.mktemp("tiledscene")
    cloud = read_cloud(sample_laz)
    x0, y0 = cloud.xyz[:, 0].min(), cloud.xyz[:, 1].min()
    write_las(base / "corner.laz", cloud.subset((cloud.xyz[:, 0] < x0 + 60) & (cloud.xyz[:, 1] < y0 + 60)))
    pipeline = get("sylva:pipeline")
    args = {p.name: p.default for p in pipeline.params}
    args.update(INPUT=str(base / "corner.laz"), OUTPUT_FOLDER=str(base / "out"), WORKERS=1)
    result = pipeline.run(args, Feedback())
    assert result.values["FAILED_TILES"] == 0 and result.values["TREE_COUNT"] >= 10
    export = get("sylva:exportmodels")
    args = {p.name: p.default for p in export.params}
    args.update({p.name: None for p in export.outputs})
    args.update(INPUT=str(base / "out" / "models" / "corner.glb"), TILES=str(base / "exported"))
    export.run(args, Feedback())
    trees = read_gpkg(base / "out" / "forest.gpkg", "trees").columns
    epsg = json.loads((base / "exported" / "tileset.json").read_text())["extras"]["georeference"]["crs_epsg"]
    return base, trees, epsg


def qgis_check(tileset: Path, bind: Path, epsg: int, extent=None, sizes=(600,)) -> dict:
    """scripts/qgis_tiled_scene_check.py's JSON for ``tileset`` (``bind``: a folder holding it; paths
    read the same inside the QGIS root and out)."""
    png = tileset.parent / (tileset.stem + "_qgis.png")
    view = ["--extent", ",".join(map(str, extent))] if extent is not None else []
    run = subprocess.run(["bash", str(SETUP), "--run", "--bind", str(bind), "python3",
                          "/sylva/scripts/qgis_tiled_scene_check.py", str(tileset), "--epsg", str(epsg),
                          "--png", str(png), "--size", *map(str, sizes), *view],
                         capture_output=True, text=True, timeout=300)
    assert run.stdout.strip(), f"no output from QGIS (exit {run.returncode}): {run.stderr[-2000:]}"
    return json.loads(run.stdout)


def _tiles_in(tileset: Path):
    """(tile count, GLB files) of a tileset and its external tilesets, as the JSON says."""
    def walk(tile, folder):
        n, glbs = 1, []
        uri = tile.get("content", {}).get("uri")
        if uri and uri.endswith(".json"):
            sub, sub_glbs = _tiles_in(folder / uri)
            n, glbs = n + sub - 1, glbs + sub_glbs   # QGIS merges an external root into the referring tile
        elif uri:
            glbs.append((folder / uri).resolve())
        for child in tile.get("children", []):
            cn, cg = walk(child, folder)
            n, glbs = n + cn, glbs + cg
        return n, glbs

    return walk(json.loads(tileset.read_text())["root"], tileset.parent)


def _check_index(out, tileset):
    n_json, glbs = _tiles_in(tileset)
    assert out["tile_count"] == n_json
    fetched = {Path(unquote(urlparse(t["content"]).path)): t for t in out["tiles"] if t.get("content")}
    assert sorted(fetched) == sorted(glbs), "every GLB of the tileset is a tile QGIS reaches"
    for path, t in fetched.items():
        assert t["glb"] and t["content_bytes"] == path.stat().st_size, path


def _check_extent(out, trees, tight: bool):
    x0, y0, x1, y1 = out["extent_source"]
    xy = np.column_stack([trees["base_x"], trees["base_y"]])
    # within a metre: the extent holds every tree's base (the trees table is the truth)
    assert np.all((xy[:, 0] >= x0 - 1) & (xy[:, 0] <= x1 + 1) & (xy[:, 1] >= y0 - 1) & (xy[:, 1] <= y1 + 1))
    if tight:   # and it is no larger than the crowns around them
        reach = float(np.max(trees["crown_diameter"])) / 2 + 2.0
        assert x0 >= xy[:, 0].min() - reach and y0 >= xy[:, 1].min() - reach
        assert x1 <= xy[:, 0].max() + reach and y1 <= xy[:, 1].max() + reach


def _rgb(png) -> np.ndarray:
    """(h, w, 3) RGB of a PNG, read with the host's Qt (QImage: no Pillow needed)."""
    from qgis.PyQt.QtGui import QImage

    image = QImage(str(png)).convertToFormat(QImage.Format_RGB888)
    assert not image.isNull(), f"{png} is not an image"
    h, w = image.height(), image.width()
    ptr = image.constBits()
    ptr.setsize(image.bytesPerLine() * h)
    return np.frombuffer(ptr, dtype=np.uint8).reshape(h, image.bytesPerLine())[:, :3 * w].reshape(h, w, 3).copy()


def _leafy_share(r) -> float:
    """Share of the drawn pixels of a rendering that are green (leaf cards; the wood is grey)."""
    img = _rgb(r["png"]).astype(int)
    drawn = np.any(img != 255, axis=2)
    return float(((img[..., 1] > img[..., 0] + 20) & drawn).sum() / max(1, drawn.sum()))


def _check_render(r, trees):
    """Rendering ``r`` (one of the check's ``renders``) draws the trees where the trees table has them."""
    assert r["errors"] == [] and r["nonbackground_share"] > 0.05
    img = _rgb(r["png"])
    drawn = np.any(img != 255, axis=2)
    assert abs(drawn.mean() - r["nonbackground_share"]) < 0.01
    h, w = drawn.shape
    x0, y0, x1, y1 = r["map_extent"]
    rows, cols = np.nonzero(drawn)
    px = np.column_stack([x0 + (cols + 0.5) * (x1 - x0) / w, y1 - (rows + 0.5) * (y1 - y0) / h])
    tops = np.column_stack([trees["x"], trees["y"]])
    bases = np.column_stack([trees["base_x"], trees["base_y"]])
    radius = np.asarray(trees["crown_diameter"], dtype=float) / 2
    # every tree is drawn where the trees table puts it: tree pixels within 1 m (or a pixel) of its top
    d, _ = cKDTree(px).query(tops)
    near = max(1.0, 1.5 * (x1 - x0) / w)
    assert np.all(d < near), f"trees without pixels near their tops: {np.flatnonzero(d >= near)}"
    # and nothing is drawn away from the trees: the drawn pixels lie in the union of the crowns (the
    # table's crown diameter, around the top or the base, 8 nearest trees) widened by 1 m
    excess = np.full(len(px), np.inf)
    for centres in (tops, bases):
        d, i = cKDTree(centres).query(px, k=min(8, len(centres)))
        excess = np.minimum(excess, (d - radius[i]).min(axis=1))
    assert (excess > 1.0).mean() < 0.01, f"{(excess > 1.0).mean():.2%} of the drawn pixels lie outside every crown"
    assert excess.max() < 3.0


@pytest.fixture(scope="module")
def exported(trixie, forest):
    base, _, epsg = forest
    return qgis_check(base / "exported" / "tileset.json", base, epsg, sizes=(600, 120))


def test_exported_tileset_in_qgis_tiled_scene_layer(trixie, forest, exported):
    base, trees, epsg = forest
    tileset = base / "exported" / "tileset.json"
    out = exported
    assert out["valid"], out.get("error")
    assert out["qgis"] >= "3.34" and out["crs"] == "EPSG:4979" and out["scene_crs"] == "EPSG:4978"
    _check_index(out, tileset)
    doc = json.loads(tileset.read_text())
    assert out["tiles_in_extent"] == len(doc["root"]["children"])   # REPLACE: the full models replace the root
    # heights (the CRS has no vertical datum: ellipsoidal, as written): from the lowest base to the highest top
    top = float(np.max(np.asarray(trees["ground_z"]) + np.asarray(trees["height"])))
    assert float(np.min(trees["base_z"])) - 1.0 <= out["z_range"][0] and top - 3.0 <= out["z_range"][1] <= top + 3.0
    _check_extent(out, trees, tight=True)
    # close up QGIS draws the full models (wood and leaf cards), from afar the coarse root (wood only),
    # both in place
    full, coarse = out["renders"]
    _check_render(full, trees)
    _check_render(coarse, trees)
    assert _leafy_share(full) > 0.2 and _leafy_share(coarse) < 0.01


def test_pipeline_tileset_in_qgis_tiled_scene_layer(trixie, forest):
    base, trees, epsg = forest
    tileset = base / "out" / "models" / "tileset.json"
    # draw the trees' area, as the exported tileset's test does
    reach = float(np.max(trees["crown_diameter"])) / 2 + 2.0
    area = [float(np.min(trees["base_x"])) - reach, float(np.min(trees["base_y"])) - reach,
            float(np.max(trees["base_x"])) + reach, float(np.max(trees["base_y"])) + reach]
    out = qgis_check(tileset, base, epsg, extent=area)
    assert out["valid"], out.get("error")
    _check_index(out, tileset)
    external = [t for t in out["tiles"] if t.get("external_tileset")]
    assert len(external) == 1 and external[0]["fetched"]
    _check_extent(out, trees, tight=True)
    _check_render(out["render"], trees)


def test_check_catches_a_misplaced_tileset(trixie, forest, exported):
    """The checks above are not vacuous: the same tileset moved 4 m east fails them."""
    import shutil

    base, trees, epsg = forest
    moved = base / "moved"
    if not moved.exists():
        shutil.copytree(base / "exported", moved)
    doc = json.loads((moved / "tileset.json").read_text())
    m = doc["root"]["transform"]
    m[12:15] = (np.array(m[12:15]) + 4.0 * np.array(m[0:3])).tolist()    # + 4 m along the ENU east axis
    (moved / "tileset.json").write_text(json.dumps(doc))
    out = qgis_check(moved / "tileset.json", base, epsg)
    assert out["valid"]
    x0 = out["extent_source"][0]
    assert x0 == pytest.approx(exported["extent_source"][0] + 4.0, abs=0.05)
    with pytest.raises(AssertionError, match="outside every crown|without pixels"):
        _check_render(out["render"], trees)
