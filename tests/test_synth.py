"""Synthetic stands and the airborne scan simulator (sylva.testing.synth)."""
from pathlib import Path

import numpy as np
import pytest

from sylva.testing import synth
from sylva.core.errors import Cancelled, CRSError, InputError
from sylva.testing.synth import (CROWN, GROUND, NOISE, STEM, ScanSpec, StandSpec, make_stand,
                              preset, read_truth, simulate_scan, write_scan)

SAMPLE = Path(__file__).resolve().parents[1] / "resources" / "sample"

SMALL = StandSpec(width_m=60.0, depth_m=60.0, stems_per_ha=300, slope_deg=8.0, seed=3)


@pytest.fixture(scope="module")
def small():
    stand = make_stand(SMALL)
    return stand, simulate_scan(stand, ScanSpec(pulse_density=10.0, rgb=True, seed=3))


def _top_per_tree(scan):
    crown = scan.truth_kind == CROWN
    top = np.full(len(scan.stand.trees) + 1, -np.inf)
    np.maximum.at(top, scan.truth_tree[crown], scan.cloud.xyz[crown, 2])
    return top[1:]


def test_deterministic_and_seeded(small):
    stand, scan = small
    again = simulate_scan(make_stand(SMALL), ScanSpec(pulse_density=10.0, rgb=True, seed=3))
    assert [t for t in again.stand.trees] == list(stand.trees)
    assert np.array_equal(again.cloud.xyz, scan.cloud.xyz)
    assert np.array_equal(again.truth_tree, scan.truth_tree)
    assert np.array_equal(again.truth_kind, scan.truth_kind)
    for name, values in scan.cloud.attrs.items():
        assert np.array_equal(again.cloud.attrs[name], values), name
    other_stand = make_stand(StandSpec(width_m=60.0, depth_m=60.0, slope_deg=8.0, seed=4))
    assert [(t.x, t.y) for t in other_stand.trees] != [(t.x, t.y) for t in stand.trees]
    other_scan = simulate_scan(stand, ScanSpec(pulse_density=10.0, rgb=True, seed=4))
    n = min(len(other_scan.cloud), len(scan.cloud))
    assert not np.array_equal(other_scan.cloud.xyz[:n], scan.cloud.xyz[:n])


@pytest.mark.parametrize("density", [1.0, 5.0, 20.0])
def test_pulse_density(density):
    stand = make_stand(StandSpec(width_m=60.0, depth_m=60.0, seed=1))
    scan = simulate_scan(stand, ScanSpec(pulse_density=density, seed=1))
    a = scan.cloud.attrs
    first = (a["return_number"] == 1) & (scan.truth_kind != NOISE)
    area = 60.0 * 60.0
    assert abs(first.sum() / area - density) <= 0.1 * density
    assert scan.n_pulses == first.sum()
    # Ground points alone sample the terrain at the pulse density times the gap fraction.
    assert len(scan.cloud) > first.sum()
    xyz = scan.cloud.xyz
    assert xyz[:, 0].min() >= 500000.0 and xyz[:, 0].max() < 500060.0
    assert xyz[:, 1].min() >= 5500000.0 and xyz[:, 1].max() < 5500060.0


def test_every_tree_has_crown_points(small):
    stand, scan = small
    crown_ids = np.unique(scan.truth_tree[scan.truth_kind == CROWN])
    assert set(crown_ids.tolist()) == {t.tree_id for t in stand.trees}
    assert np.all(scan.truth_tree[scan.truth_kind == GROUND] == 0)
    assert np.all(scan.truth_tree[scan.truth_kind == NOISE] == 0)
    assert np.all(scan.truth_tree[(scan.truth_kind == CROWN) | (scan.truth_kind == STEM)] > 0)
    assert (scan.truth_kind == STEM).sum() > 0  # off-nadir pulses hit trunks now and then


