"""Ground, height above ground, normalisation detection and CHMs against known truth."""
import numpy as np
import pyproj
import pytest
from scipy import ndimage

from sylva.core.cloud import INTERNATIONAL_FOOT, PointCloud, Units
from sylva.core.errors import EmptyInputError, InputError
from sylva.core.raster import Raster
from sylva.core.terrain import (
    CSF, SMRF, canopy_height_model, classify_ground, digital_terrain_model, ground_mask,
    height_above_ground, is_normalized, normalize,
)

UTM = pyproj.CRS.from_epsg(26912)


def plane(x, y):
    """A tilted plane (about 17 degrees) at 1500 m elevation."""
    return 1500.0 + 0.25 * x - 0.15 * y


def tilted_scene(objects_xy, object_h):
    """Ground on a 1 m grid over a tilted plane plus objects at known heights."""
    gx, gy = np.meshgrid(np.arange(0.0, 21.0), np.arange(0.0, 21.0))
    gx, gy = gx.ravel() + 400_000, gy.ravel() + 4_000_000
    ox, oy = objects_xy[:, 0] + 400_000, objects_xy[:, 1] + 4_000_000
    xyz = np.vstack([np.column_stack([gx, gy, plane(gx - 400_000, gy - 4_000_000)]),
                     np.column_stack([ox, oy, plane(ox - 400_000, oy - 4_000_000) + object_h])])
    cls = np.r_[np.full(len(gx), 2, np.uint8), np.ones(len(ox), np.uint8)]
    return PointCloud(xyz, {"classification": cls}, crs=UTM, source="tilted.laz"), len(gx)


def test_tin_is_exact_on_a_tilted_plane():
    rng = np.random.default_rng(1)
    xy = rng.uniform(0.5, 19.5, (300, 2))
    h = rng.uniform(0.0, 35.0, 300)
    cloud, n_ground = tilted_scene(xy, h)
    got = height_above_ground(cloud, method="tin")
    assert got.dtype == np.float64
    np.testing.assert_allclose(got[:n_ground], 0.0, atol=1e-9)
    np.testing.assert_allclose(got[n_ground:], h, atol=1e-9)


def test_idw_is_exact_at_symmetric_positions():
    # On ground points and at grid-cell centres with k=4, the 4 neighbours are symmetric
    # and IDW of a plane returns the plane exactly.
    xy = np.array([[3.0, 4.0], [10.0, 10.0], [3.5, 4.5], [12.5, 17.5], [0.5, 0.5]])
    h = np.array([12.0, 0.7, 25.0, 3.3, 9.0])
    cloud, n_ground = tilted_scene(xy, h)
    got = height_above_ground(cloud, method="knnidw", k=4, power=2.0)
    np.testing.assert_allclose(got[n_ground:], h, atol=1e-9)
    np.testing.assert_allclose(got[:n_ground], 0.0, atol=1e-9)


def test_points_outside_the_ground_hull_get_a_height():
    xy = np.array([[25.0, 10.0], [-3.0, -3.0]])  # beyond the 0..20 m ground grid
    cloud, n = tilted_scene(xy, np.array([10.0, 10.0]))
    got = height_above_ground(cloud, method="tin")
    assert np.all(np.isfinite(got))
    # IDW of the border ground is within the plane's rise over the extrapolated distance
    assert abs(got[n] - (10.0 + 0.25 * 5)) < 1.0 and abs(got[n + 1] - 10.0) < 1.5


def test_tin_radius_makes_heights_independent_of_the_tiling():
    """With tin_radius_m = R a point's height depends only on the ground within 2R: the core of a
    tile at the outer edge of the data, read with a 2R buffer, gets the heights the whole cloud
    gives; without it the long triangles along the outline of the data differ."""
    rng = np.random.default_rng(3)
    g = rng.uniform(0.0, 200.0, (6000, 2))
    gz = 10.0 * np.sin(g[:, 0] / 23.0) + 6.0 * np.cos(g[:, 1] / 17.0)
    q = rng.uniform([150.0, 60.0], [200.0, 110.0], (4000, 2))      # a core on the data's edge x = 200
    xyz = np.vstack([np.column_stack([g, gz]), np.column_stack([q, np.full(len(q), 30.0)])]) + [400_000, 4_000_000, 0]
    cls = np.r_[np.full(len(g), 2, np.uint8), np.ones(len(q), np.uint8)]
    whole = PointCloud(xyz, {"classification": cls}, crs=UTM, source="whole.laz")
    r = 5.0
    loc = xyz[:, :2] - [400_000, 4_000_000]
    box = (loc[:, 0] >= 150.0 - 2 * r) & (loc[:, 1] >= 60.0 - 2 * r) & (loc[:, 1] <= 110.0 + 2 * r)
    tile = whole.subset(box)
    core = slice(len(g), None)
    in_tile = np.flatnonzero(box) >= len(g)
    for radius, same in ((r, True), (None, False)):
        a = height_above_ground(whole, tin_radius_m=radius)[core]
        b = height_above_ground(tile, tin_radius_m=radius)[in_tile]
        assert np.all(np.isfinite(a)) and np.all(np.isfinite(b))
        assert (np.abs(a - b).max() < 1e-9) == same, radius
    # inside the data the radius changes nothing: the triangles there are small
    inner = (loc[core][:, 0] < 190.0)
    full, limited = height_above_ground(whole)[core], height_above_ground(whole, tin_radius_m=r)[core]
    assert np.abs(full - limited)[inner].max() < 1e-9


