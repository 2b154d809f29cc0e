"""Progress and cancel plumbing shared by every long-running core function.

Core functions take two optional callables, as ARCHITECTURE.md prescribes:

* ``progress(fraction, message)`` with ``fraction`` in [0, 1];
* ``cancelled()`` returning True when the user asked to stop.

:func:`check` turns a positive ``cancelled()`` into :class:`~.errors.Cancelled`,
and :func:`scaled` maps a sub-step's [0, 1] onto a slice of the parent's range.
"""
from __future__ import annotations

from typing import Callable, Optional

from .errors import Cancelled

Progress = Optional[Callable[[float, str], None]]
CancelCheck = Optional[Callable[[], bool]]


def report(progress: Progress, fraction: float, message: str = "") -> None:
    """Call ``progress`` if one was given, clamping the fraction to [0, 1]."""
    if progress is not None:
        progress(min(1.0, max(0.0, float(fraction))), message)


def check(cancelled: CancelCheck) -> None:
    """Raise :class:`Cancelled` when the user asked to stop."""
    if cancelled is not None and cancelled():
        raise Cancelled()


def scaled(progress: Progress, start: float, stop: float) -> Progress:
    """A progress callback that maps [0, 1] onto [start, stop] of ``progress``."""
    if progress is None:
        return None
    return lambda f, msg="": progress(start + (stop - start) * f, msg)
