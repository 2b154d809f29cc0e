"""Tree-top detection (local maxima) on points and on CHMs against known tops."""
import numpy as np
import pyproj
import pytest

from sylva.core.cloud import INTERNATIONAL_FOOT, PointCloud, Units
from sylva.core.errors import Cancelled, EmptyInputError, InputError
from sylva.core.raster import Raster
from sylva.core.terrain import canopy_height_model
from sylva.core.tops import FixedWindow, SteepApex, TreeTops, VariableWindow, find_tree_tops, union_tops

UTM = pyproj.CRS.from_epsg(26912)


def crowns(tops, density=20.0, seed=0, size=40.0, ground_z=300.0):
    """Paraboloid crowns (radius 2.5 m, depth 6 m) with known apexes, on flat ground at ground_z."""
    rng = np.random.default_rng(seed)
    n = int(density * size * size)
    xy = rng.uniform(0, size, (n, 2))
    h = np.zeros(n)
    for x, y, top in tops:
        r = np.hypot(xy[:, 0] - x, xy[:, 1] - y)
        h = np.maximum(h, np.where(r < 2.5, top - 6.0 * (r / 2.5) ** 2, 0.0))
    apex = np.asarray(tops, dtype=np.float64)
    xy = np.vstack([xy, apex[:, :2]])
    h = np.r_[h, apex[:, 2]]
    xyz = np.column_stack([xy + [500_000, 4_000_000], h + ground_z])
    cls = np.where(h == 0, 2, 1).astype(np.uint8)
    return PointCloud(xyz, {"classification": cls, "height": h}, crs=UTM, source="crowns.laz")


TOPS = [(8.0, 8.0, 20.0), (14.0, 9.0, 17.0), (30.0, 30.0, 25.0), (20.0, 32.0, 12.0), (33.0, 12.0, 22.5)]


def test_points_fixed_window_finds_the_apexes():
    cloud = crowns(TOPS)
    tops = find_tree_tops(cloud, FixedWindow(3.0), min_height_m=2.0)
    assert isinstance(tops, TreeTops) and len(tops) == len(TOPS)
    expect = sorted(TOPS, key=lambda t: -t[2])
    np.testing.assert_allclose(tops.xyz[:, :2] - [500_000, 4_000_000], np.array(expect)[:, :2])
    np.testing.assert_allclose(tops.height, np.array(expect)[:, 2])
    np.testing.assert_allclose(tops.xyz[:, 2], np.array(expect)[:, 2] + 300.0)  # CRS z
    assert tops.tree_id.dtype == np.int64 and list(tops.tree_id) == [1, 2, 3, 4, 5]
    assert tops.xyz.dtype == np.float64 and tops.height.dtype == np.float64


def test_wide_window_merges_close_trees():
    cloud = crowns(TOPS)
    # trees 1 (20 m) and 2 (17 m) are 6.1 m apart: a 13 m window keeps only the taller
    tops = find_tree_tops(cloud, FixedWindow(13.0))
    assert 17.0 not in tops.height and 20.0 in tops.height


def test_variable_window_diameter_rules():
    w = VariableWindow()
    d = w.diameter(np.array([0.0, 10.0, 30.0, 100.0]))
    assert d[0] == w.min_diameter_m and d[-1] == w.max_diameter_m
    assert np.all(np.diff(d) >= 0)
    pines = VariableWindow.pines()
    assert pines.diameter(np.array([20.0]))[0] == pytest.approx(3.75105 - 0.17919 * 20 + 0.01241 * 400)
    assert VariableWindow.combined().diameter(np.array([10.0]))[0] == pytest.approx(2.51503 + 0.901)
    tops = find_tree_tops(crowns(TOPS), VariableWindow())
    assert len(tops) == len(TOPS)


def test_chm_tops_match_point_tops():
    cloud = crowns(TOPS)
    chm = canopy_height_model(cloud, resolution_m=0.5, pit_free=False)
    tops = find_tree_tops(chm, FixedWindow(3.0))
    assert len(tops) == len(TOPS)
    expect = np.array(sorted(TOPS, key=lambda t: -t[2]))
    # the top lies in the cell holding the apex: within half a pixel diagonal
    err = np.hypot(*(tops.xyz[:, :2] - [500_000, 4_000_000] - expect[:, :2]).T)
    assert err.max() <= 0.5 * np.sqrt(2) * 0.5 + 1e-9
    np.testing.assert_allclose(tops.height, expect[:, 2], atol=1e-4)
    assert list(tops.tree_id) == [1, 2, 3, 4, 5]


