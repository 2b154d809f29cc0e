"""The dependency-free GeoPackage writer: round trip, and GDAL/QGIS read what it writes."""
import numpy as np
import pyproj
import pytest
import shapely

from sylva.core.io.gpkg import PAGE_SIZE, read_gpkg, write_gpkg
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


# --------------------------------------------------------------------------- the batched writer = the row-by-row one

def _reference_write_gpkg(path, tables):
    """The writer before batching (one INSERT per row, default pragmas), kept verbatim as the reference."""
    import sqlite3

    from sylva.core.io.gpkg import _GEOMETRY_NAMES, _header, _python_values, _srs_row

    def _promote(geoms, geometry_type):
        if geometry_type == "line":
            return np.array([shapely.MultiLineString([g]) if g is not None and g.geom_type == "LineString" else g
                             for g in geoms], dtype=object)
        if geometry_type == "polygon":
            return np.array([shapely.MultiPolygon([g]) if g is not None and g.geom_type == "Polygon" else g
                             for g in geoms], dtype=object)
        return geoms

    def _blobs(geoms, srs_id, has_z):
        wkb = shapely.to_wkb(geoms, output_dimension=3 if has_z else 2, flavor="iso", byte_order=1)
        full, empty = _header(srs_id, False), _header(srs_id, True)
        is_empty = shapely.is_empty(geoms).tolist()
        return [None if w is None else (empty if e else full) + w for w, e in zip(wkb.tolist(), is_empty)]

    def _write_table(con, table):
        name = table.name
        srs_id = _srs_row(table.crs)[0]
        types = table.field_types()
        cols = ", ".join(f'"{c}" {_SQL_TYPES[t]}' for c, t in types.items())
        spatial = table.geometry_type != "none"
        geom_col = "geom BLOB, " if spatial else ""
        con.execute(f'CREATE TABLE "{name}" (fid INTEGER PRIMARY KEY AUTOINCREMENT, {geom_col}{cols})'.replace(", )", ")"))
        n = len(table)
        values = [_python_values(v, types[c]) for c, v in table.columns.items()]
        bounds = (None,) * 4
        if spatial and table.raw:
            header = _header(srs_id, False)
            values = [[None if w is None else header + w for w in table.geometries]] + values
            if table.extent is not None:
                bounds = tuple(float(v) for v in table.extent)
            elif n:
                geoms = shapely.from_wkb(np.asarray(table.geometries, dtype=object))
                bounds = tuple(float(v) for v in shapely.total_bounds(geoms))
        elif spatial:
            geoms = _promote(np.asarray(table.geometries, dtype=object), table.geometry_type)
            blobs = _blobs(geoms, srs_id, table.has_z)
            values = [blobs] + values
            if n:
                b = shapely.total_bounds(geoms)
                bounds = tuple(float(v) for v in b) if np.all(np.isfinite(b)) else bounds
        names = (["geom"] if spatial else []) + list(types)
        placeholders = ",".join("?" * len(names))
        quoted = ",".join(f'"{c}"' for c in names)
        if names:
            con.executemany(f'INSERT INTO "{name}" ({quoted}) VALUES ({placeholders})', zip(*values))
        else:
            con.executemany(f'INSERT INTO "{name}" DEFAULT VALUES', [()] * n)
        con.execute(
            "INSERT INTO gpkg_contents (table_name, data_type, identifier, min_x, min_y, max_x, max_y, srs_id)"
            " VALUES (?,?,?,?,?,?,?,?)",
            (name, "features" if spatial else "attributes", name, *bounds, srs_id if spatial else None),
        )
        if spatial:
            con.execute(
                "INSERT INTO gpkg_geometry_columns VALUES (?,?,?,?,?,?)",
                (name, "geom", _GEOMETRY_NAMES[table.geometry_type], srs_id, 1 if table.has_z else 0,
                 1 if table.has_m else 0),
            )

    con = sqlite3.connect(path)
    con.execute("PRAGMA application_id = 1196444487")
    con.execute("PRAGMA user_version = 10200")
    con.executescript(
        """
        CREATE TABLE gpkg_spatial_ref_sys (srs_name TEXT NOT NULL, srs_id INTEGER PRIMARY KEY,
          organization TEXT NOT NULL, organization_coordsys_id INTEGER NOT NULL,
          definition TEXT NOT NULL, description TEXT);
        CREATE TABLE gpkg_contents (table_name TEXT NOT NULL PRIMARY KEY, data_type TEXT NOT NULL,
          identifier TEXT UNIQUE, description TEXT DEFAULT '',
          last_change DATETIME NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ','now')),
          min_x DOUBLE, min_y DOUBLE, max_x DOUBLE, max_y DOUBLE, srs_id INTEGER);
        CREATE TABLE gpkg_geometry_columns (table_name TEXT NOT NULL, column_name TEXT NOT NULL,
          geometry_type_name TEXT NOT NULL, srs_id INTEGER NOT NULL, z TINYINT NOT NULL,
          m TINYINT NOT NULL, CONSTRAINT pk_geom_cols PRIMARY KEY (table_name, column_name));
        """
    )
    srs = {
        (-1, "Undefined cartesian SRS", "NONE", -1, "undefined"),
        (0, "Undefined geographic SRS", "NONE", 0, "undefined"),
        (4326, "WGS 84 geodetic", "EPSG", 4326,
         'GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563]],'
         'PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433],AUTHORITY["EPSG","4326"]]'),
    }
    for table in tables:
        srs.add(_srs_row(table.crs))
    known = set()
    for row in sorted(srs, key=lambda r: r[0]):
        if row[0] not in known:
            known.add(row[0])
            con.execute("INSERT INTO gpkg_spatial_ref_sys (srs_id, srs_name, organization,"
                        " organization_coordsys_id, definition) VALUES (?,?,?,?,?)", row)
    for table in tables:
        _write_table(con, table)
    con.commit()
    con.close()


