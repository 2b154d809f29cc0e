"""Single-tree terrestrial scans as users hand them over (issue 18): no treeID, no ground class, no CRS."""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from sylva import cli
from sylva.core.export.read import read_models
from sylva.core.qsm import measure_qsm
from sylva.testing.cylinders import cylinder_tree, sample_cylinder_surfaces
from sylva.core.reconstruct import TreePoints
from sylva.core.reconstruct.levelset import LevelSetQSM
from sylva.core.qsm import cylinders_from_curves
from sylva.core.reconstruct.wood_mesh import tube_mesh

TLS = Path(__file__).resolve().parents[2] / "shared" / "data" / "tls"


def _tree(seed=0, visible=None):
    specs = [dict(start=(0, 0, 0), direction=(0, 0, 1), length=6.0, radius=(0.15, 0.05), parent=-1, n=12),
             dict(start=(0, 0, 3.0), direction=(0.7, 0, 0.7), length=2.0, radius=(0.05, 0.02), parent=0, n=4),
             dict(start=(0, 0, 4.0), direction=(-0.6, 0.3, 0.74), length=1.5, radius=(0.04, 0.02), parent=0, n=3)]
    truth = cylinder_tree(specs)
    pts = sample_cylinder_surfaces(truth, spacing_m=0.015, noise_m=0.002, seed=seed, visible=visible)
    return truth, pts


def _surface_distance(points, v, f):
    """Distance from points to the nearest vertex of a densely subdivided copy of the mesh (an upper bound)."""
    import trimesh
    from scipy.spatial import cKDTree

    s, _ = trimesh.sample.sample_surface_even(trimesh.Trimesh(v, f, process=False), 200_000, seed=0)
    return cKDTree(s).query(points)[0]


def test_level_set_model_fits_known_cylinders():
    truth, pts = _tree()
    dm = LevelSetQSM().model(TreePoints(1, pts, 0.0))
    v, f = tube_mesh(dm.mesh_curves, dm.mesh_radii)
    d = _surface_distance(pts, v, f)
    assert d.mean() < 0.01, d.mean()                     # points within a centimetre of the wood
    cyl = dm.cylinders
    q = measure_qsm(cyl, dm.branch_parent, pts, base_z=0.0)
    assert abs(q.dbh_m - 2 * (0.15 - 0.1 * 1.3 / 6.0)) < 0.01 and q.dbh_source == "measured"
    assert dm.reconstruction.skeleton.nodes[0, 2] == pytest.approx(pts[:, 2].min(), abs=1e-9)   # the base
    assert (np.asarray(cyl["parent"])[1:] < np.arange(1, len(cyl["parent"]))).all()
    # the two side branches are found: some branch of order 1 reaches each branch's end
    ends = truth["start"] + truth["axis"] * truth["length"][:, None]
    for b in (1, 2):
        tip = ends[truth["branch"] == b][-1]
        reach = np.linalg.norm(np.concatenate(dm.curves) - tip, axis=1).min()
        assert reach < 0.15, (b, reach)


def test_cylinders_from_curves_parents_and_lengths():
    curves = [np.array([[0, 0, 0], [0, 0, 1], [0, 0, 2.0]]), np.array([[0, 0, 1.0], [1, 0, 1.5]])]
    radii = [np.array([0.2, 0.15, 0.1]), np.array([0.05, 0.03])]
    cyl = cylinders_from_curves(curves, radii, [-1, 0], [0, 1])
    assert cyl["parent"].tolist() == [-1, 0, 0] or cyl["parent"].tolist() == [-1, 0, 1]
    assert cyl["length"][:2] == pytest.approx([1, 1])
    assert cyl["radius"].tolist() == pytest.approx([0.175, 0.125, 0.04])
    assert cyl["order"].tolist() == [0, 0, 1]


