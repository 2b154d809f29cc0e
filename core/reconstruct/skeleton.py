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

The loop is inherently sequential (each expansion depends on what earlier
ones visited), so it runs as a compiled kernel (:mod:`sylva.core.jit`,
numba) over the CSR arrays: a binary heap for Q, the pruning walk of
Fig. 14b as a double loop.  tests/test_skeleton_kernel.py checks its
result against the algorithm's rules (a tree over graph edges, α, β and φ
respected, nothing admissible left unvisited without regrowth).  The other
steps are kernels too (graph, voxels and thinning, trunk statistics,
screening); the method hands the graph's CSR arrays to the loop without
building a scipy matrix.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ..errors import InputError
from ..jit import njit
from ..progress import CancelCheck, Progress, check, report
from .direction import direction_field
from .graph import graph_arrays
from .model import Reconstruction, Skeleton, TreePoints, screen
from .thinning import thin_voxels
from .trunk import add_trunk_points


class GreedyResult(NamedTuple):
    """Result of :func:`greedy_skeleton`."""

    point_of_node: np.ndarray   # (m,) candidate point index of each skeleton node (node 0 = start)
    parent: np.ndarray          # (m,) parent node, -1 for the root, parents before children
    visited: np.ndarray         # (n,) candidate points reached (kept or pruned)
    alpha_deg: np.ndarray       # (m,) bending angle of each node's segment to its parent's (nan at the root/end)