_SQL_TYPES = {"integer": "INTEGER", "real": "DOUBLE", "text": "TEXT"}


def gpkg_content(path):
    """Everything a GeoPackage holds but its page layout: pragmas, schema, every table's rows with their
    SQLite types (gpkg_contents.last_change, the time of writing, left out)."""
    import sqlite3

    con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        out = {p: con.execute(f"PRAGMA {p}").fetchone() for p in ("application_id", "user_version")}
        out["schema"] = con.execute("SELECT type, name, tbl_name, sql FROM sqlite_master ORDER BY name").fetchall()
        for (t,) in con.execute("SELECT name FROM sqlite_master WHERE type = 'table'").fetchall():
            cols = [r[1] for r in con.execute(f'PRAGMA table_info("{t}")') if r[1] != "last_change"]
            sel = ", ".join(f'"{c}", typeof("{c}")' for c in cols)
            out[t] = con.execute(f'SELECT {sel} FROM "{t}" ORDER BY rowid').fetchall()
    finally:
        con.close()
    return out


def varied_tables(rng, n_points: int):
    """Layers that reach every branch of the writer: point, line, polygon and attribute layers; shapely
    and WKB geometries, with and without extent; None and empty geometries; 2D; NaN reals, booleans, text
    with None; no CRS, EPSG and custom CRSs; row counts around the rows-per-statement boundaries."""
    from sylva.core.table import multilinestring_zm_wkb, point_layer

    crs = pyproj.CRS("EPSG:32632")
    local = pyproj.CRS.from_proj4("+proj=tmerc +lat_0=0 +lon_0=9.1 +k=1 +x_0=0 +y_0=0 +ellps=GRS80 +units=m")
    xyz = rng.uniform(0, 100, (n_points, 3)) + [500000, 5500000, 250]
    ids = rng.integers(1, 2 ** 31, n_points)
    height = rng.uniform(0, 30, n_points)
    height[rng.random(n_points) < 0.1] = np.nan
    pts = point_layer("crown_points", xyz, {"tree_id": ids, "height": height}, crs)
    shp = VectorTable("shapely_points", "point", shapely.points(xyz), {"tree_id": ids, "height": height}, crs)
    odd = np.array([shapely.Point(1, 2, 3), None, shapely.Point(), shapely.Point(4, 5, 6)], dtype=object)
    missing = VectorTable("missing", "point", odd, {"k": np.array([True, False, True, True])}, local)
    lines = np.array([shapely.LineString(rng.uniform(0, 9, (k, 3))) for k in (2, 3, 5)]
                     + [shapely.MultiLineString([[(0, 0, 0), (1, 1, 1)], [(2, 2, 2), (3, 3, 4)]]), None],
                     dtype=object)
    line = VectorTable("lines", "line", lines, {"n": np.arange(5)}, crs)
    poly = shapely.Polygon([(0, 0), (4, 0), (4, 3), (0, 0)])
    polys = VectorTable("crowns", "polygon", np.array([poly, shapely.MultiPolygon([poly, poly]), None], dtype=object),
                        {"area": np.array([6.0, np.nan, 1.0]), "name": np.array(["a", None, "c"], dtype=object)},
                        crs, has_z=False)
    zm = [multilinestring_zm_wkb([rng.uniform(0, 9, (k, 4))]) for k in (2, 4)] + [None]
    skel = VectorTable("skeletons", "line", np.array(zm, dtype=object), {"tree_id": np.array([1, 2, 3])}, crs,
                       has_m=True)
    wkb = VectorTable("wkb_extent", "polygon", np.array([shapely.to_wkb(poly, flavor="iso")], dtype=object),
                      {"n": np.array([1])}, None, has_z=False, wkb=True, extent=(0.0, 0.0, 4.0, 3.0))
    wide_cols = {f"c{k}": rng.uniform(0, 1, n_points // 3) if k % 3 else np.arange(n_points // 3) for k in range(40)}
    wide_cols["label"] = np.array([f"t{k}" for k in range(n_points // 3)], dtype=object)
    wide = VectorTable("wide", "none", None, wide_cols, None)
    empty = VectorTable("empty", "point", np.zeros(0, dtype=object), {"k": np.zeros(0, dtype=np.int64)}, crs)
    empty_pts = point_layer("empty_points", np.zeros((0, 3)), {"k": np.zeros(0, dtype=np.int64)}, crs)
    nothing = VectorTable("nothing", "none", None, {}, None)
    return [pts, shp, missing, line, polys, skel, wkb, wide, empty, empty_pts, nothing]


@pytest.mark.parametrize("n_points", [0, 1, 332, 333, 334, 999, 1000, 2501])
def test_batched_writer_writes_the_rows_of_the_row_by_row_one(tmp_path, n_points):
    tables = varied_tables(np.random.default_rng(n_points), n_points)
    _reference_write_gpkg(tmp_path / "ref.gpkg", tables)
    write_gpkg(tmp_path / "new.gpkg", tables)
    ref, new = gpkg_content(tmp_path / "ref.gpkg"), gpkg_content(tmp_path / "new.gpkg")
    assert ref == new
    assert len(new["crown_points"]) == n_points and len(new["wide"]) == n_points // 3
    assert _page_size(tmp_path / "new.gpkg") == PAGE_SIZE     # set before the file is created


def _page_size(path) -> int:
    import sqlite3

    con = sqlite3.connect(path)
    try:
        return con.execute("PRAGMA page_size").fetchone()[0]
    finally:
        con.close()


def test_point_layer_is_the_layer_of_shapely_points(tmp_path):
    from sylva.core.table import point_layer, point_z_wkb

    rng = np.random.default_rng(4)
    xyz = rng.normal(0, 1e5, (500, 3))
    xyz[:3] = [[0.0, -0.0, 0.0], [1e-310, 5e-324, -1e300], [np.pi, np.e, 1.0]]   # zero bytes, subnormals
    want = shapely.to_wkb(shapely.points(xyz), output_dimension=3, flavor="iso", byte_order=1)
    assert point_z_wkb(xyz).dtype == object and list(point_z_wkb(xyz)) == list(want)
    cols = {"k": np.arange(len(xyz))}
    assert point_layer("p", xyz, cols).wkb
    with_nan = xyz.copy()
    with_nan[7, 2] = np.nan                                  # not finite: shapely points, as before
    for k, arr in enumerate((xyz, with_nan, xyz[:1], xyz[:0])):
        write_gpkg(tmp_path / f"a{k}.gpkg", [point_layer("p", arr, {"k": np.arange(len(arr))})])
        _reference_write_gpkg(tmp_path / f"b{k}.gpkg", [VectorTable("p", "point", shapely.points(arr),
                                                                    {"k": np.arange(len(arr))}, None)])
        assert gpkg_content(tmp_path / f"a{k}.gpkg") == gpkg_content(tmp_path / f"b{k}.gpkg")
    assert not point_layer("p", with_nan, cols).wkb