def test_single_tree_scan_without_treeid_ground_or_crs(tmp_path, capsys):
    truth, pts = _tree(seed=3)
    pts = pts + np.array([120.0, -40.0, 7.5])             # any local frame
    scan = tmp_path / "tree.xyz"
    np.savetxt(scan, pts, fmt="%.4f")
    glb, qsm = tmp_path / "tree.glb", tmp_path / "qsm"
    rc = cli.main(["reconstructtrees", f"--INPUT={scan}", f"--MODELS={glb}", f"--TREES={tmp_path / 't.gpkg'}",
                   f"--QSM_FOLDER={qsm}", f"--CYLINDERS={tmp_path / 'c.gpkg'}"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    said = out.out + out.err
    assert "local engineering frame" in said and "one tree" in said
    models, frame = read_models(glb)
    assert len(models) == 1 and frame.crs is None
    m = models[0]
    assert m.base[2] == pytest.approx(pts[:, 2].min(), abs=0.01)       # stands on its lowest points
    assert m.leaves is None or len(m.leaves.faces) == 0                # dense wood: no leaf cards
    v, f = m.wood_arrays()
    d = _surface_distance(pts, m.base + v, f)
    assert d.mean() < 0.012
    rows = list(csv.DictReader(open(qsm / "trees.csv")))
    assert len(rows) == 1 and rows[0]["qsm_method"] == "fitted_cylinders"
    dbh = float(rows[0]["dbh_m"])
    assert abs(dbh - 2 * (0.15 - 0.1 * 1.3 / 6.0)) < 0.02 and rows[0]["dbh_source"] == "measured"
    assert (qsm / "cylinders.csv").stat().st_size > 0 and (qsm / "branches.csv").stat().st_size > 0


def test_wide_cloud_without_treeid_says_what_to_do(tmp_path, capsys):
    rng = np.random.default_rng(0)
    scan = tmp_path / "plot.xyz"
    np.savetxt(scan, rng.uniform(0, 100, (3000, 3)), fmt="%.3f")
    rc = cli.main(["reconstructtrees", f"--INPUT={scan}", f"--TREES={tmp_path / 't.gpkg'}"])
    err = capsys.readouterr().err
    assert rc == 1 and "no treeID" in err and "sylva:segmenttrees" in err
    assert "classify_ground" not in err and "normalize(" not in err


@pytest.mark.skipif(not (TLS / "tree7.xyz").exists(), reason="the shared TLS scans are not here")
def test_tls_tree7_default_model_is_close_to_the_points(tmp_path):
    xyz = np.loadtxt(TLS / "tree7.xyz")
    dm = LevelSetQSM().model(TreePoints(1, xyz, float(xyz[:, 2].min())))
    v, f = tube_mesh(dm.mesh_curves, dm.mesh_radii)
    assert _surface_distance(xyz, v, f).mean() < 0.012     # AdTree: 1.68 cm (issue 18)


def test_ply_point_clouds_are_read(tmp_path):
    import trimesh

    from sylva.core.errors import InputError
    from sylva.core.io import read_cloud

    rng = np.random.default_rng(2)
    xyz = rng.uniform(-2, 2, (500, 3))
    rgb = rng.integers(0, 256, (500, 4), dtype=np.uint8)
    rgb[:, 3] = 255
    path = tmp_path / "scan.ply"
    trimesh.PointCloud(xyz, colors=rgb).export(str(path))          # binary little endian
    cloud = read_cloud(path)
    assert cloud.crs is None and len(cloud) == 500
    assert cloud.xyz == pytest.approx(xyz, abs=1e-6)                 # float32 vertices in the file
    assert cloud.attrs["red"].dtype == np.uint16 and (cloud.attrs["red"] == rgb[:, 0] * 257).all()
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"not a ply")
    with pytest.raises(InputError, match="not a PLY file"):
        read_cloud(bad)
    with pytest.raises(InputError, match="file not found"):
        read_cloud(tmp_path / "missing.ply")


def test_thick_stem_is_one_fitted_tube_not_parallel_thin_ones():
    """A fully scanned 30 cm stem: one tube from circle fits carries it (the fine level's arcs of bark
    used to become parallel thin tubes), so the model's surface stays near the points."""
    import trimesh
    from scipy.spatial import cKDTree

    truth, pts = _tree(seed=5)
    dm = LevelSetQSM().model(TreePoints(1, pts, 0.0))
    v, f = tube_mesh(dm.mesh_curves, dm.mesh_radii)
    p2s = _surface_distance(pts, v, f).mean()
    s, _ = trimesh.sample.sample_surface_even(trimesh.Trimesh(v, f, process=False), 50_000, seed=1)
    s2p = cKDTree(pts).query(s)[0].mean()
    assert p2s < 0.01 and s2p < 2 * p2s, (p2s, s2p)
    # tubes crossing 1.5 m inside the stem: one
    crossing = 0
    for c, r in zip(dm.mesh_curves, dm.mesh_radii):
        z = c[:, 2]
        if len(c) >= 2 and z.min() <= 1.5 <= z.max():
            k = int(np.clip(np.searchsorted(z, 1.5), 1, len(z) - 1)) if np.all(np.diff(z) > 0) else 0
            if np.hypot(*c[k, :2]) < 0.1 and r.max() > 0.1:
                crossing += 1
    assert crossing == 1


def test_tube_polygons_fans_and_pointed_twigs():
    """Sides from the chord tolerance, polygons as far from the axis on average as the circle, ends closed by
    fans of their own rings (no centre vertex), twigs starting at a point: every tube closed and outward."""
    import trimesh

    from sylva.core.reconstruct.wood_mesh import mean_radius_factor, polygon_sides

    assert polygon_sides([0.002, 0.016, 0.05, 0.5], 0.008, 8).tolist() == [3, 3, 6, 8]
    r = np.array([0.002, 0.016, 0.05])
    n = polygon_sides(r, 0.008, 8)
    assert (r * (1 - np.cos(np.pi / n)) <= 0.008 + 1e-12).all()
    assert (r * (1 - np.cos(np.pi / (n - 1))) > 0.008)[n > 3].all()      # the fewest (3 at least)
    # mean distance to the axis of a regular polygon, numerically
    for s in (3, 6, 10):
        th = np.linspace(0, np.pi / s, 20001)
        assert np.mean(np.cos(np.pi / s) / np.cos(th)) == pytest.approx(mean_radius_factor(s), rel=1e-4)
    curves = [np.array([[0, 0, 0], [0, 0, 1.0], [0, 0.1, 2.0]]), np.array([[0, 0, 1.0], [0.5, 0, 1.2], [1, 0, 1.3]])]
    radii = [np.array([0.1, 0.1, 0.05]), np.array([0.005, 0.004, 0.003])]
    v0, f0 = tube_mesh(curves, radii, sides=8, tolerance_m=0.008)
    v1, f1 = tube_mesh(curves, radii, sides=8, tolerance_m=0.008, match=True, pointed_m=0.008)
    assert len(v0) == 3 * 8 + 3 * 3 and len(v1) == 3 * 8 + 1 + 2 * 3
    for v, f in ((v0, f0), (v1, f1)):
        parts = trimesh.Trimesh(v, f, process=False).split(only_watertight=False)
        assert len(parts) == 2 and all(p.is_watertight and p.is_winding_consistent and p.volume > 0 for p in parts)
    # the matched stem's polygon is on average as far from the axis as its radius
    ring = v1[np.arange(8) * 3 + 0]          # corner j of ring 0 of the stem batch: vertex j * n + 0, n = 3
    assert np.linalg.norm(ring[:, :2], axis=1).mean() * mean_radius_factor(8) == pytest.approx(0.1, rel=1e-9)