def test_plateau_gives_one_top():
    # a flat-topped 4 x 4 m "crown" at 15 m on a regular grid of points
    g = np.arange(0.0, 20.0, 0.25)
    x, y = np.meshgrid(g, g)
    x, y = x.ravel(), y.ravel()
    h = np.where((np.abs(x - 10) <= 2) & (np.abs(y - 10) <= 2), 15.0, 0.0)
    cloud = PointCloud(np.column_stack([x, y, h]), {"height": h})
    for window in (FixedWindow(1.0), FixedWindow(3.0), VariableWindow()):
        tops = find_tree_tops(cloud, window)
        assert len(tops) == 1, window
        assert tops.height[0] == 15.0
        assert abs(tops.xyz[0, 0] - 10) <= 0.25 and abs(tops.xyz[0, 1] - 10) <= 0.25
    chm = Raster(np.where((np.abs(np.arange(40)[:, None] - 20) < 8) & (np.abs(np.arange(40) - 20) < 8),
                          15.0, 0.0), x0=0.0, y0=20.0, pixel=0.5)
    for window in (FixedWindow(1.0), FixedWindow(3.0), VariableWindow()):
        tops = find_tree_tops(chm, window)
        assert len(tops) == 1 and tops.height[0] == 15.0


def test_flat_and_empty_chm_give_no_tops():
    flat = Raster(np.full((50, 60), 1.2, np.float32), x0=0.0, y0=0.0, pixel=0.5)
    tops = find_tree_tops(flat, FixedWindow(3.0), min_height_m=2.0)
    assert len(tops) == 0 and tops.xyz.shape == (0, 3) and tops.tree_id.dtype == np.int64
    nodata = Raster(np.full((10, 10), np.nan, np.float32), x0=0.0, y0=0.0, pixel=0.5)
    assert len(find_tree_tops(nodata, VariableWindow())) == 0
    low = crowns([(10.0, 10.0, 1.5)])
    assert len(find_tree_tops(low, min_height_m=2.0)) == 0


def test_chm_in_feet_uses_metre_windows():
    feet_crs = pyproj.CRS.from_epsg(2994)  # NAD83(HARN) / Oregon GIC Lambert (ft)
    assert feet_crs.axis_info[0].unit_conversion_factor == pytest.approx(INTERNATIONAL_FOOT)
    cloud = crowns(TOPS)
    feet = PointCloud(cloud.xyz / INTERNATIONAL_FOOT, cloud.attrs, crs=feet_crs,
                      units=Units(INTERNATIONAL_FOOT, INTERNATIONAL_FOOT))
    chm = canopy_height_model(feet, resolution_m=0.5, pit_free=False)
    assert chm.pixel == pytest.approx(0.5 / INTERNATIONAL_FOOT)
    assert len(find_tree_tops(chm, FixedWindow(3.0))) == len(TOPS)
    assert len(find_tree_tops(feet, FixedWindow(3.0))) == len(TOPS)


def test_errors_and_cancel():
    with pytest.raises(InputError, match="unknown tree-top window"):
        find_tree_tops(crowns(TOPS), window="lmf")
    with pytest.raises(EmptyInputError, match="empty.laz"):
        find_tree_tops(PointCloud(np.zeros((0, 3)), source="empty.laz"))
    with pytest.raises(Cancelled):
        find_tree_tops(crowns(TOPS), cancelled=lambda: True)
    # without a height attribute and without ground: the normalisation error names the file
    bare = PointCloud(crowns(TOPS).xyz, {"classification": np.ones(len(crowns(TOPS)), np.uint8)},
                      source="bare.laz")
    with pytest.raises(EmptyInputError, match="bare.laz.*no ground points"):
        find_tree_tops(bare)


