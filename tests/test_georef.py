"""Frames of the 3D exports: source CRS <-> WGS 84 <-> ECEF <-> ENU (sylva.core.export.georef)."""
import warnings

import numpy as np
import pytest
from pyproj import CRS

from sylva.core.errors import CRSError
from sylva.core.export.georef import Georef, enu_rotation, geodesic_distance, Z_UP_TO_Y_UP, Y_UP_TO_Z_UP
from sylva.core.export.model import ExportFrame

UTM = (500123.0, 5400456.0, 310.0)
CUSTOM_TM = CRS.from_proj4("+proj=tmerc +lat_0=0 +lon_0=10.7 +k=0.9999 +x_0=300000 +y_0=-4500000 "
                           "+ellps=GRS80 +units=m +no_defs").to_wkt()
ENGINEERING = ('ENGCRS["plot frame",EDATUM["plot 7 pegs"],CS[Cartesian,2],'
               'AXIS["x",east,LENGTHUNIT["metre",1]],AXIS["y",north,LENGTHUNIT["metre",1]]]')


def test_utm_round_trip_and_origin():
    g = Georef(ExportFrame("EPSG:32632"), UTM)
    assert g.has_geodetic and g.epsg == 32632
    rng = np.random.default_rng(0)
    pts = np.array(UTM) + rng.uniform(-200, 200, (50, 3))
    enu = g.source_to_enu(pts)
    assert np.abs(g.enu_to_source(enu) - pts).max() < 1e-6
    assert np.abs(g.source_to_enu(np.array([UTM]))).max() < 1e-6      # the origin is ENU (0, 0, 0)
    # UTM zone 32 central meridian is 9 E; the origin is 123 m east of it
    assert abs(g.origin_llh[0] - 9.0) < 0.01 and 48.0 < g.origin_llh[1] < 49.5
    assert abs(g.origin_llh[2] - 310.0) < 1e-6                      # 2D CRS: z taken as ellipsoidal
    assert "assumed" in g.vertical


def test_enu_distances_match_geodesic():
    """Horizontal ENU distance between two points at the origin's height equals the geodesic (GeographicLib)."""
    g = Georef(ExportFrame("EPSG:32632"), UTM)
    pts = np.array([UTM, (UTM[0] + 300.0, UTM[1] + 400.0, UTM[2])])
    llh = g.source_to_geodetic(pts)
    enu = g.source_to_enu(pts)
    s = geodesic_distance(llh[0, 0], llh[0, 1], llh[1, 0], llh[1, 1]) * (1 + llh[0, 2] / 6.371e6)
    assert abs(np.linalg.norm(enu[1, :2]) - s) < 0.01
    # grid distance 500 m, true distance 500 / k (k ~ 0.9996 at the central meridian)
    assert abs(np.linalg.norm(enu[1, :2]) - 500.0 / 0.9996) < 0.05


def test_enu_to_ecef_matrix_is_a_rotation_onto_the_ellipsoid_normal():
    g = Georef(ExportFrame("EPSG:32632"), UTM)
    m = g.enu_to_ecef
    r = m[:3, :3]
    assert np.allclose(r.T @ r, np.eye(3), atol=1e-12)
    assert np.allclose(m[:3, 3], g.origin_ecef)
    # a point 100 m above the origin along the normal
    up = g.geodetic_to_ecef([[g.origin_llh[0], g.origin_llh[1], g.origin_llh[2] + 100.0]])[0]
    assert np.allclose((up - g.origin_ecef) / 100.0, r[:, 2], atol=1e-9)
    assert np.allclose(enu_rotation(0.0, 0.0), [[0, 0, 1], [1, 0, 0], [0, 1, 0]], atol=1e-15)
    assert np.allclose(Y_UP_TO_Z_UP @ Z_UP_TO_Y_UP, np.eye(4))
    assert np.allclose(Z_UP_TO_Y_UP[:3, :3] @ [0, 0, 1.0], [0, 1, 0])  # up becomes glTF +y


def test_tree_frame_is_affine_to_a_tenth_of_a_millimetre():
    g = Georef(ExportFrame("EPSG:32632"), UTM)
    base = np.array(UTM) + (40.0, -25.0, 2.0)
    rng = np.random.default_rng(1)
    local = rng.uniform([-6, -6, 0], [6, 6, 30], (200, 3))
    c, j = g.tree_frames([base])
    approx = c[0] + local @ j[0].T
    exact = g.model_to_enu(local, base)
    assert np.abs(approx - exact).max() < 1e-4
    # the Jacobian: inverse grid scale factor (~1/0.9996 near the central meridian) times the
    # height factor (R + h) / R horizontally, 1 vertically
    expected = (1 / 0.9996) * (1 + base[2] / 6.371e6)
    assert abs(np.linalg.det(j[0][:2, :2]) ** 0.5 - expected) < 5e-6 and abs(j[0][2, 2] - 1) < 1e-6


