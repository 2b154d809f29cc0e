"""Tree IDs from tree-top positions: the same tree gets the same ID in any tiling, run order or worker count.

(Sylva, not in the papers.) A tree's ID is a 64-bit splitmix hash of its top's position snapped to
:data:`ID_GRID_M`, cut to the low ``bits`` bits (31 for LAS's int32 ``treeID``); collisions are
resolved by a deterministic rule over the set of positions (:func:`tree_ids`), which a catalog run
applies once more over the whole run's trees (:func:`run_wide_remaps`).
"""
from __future__ import annotations

from typing import Dict, Mapping, Tuple

import numpy as np

from .errors import InputError

#: Tree tops are snapped to this grid (metres) before hashing them into an ID.
ID_GRID_M = 0.01
_MASK64 = np.uint64(0xFFFFFFFFFFFFFFFF)


def _splitmix64(x: np.ndarray) -> np.ndarray:
    with np.errstate(over="ignore"):
        z = (x + np.uint64(0x9E3779B97F4A7C15)) & _MASK64
        z = ((z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)) & _MASK64
        z = ((z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)) & _MASK64
        return z ^ (z >> np.uint64(31))


def grid_keys(xy: np.ndarray, metres_per_unit: float = 1.0) -> np.ndarray:
    """(n, 2) int64 top positions snapped to :data:`ID_GRID_M` (source CRS, any units)."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    return np.round(xy * metres_per_unit / ID_GRID_M).astype(np.int64)


def _hash_ids(keys: np.ndarray, salt: np.ndarray, bits: int) -> np.ndarray:
    gx = keys[:, 0].astype(np.uint64)
    gy = keys[:, 1].astype(np.uint64)
    with np.errstate(over="ignore"):
        h = _splitmix64(_splitmix64(gx) ^ gy)
        h = _splitmix64(h ^ np.asarray(salt, dtype=np.uint64))
    return (h & np.uint64((1 << bits) - 1)).astype(np.int64)


def tree_ids(keys: np.ndarray, bits: int = 31) -> np.ndarray:
    """Stable positive IDs (< 2**bits) of trees whose tops snap to ``keys`` (:func:`grid_keys`).

    ID = low ``bits`` bits of a 64-bit splitmix hash of the snapped (x, y), salt 0.
    Collisions are resolved deterministically: the trees are taken in (gx, gy)
    order and each gets the first salt 0, 1, 2, ... whose ID is neither 0 nor
    already taken by an earlier tree.  The result therefore depends only on the
    *set* of positions; :mod:`sylva.core.catalog` applies the same rule to the
    whole run's set and rewrites the rare tile whose local set resolved
    differently.
    """
    keys = np.asarray(keys, dtype=np.int64).reshape(-1, 2)
    if not 2 <= bits <= 31:
        raise InputError(f"tree IDs need 2..31 bits, got {bits}")
    ids = _hash_ids(keys, np.zeros(len(keys), dtype=np.uint64), bits)
    if len(ids) == 0 or ((ids > 0).all() and len(np.unique(ids)) == len(ids)):
        return ids
    if len(keys) >= (1 << bits) - 1:
        raise InputError(f"{len(keys)} trees do not fit {bits}-bit tree IDs")
    order = np.lexsort((keys[:, 1], keys[:, 0]))
    taken = set()
    out = np.zeros(len(keys), dtype=np.int64)
    for i in order:
        salt = 0
        v = int(ids[i])
        while v == 0 or v in taken:
            salt += 1
            v = int(_hash_ids(keys[i:i + 1], np.array([salt], dtype=np.uint64), bits)[0])
        taken.add(v)
        out[i] = v
    return out


def run_wide_remaps(tiles: Mapping[str, Tuple[np.ndarray, np.ndarray, np.ndarray]], bits: int = 31,
                    complete: bool = True) -> Dict[str, dict]:
    """Per tile, the {old ID: new ID} its files need once :func:`tree_ids` has run over the whole run.

    ``tiles``: per tile name, (keys of the trees it owns, keys of every tree it saw, the IDs it gave
    those); each tile resolved collisions among the tops it saw, so a tile whose local choice differs
    from the run-wide one is rewritten (rare: IDs then depend only on the run's set of trees).
    An ID a tile saw that no tile owns maps to 0 (no tree): a segment across a tile edge that the
    neighbouring tiles' buffered segmentations cut differently, so that each tile's apex of it lies
    in another tile; its points then carry no ID rather than one that no table holds.  Only when the
    run is ``complete``: a tile that failed may own it when it is run again.
    """
    owned = [np.asarray(k, dtype=np.int64).reshape(-1, 2) for k, _, _ in tiles.values()]
    if not owned:
        return {}
    allk = np.concatenate(owned)
    lookup = {tuple(k): int(v) for k, v in zip(allk.tolist(), tree_ids(allk, bits).tolist())}
    maps = {}
    for name, (_, seen_keys, seen_ids) in tiles.items():
        m = {}
        for k, v in zip(np.asarray(seen_keys).reshape(-1, 2).tolist(), np.asarray(seen_ids).tolist()):
            if v == 0:
                continue   # emptied by an earlier run: its points carry no ID ({0: new} would take every point)
            new = lookup.get(tuple(k), 0 if complete else v)
            if new != v:
                m[int(v)] = new
        if m:
            maps[name] = m
    return maps


def unowned_trees(maps: Mapping[str, dict]) -> int:
    """How many tree IDs :func:`run_wide_remaps` found seen by some tile and owned by none."""
    return len({old for m in maps.values() for old, new in m.items() if new == 0})
