"""Bad inputs and faults (issue 17): damaged files, outputs over inputs, mixed CRSs, full disks,
signals mid-run then RESUME, two runs into one folder.

Each case runs the `sylva` command as a user would (a subprocess) and asserts the one-line message,
the exit code, that the inputs are byte-identical afterwards and that no partial output or ``.part``
file remains; the important ones run through ``qgis_process`` too.  Files are small (the bundled
sample, or 30 m corners of it) so the whole suite takes about a minute once numba's cache is warm.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import signal
import sqlite3
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

from badfiles import corner_tiles, make_damaged_files, mixed_crs_tiles

from sylva.algorithms import all_algorithms
from sylva.algorithms import spec as S


def sylva(*args, cwd=None, env=None, umask=None, timeout=600):
    def pre():
        if umask is not None:
            os.umask(umask)

    return subprocess.run([sys.executable, "-m", "sylva.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, env=env, timeout=timeout, preexec_fn=pre)


class _Run:
    def __init__(self, returncode, stdout, stderr):
        self.returncode, self.stdout, self.stderr = returncode, stdout, stderr


def cli(*args):
    """``sylva ARGS`` run in this process (the same main() as the command; quicker for the big matrices)."""
    import contextlib
    import io

    from sylva.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main([str(a) for a in args])
        except SystemExit as exc:   # argparse
            code = exc.code
    return _Run(code, out.getvalue(), err.getvalue())


def digest(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def digests(paths) -> dict:
    return {str(p): digest(p) for p in paths}


def one_line_error(out, *words):
    """The command failed with exit code 1 and one error line (no traceback) holding every word."""
    text = out.stdout + out.stderr
    assert out.returncode == 1, text
    assert "Traceback" not in text, text
    errors = [ln for ln in out.stderr.splitlines() if ": error: " in ln]
    assert len(errors) == 1, out.stderr
    for w in words:
        assert str(w) in errors[0], (w, errors[0])
    return errors[0]


def leftovers(folder: Path) -> list:
    """Temporary files of atomic writes (.part) anywhere under ``folder``."""
    return sorted(str(p) for p in Path(folder).rglob("*.part"))


@pytest.fixture(scope="module")
def damaged(tmp_path_factory, sample_laz):
    return make_damaged_files(tmp_path_factory.mktemp("damaged"), sample_laz)


@pytest.fixture(scope="module")
def corner(tmp_path_factory, sample_laz):
    """Four 30 m LAZ tiles of the sample's corner (a pipeline over them takes seconds)."""
    folder = tmp_path_factory.mktemp("corner")
    corner_tiles(folder, sample_laz, 30.0, 2)
    return folder


# --------------------------------------------------------------------------- damaged files

@pytest.mark.parametrize("case", [
    "laz_truncated_100", "laz_truncated_500", "laz_truncated_900", "laz_truncated_999",
    "las_truncated_100", "las_truncated_500", "las_truncated_999",
    "laz_zeroed_20", "laz_zeroed_50", "laz_zeroed_80",
    "laz_count_half", "laz_count_slightly_low", "laz_count_high", "laz_count_slightly_high",
    "las_count_low", "las_count_high", "laz_bounds_lie"])
def test_damaged_file_is_refused_in_one_line(damaged, tmp_path, case):
    path, words = damaged[case]
    before = digest(path)
    target = tmp_path / "tops.gpkg"
    out = cli("treetops", f"--INPUT={path}", "--WINDOW=fixed", f"--OUTPUT={target}")
    one_line_error(out, path.name, words)
    assert digest(path) == before
    assert not target.exists() and leftovers(tmp_path) == []


def test_zeroed_laz_through_the_command(damaged, tmp_path):
    """The issue's case: 20 kB zeroed in the middle of a LAZ; segmenttrees used to write 457 trees."""
    path, _ = damaged["laz_zeroed_50"]
    before = digest(path)
    out = sylva("segmenttrees", f"--INPUT={path}", f"--OUTPUT={tmp_path / 'seg.laz'}", f"--TREES={tmp_path / 't.gpkg'}")
    one_line_error(out, path.name, "damaged", "outside the header's bounds")
    assert digest(path) == before and sorted(tmp_path.iterdir()) == []


