"""The dependency-free GeoPackage writer: round trip, and GDAL/QGIS read what it writes."""
import numpy as np
import pyproj
import pytest
import shapely

from sylva.core.io.gpkg import read_gpkg, write_gpkg
from sylva.core.table import VectorTable


def tables():
    rng = np.random.default_rng(1)
    crs = pyproj.CRS("EPSG:32632")
    pts = rng.uniform(0, 100, (7, 3)) + [500000, 5500000, 250]
    tops = VectorTable("tree_tops", "point", shapely.points(pts),
                       {"tree_id": np.arange(1, 8), "height": rng.uniform(2, 30, 7),
                        "species": np.array(["pine", "oak", "x", "y", "z", "w", "v"], dtype=object)}, crs)
    poly = shapely.Polygon([(0, 0, 5), (4, 0, 5), (4, 3, 5), (0, 0, 5)])
    crowns = VectorTable("crowns", "polygon", np.array([poly, shapely.MultiPolygon([poly])], dtype=object),
                         {"area": np.array([6.0, np.nan])}, crs)
    line = shapely.LineString([(0, 0, 0), (0, 0, 5), (1, 1, 7)])
    lines = VectorTable("skeletons", "line", np.array([line], dtype=object), {"tree_id": np.array([3])}, crs)
    table = VectorTable("trees", "none", None, {"tree_id": np.array([1, 2]), "dbh": np.array([0.3, 0.4])}, None)
    # a CRS with no EPSG code (WKT only) must survive too
    local = pyproj.CRS.from_proj4("+proj=tmerc +lat_0=0 +lon_0=9.1 +k=1 +x_0=0 +y_0=0 +ellps=GRS80 +units=m")
    custom = VectorTable("custom", "point", shapely.points(pts[:2]), {"n": np.array([1, 2])}, local)
    return [tops, crowns, lines, table, custom]


def test_round_trip(tmp_path):
    path = write_gpkg(tmp_path / "out.gpkg", tables())
    tops = read_gpkg(path, "tree_tops")
    src = tables()[0]
    np.testing.assert_allclose(shapely.get_coordinates(tops.geometries, include_z=True),
                               shapely.get_coordinates(src.geometries, include_z=True))
    np.testing.assert_array_equal(tops.columns["tree_id"], src.columns["tree_id"])
    assert list(tops.columns["species"]) == list(src.columns["species"])
    assert tops.crs.to_epsg() == 32632
    crowns = read_gpkg(path, "crowns")
    assert all(g.geom_type == "MultiPolygon" for g in crowns.geometries)
    assert np.isnan(crowns.columns["area"][1])
    assert read_gpkg(path, "trees").geometries is None
    custom = read_gpkg(path, "custom")
    assert custom.crs.to_epsg() is None and custom.crs.equals(tables()[4].crs, ignore_axis_order=True)
    assert not list(tmp_path.glob(".*tmp"))


def test_gdal_reads_every_layer(tmp_path):
    ogr = pytest.importorskip("osgeo.ogr")
    path = write_gpkg(tmp_path / "out.gpkg", tables())
    ds = ogr.Open(str(path))
    names = {ds.GetLayer(i).GetName(): ds.GetLayer(i) for i in range(ds.GetLayerCount())}
    assert set(names) == {"tree_tops", "crowns", "skeletons", "trees", "custom"}
    assert ogr.GeometryTypeToName(names["tree_tops"].GetGeomType()) == "3D Point"
    assert ogr.GeometryTypeToName(names["crowns"].GetGeomType()) == "3D Multi Polygon"
    assert ogr.GeometryTypeToName(names["skeletons"].GetGeomType()) == "3D Multi Line String"
    assert names["tree_tops"].GetFeatureCount() == 7
    assert names["tree_tops"].GetSpatialRef().GetAuthorityCode(None) == "32632"
    feature = names["tree_tops"].GetNextFeature()
    assert feature["tree_id"] == 1 and feature["species"] == "pine"


def test_failed_write_leaves_nothing(tmp_path):
    bad = VectorTable("bad", "point", np.array(["not a geometry"], dtype=object), {}, None)
    with pytest.raises(Exception):
        write_gpkg(tmp_path / "bad.gpkg", [bad])
    assert list(tmp_path.iterdir()) == []
