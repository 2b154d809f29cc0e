"""QSM cylinder / branch tables and tree measurements (core/qsm.py)."""
import csv

import numpy as np
import pytest

from sylva.core.errors import InputError
from sylva.core.qsm import (BRANCH_FIELDS, CYLINDER_FIELDS, branches_table, cylinders_from_curves, cylinders_table,
                            measure_qsm, trees_table, write_branches_csv, write_cylinders_csv, write_trees_csv)
from sylva.testing.cylinders import cylinder_tree, sample_cylinder_surfaces


def two_level_tree():
    return cylinder_tree([
        dict(start=(0, 0, 0), direction=(0, 0, 1), length=6.0, radius=(0.15, 0.05), parent=-1, n=12),
        dict(start=(0, 0, 2.0), direction=(1, 0, 1), length=2.0, radius=(0.06, 0.02), parent=0, n=4),
        dict(start=(0, 0, 3.5), direction=(-1, 0.2, 1), length=1.5, radius=(0.05, 0.02), parent=0, n=3),
        dict(start=(0.7071, 0, 2.7071), direction=(0, 1, 0.5), length=0.5, radius=(0.02, 0.01), parent=1, n=2),
    ])


def frustum_volume(r0, r1, length, n):
    r = np.linspace(r0, r1, n + 1)
    rm = (r[:-1] + r[1:]) / 2
    return float(np.pi * (rm ** 2).sum() * length / n)


def test_cylinder_table_structure():
    cyl = two_level_tree()
    assert len(cyl["id"]) == 12 + 4 + 3 + 2
    assert cyl["parent"][0] == -1
    assert np.all(cyl["parent"][1:12] == np.arange(0, 11))
    assert cyl["branch"].tolist() == [0] * 12 + [1] * 4 + [2] * 3 + [3] * 2
    assert cyl["order"].tolist() == [0] * 12 + [1] * 7 + [2] * 2
    # first cylinder of branch 1 hangs off the trunk cylinder at 2 m (1.5-2.0 m or 2.0-2.5 m)
    p = cyl["parent"][12]
    assert cyl["branch"][p] == 0 and 1.5 <= cyl["start"][p, 2] <= 2.0 + 1e-9
    # branch 3 hangs off branch 1
    assert cyl["branch"][cyl["parent"][19]] == 1
    assert np.allclose(np.linalg.norm(cyl["axis"], axis=1), 1.0)
    assert cyl["length"][:12] == pytest.approx(np.full(12, 0.5))


def test_volumes_heights_counts_exact():
    cyl = two_level_tree()
    q = measure_qsm(cyl, [-1, 0, 0, 1], base_z=0.0, tree_id=7)
    trunk = frustum_volume(0.15, 0.05, 6.0, 12)
    total = trunk + frustum_volume(0.06, 0.02, 2.0, 4) + frustum_volume(0.05, 0.02, 1.5, 3) \
        + frustum_volume(0.02, 0.01, 0.5, 2)
    assert q.trunk_volume_m3 == pytest.approx(trunk, rel=1e-9)
    assert q.total_volume_m3 == pytest.approx(total, rel=1e-9)
    # the pipe-free truth (a cone frustum) differs from the stepped cylinders by < 1 %
    cone = np.pi * 6.0 * (0.15 ** 2 + 0.15 * 0.05 + 0.05 ** 2) / 3
    assert trunk == pytest.approx(cone, rel=0.01)
    assert q.height_m == pytest.approx(6.0)
    assert q.branch_counts == {1: 2, 2: 1}
    assert q.dbh_source == "cylinder"
    # the stem cylinder spanning 1.0-1.5 m has the mean radius of its ends
    assert q.dbh_m == pytest.approx(2 * (0.15 - 0.1 * 1.25 / 6.0), abs=1e-9)
    br = q.branches
    assert br["order"].tolist() == [0, 1, 1, 2]
    assert br["n_cylinders"].tolist() == [12, 4, 3, 2]
    assert br["length"] == pytest.approx([6.0, 2.0, 1.5, 0.5])
    assert br["angle_deg"][1] == pytest.approx(45.0, abs=1e-6)
    assert br["base_diameter"][1] == pytest.approx(2 * 0.055)


