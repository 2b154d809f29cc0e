"""Compile time is measured and reported apart from work; the warm-up's stamp says when it was done."""
from __future__ import annotations

import json
import os

import pytest

from sylva.core import jit


def test_compile_seconds_counts_a_real_compilation():
    if not jit.jit_status()["numba"]:
        pytest.skip("numba is off (SYLVA_NO_JIT) or missing")
    ns = {}
    exec("def twice_plus_one(x):\n    return x * 2.0 + 1.0\n", ns)   # no source file: never in numba's cache
    kernel = jit.Kernel(ns["twice_plus_one"])
    before = jit.compile_seconds()
    assert kernel(3.0) == 7.0
    assert jit.compile_seconds() > before
    assert kernel in jit.kernels()
    again = jit.compile_seconds()
    kernel(4.0)                                   # same types: no new compilation
    assert jit.compile_seconds() == again


def test_the_run_report_separates_compile_time_from_work():
    from sylva.core.catalog import RunReport

    report = RunReport(tiles=[], failures=[], skipped=[], trees=222, points=126_302, seconds=43.5, workers=1,
                       scheduler=None, peak_rss_mb_per_worker={}, id_collisions_rewritten=0, gpkg=None, tileset=None,
                       compile_seconds=40.0)
    text = report.summary()
    assert "of which 40.0 s compiling the numba kernels" in text and "3.5 s of work" in text
    d = report.as_dict()
    assert d["work_seconds"] == 3.5 and d["work_points_per_s"] == round(126_302 / 3.5, 1)
    warm = RunReport(**{**report.__dict__, "compile_seconds": 0.0})
    assert "compiling" not in warm.summary()


def test_the_stamp_follows_the_fingerprint(tmp_path, monkeypatch):
    from sylva.plugin import warmup

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    assert warmup.stamp_path().parent == tmp_path and warmup.stamp_path().name.startswith("sylva-warm-")
    assert not warmup.is_warm()
    warmup.stamp_path().write_text(json.dumps({"fingerprint": warmup.fingerprint()}))
    assert warmup.is_warm()
    warmup.stamp_path().write_text(json.dumps({"fingerprint": "another sylva"}))
    assert not warmup.is_warm()


@pytest.mark.slow
def test_the_warm_up_reaches_every_kernel(tmp_path, monkeypatch):
    """Every kernel the modules define is compiled (or loaded from the cache) by the warm-up's runs."""
    from sylva.plugin import warmup

    if os.environ.get("NUMBA_CACHE_DIR"):
        monkeypatch.setenv("NUMBA_CACHE_DIR", os.environ["NUMBA_CACHE_DIR"])
    monkeypatch.setattr(warmup, "stamp_path", lambda: tmp_path / "sylva-warm.json")
    summary = warmup.warm_up()
    assert summary["unused"] == [] and summary["compiled"] == summary["kernels"] >= 40
    assert json.loads((tmp_path / "sylva-warm.json").read_text())["fingerprint"] == warmup.fingerprint()
