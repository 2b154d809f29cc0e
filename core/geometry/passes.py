"""Passes over a skeleton's nodes, and the forest of many skeletons the batch forms work on.

Depth levels and subtree sums for level-wise vectorised passes (:func:`depth_levels`, :func:`subtree_sum`),
the input check of every geometry function (:func:`check_skeleton`, :func:`tree_name`), and the forest:
skeletons joined into one set of arrays (:func:`join_forest`) and cut back into trees
(:func:`localise_parents`, :func:`trusted_skeleton`).
"""
from __future__ import annotations

from typing import List

import numpy as np

from ..errors import InputError
from ..skeleton import Skeleton


def _depth(parent: np.ndarray) -> np.ndarray:
    """Number of segments from the root to each node, by pointer jumping (O(m log depth))."""
    depth = (parent >= 0).astype(np.int64)
    nxt = parent.copy()
    live = np.flatnonzero(nxt >= 0)
    while len(live):   # after step k every node has summed 2^k links up its path
        tgt = nxt[live]
        depth[live] += depth[tgt]
        nxt[live] = nxt[tgt]
        live = live[nxt[live] >= 0]
    return depth


def depth_levels(skeleton: Skeleton) -> List[np.ndarray]:
    """Node indices grouped by depth (root level first), for level-wise vectorised passes."""
    if len(skeleton) == 0:
        return []
    d = _depth(skeleton.parent)
    order = np.argsort(d, kind="stable")
    cuts = np.flatnonzero(np.diff(d[order])) + 1
    return np.split(order, cuts)


def subtree_sum(parent: np.ndarray, values: np.ndarray, levels: List[np.ndarray]) -> np.ndarray:
    """Sum of ``values`` over each node's subtree (node included): deepest level first."""
    acc = np.array(values, dtype=np.float64, copy=True)
    for idx in reversed(levels[1:]):
        np.add.at(acc, parent[idx], acc[idx])
    return acc


def check_skeleton(skeleton) -> Skeleton:
    if not isinstance(skeleton, Skeleton):
        raise InputError(f"expected a Skeleton, got {type(skeleton).__name__}")
    return skeleton


def tree_name(skeleton) -> str:
    tid = getattr(skeleton, "tree_id", None)
    return f"tree {tid}" if tid is not None else "skeleton"


def join_forest(skeletons):
    """(nodes, parent, node offsets) of skeletons joined into one forest (parents shifted, roots -1)."""
    sizes = np.array([len(sk) for sk in skeletons], dtype=np.int64)
    off = np.r_[0, np.cumsum(sizes)]
    nodes = np.concatenate([sk.nodes for sk in skeletons]).reshape(-1, 3)
    parent = np.concatenate([sk.parent for sk in skeletons]).astype(np.int64)
    return nodes, np.where(parent >= 0, parent + np.repeat(off[:-1], sizes), -1), off


def localise_parents(parent: np.ndarray, off: np.ndarray) -> np.ndarray:
    """Forest parents (global indices, -1 at roots) made relative to each tree's first node."""
    tree = np.repeat(np.arange(len(off) - 1), np.diff(off))
    return np.where(parent >= 0, parent - off[:-1][tree], -1)


def trusted_skeleton(nodes: np.ndarray, parent: np.ndarray, radius: np.ndarray, is_added: np.ndarray) -> Skeleton:
    """A :class:`Skeleton` of arrays that are valid by construction (a slice of a forest of valid
    skeletons: float64 (m, 3) nodes, int64 parents before their children and one root, float64
    radii, bool flags), without ``Skeleton``'s checks and conversions (Sylva, not in the paper)."""
    sk = object.__new__(Skeleton)
    sk.nodes, sk.parent, sk.radius, sk.is_added = nodes, parent, radius, is_added
    return sk
