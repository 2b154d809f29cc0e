#!/usr/bin/env python3
"""Open a 3D Tiles tileset in QGIS's tiled scene layer (QGIS >= 3.34) and report what QGIS makes of it.

Runs with a QGIS >= 3.34 Python (Debian 13's, inside the root that scripts/setup_qgis_trixie.sh
installs); it imports nothing from Sylva. Usage::

    python3 qgis_tiled_scene_check.py TILESET_JSON --epsg 32632 --png OUT.png \\
        [--size 800 [150 ...]] [--extent X0,Y0,X1,Y1]

Prints one JSON object:

* ``valid`` / ``error``: ``QgsTiledSceneLayer(uri, "trees", "cesiumtiles").isValid()`` and why not;
* ``crs`` (the layer's), ``scene_crs`` (the provider's 3D scene CRS);
* ``extent`` in the layer CRS and ``extent_source`` transformed to ``--epsg`` (xmin, ymin, xmax, ymax);
* ``z_range`` of the provider (scene heights);
* ``tiles``: every tile of the index, walked from the root (child hierarchies of external tilesets
  fetched), each with its id, depth, geometric error, refinement, content URI, content size in
  bytes as QGIS retrieved it (``QgsTiledSceneIndex.retrieveContent``), whether that content is a
  GLB (``glTF`` magic), and its bounding volume's 2D bounds in ``--epsg``;
* ``tiles_in_extent``: how many tile ids ``QgsTiledSceneIndex.getTiles`` returns for a request
  filtered by the layer's whole 3D bounding volume (no geometric-error limit);
* ``render``: the layer drawn in 2D (``QgsMapSettings`` + ``QgsMapRendererParallelJob``) in
  ``--epsg`` on a white background into ``--png`` (a square around the layer's extent, or around
  ``--extent``, plus ``--margin``): ``map_extent`` (source CRS), ``width``/``height``
  (pixels), ``nonbackground_share`` (fraction of pixels that are not the background colour),
  ``errors`` (the render job's); ``renders``: one such record per ``--size`` (``render`` is the
  first; the others are written to ``OUT_<size>.png``).
"""
import argparse
import json
import os
import sys
from array import array


