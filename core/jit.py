"""Compiled kernels for the inherently sequential loops (numba), in one place.

Kernels are plain Python functions over numpy arrays and scalars, decorated
with :func:`njit`.  Nothing is imported or compiled at import time: the
first call of a kernel imports numba and compiles it with
``numba.njit(cache=True, nogil=True)``, so loading the plugin (QGIS start-up,
every worker process of the pipeline) does not pay for numba, and a process
that never reconstructs a tree never imports it.

Caching: numba stores the machine code next to the kernel's module
(``__pycache__``) and, where that folder is not writable (a system-wide
install), in the user's cache folder (``~/.cache/numba`` or the platform's
equivalent); ``NUMBA_CACHE_DIR`` overrides both.  When neither can be
written the kernel is compiled without a cache (a cold compile per process,
still correct); Sylva does not fall back to a shared temporary folder, as
numba's cache index is a pickle that another user could plant there.  A
cache written by another numba/Python version or for another CPU is
recompiled, never used wrongly (numba checks both).

Without numba, or with the environment variable ``SYLVA_NO_JIT=1``, the
kernels run as ordinary Python (same results, much slower);
:func:`jit_status` says which is in use.
"""
from __future__ import annotations

import functools
import os
import threading

__all__ = ["njit", "jit_status", "Kernel", "compile_seconds", "kernels", "recording"]

_LOCK = threading.RLock()
_NUMBA = None          # the numba module once imported, False when unavailable/disabled
_KERNELS = []          # every Kernel defined (see kernels())
_COMPILE = {"seconds": 0.0, "count": 0}   # numba compilations (cache misses) in this process
_DEPTH = threading.local()
_RECORD = None         # while recording(): {kernel: (size, copied arguments)} of each kernel's smallest call


def _count_compiles(numba) -> None:
    """Time numba's own "numba:compile" events (real compilations, not cache loads) for compile_seconds()."""
    import time

    try:
        from numba.core import event
    except ImportError:  # pragma: no cover - numba < 0.53
        return

    class _Timer(event.Listener):
        def on_start(self, ev):
            depth = getattr(_DEPTH, "n", 0)
            if depth == 0:
                _DEPTH.t0 = time.perf_counter()
            _DEPTH.n = depth + 1

        def on_end(self, ev):
            _DEPTH.n = getattr(_DEPTH, "n", 1) - 1
            if _DEPTH.n == 0:
                with _LOCK:
                    _COMPILE["seconds"] += time.perf_counter() - _DEPTH.t0
                    _COMPILE["count"] += 1

    event.register("numba:compile", _Timer())


def compile_seconds() -> float:
    """Seconds this process has spent compiling kernels (numba cache misses); 0 when all came from the cache.

    Run reports subtract it from the work (the first run after installing compiles, later runs load)."""
    return float(_COMPILE["seconds"])


def kernels() -> list:
    """Every :class:`Kernel` defined by the modules imported so far."""
    return list(_KERNELS)


def _numba():
    global _NUMBA
    if _NUMBA is None:
        with _LOCK:
            if _NUMBA is None:
                if os.environ.get("SYLVA_NO_JIT", "").strip() not in ("", "0"):
                    _NUMBA = False
                else:
                    try:
                        import numba
                        _count_compiles(numba)
                        _NUMBA = numba
                    except ImportError:          # pragma: no cover - numba is a dependency
                        _NUMBA = False
    return _NUMBA


class Kernel:
    """A function compiled by numba on its first call (see the module docstring).

    ``py_func`` is the undecorated Python function; ``compiled`` is what
    calls go to once loaded (the numba dispatcher, or ``py_func`` itself
    without numba).
    """

    def __init__(self, py_func):
        self.py_func = py_func
        self.compiled = None
        self.cached = None          # True: cache enabled; False: compiled without cache; None: not numba
        functools.update_wrapper(self, py_func)
        _KERNELS.append(self)

    def load(self):
        """Compile or load the kernel now (normally done by the first call); returns the callable."""
        if self.compiled is None:
            with _LOCK:
                if self.compiled is None:
                    numba = _numba()
                    if not numba:
                        self.compiled = self.py_func
                    else:
                        try:
                            fn = numba.njit(cache=True, nogil=True)(self.py_func)
                            self.cached = True
                        except RuntimeError:     # "cannot cache function ...: no locator available"
                            fn = numba.njit(nogil=True)(self.py_func)
                            self.cached = False
                        self.compiled = fn
        return self.compiled

    def __call__(self, *args):
        fn = self.compiled
        if fn is None:
            fn = self.load()
        if _RECORD is not None:
            _remember(self, args)
        return fn(*args)


def _size(value) -> int:
    if isinstance(value, (tuple, list)):
        return sum(_size(v) for v in value)
    return int(getattr(value, "nbytes", 8))


def _remember(kernel: "Kernel", args) -> None:
    import copy

    size = _size(args)
    with _LOCK:
        if _RECORD is not None and (kernel not in _RECORD or size < _RECORD[kernel][0]):
            _RECORD[kernel] = (size, copy.deepcopy(args))


class recording:
    """``with recording() as calls:`` keeps, per kernel, a copy of the arguments of its smallest call.

    ``calls`` is {Kernel: args}; tests run a kernel's Python and compiled forms on them and compare.
    """

    def __enter__(self):
        global _RECORD
        _RECORD = {}
        self.calls = {}
        return self.calls

    def __exit__(self, *exc):
        global _RECORD
        with _LOCK:
            self.calls.update({k: args for k, (_, args) in _RECORD.items()})
            _RECORD = None
        return False


def njit(py_func):
    """Decorator: ``py_func`` becomes a :class:`Kernel` (numba ``njit(cache=True, nogil=True)`` on first call).

    Kernels must not call other kernels (each is compiled on its own); write
    them as self-contained loops over numpy arrays.
    """
    return Kernel(py_func)


def jit_status() -> dict:
    """Which backend runs the kernels: ``{"numba": version or None, "cache_dir": override or None}``."""
    numba = _numba()
    return {"numba": getattr(numba, "__version__", None) if numba else None,
            "cache_dir": os.environ.get("NUMBA_CACHE_DIR") or None}
