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

__all__ = ["njit", "helper", "jit_status", "Kernel", "Helper", "compile_seconds", "kernels", "helpers", "recording"]

_LOCK = threading.RLock()
_NUMBA = None          # the numba module once imported, False when unavailable/disabled
_KERNELS = []          # every Kernel defined (see kernels())
_HELPERS = []          # every Helper defined (see helpers())
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


def helpers() -> list:
    """Every :class:`Helper` defined by the modules imported so far."""
    return list(_HELPERS)


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
                        func = _with_helpers(self.py_func)
                        try:
                            fn = numba.njit(cache=True, nogil=True)(func)
                            self.cached = True
                        except RuntimeError:     # "cannot cache function ...: no locator available"
                            fn = numba.njit(nogil=True)(func)
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


class Helper:
    """A function kernels may call (see :func:`helper`): compiled with the kernel that calls it.

    ``py_func`` is the Python function; called from Python, a helper runs compiled (or as Python
    without numba), like a kernel.
    """

    def __init__(self, py_func):
        self.py_func = py_func
        self.compiled = None
        functools.update_wrapper(self, py_func)
        _HELPERS.append(self)

    def load(self):
        """The numba dispatcher of the helper (``py_func`` itself without numba)."""
        if self.compiled is None:
            with _LOCK:
                if self.compiled is None:
                    numba = _numba()
                    self.compiled = (numba.njit(nogil=True)(_with_helpers(self.py_func)) if numba
                                     else self.py_func)
        return self.compiled

    def __call__(self, *args):
        fn = self.compiled
        if fn is None:
            fn = self.load()
        return fn(*args)


def _used_helpers(py_func, seen=None) -> list:
    """The helpers ``py_func`` calls (by global name, nested code included), and the helpers they call."""
    import types

    seen = {} if seen is None else seen
    codes = [py_func.__code__]
    while codes:
        code = codes.pop()
        codes.extend(c for c in code.co_consts if isinstance(c, types.CodeType))
        for name in code.co_names:
            value = py_func.__globals__.get(name)
            if isinstance(value, Helper) and name not in seen:
                seen[name] = value
                _used_helpers(value.py_func, seen)
    return sorted(seen.items())


def _with_helpers(py_func):
    """``py_func`` ready for numba: the helpers it calls bound as compiled dispatchers in its module, and,
    when it calls any, a copy named after their sources.

    numba's cache is keyed by the kernel's own file and name: a kernel whose helper changed would load
    stale machine code.  The copy's name ends in a hash of the helpers' sources, so that a changed helper
    is a cache miss (recompiled), never a wrong answer (Sylva, not in numba)."""
    import hashlib
    import inspect
    import types

    used = _used_helpers(py_func)
    if not used:
        return py_func
    digest = hashlib.sha1()
    for name, h in used:
        py_func.__globals__[name] = h.load()     # numba resolves globals when it compiles
        digest.update(inspect.getsource(h.py_func).encode("utf-8"))
    copy = types.FunctionType(py_func.__code__, py_func.__globals__, py_func.__name__, py_func.__defaults__,
                              py_func.__closure__)
    copy.__qualname__ = f"{py_func.__qualname__}__h{digest.hexdigest()[:10]}"
    copy.__doc__ = py_func.__doc__
    return copy


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

    Kernels do not call other kernels; what several kernels share is a :func:`helper` (``core/kernels/``).
    """
    return Kernel(py_func)


def helper(py_func):
    """Decorator: ``py_func`` becomes a :class:`Helper`, a function kernels call by its global name.

    When a kernel is compiled its helpers are compiled into it, and a change to a helper's source
    recompiles the kernels that use it (see :func:`_with_helpers`).
    """
    return Helper(py_func)


def jit_status() -> dict:
    """Which backend runs the kernels: ``{"numba": version or None, "cache_dir": override or None}``."""
    numba = _numba()
    return {"numba": getattr(numba, "__version__", None) if numba else None,
            "cache_dir": os.environ.get("NUMBA_CACHE_DIR") or None}
