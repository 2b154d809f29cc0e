"""The README's pictures are renders of QGIS (scripts/render_3d.py; the desktop check is test_desktop_outputs.py)."""
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))
import pytest  # noqa: E402
import render_3d  # noqa: E402

SHOTS = ROOT / "resources" / "screenshots"


def test_readme_pictures_are_the_default_3d_view_and_the_map(qgis_app):
    readme = (ROOT / "README.md").read_text()
    for name in ("trees_3d.png", "crowns_2d.png"):
        assert (SHOTS / name).exists(), "scripts/render_3d.py writes it"
        assert f"resources/screenshots/{name}" in readme
    trees = render_3d.tree_pixels(render_3d.pixels(SHOTS / "trees_3d.png"))
    assert trees.mean() > 0.3                      # crowns: 40.7 % (the wood alone 4.7 %)
    rgb = render_3d.pixels(SHOTS / "crowns_2d.png").astype(int)
    assert ((rgb[..., 1] > rgb[..., 0] + 10) & (rgb[..., 1] > rgb[..., 2] + 5)).mean() > 0.2


def test_tree_pixels_are_the_bark_and_crown_colours_not_the_maps():
    import numpy as np

    bark = np.array([[[139, 90, 43], [70, 45, 22], [200, 140, 70]]], dtype=np.uint8)
    # crowns_3d.qml: in the light (ambient 64,110,24 to ambient + diffuse 134,230,48) and in the shade
    crowns = np.array([[[64, 110, 24], [99, 170, 36], [134, 230, 48], [8, 40, 0], [16, 48, 0], [24, 56, 4]]],
                      dtype=np.uint8)
    # the 2D map's greys and greens (crowns.qml's ramp, half transparent over the CHM; tree_tops.qml), white
    maps = np.array([[[235, 235, 235], [50, 50, 50], [46, 125, 50], [120, 198, 121], [255, 255, 255],
                      [0, 104, 55], [49, 163, 84], [194, 230, 153], [142, 199, 160], [27, 77, 27], [11, 61, 11]]],
                    dtype=np.uint8)
    assert render_3d.tree_pixels(bark).all() and not render_3d.crown_pixels(bark).any()
    assert render_3d.tree_pixels(crowns).all() and render_3d.crown_pixels(crowns).all()
    assert not render_3d.tree_pixels(maps).any()


@pytest.mark.parametrize("style", ["models_3d.qml", "crowns_3d.qml"])
def test_3d_style_stands_models_without_base_z_on_their_lowest_point(qgis_app, style):
    """models_3d.qml's and crowns_3d.qml's height is -base_z, or minus the lowest vertex when a layer has no
    base_z."""
    from qgis._3d import Qgs3D, QgsPolygon3DSymbol, QgsVectorLayer3DRenderer
    from qgis.core import (QgsApplication, QgsExpressionContext, QgsExpressionContextUtils, QgsFeature,
                           QgsGeometry, QgsVectorLayer)
    from qgis.PyQt import sip

    if QgsApplication.renderer3DRegistry().rendererMetadata("vector") is None:
        Qgs3D.initialize()   # the desktop does it at start; a bare QgsApplication does not

    from sylva.processing.outputs import StyledOutput

    for fields, base in (("&field=base_z:double", 250.0), ("", None)):
        layer = QgsVectorLayer(f"MultiPolygonZ?crs=EPSG:32632{fields}", "m", "memory")
        feature = QgsFeature(layer.fields())
        feature.setGeometry(QgsGeometry.fromWkt(
            "MultiPolygonZ(((0 0 251, 1 0 251, 0 1 270, 0 0 251)))"))
        if base is not None:
            feature.setAttributes([base])
        layer.dataProvider().addFeatures([feature])
        StyledOutput.get(style).postProcessLayer(layer, _NoProject(), None)
        renderer = sip.cast(layer.renderer3D(), QgsVectorLayer3DRenderer)
        prop = sip.cast(renderer.symbol(), QgsPolygon3DSymbol).dataDefinedProperties().property(
            QgsPolygon3DSymbol.PropertyHeight)
        context = QgsExpressionContext(QgsExpressionContextUtils.globalProjectLayerScopes(layer))
        context.setFeature(next(layer.getFeatures()))
        value, ok = prop.valueAsDouble(context, 0.0)
        assert ok and value == (-250.0 if base is not None else -251.0)


class _NoProject:
    @staticmethod
    def project():
        return None