def test_truth_consistency(small):
    stand, scan = small
    spec = scan.spec
    xyz, kind, tid = scan.cloud.xyz, scan.truth_kind, scan.truth_tree
    tol = 0.5 * spec.footprint_diameter_m + 6 * spec.range_noise_m
    veg = (kind == CROWN) | (kind == STEM)
    # Against the exact primitives (cone / ellipsoids / leaning cylinders).
    assert stand.inside(tid[veg], kind[veg], xyz[veg], tolerance_m=tol).all()
    # ... and, independently, against the per-tree truth table.
    cols = stand.tree_arrays()
    i = tid[veg] - 1
    horizontal = np.hypot(xyz[veg, 0] - cols["x"][i], xyz[veg, 1] - cols["y"][i])
    assert np.all(horizontal <= cols["crown_radius"][i] + tol)
    h = xyz[veg, 2] - cols["ground_z"][i]
    assert np.all(h <= cols["height"][i] + tol)
    crown = kind[veg] == CROWN
    assert np.all(h[crown] >= cols["crown_base_height"][i][crown] - tol)
    stem = ~crown
    assert np.all(horizontal[stem] <= 0.5 * cols["dbh"][i][stem] + cols["crown_radius"][i][stem] * 0.4 + tol)
    g = kind == GROUND
    resid = xyz[g, 2] - stand.ground_z(xyz[g, 0], xyz[g, 1])
    assert np.abs(resid).max() < 6 * spec.range_noise_m + 1e-3
    assert abs(resid.std() - spec.range_noise_m) < 0.3 * spec.range_noise_m
    n = kind == NOISE
    gz = stand.ground_z(xyz[n, 0], xyz[n, 1])
    top = max(t.height for t in stand.trees)
    assert np.all((xyz[n, 2] > gz + top + 4) | (xyz[n, 2] < gz - 0.9))


def test_ground_classification(small):
    stand, scan = small
    cls = scan.cloud.attrs["classification"]
    assert np.all(cls[scan.truth_kind == GROUND] == 2)
    assert np.all(cls[scan.truth_kind != GROUND] == 1)
    other = simulate_scan(stand, ScanSpec(pulse_density=2.0, classify_ground=False,
                                          classify_noise=True, noise_fraction=0.05))
    cls = other.cloud.attrs["classification"]
    noise = other.truth_kind == NOISE
    assert np.all(cls[~noise] == 1)
    assert set(np.unique(cls[noise]).tolist()) == {7, 18}


def test_tree_tops_at_20_pts():
    stand_spec, scan_spec = preset("open", pulse_density=20.0, seed=0)
    stand = make_stand(stand_spec)
    scan = simulate_scan(stand, scan_spec)
    top = _top_per_tree(scan)
    err = top - np.array([t.top_z for t in stand.trees])
    assert np.all(np.isfinite(err))
    assert np.all(err < 0.1)                        # never above the tree (noise 0.02 m)
    assert np.mean(np.abs(err) <= 0.5) >= 0.98      # within 0.5 m for (almost) all trees
    assert np.all(err > -0.8)
    assert np.median(np.abs(err)) < 0.05


def test_slope_respected():
    spec = StandSpec(width_m=60.0, depth_m=60.0, slope_deg=20.0, slope_azimuth_deg=135.0,
                     undulation_m=0.0, stems_per_ha=150, seed=2)
    stand = make_stand(spec)
    scan = simulate_scan(stand, ScanSpec(pulse_density=4.0, seed=2))
    g = scan.truth_kind == GROUND
    x, y, z = scan.cloud.xyz[g].T
    A = np.column_stack([x - x.mean(), y - y.mean(), np.ones_like(x)])
    (gx, gy, _), *_ = np.linalg.lstsq(A, z, rcond=None)
    assert np.degrees(np.arctan(np.hypot(gx, gy))) == pytest.approx(20.0, abs=0.2)
    descent_azimuth = np.degrees(np.arctan2(-gx, -gy)) % 360
    assert descent_azimuth == pytest.approx(135.0, abs=1.0)
    # Tree bases sit on the terrain; the stand's centre is at ground_z0.
    for t in stand.trees:
        assert t.ground_z == pytest.approx(float(stand.ground_z(t.x, t.y)), abs=1e-9)
    assert float(stand.ground_z(500030.0, 5500030.0)) == pytest.approx(250.0)
    # Height above terrain, not above z0, stays correct on the slope.
    top = _top_per_tree(scan)
    assert np.median(top - np.array([t.top_z for t in stand.trees])) > -0.3