def test_feet_are_converted():
    frame = ExportFrame("EPSG:2994")  # NAD83(HARN) / Oregon GIC Lambert (ft), international feet
    base = np.array([4200000.0, 900000.0, 1000.0])
    g = Georef(frame, base)
    assert g.units.horizontal_m == pytest.approx(0.3048) and g.units.vertical_m == pytest.approx(0.3048)
    src = g.local_to_source([[0.0, 0.0, 10.0], [3.048, 0.0, 0.0]], base)
    assert np.allclose(src[0], base + (0, 0, 10 / 0.3048)) and np.allclose(src[1], base + (10.0, 0, 0))
    enu = g.source_to_enu(np.vstack([base, src]))
    assert abs(np.linalg.norm(enu[1] - enu[0]) - 10.0) < 1e-3    # 10 m up, not 10 ft
    assert 3.0 < np.linalg.norm(enu[2] - enu[0]) < 3.1             # 10 ft east = 3.048 m (x scale)
    assert abs(g.origin_llh[2] - 1000 * 0.3048) < 2.0               # height ~ 304.8 m (+ datum shift)
    assert np.abs(g.enu_to_source(enu) - np.vstack([base, src])).max() < 1e-6


def test_wkt_only_crs():
    g = Georef(ExportFrame(CUSTOM_TM), (300500.0, 900800.0, 200.0))
    assert g.epsg is None and g.has_geodetic and "PROJCRS" in g.describe()["crs_wkt"]
    assert abs(g.origin_llh[0] - 10.7) < 0.02
    pts = np.array([[300500.0, 900800.0, 200.0], [300600.0, 900700.0, 230.0]])
    assert np.abs(g.enu_to_source(g.source_to_enu(pts)) - pts).max() < 1e-6


def test_local_engineering_crs_has_no_ecef():
    for crs in (ENGINEERING, None):
        g = Georef(ExportFrame(crs), (100.0, 200.0, 5.0))
        assert not g.has_geodetic
        with pytest.raises(CRSError, match="no geodetic datum"):
            g.require_geodetic("3D Tiles export")
        with pytest.raises(CRSError):
            g.enu_to_ecef
        # the grid frame: metres relative to the origin
        assert np.allclose(g.source_to_enu([[101.0, 203.0, 6.0]]), [[1.0, 3.0, 1.0]])
        assert g.describe()["frame"] == "local grid"


def test_geoid_heights_without_grid_warn_and_are_taken_as_ellipsoidal():
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        g = Georef(ExportFrame("EPSG:32632+5783"), UTM)   # UTM 32N + DHHN92 height
    if "converted" in g.vertical:   # a machine with the German geoid grid installed
        assert abs(g.origin_llh[2] - UTM[2]) > 30.0           # undulation ~ 47 m in Germany
        return
    assert any("geoid" in str(w.message) for w in caught)
    assert "assumed; geoid grid unavailable" in g.vertical
    assert abs(g.origin_llh[2] - UTM[2]) < 1e-6


def test_geoid_heights_are_converted_when_the_grid_is_installed():
    """EGM96 (egm96_15.gtx ships with Debian's proj-data): h = H + N, N ~ 48 m in southern Germany."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)   # no "treated as ellipsoidal" warning
        try:
            g = Georef(ExportFrame("EPSG:32632+5773"), UTM)  # UTM 32N + EGM96 height
        except UserWarning as w:
            pytest.skip(f"EGM96 grid not installed: {w}")
    assert "converted from EGM96" in g.vertical
    assert 45.0 < g.origin_llh[2] - UTM[2] < 52.0
    pts = np.array([UTM, (UTM[0] + 50.0, UTM[1] - 80.0, UTM[2] + 25.0)])
    enu = g.source_to_enu(pts)
    assert np.abs(g.enu_to_source(enu) - pts).max() < 1e-6
    assert abs(enu[1, 2] - 25.0) < 0.05                     # relative heights survive the geoid


def test_ellipsoidal_3d_crs_keeps_heights():
    g = Georef(ExportFrame(CRS("EPSG:32632").to_3d()), UTM)
    assert "3D" in g.vertical and abs(g.origin_llh[2] - UTM[2]) < 1e-6


def test_geographic_crs_is_refused():
    with pytest.raises(CRSError, match="geographic"):
        Georef(ExportFrame("EPSG:4326"), (9.0, 48.0, 300.0))


def test_unknown_crs_is_a_clear_error():
    with pytest.raises(CRSError, match="not understood"):
        Georef(ExportFrame("EPSG:999999"), (0.0, 0.0, 0.0))