@njit
def _greedy_kernel(points, indptr, indices, directions, start, end, v0, cos_a, cos_b, cos_p, regrow):
    """Algorithm 2's loop (see :func:`greedy_skeleton`); plain loops for numba.

    Returns (point_of_node, parent, cos α of each node's segment (nan for the
    first segment), all three of the returned node count, visited).  Dot products are written out as
    (x·x' + y·y') + z·z' everywhere, so the results do not depend on a BLAS.
    """
    n = points.shape[0]
    visited = np.zeros(n, np.bool_)
    node_of_point = np.empty(n, np.int64)
    for i in range(n):
        node_of_point[i] = -1
    point_of_node = np.empty(n, np.int64)
    parent = np.empty(n, np.int64)
    node_cos = np.empty(n)
    visited[start] = True
    visited[end] = True
    point_of_node[0] = start
    parent[0] = -1
    node_cos[0] = np.nan
    node_of_point[start] = 0
    nodes = 1
    # Q: binary heap of (key, counter, point j, unit segment u to j); key = -cos α
    # (α ascending), the counter makes equal keys first in, first out.
    h_key = np.empty(n + 1)
    h_cnt = np.empty(n + 1, np.int64)
    h_j = np.empty(n + 1, np.int64)
    h_u = np.empty((n + 1, 3))
    hs = 0
    if end != start:
        point_of_node[1] = end
        parent[1] = 0
        node_cos[1] = np.nan
        node_of_point[end] = 1
        nodes = 2
        h_key[0] = 0.0
        h_cnt[0] = 0
        h_j[0] = end
        h_u[0, 0] = v0[0]
        h_u[0, 1] = v0[1]
        h_u[0, 2] = v0[2]
        hs = 1
    counter = 1
    deg = 0
    for i in range(n):
        deg = max(deg, indptr[i + 1] - indptr[i])
    # the row of the point expanded (each point is expanded at most once)
    e_j = np.empty(deg, np.int64)
    e_u = np.empty((deg, 3))
    e_len = np.empty(deg)
    c_edge = np.empty(deg, np.int64)
    c_cos = np.empty(deg)
    c_rank = np.empty(deg)
    alive = np.empty(deg, np.bool_)
    while hs > 0:
        # pop the smallest (key, counter)
        i = h_j[0]
        vx = h_u[0, 0]
        vy = h_u[0, 1]
        vz = h_u[0, 2]
        hs -= 1
        if hs > 0:
            k_last = h_key[hs]
            c_last = h_cnt[hs]
            pos = 0
            while True:
                ch = 2 * pos + 1
                if ch >= hs:
                    break
                r = ch + 1
                if r < hs and (h_key[r] < h_key[ch] or (h_key[r] == h_key[ch] and h_cnt[r] < h_cnt[ch])):
                    ch = r
                if h_key[ch] < k_last or (h_key[ch] == k_last and h_cnt[ch] < c_last):
                    h_key[pos] = h_key[ch]
                    h_cnt[pos] = h_cnt[ch]
                    h_j[pos] = h_j[ch]
                    h_u[pos, 0] = h_u[ch, 0]
                    h_u[pos, 1] = h_u[ch, 1]
                    h_u[pos, 2] = h_u[ch, 2]
                    pos = ch
                else:
                    break
            h_key[pos] = k_last
            h_cnt[pos] = c_last
            h_j[pos] = h_j[hs]
            h_u[pos, 0] = h_u[hs, 0]
            h_u[pos, 1] = h_u[hs, 1]
            h_u[pos, 2] = h_u[hs, 2]
        # the unvisited neighbours j of i that pass β_j < β_max, by decreasing
        # length (stable), with their unit vectors
        m = 0
        for e in range(indptr[i], indptr[i + 1]):
            j = indices[e]
            if visited[j]:
                continue
            dx = points[j, 0] - points[i, 0]
            dy = points[j, 1] - points[i, 1]
            dz = points[j, 2] - points[i, 2]
            ln = math.sqrt(dx * dx + dy * dy + dz * dz)
            if not ln > 1e-12:
                continue
            ux = dx / ln
            uy = dy / ln
            uz = dz / ln
            if ux * directions[j, 0] + uy * directions[j, 1] + uz * directions[j, 2] > cos_b:
                q = m - 1                           # insertion sort: stable, rows are short
                while q >= 0 and e_len[q] < ln:
                    e_j[q + 1] = e_j[q]
                    e_u[q + 1, 0] = e_u[q, 0]
                    e_u[q + 1, 1] = e_u[q, 1]
                    e_u[q + 1, 2] = e_u[q, 2]
                    e_len[q + 1] = e_len[q]
                    q -= 1
                e_j[q + 1] = j
                e_u[q + 1, 0] = ux
                e_u[q + 1, 1] = uy
                e_u[q + 1, 2] = uz
                e_len[q + 1] = ln
                m += 1
        # candidates: α_j < α_max (β_j < β_max already holds)
        c = 0
        for e in range(m):
            cs = e_u[e, 0] * vx + e_u[e, 1] * vy + e_u[e, 2] * vz
            if cs > cos_a:
                c_edge[c] = e
                c_cos[c] = cs
                c_rank[c] = -np.rint(cs * 1e12)
                c += 1
        if c == 0:
            continue
        for t in range(c):
            visited[e_j[c_edge[t]]] = True
        # α ascending, cos α equal to 1e-12 counting as a tie (stable: the longer first)
        for t in range(1, c):
            ke = c_edge[t]
            kc = c_cos[t]
            kr = c_rank[t]
            q = t - 1
            while q >= 0 and c_rank[q] > kr:
                c_edge[q + 1] = c_edge[q]
                c_cos[q + 1] = c_cos[q]
                c_rank[q + 1] = c_rank[q]
                q -= 1
            c_edge[q + 1] = ke
            c_cos[q + 1] = kc
            c_rank[q + 1] = kr
        # pruning (Fig. 14b): each candidate still alive is kept and removes the
        # alive ones within φ_max of it; with regrow, those farther are released.
        for t in range(c):
            alive[t] = True
        parent_node = node_of_point[i]
        for t in range(c):
            if not alive[t]:
                continue
            el = c_edge[t]
            if c > 1:
                lx = e_u[el, 0]
                ly = e_u[el, 1]
                lz = e_u[el, 2]
                for q in range(c):
                    if alive[q]:
                        eq = c_edge[q]
                        if lx * e_u[eq, 0] + ly * e_u[eq, 1] + lz * e_u[eq, 2] > cos_p:
                            alive[q] = False
                            if regrow and e_len[eq] > e_len[el]:
                                visited[e_j[eq]] = False
            # keep t: a new node, pushed with key -cos α
            j = e_j[el]
            node_of_point[j] = nodes
            point_of_node[nodes] = j
            parent[nodes] = parent_node
            node_cos[nodes] = c_cos[t]
            nodes += 1
            key = -min(c_cos[t], 1.0)
            pos = hs
            hs += 1
            while pos > 0:
                up = (pos - 1) // 2
                if key < h_key[up] or (key == h_key[up] and counter < h_cnt[up]):
                    h_key[pos] = h_key[up]
                    h_cnt[pos] = h_cnt[up]
                    h_j[pos] = h_j[up]
                    h_u[pos, 0] = h_u[up, 0]
                    h_u[pos, 1] = h_u[up, 1]
                    h_u[pos, 2] = h_u[up, 2]
                    pos = up
                else:
                    break
            h_key[pos] = key
            h_cnt[pos] = counter
            h_j[pos] = j
            h_u[pos, 0] = e_u[el, 0]
            h_u[pos, 1] = e_u[el, 1]
            h_u[pos, 2] = e_u[el, 2]
            counter += 1
    return point_of_node[:nodes], parent[:nodes], node_cos[:nodes], nodes, visited


