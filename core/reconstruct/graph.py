"""Graph of candidate skeleton points (Hu et al. 2017, §5.2, Algorithm 1).

Algorithm 1 (GraphGenerate(r_p, k)) inserts the candidate points P into a
k-d tree, connects every p_i to all points within the fixed radius r_p
(FRNN), counts its neighbours n_i, and then, for every p_i with n_i < k,
also connects its k nearest points (kNN).  Edges are undirected and weighted
by the Euclidean distance ‖p_i − p_j‖.  The kNN pass connects sparse parts
that a small radius alone leaves apart (Fig. 10), so that the skeleton can
be grown over one connected graph.

Defaults (§6.2, Table 1): r_p = 1.2 m, k ∈ [10, 30] "according to r_p";
Sylva uses k = 30 (see :class:`~.skeleton.GreedySkeleton` for why).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree


class Graph(NamedTuple):
    """Result of :func:`build_graph`."""

    adjacency: csr_matrix   # (n, n) symmetric, data = edge length in metres, sorted indices
    n_components: int       # connected components (1 = connected, as Algorithm 2 needs)
    labels: np.ndarray      # (n,) component of every point
    n_knn: int              # points that needed the kNN pass (n_i < k)

    @property
    def connected(self) -> bool:
        return self.n_components <= 1

    @property
    def n_edges(self) -> int:
        return self.adjacency.nnz // 2


def build_graph(points: np.ndarray, radius_m: float = 1.2, k: int = 30) -> Graph:
    """Connect candidate points by FRNN within ``radius_m`` plus kNN where sparse (Algorithm 1).

    Pure function of its inputs; returns the symmetric adjacency (CSR with
    sorted column indices), its connected components (scipy.sparse.csgraph)
    and how many points needed the kNN pass.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = len(points)
    if n == 0:
        return Graph(csr_matrix((0, 0)), 0, np.zeros(0, dtype=np.int64), 0)
    tree = cKDTree(points)
    pairs = tree.query_pairs(radius_m, output_type="ndarray").astype(np.int64)   # FRNN, i < j
    n_i = np.bincount(pairs.ravel(), minlength=n)
    need = np.flatnonzero(n_i < k)
    kk = min(k + 1, n)
    if len(need) and kk > 1:
        _, nn = tree.query(points[need], k=kk)
        nn = np.asarray(nn).reshape(len(need), kk)
        src = np.repeat(need, kk)
        dst = nn.ravel()
        ok = (dst != src) & (dst < n)
        knn = np.stack([src[ok], dst[ok]], axis=1)
        pairs = np.concatenate([pairs, np.sort(knn, axis=1)])
    # Undirected edge set -> symmetric CSR built directly from sorted keys.
    a, b = pairs[:, 0], pairs[:, 1]
    key = np.unique(np.concatenate([a * n + b, b * n + a]))
    rows, cols = key // n, key % n
    indptr = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(rows, minlength=n), out=indptr[1:])
    length = np.linalg.norm(points[rows] - points[cols], axis=1)
    adj = csr_matrix((length, cols, indptr), shape=(n, n))
    adj.has_sorted_indices = True
    structure = csr_matrix((np.ones(len(cols)), cols, indptr), shape=(n, n))
    ncomp, labels = connected_components(structure, directed=False)
    return Graph(adj, int(ncomp), labels, int(len(need)))