def test_damaged_tile_fails_alone_in_the_pipeline(damaged, corner, tmp_path):
    tiles = tmp_path / "tiles"
    tiles.mkdir()
    good = sorted(corner.glob("*.laz"))
    for p in good[:3]:
        (tiles / p.name).write_bytes(p.read_bytes())
    data = good[3].read_bytes()   # the fourth tile, 8 kB zeroed in the middle of its points
    mid = len(data) // 2
    (tiles / "zeroed.laz").write_bytes(data[:mid] + bytes(8192) + data[mid + 8192:])
    before = digests(tiles.iterdir())
    out_dir = tmp_path / "out"
    out = sylva("pipeline", f"--INPUT={tiles}", "--RECONSTRUCT=false", f"--OUTPUT_FOLDER={out_dir}")
    assert out.returncode == 0, out.stderr
    assert "Traceback" not in out.stderr
    report = json.loads((out_dir / "report.json").read_text())
    assert [f["name"] for f in report["failures"]] == ["zeroed"]
    assert "zeroed.laz" in report["failures"][0]["reason"] and report["failures"][0]["attempts"] >= 1
    assert any(w in report["failures"][0]["reason"] for w in ("damaged", "truncated"))
    assert len(report["tiles"]) == 3
    assert not (out_dir / "tiles" / "zeroed.laz").exists()
    assert "(0 attempt(s))" not in (out_dir / "report.txt").read_text()
    assert digests(tiles.iterdir()) == before and leftovers(out_dir) == []


@pytest.mark.parametrize("case", ["laz_zeroed_20", "laz_zeroed_50", "laz_bounds_lie", "laz_count_slightly_low",
                                  "laz_count_slightly_high"])
def test_damaged_file_cut_into_chunks_fails_alone(damaged, corner, case, tmp_path):
    """CHUNK_SIZE_M cuts a large file by copying its records: the cut makes every check a read makes, and a
    damaged file is one failed tile (the others go on; nothing of its cut stays)."""
    tiles = tmp_path / "tiles"
    tiles.mkdir()
    good = sorted(corner.glob("*.laz"))[0]
    (tiles / good.name).write_bytes(good.read_bytes())
    (tiles / f"{case}.laz").write_bytes(damaged[case][0].read_bytes())
    before = digests(tiles.iterdir())
    out_dir = tmp_path / "out"
    out = sylva("pipeline", f"--INPUT={tiles}", "--RECONSTRUCT=false", "--CHUNK_SIZE_M=50",
                f"--OUTPUT_FOLDER={out_dir}")
    assert out.returncode == 0 and "Traceback" not in out.stderr, out.stderr
    report = json.loads((out_dir / "report.json").read_text())
    assert [f["name"] for f in report["failures"]] == [case] and report["failures"][0]["attempts"] == 1
    assert f"{case}.laz" in report["failures"][0]["reason"]
    assert any(w in report["failures"][0]["reason"] for w in ("damaged", "truncated"))
    assert [t["name"] for t in report["tiles"]] == [good.stem]
    assert not (out_dir / "parts" / "chunks").exists()
    assert digests(tiles.iterdir()) == before and leftovers(out_dir) == []


def test_every_tile_failing_exits_non_zero(damaged, tmp_path):
    tiles = tmp_path / "tiles"
    tiles.mkdir()
    for case in ("laz_zeroed_50", "laz_count_half"):
        (tiles / f"{case}.laz").write_bytes(damaged[case][0].read_bytes())
    out = sylva("pipeline", f"--INPUT={tiles}", "--RECONSTRUCT=false", f"--OUTPUT_FOLDER={tmp_path / 'out'}")
    one_line_error(out, "tile", "damaged")
    assert leftovers(tmp_path / "out") == [] and not (tmp_path / "out" / "forest.gpkg").exists()


def test_nan_buffer_is_one_line_naming_the_parameter(corner, tmp_path):
    out = sylva("pipeline", f"--INPUT={corner}", "--BUFFER_M=nan", f"--OUTPUT_FOLDER={tmp_path / 'out'}")
    one_line_error(out, "BUFFER_M")
    assert "IndexError" not in out.stderr


# --------------------------------------------------------------------------- outputs over inputs

def _inputs_for(alg, folder: Path, sample: Path, glb: Path) -> dict:
    """Valid required inputs of ``alg`` (copies in ``folder``): {param: path}."""
    values = {}
    for p in alg.inputs:
        if p.optional or p.kind not in (S.FILE, S.RASTER, S.VECTOR):
            continue
        if alg.id == "exportmodels":
            src = glb
        elif p.kind == S.VECTOR:
            src = None
        else:
            src = sample
        if src is None:
            continue
        dst = folder / f"{p.name.lower()}{src.suffix}"
        if not dst.exists():
            dst.write_bytes(src.read_bytes())
        values[p.name] = dst
    return values


def _cases():
    for alg in all_algorithms().values():
        for out in alg.outputs:
            yield alg.id, out.name


