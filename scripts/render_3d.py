"""Render Sylva's tree models in QGIS's own 3D map view to a PNG (headless, under Xvfb).

    xvfb-run -a -s "-screen 0 1920x1080x24" .venv/bin/python scripts/render_3d.py \\
        [--models trees_3d.gpkg | --glb trees.glb] [--size-m 50] [--out resources/screenshots/trees_3d.png]

Without ``--models``/``--glb`` the sample tile's corner of ``--size-m`` metres is
segmented, reconstructed (``sylva:reconstructtrees``, LOD 0) and exported
(``sylva:exportmodels``, MODELS_3D) first, through the CLI.  The MODELS_3D layer
gets ``resources/styles/models_3d.qml`` (its 3D renderer: polygon symbol,
absolute altitude, no extrusion) and is drawn by QGIS 3.22's 3D engine: a
``Qgs3DMapSettings`` in a print layout's 3D map item (``QgsLayoutItem3DMap``,
which renders through ``QgsOffscreen3DEngine`` and waits for the scene to load;
PyQGIS 3.22 exposes neither the engine nor ``Qgs3DUtils`` directly), exported
with ``QgsLayoutExporter``.  The 3D engine needs an OpenGL context, which
QT_QPA_PLATFORM=offscreen does not give: run under Xvfb (Mesa llvmpipe).

Prints the image size, the fraction of pixels that differ from the background
and the time taken.
"""
from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BACKGROUND = (235, 240, 245)


def _cli(*args: str) -> None:
    env = dict(os.environ, PROJ_DATA=os.environ.get("PROJ_DATA", "/usr/share/proj"))
    run = subprocess.run([sys.executable, "-m", "sylva.cli", "--quiet", *args], capture_output=True, text=True,
                         env=env)
    if run.returncode != 0:
        sys.exit(f"render_3d: sylva {args[0]} failed:\n{run.stderr}")


def sample_models(workdir: Path, size_m: float) -> Path:
    """MODELS_3D GeoPackage of a ``size_m`` corner of the bundled sample (segment, reconstruct, export)."""
    from sylva.core.io import read_cloud
    from sylva.core.io.las import write_las

    cloud = read_cloud(ROOT / "resources" / "sample" / "sample.laz")
    x0, y0 = cloud.xyz[:, 0].min(), cloud.xyz[:, 1].min()
    corner = cloud.subset((cloud.xyz[:, 0] < x0 + size_m) & (cloud.xyz[:, 1] < y0 + size_m))
    write_las(workdir / "corner.laz", corner)
    _cli("segmenttrees", f"--INPUT={workdir / 'corner.laz'}", f"--OUTPUT={workdir / 'segmented.laz'}")
    return glb_models(workdir, _reconstruct(workdir))


def _reconstruct(workdir: Path) -> Path:
    glb = workdir / "trees.glb"
    _cli("reconstructtrees", f"--INPUT={workdir / 'segmented.laz'}", "--LOD=0", f"--MODELS={glb}")
    return glb


def glb_models(workdir: Path, glb: Path) -> Path:
    out = workdir / "trees_3d.gpkg"
    _cli("exportmodels", f"--INPUT={glb}", f"--MODELS_3D={out}")
    return out


def render(models_gpkg: Path, out_png: Path, width_px: int = 1600, height_px: int = 1000,
           heading_deg: float = 35.0, pitch_deg: float = 62.0) -> dict:
    """Draw the models_3d layer of ``models_gpkg`` with QGIS's 3D renderer into ``out_png``."""
    from qgis.core import QgsApplication, QgsProject

    if not os.environ.get("DISPLAY"):
        sys.exit("render_3d: QGIS's 3D engine needs an X display with OpenGL; run under Xvfb: "
                 "xvfb-run -a -s '-screen 0 1920x1080x24' python scripts/render_3d.py ...")
    # the offscreen platform has no OpenGL: Qt3D's makeCurrent fails and the render never ends
    os.environ["QT_QPA_PLATFORM"] = "xcb"
    app = QgsApplication([], True)
    app.initQgis()
    try:
        return _render(models_gpkg, out_png, width_px, height_px, heading_deg, pitch_deg)
    finally:
        QgsProject.instance().clear()   # layers and layout go before QGIS shuts down (else a crash on exit)
        app.exitQgis()