def test_multiple_returns(small):
    stand, scan = small
    a = scan.cloud.attrs
    rn, nr = a["return_number"], a["number_of_returns"]
    assert set(np.unique(nr).tolist()) == {1, 2, 3, 4}
    assert np.all((rn >= 1) & (rn <= nr))
    # Last returns are mostly ground, first returns of multi-return pulses mostly crown.
    last = (rn == nr) & (nr > 1)
    assert np.mean(scan.truth_kind[last] == GROUND) > 0.5
    first = (rn == 1) & (nr > 1)
    assert np.mean(scan.truth_kind[first] == CROWN) > 0.9
    # Returns of one pulse share its GPS time and come in range order.
    t = a["gps_time"]
    assert np.all(np.diff(t) >= 0)
    few = simulate_scan(stand, ScanSpec(pulse_density=5.0, max_returns=2))
    assert few.cloud.attrs["number_of_returns"].max() == 2


def test_intensity_and_rgb(small):
    stand, scan = small
    a = scan.cloud.attrs
    assert a["intensity"].dtype == np.uint16 and a["intensity"].min() > 0
    for c in ("red", "green", "blue"):
        assert a[c].dtype == np.uint16
    crown = scan.truth_kind == CROWN
    assert a["green"][crown].mean() > a["red"][crown].mean() > 0
    assert a["scan_angle"].dtype == np.int16
    assert np.abs(a["scan_angle"]).max() * 0.006 <= 15.0 + 1e-6
    plain = simulate_scan(stand, ScanSpec(pulse_density=2.0, rgb=False, intensity=False))
    assert not {"red", "green", "blue", "intensity"} & set(plain.cloud.attrs)


def test_species_shapes_and_allometry():
    stand = make_stand(StandSpec(stems_per_ha=300, seed=5))
    trees = stand.trees
    assert {t.species for t in trees} == {"conifer", "broadleaf", "multistem"}
    assert [t.tree_id for t in trees] == list(range(1, len(trees) + 1))
    assert len(trees) >= 0.9 * 300
    for t in trees:
        assert 8.0 <= t.height <= 35.0
        assert 1.5 <= t.crown_base_height_m < t.height
        assert 0.03 < t.dbh_m < 1.5
        assert (t.n_stems == 1) == (t.species != "multistem")
        assert t.n_stems <= 4
    cols = stand.tree_arrays()
    for sp in ("conifer", "broadleaf"):
        m = cols["species"] == sp
        # DBH grows with height (Näslund): strong rank correlation despite the scatter.
        r = np.corrcoef(np.argsort(np.argsort(cols["height"][m])),
                        np.argsort(np.argsort(cols["dbh"][m])))[0, 1]
        assert r > 0.8
    # Primitive kinds per species: cone for conifers, ellipsoids otherwise.
    kinds = stand.parts["kind"]
    for i, t in enumerate(trees):
        k = kinds[stand.part_ptr[i]:stand.part_ptr[i + 1]]
        assert (k == 2).sum() == t.n_stems
        if t.species == "conifer":
            assert (k == 0).sum() == 1
        else:
            assert (k == 1).sum() == t.n_stems


def test_crown_overlap_settings():
    def min_ratio(spec):
        trees = make_stand(spec).trees
        xy = np.array([[t.x, t.y] for t in trees])
        r = np.array([t.crown_radius_m for t in trees])
        d = np.hypot(*(xy[:, None, :] - xy[None, :, :]).transpose(2, 0, 1))
        ratio = d / (r[:, None] + r[None, :])
        np.fill_diagonal(ratio, np.inf)
        return ratio.min(), len(trees)

    open_ratio, n_open = min_ratio(preset("open")[0])
    dense_ratio, n_dense = min_ratio(preset("dense")[0])
    assert open_ratio >= 1.0          # crowns never touch
    assert 0.7 - 1e-9 <= dense_ratio < 0.9   # crowns overlap, by at most 30 % of the radii
    assert n_dense > 2 * n_open