@pytest.mark.parametrize("alg_id,output", list(_cases()))
def test_an_output_can_never_overwrite_an_input(tmp_path, sample_laz, alg_id, output):
    """Every output of every algorithm, pointed at its input (or the input's folder): refused, input intact."""
    alg = all_algorithms()[alg_id]
    glb = tmp_path / "models.glb"
    glb.write_bytes(b"glTF" + bytes(16))      # never read: the check comes first
    inputs = _inputs_for(alg, tmp_path, sample_laz, glb)
    if not inputs:
        pytest.skip(f"{alg_id} has only layer inputs (see the sketch case below)")
    name, path = next(iter(inputs.items()))
    p = alg.param(output)
    target = path.parent if p.kind == S.FOLDER_OUT else path
    if alg_id == "pipeline":
        target = path.parent
    before = digest(path)
    args = [f"--{k}={v}" for k, v in inputs.items()] + [f"--{output}={target}"]
    out = cli(alg_id, *args)
    one_line_error(out, f"--{output}=", "input")
    assert digest(path) == before
    assert leftovers(tmp_path) == []


def test_sketch_output_over_its_layer_input(tmp_path):
    import shapely

    from sylva.core.io.gpkg import write_gpkg
    from sylva.core.table import VectorTable

    front = tmp_path / "front.gpkg"
    write_gpkg(front, [VectorTable("front", "line", np.array([shapely.LineString([(0, 0), (0, 5)])], dtype=object),
                                   {}, None)])
    before = digest(front)
    out = sylva("treefromsketch", f"--FRONT={front}", f"--SIDE={front}", f"--LOCATION={front}",
                f"--MODEL={front}")
    assert out.returncode == 1 and "Traceback" not in out.stderr, out.stderr
    assert digest(front) == before


@pytest.mark.parametrize("alg_id,output,name,words", [
    ("segmenttrees", "OUTPUT", "x.txt", ".laz"),
    ("canopyheightmodel", "OUTPUT", "chm.laz", ".tif"),
    ("reconstructtrees", "MODELS", "m.gml", ".glb"),
    ("segmenttrees", "TREES", "trees.shp", ".gpkg"),
])
def test_output_extension_must_match_its_format(tmp_path, sample_laz, alg_id, output, name, words):
    out = cli(alg_id, f"--INPUT={sample_laz}", f"--{output}={tmp_path / name}")
    one_line_error(out, name, words)
    assert list(tmp_path.iterdir()) == []


def test_output_folder_that_is_a_file_or_read_only(corner, tmp_path):
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    out = sylva("pipeline", f"--INPUT={corner}", f"--OUTPUT_FOLDER={a_file}")
    one_line_error(out, "a_file", "file")
    ro = tmp_path / "ro"
    ro.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=1m", "tmpfs", str(ro)], capture_output=True).returncode:
        pytest.skip("cannot mount a read-only tmpfs here (not root?)")
    try:
        out = sylva("pipeline", f"--INPUT={corner}", f"--OUTPUT_FOLDER={ro / 'out'}")
        one_line_error(out, "not writable")
        out = sylva("canopyheightmodel", f"--INPUT={next(corner.glob('*.laz'))}", f"--OUTPUT={ro / 'chm.tif'}")
        one_line_error(out, "not writable")
    finally:
        subprocess.run(["umount", str(ro)], capture_output=True)


# --------------------------------------------------------------------------- CRSs

def test_tiles_in_different_crss_are_refused(tmp_path, sample_laz):
    paths = mixed_crs_tiles(tmp_path / "mixed", sample_laz)
    before = digests(paths)
    out = sylva("pipeline", f"--INPUT={tmp_path / 'mixed'}", f"--OUTPUT_FOLDER={tmp_path / 'out'}")
    line = one_line_error(out, "one CRS", "CRS parameter")
    assert sum(p.name in line for p in paths) == 2   # the two odd tiles are named
    assert digests(paths) == before and not (tmp_path / "out" / "forest.gpkg").exists()
    # an explicit CRS: every tile is read in it (the user says the tags are wrong), and the layers carry it
    out = sylva("pipeline", f"--INPUT={tmp_path / 'mixed'}", "--CRS=EPSG:26912", "--RECONSTRUCT=false",
                f"--OUTPUT_FOLDER={tmp_path / 'out'}")
    assert out.returncode == 0, out.stderr
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert len(report["tiles"]) == 3 and report["failures"] == []
    with sqlite3.connect(tmp_path / "out" / "forest.gpkg") as db:
        codes = {c for (c,) in db.execute("SELECT DISTINCT s.organization_coordsys_id FROM gpkg_geometry_columns g "
                                          "JOIN gpkg_spatial_ref_sys s ON s.srs_id = g.srs_id")}
    assert codes == {26912}
    assert digests(paths) == before