def test_measured_dbh_from_points_of_a_30cm_stem():
    cyl = cylinder_tree([dict(start=(10, 20, 50), direction=(0, 0, 1), length=4.0, radius=(0.15, 0.15), n=8)])
    pts = sample_cylinder_surfaces(cyl, spacing_m=0.02, noise_m=0.003, seed=0)
    q = measure_qsm(cyl, [-1], pts)
    assert q.base_z == pytest.approx(50.0, abs=0.01)
    assert q.dbh_source == "measured"
    assert abs(q.dbh_m - 0.30) < 0.01
    assert q.height_m == pytest.approx(4.0, abs=0.02)


def test_tables_and_csv(tmp_path):
    cyl = two_level_tree()
    qs = [measure_qsm(cyl, [-1, 0, 0, 1], base_z=0.0, tree_id=1),
          measure_qsm(cyl, [-1, 0, 0, 1], base_z=0.0, tree_id=2)]
    t = cylinders_table(qs, origin=(500000.0, 5500000.0, 0.0))
    assert t.geometry_type == "line" and len(t) == 42
    g = t.geometries[0]
    assert g.has_z and g.coords[0][0] == pytest.approx(500000.0) and g.coords[1][2] == pytest.approx(0.5)
    assert t.field_types()["radius"] == "real" and t.field_types()["branch"] == "integer"
    assert len(cylinders_table(qs[0], geometry=False)) == 21
    assert len(branches_table(qs)) == 8
    tr = trees_table(qs)
    assert tr.columns["branches_order2"].tolist() == [1, 1]
    write_cylinders_csv(tmp_path / "cyl.csv", qs)
    write_branches_csv(tmp_path / "br.csv", qs)
    write_trees_csv(tmp_path / "trees.csv", qs)
    rows = list(csv.DictReader(open(tmp_path / "cyl.csv")))
    assert len(rows) == 42 and list(rows[0]) == ["tree_id", *CYLINDER_FIELDS]
    assert float(rows[0]["radius"]) == pytest.approx(cyl["radius"][0])
    brows = list(csv.DictReader(open(tmp_path / "br.csv")))
    assert list(brows[0]) == ["tree_id", *BRANCH_FIELDS]
    assert [p.name for p in tmp_path.iterdir() if p.name.endswith(".part")] == []
    with pytest.raises(InputError):
        write_cylinders_csv(tmp_path / "missing" / "cyl.csv", qs)


def test_empty_and_bad_inputs():
    empty = cylinders_from_curves([], [], [])
    q = measure_qsm(empty, [], base_z=0.0)
    assert q.total_volume_m3 == 0.0 and q.dbh_source == "none"
    with pytest.raises(InputError):
        measure_qsm({"x": 1}, [])


def test_one_sided_sampling_keeps_half():
    cyl = cylinder_tree([dict(start=(0, 0, 0), direction=(0, 0, 1), length=1.0, radius=(0.1, 0.1), n=2)])
    full = sample_cylinder_surfaces(cyl, 0.01, seed=0)
    half = sample_cylinder_surfaces(cyl, 0.01, seed=0, visible=(1, 0, 0))
    assert len(half) == pytest.approx(len(full) / 2, rel=0.05)
    assert np.all(half[:, 0] <= 1e-9)
    assert np.allclose(np.hypot(full[:, 0], full[:, 1]), 0.1)


def test_cylinders_from_a_skeleton_with_radii():
    from sylva.core.qsm import cylinders_from_skeleton
    from sylva.core.skeleton import Skeleton

    nodes = np.array([[0, 0, 0], [0, 0, 1], [0, 0, 2], [0, 0, 3], [0.5, 0, 2.5], [1.0, 0, 3.0]], float)
    parent = np.array([-1, 0, 1, 2, 2, 4])
    radius = np.array([0.2, 0.15, 0.1, 0.05, 0.04, 0.02])
    cyl, bpar = cylinders_from_skeleton(Skeleton(nodes, parent, radius))
    assert bpar.tolist() == [-1, 0]
    assert cyl["branch"].tolist() == [0, 0, 0, 1, 1]
    assert cyl["radius"].tolist() == [0.15, 0.1, 0.05, 0.04, 0.02]     # each edge: its child node's radius
    assert cyl["length"] == pytest.approx([1, 1, 1, np.sqrt(0.5), np.sqrt(0.5)])
    # the side branch hangs off a trunk cylinder touching its fork at z = 2
    p = cyl["parent"][3]
    assert cyl["branch"][p] == 0 and 1.0 <= cyl["start"][p, 2] <= 2.0
    q = measure_qsm(cyl, bpar, base_z=0.0)
    assert q.total_volume_m3 == pytest.approx(np.pi * (0.15 ** 2 + 0.1 ** 2 + 0.05 ** 2
                                                       + np.sqrt(0.5) * (0.04 ** 2 + 0.02 ** 2)))
    assert q.branch_counts == {1: 1}