def _rect(r):
    return [r.xMinimum(), r.yMinimum(), r.xMaximum(), r.yMaximum()]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("tileset")
    ap.add_argument("--epsg", type=int, required=True, help="source CRS of the tileset (EPSG code)")
    ap.add_argument("--png", required=True, help="where to write the 2D rendering")
    ap.add_argument("--size", type=int, nargs="+", default=[800],
                    help="rendering width and height in pixels; more sizes: more renderings, OUT_<size>.png")
    ap.add_argument("--margin", type=float, default=0.05, help="map margin around the extent (fraction)")
    ap.add_argument("--extent", help="render this XMIN,YMIN,XMAX,YMAX (source CRS) instead of the layer's extent")
    a = ap.parse_args(argv)
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

    from qgis.core import (Qgis, QgsApplication, QgsCoordinateReferenceSystem, QgsCoordinateTransform,
                           QgsMapRendererParallelJob, QgsMapSettings, QgsProject, QgsRectangle,
                           QgsTiledSceneLayer, QgsTiledSceneRequest)
    from qgis.PyQt.QtCore import QSize
    from qgis.PyQt.QtGui import QColor, QImage

    app = QgsApplication([], False)
    app.initQgis()
    out = {"qgis": Qgis.version(), "tileset": a.tileset}
    try:
        layer = QgsTiledSceneLayer(a.tileset, "trees", "cesiumtiles")
        out["valid"] = layer.isValid()
        if not layer.isValid():
            err = layer.error()
            out["error"] = "" if err.isEmpty() else err.summary()
            return out
        prov = layer.dataProvider()
        src = QgsCoordinateReferenceSystem(f"EPSG:{a.epsg}")
        ctx = QgsProject.instance().transformContext()
        out["crs"] = layer.crs().authid()
        out["scene_crs"] = prov.sceneCrs().authid()
        ext = layer.extent()
        out["extent"] = _rect(ext)
        to_src = QgsCoordinateTransform(layer.crs(), src, ctx)
        ext_src = to_src.transformBoundingBox(ext)
        out["extent_source"] = _rect(ext_src)
        zr = prov.zRange()
        out["z_range"] = [zr.lower(), zr.upper()]

        # walk the whole tile hierarchy (fetching external tilesets' hierarchies on the way)
        index = prov.index()
        scene_to_src = QgsCoordinateTransform(prov.sceneCrs(), src, ctx)
        tiles = []
        todo = [(index.rootTile().id(), 0)]
        while todo:
            tid, depth = todo.pop(0)
            rec = {"id": tid, "depth": depth}
            if index.childAvailability(tid) == Qgis.TileChildrenAvailability.NeedFetching:
                # an external tileset: QGIS hangs its root's children under this tile and gives the
                # tile the external root's content
                rec["external_tileset"] = index.getTile(tid).resources().get("content")
                rec["fetched"] = bool(index.fetchHierarchy(tid))
            tile = index.getTile(tid)
            uri = tile.resources().get("content")
            rec.update({"geometric_error": tile.geometricError(),
                   "refine": tile.refinementProcess().name if hasattr(tile.refinementProcess(), "name")
                   else int(tile.refinementProcess()),
                   "content": uri, "children": list(index.childTileIds(tid))})
            if uri:
                data = bytes(index.retrieveContent(uri))
                rec["content_bytes"] = len(data)
                rec["glb"] = data[:4] == b"glTF"
            try:
                box = tile.boundingVolume().bounds(scene_to_src)
                rec["bounds_source"] = [box.xMinimum(), box.yMinimum(), box.xMaximum(), box.yMaximum()]
            except Exception as e:  # noqa: BLE001 - report, do not stop the walk
                rec["bounds_error"] = str(e)
            tiles.append(rec)
            todo.extend((c, depth + 1) for c in index.childTileIds(tid))
        out["tiles"] = tiles
        out["tile_count"] = len(tiles)
        req = QgsTiledSceneRequest()
        req.setFilterBox(prov.boundingVolume().box())
        out["tiles_in_extent"] = len(index.getTiles(req))

        # 2D rendering in the source CRS, at each requested size (QGIS picks the tiles whose geometric
        # error suits the scale: a small image draws coarser levels of detail)
        view = QgsRectangle(*map(float, a.extent.split(","))) if a.extent else ext_src
        side = max(view.width(), view.height()) * (1 + 2 * a.margin)
        cx, cy = view.center().x(), view.center().y()
        renders = []
        for k, size in enumerate(a.size):
            ms = QgsMapSettings()
            ms.setLayers([layer])
            ms.setDestinationCrs(src)
            ms.setOutputSize(QSize(size, size))
            ms.setBackgroundColor(QColor(255, 255, 255))
            ms.setExtent(QgsRectangle(cx - side / 2, cy - side / 2, cx + side / 2, cy + side / 2))
            job = QgsMapRendererParallelJob(ms)
            job.start()
            job.waitForFinished()
            img = job.renderedImage().convertToFormat(QImage.Format.Format_ARGB32)
            png = a.png if k == 0 else "%s_%d%s" % (os.path.splitext(a.png)[0], size, os.path.splitext(a.png)[1])
            img.save(png)
            px = array("I")
            bits = img.constBits()
            bits.setsize(img.sizeInBytes())
            px.frombytes(bytes(bits))
            nonbg = len(px) - px.count(QColor(255, 255, 255).rgba())
            renders.append({"png": png, "map_extent": _rect(ms.visibleExtent()), "width": img.width(),
                            "height": img.height(), "nonbackground_share": nonbg / max(1, len(px)),
                            "errors": [f"{e.layerID}: {e.message}" for e in job.errors()]})
        out["render"] = renders[0]
        out["renders"] = renders
        return out
    finally:
        app.exitQgis()


if __name__ == "__main__":
    result = main()
    print(json.dumps(result, indent=1))
    sys.exit(0 if result.get("valid") else 2)