def test_the_same_crs_written_two_ways_is_one_crs(tmp_path, sample_laz):
    """A WKT and GeoTIFF keys of one CRS are equal; compared as CRSs, not by name."""
    import laspy
    import pyproj

    from sylva.core.io.tiles import list_tiles

    las = laspy.read(sample_laz)
    for name, crs in (("wkt", pyproj.CRS.from_wkt(pyproj.CRS.from_epsg(32632).to_wkt())),
                      ("epsg", pyproj.CRS.from_epsg(32632))):
        sub = laspy.LasData(laspy.LasHeader(point_format=1, version="1.2"))
        sub.header.offsets, sub.header.scales = las.header.offsets, las.header.scales
        sub.header.add_crs(crs, keep_compatibility=name == "epsg")
        sub.x, sub.y, sub.z = las.x[:500], las.y[:500], las.z[:500]
        sub.write(tmp_path / f"{name}.las")
    tiles, failures = list_tiles([tmp_path])
    assert len(tiles) == 2 and failures == []


# --------------------------------------------------------------------------- full disk

@contextlib.contextmanager
def filled_tmpfs(folder: Path, size_mb: int, free_kb: int = 0):
    """A tmpfs of ``size_mb`` at ``folder`` with a filler leaving ``free_kb`` free (skips where mounting is not
    allowed); unmounted afterwards."""
    folder.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_mb}m", "tmpfs", str(folder)],
                      capture_output=True).returncode:
        pytest.skip("cannot mount a tmpfs here (not root?)")
    try:
        free = os.statvfs(folder).f_bavail * os.statvfs(folder).f_frsize
        (folder / "filler").write_bytes(bytes(max(free - free_kb * 1024, 0)))
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], capture_output=True)


@pytest.fixture()
def tiny_disk(tmp_path):
    """A 2 MB tmpfs, filled to its last block."""
    with filled_tmpfs(tmp_path / "disk", 2) as disk:
        yield disk


def _only_filler(disk: Path):
    assert sorted(p.name for p in disk.rglob("*")) == ["filler"], sorted(map(str, disk.rglob("*")))


def test_full_disk_canopyheightmodel(tiny_disk, corner):
    out = sylva("canopyheightmodel", f"--INPUT={corner / 'c_0_0.laz'}", f"--OUTPUT={tiny_disk / 'chm.tif'}")
    one_line_error(out, "chm.tif", "disk is full")
    _only_filler(tiny_disk)


@pytest.mark.slow
def test_full_disk_reconstruct_and_export(tiny_disk, models_of_corner):
    seg, glb = models_of_corner
    before = digests([seg, glb])
    out = sylva("reconstructtrees", f"--INPUT={seg}", f"--MODELS={tiny_disk / 'models.glb'}",
                f"--TREES={tiny_disk / 'trees.gpkg'}")
    one_line_error(out, "disk is full")
    _only_filler(tiny_disk)
    out = sylva("exportmodels", f"--INPUT={glb}", f"--GLB_FOLDER={tiny_disk / 'per_tree'}",
                f"--OBJ={tiny_disk / 'trees.obj'}")
    one_line_error(out, "disk is full")
    _only_filler(tiny_disk)
    assert digests([seg, glb]) == before


@pytest.mark.parametrize("free_kb", [0, 1024])
def test_full_disk_pipeline(tmp_path, corner, free_kb):
    """A disk full from the start (the run lock cannot be written) or filling up during the run: one line
    saying the disk is full, exit 1, and nothing but the filler and the run's report left (no empty lock,
    no parts)."""
    with filled_tmpfs(tmp_path / "disk", 3, free_kb) as disk:
        out = sylva("pipeline", f"--INPUT={corner}", "--RECONSTRUCT=false", f"--OUTPUT_FOLDER={disk / 'out'}")
        one_line_error(out, "disk is full")
        left = [p for p in disk.rglob("*") if p.is_file() and p.name not in ("filler", "report.txt", "report.json")]
        assert left == [], left      # the report the error line names may stay; nothing else


# --------------------------------------------------------------------------- signals, RESUME, locks

