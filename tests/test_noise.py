"""Noise points: classes, withheld flags, isolated voxels, isolated canopy points."""
import numpy as np
import pytest

from sylva.core.cloud import PointCloud
from sylva.core.noise import IsolatedVoxels, isolated_points, noise_mask
from sylva.core.synth import NOISE, ScanSpec, StandSpec, make_stand, simulate_scan


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
