"""The registry of Sylva's algorithms, shared by the Processing provider and the CLI.

Importing this package is cheap and needs no third-party package (the plugin
must load, and name what is missing, even when numpy or laspy are not
installed): :func:`all_algorithms` imports the definitions on first use.
"""
from __future__ import annotations

import importlib
from typing import Dict

#: Modules that define algorithms, each exporting its Algorithm values in ``ALGORITHMS``.
MODULES = ("terrain", "tops", "segment", "reconstruct", "export", "pipeline", "sketch", "billboard")

_cache: Dict[str, object] = {}


def all_algorithms() -> Dict[str, "Algorithm"]:  # noqa: F821
    """id -> Algorithm, in toolbox order."""
    if not _cache:
        for name in MODULES:
            module = importlib.import_module(f"{__name__}.{name}")
            for alg in module.ALGORITHMS:
                _cache[alg.id] = alg
    return _cache


def get(algorithm_id: str):
    """The algorithm with this id (``sylva:`` prefix allowed)."""
    key = algorithm_id.split(":", 1)[-1]
    algorithms = all_algorithms()
    if key not in algorithms:
        from ..core.errors import InputError

        raise InputError(f"unknown algorithm {algorithm_id!r}; known: {', '.join(sorted(algorithms))}")
    return algorithms[key]