def _start_pipeline(inputs, out_dir, *extra):
    return subprocess.Popen([sys.executable, "-m", "sylva.cli", "pipeline", f"--INPUT={inputs}",
                             f"--OUTPUT_FOLDER={out_dir}", "--RECONSTRUCT=false", *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for(predicate, proc, timeout=300):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if predicate():
            return True
        if proc.poll() is not None:
            return False
        time.sleep(0.05)
    return False


@pytest.fixture(scope="module")
def clean_run(corner, tmp_path_factory):
    out_dir = tmp_path_factory.mktemp("clean") / "out"
    out = sylva("pipeline", f"--INPUT={corner}", "--RECONSTRUCT=false", f"--OUTPUT_FOLDER={out_dir}")
    assert out.returncode == 0, out.stderr
    return json.loads((out_dir / "report.json").read_text())


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGKILL])
def test_signal_mid_run_then_resume(corner, clean_run, tmp_path, sig):
    before = digests(corner.glob("*.laz"))
    out_dir = tmp_path / "out"
    proc = _start_pipeline(corner, out_dir)
    started = _wait_for(lambda: any((out_dir / "parts").glob("*.done.json")), proc)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    assert started, err
    if sig == signal.SIGKILL:
        assert proc.returncode == -9
        # what a killed run leaves: its lock, and maybe .part files (one planted to be sure)
        (out_dir / "tiles" / ".c_0_0.laz.999.deadbeef.part").write_bytes(b"half a tile")
    else:
        assert proc.returncode == {signal.SIGINT: 130, signal.SIGTERM: 143}[sig], err
        assert "Traceback" not in err and len(err.strip().splitlines()[-1]) > 0
        assert leftovers(out_dir) == [] and not (out_dir / ".sylva-run.lock").exists()
    out = sylva("pipeline", f"--INPUT={corner}", "--RECONSTRUCT=false", "--RESUME=true", f"--OUTPUT_FOLDER={out_dir}")
    assert out.returncode == 0, out.stderr
    assert leftovers(out_dir) == [] and not (out_dir / ".sylva-run.lock").exists()
    report = json.loads((out_dir / "report.json").read_text())
    assert report["trees"] == clean_run["trees"] and report["failures"] == []
    assert digests(corner.glob("*.laz")) == before


def test_a_second_run_into_a_locked_folder_refuses(corner, tmp_path):
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        lock = {"pid": holder.pid, "host": os.uname().nodename, "started": "2026-01-01T00:00:00"}
        (out_dir / ".sylva-run.lock").write_text(json.dumps(lock))
        out = sylva("pipeline", f"--INPUT={corner}", f"--OUTPUT_FOLDER={out_dir}")
        one_line_error(out, "another Sylva run", f"pid {holder.pid}")
        assert sorted(p.name for p in out_dir.iterdir()) == [".sylva-run.lock"]
    finally:
        holder.kill()
        holder.wait()
    # the holder is gone: its lock is stale and taken over
    out = sylva("pipeline", f"--INPUT={corner}", "--RECONSTRUCT=false", f"--OUTPUT_FOLDER={out_dir}")
    assert out.returncode == 0, out.stderr
    assert not (out_dir / ".sylva-run.lock").exists()


def test_two_runs_into_one_folder_never_mix(corner, tmp_path):
    """Another parameter set, then another set of tiles: the folder holds only the last run's results."""
    from sylva.core.io.gpkg import read_gpkg
    from sylva.core.io.las import read_las

    out_dir = tmp_path / "out"
    first = sylva("pipeline", f"--INPUT={corner}", "--RECONSTRUCT=false", f"--OUTPUT_FOLDER={out_dir}")
    assert first.returncode == 0, first.stderr
    two = sorted(corner.glob("*.laz"))[:2]
    second = sylva("pipeline", f"--INPUT={';'.join(map(str, two))}", "--RECONSTRUCT=false", "--MIN_HEIGHT_M=8",
                   f"--OUTPUT_FOLDER={out_dir}")
    assert second.returncode == 0, second.stderr
    report = json.loads((out_dir / "report.json").read_text())
    trees = read_gpkg(out_dir / "forest.gpkg", "trees")
    assert len(trees) == report["trees"]
    assert sorted(p.stem for p in (out_dir / "tiles").glob("*.laz")) == sorted(p.stem for p in two)
    ids = set(np.asarray(trees.columns["tree_id"]).tolist())
    for tile in (out_dir / "tiles").glob("*.laz"):
        labels = set(np.unique(np.asarray(read_las(tile).attrs["treeID"])).tolist()) - {0}
        owned = set(np.asarray(trees.columns["tree_id"])[trees.columns["tile"] == tile.stem].tolist())
        assert owned <= labels and owned <= ids
    assert np.all(np.asarray(trees.columns["height"]) >= 8 - 1e-6)
    assert leftovers(out_dir) == []


