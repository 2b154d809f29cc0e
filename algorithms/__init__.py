"""The registry of Sylva's algorithms, shared by the Processing provider and the CLI."""
from __future__ import annotations

from typing import Dict

from .spec import Algorithm
from .terrain import CANOPY_HEIGHT_MODEL
from .tops import TREE_TOPS

ALGORITHMS: Dict[str, Algorithm] = {a.id: a for a in (CANOPY_HEIGHT_MODEL, TREE_TOPS)}


def get(algorithm_id: str) -> Algorithm:
    """The algorithm with this id (``sylva:`` prefix allowed)."""
    key = algorithm_id.split(":", 1)[-1]
    if key not in ALGORITHMS:
        from ..core.errors import InputError

        raise InputError(f"unknown algorithm {algorithm_id!r}; known: {', '.join(sorted(ALGORITHMS))}")
    return ALGORITHMS[key]
