"""The skeleton of a tree: a rooted tree of nodes, what every reconstruction method returns.

A :class:`Skeleton` holds node positions and a ``parent`` array (parents before children) — the
common output of Hu et al.'s greedy skeleton (:mod:`sylva.core.reconstruct.skeleton`), Guo et al.'s
guided growth (``colonize``), the QSMs and any later method; ``radius`` stays unset until
:mod:`sylva.core.geometry` fills it (pipe model, Hu et al. 2017 §5.5, Eq. 6).  It lives below the
geometry, the leaves and the reconstruction methods, which all use it.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import List, Optional

import numpy as np



@dataclass
class Skeleton:
    """A rooted tree of nodes in the same metric frame as the tree's points.

    ``nodes`` (m, 3) positions; ``parent`` (m,) int64 with -1 for the root
    (node 0 in every skeleton Sylva builds) and ``parent[i] < i`` otherwise,
    so a forward pass visits parents before children; ``radius`` (m,) metres,
    0 until geometry fills it; ``is_added`` (m,) True where a node stands for
    added trunk/root points (Hu et al. §4.2) rather than measured ones.
    """

    nodes: np.ndarray
    parent: np.ndarray
    radius: Optional[np.ndarray] = None
    is_added: Optional[np.ndarray] = None

    def __post_init__(self):
        self.nodes = np.asarray(self.nodes, dtype=np.float64).reshape(-1, 3)
        m = len(self.nodes)
        self.parent = np.asarray(self.parent, dtype=np.int64).reshape(-1)
        self.radius = (np.zeros(m) if self.radius is None
                       else np.asarray(self.radius, dtype=np.float64).reshape(-1))
        self.is_added = (np.zeros(m, dtype=bool) if self.is_added is None
                         else np.asarray(self.is_added, dtype=bool).reshape(-1))
        if not (len(self.parent) == len(self.radius) == len(self.is_added) == m):
            raise ValueError("skeleton arrays must all have one entry per node")
        if m:
            idx = np.arange(m)
            bad = (self.parent >= idx) | (self.parent < -1)
            if bad.any() or (self.parent == -1).sum() != 1:
                raise ValueError("skeleton parent array must have exactly one root (-1) "
                                 "and every parent before its child")

    def __len__(self) -> int:
        return len(self.nodes)

    @property
    def root(self) -> int:
        """Index of the root node (-1 for an empty skeleton)."""
        roots = np.flatnonzero(self.parent == -1)
        return int(roots[0]) if len(roots) else -1

    def children(self) -> List[np.ndarray]:
        """For every node, the indices of its children (ascending)."""
        m = len(self)
        kids = np.flatnonzero(self.parent >= 0)
        order = np.argsort(self.parent[kids], kind="stable")
        kids = kids[order]
        counts = np.bincount(self.parent[kids], minlength=m)
        return np.split(kids, np.cumsum(counts)[:-1]) if m else []

    def n_children(self) -> np.ndarray:
        """Number of children per node."""
        ok = self.parent >= 0
        return np.bincount(self.parent[ok], minlength=len(self))

    def tips(self) -> np.ndarray:
        """Indices of nodes without children (a lone root counts as a tip)."""
        return np.flatnonzero(self.n_children() == 0)

    def segments(self):
        """(child, parent) index arrays of every segment (edge) of the skeleton."""
        child = np.flatnonzero(self.parent >= 0)
        return child, self.parent[child]

    def segment_lengths(self) -> np.ndarray:
        child, par = self.segments()
        return np.linalg.norm(self.nodes[child] - self.nodes[par], axis=1)

    def length(self) -> float:
        """Total length of all segments in metres."""
        return float(self.segment_lengths().sum())

    def depth(self) -> np.ndarray:
        """Number of segments from the root to each node."""
        d = np.zeros(len(self), dtype=np.int64)
        for i in range(1, len(self)):  # parents precede children
            if self.parent[i] >= 0:
                d[i] = d[self.parent[i]] + 1
        return d

    def distance(self, points: np.ndarray, chunk: int = 200_000) -> np.ndarray:
        """Distance in metres from each point to the nearest skeleton segment (or node)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if len(self) == 0:
            return np.full(len(points), np.inf)
        child, par = self.segments()
        if len(child) == 0:
            return np.linalg.norm(points - self.nodes[self.root], axis=1)
        a = self.nodes[par]
        ab = self.nodes[child] - a
        ab2 = np.maximum((ab * ab).sum(axis=1), 1e-18)
        out = np.empty(len(points))
        step = max(1, chunk // len(a))
        for s in range(0, len(points), step):
            p = points[s:s + step, None, :] - a[None, :, :]  # (c, m, 3)
            t = np.clip((p * ab[None]).sum(axis=2) / ab2[None], 0.0, 1.0)
            d = p - t[..., None] * ab[None]
            out[s:s + step] = np.sqrt((d * d).sum(axis=2).min(axis=1))
        return out