def _render(models_gpkg, out_png, width_px, height_px, heading_deg, pitch_deg) -> dict:
    from qgis.core import (QgsLayoutExporter, QgsLayoutSize, QgsPrintLayout, QgsProject, QgsUnitTypes,
                           QgsVector3D, QgsVectorLayer)
    from qgis.PyQt.QtCore import QRectF
    from qgis.PyQt.QtGui import QColor, QImage

    from qgis._3d import (Qgs3D, QgsCameraPose, QgsDirectionalLightSettings,
                          QgsLayoutItem3DMap, QgsPointLightSettings)

    Qgs3D.initialize()
    project = QgsProject.instance()
    layer = QgsVectorLayer(f"{models_gpkg}|layername=models_3d", "trees 3D", "ogr")
    if not layer.isValid():
        sys.exit(f"render_3d: {models_gpkg} has no models_3d layer")
    message, ok = layer.loadNamedStyle(str(ROOT / "resources" / "styles" / "models_3d.qml"))
    if not ok or layer.renderer3D() is None:
        sys.exit(f"render_3d: the 3D style did not load: {message}")
    project.addMapLayer(layer)
    project.setCrs(layer.crs())
    extent = layer.extent()
    zs = [v.z() for f in layer.getFeatures() for v in f.geometry().vertices()]
    z_lo, z_hi = min(zs), max(zs)

    settings = flat_terrain_settings(extent)
    settings.setCrs(layer.crs())
    settings.setTransformContext(project.transformContext())
    settings.setPathResolver(project.pathResolver())
    settings.setMapThemeCollection(project.mapThemeCollection())
    cx, cy = extent.center().x(), extent.center().y()
    settings.setOrigin(QgsVector3D(cx, cy, 0.0))
    settings.setLayers([layer])
    settings.setTerrainRenderingEnabled(False)  # a shaded flat terrain came out blank in 3.22's layout export
    settings.setBackgroundColor(QColor(*BACKGROUND))
    sun = QgsDirectionalLightSettings()
    sun.setDirection(QgsVector3D(-0.5, -1.0, -0.3))
    sun.setIntensity(0.8)
    settings.setDirectionalLights([sun])
    lamp = QgsPointLightSettings()
    lamp.setPosition(QgsVector3D(0.0, z_hi + 200.0, 0.0))
    lamp.setIntensity(0.6)
    lamp.setConstantAttenuation(1.0)
    settings.setPointLights([lamp])
    settings.setFieldOfView(40.0)

    layout = QgsPrintLayout(project)
    layout.initializeDefaults()
    page_mm = (width_px * 25.4 / 96.0, height_px * 25.4 / 96.0)
    layout.pageCollection().page(0).setPageSize(QgsLayoutSize(page_mm[0], page_mm[1],
                                                               QgsUnitTypes.LayoutMillimeters))
    item = QgsLayoutItem3DMap(layout)
    item.attemptSetSceneRect(QRectF(0.0, 0.0, page_mm[0], page_mm[1]))
    item.setFrameEnabled(False)
    item.setMapSettings(settings)          # the item takes ownership
    pose = QgsCameraPose()
    # 3D world coordinates of QGIS 3.22: x = east, y = up, z = south, relative to the origin
    pose.setCenterPoint(QgsVector3D(0.0, (z_lo + z_hi) / 2.0 - 0.1 * (z_hi - z_lo), 0.0))
    span = max(extent.width(), extent.height(), z_hi - z_lo)
    pose.setDistanceFromCenterPoint(1.15 * span / (2.0 * math.tan(math.radians(20.0))))
    pose.setPitchAngle(pitch_deg)
    pose.setHeadingAngle(heading_deg)
    item.setCameraPose(pose)
    layout.addLayoutItem(item)

    out_png.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_png.with_name(f".{out_png.stem}.part.png")
    exporter = QgsLayoutExporter(layout)
    image_settings = QgsLayoutExporter.ImageExportSettings()
    image_settings.dpi = 96.0
    image_settings.generateWorldFile = False
    start = time.perf_counter()
    result = exporter.exportToImage(str(tmp), image_settings)
    seconds = time.perf_counter() - start
    if result != QgsLayoutExporter.Success:
        sys.exit(f"render_3d: the layout export failed (code {result})")
    os.replace(tmp, out_png)
    image = QImage(str(out_png))
    stats = image_stats(out_png)
    stats.update(width=image.width(), height=image.height(), seconds=seconds,
                 features=layer.featureCount())
    del exporter, layout, item
    return stats