def test_deterministic():
    cloud = crowns(TOPS, seed=3)
    a = find_tree_tops(cloud, VariableWindow())
    b = find_tree_tops(cloud, VariableWindow())
    assert np.array_equal(a.xyz, b.xyz) and np.array_equal(a.tree_id, b.tree_id)


# ---------------------------------------------------------------- synthetic stands (testing.synth)

def match_tops(tops_xy, tops_h, trees_xy, trees_h, crowns_r):
    """Greedy one-to-one matching, tallest true tree first: a detected top matches when within
    0.5 x the true crown radius and within 15 % of the true height."""
    used = np.zeros(len(tops_xy), dtype=bool)
    hits = 0
    for i in np.argsort(-trees_h):
        d = np.hypot(*(tops_xy - trees_xy[i]).T)
        ok = ~used & (d <= 0.5 * crowns_r[i]) & (np.abs(tops_h - trees_h[i]) <= 0.15 * trees_h[i])
        if ok.any():
            used[np.argmin(np.where(ok, d, np.inf))] = True
            hits += 1
    precision = hits / max(len(tops_xy), 1)
    recall = hits / max(len(trees_xy), 1)
    return precision, recall, 2 * precision * recall / max(precision + recall, 1e-12)


def test_f1_on_open_synthetic_stand():
    synth = pytest.importorskip("sylva.testing.synth")
    from sylva.core.terrain import normalize

    stand_spec, scan_spec = synth.preset("open", pulse_density=10.0, seed=0)
    stand = synth.make_stand(stand_spec)
    scan = synth.simulate_scan(stand, scan_spec)
    cloud = normalize(scan.cloud)  # synth classifies ground (class 2); noise stays class 1
    trees = stand.trees
    xy = np.array([[t.x, t.y] for t in trees])
    h = np.array([t.height for t in trees])
    r = np.array([t.crown_radius_m for t in trees])
    # measured (seed 0, 120 trees): F1 0.949 FixedWindow(3 m) and 0.956 VariableWindow() on the
    # points, 0.964 VariableWindow() on the pit-free CHM (recall 1.00, precision 0.90-0.93)
    for source, window in ((cloud, FixedWindow()), (cloud, VariableWindow()),
                           (canopy_height_model(cloud, resolution_m=0.5), VariableWindow())):
        tops = find_tree_tops(source, window)
        p, rc, f1 = match_tops(tops.xyz[:, :2], tops.height, xy, h, r)
        assert f1 > 0.9, (window, p, rc, f1)
    # the tops' z is the elevation of the top in the CRS (ground + height)
    tops = find_tree_tops(cloud, VariableWindow())
    ground = stand.ground_z(tops.xyz[:, 0], tops.xyz[:, 1])
    np.testing.assert_allclose(tops.xyz[:, 2] - ground, tops.height, atol=0.15)


def tucked(step=0.2, small_height=13.5):
    """A tall cone (apex (10, 10), 22 m, radius 4 m) whose flank rises above the apex of a
    narrow cone (13.2, 10), 1.2 m radius, 0.8 m from that apex: a grid-sampled canopy surface."""
    g = np.arange(0.0, 24.0, step)
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    big = 22.0 - (22.0 - 7.7) / 4.0 * np.hypot(x - 10.0, y - 10.0)
    small = small_height - (small_height - 4.7) / 1.2 * np.hypot(x - 13.2, y - 10.0)
    h = np.maximum(np.maximum(big, small), 0.0)
    return PointCloud(np.column_stack([x, y, h]), {"height": h}, source="tucked.laz")


def test_steep_apex_adds_the_tip_a_wide_window_misses():
    cloud = tucked()
    wide = find_tree_tops(cloud, FixedWindow(2.0))
    assert len(wide) == 1 and wide.height[0] == pytest.approx(22.0, abs=0.1)   # the tip is overtopped
    # the tall cone's flank covers the 3 sectors facing it and part of a 4th
    rule = SteepApex(sectors=4)
    tops = find_tree_tops(cloud, FixedWindow(2.0), apex=rule)
    assert len(tops) == 2
    np.testing.assert_allclose(tops.xyz[1, :2], [13.2, 10.0], atol=1e-9)
    assert tops.height[1] == pytest.approx(13.5) and list(tops.tree_id) == [1, 2]
    # required drop steeper than the narrow cone's 7.3 m/m: not a steep apex
    assert len(find_tree_tops(cloud, FixedWindow(2.0), apex=SteepApex(slope=8.0, sectors=4))) == 1
    # a higher top within separation_m: a second steep point of that tree, not a tree
    assert len(find_tree_tops(cloud, FixedWindow(2.0), apex=SteepApex(sectors=4, separation_m=4.0))) == 1


