"""Greedy skeleton production (Hu et al. 2017, §5.4, Algorithm 2) and the
:class:`GreedySkeleton` method that chains §4.2 → §5.1 → §5.2 → §5.3 → §5.4.

Algorithm 2 (SkeletonProduce(start, end)) grows a tree over the graph of
candidate points from the root segment (start = root on the ground, end =
the next point up the trunk).  A priority queue Q holds segments (k → i)
keyed by α/α_max.  For the segment popped, with v_parent = p_i − p_k, every
unvisited graph neighbour p_j of p_i is a candidate when

* its bending angle α_j = ∠(v_child, v_parent) < α_max, v_child = p_j − p_i,
* and β_j = ∠(u_j, v_child) < β_max, u_j the direction field (§5.3, Eq. 5);

candidates are marked visited and sorted by α ascending; a candidate whose
child segment is within φ_max of a better one is removed (pruning, Fig. 14b,
it stays visited); the remaining ones become children of p_i and are pushed
with key α_j/α_max.  The loop ends when Q is empty.  It is greedy: no
backtracking, each point becomes a node at most once, so the result is a
tree rooted at ``start``.

Defaults (§6.2): α_max = 70°, β_max = 70°, φ_max = 30°.

Where Sylva goes beyond the printed algorithm (each documented where it is
done): ties in α (cos α equal to 1e-12, e.g. collinear added trunk points)
go to the longer segment, so a straight run advances by up to r_p instead
of stalling among points its predecessor already visited; equal keys in Q
are first in, first out; pruned candidates beyond the kept child are
released (``regrow_pruned``, see :func:`greedy_skeleton`); and the direction
field at added trunk points is the trunk's own direction (§4.2 gives it;
Eq. 5 knows nothing of an Eq. 3 trunk that leans).
"""
from __future__ import annotations

import heapq
import time
from dataclasses import dataclass
from typing import NamedTuple, Optional

import numpy as np

from ..errors import InputError
from ..progress import CancelCheck, Progress, check, report
from .direction import direction_field
from .graph import build_graph
from .model import Reconstruction, Skeleton, TreePoints, screen
from .thinning import thin_voxels
from .trunk import add_trunk_points


class GreedyResult(NamedTuple):
    """Result of :func:`greedy_skeleton`."""

    point_of_node: np.ndarray   # (m,) candidate point index of each skeleton node (node 0 = start)
    parent: np.ndarray          # (m,) parent node, -1 for the root, parents before children
    visited: np.ndarray         # (n,) candidate points reached (kept or pruned)
    alpha_deg: np.ndarray       # (m,) bending angle of each node's segment to its parent's (nan at the root/end)


_POW2 = 1 << np.arange(62, dtype=np.int64)


def _prune(close: np.ndarray, beyond: Optional[np.ndarray]):
    """Greedy pruning of candidates sorted by α (Algorithm 2's double loop).

    Walking the candidates in order, each one still alive is kept and
    removes the alive ones within φ_max of it (``close``); with ``beyond``
    given, those removed that lie farther than the kept one are returned as
    ``released``.  Rows become bit masks (Python ints) when there are at
    most 62 candidates, which keeps the sequential walk cheap.
    """
    c = len(close)
    kept, released = [], []
    if c <= 62:
        w = _POW2[:c]
        rows = (close @ w).tolist()
        far_rows = (beyond @ w).tolist() if beyond is not None else None
        alive = (1 << c) - 1
        for l in range(c):
            if alive >> l & 1:
                kept.append(l)
                pruned = alive & rows[l]
                alive &= ~rows[l]
                if far_rows is not None:
                    rel = pruned & far_rows[l]
                    while rel:
                        low = rel & -rel
                        released.append(low.bit_length() - 1)
                        rel ^= low
        return kept, released
    alive = np.ones(c, dtype=bool)
    for l in range(c):
        if alive[l]:
            kept.append(l)
            pruned = alive & close[l]
            alive &= ~close[l]
            if beyond is not None:
                released.extend(np.flatnonzero(pruned & beyond[l]).tolist())
    return kept, released