def flat_terrain_settings(extent):
    """Qgs3DMapSettings with a flat terrain generator (not rendered).

    A 3D scene needs a terrain generator, and PyQGIS 3.22 does not expose
    QgsFlatTerrainGenerator: readXml creates one for a <terrain> element.
    """
    from qgis.core import QgsReadWriteContext
    from qgis.PyQt.QtXml import QDomDocument
    from qgis._3d import Qgs3DMapSettings

    doc = QDomDocument()
    ok = doc.setContent(
        '<qgis3d><terrain terrain-rendering-enabled="0" exaggeration="1"><generator type="flat">'
        f'<extent xmin="{extent.xMinimum()!r}" ymin="{extent.yMinimum()!r}" xmax="{extent.xMaximum()!r}" '
        f'ymax="{extent.yMaximum()!r}"/></generator></terrain></qgis3d>')
    assert ok[0] if isinstance(ok, tuple) else ok
    settings = Qgs3DMapSettings()
    settings.readXml(doc.documentElement(), QgsReadWriteContext())
    return settings


def image_stats(png: Path) -> dict:
    """Fraction of pixels that differ from the background (the most common colour), distinct colours."""
    import numpy as np
    from qgis.PyQt.QtGui import QImage

    image = QImage(str(png)).convertToFormat(QImage.Format_RGB888)
    w, h = image.width(), image.height()
    ptr = image.constBits()
    ptr.setsize(image.bytesPerLine() * h)
    rows = np.frombuffer(ptr, dtype=np.uint8).reshape(h, image.bytesPerLine())[:, :3 * w]
    rgb = rows.reshape(h, w, 3).astype(np.int16)
    colours, counts = np.unique(rgb.reshape(-1, 3), axis=0, return_counts=True)
    background = colours[np.argmax(counts)]
    differs = np.abs(rgb - background).max(axis=2) > 12
    return {"foreground_fraction": float(differs.mean()), "colours": int(len(colours)),
            "background": tuple(int(c) for c in background)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--models", type=Path, help="a GeoPackage with a models_3d layer (sylva:exportmodels)")
    ap.add_argument("--glb", type=Path, help="a Sylva GLB (sylva:reconstructtrees MODELS) to export first")
    ap.add_argument("--size-m", type=float, default=50.0, help="corner of the sample to model (default 50 m)")
    ap.add_argument("--out", type=Path, default=ROOT / "resources" / "screenshots" / "trees_3d.png")
    ap.add_argument("--width", type=int, default=1600)
    ap.add_argument("--height", type=int, default=1000)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="sylva-render-") as tmp:
        work = Path(tmp)
        start = time.perf_counter()
        if args.models:
            models = args.models
        elif args.glb:
            models = glb_models(work, args.glb)
        else:
            models = sample_models(work, args.size_m)
        prepared = time.perf_counter() - start
        stats = render(models, args.out, args.width, args.height)
    print(f"{args.out}: {stats['width']} x {stats['height']} px, {stats['features']} trees, "
          f"{100 * stats['foreground_fraction']:.1f} % of the pixels differ from the background, "
          f"{stats['colours']} colours; models {prepared:.1f} s, 3D render {stats['seconds']:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