def test_steep_apex_adds_nothing_on_rounded_crowns_and_needs_points():
    cloud = crowns(TOPS)
    tops = find_tree_tops(cloud, FixedWindow(3.0), apex=SteepApex())
    assert len(tops) == len(TOPS)   # paraboloid crowns: no surplus tips
    with pytest.raises(InputError, match="point cloud"):
        find_tree_tops(canopy_height_model(cloud, resolution_m=0.5), apex=SteepApex())
    with pytest.raises(InputError, match="apex rule"):
        find_tree_tops(cloud, apex="steep")
    with pytest.raises(InputError, match="sectors"):
        SteepApex(sectors=9)


def test_window_maxima_equal_a_brute_force_search():
    """The bucketed kernel keeps exactly the candidates with no higher point within
    their (height-dependent) window radius, as an all-pairs search does."""
    from sylva.core.tops import VariableWindow, _local_maxima, _one_per_plateau

    rng = np.random.default_rng(11)
    xy = rng.uniform(0, 60, size=(3000, 2))
    h = np.round(rng.uniform(2, 30, size=3000), 1)      # rounded: ties happen
    window = VariableWindow.combined()
    got = _local_maxima(xy, h, window, None, None, cand=np.arange(len(xy)))
    r = window.diameter(h) / 2.0
    d = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1])
    higher = (h[None, :] > h[:, None]) & (d <= r[:, None])
    maxima = np.flatnonzero(~higher.any(axis=1))
    expected = maxima[_one_per_plateau(xy[maxima], h[maxima], r[maxima])]   # one per plateau
    assert len(expected) > 10 and np.array_equal(got, expected)


# --- the kernels against the numpy code they replaced (kept here as references) -------------

def reference_cell_maxima(xy, h, cell):
    key = np.floor(xy / cell).astype(np.int64)
    order = np.lexsort((xy[:, 1], xy[:, 0], -h, key[:, 1], key[:, 0]))
    first = np.ones(len(order), dtype=bool)
    first[1:] = np.any(key[order][1:] != key[order][:-1], axis=1)
    return order[first]


def reference_local_maxima(xy, h, window):
    from sylva.core import tops as tops_mod

    cand = reference_cell_maxima(xy, h, max(window.min_diameter / 2.0 / np.sqrt(2.0), 1e-3))
    radius = window.diameter(h[cand]) / 2.0
    lo = xy.min(axis=0)
    span = np.maximum(xy.max(axis=0) - lo, 1e-6)
    cell = max(float(radius.max()), float(np.sqrt(span[0] * span[1] / (2.0 * len(xy) + 1024))), 1e-3)
    nx, ny = (np.floor(span / cell).astype(np.int64) + 1).tolist()
    key = np.floor((xy[:, 0] - lo[0]) / cell).astype(np.int64) * ny + np.floor((xy[:, 1] - lo[1]) / cell).astype(np.int64)
    order = np.argsort(key, kind="stable")
    starts = np.searchsorted(key[order], np.arange(nx * ny + 1))
    is_top = tops_mod._window_tops(np.ascontiguousarray(xy[order]), np.ascontiguousarray(h[order]), starts,
                                   xy[cand], h[cand], radius, float(lo[0]), float(lo[1]), cell, nx, ny)
    tops = cand[is_top]
    return tops[tops_mod._one_per_plateau(xy[tops], h[tops], radius[is_top])]


def quantised_canopy(n=40000, seed=0):
    """Centimetre positions and heights: equal heights, equal x and duplicates happen."""
    rng = np.random.default_rng(seed)
    xy = np.round(rng.uniform(-10, 90, (n, 2)), 2)
    h = np.round(2 + 18 * np.abs(np.sin(xy[:, 0] / 4.0) * np.cos(xy[:, 1] / 5.0)), 1)
    return np.vstack([xy, xy[:200]]), np.r_[h, h[:200]]


