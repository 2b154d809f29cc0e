"""Vector and raster layer inputs reach an algorithm's run() the same way from QGIS and from the CLI."""
from __future__ import annotations

import numpy as np
import pyproj
import pytest
import shapely

from sylva.algorithms import spec as S
from sylva.core.errors import InputError
from sylva.core.table import VectorTable

STROKE = [(0.0, 0.0, 1.0), (0.5, 2.0, 1.5), (0.2, 4.0, 2.0)]


def _echo(args, feedback):
    table = args["STROKES"]
    coords = np.asarray(shapely.get_coordinates(table.geometries[0], include_z=True))
    return S.Result(values={
        "N": len(table), "KIND": table.geometry_type, "EPSG": table.crs.to_epsg() if table.crs else None,
        "LAST_Z": float(coords[-1, 2]), "LABEL": str(table.columns["label"][0]),
        "IMAGE": args["IMAGE"], "MASK": None if args["MASK"] is None else len(args["MASK"])})


ECHO = S.Algorithm(
    id="echolayers", name="Echo layers", group="Test", summary="Returns what it was given.", run=_echo,
    params=(S.Param("STROKES", S.VECTOR, "Strokes", geometry=S.LINE),
            S.Param("MASK", S.VECTOR, "Mask", geometry=S.POLYGON, optional=True),
            S.Param("IMAGE", S.RASTER, "Image", optional=True)))


def _strokes_gpkg(path):
    from sylva.core.io.gpkg import write_gpkg

    crs = pyproj.CRS.from_epsg(25832)
    line = VectorTable("front", "line", np.array([shapely.MultiLineString([STROKE])], dtype=object),
                       {"label": np.array(["trunk"], dtype=object)}, crs)
    point = VectorTable("location", "point", np.array([shapely.Point(1, 2, 3)], dtype=object),
                        {"n": np.array([1])}, crs)
    write_gpkg(path, [line, point])
    return path


def test_cli_reads_a_named_geopackage_layer(tmp_path):
    from sylva.cli import convert

    gpkg = _strokes_gpkg(tmp_path / "strokes.gpkg")
    args = convert(ECHO, {"STROKES": f"{gpkg}|layername=front"})
    out = ECHO.run(args, S.Feedback()).values
    assert out == {"N": 1, "KIND": "line", "EPSG": 25832, "LAST_Z": 2.0, "LABEL": "trunk", "IMAGE": None,
                   "MASK": None}


def test_cli_names_the_problem_with_a_vector_input(tmp_path):
    from sylva.cli import convert

    gpkg = _strokes_gpkg(tmp_path / "strokes.gpkg")
    with pytest.raises(InputError, match="2 layers.*layername"):
        convert(ECHO, {"STROKES": str(gpkg)})
    with pytest.raises(InputError, match="point geometries.*Strokes needs lines"):
        convert(ECHO, {"STROKES": f"{gpkg}|layername=location"})
    with pytest.raises(InputError, match="no layer named 'nope'"):
        convert(ECHO, {"STROKES": f"{gpkg}|layername=nope"})
    text = tmp_path / "notes.gpkg"
    text.write_text("not a database")
    with pytest.raises(InputError, match="notes.gpkg"):
        convert(ECHO, {"STROKES": str(text)})


def test_qgis_layers_become_vector_tables_and_raster_paths(qgis_processing, tmp_path):
    from qgis.core import (QgsFeature, QgsField, QgsGeometry, QgsProcessingContext, QgsProcessingFeedback,
                           QgsVectorLayer)
    from qgis.PyQt.QtCore import QVariant

    from sylva.core.raster import Raster, write_geotiff
    from sylva.processing.algorithm import SylvaAlgorithm

    layer = QgsVectorLayer("MultiLineStringZM?crs=EPSG:25832", "strokes", "memory")
    layer.dataProvider().addAttributes([QgsField("label", QVariant.String)])
    layer.updateFields()
    feature = QgsFeature(layer.fields())
    wkt = ", ".join(f"{x} {y} {z} 7" for x, y, z in STROKE)
    feature.setGeometry(QgsGeometry.fromWkt(f"MultiLineStringZM(({wkt}))"))
    feature.setAttributes(["trunk"])
    assert layer.dataProvider().addFeatures([feature])[0]
    tif = write_geotiff(tmp_path / "ortho.tif", Raster(np.ones((4, 4), np.float32), 0.0, 4.0, 1.0,
                                                       pyproj.CRS.from_epsg(25832)))

    alg = SylvaAlgorithm(ECHO)
    alg.initAlgorithm({})
    context = QgsProcessingContext()
    results, ok = alg.run({"STROKES": layer, "IMAGE": str(tif)}, context, QgsProcessingFeedback())
    assert ok
    assert {k: results[k] for k in ("N", "KIND", "EPSG", "LAST_Z", "LABEL", "MASK")} == {
        "N": 1, "KIND": "line", "EPSG": 25832, "LAST_Z": 2.0, "LABEL": "trunk", "MASK": None}
    assert results["IMAGE"] == str(tif)
