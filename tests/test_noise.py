"""Noise points: classes, withheld flags, isolated voxels, isolated canopy points."""
import numpy as np
import pytest

from sylva.core.cloud import PointCloud
from sylva.core.noise import IsolatedVoxels, isolated_points, noise_mask
from sylva.testing.synth import NOISE, ScanSpec, StandSpec, make_stand, simulate_scan


def test_isolated_voxels_catch_birds_and_keep_the_canopy():
    rng = np.random.default_rng(3)
    canopy = rng.uniform([0, 0, 10], [50, 50, 20], (20000, 3))
    birds = np.array([[25.0, 25.0, 60.0], [5.0, 40.0, 80.0], [40.0, 5.0, -30.0]])
    cloud = PointCloud(np.vstack([canopy, birds]))
    mask = noise_mask(cloud)
    assert mask[-3:].all() and not mask[:-3].any()


def test_classes_and_withheld_are_noise():
    xyz = np.random.default_rng(0).uniform(0, 10, (500, 3))
    cls = np.ones(500, np.uint8)
    cls[:3] = 7
    cls[3:5] = 18
    withheld = np.zeros(500, bool)
    withheld[10] = True
    mask = noise_mask(PointCloud(xyz, {"classification": cls, "withheld": withheld}))
    assert np.flatnonzero(mask).tolist() == [0, 1, 2, 3, 4, 10]


def test_simulated_noise_is_found_without_false_alarms():
    stand = make_stand(StandSpec(width_m=60, depth_m=60, seed=4))
    scan = simulate_scan(stand, ScanSpec(pulse_density=10, noise_fraction=0.002, seed=4))
    mask = noise_mask(scan.cloud)
    truth = scan.truth_kind == NOISE
    assert (mask & ~truth).sum() == 0
    assert (mask & truth).sum() >= 0.6 * truth.sum()


def test_isolated_points_among_a_subset():
    xyz = np.array([[0, 0, 0], [0.5, 0, 0], [10, 10, 10.0]])
    cloud = PointCloud(xyz)
    assert isolated_points(cloud, 2.0).tolist() == [False, False, True]
    assert isolated_points(cloud, 2.0, among=np.array([True, False, True])).tolist() == [True, False, True]
    assert not isolated_points(cloud, None).any()


def test_parameters_change_the_verdict():
    xyz = np.vstack([np.random.default_rng(1).uniform(0, 3, (4, 3)), [[50, 50, 50]]])
    assert noise_mask(PointCloud(xyz), IsolatedVoxels(min_points=6))[:4].all()
    assert not noise_mask(PointCloud(xyz), IsolatedVoxels(min_points=3))[:4].any()


@pytest.mark.parametrize("n", [0, 1])
def test_tiny_clouds(n):
    assert noise_mask(PointCloud(np.zeros((n, 3)))).tolist() == [True] * n


def test_alone_equals_a_kd_tree_search_on_quantised_coordinates():
    """The bucketed kernel agrees with cKDTree.query(k=2, distance_upper_bound)
    (a neighbour at exactly the radius does not count), duplicates included."""
    from scipy.spatial import cKDTree
    from sylva.core.noise import _alone

    rng = np.random.default_rng(4)
    xyz = np.round(rng.uniform([0, 0, 0], [200, 150, 40], size=(20000, 3)), 0)   # 1 m grid: exact 2 m gaps
    xyz = np.vstack([xyz, xyz[:50]])                                            # duplicates
    dist, _ = cKDTree(xyz).query(xyz, k=2, distance_upper_bound=2.0)
    expected = ~np.isfinite(dist[:, 1])
    got = _alone(xyz, 2.0)
    assert 100 < expected.sum() < len(xyz) - 100 and np.array_equal(got, expected)


# --- the kernels against the numpy code they replaced (kept here as references) -------------

def reference_isolated(loc, voxel_m=5.0, min_points=6):
    from sylva.core.noise import _keys

    ijk = np.floor(loc / voxel_m).astype(np.int64)
    ijk -= ijk.min(axis=0)
    keys = _keys(ijk)
    occupied, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    cells = ijk[np.unique(inverse, return_index=True)[1]]
    total = np.zeros(len(occupied), dtype=np.int64)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                probe = _keys(cells + (dx, dy, dz))
                pos = np.clip(np.searchsorted(occupied, probe), 0, len(occupied) - 1)
                hit = occupied[pos] == probe
                total[hit] += counts[pos[hit]]
    return (total < min_points)[inverse]