def test_no_ground_points_names_the_file():
    cloud = PointCloud(np.random.default_rng(0).uniform(0, 10, (50, 3)),
                       {"classification": np.ones(50, np.uint8)}, source="/data/tile_17.laz")
    with pytest.raises(EmptyInputError, match=r"tile_17\.laz.*no ground points \(class 2\)"):
        height_above_ground(cloud)
    with pytest.raises(EmptyInputError, match="tile_17.laz"):
        normalize(PointCloud(cloud.xyz + [0, 0, 800], cloud.attrs, source="/data/tile_17.laz"))
    with pytest.raises(InputError, match="unknown height-above-ground method"):
        height_above_ground(tilted_scene(np.zeros((1, 2)), np.ones(1))[0], method="kriging")


def test_is_normalized_both_kinds():
    rng = np.random.default_rng(2)
    xy = rng.uniform(0.5, 19.5, (200, 2))
    h = rng.uniform(0.0, 30.0, 200)
    raw, _ = tilted_scene(xy, h)
    assert not is_normalized(raw)
    normed = PointCloud(np.column_stack([raw.xyz[:, :2], height_above_ground(raw)]), raw.attrs)
    assert is_normalized(normed)
    # without classification: decided from the lowest point of 10 m cells
    assert is_normalized(PointCloud(normed.xyz))
    assert not is_normalized(PointCloud(raw.xyz))
    # a few low outliers do not fool it
    noisy = normed.xyz.copy()
    noisy[:3, 2] = -12.0
    assert is_normalized(PointCloud(noisy, normed.attrs))
    # sea-level terrain that undulates by metres is not "normalised"
    wavy = raw.xyz.copy()
    wavy[:, 2] -= 1500.0
    assert not is_normalized(PointCloud(wavy, raw.attrs))


def test_normalize_attr_in_metres_for_feet():
    rng = np.random.default_rng(3)
    xy = rng.uniform(0.5, 19.5, (100, 2))
    h = rng.uniform(1.0, 30.0, 100)
    cloud, n = tilted_scene(xy, h)
    feet = PointCloud(cloud.xyz / INTERNATIONAL_FOOT, cloud.attrs,
                      units=Units(INTERNATIONAL_FOOT, INTERNATIONAL_FOOT), source="feet.laz")
    out = normalize(feet)
    np.testing.assert_allclose(out.attrs["height"][n:], h, atol=1e-6)
    assert out.xyz is feet.xyz or np.array_equal(out.xyz, feet.xyz)
    # an already normalised tile in feet: height = z * 0.3048
    already = PointCloud(np.column_stack([feet.xyz[:, :2], out.attrs["height"] / INTERNATIONAL_FOOT]),
                         feet.attrs, units=feet.units)
    np.testing.assert_allclose(normalize(already).attrs["height"], out.attrs["height"], atol=1e-9)


def rough_terrain(slope_deg, seed=0):
    """Ground on a slope with undulation, cone-shaped trees and a few low outliers."""
    rng = np.random.default_rng(seed)
    t = np.tan(np.radians(slope_deg))

    def z0(x, y):
        return 200.0 + t * x + 0.8 * np.sin(y / 9.0) + 0.5 * np.cos(x / 6.0)

    n_g = 6000
    gx, gy = rng.uniform(0, 60, (2, n_g))
    parts, kind = [np.column_stack([gx, gy, z0(gx, gy)])], [np.zeros(n_g, int)]
    for _ in range(25):
        cx, cy = rng.uniform(5, 55, 2)
        top = rng.uniform(12, 28)
        m = 250
        r = np.sqrt(rng.uniform(0, 1, m)) * 0.25 * top
        a = rng.uniform(0, 2 * np.pi, m)
        px, py = cx + r * np.cos(a), cy + r * np.sin(a)
        hz = top * (1 - r / (0.25 * top)) * 0.6 + 0.4 * top - rng.uniform(0, 4, m)
        parts.append(np.column_stack([px, py, z0(px, py) + np.maximum(hz, 1.5)]))
        kind.append(np.ones(m, int))
    lx, ly = rng.uniform(0, 60, (2, 10))
    parts.append(np.column_stack([lx, ly, z0(lx, ly) - 8.0]))
    kind.append(np.full(10, 3))
    return PointCloud(np.vstack(parts), source="rough.laz"), np.concatenate(kind)


