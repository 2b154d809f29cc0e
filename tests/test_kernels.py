"""Every compiled kernel (core/jit.py) equals its Python form, on the arguments a real run gives it.

The warm-up (every algorithm on a 40 m corner of the bundled sample) runs while core.jit records, per
kernel, the arguments of its smallest call; each kernel's Python function and its numba-compiled form
then run on copies of them and must return the same values and leave the same arrays behind (kernels
fill output arrays in place).  A kernel that no run reaches fails: a new kernel needs a warm-up run.
"""
import copy
import importlib
import pkgutil

import numpy as np
import pytest

from sylva.core import jit


def _all_kernels():
    from sylva import core

    for info in pkgutil.walk_packages(core.__path__, core.__name__ + "."):
        try:
            importlib.import_module(info.name)
        except ImportError:   # an optional dependency this Python lacks
            pass
    return sorted(jit.kernels(), key=lambda k: f"{k.__module__}.{k.__name__}")


KERNELS = _all_kernels()


@pytest.fixture(scope="module")
def calls():
    if not jit.jit_status()["numba"]:
        pytest.skip("numba is off (SYLVA_NO_JIT=1 or not installed): no compiled form to compare")
    from sylva.plugin.warmup import warm_up

    with jit.recording() as recorded:
        warm_up()
    return recorded


def _same(a, b, where):
    if isinstance(a, tuple) or isinstance(b, tuple):
        assert isinstance(a, tuple) and isinstance(b, tuple) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f"{where}[{i}]")
        return
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape, f"{where}: shapes {a.shape} and {b.shape}"
    if a.dtype.kind == "f" or b.dtype.kind == "f":
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9, equal_nan=True, err_msg=where)
    else:
        assert np.array_equal(a, b), where


def test_every_kernel_is_registered_and_named_for_its_module():
    assert len(KERNELS) >= 40
    names = [f"{k.__module__}.{k.__name__}" for k in KERNELS]
    assert len(set(names)) == len(names)
    assert all(k.__module__.startswith("sylva.core.") for k in KERNELS)


@pytest.mark.parametrize("kernel", KERNELS, ids=lambda k: f"{k.__module__.removeprefix('sylva.core.')}.{k.__name__}")
def test_python_and_compiled_forms_agree(kernel, calls):
    assert kernel in calls, f"no warm-up run reaches {kernel.__module__}.{kernel.__name__}: add one to plugin/warmup.py"
    args = calls[kernel]
    py_args, nb_args = copy.deepcopy(args), copy.deepcopy(args)
    expected = kernel.py_func(*py_args)
    got = kernel.load()(*nb_args)
    _same(got, expected, "returned")
    for i, (x, y) in enumerate(zip(nb_args, py_args)):
        if isinstance(x, np.ndarray):
            _same(x, y, f"argument {i} after the call")


# --------------------------------------------------------------------------- helpers kernels share

def _all_helpers():
    _all_kernels()
    return sorted(jit.helpers(), key=lambda h: f"{h.__module__}.{h.__name__}")


#: Arguments for each helper's Python-versus-compiled comparison (every helper needs one).
HELPER_CASES = {
    "grid_cells": [
        (np.random.default_rng(1).uniform(-20.0, 30.0, (500, 3)), 0.7, 10_000_000),
        (np.random.default_rng(2).uniform(0.0, 1e4, (200, 2)), 0.5, 1000),          # too many cells
        (np.array([[0.0, np.nan]]), 1.0, 100),                                       # not finite
        (np.zeros((0, 2)), 1.0, 100),                                                # no position
    ],
    "bucket_by_cell": [(np.random.default_rng(3).integers(0, 50, 400), 50), (np.zeros(0, dtype=np.int64), 3)],
    "_grid3": [(np.random.default_rng(4).uniform(-5.0, 25.0, (300, 3)), 1.0),
               (np.random.default_rng(5).uniform(0.0, 1e3, (50, 3)), 0.5)],          # cells widened
    "_near_cells": [(13, 3, 3, 3, np.zeros(27, dtype=np.int64)), (0, 3, 3, 3, np.zeros(27, dtype=np.int64)),
                    (5, 1, 2, 4, np.zeros(27, dtype=np.int64))],                  # 27, 8 and 6 cells
    "uf_find": [(np.array([0, 0, 1, 2, 4, 4]), 3), (np.arange(5), 4)],
    "uf_union": [(np.array([0, 0, 1, 2, 4, 4]), 3, 5), (np.array([0, 0, 1, 2, 4, 4]), 3, 1)],
    "grown_nodes": [(7, 3, np.arange(15.0).reshape(5, 3), -np.arange(15.0).reshape(5, 3), np.array([-1, 0, 1, 2, 3]),
                     np.array([1, 1, 0, 4, 4]), *(np.array(b, dtype=bool) for b in ([1, 0, 1, 1, 0], [0, 1, 1, 0, 1],
                                                                                      [1, 1, 0, 0, 1], [0, 0, 1, 1, 1])))],
}


@pytest.mark.parametrize("helper", _all_helpers(), ids=lambda h: h.__name__)
def test_every_helper_agrees_with_its_python_form(helper):
    assert helper.__name__ in HELPER_CASES, f"add a case for {helper.__module__}.{helper.__name__}"
    if not jit.jit_status()["numba"]:
        pytest.skip("numba is off: no compiled form to compare")
    for args in HELPER_CASES[helper.__name__]:
        _same(helper.load()(*copy.deepcopy(args)), helper.py_func(*copy.deepcopy(args)), helper.__name__)


def test_a_changed_helper_recompiles_the_kernels_that_call_it(tmp_path):
    """numba's cache is keyed by the kernel's file: a kernel whose helper (in another file) changed must not
    load its old machine code (core/jit.py names the compiled copy after its helpers' sources)."""
    import os
    import subprocess
    import sys

    if not jit.jit_status()["numba"]:
        pytest.skip("numba is off")
    (tmp_path / "demo_helpers.py").write_text(
        "from sylva.core.jit import helper\n\n@helper\ndef step(x):\n    return x + 1.0\n")
    (tmp_path / "demo_kernel.py").write_text(
        "from sylva.core.jit import njit\nfrom demo_helpers import step\n\n@njit\ndef kern(a):\n"
        "    out = a.copy()\n    for i in range(a.shape[0]):\n        out[i] = step(a[i])\n    return out\n")
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "SYLVA_NO_JIT")}
    env["PYTHONPATH"] = os.pathsep.join([str(tmp_path), env.get("PYTHONPATH", "")])
    run = [sys.executable, "-c", "import numpy as np, demo_kernel; print(demo_kernel.kern(np.arange(3.0)).tolist())"]

    def result():
        out = subprocess.run(run, capture_output=True, text=True, env=env, cwd=tmp_path)
        assert out.returncode == 0, out.stderr
        return out.stdout.strip()

    assert result() == "[1.0, 2.0, 3.0]"
    assert any(p.suffix == ".nbi" for p in (tmp_path / "__pycache__").iterdir())     # cached
    assert result() == "[1.0, 2.0, 3.0]"                                               # from the cache
    (tmp_path / "demo_helpers.py").write_text(
        "from sylva.core.jit import helper\n\n@helper\ndef step(x):\n    return x + 2.0\n")
    assert result() == "[2.0, 3.0, 4.0]"