def greedy_skeleton(points: np.ndarray, adjacency, directions: np.ndarray, start: int, end: int,
                    alpha_max_deg: float = 70.0, beta_max_deg: float = 70.0,
                    phi_max_deg: float = 30.0, regrow_pruned: bool = True) -> GreedyResult:
    """Hu et al. §5.4, Algorithm 2: greedy tree over ``adjacency`` from segment start → end.

    ``points`` (n, 3) candidate points, ``adjacency`` the CSR graph of
    :func:`~.graph.build_graph`, ``directions`` (n, 3) unit vectors u_j from
    :func:`~.direction.direction_field`.  The inner work per popped segment
    is vectorised over the neighbours of p_i; β_j does not depend on the
    parent segment and is computed once per directed edge.  Pure function.

    ``regrow_pruned`` (Sylva, not in the paper): a pruned candidate lying
    *farther* from p_i than the kept child that pruned it is not left
    visited but released, so the branch can reach it later from that child.
    Algorithm 2 as printed marks every candidate visited; with the kNN edges
    of §5.2, which can be several metres long where points are sparse (a
    stem seen by a few pulses, a gap in the crown), one expansion then
    "visits" a whole collinear run and the branch stops dead.  Pruned
    candidates nearer than the kept child lie along its segment and stay
    visited, as in the paper.  ``regrow_pruned=False`` is Algorithm 2 verbatim.
    """
    points = np.asarray(points, dtype=np.float64)
    n = len(points)
    indptr = adjacency.indptr
    indices = adjacency.indices.astype(np.int64)
    rows = np.repeat(np.arange(n), np.diff(indptr))
    vec = points[indices] - points[rows]
    length = np.linalg.norm(vec, axis=1)
    # Within each row, neighbours by decreasing distance: a stable sort on α
    # then breaks ties by the longer segment.
    order = np.lexsort((-length, rows))
    indices, vec, length = indices[order], vec[order], length[order]
    good = length > 1e-12
    unit = np.zeros_like(vec)
    unit[good] = vec[good] / length[good, None]
    cos_a = np.cos(np.radians(alpha_max_deg))
    cos_b = np.cos(np.radians(beta_max_deg))
    cos_p = np.cos(np.radians(phi_max_deg))
    beta_ok = good & ((unit * directions[indices]).sum(axis=1) > cos_b)   # β_j < β_max
    # β_j does not depend on the parent segment: drop the failing edges once.
    indices, unit, length = indices[beta_ok], unit[beta_ok], length[beta_ok]
    indptr = np.r_[0, np.cumsum(np.bincount(rows[order][beta_ok], minlength=n))]

    visited = np.zeros(n, dtype=bool)
    visited[start] = visited[end] = True
    node_of_point = np.full(n, -1, dtype=np.int64)
    point_of_node = [start]
    parent = [-1]
    alphas = [np.nan]
    node_of_point[start] = 0
    queue = []
    if end != start:
        point_of_node.append(end)
        parent.append(0)
        alphas.append(np.nan)
        node_of_point[end] = 1
        first_seg = points[end] - points[start]
        queue.append((1.0, 0, end, first_seg / np.linalg.norm(first_seg)))
    ptr = indptr.tolist()
    counter = 1
    while queue:
        # Q holds (key = α/α_max, FIFO counter, point i, unit v_parent ending at i).
        _, _, i, v_parent = heapq.heappop(queue)
        a, b = ptr[i], ptr[i + 1]
        js = indices[a:b]
        u_all = unit[a:b]
        cos_all = u_all @ v_parent
        # α_j < α_max, β_j < β_max, not visited
        cand = ((cos_all > cos_a) & ~visited[js]).nonzero()[0]
        if cand.size == 0:
            continue
        visited[js[cand]] = True
        parent_node = node_of_point[i]
        if cand.size == 1:
            kept = cand
        else:
            cand = cand[np.argsort(-np.rint(cos_all[cand] * 1e12), kind="stable")]  # α ascending
            far = length[a:b][cand]
            u = u_all[cand]
            close = (u @ u.T) > cos_p                                    # φ_lm < φ_max
            beyond = far[None, :] > far[:, None]                         # m farther than l
            kept, released = _prune(close, beyond if regrow_pruned else None)
            if released:
                visited[js[cand[released]]] = False
            kept = cand[kept]
        alpha = np.degrees(np.arccos(np.minimum(cos_all[kept], 1.0))).tolist()   # cos > cos α_max > -1
        for l, al in zip(kept.tolist(), alpha):
            j = int(js[l])
            node_of_point[j] = len(point_of_node)
            point_of_node.append(j)
            parent.append(parent_node)
            alphas.append(al)
            heapq.heappush(queue, (al / alpha_max_deg, counter, j, u_all[l]))
            counter += 1
    return GreedyResult(np.asarray(point_of_node, dtype=np.int64), np.asarray(parent, dtype=np.int64),
                        visited, np.asarray(alphas))