def test_unreachable_or_unsafe_scheduler(corner, tmp_path):
    pytest.importorskip("distributed")
    env = dict(os.environ, SYLVA_SCHEDULER_TIMEOUT_S="3")
    out = sylva("pipeline", f"--INPUT={corner}", "--SCHEDULER=tcp://127.0.0.1:9", f"--OUTPUT_FOLDER={tmp_path / 'a'}",
                env=env)
    one_line_error(out, "SCHEDULER", "cannot reach")
    out = sylva("pipeline", f"--INPUT={corner}", "--SCHEDULER=inproc://x", f"--OUTPUT_FOLDER={tmp_path / 'b'}")
    one_line_error(out, "SCHEDULER", "tcp://")
    assert leftovers(tmp_path) == []


def _loaded(proc, library: str) -> bool:
    """True once the process has mapped ``library`` (Linux /proc): it is importing Sylva's dependencies."""
    try:
        return library in Path(f"/proc/{proc.pid}/maps").read_text()
    except OSError:
        return True


def test_a_first_signal_inside_the_import_system_waits_for_the_cancel_check(monkeypatch):
    """A Ctrl-C landing in importlib's own frames is not raised there (its module-lock clean-up printed
    the traceback before Sylva's one line); it is recorded, a second one is raised at once, and one
    landing in Sylva's own code before the computation is raised at once too."""
    import types

    from sylva import cli

    def frame(filename):
        return types.SimpleNamespace(f_code=types.SimpleNamespace(co_filename=filename))

    monkeypatch.setitem(cli._SIGNALLED, "signal", None)
    monkeypatch.setitem(cli._SIGNALLED, "computing", False)
    cli._on_interrupt(signal.SIGINT, frame("<frozen importlib._bootstrap>"))     # recorded, not raised
    assert cli._SIGNALLED["signal"] == signal.SIGINT
    with pytest.raises(KeyboardInterrupt):
        cli._on_interrupt(signal.SIGINT, frame("<frozen importlib._bootstrap>"))
    monkeypatch.setitem(cli._SIGNALLED, "signal", None)
    with pytest.raises(KeyboardInterrupt):
        cli._on_interrupt(signal.SIGINT, frame(cli.__file__))


def test_ctrl_c_during_start_up_is_one_line(sample_laz, tmp_path):
    """Ctrl-C while Sylva imports numpy, pyproj, laspy (and numba compiles): one line, exit 130.

    (Before Python has started Sylva at all — during the interpreter's own start-up — Python
    itself answers a Ctrl-C; the test waits until the child maps numpy, then the next library.)"""
    for library, extra in (("numpy", 0.0), ("pyproj", 0.0), ("numpy", 1.0)):
        proc = subprocess.Popen([sys.executable, "-m", "sylva.cli", "segmenttrees", f"--INPUT={sample_laz}",
                                 f"--OUTPUT={tmp_path / 'seg.laz'}"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True)
        _wait_for(lambda: _loaded(proc, library), proc, timeout=120)
        time.sleep(extra)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=120)
        assert proc.returncode == 130, err
        assert "Traceback" not in err and err.strip().splitlines()[-1].endswith("cancelled"), err
    assert not (tmp_path / "seg.laz").exists() and leftovers(tmp_path) == []


@pytest.mark.parametrize("sig, code, word", [(signal.SIGINT, 130, "cancelled"), (signal.SIGTERM, 143, "terminated")])
def test_signal_mid_run_of_one_algorithm(sample_laz, tmp_path, sig, code, word):
    """Ctrl-C or SIGTERM while segmenttrees computes: one line, its exit code, no output and no .part file."""
    proc = subprocess.Popen([sys.executable, "-m", "sylva.cli", "segmenttrees", f"--INPUT={sample_laz}",
                             f"--OUTPUT={tmp_path / 'seg.laz'}", f"--TREES={tmp_path / 'trees.gpkg'}"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stderr), daemon=True)
    reader.start()
    # the signal as soon as the computation reports its first step (the run takes a few seconds more)
    assert _wait_for(lambda: any("height above ground" in ln for ln in lines), proc, timeout=120), lines
    proc.send_signal(sig)
    proc.wait(timeout=120)
    reader.join(timeout=10)
    err = "".join(lines)
    assert proc.returncode == code, err
    assert "Traceback" not in err and err.strip().splitlines()[-1].endswith(word), err
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_omitted_outputs_leave_no_temporary_folder(corner, tmp_path):
    private = tmp_path / "tmp"      # the command's own TMPDIR: other programs share /tmp
    private.mkdir()
    env = dict(os.environ, TMPDIR=str(private))
    out = sylva("canopyheightmodel", f"--INPUT={corner / 'c_0_0.laz'}", "--PIT_FREE=false", env=env)
    assert out.returncode == 0, out.stderr
    assert "not kept" in out.stdout
    out = sylva("canopyheightmodel", f"--INPUT={corner / 'c_0_0.laz'}", "--RESOLUTION_M=nan", env=env)
    assert out.returncode == 1
    assert [p.name for p in private.iterdir() if p.name.startswith("sylva-")] == []