def test_refit_radii_recovers_true_radii_and_axis_offsets():
    from sylva.core.qsm import refit_radii, surface_distance, taper_radii

    truth = two_level_tree()
    pts = sample_cylinder_surfaces(truth, spacing_m=0.01, noise_m=0.002, seed=4)
    guess = dict(truth)
    guess["radius"] = truth["radius"] * 0.7                     # biased radii (as enclosing circles of patches)
    shifted = dict(guess)
    shifted["start"] = truth["start"] + np.array([0.02, 0.0, 0.0])   # and an axis 2 cm off
    out, good, shift = refit_radii(pts, shifted, return_shift=True)
    assert good[:12].all()
    assert out["radius"][good] == pytest.approx(truth["radius"][good], abs=0.004)
    trunk = np.arange(12)
    assert np.allclose(shift[trunk, 0], -0.02, atol=0.004) and np.allclose(shift[trunk, 1:], 0, atol=0.004)
    d0 = surface_distance(pts, truth)
    assert np.median(d0) < 0.003
    # a thin branch without a circle (points on a line) takes the median distance to its axis
    line = cylinders_from_curves([np.array([[0, 0, 0], [0, 0, 1.0]])], [np.array([0.2, 0.2])], [-1])
    rng = np.random.default_rng(0)
    p = np.c_[rng.normal(0, 0.01, 200), np.zeros(200), rng.uniform(0, 1, 200)]
    out, good = refit_radii(p, line)
    assert not good[0] and out["radius"][0] == pytest.approx(np.median(np.abs(p[:, 0])), rel=0.05)
    # taper: a branch is never thicker than the cylinder it leaves
    fat = dict(truth)
    fat["radius"] = truth["radius"].copy()
    fat["radius"][12] = 0.5
    tp = taper_radii(fat)
    assert tp["radius"][12] == pytest.approx(truth["radius"][fat["parent"][12]])
    assert np.array_equal(tp["radius"][13:], truth["radius"][13:])


def test_cylinders_from_curves_joins_each_branch_to_the_nearest_cylinder_of_its_parent():
    rng = np.random.default_rng(5)
    curves, radii, parents = [np.cumsum(rng.normal(0, 0.3, (30, 3)), axis=0)], [rng.uniform(0.1, 0.2, 30)], [-1]
    for b in range(1, 25):
        p = int(rng.integers(0, b))
        start = curves[p][int(rng.integers(0, len(curves[p])))]
        n = int(rng.integers(1, 12))          # a branch of one sample has no cylinder
        curves.append(start + np.cumsum(rng.normal(0, 0.2, (n, 3)), axis=0))
        radii.append(rng.uniform(0.01, 0.1, n))
        parents.append(p)
    for segment_radii in (False, True):
        rr = [r[:-1] if segment_radii else r for r in radii]
        cyl = cylinders_from_curves(curves, rr, parents, segment_radii=segment_radii)
        n = len(cyl["id"])
        assert n == sum(len(c) - 1 for c in curves)
        assert (cyl["parent"] < np.arange(n)).all()
        mid = cyl["start"] + cyl["axis"] * cyl["length"][:, None] / 2
        depth = {-1: -1}
        for b, p in enumerate(parents):
            depth[b] = depth[p] + 1
        for b, c in enumerate(curves):
            mine = np.flatnonzero(cyl["branch"] == b)
            if len(mine) == 0:
                continue
            assert np.allclose(cyl["start"][mine], c[:-1]) and (cyl["order"][mine] == depth[b]).all()
            want = rr[b] if segment_radii else (radii[b][:-1] + radii[b][1:]) / 2
            assert np.allclose(cyl["radius"][mine], want)
            assert (cyl["parent"][mine[1:]] == mine[:-1]).all()
            of_parent = np.flatnonzero(cyl["branch"] == parents[b])
            if parents[b] < 0 or len(of_parent) == 0:
                assert cyl["parent"][mine[0]] == -1
            else:
                nearest = of_parent[np.argmin(np.linalg.norm(mid[of_parent] - c[0], axis=1))]
                assert cyl["parent"][mine[0]] == nearest
