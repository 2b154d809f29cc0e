"""The `sylva` command: help, the same ids as qgis_process, real runs, clear errors."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sylva.algorithms import all_algorithms
from sylva.core.io.gpkg import read_gpkg

from badfiles import make_bad_inputs  # noqa: E402  (tests/ is on sys.path via rootdir conftest)


def sylva(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "sylva.cli", *args], capture_output=True, text=True, cwd=cwd)


def test_help_lists_every_algorithm():
    out = sylva("--help")
    assert out.returncode == 0
    for alg_id in all_algorithms():
        assert alg_id in out.stdout


def test_algorithm_help_lists_every_parameter():
    for alg in all_algorithms().values():
        out = sylva(alg.id, "--help")
        assert out.returncode == 0, out.stderr
        for p in alg.params:
            assert f"--{p.name}" in out.stdout


def test_treetops_on_the_sample(tmp_path, sample_laz):
    target = tmp_path / "tops.gpkg"
    out = sylva("treetops", f"--INPUT={sample_laz}", "--WINDOW=fixed", f"--OUTPUT={target}")
    assert out.returncode == 0, out.stderr
    assert f"OUTPUT: {target}" in out.stdout
    tops = read_gpkg(target, "tree_tops")
    assert len(tops) > 20
    assert tops.crs is not None and tops.crs.to_epsg() == 32632
    assert np.all(tops.columns["height"] >= 2.0)
    # qgis_process passes enums by index: the CLI takes both spellings, with identical results.
    again = tmp_path / "tops_by_index.gpkg"
    assert sylva("sylva:treetops", f"--INPUT={sample_laz}", "--WINDOW=0", f"--OUTPUT={again}").returncode == 0
    np.testing.assert_array_equal(read_gpkg(again, "tree_tops").columns["height"], tops.columns["height"])


def test_chm_then_tops_from_the_chm(tmp_path, sample_laz):
    chm = tmp_path / "chm.tif"
    out = sylva("canopyheightmodel", f"--INPUT={sample_laz}", "--RESOLUTION_M=1.0", f"--OUTPUT={chm}")
    assert out.returncode == 0, out.stderr
    tops = tmp_path / "tops.gpkg"
    out = sylva("treetops", f"--INPUT={chm}", f"--OUTPUT={tops}")
    assert out.returncode == 0, out.stderr
    assert len(read_gpkg(tops, "tree_tops")) > 20


@pytest.mark.parametrize("case", ["missing", "not_las", "truncated", "empty", "no_crs"])
def test_bad_input_gives_one_clear_message(tmp_path, sample_laz, case):
    path, words = make_bad_inputs(tmp_path / "bad", sample_laz)[case]
    target = tmp_path / "out" / "tops.gpkg"
    target.parent.mkdir()
    out = sylva("treetops", f"--INPUT={path}", f"--OUTPUT={target}")
    assert out.returncode == 1
    assert "Traceback" not in out.stderr
    assert path.name in out.stderr
    assert words in out.stderr
    assert list(target.parent.iterdir()) == []  # nothing half-written


def test_bad_parameter_value(tmp_path, sample_laz):
    out = sylva("treetops", f"--INPUT={sample_laz}", "--TOP_WINDOW_M=abc")
    assert out.returncode == 1 and "TOP_WINDOW_M" in out.stderr and "Traceback" not in out.stderr
    out = sylva("treetops", f"--INPUT={sample_laz}", "--MIN_HEIGHT_M=-5")
    assert out.returncode == 1 and "outside" in out.stderr


def test_an_earlier_parameter_name_is_still_accepted(tmp_path, sample_laz):
    """treetops' WINDOW_DIAMETER_M is now TOP_WINDOW_M, the name segmenttrees and pipeline use; the earlier
    name gives the same value (scripts and batch files written with it keep working)."""
    counts = {}
    for name, value in (("TOP_WINDOW_M", 6), ("WINDOW_DIAMETER_M", 6), ("TOP_WINDOW_M", 2)):
        out = tmp_path / f"{name}{value}.gpkg"
        r = sylva("treetops", f"--INPUT={sample_laz}", "--WINDOW=fixed", f"--{name}={value}", f"--OUTPUT={out}")
        assert r.returncode == 0, r.stderr
        counts[name, value] = len(read_gpkg(out, "tree_tops"))
    assert counts["WINDOW_DIAMETER_M", 6] == counts["TOP_WINDOW_M", 6] < counts["TOP_WINDOW_M", 2]