def greedy_skeleton(points: np.ndarray, adjacency, directions: np.ndarray, start: int, end: int,
                    alpha_max_deg: float = 70.0, beta_max_deg: float = 70.0,
                    phi_max_deg: float = 30.0, regrow_pruned: bool = True) -> GreedyResult:
    """Hu et al. §5.4, Algorithm 2: greedy tree over ``adjacency`` from segment start → end.

    ``points`` (n, 3) candidate points, ``adjacency`` the CSR graph of
    :func:`~.graph.build_graph` (or its :class:`~.graph.CSRArrays`),
    ``directions`` (n, 3) unit vectors u_j from
    :func:`~.direction.direction_field`.  Pure function; the loop is a
    compiled kernel (:mod:`sylva.core.jit`).  β_j does not depend on the
    parent segment: it is tested when p_i is expanded (each point is at most
    once), for its unvisited neighbours only.

    Q is keyed by α/α_max in the paper; the kernel keys it by −cos α, the
    same order (arccos is decreasing) without an arccos per push.  Ties go
    first in, first out (cos α ≥ 1 is clamped to 1, so collinear segments
    tie); candidates are sorted by α ascending with cos α equal to 1e-12
    counting as a tie, broken by the longer segment (a straight run then
    advances by up to r_p instead of stalling among points its predecessor
    already visited).  Dot products are evaluated as (x·x' + y·y') + z·z'.

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
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    directions = np.ascontiguousarray(directions, dtype=np.float64).reshape(-1, 3)
    n = len(points)
    if len(directions) != n or adjacency.shape != (n, n):
        raise InputError(f"greedy_skeleton: {n} points, {len(directions)} directions and a "
                         f"{adjacency.shape} adjacency do not match")
    start, end = int(start), int(end)
    first_seg = points[end] - points[start]
    v0 = first_seg / np.linalg.norm(first_seg) if end != start else np.zeros(3)
    pon, parent, cos_alpha, m, visited = _greedy_kernel(
        points, adjacency.indptr, adjacency.indices, directions, start, end, v0,
        float(np.cos(np.radians(alpha_max_deg))), float(np.cos(np.radians(beta_max_deg))),
        float(np.cos(np.radians(phi_max_deg))), bool(regrow_pruned))
    pon, parent, cos_alpha = pon[:m].copy(), parent[:m].copy(), cos_alpha[:m]
    alpha = np.full(m, np.nan)
    grown = slice(2 if end != start else 1, None)
    alpha[grown] = np.degrees(np.arccos(np.minimum(cos_alpha[grown], 1.0)))   # cos > cos α_max > -1
    return GreedyResult(pon, parent, visited, alpha)


def load_kernels() -> float:
    """Compile, or load from numba's cache, the kernels of :class:`GreedySkeleton`; returns the seconds taken.

    The first tree reconstructed in a process does this anyway; a parent
    process can call it once before starting its workers, so that on a
    fresh install the workers find the cache written instead of each
    compiling the kernels (see :mod:`sylva.core.jit`).
    """
    t0 = time.perf_counter()
    rng = np.random.default_rng(0)
    xyz = rng.random((200, 3)) * [3.0, 3.0, 8.0] + [0.0, 0.0, 2.0]
    GreedySkeleton().reconstruct(TreePoints(0, xyz, 0.0))
    return time.perf_counter() - t0


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
        is_added_pt = np.zeros(len(all_xyz), bool)
        is_added_pt[len(xyz):] = True
        thin = thin_voxels(all_xyz, self.voxel_m, keep=is_added_pt)
        measured = np.bincount(thin.voxel_of_point[:len(xyz)], minlength=len(thin.voxel_means))
        cand = np.concatenate([trunk.root[None, :], thin.points])
        cand_added = np.concatenate([[True], measured[thin.voxel_index] == 0])
        stats.update(t_thinning_s=time.perf_counter() - t0, n_voxels=int(len(thin.voxel_means)),
                     n_candidates=int(len(cand)), thinning_passes=int(thin.passes))
        report(progress, 0.3, "thinning")

        check(cancelled)
        t0 = time.perf_counter()
        graph = graph_arrays(cand, self.radius_m, self.k)       # the CSR arrays, no scipy matrix
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
