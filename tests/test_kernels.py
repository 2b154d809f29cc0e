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