@pytest.mark.parametrize("cell", [0.3, 1.06, 5.0])
def test_cell_maxima_are_the_lexsort(cell):
    from sylva.core.tops import _cell_maxima

    xy, h = quantised_canopy()
    assert np.array_equal(_cell_maxima(xy, h, cell), reference_cell_maxima(xy, h, cell))


def test_cell_maxima_of_a_sparse_extent_sort():
    from sylva.core.tops import _cell_maxima, _cell_maxima_kernel

    xy = np.array([[0.0, 0.0], [1e8, 5.0], [0.1, 0.2], [1e8, 5.1]])
    h = np.array([3.0, 4.0, 3.0, 4.0])
    assert len(_cell_maxima_kernel(xy, h, 1.0, 4 * len(xy) + 1024)) == 0
    assert np.array_equal(_cell_maxima(xy, h, 1.0), reference_cell_maxima(xy, h, 1.0))


@pytest.mark.parametrize("window", [FixedWindow(3.0), FixedWindow(1.2), VariableWindow()])
def test_local_maxima_are_the_reference(window):
    from sylva.core.tops import _local_maxima

    xy, h = quantised_canopy(seed=3)
    got = _local_maxima(xy, h, window, None, None)
    assert len(got) > 20 and np.array_equal(got, reference_local_maxima(xy, h, window))


def test_cell_maxima_kernel_runs_as_python():
    from sylva.core.tops import _cell_maxima_kernel

    xy, h = quantised_canopy(n=500)
    assert np.array_equal(_cell_maxima_kernel.py_func(xy, h, 1.06, 10000), _cell_maxima_kernel(xy, h, 1.06, 10000))


def test_steep_apex_columns_do_not_depend_on_the_tile_extent():
    """The canopy surface the apex rule measures against is a grid of columns of the anchored local
    frame: points far away (another tile's extent) do not move the columns, so the rule keeps the same
    candidates (before, the columns started at the tile's lowest x and y: tiling changed the tops)."""
    from sylva.core.tops import _steep, steep_column_m

    assert steep_column_m(0.3) == pytest.approx(70.0 / 234) and (70.0 / steep_column_m(0.5)) == 140
    rng = np.random.default_rng(3)
    xy = rng.uniform(0.0, 30.0, (20000, 2))
    h = 20.0 + 3.0 * np.sin(xy[:, 0] * 1.7) * np.cos(xy[:, 1] * 1.3) + rng.normal(0.0, 0.6, len(xy))
    cand = np.nonzero((xy > 3.0).all(axis=1) & (xy < 27.0).all(axis=1) & (h > 22.0))[0]
    rule = SteepApex(slope=1.5, sectors=3)
    alone = _steep(xy, h, cand, rule)
    assert 0 < alone.sum() < len(cand)
    far = rng.uniform(-40.17, -20.0, (500, 2))          # a neighbour's points, 20 m and more away
    wider = _steep(np.vstack([xy, far]), np.concatenate([h, np.full(len(far), 25.0)]), cand, rule)
    assert np.array_equal(alone, wider)


def test_union_tops_adds_the_taken_tops_once_in_find_order():
    cloud = crowns([(10.0, 10.0, 20.0), (13.0, 10.0, 18.0), (30.0, 30.0, 15.0)])
    wide = find_tree_tops(cloud, window=FixedWindow(8.0))
    narrow = find_tree_tops(cloud, window=FixedWindow(2.0))
    assert len(wide) == 2 and len(narrow) == 3
    none = union_tops(wide, narrow, np.zeros(len(narrow), dtype=bool))
    np.testing.assert_array_equal(none.xyz, wide.xyz)
    every = union_tops(wide, narrow, np.ones(len(narrow), dtype=bool))
    np.testing.assert_array_equal(every.xyz, narrow.xyz)            # no top twice, ordered by height
    np.testing.assert_array_equal(every.tree_id, [1, 2, 3])
    np.testing.assert_array_equal(every.height, [20.0, 18.0, 15.0])

