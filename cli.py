"""`sylva ALGORITHM --PARAM=value ...`: Sylva's algorithms without QGIS.

Ids, parameter names, defaults and help are those of
``qgis_process run sylva:ALGORITHM --PARAM=value``: both front ends are built
from the same :mod:`sylva.algorithms` definitions.  Vector outputs are
written as GeoPackage files; an output left out goes to a temporary folder,
as qgis_process's TEMPORARY_OUTPUT does, and its path is printed.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path
from typing import List, Optional

from .algorithms import all_algorithms, get
from .algorithms import spec as S
from .core.errors import Cancelled, InputError, SylvaError, disk_error


class CliFeedback(S.Feedback):
    """Progress as a percentage on stderr; Ctrl-C cancels."""

    def __init__(self, quiet: bool = False):
        self.quiet = quiet
        self.tty = sys.stderr.isatty()
        self._last = -1
        self._open = False  # a progress line is being rewritten in place

    def progress(self, fraction: float, message: str = "") -> None:
        pct = int(fraction * 100)
        if self.quiet or pct == self._last or (not self.tty and pct // 10 == self._last // 10):
            return
        self._last = pct
        if self.tty:
            print(f"\r{pct:3d}% {message[:60]:<60}", end="", file=sys.stderr, flush=True)
            self._open = pct < 100
            if not self._open:
                print(file=sys.stderr)
        else:
            print(f"{pct:3d}% {message}", file=sys.stderr)

    def info(self, message: str) -> None:
        if not self.quiet:
            print(f"\n{message}" if self._open else message, file=sys.stderr)
            self._open = False

    warn = info

    def cancelled(self) -> bool:
        """True once Ctrl-C or SIGTERM arrived, even when the KeyboardInterrupt it raised was swallowed
        (a signal handled inside a finaliser or weakref callback only prints "Exception ignored")."""
        return _SIGNALLED["signal"] is not None


def _parser() -> argparse.ArgumentParser:
    top = argparse.ArgumentParser(
        prog="sylva",
        description="Individual trees and 3D tree models from LiDAR. The same algorithms, ids and "
                    "parameters as `qgis_process run sylva:ALGORITHM`.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="algorithms:\n" + "\n".join(f"  {a.id:<22}{a.name}" for a in all_algorithms().values())
               + "\n\n`sylva ALGORITHM --help` lists an algorithm's parameters.",
    )
    top.add_argument("--quiet", action="store_true", help="no progress or messages on stderr")
    subs = top.add_subparsers(dest="algorithm", metavar="ALGORITHM")
    for alg in all_algorithms().values():
        sub = subs.add_parser(alg.id, help=alg.name, description=alg.summary,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
        for p in alg.params:
            sub.add_argument(f"--{p.name}", dest=p.name, metavar=_metavar(p), help=_help(p))
            for old in p.aliases:    # an earlier name: the same value, not listed in --help
                sub.add_argument(f"--{old}", dest=p.name, metavar=_metavar(p), help=argparse.SUPPRESS)
    return top


def _metavar(p: S.Param) -> str:
    return {S.NUMBER: "NUMBER", S.INTEGER: "INT", S.BOOLEAN: "true|false", S.ENUM: "|".join(p.options),
            S.FILE: "FILE", S.CRS: "CRS", S.RASTER: "GEOTIFF", S.VECTOR: "GPKG[|layername=NAME]"}.get(p.kind, "PATH" if p.is_output else "VALUE")


def _help(p: S.Param) -> str:
    text = f"{p.description}. {p.help}{S.alias_text(p)}".replace("%", "%%")
    if p.is_output:
        return text + (" (optional: not written when left out)" if p.optional
                       else " (written to a temporary folder when left out)")
    if p.kind in (S.NUMBER, S.INTEGER):
        text += f" Range: {p.range_text()}."
    if p.kind == S.ENUM and p.labels:
        text += " " + "; ".join(f"{o}: {lab}" for o, lab in zip(p.options, p.labels)) + "."
    if p.default is not None:
        return text + f" (default: {p.default})"
    return text + (" (optional)" if p.optional else " (required)")


def convert(alg: S.Algorithm, raw: dict, scratch: Optional[list] = None) -> dict:
    """Turn command-line strings into the typed values ``run`` expects (defaults filled in).

    A required output left out goes to a temporary folder (made once, appended to
    ``scratch``: :func:`main` removes it when the command ends, as qgis_process does
    with TEMPORARY_OUTPUT).
    """
    args = {}
    scratch = [] if scratch is None else scratch
    for p in alg.params:
        value = raw.get(p.name)
        if value is None:
            if p.is_output and p.optional:
                value = None  # an optional output left out is not written
            elif p.is_output:
                if not scratch:
                    scratch.append(tempfile.mkdtemp(prefix="sylva-"))
                value = str(Path(scratch[0]) / f"{p.name.lower()}{p.default_extension()}")
            elif p.default is None and not p.optional:
                raise InputError(f"{alg.id}: parameter --{p.name} ({p.description}) is required")
            else:
                value = p.default
        else:
            value = _typed(alg, p, value)
        args[p.name] = value
    return args


def _typed(alg: S.Algorithm, p: S.Param, value: str):
    try:
        if p.kind == S.NUMBER:
            v = float(value)
        elif p.kind == S.INTEGER:
            v = float(value)
            if v.is_integer():
                v = int(v)
        elif p.kind == S.BOOLEAN:
            low = value.strip().lower()
            if low not in ("true", "false", "1", "0", "yes", "no"):
                raise ValueError
            return low in ("true", "1", "yes")
        elif p.kind == S.VECTOR:
            return _vector(alg, p, value)
        elif p.kind == S.ENUM:
            return p.option(value)  # the option's id, its label, or its index (qgis_process passes indices)
        else:
            return value
    except (ValueError, IndexError, OverflowError):
        raise InputError(f"{alg.id}: --{p.name}={value!r} is not a valid {_metavar(p)}") from None
    why = p.problem(v)
    if why:
        raise InputError(f"{alg.id}: --{p.name} ({p.description}): {why}")
    return v


def _vector(alg: S.Algorithm, p: S.Param, value: str):
    """A VECTOR input: the GeoPackage layer ``value`` names, as a VectorTable of the required geometry type."""
    from .core.io.gpkg import read_layer

    table = read_layer(value)
    if p.geometry != S.NO_GEOMETRY and table.geometry_type != p.geometry:
        raise InputError(f"{alg.id}: --{p.name}={value} holds {table.geometry_type} geometries; "
                         f"{p.description} needs {p.geometry}s")
    return table


def write_outputs(alg: S.Algorithm, args: dict, result: S.Result) -> dict:
    """Write vector tables to GeoPackages (with their QGIS styles); return every output's path.

    Outputs naming the same file become layers of that one GeoPackage
    (``--TREES=all.gpkg --CROWNS=all.gpkg``); ``file.gpkg|layername=NAME``
    names the layer and keeps the file's other layers, as QGIS does.
    """
    from dataclasses import replace

    from .core.io.gpkg import split_source, write_gpkg

    paths = dict(result.files)
    files: dict = {}                                   # resolved path -> (path, [(param, table, style)], update)
    for name, table in result.vectors.items():
        if not args.get(name):
            continue
        file, layer = split_source(args[name])
        path = Path(file)
        if path.suffix.lower() != ".gpkg":
            raise InputError(f"{path}: the command line writes vector outputs as GeoPackage (.gpkg) files")
        if layer is not None:
            if not layer:
                raise InputError(f"--{name}={args[name]}: the layer name after layername= is empty")
            table = replace(table, name=layer)
        entry = files.setdefault(path.resolve(), (path, [], [False]))
        entry[1].append((name, table, alg.param(name).style))
        entry[2][0] = entry[2][0] or layer is not None
    for path, items, update in files.values():
        seen = {}
        for name, table, _ in items:
            other = seen.setdefault(table.name.lower(), name)
            if other != name:
                raise InputError(f"--{other} and --{name} both write layer {table.name!r} of {path}; "
                                 f"name them apart with {path}|layername=NAME")
        try:
            write_gpkg(path, [_rounded(t) for _, t, _ in items], styles={t.name: s for _, t, s in items if s},
                       update=update[0])
        except OSError as err:
            raise disk_error(path, err) from None
        for name, table, _ in items:
            paths[name] = f"{path}|layername={table.name}" if len(items) > 1 or update[0] else str(path)
    return paths


class _Terminated(BaseException):
    """SIGTERM (or SIGHUP) arrived: unwinds like Ctrl-C, so every temporary file is removed."""


_SIGNALLED = {"signal": None, "computing": False}   # the last SIGINT/SIGTERM main() received


def _deferred(signum) -> bool:
    """Record the signal; True when the run should stop at its next cancel check instead of now.

    While an algorithm computes, a signal only sets the flag that :meth:`CliFeedback.cancelled` reports
    (the run stops at its next check, within a step): an exception raised at any bytecode could land inside
    a C extension's half-built object (scipy's Qhull and its message stream were torn and the process died
    with SIGSEGV).  Before the computation, or at a second signal, it is raised at once."""
    again = _SIGNALLED["signal"] is not None
    _SIGNALLED["signal"] = signum
    return _SIGNALLED["computing"] and not again


def _at_once(signum, frame) -> bool:
    """Whether the signal is raised now (see :func:`_deferred`).  Not while the first one lands in
    the import system's own frames either: raised there, the exception surfaced as a traceback
    printed from importlib's module-lock clean-up (``_lock_unlock_module``) before the one line;
    the run then stops at the cancel check that opens the computation."""
    again = _SIGNALLED["signal"] is not None
    importing = frame is not None and frame.f_code.co_filename.startswith("<frozen importlib")
    return not _deferred(signum) and (again or not importing)


def _on_signal(signum, frame):
    if _at_once(signum, frame):
        raise _Terminated(signum)


def _on_interrupt(signum, frame):
    if _at_once(signum, frame):
        raise KeyboardInterrupt


def _rounded(table):
    """The table with its real columns rounded for display (spec.display_round), as the QGIS sinks write them."""
    from dataclasses import replace

    from .core.table import field_type

    columns = {name: S.display_round(v) if field_type(v) == "real" else v for name, v in table.columns.items()}
    return replace(table, columns=columns)


def main(argv: Optional[List[str]] = None) -> int:
    """Run one algorithm; every SylvaError (and Ctrl-C, SIGTERM, a full disk) is one line on stderr.

    Exit codes: 0 done, 1 error, 2 usage, 130 cancelled (Ctrl-C), 143 terminated (SIGTERM).
    """
    import signal

    name = "sylva"
    scratch: list = []
    previous = {}
    _SIGNALLED["signal"], _SIGNALLED["computing"] = None, False
    try:
        for sig, handler in ((signal.SIGTERM, _on_signal), (getattr(signal, "SIGHUP", None), _on_signal),
                             (signal.SIGINT, _on_interrupt)):
            if sig is not None:
                try:
                    previous[sig] = signal.signal(sig, handler)
                except (ValueError, OSError):  # not the main thread
                    pass
        # numpy first, on its own: a Ctrl-C while it loads is then its (silent) ImportError, caught
        # below, and not a C extension built on it printing the failed import (numpy's import_array)
        import numpy  # noqa: F401

        argv = list(sys.argv[1:] if argv is None else argv)
        if argv and argv[0].startswith("sylva:"):
            argv[0] = argv[0].split(":", 1)[1]
        parser = _parser()
        ns = parser.parse_args(argv)
        if not ns.algorithm:
            parser.print_help()
            return 2
        alg = get(ns.algorithm)
        name = f"sylva {alg.id}"
        return _run(alg, ns, scratch)
    except (KeyboardInterrupt, Cancelled) as exc:
        if isinstance(exc, Cancelled) and _SIGNALLED["signal"] not in (None, signal.SIGINT):
            print(f"\n{name}: terminated", file=sys.stderr)
            return 143
        print(f"\n{name}: cancelled", file=sys.stderr)
        return 130
    except _Terminated:
        print(f"\n{name}: terminated", file=sys.stderr)
        return 143
    except SylvaError as exc:
        print(f"\n{name}: error: {_one_line(exc)}", file=sys.stderr)
        return 1
    except Exception:
        # a library turned the Ctrl-C or SIGTERM that interrupted its import into an ImportError
        # (numpy does): the user cancelled, this is no bug
        if _SIGNALLED["signal"] == signal.SIGINT:
            print(f"\n{name}: cancelled", file=sys.stderr)
            return 130
        if _SIGNALLED["signal"] is not None:
            print(f"\n{name}: terminated", file=sys.stderr)
            return 143
        raise
    finally:
        import shutil

        for folder in scratch:
            shutil.rmtree(folder, ignore_errors=True)
        for sig, handler in previous.items():
            try:
                signal.signal(sig, handler)
            except (ValueError, OSError, TypeError):
                pass


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def _run(alg: S.Algorithm, ns, scratch: list) -> int:
    from .algorithms.common import OutputGuard, check_paths
    from .core.progress import check

    feedback = CliFeedback(ns.quiet)
    raw = vars(ns)
    check_paths(alg, raw, raw=raw)       # before reading anything: the paths as given
    args = convert(alg, raw, scratch)
    check_paths(alg, args, raw=raw)       # again with the temporary outputs filled in
    guard = OutputGuard(alg, args)
    try:
        _SIGNALLED["computing"] = True
        check(feedback.cancelled)                     # a signal during the set-up above
        result = alg.run(args, feedback)
        check(feedback.cancelled)
        paths = write_outputs(alg, args, result)
    except OSError as err:
        guard.rollback()
        raise disk_error(err.filename or guard.describe(), err) from None
    except BaseException:
        guard.rollback()
        raise
    kept = {str(Path(f)) for f in scratch}
    for key, path in paths.items():
        if any(str(path).startswith(k) for k in kept):
            print(f"{key}: not kept (a temporary file; give --{key}=PATH to keep it)")
        else:
            print(f"{key}: {path}")
    for key, value in result.values.items():
        print(f"{key}: {value}")
    return 0


def run() -> None:
    """The process entry point (the ``sylva`` command and ``python -m sylva.cli``): exit with main()'s code.

    Once main() has returned, Ctrl-C and SIGTERM are ignored: the outputs are complete (or rolled back).  A
    cancelled or terminated run (130, 143) then leaves at once, without the interpreter's shutdown: the
    interrupt may have landed inside a library's own initialisation (numba and llvmlite are imported on a
    kernel's first call; a Cython module runs code through ``PyRun_String`` while imported), and that
    half-initialised library's finalizers crashed the exit (SIGSEGV) or turned 130 into death by SIGINT
    (Python's unhandled-interrupt flag).  Sylva's own clean-up has run by then (main()'s ``finally``).
    """
    import os
    import signal

    try:
        code = main()
    except KeyboardInterrupt:  # between the handlers' restoration and here
        code = 130
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    if code in (130, 143):
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":
    run()