def reference_buckets(xy, x0, y0, cell, nx, ny):
    key = np.floor((xy[:, 0] - x0) / cell).astype(np.int64) * ny + np.floor((xy[:, 1] - y0) / cell).astype(np.int64)
    order = np.argsort(key, kind="stable")
    return order, np.searchsorted(key[order], np.arange(nx * ny + 1)), key[order]


@pytest.mark.parametrize("voxel_m, min_points", [(5.0, 6), (1.0, 3), (2.5, 12)])
def test_isolated_voxels_equal_the_sorted_look_ups(voxel_m, min_points):
    from sylva.core.noise import isolated

    rng = np.random.default_rng(int(voxel_m * 10) + min_points)
    canopy = rng.uniform([0, 0, 300], [120, 90, 330], (30000, 3))
    sparse = rng.uniform([-50, -50, 250], [170, 140, 600], (400, 3))          # birds, low points
    loc = np.vstack([canopy, sparse, np.round(canopy[:300], 0)])              # on voxel faces too
    got = isolated(PointCloud(loc), IsolatedVoxels(voxel_m, min_points))
    expected = reference_isolated(PointCloud(loc).local_xyz(), voxel_m, min_points)
    assert np.array_equal(got, expected) and 0 < got.sum() < len(loc)


def test_isolated_voxels_far_apart_fall_back_to_sorting():
    from sylva.core.noise import _isolated_voxels, isolated

    loc = np.vstack([np.random.default_rng(2).uniform(0, 10, (50, 3)), [[1e7, 0.0, 0.0]]])
    assert len(_isolated_voxels(loc, 5.0, 6, 4 * len(loc) + 65536)) == 0
    assert np.array_equal(isolated(PointCloud(loc)), reference_isolated(PointCloud(loc).local_xyz()))


def test_grid_buckets_are_the_stable_argsort():
    from sylva.core.noise import _grid_buckets, grid_buckets

    rng = np.random.default_rng(7)
    xy = np.round(rng.uniform(0, 50, (20000, 3)), 1)
    for cell in (2.0, 0.7, 60.0):
        nx, ny = int(50 // cell) + 1, int(50 // cell) + 1
        got = grid_buckets(xy, 0.0, 0.0, cell, nx, ny)
        for a, b in zip(got, reference_buckets(xy, 0.0, 0.0, cell, nx, ny)):
            assert np.array_equal(a, b) and a.dtype == b.dtype
    off = xy.copy()
    off[5, 0] = -3.0                                              # off the grid: the argsort path
    assert len(_grid_buckets(off, 0.0, 0.0, 2.0, 26, 26)[0]) == 0
    for a, b in zip(grid_buckets(off, 0.0, 0.0, 2.0, 26, 26), reference_buckets(off, 0.0, 0.0, 2.0, 26, 26)):
        assert np.array_equal(a, b)


def test_kernels_run_as_python():
    """``SYLVA_NO_JIT``: the kernels are plain Python with the same results."""
    from sylva.core.noise import _alone_sorted, _grid_buckets, _isolated_voxels

    rng = np.random.default_rng(1)
    loc = np.round(rng.uniform(0, 30, (600, 3)), 0)
    assert np.array_equal(_isolated_voxels.py_func(loc, 5.0, 6, 10000), _isolated_voxels(loc, 5.0, 6, 10000))
    a, b = _grid_buckets.py_func(loc, 0.0, 0.0, 2.0, 16, 16), _grid_buckets(loc, 0.0, 0.0, 2.0, 16, 16)
    assert all(np.array_equal(u, v) for u, v in zip(a, b))
    order, starts, key = b
    pts = np.ascontiguousarray(loc[order])
    assert np.array_equal(_alone_sorted.py_func(pts, key, starts, 16, 2.0), _alone_sorted(pts, key, starts, 16, 2.0))


@pytest.mark.parametrize("radius", [0.3, 2.0, 7.5])
def test_alone_equals_a_kd_tree_search_on_scan_lines(radius):
    """Points in scan-line order (the own column is searched outwards from each point),
    clustered crowns, strays and duplicates."""
    from scipy.spatial import cKDTree
    from sylva.core.noise import _alone

    rng = np.random.default_rng(int(radius * 10))
    t = np.sort(rng.uniform(0, 1, 20000))
    line = np.column_stack([80 * t, 40 * np.sin(300 * t), 20 + rng.normal(0, 3, len(t))])
    xyz = np.vstack([np.round(line, 1), rng.uniform([-40, -60, 0], [120, 60, 80], (300, 3)), line[:20]])
    dist, _ = cKDTree(xyz).query(xyz, k=2, distance_upper_bound=radius)
    expected = ~np.isfinite(dist[:, 1])
    assert 10 < expected.sum() and np.array_equal(_alone(xyz, radius), expected)