def choose_end(points: np.ndarray, adjacency, start: int, direction: np.ndarray,
               max_angle_deg: float) -> int:
    """The point that closes the first segment start → end (Hu et al. §5.4, last paragraph).

    "We automatically choose the root position as the initial starting
    point, and derive the ending point in the direction of the trunk by
    Eq. 3 and Eq. 4": the nearest graph neighbour of ``start`` within
    ``max_angle_deg`` of the trunk ``direction``; failing that, the
    neighbour best aligned with it; ``start`` itself when it has none.
    """
    nb = adjacency.indices[adjacency.indptr[start]:adjacency.indptr[start + 1]].astype(np.int64)
    vec = points[nb] - points[start]
    dist = np.linalg.norm(vec, axis=1)
    nb, vec, dist = nb[dist > 1e-9], vec[dist > 1e-9], dist[dist > 1e-9]   # not a copy of the root
    if len(nb) == 0:
        return start
    cosang = (vec @ direction) / np.maximum(dist, 1e-12)
    inside = cosang > np.cos(np.radians(max_angle_deg))
    if inside.any():
        cand = np.flatnonzero(inside)
        return int(nb[cand[np.lexsort((cand, dist[cand]))[0]]])
    return int(nb[int(np.argmax(cosang))])


@dataclass(frozen=True)
class GreedySkeleton:
    """Hu et al. (2017) airborne tree skeleton: trunk points, thinning, graph, direction field, greedy tree.

    Parameters (defaults from §6.2 / Table 1 unless noted):

    * ``voxel_m`` d_l, thinning voxel pitch (§5.1), 0.2 m;
    * ``radius_m`` r_p, FRNN radius of the graph (§5.2), 1.2 m;
    * ``k`` kNN neighbours for points with fewer than k within r_p (§5.2).
      Table 1 gives 10–30 "according to r_p"; Sylva uses 30, the top of
      that range, because its airborne data are sparser (10–20 pts/m², and
      about 5 in lidR's MixedConifer tile) than the paper's 40 pts/m², so
      fewer candidates fall within r_p and the kNN pass must reach further
      to bridge gaps.  Measured with benchmarks/reconstruction.py (seed 2),
      k = 16 → 30 raised the median visited fraction from 0.85 to 0.94
      (synthetic stand, 10 pulses/m²), 0.88 → 0.94 (20 pulses/m²) and
      0.51 → 0.80 (MixedConifer), and the share of trees passing the
      paper's hybrid test (connected, ≥ 85 % visited) from 50 % to 81 %,
      63 % to 85 % and 0 % to 24 %, for about 1.3–1.6× the time;
    * ``theta_upper_deg`` θ_u = 80°, ``theta_lower_deg`` θ_l = −40°,
      ``k1`` = 1.4, ``k2`` = 1.0: direction field (§5.3, Eq. 5);
    * ``alpha_max_deg`` α_max = 70°, ``beta_max_deg`` β_max = 70°,
      ``phi_max_deg`` φ_max = 30° (§5.4);
    * ``lambda1_max_deg`` λ1 ≤ 30°, ``lambda2_max`` λ2 ≤ 0.5: Eq. 3 vs Eq. 4 (§4.2);
    * ``trunk_radius_m`` r, neighbourhood of the lowest point in §4.2 (not
      given by the paper: 1.0 m); ``trunk_spacing_m`` spacing of added
      trunk points (not given: 0.1 m, half of d_l, so the trunk stays one
      26-connected run of voxels);
    * ``min_points`` fewer (distinct) points than this give a minimal
      skeleton and a flag (Sylva, not the paper: 10);
    * ``min_visited_fraction`` below this share of visited candidates, or
      with a disconnected graph, the result is flagged ``"needs_fallback"``
      (§6.2: 85 %, the hybrid threshold);
    * ``regrow_pruned`` let pruned candidates beyond the kept child be
      reached again (Sylva; see :func:`greedy_skeleton`; False = Algorithm 2
      verbatim).
    """

    voxel_m: float = 0.2
    radius_m: float = 1.2
    k: int = 30
    theta_upper_deg: float = 80.0
    theta_lower_deg: float = -40.0
    k1: float = 1.4
    k2: float = 1.0
    alpha_max_deg: float = 70.0
    beta_max_deg: float = 70.0
    phi_max_deg: float = 30.0
    lambda1_max_deg: float = 30.0
    lambda2_max: float = 0.5
    trunk_radius_m: float = 1.0
    trunk_spacing_m: float = 0.1
    min_points: int = 10
    min_visited_fraction: float = 0.85
    regrow_pruned: bool = True

    name = "greedy_skeleton"

    def __post_init__(self):
        positive = ("voxel_m", "radius_m", "k1", "k2", "trunk_radius_m", "trunk_spacing_m")
        for attr in positive:
            if not getattr(self, attr) > 0:
                raise InputError(f"GreedySkeleton: {attr} must be positive, got {getattr(self, attr)!r}")
        if int(self.k) != self.k or self.k < 1:
            raise InputError(f"GreedySkeleton: k must be a whole number of neighbours >= 1, got {self.k!r}")
        for attr in ("alpha_max_deg", "beta_max_deg", "phi_max_deg", "lambda1_max_deg"):
            if not 0 < getattr(self, attr) <= 180:
                raise InputError(f"GreedySkeleton: {attr} must be in (0, 180] degrees, got {getattr(self, attr)!r}")
        if not -90 <= self.theta_lower_deg <= 90 or not -90 <= self.theta_upper_deg <= 90:
            raise InputError("GreedySkeleton: theta_upper_deg and theta_lower_deg must be in [-90, 90] degrees")
        if self.lambda2_max < 0 or not 0 <= self.min_visited_fraction <= 1:
            raise InputError("GreedySkeleton: lambda2_max must be >= 0 and min_visited_fraction in [0, 1]")

    # -- degenerate input ---------------------------------------------------

    def reconstruct(self, tree: TreePoints, progress: Progress = None,
                    cancelled: CancelCheck = None) -> Reconstruction:
        """Run §4.2 → §5.4 on one tree; see :func:`sylva.core.reconstruct.reconstruct_tree`."""
        t_all = time.perf_counter()
        xyz = tree.xyz
        ground_z, flags, degenerate = screen(tree, self.min_points, self.name, progress)
        if degenerate is not None:
            return degenerate
        stats = {"n_points": int(len(xyz))}

        check(cancelled)
        t0 = time.perf_counter()
        trunk = add_trunk_points(xyz, ground_z, self.trunk_radius_m, self.trunk_spacing_m,
                                 self.lambda1_max_deg, self.lambda2_max)
        stats.update(t_trunk_s=time.perf_counter() - t0, n_added=int(len(trunk.points)),
                     trunk_rule=trunk.rule, lambda1_deg=trunk.lambda1_deg, lambda2=trunk.lambda2)
        report(progress, 0.1, "trunk points")

        check(cancelled)
        t0 = time.perf_counter()
        added = trunk.points[1:]                      # the root joins the candidates on its own
        all_xyz = np.concatenate([xyz, added])
        is_added_pt = np.r_[np.zeros(len(xyz), bool), np.ones(len(added), bool)]
        thin = thin_voxels(all_xyz, self.voxel_m, keep=is_added_pt)
        measured = np.bincount(thin.voxel_of_point[~is_added_pt], minlength=len(thin.voxel_means))
        cand = np.concatenate([trunk.root[None, :], thin.points])
        cand_added = np.r_[True, measured[thin.voxel_index] == 0]
        stats.update(t_thinning_s=time.perf_counter() - t0, n_voxels=int(len(thin.voxel_means)),
                     n_candidates=int(len(cand)), thinning_passes=int(thin.passes))
        report(progress, 0.3, "thinning")

        check(cancelled)
        t0 = time.perf_counter()
        graph = build_graph(cand, self.radius_m, self.k)
        stats.update(t_graph_s=time.perf_counter() - t0, n_edges=graph.n_edges,
                     n_components=graph.n_components, n_knn=graph.n_knn)
        report(progress, 0.5, "graph")

        check(cancelled)
        t0 = time.perf_counter()
        u = direction_field(cand, self.theta_upper_deg, self.theta_lower_deg, self.k1, self.k2)
        u[cand_added] = trunk.direction        # added trunk points grow along the trunk (§4.2)
        stats["t_direction_s"] = time.perf_counter() - t0
        report(progress, 0.6, "direction field")

        check(cancelled)
        t0 = time.perf_counter()
        end = choose_end(cand, graph.adjacency, 0, trunk.direction, self.alpha_max_deg)
        res = greedy_skeleton(cand, graph.adjacency, u, 0, end, self.alpha_max_deg,
                              self.beta_max_deg, self.phi_max_deg, self.regrow_pruned)
        skel = Skeleton(cand[res.point_of_node], res.parent, is_added=cand_added[res.point_of_node])
        stats["t_skeleton_s"] = time.perf_counter() - t0
        # Visited share over the candidates that hold measured points: the added
        # trunk is reached by construction and would only flatter the figure.
        meas = ~cand_added
        visited = float(res.visited[meas].mean()) if meas.any() else 0.0
        stats.update(n_nodes=int(len(skel)), n_visited=int(res.visited.sum()),
                     visited_fraction_all=float(res.visited.mean()),
                     t_total_s=time.perf_counter() - t_all)
        if end == 0:
            flags.append("isolated_root")
        if not graph.connected:
            flags.append("graph_disconnected")
        if not graph.connected or visited < self.min_visited_fraction:
            flags.append("needs_fallback")
        report(progress, 1.0, "skeleton")
        return Reconstruction(skel, self.name, visited, graph.connected, stats, flags, tree.tree_id)
