"""Branch reconstruction from the clusters: Yan et al. 2009 §3.

Cluster adjacency (§3.1), junction points and the shortest-path tree (§3.2), and the branches and their
orders by the longest-path rule of Algorithm 3.1 (:func:`branch_structure`).
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import List

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from .segmentation import Segmentation


# --------------------------------------------------------------------------- §3 branches

@dataclass
class BranchStructure:
    """Yan §3 on the clusters.

    ``parent`` (n,) parent cluster in the shortest-path tree (-1 root / unreached);
    ``root`` the cluster holding the lowest point; ``junction`` (n, 3) the
    junction point between each cluster and its parent (§3.2; for the root
    its extra junction); ``tip`` (n, 3) extra junction of leaf clusters (NaN
    elsewhere); ``branches`` lists of cluster indices (Algorithm 3.1), each
    starting at the cluster it leaves (none for the trunk, branch 0);
    ``branch_parent`` / ``branch_order`` per branch; ``n_edges`` of the
    adjacency graph; ``bridged`` number of graph components joined by
    their nearest centres."""

    parent: np.ndarray
    root: int
    junction: np.ndarray
    tip: np.ndarray
    centre: np.ndarray
    branches: List[List[int]]
    branch_parent: np.ndarray
    branch_order: np.ndarray
    n_edges: int
    bridged: int


def branch_structure(xyz: np.ndarray, seg: Segmentation, on_axis: bool = False) -> BranchStructure:
    """Adjacency graph, junctions, shortest-path tree and branches (Yan §3.1–3.3, Alg. 3.1).

    Cluster centres are the point centroids ``c_i`` (§2.2).  With ``on_axis``
    (not in the paper) a fixed cluster is represented by the centre of its
    fitted circle on its axis and its junctions are projected onto that
    axis: a stem scanned from one side, or cut into half rings, then keeps a
    straight skeleton instead of zigzagging along the bark.
    """
    labels, nbr = seg.labels, seg.nbr
    nc = seg.n_clusters
    centre = seg.cylinders["mean"]
    if on_axis:
        centre = np.where(seg.fixed[:, None], seg.cylinders["fit_centre"], centre)
    n, k = nbr.shape
    a = np.repeat(labels, k)
    pi = np.repeat(np.arange(n), k)
    qi = nbr.ravel()
    b = labels[qi]
    cross = (a >= 0) & (b >= 0) & (a != b)
    pi, qi, a, b = pi[cross], qi[cross], a[cross], b[cross]
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    key = lo * nc + hi
    # §3.2 boundary points: p in C_i with a neighbour in C_j, and vice versa
    pts = np.r_[pi, qi]
    kk = np.r_[key, key]
    pk = np.unique(np.stack([kk, pts], axis=1), axis=0)
    ukey, inv = np.unique(pk[:, 0], return_inverse=True)
    cnt = np.bincount(inv).astype(np.float64)
    junc = np.stack([np.bincount(inv, weights=xyz[pk[:, 1], j]) for j in range(3)], axis=1) / cnt[:, None]
    ea, eb = ukey // nc, ukey % nc
    w = np.linalg.norm(junc - centre[ea], axis=1) + np.linalg.norm(junc - centre[eb], axis=1)
    w = np.maximum(w, 1e-9)
    # bridge disconnected parts of the adjacency graph by nearest cluster centres
    present = np.bincount(labels[labels >= 0], minlength=nc) > 0
    G = sparse.coo_matrix((w, (ea, eb)), shape=(nc, nc)).tocsr()
    G = G.maximum(G.T)
    ncomp, comp = csgraph.connected_components(G, directed=False)
    low = int(np.argmin(np.where(labels >= 0, xyz[:, 2], np.inf)))
    root = int(labels[low])
    bridged = 0
    extra_j, extra_a, extra_b = [], [], []
    if ncomp > 1:
        comps = [c for c in range(ncomp) if present[comp == c].any()]
        main = comp[root]
        joined = {main}
        rest = [c for c in comps if c != main]
        while rest:
            inj = np.flatnonzero(np.isin(comp, list(joined)) & present)
            t = cKDTree(centre[inj])
            best = None
            for c in rest:
                mem = np.flatnonzero((comp == c) & present)
                d, i = t.query(centre[mem])
                j = int(np.argmin(d))
                if best is None or d[j] < best[0]:
                    best = (d[j], int(mem[j]), int(inj[i[j]]), c)
            _, u, v, c = best
            extra_a.append(u)
            extra_b.append(v)
            extra_j.append((centre[u] + centre[v]) / 2)
            joined.add(c)
            rest.remove(c)
            bridged += 1
        ea = np.r_[ea, extra_a]
        eb = np.r_[eb, extra_b]
        junc = np.vstack([junc, np.asarray(extra_j).reshape(-1, 3)])
        w = np.r_[w, np.linalg.norm(junc[-bridged:] - centre[extra_a], axis=1) * 2 + 1e-9]
        G = sparse.coo_matrix((w, (ea, eb)), shape=(nc, nc)).tocsr()
        G = G.maximum(G.T)
    dist, pred = csgraph.dijkstra(G, directed=False, indices=root, return_predecessors=True)
    parent = np.where(pred >= 0, pred, -1).astype(np.int64)
    parent[root] = -1
    # junction between each cluster and its parent
    jmap = {}
    for i, (u, v) in enumerate(zip(ea.tolist(), eb.tolist())):
        jmap[(min(u, v), max(u, v))] = i
    junction = np.full((nc, 3), np.nan)
    has_p = np.flatnonzero(parent >= 0)
    for c in has_p.tolist():
        p = int(parent[c])
        junction[c] = junc[jmap[(min(c, p), max(c, p))]]
    if on_axis:   # junctions onto the child's axis
        fx = np.flatnonzero(seg.fixed & (parent >= 0))
        ax = seg.cylinders["axis"][fx]
        off = ((junction[fx] - centre[fx]) * ax).sum(axis=1)
        junction[fx] = centre[fx] + off[:, None] * ax
    reached = np.isfinite(dist)
    nkids = np.bincount(parent[parent >= 0], minlength=nc)
    tip = np.full((nc, 3), np.nan)
    leaf = reached & (nkids == 0) & (np.arange(nc) != root)
    tip[leaf] = 2 * centre[leaf] - junction[leaf]          # symmetric junction (Fig. 4)
    # Algorithm 3.1: longest distance to a leaf, then branches by a FIFO queue
    edge_len = np.zeros(nc)
    edge_len[has_p] = dist[has_p] - dist[parent[has_p]]
    order = np.argsort(dist, kind="stable")
    order = order[reached[order]]
    longest = np.zeros(nc)
    for c in order[::-1].tolist():
        p = int(parent[c])
        if p >= 0:
            longest[p] = max(longest[p], longest[c] + edge_len[c])
    kids: List[list] = [[] for _ in range(nc)]
    for c in order.tolist():
        if parent[c] >= 0:
            kids[int(parent[c])].append(c)
    # root's extra junction: mirror of its junction to the child on the main path
    if kids[root]:
        main_kid = max(kids[root], key=lambda c: (longest[c] + edge_len[c], -c))
        junction[root] = 2 * centre[root] - junction[main_kid]
    else:
        junction[root] = centre[root] - np.array([0, 0, max(seg.cylinders["length"][root] / 2, 0.01)])
        tip[root] = 2 * centre[root] - junction[root]
    selected = np.zeros(nc, dtype=bool)
    branch_of = np.full(nc, -1, dtype=np.int64)
    branches: List[List[int]] = []
    bpar: List[int] = []
    bord: List[int] = []
    queue = deque([root])
    selected[root] = True
    while queue:
        t = queue.popleft()
        free = [c for c in kids[t] if not selected[c]]
        if t == root and not branches:
            chain, c, start_parent, ordr = [root], root, -1, 0
        else:
            if not free:
                continue
            c = max(free, key=lambda x: (longest[x] + edge_len[x], -x))
            selected[c] = True
            chain = [t, c]
            start_parent = int(branch_of[t])
            ordr = bord[start_parent] + 1
        while True:
            nxt = [x for x in kids[c] if not selected[x]]
            if not nxt:
                break
            c = max(nxt, key=lambda x: (longest[x] + edge_len[x], -x))
            selected[c] = True
            chain.append(c)
        b = len(branches)
        branches.append(chain)
        bpar.append(start_parent)
        bord.append(ordr)
        for node in (chain if start_parent < 0 else chain[1:]):
            branch_of[node] = b
        for node in chain:
            if any(not selected[x] for x in kids[node]):
                queue.append(node)
    return BranchStructure(parent, root, junction, tip, centre, branches,
                           np.asarray(bpar, dtype=np.int64), np.asarray(bord, dtype=np.int64),
                           int(len(ukey)), bridged)