def test_write_and_read_back(small, tmp_path):
    laspy = pytest.importorskip("laspy")
    stand, scan = small
    laz, csv_path = write_scan(scan, tmp_path, "stand")
    assert laz.name == "stand.laz" and csv_path.name == "stand_trees.csv"
    las = laspy.read(laz)
    assert las.header.parse_crs().to_epsg() == 32632
    assert len(las.points) == len(scan.cloud)
    assert np.array_equal(np.asarray(las.true_tree), scan.truth_tree)
    assert np.asarray(las.true_tree).dtype == np.int32
    assert np.array_equal(np.asarray(las.true_kind), scan.truth_kind)
    assert np.asarray(las.true_kind).dtype == np.uint8
    assert np.abs(np.asarray(las.z) - scan.cloud.xyz[:, 2]).max() <= 0.0006
    assert np.array_equal(np.asarray(las.classification), scan.cloud.attrs["classification"])
    assert np.array_equal(np.asarray(las.red), scan.cloud.attrs["red"])
    assert las.header.creation_date.year == 2024
    # Sylva's own reader sees the same cloud, CRS and truth.
    from sylva.core.io.las import read_las
    cloud = read_las(laz)
    assert cloud.crs.to_epsg() == 32632 and len(cloud) == len(scan.cloud)
    assert np.array_equal(cloud.attrs["true_kind"], scan.truth_kind)
    assert np.array_equal(cloud.attrs["scan_angle"], scan.cloud.attrs["scan_angle"])
    trees = read_truth(csv_path)
    assert [t.tree_id for t in trees] == [t.tree_id for t in stand.trees]
    for a, b in zip(trees, stand.trees):
        assert a.species == b.species and a.n_stems == b.n_stems
        assert a.x == pytest.approx(b.x, abs=1e-3) and a.height == pytest.approx(b.height, abs=1e-3)
        assert a.dbh_m == pytest.approx(b.dbh_m, abs=1e-4)
    # Byte-identical when written again.
    laz2, csv2 = write_scan(scan, tmp_path, "again")
    assert laz2.read_bytes() == laz.read_bytes()
    assert csv2.read_bytes() == csv_path.read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["stand.laz", "stand_trees.csv", "again.laz", "again_trees.csv"])


def test_shipped_sample():
    laspy = pytest.importorskip("laspy")
    laz = SAMPLE / "sample.laz"
    table = SAMPLE / "sample_trees.csv"
    assert laz.is_file() and table.is_file()
    assert laz.stat().st_size < 2_000_000
    las = laspy.read(laz)
    assert las.header.parse_crs().is_projected
    assert {"true_tree", "true_kind"} <= set(las.point_format.extra_dimension_names)
    assert {"red", "green", "blue", "intensity"} <= set(las.point_format.dimension_names)
    ids = {t.tree_id for t in read_truth(table)}
    assert set(np.unique(np.asarray(las.true_tree)).tolist()) - {0} == ids
    assert 2 in set(np.unique(np.asarray(las.classification)).tolist())
    area = (las.header.maxs[0] - las.header.mins[0]) * (las.header.maxs[1] - las.header.mins[1])
    assert 8.0 <= len(las.points) / area <= 20.0


def test_bad_input_and_cancel():
    with pytest.raises(InputError, match="crown_overlap"):
        StandSpec(crown_overlap=2.0)
    with pytest.raises(InputError, match="species_weights"):
        StandSpec(species=("conifer",), species_weights=(0.5, 0.5))
    with pytest.raises(InputError, match="oak"):
        StandSpec(species=("oak",), species_weights=(1.0,))
    with pytest.raises(CRSError, match="projected"):
        StandSpec(crs="EPSG:4326")
    with pytest.raises(InputError, match="pulse_density"):
        ScanSpec(pulse_density=0.0)
    with pytest.raises(InputError, match="preset"):
        preset("jungle")
    with pytest.raises(InputError, match="folder"):
        write_scan(simulate_scan(make_stand(StandSpec(width_m=20, depth_m=20)), ScanSpec(pulse_density=1)),
                   "/nonexistent/folder", "x")
    stand = make_stand(StandSpec(width_m=30, depth_m=30))
    with pytest.raises(Cancelled):
        simulate_scan(stand, ScanSpec(pulse_density=2.0), cancelled=lambda: True)
    seen = []
    simulate_scan(stand, ScanSpec(pulse_density=2.0), progress=lambda f, m: seen.append(f))
    assert seen[0] == 0.0 and seen[-1] == 1.0 and seen == sorted(seen)


def test_presets():
    for name in ("open", "medium", "dense"):
        stand_spec, scan_spec = preset(name, pulse_density=5.0)
        assert scan_spec.pulse_density == 5.0
        assert stand_spec.crs == "EPSG:32632" and stand_spec.origin == (500000.0, 5500000.0)
    assert preset("dense")[0].crown_overlap == 1.0 and preset("open")[0].crown_overlap == 0.0
    assert synth.KIND_NAMES == {0: "ground", 1: "stem", 2: "crown", 3: "noise"}
