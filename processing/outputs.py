"""Load a run's layers into the project when its algorithm finishes in QGIS, each with its Sylva style.

Processing loads feature sinks and raster destinations by itself, but not the
files inside a folder output such as ``sylva:pipeline``'s OUTPUT_FOLDER.
:func:`load_on_completion` asks the context to load them at the end of the
run (``QgsProcessingContext.addLayerToLoadOnCompletion``), each with a
post-processor (:class:`StyledOutput`) that applies its ``.qml`` from
``resources/styles``, hides the busy point layers and puts the rasters at
the bottom of the layer tree (Processing loads them in the order of their
sources' names).

The 3D view: ``models_3d.qml`` (the wood) and ``crowns_3d.qml`` (a green crown envelope
per tree) stand every tree on the terrain (altitude
clamping *relative*, bound to each triangle's centroid, height ``-"base_z"``, else minus the lowest vertex),
so on QGIS 3.22's flat terrain at 0 m a new 3D view shows the forest on the
2D map without any setting; with the run's ``dtm.vrt`` as a DEM terrain
(3D view ▸ Configure ▸ Terrain) the trees stand on it.  QGIS 3.22 has no
project-wide terrain; from QGIS 3.26 the project's terrain
(``QgsProject.elevationProperties()``) is set to the DTM, which new 3D views
read (Sylva, not in a paper).
"""
from __future__ import annotations

from pathlib import Path

from qgis.core import QgsProcessingContext, QgsProcessingLayerPostProcessorInterface, QgsProcessingUtils

STYLES = Path(__file__).resolve().parents[1] / "resources" / "styles"

#: forest.gpkg's layers: (layer name, style, visible when loaded).
FOREST_LAYERS = (
    ("trees", None, True),
    ("tree_tops", "tree_tops.qml", True),
    ("crowns", "crowns.qml", True),
    ("crown_points", "crown_points.qml", False),
    ("stem_points", "stem_points.qml", False),
    ("skeletons", "skeletons.qml", False),
    ("models_3d", "models_3d.qml", True),
    ("crowns_3d", "crowns_3d.qml", True),
)
#: The run's rasters: (result name, file, layer name, style, visible).
RUN_RASTERS = (
    ("DTM", "dtm.vrt", "DTM (terrain)", "dtm.qml", True),
    ("CHM", "chm.vrt", "CHM (canopy height)", "chm.qml", True),
)


class StyledOutput(QgsProcessingLayerPostProcessorInterface):
    """Applies a .qml to a layer Processing has just loaded; may hide it or move it to the bottom.

    Used for every layer Sylva's algorithms have QGIS load (sinks with a style, and the folder outputs
    here).  ``setPostProcessor`` transfers ownership to QGIS, which deletes the post-processor once the
    layer is loaded: each layer gets an instance of its own (one shared by a second run in a desktop
    session failed with "wrapped C/C++ object ... has been deleted"), and ``_instances`` keeps the Python
    side of the last ones referenced until QGIS has used them.
    """

    _instances: list = []

    def __init__(self, qml, visible: bool, bottom: bool, terrain: bool = False):
        super().__init__()
        self.qml, self.visible, self.bottom, self.terrain = qml, visible, bottom, terrain

    @classmethod
    def get(cls, style, visible: bool = True, bottom: bool = False, terrain: bool = False) -> "StyledOutput":
        """A new post-processor for one layer (kept alive in ``_instances``)."""
        post = cls(str(STYLES / style) if style else None, visible, bottom, terrain)
        cls._instances = cls._instances[-200:] + [post]
        return post

    def postProcessLayer(self, layer, context, feedback):  # noqa: N802
        if self.qml:
            message, ok = layer.loadNamedStyle(self.qml)
            if not ok and feedback is not None:
                feedback.reportError(f"style {self.qml} not applied: {message}", fatalError=False)
        project = context.project() if context is not None else None
        node = project.layerTreeRoot().findLayer(layer.id()) if project is not None else None
        if node is not None:
            if self.bottom:   # rasters under the vectors, the DTM under the CHM (loaded after it)
                parent = node.parent()
                clone = node.clone()
                parent.addChildNode(clone)
                parent.removeChildNode(node)
                node = clone
            node.setItemVisibilityChecked(self.visible)
        if self.terrain and project is not None:
            _project_terrain(project, layer)
        layer.triggerRepaint()


def _add(context, uri: str, name: str, hint, post) -> None:
    details = QgsProcessingContext.LayerDetails(name, context.project(), name, hint)
    details.setPostProcessor(post)
    context.addLayerToLoadOnCompletion(uri, details)


def load_on_completion(algorithm_id: str, files: dict, values: dict, context) -> list:
    """Have Processing load the layers of ``sylva:pipeline`` (forest.gpkg's, dtm.vrt, chm.vrt) or of
    ``sylva:terraintiles`` (dtm.vrt, chm.vrt) at the end of the run; returns their sources.

    ``files``/``values``: the run's Result (OUTPUT_FOLDER, DTM, CHM, GEOPACKAGE).
    Only the desktop acts on the list (the dialog, the batch dialog and
    ``processing.runAndLoadResults`` call Processing's handleAlgorithmResults);
    ``qgis_process`` and ``processing.run`` ignore it.
    """
    if algorithm_id not in ("pipeline", "terraintiles") or context.project() is None:
        return []
    added = []
    gpkg = values.get("GEOPACKAGE")
    if gpkg and Path(gpkg).is_file():
        present = _gpkg_layers(gpkg)
        for layer, style, visible in FOREST_LAYERS:
            if layer in present:
                uri = f"{gpkg}|layername={layer}"
                _add(context, uri, layer, QgsProcessingUtils.LayerHint.Vector, StyledOutput.get(style, visible))
                added.append(uri)
    for key, _file, name, style, visible in RUN_RASTERS:
        path = files.get(key)
        if path and Path(path).is_file():
            _add(context, path, name, QgsProcessingUtils.LayerHint.Raster,
                 StyledOutput.get(style, visible, True, terrain=key == "DTM"))
            added.append(path)
    return added


def _gpkg_layers(path) -> set:
    import sqlite3

    try:
        with sqlite3.connect(f"file:{path}?mode=ro", uri=True) as db:
            return {r[0] for r in db.execute("SELECT table_name FROM gpkg_contents")}
    except sqlite3.Error:
        return set()


def _project_terrain(project, layer) -> None:
    """QGIS >= 3.26: the project's terrain becomes the DTM ``layer`` (3.22 has no project terrain).

    Called from the DTM's post-processor, on the main thread once QGIS has loaded the layer: an earlier
    form connected to ``layersAdded`` from ``processAlgorithm``, i.e. from the dialog's worker thread
    (a Python slot then lives in that thread), and QGIS 3.40's dialog left the terrain flat."""
    props = getattr(project, "elevationProperties", None)
    if props is None:
        return
    try:
        from qgis.core import QgsRasterDemTerrainProvider
    except ImportError:  # pragma: no cover - QGIS < 3.26
        return
    provider = QgsRasterDemTerrainProvider()
    provider.setLayer(layer)
    props().setTerrainProvider(provider)
