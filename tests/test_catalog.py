"""The catalog engine: tiles + buffers give the same forest as one tile; resume, failures, workers, .vpc."""
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from sylva.core.catalog import run_catalog
from sylva.core.errors import InputError
from sylva.core.io.gpkg import read_gpkg
from sylva.core.io.las import read_las, write_las
from sylva.core.io.tiles import list_tiles, read_vpc, write_vpc
from sylva.core.pipeline import PipelineOptions
from sylva.core.treeids import grid_keys, run_wide_remaps, tree_ids, unowned_trees
from sylva.testing.synth import ScanSpec, StandSpec, make_stand, simulate_scan

FAST = PipelineOptions(reconstruct=False)


def cut(cloud, truth, folder: Path, n: int):
    """Write ``cloud`` as n x n LAS tiles (by position) into ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    x, y = cloud.xyz[:, 0], cloud.xyz[:, 1]
    ix = np.minimum(((x - x.min()) / (np.ptp(x) + 1e-9) * n).astype(int), n - 1)
    iy = np.minimum(((y - y.min()) / (np.ptp(y) + 1e-9) * n).astype(int), n - 1)
    for i in range(n):
        for j in range(n):
            m = (ix == i) & (iy == j)
            write_las(folder / f"t_{i}_{j}.las", cloud.subset(m), extra={"true_tree": truth[m]})
    return folder


@pytest.fixture(scope="module")
def stand(tmp_path_factory):
    root = tmp_path_factory.mktemp("catalog")
    spec = StandSpec(width_m=60.0, depth_m=60.0, stems_per_ha=250, crown_overlap=0.5, seed=3)
    scan = simulate_scan(make_stand(spec), ScanSpec(pulse_density=5.0, seed=3))
    cut(scan.cloud, scan.truth_tree, root / "one", 1)
    cut(scan.cloud, scan.truth_tree, root / "three", 3)
    whole = run_catalog([root / "one"], root / "out_one", FAST)
    return root, scan, whole


def labelled_points(out: Path):
    """(mm-rounded xyz + gps_time sort key, treeID) of every output tile, in one canonical order."""
    clouds = [read_las(p) for p in sorted((out / "tiles").glob("*.la?"))]
    xyz = np.round(np.concatenate([c.xyz for c in clouds]) * 1000).astype(np.int64)
    t = np.concatenate([c.attrs["gps_time"] for c in clouds])
    lab = np.concatenate([np.asarray(c.attrs["treeID"]) for c in clouds])
    order = np.lexsort((xyz[:, 2], xyz[:, 1], xyz[:, 0], t))
    return xyz[order], lab[order]


def tree_table(out: Path):
    return read_gpkg(out / "forest.gpkg", "trees")


def assert_same_forest(a: Path, b: Path, min_agreement=0.995):
    xa, la = labelled_points(a)
    xb, lb = labelled_points(b)
    assert np.array_equal(xa, xb)                           # no point lost or duplicated
    assert (la == lb).mean() >= min_agreement
    ta, tb = tree_table(a).columns["tree_id"], tree_table(b).columns["tree_id"]
    assert len(np.unique(ta)) == len(ta) and len(np.unique(tb)) == len(tb)   # no tree twice
    assert np.array_equal(np.sort(ta), np.sort(tb))         # the same trees, the same IDs
    assert np.isin(la[la > 0], ta).all() and np.isin(lb[lb > 0], tb).all()   # every point's tree is in the table
    return (la == lb).mean()


def test_a_file_cut_into_chunks_gives_the_trees_of_the_whole_file(stand, tmp_path):
    """CHUNK_SIZE_M: one file becomes square chunks (here 2 x 2 + edges), each a tile with its buffer:
    the same trees, IDs and point labels as the file whole; the scratch chunks are gone afterwards."""
    from dataclasses import replace

    from sylva.core.io.chunks import needs_chunks
    from sylva.core.io.tiles import list_tiles

    root, _, whole = stand
    tiles, _ = list_tiles([root / "one"])
    assert needs_chunks(tiles[0], 25.0) and not needs_chunks(tiles[0], 0.0)
    chunked = run_catalog([root / "one"], tmp_path / "out", replace(FAST, chunk_size_m=25.0))
    assert chunked.failures == [] and len(chunked.tiles) >= 4
    assert all(t["name"].startswith("t_0_0_") for t in chunked.tiles)
    assert chunked.trees == whole.trees
    assert assert_same_forest(root / "out_one", tmp_path / "out") >= 0.995
    assert not (tmp_path / "out" / "parts" / "chunks").exists()
    again = run_catalog([root / "one"], tmp_path / "out", replace(FAST, chunk_size_m=25.0))   # resumed: same chunks
    assert sorted(again.skipped) == sorted(t["name"] for t in chunked.tiles)


def test_chunks_with_two_workers_finish(sample_laz, tmp_path):
    """The cut decodes the LAZ in the run's own process before it forks its workers: with lazrs's thread pool
    (laspy's default) the forked workers waited for its threads forever, at their first LAZ write."""
    import subprocess
    import sys

    import laspy

    las = laspy.read(sample_laz)      # four copies side by side: chunks of 126k points, LAZ written in chunks
    copies = []
    for dx in (0, 100):
        for dy in (0, 100):
            a = las.points.array.copy()
            a["X"] += int(round(dx / las.header.scales[0]))
            a["Y"] += int(round(dy / las.header.scales[1]))
            copies.append(a)
    four = laspy.LasData(las.header)
    four.points = laspy.ScaleAwarePointRecord(np.concatenate(copies), las.header.point_format, las.header.scales,
                                              las.header.offsets)
    four.update_header()
    four.write(tmp_path / "four.laz")
    out = subprocess.run([sys.executable, "-m", "sylva.cli", "pipeline", f"--INPUT={tmp_path / 'four.laz'}",
                          "--CHUNK_SIZE_M=100", "--WORKERS=2", "--RECONSTRUCT=false",
                          f"--OUTPUT_FOLDER={tmp_path / 'out'}"], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    rep = json.loads((tmp_path / "out" / "report.json").read_text())
    assert len(rep["tiles"]) == 4 and rep["failures"] == [] and len(rep["peak_rss_mb_per_worker"]) == 2


def test_too_many_chunks_is_one_line(stand, tmp_path):
    from dataclasses import replace

    root, _, _ = stand
    with pytest.raises(InputError, match="CHUNK_SIZE_M=1: .* would be cut into .* chunks"):
        run_catalog([root / "one"], tmp_path / "out", replace(FAST, chunk_size_m=1.0))


def test_three_by_three_tiles_give_the_trees_of_one_tile(stand, tmp_path):
    root, scan, whole = stand
    truth = int(len(np.unique(scan.truth_tree[scan.truth_tree > 0])))
    assert whole.failures == [] and len(whole.tiles) == 1
    assert 0.8 * truth <= whole.trees <= 1.2 * truth        # a real segmentation, not a trivial one
    tiled = run_catalog([root / "three"], tmp_path / "out", FAST)
    assert len(tiled.tiles) == 9 and tiled.failures == []
    assert tiled.trees == whole.trees
    agreement = assert_same_forest(root / "out_one", tmp_path / "out")
    assert agreement >= 0.995
    # every owned tree is in exactly one tile's part; the report knows the points
    rep = json.loads((tmp_path / "out" / "report.json").read_text())
    assert rep["points"] == len(scan.cloud) and rep["trees"] == whole.trees
    assert (tmp_path / "out" / "report.txt").read_text().startswith("Sylva catalog run: 9 tiles")
    # IDs fit int32 and are derived from the top's position
    tops = read_gpkg(tmp_path / "out" / "forest.gpkg", "tree_tops")
    import shapely

    xy = shapely.get_coordinates(tops.geometries)[:, :2]
    assert np.array_equal(tops.columns["tree_id"], tree_ids(grid_keys(xy)))
    assert tops.columns["tree_id"].max() < 2 ** 31


def test_tiles_give_the_suppressed_trees_of_one_tile(tmp_path):
    """A dense broadleaf stand whose suppressed trees are found by NormalizedCut's understory rule
    (graph components no top reaches): 2 x 2 tiles give the trees of one tile, those included."""
    from sylva.core.segment import NormalizedCut, segment_trees
    from sylva.core.terrain import normalize
    from sylva.testing import crowns

    stand, spec = crowns.suite_preset("broadleaf", "dense", 10, seed=1, width_m=50.0)
    scan = simulate_scan(stand, spec)
    cloud = normalize(scan.cloud)
    with_rule = segment_trees(cloud, NormalizedCut())
    without = segment_trees(cloud, NormalizedCut(understory_points=0))
    assert len(np.unique(with_rule[with_rule > 0])) > len(np.unique(without[without > 0]))
    cut(scan.cloud, scan.truth_tree, tmp_path / "one", 1)
    cut(scan.cloud, scan.truth_tree, tmp_path / "two", 2)
    whole = run_catalog([tmp_path / "one"], tmp_path / "out_one", FAST)
    tiled = run_catalog([tmp_path / "two"], tmp_path / "out_two", FAST)
    assert whole.failures == [] and tiled.failures == [] and len(tiled.tiles) == 4
    assert tiled.trees == whole.trees
    assert assert_same_forest(tmp_path / "out_one", tmp_path / "out_two") >= 0.995


def test_rerun_skips_complete_tiles_and_redoes_a_changed_one(stand, tmp_path):
    root, _, _ = stand
    src = tmp_path / "tiles"
    shutil.copytree(root / "three", src)
    first = run_catalog([src], tmp_path / "out", FAST)
    assert first.skipped == []
    again = run_catalog([src], tmp_path / "out", FAST)
    assert sorted(again.skipped) == sorted(r["name"] for r in first.tiles)
    assert again.trees == first.trees
    # a changed input invalidates that tile and the neighbours that read it as a buffer
    cloud = read_las(src / "t_0_0.las")
    write_las(src / "t_0_0.las", cloud.subset(np.arange(len(cloud)) % 2 == 0))
    third = run_catalog([src], tmp_path / "out", FAST)
    redone = {r["name"] for r in third.tiles} - set(third.skipped)
    assert {"t_0_0", "t_0_1", "t_1_0", "t_1_1"} <= redone and "t_2_2" not in redone


def test_corrupt_tile_is_reported_not_fatal(stand, tmp_path):
    root, _, _ = stand
    src = tmp_path / "tiles"
    shutil.copytree(root / "three", src)
    data = (src / "t_2_2.las").read_bytes()
    (src / "t_2_2.las").write_bytes(data[: len(data) // 2])        # truncated: header fine, points missing
    (src / "junk.las").write_bytes(b"this is not a LAS file at all" * 10)
    rep = run_catalog([src], tmp_path / "out", FAST)
    failed = {f["name"]: f for f in rep.failures}
    assert set(failed) == {"t_2_2", "junk"}
    assert "truncated" in failed["t_2_2"]["reason"] and "junk.las" in failed["junk"]["reason"]
    assert len(rep.tiles) == 8 and rep.trees > 0
    text = (tmp_path / "out" / "report.txt").read_text()
    assert "FAILED t_2_2" in text and "FAILED junk" in text


def test_failing_tile_is_retried_once_then_reported(stand, tmp_path, monkeypatch):
    import sylva.core.catalog as catalog

    root, _, _ = stand
    real = catalog.process_tile
    calls = []

    def flaky(job, **kw):
        calls.append((job.name, job.attempt))
        if job.name == "t_1_1" and job.attempt == 1:
            raise RuntimeError("worker lost")      # transient: the retry succeeds
        if job.name == "t_0_2":
            raise MemoryError("out of memory")     # persistent: reported after two attempts
        return real(job, **kw)

    monkeypatch.setattr(catalog, "process_tile", flaky)
    rep = run_catalog([root / "three"], tmp_path / "out", FAST)
    assert ("t_1_1", 2) in calls and ("t_0_2", 2) in calls and ("t_0_2", 3) not in calls
    assert [(f["name"], f["attempts"]) for f in rep.failures] == [("t_0_2", 2)]
    assert "MemoryError" in rep.failures[0]["reason"] and len(rep.tiles) == 8


def test_worker_count_does_not_change_the_result(stand, tmp_path):
    root, _, _ = stand
    rep = run_catalog([root / "three"], tmp_path / "out", FAST, workers=2)
    assert len({r["pid"] for r in rep.tiles}) == 2                   # really two processes
    assert assert_same_forest(root / "out_one", tmp_path / "out") >= 0.995
    assert rep.peak_rss_mb_per_worker and all(v > 0 for v in rep.peak_rss_mb_per_worker.values())


def test_vpc_input(stand, tmp_path):
    root, _, _ = stand
    tiles, failures = list_tiles([root / "three"])
    assert failures == []
    vpc = write_vpc(tmp_path / "survey.vpc", tiles[:4], crs=read_las(tiles[0].path).crs)
    listed = read_vpc(vpc)
    assert [p for p, _ in listed] == [t.path for t in tiles[:4]]
    assert listed[0][1] == pytest.approx(tiles[0].bounds)
    doc = json.loads(vpc.read_text())
    assert doc["type"] == "FeatureCollection" and "proj:bbox" in doc["features"][0]["properties"]
    rep = run_catalog([vpc], tmp_path / "out", FAST)
    assert len(rep.tiles) == 4 and rep.failures == [] and rep.trees > 0
    # a .vpc as PDAL wrench / QGIS write it (STAC ItemCollection, relative hrefs, proj:bbox)
    folder = tmp_path / "survey"
    shutil.copytree(root / "three", folder)
    feats = [{"type": "Feature", "stac_version": "1.0.0", "id": t.name, "geometry": None,
              "bbox": [t.bounds[0], t.bounds[1], 0.0, t.bounds[2], t.bounds[3], 100.0],
              "properties": {"datetime": "2024-01-01T00:00:00Z", "pc:count": t.points, "proj:epsg": 32632,
                             "proj:bbox": [t.bounds[0], t.bounds[1], 0.0, t.bounds[2], t.bounds[3], 100.0]},
              "links": [], "assets": {"data": {"href": f"./{Path(t.path).name}", "roles": ["data"]}}}
             for t in tiles]
    (folder / "all.vpc").write_text(json.dumps({"type": "FeatureCollection", "features": feats}))
    listed = read_vpc(folder / "all.vpc")
    assert len(listed) == 9 and listed[4][1] == pytest.approx(tiles[4].bounds)
    rep = run_catalog([folder / "all.vpc"], tmp_path / "out9", FAST)
    assert len(rep.tiles) == 9 and rep.trees == stand[2].trees


def test_tree_ids_are_stable_and_collisions_resolved_run_wide(stand, tmp_path):
    rng = np.random.default_rng(0)
    keys = rng.integers(-10 ** 9, 10 ** 9, size=(300, 2))
    perm = rng.permutation(len(keys))
    with pytest.raises(InputError, match="do not fit"):
        tree_ids(keys, bits=8)                            # 300 trees, 255 IDs
    small = keys[:150]                                    # 150 trees in 255 IDs: collisions certain
    assert len(np.unique(tree_ids(small, bits=31))) == 150
    ids = tree_ids(small, bits=8)
    assert len(np.unique(ids)) == 150 and ids.min() > 0 and ids.max() < 256
    p = perm[perm < 150]
    assert np.array_equal(tree_ids(small[p], bits=8), ids[p])          # order does not matter
    # an ID a tile saw (its points carry it) that no tile owns becomes 0; owned ones keep or change theirs
    k = np.array([[5, 7]]), np.array([[9, 9]])
    maps = run_wide_remaps({"a": (k[0], np.concatenate(k), np.array([11, 12])),
                            "b": (np.zeros((0, 2), dtype=np.int64), k[0], np.array([13]))}, bits=31)
    own = int(tree_ids(k[0])[0])
    assert maps == {"a": {11: own, 12: 0}, "b": {13: own}} and unowned_trees(maps) == 1
    incomplete = run_wide_remaps({"a": (k[0], np.concatenate(k), np.array([11, 12]))}, complete=False)
    assert incomplete == {"a": {11: own}}                # a failed tile may yet own the other
    # a resumed run in which another tile now owns a tree an earlier run emptied (ID 0) leaves it empty
    rerun = run_wide_remaps({"a": (np.zeros((0, 2), dtype=np.int64), k[1], np.array([0])),
                             "b": (k[1], k[1], np.array([12]))})
    assert 0 not in rerun.get("a", {}) and unowned_trees(rerun) == 0
    from sylva.core.catalog import RunReport

    rep = RunReport(tiles=[], failures=[], skipped=[], trees=1, points=9, seconds=1.0, workers=1, scheduler=None,
                    peak_rss_mb_per_worker={}, id_collisions_rewritten=0, gpkg=None, tileset=None,
                    unowned_edge_trees=1, unowned_edge_points=1234)
    assert "WARNING 1 segment(s) across tile edges owned by no tile" in rep.summary()
    assert "1,234 points carry no tree ID" in rep.summary()
    # a whole run with 9-bit IDs (many collisions): tiled and single give the same IDs
    root, _, _ = stand
    opts = PipelineOptions(reconstruct=False, id_bits=9)
    one = run_catalog([root / "one"], tmp_path / "one", opts)
    three = run_catalog([root / "three"], tmp_path / "three", opts)
    assert one.trees == three.trees
    assert assert_same_forest(tmp_path / "one", tmp_path / "three") >= 0.995


def test_dask_local_cluster(stand, tmp_path):
    distributed = pytest.importorskip("distributed")
    root, _, _ = stand
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        rep = run_catalog([root / "three"], tmp_path / "out", FAST, scheduler=client)
    assert rep.failures == [] and len(rep.tiles) == 9
    assert assert_same_forest(root / "out_one", tmp_path / "out") >= 0.995


def test_halos_give_the_same_buffer_as_reading_the_neighbours(stand, tmp_path):
    """A neighbour's points in a buffer come from its halo once written: the same points and attributes."""
    from sylva.core.catalog import make_jobs
    from sylva.core.pipeline import halo_path, read_buffered

    from dataclasses import replace

    root, _, _ = stand
    opts = replace(FAST, buffer_m=5.0)   # 20 m tiles: a 5 m ring is less than the whole tile
    tiles, _ = list_tiles([root / "three"])
    jobs = make_jobs(tiles, tmp_path, opts)
    centre = next(j for j in jobs if j.name == "t_1_1")
    assert len(centre.neighbours) == 8
    assert not (tmp_path / "parts" / "halo").exists()
    _, first, _ = read_buffered(centre)            # reads the 8 files, writes their halos and its own
    halos = sorted((tmp_path / "parts" / "halo").glob("*.npz"))
    assert len(halos) == 9
    assert all(halo_path(tmp_path, c, opts).exists() for _, _, _, c in centre.neighbours)
    # a halo holds the ring within buffer_m of the tile's edges, not the whole tile
    whole = read_las(root / "three" / "t_0_0.las")
    with np.load(halo_path(tmp_path, centre.neighbours[0][3], opts)) as z:
        assert 0 < len(z["xyz"]) < len(whole)
    _, again, _ = read_buffered(centre)            # now from the halos
    key = lambda c: np.lexsort(np.round(c.xyz * 1000).T)  # noqa: E731
    a, b = key(first), key(again)
    assert np.array_equal(first.xyz[a], again.xyz[b])
    assert set(first.attrs) == set(again.attrs)
    for name in first.attrs:
        assert np.array_equal(np.asarray(first.attrs[name])[a], np.asarray(again.attrs[name])[b]), name
    # a run leaves no scratch halos behind
    run_catalog([root / "three"], tmp_path / "run", FAST)
    assert not (tmp_path / "run" / "parts" / "halo").exists()


def test_a_dying_worker_costs_only_its_own_tile(stand, tmp_path):
    """A worker killed mid-run (out of memory, native crash) breaks the pool; the other tiles still finish."""
    from functools import partial

    from badfiles import die_on
    from sylva.core.catalog import make_jobs
    from sylva.core.engine import WorkerDied, run_pool

    root, _, _ = stand
    tiles, _ = list_tiles([root / "three"])
    jobs = make_jobs(tiles, tmp_path, FAST)
    outcome = {}

    def on_done(job, record, err):
        outcome[job.name] = err if err is not None else record
        return None

    run_pool(jobs, partial(die_on, "t_1_1"), 2, on_done)
    assert sorted(outcome) == sorted(j.name for j in jobs)
    assert isinstance(outcome["t_1_1"], WorkerDied) and "t_1_1" in str(outcome["t_1_1"])
    others = [v for k, v in outcome.items() if k != "t_1_1"]
    assert all(isinstance(r, dict) and r["status"] == "done" for r in others)


def test_progress_moves_inside_a_tile(stand, tmp_path):
    """One big tile must not sit at 0 %: the tile's own steps are reported, in order."""
    root, _, _ = stand
    seen = []
    run_catalog([root / "one"], tmp_path / "out", FAST, progress=lambda f, m="": seen.append((f, m)))
    inside = [(f, m) for f, m in seen if "segmenting" in m or "tree tops" in m or "measuring" in m]
    assert len(inside) >= 3 and all(0.0 < f < 0.9 for f, _ in inside)
    fractions = [f for f, _ in seen]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0


def test_billboards_are_the_far_level_of_detail(stand, tmp_path):
    """With billboards on, each tile's 3D Tiles root (far) content draws one textured billboard per tree."""
    from dataclasses import replace

    from sylva.core.export.gltf import read_glb

    root, _, _ = stand
    rep = run_catalog([root / "one"], tmp_path / "out", replace(FAST, reconstruct=True, billboards=True))
    assert not rep.failures and rep.trees > 20
    far = next((tmp_path / "out" / "models" / "tileset").glob("*/content/root.glb"))
    doc, _ = read_glb(far)
    boards = [m for m in doc["materials"] if m["name"].startswith("billboard_")]
    assert len(boards) == rep.trees
    assert all(m["alphaMode"] == "MASK" and m["doubleSided"] for m in boards)
    assert len(doc["images"]) == rep.trees


# --------------------------------------------------------------------------- merging: the parts' rows, in order

def _ogr_features(path):
    """{layer: (its field names, [(ISO WKB or None, {field: value})])} of every layer, as GDAL/OGR reads it."""
    from osgeo import ogr

    ds = ogr.Open(str(path))
    out = {}
    for k in range(ds.GetLayerCount()):
        layer = ds.GetLayerByIndex(k)
        defn = layer.GetLayerDefn()
        names = [defn.GetFieldDefn(j).GetName() for j in range(defn.GetFieldCount())]
        out[layer.GetName()] = (set(names), [
            (None if f.GetGeometryRef() is None else bytes(f.GetGeometryRef().ExportToIsoWkb()),
             {n: (None if f.IsFieldNull(j) else f.GetField(j)) for j, n in enumerate(names)})
            for f in layer])
    return out


def _extents(path):
    import sqlite3
    from contextlib import closing

    with closing(sqlite3.connect(path)) as con:
        return {t: box for t, *box in con.execute("SELECT table_name, min_x, min_y, max_x, max_y FROM gpkg_contents")}


def _parts(folder: Path):
    """Three tile parts: a column only in the second, a layer missing from the third and one only in it,
    an empty layer (no extent), another CRS; their tree_id values, for ID maps."""
    import pyproj
    import shapely

    from sylva.core.io.gpkg import write_gpkg
    from sylva.core.table import VectorTable, point_layer

    rng = np.random.default_rng(5)
    crs, other = pyproj.CRS("EPSG:32632"), pyproj.CRS("EPSG:25832")
    paths, ids = [], []
    for k, n in enumerate((40, 700, 0)):
        tid = rng.integers(1, 50, n)
        xyz = rng.uniform(0, 100, (n, 3)) + [500000 + 100 * k, 5500000, 250]
        trees = {"tree_id": tid, "height": rng.uniform(2, 30, n)}
        if k == 1:
            trees["dbh"] = rng.uniform(0.1, 0.5, n)
        tables = [VectorTable("trees", "none", None, trees, None),
                  point_layer("crown_points", xyz, {"tree_id": tid, "height": xyz[:, 2] - 250}, crs)]
        if k < 2:
            boxes = np.array([shapely.box(x, y, x + 1, y + 1) for x, y in xyz[:5, :2]], dtype=object)
            tables.append(VectorTable("crowns", "polygon", boxes, {"tree_id": tid[:5]}, crs, has_z=False))
        else:
            tables.append(point_layer("extra", xyz[:0], {"tree_id": tid[:0]}, other))
        paths.append(write_gpkg(folder / f"p{k}.gpkg", tables, spatial_index=False))   # as the pipeline writes parts
        ids.append(tid)
    return paths, ids


@pytest.mark.parametrize("remap", [False, True])
def test_merge_gpkg_holds_the_parts_rows_in_order(tmp_path, remap):
    """The merge holds every layer of every part, each part's rows after the previous part's, with the
    union of the parts' columns (None where a part has no such column), tree_id through that part's ID
    map, the union of the parts' extents; a conforming GeoPackage with R-trees, as GDAL reads it."""
    import sqlite3
    from contextlib import closing

    from sylva.core.io.gpkg_merge import merge_gpkg
    from sylva.core.io.gpkg import PAGE_SIZE

    parts, ids = _parts(tmp_path)
    # the second part's map holds the first part's last ID too: only the second part's rows may change
    maps = [{int(ids[0][0]): 1000}, {int(ids[1][3]): 1001, int(ids[1][5]): 1002, int(ids[0][-1]): 1003}, {}] \
        if remap else [{}, {}, {}]
    new = merge_gpkg(parts, tmp_path / "new.gpkg", maps if remap else None)
    got = _ogr_features(new)
    got.pop("layer_styles", None)         # the styles the merge adds (test_merge_conforms_is_indexed_and_styled)
    read = [_ogr_features(p) for p in parts]
    assert set(got) == {"trees", "crown_points", "crowns", "extra"}
    for layer, (columns, rows) in got.items():
        assert columns == set().union(*(part[layer][0] for part in read if layer in part)), layer
        want = []
        for part, id_map in zip(read, maps):
            for geom, fields in part.get(layer, (None, []))[1]:
                fields = {c: fields.get(c) for c in columns}
                if fields.get("tree_id") is not None:
                    fields["tree_id"] = id_map.get(fields["tree_id"], fields["tree_id"])
                want.append((geom, fields))
        assert rows == want, layer
    boxes = [_extents(p) for p in parts]
    for layer, box in _extents(new).items():
        have = [b[layer] for b in boxes if layer in b and b[layer][0] is not None]
        assert box == ([min(b[0] for b in have), min(b[1] for b in have), max(b[2] for b in have),
                        max(b[3] for b in have)] if have else [None] * 4), layer
    from test_gpkg import check_rtrees, validate

    assert validate(new) == ""
    check_rtrees(new)
    assert len(got["crown_points"][1]) == 740 and got["trees"][0] == {"tree_id", "height", "dbh"}
    assert (1001 in {f["tree_id"] for _, f in got["trees"][1]}) == remap
    with closing(sqlite3.connect(new)) as con:
        assert con.execute("PRAGMA page_size").fetchone()[0] == PAGE_SIZE     # set before the file is created


def _rows(path, table):
    import sqlite3

    con = sqlite3.connect(path)
    try:
        cols = [r[1] for r in con.execute(f'PRAGMA table_info("{table}")') if r[1] != "last_change"]
        return con.execute(f'SELECT {",".join(cols)} FROM "{table}" ORDER BY fid').fetchall()
    finally:
        con.close()


def test_forest_is_merged_while_tiles_run_in_processing_order(stand, tmp_path):
    """The merge during the run gives the rows merge_gpkg gives the parts in processing order (largest
    tile first, then by name), whatever the number of workers; nothing temporary is left."""
    from sylva.core.io.gpkg_merge import merge_gpkg
    from sylva.core.pipeline import part_paths

    root, _, _ = stand
    one = run_catalog([root / "three"], tmp_path / "w1", FAST, workers=1)
    two = run_catalog([root / "three"], tmp_path / "w2", FAST, workers=2)
    tiles, _ = list_tiles([root / "three"])
    order = [t.name for t in sorted(tiles, key=lambda t: -t.points)]
    assert order != sorted(order)                                   # the orders differ here
    ref = merge_gpkg([part_paths(tmp_path / "w1", n)["gpkg"] for n in order], tmp_path / "ref.gpkg")
    for table in ("trees", "crown_points", "crowns"):
        expected = _rows(ref, table)
        assert len(expected) > 10
        assert _rows(one.gpkg, table) == expected == _rows(two.gpkg, table)
    assert not list((tmp_path / "w1").glob(".forest.gpkg.*")) and not list((tmp_path / "w2").glob(".forest.gpkg.*"))


def test_the_pool_hands_its_waits_to_the_merge(stand, tmp_path):
    """While tiles are in flight the pool calls idle() (the merge's step); a busy idle() is called
    again at once, an idle one is not spun on; every tile still finishes."""
    from functools import partial

    from badfiles import slow_name
    from sylva.core.catalog import make_jobs
    from sylva.core.engine import run_pool

    root, _, _ = stand
    tiles, _ = list_tiles([root / "three"])
    jobs = make_jobs(tiles, tmp_path, FAST)
    finished, calls = [], []

    def on_done(job, record, err):
        assert err is None and record == job.name
        finished.append(job.name)

    def idle():
        calls.append(len(finished))
        return len(calls) <= 3                      # three steps of work, then nothing to do

    run_pool(jobs, partial(slow_name, 0.3), 2, on_done, idle=idle)
    assert sorted(finished) == sorted(j.name for j in jobs)
    assert calls[:4] == [0, 0, 0, 0]                # called before any tile is back
    assert len(calls) < 10 * len(jobs)              # not a busy loop once idle() has nothing to do


def test_cancel_leaves_no_forest_behind(stand, tmp_path):
    from sylva.core.errors import Cancelled

    root, _, _ = stand
    done = []

    def cancelled():
        return len(done) >= 3

    def progress(f, message=""):
        if message.endswith("tiles") and " of " in message:
            done.append(message)

    with pytest.raises(Cancelled):
        run_catalog([root / "three"], tmp_path / "out", FAST, progress=progress, cancelled=cancelled)
    assert not (tmp_path / "out" / "forest.gpkg").exists()
    assert not list((tmp_path / "out").glob(".forest.gpkg.*"))


@pytest.mark.parametrize("workers", [1, 2])
def test_the_engine_runs_any_function_with_retries(workers):
    """core.engine.apply knows nothing of tiles: any picklable function of a job, here or in a pool;
    the job on_done returns is run again, and cancel stops the run."""
    from dataclasses import replace

    from badfiles import Job, fail_first
    from sylva.core.engine import apply
    from sylva.core.errors import Cancelled

    jobs = [Job(n) for n in ("a", "flaky-b", "c", "flaky-d")]
    outcomes = []

    def on_done(job, result, err):
        outcomes.append((job.name, job.attempt, result, None if err is None else str(err)))
        return replace(job, attempt=2) if err is not None else None

    apply(jobs, fail_first, on_done, workers=workers)
    assert sorted(outcomes) == sorted([("a", 1, ("a", 1), None), ("c", 1, ("c", 1), None),
                                       ("flaky-b", 1, None, "flaky-b failed once"), ("flaky-b", 2, ("flaky-b", 2), None),
                                       ("flaky-d", 1, None, "flaky-d failed once"), ("flaky-d", 2, ("flaky-d", 2), None)])
    with pytest.raises(Cancelled):
        apply(jobs, fail_first, on_done, workers=workers, cancelled=lambda: True)