@pytest.mark.parametrize("method", [SMRF(), CSF()], ids=["SMRF", "CSF"])
@pytest.mark.parametrize("slope", [0, 30])
def test_ground_classification_on_slopes(method, slope):
    cloud, kind = rough_terrain(slope)
    g = classify_ground(cloud, method)
    truth = kind == 0
    precision = (g & truth).sum() / g.sum()
    recall = (g & truth).sum() / truth.sum()
    assert precision > 0.98, precision
    assert recall > 0.9, recall
    assert not g[kind == 3].any(), "low outliers classified as ground"


def test_normalize_classifies_when_asked():
    cloud, kind = rough_terrain(15, seed=4)
    assert not ground_mask(cloud).any()
    with pytest.raises(EmptyInputError):
        normalize(cloud)
    out = normalize(cloud, classify=SMRF())
    assert ground_mask(out).sum() > 0.9 * (kind == 0).sum()
    h = out.attrs["height"]
    assert np.percentile(np.abs(h[kind == 0]), 95) < 0.3
    assert np.median(h[kind == 1]) > 5.0


def test_dtm_from_ground():
    cloud, _ = tilted_scene(np.array([[5.0, 5.0]]), np.array([20.0]))
    dtm = digital_terrain_model(cloud, resolution_m=1.0)
    cx, cy = dtm.cell_centres()
    inside = (cx - 400_000 <= 20) & (cy - 4_000_000 <= 20) & (cx >= 400_000) & (cy >= 4_000_000)
    np.testing.assert_allclose(dtm.data[inside], plane(cx - 400_000, cy - 4_000_000)[inside], atol=1e-3)


def test_plain_chm_is_the_max_per_cell():
    rng = np.random.default_rng(5)
    n = 4000
    xy = rng.uniform(0, 20, (n, 2)) + [650_000, 5_200_000]
    h = rng.uniform(0, 30, n)
    rn = rng.integers(1, 3, n)
    cloud = PointCloud(np.column_stack([xy, h]), {"return_number": rn, "height": h}, crs=UTM)
    chm = canopy_height_model(cloud, resolution_m=1.0, pit_free=False, isolation_m=None)
    assert chm.crs == UTM and chm.pixel == 1.0
    assert chm.x0 == 650_000.0 and chm.y0 == 5_200_020.0
    row, col = chm.index_of(xy[:, 0], xy[:, 1])
    first = rn == 1
    expect = np.full(chm.shape, -np.inf)
    np.maximum.at(expect, (row[first], col[first]), h[first])
    has = np.isfinite(expect)
    assert has.mean() > 0.95
    np.testing.assert_array_equal(chm.data[has], expect[has].astype(np.float32))


def test_chm_leaves_out_noise():
    rng = np.random.default_rng(8)
    xy = rng.uniform(0, 20, (8000, 2))
    h = 10.0 + rng.uniform(0, 1, 8000)            # a dense canopy layer 10-11 m
    h[:3] = [60.0, 75.0, 12.5]                     # a bird, a cloud, a real top just above
    cls = np.ones(8000, np.uint8)
    cls[3] = 18                                    # classified high noise
    h[3] = 90.0
    cloud = PointCloud(np.column_stack([xy, h]), {"height": h, "classification": cls})
    chm = canopy_height_model(cloud, resolution_m=1.0, pit_free=False)
    assert np.nanmax(chm.data) == pytest.approx(12.5)
    assert np.nanmax(canopy_height_model(cloud, 1.0, pit_free=False, isolation_m=None).data) == 75.0


def test_chm_pixel_in_feet():
    rng = np.random.default_rng(6)
    xy = rng.uniform(0, 100, (3000, 2))
    h = rng.uniform(0, 30, 3000)
    cloud = PointCloud(np.column_stack([xy, h / INTERNATIONAL_FOOT]), {"height": h},
                       units=Units(INTERNATIONAL_FOOT, INTERNATIONAL_FOOT))
    chm = canopy_height_model(cloud, resolution_m=3.048, pit_free=False)
    assert chm.pixel == pytest.approx(10.0)
    assert np.nanmax(chm.data) == pytest.approx(h.max(), rel=1e-6)  # values in metres


