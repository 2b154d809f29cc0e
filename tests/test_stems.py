"""Stem-based segmentation of terrestrial plot scans (core/segment/stems.py) on synthetic plots with known stems."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sylva.core.cloud import PointCloud
from sylva.core.segment import segment_trees
from sylva.core.segment.stems import StemSegmentation, ground_under_canopy

from sylva.testing.plots import plot_scan


def _match(stems_xy, truth, tol=0.3):
    t = np.c_[truth["x"], truth["y"]]
    d = np.linalg.norm(stems_xy[:, None] - t[None], axis=2)
    j = d.argmin(axis=1)
    ok = d[np.arange(len(j)), j] < tol
    return j, ok, d[np.arange(len(j)), j]


def test_stems_found_measured_and_points_assigned():
    pts, truth = plot_scan(n_trees=8, size_m=16, seed=1)
    cloud = PointCloud(pts, {})
    labels, stems = StemSegmentation().segment_with_stems(cloud)
    xy = stems.xy + cloud.origin[:2]
    j, ok, err = _match(xy, truth)
    recall = len(set(j[ok])) / len(truth["x"])
    precision = ok.mean()
    assert recall >= 0.85 and precision >= 0.9, (recall, precision)
    assert np.sqrt(np.mean((stems.dbh_m[ok] - truth["dbh"][j[ok]]) ** 2)) < 0.03        # DBH RMSE < 3 cm
    assert err[ok].max() < 0.1
    # the stem points of a found tree get its ID; ground points none
    for k in np.flatnonzero(ok):
        mine = truth["tree"] == j[k] + 1
        assert (labels[mine] == k + 1).mean() > 0.8
    assert (labels[truth["tree"] == 0] == 0).mean() > 0.95


def test_ground_under_canopy_follows_a_slope():
    rng = np.random.default_rng(0)
    g = rng.uniform(0, 20, (4000, 2))
    ground = np.c_[g, 0.1 * g[:, 0]]
    canopy = np.c_[rng.uniform(0, 20, (4000, 2)), rng.uniform(5, 15, 4000)]
    xyz = np.vstack([ground, canopy])
    z = ground_under_canopy(xyz)
    assert np.abs(z[:4000] - ground[:, 2]).max() < 0.1
    assert np.abs(z[4000:] - 0.1 * canopy[:, 0]).mean() < 0.1


def test_segment_trees_verb_dispatches_to_stems():
    pts, truth = plot_scan(n_trees=4, size_m=12, seed=2)
    labels = segment_trees(PointCloud(pts, {"height": pts[:, 2] - 0.0}), StemSegmentation())
    assert labels.dtype == np.int32 and labels.max() >= 3


def test_bad_parameters_say_which():
    with pytest.raises(Exception, match="slice"):
        StemSegmentation(slice_low_m=2.0, slice_high_m=1.0)


TLS = Path(__file__).resolve().parents[2] / "shared" / "data" / "tls"


@pytest.mark.skipif(not (TLS / "tree1.xyz").exists(), reason="the shared TLS scans are not here")
def test_real_trees_that_fork_near_breast_height_are_found():
    """tree1, tree7, tree13 (small trees branching at 1.0-1.4 m, tree13 sparse) placed 6 m apart."""
    rng = np.random.default_rng(0)
    parts, src = [], []
    for k, i in enumerate((1, 7, 13)):
        x = np.loadtxt(TLS / f"tree{i}.xyz")
        low = x[x[:, 2] < x[:, 2].min() + 0.3]
        parts.append(x - np.r_[low[:, :2].mean(axis=0), x[:, 2].min()] + np.r_[4 + 6 * k, 10, 0])
        src.append(np.full(len(x), k + 1))
    g = rng.uniform(0, 20, (16000, 2))
    parts.append(np.c_[g, rng.normal(0, 0.02, len(g))])
    src.append(np.zeros(len(g), int))
    pts, src = np.vstack(parts), np.concatenate(src)
    cloud = PointCloud(pts, {})
    labels, stems = StemSegmentation().segment_with_stems(cloud)
    assert len(stems) == 3
    xy = stems.xy + cloud.origin[:2]
    assert np.abs(xy - np.c_[[4, 10, 16], [10, 10, 10]]).max() < 0.3
    assert ((stems.dbh_m > 0.1) & (stems.dbh_m < 0.5)).all()
    for k in range(3):
        assert (labels[src == k + 1] == k + 1).mean() > 0.8


def test_segmenttrees_cli_finds_the_stems_of_a_plot_scan_without_crs(tmp_path, capsys):
    """A terrestrial plot scan as a text file, no CRS, no ground class: METHOD auto picks stems."""
    import laspy

    from sylva import cli
    from sylva.core.io.gpkg import read_gpkg

    pts, truth = plot_scan(n_trees=6, size_m=14, seed=5)
    scan = tmp_path / "plot.xyz"
    np.savetxt(scan, pts + np.array([500.0, 200.0, 30.0]), fmt="%.4f")
    trees, seg = tmp_path / "trees.gpkg", tmp_path / "seg.laz"
    rc = cli.main(["segmenttrees", f"--INPUT={scan}", f"--OUTPUT={seg}", f"--TREES={trees}"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    said = out.out + out.err
    assert "METHOD stems" in said and "local engineering frame" in said
    table = read_gpkg(trees, "trees")
    assert len(table) == 6
    labels = np.asarray(laspy.read(seg)["treeID"])
    for t in range(1, 7):                      # each true tree's points mostly under one ID
        mine = labels[truth["tree"] == t]
        assert np.bincount(mine).argmax() > 0 and (mine == np.bincount(mine).argmax()).mean() > 0.8
    # the same scan through METHOD ncut is refused for want of a CRS, in one line naming the file
    rc = cli.main(["--quiet", "segmenttrees", f"--INPUT={scan}", "--METHOD=ncut", f"--TREES={tmp_path / 'n.gpkg'}"])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and len(err.splitlines()) == 1 and "plot.xyz" in err and "CRS" in err


def test_airborne_tiles_are_not_plot_scans(sample_laz):
    from sylva.core.io import read_cloud
    from sylva.core.segment.stems import AutoSegmentation, is_plot_scan
    from sylva.core.segment.tile import segment_tile
    from sylva.core.segment import NormalizedCut
    from sylva.core.terrain import SMRF, normalize

    assert not is_plot_scan(normalize(read_cloud(sample_laz), classify=SMRF()))
    pts, _ = plot_scan(n_trees=4, size_m=12, seed=2)
    assert isinstance(AutoSegmentation().resolve(normalize(PointCloud(pts, {}), classify=SMRF())), StemSegmentation)
    assert isinstance(AutoSegmentation().resolve(PointCloud(pts[:100], {"height": pts[:100, 2]})), NormalizedCut)


def test_a_plot_around_z_0_still_gets_its_ground():
    """z within half a metre of 0 looks normalised; the stems chain classifies the ground anyway (the
    plot slopes: taking z as height put its ground up to 0.56 m off)."""
    from sylva.core.segment.stems import AutoSegmentation
    from sylva.core.segment.tile import segment_tile

    pts, truth = plot_scan(n_trees=8, size_m=16, seed=1)
    seg = segment_tile(PointCloud(pts, {}), AutoSegmentation())
    assert isinstance(seg.method, StemSegmentation)
    h = np.full(len(pts), np.nan)
    h[seg.keep] = seg.cloud.attrs["height"]
    ground = truth["tree"] == 0
    assert np.nanmean(np.abs(h[ground])) < 0.06