# --------------------------------------------------------------------------- files and names

def test_outputs_follow_the_umask(corner, tmp_path):
    tile = corner / "c_0_0.laz"
    out = sylva("canopyheightmodel", f"--INPUT={tile}", "--PIT_FREE=false", f"--OUTPUT={tmp_path / 'chm.tif'}",
                umask=0o022)
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "chm.tif").stat().st_mode & 0o777 == 0o644
    out = sylva("canopyheightmodel", f"--INPUT={tile}", "--PIT_FREE=false", f"--OUTPUT={tmp_path / 'chm2.tif'}",
                umask=0o007)
    assert (tmp_path / "chm2.tif").stat().st_mode & 0o777 == 0o660
    out = sylva("segmenttrees", f"--INPUT={tile}", f"--OUTPUT={tmp_path / 'seg.laz'}",
                f"--TREES={tmp_path / 'trees.gpkg'}", umask=0o027)
    assert out.returncode == 0, out.stderr
    for name in ("seg.laz", "trees.gpkg"):
        assert (tmp_path / name).stat().st_mode & 0o777 == 0o640, name


def test_lidr_float_tree_id_no_tree_reads_as_zero(tmp_path):
    from sylva.core.io.las import tree_labels

    values = np.array([1.0, 2.0, np.finfo(np.float64).max, np.nan, 0.0, -1.0, 3.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        labels = tree_labels(values)
    assert labels.tolist() == [1, 2, 0, 0, 0, 0, 3] and labels.dtype == np.int64


@pytest.fixture(scope="module")
def models_of_corner(tmp_path_factory, sample_laz):
    """A segmented 40 m corner of the sample and its models (GLB), through the CLI."""
    folder = tmp_path_factory.mktemp("models")
    from sylva.core.io import read_cloud
    from sylva.core.io.las import write_las

    cloud = read_cloud(sample_laz)
    x0, y0 = cloud.xyz[:, 0].min(), cloud.xyz[:, 1].min()
    m = (cloud.xyz[:, 0] < x0 + 40) & (cloud.xyz[:, 1] < y0 + 40)
    write_las(folder / "corner.laz", cloud.subset(m))
    out = sylva("segmenttrees", f"--INPUT={folder / 'corner.laz'}", f"--OUTPUT={folder / 'seg.laz'}")
    assert out.returncode == 0, out.stderr
    out = sylva("reconstructtrees", f"--INPUT={folder / 'seg.laz'}", f"--MODELS={folder / 'models.glb'}")
    assert out.returncode == 0, out.stderr
    return folder / "seg.laz", folder / "models.glb"


def test_obj_names_with_spaces_and_textures_per_export(models_of_corner, tmp_path):
    _, glb = models_of_corner
    for name in ("my trees.obj", "other.obj"):
        out = sylva("exportmodels", f"--INPUT={glb}", f"--OBJ={tmp_path / name}")
        assert out.returncode == 0, out.stderr
    text = (tmp_path / "my trees.obj").read_text()
    mtllib = [ln for ln in text.splitlines() if ln.startswith("mtllib ")]
    assert mtllib == ["mtllib my_trees.mtl"] and (tmp_path / "my_trees.mtl").exists()
    for mtl in ("my_trees.mtl", "other.mtl"):
        maps = [ln.split(None, 1)[1] for ln in (tmp_path / mtl).read_text().splitlines() if ln.startswith("map_Kd")]
        assert maps and all(" " not in m and (tmp_path / m).exists() for m in maps)
        assert all(m.startswith(Path(mtl).stem + "_leaf_") for m in maps)


# --------------------------------------------------------------------------- qgis_process

@pytest.mark.qgis
def test_qgis_process_refuses_output_over_input(tmp_path, sample_laz):
    from conftest import qgis_process

    tile = tmp_path / "t.laz"
    tile.write_bytes(sample_laz.read_bytes())
    before = digest(tile)
    out = qgis_process("run", "sylva:canopyheightmodel", f"--INPUT={tile}", f"--OUTPUT={tile}")
    text = out.stdout + out.stderr
    assert out.returncode != 0 and "is the input" in text and "Traceback" not in text, text
    assert digest(tile) == before
    out = qgis_process("run", "sylva:segmenttrees", f"--INPUT={tile}", f"--OUTPUT={tmp_path / 'x.txt'}")
    text = out.stdout + out.stderr
    assert out.returncode != 0 and "x.txt" in text and "Traceback" not in text, text
    assert not (tmp_path / "x.txt").exists()


@pytest.mark.qgis
def test_qgis_process_damaged_laz_and_failed_pipeline(damaged, tmp_path):
    from conftest import qgis_process

    path, _ = damaged["laz_zeroed_50"]
    out = qgis_process("run", "sylva:treetops", f"--INPUT={path}", f"--OUTPUT={tmp_path / 'tops.gpkg'}")
    text = out.stdout + out.stderr
    assert out.returncode != 0 and path.name in text and "damaged" in text and "Traceback" not in text, text
    tiles = tmp_path / "tiles"
    tiles.mkdir()
    (tiles / "z.laz").write_bytes(path.read_bytes())
    out = qgis_process("run", "sylva:pipeline", f"--INPUT={tiles}", "--RECONSTRUCT=false",
                       f"--OUTPUT_FOLDER={tmp_path / 'out'}")
    text = out.stdout + out.stderr
    assert out.returncode != 0 and "every tile failed" in text and "Traceback" not in text, text
    assert leftovers(tmp_path) == []


# --------------------------------------------------------------------------- every GLB is valid glTF

@pytest.mark.slow
def test_every_glb_sylva_writes_passes_the_khronos_validator(sample_laz, tmp_path):
    """Every GLB of the whole sample: the pipeline's tile GLB and 3D Tiles content, exportmodels' per-tree
    GLBs and tileset, billboards and their tileset, and a sketched tree: 0 errors each."""
    import shutil

    from conftest import ROOT
    from sylva.core.io.gpkg import write_gpkg
    from test_sketch import H, _tables

    viewers = ROOT / "tools" / "viewers"
    if shutil.which("node") is None or not (viewers / "node_modules" / "gltf-validator").is_dir():
        pytest.skip("the Khronos validator is not installed (npm install in tools/viewers)")
    forest = tmp_path / "forest"
    out = sylva("pipeline", f"--INPUT={sample_laz}", f"--OUTPUT_FOLDER={forest}")
    assert out.returncode == 0, out.stderr
    seg, glb = forest / "tiles" / "sample.laz", forest / "models" / "sample.glb"
    out = sylva("exportmodels", f"--INPUT={glb}", f"--GLB_FOLDER={tmp_path / 'per_tree'}", f"--TILES={tmp_path / 'tiles'}")
    assert out.returncode == 0, out.stderr
    out = sylva("billboards", f"--INPUT={seg}", f"--OUTPUT={tmp_path / 'bb.glb'}", f"--TILESET={tmp_path / 'bb_tiles'}",
                "--TEXTURE_PX=32")
    assert out.returncode == 0, out.stderr
    src = tmp_path / "sketch.gpkg"
    write_gpkg(src, list(_tables()))
    out = sylva("treefromsketch", f"--FRONT={src}|layername=front", f"--SIDE={src}|layername=side",
                f"--LOCATION={src}|layername=location", f"--HEIGHT_M={H}", f"--MODEL={tmp_path / 'sketch.glb'}")
    assert out.returncode == 0, out.stderr
    files = sorted(tmp_path.rglob("*.glb"))
    assert len(list((tmp_path / "per_tree").glob("*.glb"))) >= 200       # one per tree of the sample
    kinds = {"per_tree": 0, "tiles": 0, "bb_tiles": 0, "forest": 0}
    for f in files:
        for k in kinds:
            kinds[k] += k in f.relative_to(tmp_path).parts if f.is_relative_to(tmp_path) else 0
    assert all(kinds.values()) and (tmp_path / "bb.glb").exists() and (tmp_path / "sketch.glb").exists(), kinds
    bad = []
    for start in range(0, len(files), 200):
        run = subprocess.run(["node", "validate_gltf.mjs", *map(str, files[start:start + 200])], cwd=viewers,
                             capture_output=True, text=True, timeout=600)
        reports = [json.loads(line) for line in run.stdout.splitlines() if line.startswith("{")]
        assert len(reports) == len(files[start:start + 200]), run.stderr
        bad += [r for r in reports if r["errors"]]
    assert bad == [], bad[:3]