def sparse_crown(seed=7):
    """One parabolic crown sampled at ~6 first returns/m2, 35 % of them falling deep into it."""
    rng = np.random.default_rng(seed)
    n = 3000
    xy = rng.uniform(-10, 10, (n, 2))
    r = np.hypot(xy[:, 0], xy[:, 1])
    surface = np.where(r < 8, 25.0 - 15.0 * (r / 8) ** 2, 0.0)
    h = surface.copy()
    deep = (rng.uniform(size=n) < 0.35) & (r < 8)
    h[deep] = surface[deep] * rng.uniform(0.0, 0.6, deep.sum())
    cloud = PointCloud(np.column_stack([xy + 1000.0, h]), {"height": h}, crs=UTM)
    return cloud


def count_pits(chm: Raster, inside: np.ndarray, depth_m: float = 2.0) -> int:
    data = chm.data.astype(np.float64)
    filled = np.where(np.isfinite(data), data, -np.inf)
    footprint = np.ones((3, 3), bool)
    footprint[1, 1] = False
    neighbours = ndimage.median_filter(np.where(np.isfinite(data), data, 0.0), footprint=footprint)
    pits = (~np.isfinite(data)) | (filled < neighbours - depth_m)
    return int((pits & inside).sum())


def test_pit_free_chm_has_fewer_pits():
    cloud = sparse_crown()
    plain = canopy_height_model(cloud, resolution_m=0.25, pit_free=False)
    free = canopy_height_model(cloud, resolution_m=0.25, pit_free=True, max_edge_m=1.5)
    assert plain.shape == free.shape and plain.x0 == free.x0 and plain.y0 == free.y0
    cx, cy = free.cell_centres()
    inside = np.hypot(cx - 1000.0, cy - 1000.0) < 7.0
    pits_plain, pits_free = count_pits(plain, inside), count_pits(free, inside)
    assert pits_plain > 100
    assert pits_free < 0.1 * pits_plain, (pits_plain, pits_free)
    # the pit-free surface follows the crown top, never above the highest return
    assert np.nanmax(free.data) <= cloud.attrs["height"].max() + 1e-4
    r = np.hypot(cx - 1000.0, cy - 1000.0)
    true = 25.0 - 15.0 * (r / 8) ** 2
    assert np.median(np.abs(free.data[inside] - true[inside])) < 0.5


def test_chm_progress_and_cancel():
    from sylva.core.errors import Cancelled

    cloud = sparse_crown()
    seen = []
    canopy_height_model(cloud, resolution_m=0.5, progress=lambda f, m: seen.append(f))
    assert seen[0] == 0.0 and seen[-1] == 1.0
    with pytest.raises(Cancelled):
        canopy_height_model(cloud, resolution_m=0.5, cancelled=lambda: True)


# ---------------------------------------------------------------- real tiles (../shared/data)

def _shared_tile(name):
    from pathlib import Path

    path = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "als" / name
    if not path.exists():
        pytest.skip(f"real data file {path} is absent")
    las = pytest.importorskip("sylva.core.io.las")
    return las.read_las(path)


def test_is_normalized_on_real_tiles():
    conifer = _shared_tile("MixedConifer.laz")  # lidR's sample: Z is already height above ground
    assert is_normalized(conifer)
    out = normalize(conifer)
    np.testing.assert_array_equal(out.attrs["height"], conifer.xyz[:, 2])
    autzen = _shared_tile("autzen_trim.laz")    # elevations in international feet
    assert not is_normalized(autzen)
    h = normalize(autzen).attrs["height"]
    ground = ground_mask(autzen)
    assert np.all(np.abs(h[ground]) < 1e-6)     # TIN through the ground points
    assert 20.0 < h.max() < 40.0                # metres, not feet (tallest tree)


def test_tin_walk_finds_the_triangles_qhull_finds():
    """The compiled visibility walk locates every query in the triangle
    Delaunay.find_simplex gives (or one sharing the point, on an edge), with
    the barycentric coordinates that reproduce it; outside the hull it says -1."""
    from scipy.spatial import Delaunay
    from sylva.core.terrain.interpolation import _locate

    rng = np.random.default_rng(8)
    xy = rng.uniform(0, 100, size=(3000, 2))
    tri = Delaunay(xy)
    query = rng.uniform(-10, 110, size=(20000, 2))
    simplex, bary = _locate(tri, query)
    expected = tri.find_simplex(query)
    assert np.array_equal(simplex < 0, expected < 0) and (expected < 0).sum() > 100
    inside = simplex >= 0
    assert (simplex[inside] == expected[inside]).mean() > 0.999
    corners = tri.points[tri.simplices[simplex[inside]]]
    back = (corners * bary[inside, :, None]).sum(axis=1)
    np.testing.assert_allclose(back, query[inside], atol=1e-9)
    assert (bary[inside] >= -1e-12).all()
