"""Branch geometry: radii, branch chains, smoothing and generalised cylinders.

From a :class:`~sylva.core.reconstruct.model.Skeleton` (nodes, parents) to a
closed triangle mesh of the wood, following Hu et al. 2017 §5.5 ("Branch
geometry"):

1. **Radii.**  :func:`pipe_model_radii` — the pipe model, Hu et al. Eq. 6
   (``R_up,i^2 = sum_j R_low,j^2``, ``R_low,i = R_up,i``,
   ``R_up,tip = R_const``), generalised to any exponent ``e``;
   :func:`allometric_radii` — Guo et al. 2018 §5.1 Eq. 5
   (``d_ci = d_p (l_ci / sum_j l_cj)^gamma``) root to tip.
2. **Branches.**  :func:`branches` — chains from the root or a branching node
   to a tip; at a branching node the chain continues into the child that
   bends least (Hu §5.5: "branches with a small change of thickness and
   bending angle"), so the trunk is one chain.
3. **Smoothing.**  :func:`hermite_smooth` — cubic Hermite curves through the
   chain's nodes (Hu §5.5; Catmull-Rom tangents), radii interpolated along.
4. **Generalised cylinders.**  :func:`sweep_tube` — a polygon swept along any
   centre line with per-point radii, oriented by rotation-minimising frames
   computed with the double reflection method of Wang, Jüttler, Zheng & Liu,
   "Computation of rotation minimizing frames", ACM Trans. Graph. 27(1), 2008
   (the frames Yan et al. 2009 §4.2 use for lofting, so a B-spline centre line
   can be swept with the same function).
5. **Tree mesh.**  :func:`tree_mesh` — every branch a closed tube (caps at
   both ends), side branches starting on their parent's axis so the union
   looks joined; :class:`LevelOfDetail` trades sides, smoothing samples and
   pruned twigs.

Measurements for the trees table: :func:`wood_volume` (frusta between
nodes), :func:`branch_count`, :func:`total_branch_length`.

All loops over nodes are vectorised: per-depth-level passes for radii,
pointer jumping for chains, and one segmented parallel prefix product of the
double-reflection rotations for the frames of all tubes at once.  The batch
forms :func:`branches_batch`, :func:`simplify_skeletons`,
:func:`tree_mesh_arrays_batch` and :func:`tree_meshes` run the same passes over
many trees joined into one forest (every step works per node, per chain or
per polyline), so each tree gets exactly what the single-tree call gives it.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator, List, Optional, Tuple, Union

import numpy as np

from .errors import InputError
from .reconstruct.model import Skeleton

__all__ = [
    "PipeModel", "Allometric", "assign_radii", "pipe_model_radii", "allometric_radii",
    "with_radii", "BranchSet", "branches", "branches_batch", "hermite_smooth", "rotation_minimizing_frames",
    "sweep_tube", "LevelOfDetail", "LOD", "tree_mesh", "tree_meshes", "TreeMeshParts", "tree_mesh_arrays",
    "tree_mesh_arrays_batch",
    "wood_volume", "branch_count", "total_branch_length", "depth_levels", "simplify_skeleton",
    "simplify_skeletons",
]

_EPS = 1e-9


# --------------------------------------------------------------------------- tree passes

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


def _subtree_sum(parent: np.ndarray, values: np.ndarray, levels: List[np.ndarray]) -> np.ndarray:
    """Sum of ``values`` over each node's subtree (node included): deepest level first."""
    acc = np.array(values, dtype=np.float64, copy=True)
    for idx in reversed(levels[1:]):
        np.add.at(acc, parent[idx], acc[idx])
    return acc


def _check_skeleton(skeleton) -> Skeleton:
    if not isinstance(skeleton, Skeleton):
        raise InputError(f"expected a Skeleton, got {type(skeleton).__name__}")
    return skeleton


def _tree_name(skeleton) -> str:
    tid = getattr(skeleton, "tree_id", None)
    return f"tree {tid}" if tid is not None else "skeleton"


# --------------------------------------------------------------------------- radii

@dataclass(frozen=True)
class PipeModel:
    """Pipe-model radii, Hu et al. 2017 §5.5 Eq. 6 (Shinozaki et al. 1964).

    ``tip_radius_m`` is R_const, the radius of a branch tip (user defined in
    the paper; 1 cm here); ``exponent`` the pipe exponent e in
    ``r_parent^e = sum r_child^e`` (2 in Eq. 6, da Vinci's rule);
    ``trunk_radius_m`` if given rescales all radii so that the root has it
    (e.g. DBH/2 from a measurement or an allometric estimate).
    """

    tip_radius_m: float = 0.01
    exponent: float = 2.0
    trunk_radius_m: Optional[float] = None


@dataclass(frozen=True)
class Allometric:
    """Allometric radii, Guo et al. 2018 §5.1 Eq. 5, from a known root radius.

    ``root_radius_m`` is d_root/2; ``gamma`` the diameter coefficient γ
    (0.5 makes cross-sections proportional to supported length, da Vinci's
    area rule); ``min_radius_m`` an optional floor for the thinnest twigs.
    """

    root_radius_m: float = 0.15
    gamma: float = 0.5
    min_radius_m: float = 0.0


def pipe_model_radii(skeleton: Skeleton, tip_radius_m: float = 0.01, exponent: float = 2.0,
                     trunk_radius_m: Optional[float] = None, inplace: bool = False) -> np.ndarray:
    """Node radii by the pipe model, Hu et al. 2017 §5.5 Eq. 6.

    Eq. 6 sets every tip to ``R_const`` and every parent segment to
    ``R_up,i^2 = sum_j R_low,j^2`` over its child segments.  Here a node's
    radius is the pipe radius at that node (all pipes of its subtree pass
    through it), so with exponent ``e``::

        r_tip = tip_radius_m,      r_i^e = sum_{children c} r_c^e

    which telescopes to ``r_i = tip_radius_m * N_i^(1/e)`` with ``N_i`` the
    number of tips in the subtree of ``i`` — computed with one vectorised
    pass per depth level.  Radii are therefore non-increasing from the root to
    the tips, and the frustum between a node and its child tapers as Hu's
    "adjusted upper radius" does.  With ``trunk_radius_m`` all radii are scaled
    by one factor so the root radius equals it (the relation is homogeneous,
    so Eq. 6 still holds exactly).  Returns a new (m,) array; with
    ``inplace=True`` also stores it in ``skeleton.radius``.
    """
    skeleton = _check_skeleton(skeleton)
    if not (np.isfinite(tip_radius_m) and tip_radius_m > 0):
        raise InputError(f"{_tree_name(skeleton)}: tip_radius_m must be > 0 m, got {tip_radius_m}")
    if not (np.isfinite(exponent) and exponent > 0):
        raise InputError(f"{_tree_name(skeleton)}: pipe-model exponent must be > 0, got {exponent}")
    m = len(skeleton)
    if m == 0:
        return np.zeros(0)
    tips = (skeleton.n_children() == 0).astype(np.float64)
    n_tips = _subtree_sum(skeleton.parent, tips, depth_levels(skeleton))
    radii = tip_radius_m * n_tips ** (1.0 / exponent)
    if trunk_radius_m is not None:
        if not (np.isfinite(trunk_radius_m) and trunk_radius_m > 0):
            raise InputError(f"{_tree_name(skeleton)}: trunk_radius_m must be > 0 m, got {trunk_radius_m}")
        radii *= trunk_radius_m / radii[skeleton.root]
    if inplace:
        skeleton.radius = radii.copy()
    return radii


def allometric_radii(skeleton: Skeleton, root_radius_m: float = 0.15, gamma: float = 0.5,
                     min_radius_m: float = 0.0, inplace: bool = False) -> np.ndarray:
    """Node radii by the allometric rule of Guo et al. 2018 §5.1, Eq. 5, root to tip.

    ``d_c = d_p (l_c / sum_j l_cj)^gamma`` for every child ``c`` of ``p``,
    where ``l_c`` is the total branch length the child supports: the length
    of its subtree plus its own segment from ``p``.  The root gets
    ``root_radius_m`` (Guo measures d_root from the points at the plant base);
    a single child keeps its parent's radius.  ``min_radius_m`` floors the
    result.  Vectorised: subtree lengths by a reverse pass per depth level,
    then products of the ratios by a forward pass per depth level.
    """
    skeleton = _check_skeleton(skeleton)
    if not (np.isfinite(root_radius_m) and root_radius_m > 0):
        raise InputError(f"{_tree_name(skeleton)}: root_radius_m must be > 0 m, got {root_radius_m}")
    if not (np.isfinite(gamma) and gamma >= 0):
        raise InputError(f"{_tree_name(skeleton)}: gamma must be >= 0, got {gamma}")
    m = len(skeleton)
    if m == 0:
        return np.zeros(0)
    parent = skeleton.parent
    levels = depth_levels(skeleton)
    child, par = skeleton.segments()
    seg = np.zeros(m)
    seg[child] = np.linalg.norm(skeleton.nodes[child] - skeleton.nodes[par], axis=1)
    supported = _subtree_sum(parent, seg, levels)          # subtree length incl. own segment
    sibling_total = np.zeros(m)
    np.add.at(sibling_total, par, supported[child])
    ratio = np.ones(m)
    tot = sibling_total[par]
    ok = tot > 0
    # zero-length children (duplicate nodes) share equally
    nsib = np.bincount(par, minlength=m)[par]
    ratio[child] = np.where(ok, supported[child] / np.where(ok, tot, 1.0), 1.0 / nsib)
    factor = ratio ** gamma
    radii = np.empty(m)
    radii[levels[0]] = root_radius_m
    for idx in levels[1:]:
        radii[idx] = radii[parent[idx]] * factor[idx]
    if min_radius_m > 0:
        radii = np.maximum(radii, min_radius_m)
    if inplace:
        skeleton.radius = radii.copy()
    return radii


def assign_radii(skeleton: Skeleton, method: Union[PipeModel, Allometric] = PipeModel(),
                 inplace: bool = False) -> np.ndarray:
    """Radii of ``skeleton`` by ``method`` (:class:`PipeModel` or :class:`Allometric`)."""
    if isinstance(method, PipeModel):
        return pipe_model_radii(skeleton, method.tip_radius_m, method.exponent,
                                method.trunk_radius_m, inplace=inplace)
    if isinstance(method, Allometric):
        return allometric_radii(skeleton, method.root_radius_m, method.gamma,
                                method.min_radius_m, inplace=inplace)
    raise InputError(f"unknown radius method {method!r}: use PipeModel(...) or Allometric(...)")


def with_radii(skeleton: Skeleton, radii: np.ndarray) -> Skeleton:
    """A copy of ``skeleton`` whose ``radius`` is ``radii`` (the input is not changed)."""
    skeleton = _check_skeleton(skeleton)
    radii = np.asarray(radii, dtype=np.float64).reshape(-1)
    if len(radii) != len(skeleton):
        raise InputError(f"{_tree_name(skeleton)}: {len(radii)} radii for {len(skeleton)} skeleton nodes")
    if not np.all(np.isfinite(radii)) or (radii < 0).any():
        raise InputError(f"{_tree_name(skeleton)}: radii must be finite and >= 0 m")
    return Skeleton(skeleton.nodes.copy(), skeleton.parent.copy(), radii.copy(),
                    skeleton.is_added.copy())


def _radii_or_default(skeleton: Skeleton, radii) -> np.ndarray:
    if radii is not None:
        r = np.asarray(radii, dtype=np.float64).reshape(-1)
        if len(r) != len(skeleton):
            raise InputError(f"{_tree_name(skeleton)}: {len(r)} radii for {len(skeleton)} skeleton nodes")
        if not np.all(np.isfinite(r)) or (r < 0).any():
            raise InputError(f"{_tree_name(skeleton)}: radii must be finite and >= 0 m")
        return r
    if len(skeleton) and np.any(skeleton.radius > 0):
        return skeleton.radius
    return pipe_model_radii(skeleton) if len(skeleton) else np.zeros(0)


# --------------------------------------------------------------------------- branches

@dataclass
class BranchSet:
    """A skeleton decomposed into branch chains (Hu et al. §5.5).

    ``chains[b]`` are the node indices of branch ``b`` from its attachment
    node (the branching node it leaves, shared with the parent branch) to its
    tip; branch 0 is the trunk and starts at the root.  ``parent[b]`` is the
    index of the branch it leaves (-1 for the trunk), ``attach[b]`` the
    attachment node (-1 for the trunk), ``node_branch[i]`` the branch that owns
    node ``i`` (the attachment node belongs to the parent branch), ``order[b]``
    the branching order (trunk 0).  Behaves as a sequence of the chains.

    The chains are stored flat: ``nodes`` is their concatenation and
    ``offsets`` (n_branches + 1,) the start of each (chain ``b`` is
    ``nodes[offsets[b]:offsets[b + 1]]``), so batched consumers need no
    Python loop; the list ``chains`` is built on first use.
    """

    nodes: np.ndarray
    offsets: np.ndarray
    parent: np.ndarray
    attach: np.ndarray
    node_branch: np.ndarray
    order: np.ndarray
    continuation: np.ndarray  # per node: the child its chain continues into (-1 at tips)

    @property
    def chains(self) -> List[np.ndarray]:
        c = self.__dict__.get("_chains")
        if c is None:
            nodes, off = self.nodes, self.offsets.tolist()
            c = self.__dict__["_chains"] = [nodes[a:b] for a, b in zip(off[:-1], off[1:])]
        return c

    @property
    def lengths(self) -> np.ndarray:
        """Number of nodes of every chain."""
        return np.diff(self.offsets)

    def __len__(self) -> int:
        return len(self.offsets) - 1

    def __getitem__(self, b):
        return self.chains[b]

    def __iter__(self) -> Iterator[np.ndarray]:
        return iter(self.chains)


def _continuation_cos(skeleton: Skeleton):
    """(child, parent, cos) per segment: cosine of the bend from the incoming segment, rounded to 9 digits."""
    return _continuation_cos_arrays(skeleton.nodes, skeleton.parent)


def _continuation_cos_arrays(nodes: np.ndarray, parent: np.ndarray):
    """:func:`_continuation_cos` of node / parent arrays (one tree or a forest of concatenated trees)."""
    child = np.flatnonzero(parent >= 0)
    par = parent[child]
    if len(child) == 0:
        return child, par, np.zeros(0)
    gp = parent[par]
    incoming = np.where((gp >= 0)[:, None], nodes[par] - nodes[np.maximum(gp, 0)], [0.0, 0.0, 1.0])
    out = nodes[child] - nodes[par]
    cos = (incoming * out).sum(axis=1) / np.maximum(
        np.linalg.norm(incoming, axis=1) * np.linalg.norm(out, axis=1), 1e-12)
    return child, par, np.round(cos, 9)  # exact ties are decided by radius, then by index


def _continuation_from_cos(m: int, child, par, cos, radii: Optional[np.ndarray] = None) -> np.ndarray:
    cont = np.full(m, -1, dtype=np.int64)
    if len(child) == 0:
        return cont
    r = radii[child] if radii is not None else np.zeros(len(child))
    order = np.lexsort((-child, r, cos, par))
    p_sorted = par[order]
    last = np.r_[np.flatnonzero(np.diff(p_sorted)), len(order) - 1]
    cont[p_sorted[last]] = child[order][last]
    return cont


def _continuation_child(skeleton: Skeleton, radii: Optional[np.ndarray] = None) -> np.ndarray:
    """Per node, the child with the smallest bending angle (ties: the thicker one), or -1."""
    return _continuation_from_cos(len(skeleton), *_continuation_cos(skeleton), radii)


def branches(skeleton: Skeleton, radii: Optional[np.ndarray] = None) -> BranchSet:
    """Decompose ``skeleton`` into branch chains, Hu et al. 2017 §5.5.

    Every chain runs from the root or a branching node to a tip; at each
    branching node it continues into the child whose direction bends least
    from the incoming segment (the root's incoming direction is +z; exact
    ties go to the thicker child by ``radii``), so the trunk is one chain and
    every segment belongs to exactly one chain.  Chains are numbered by their
    first own node, so a parent branch always precedes its children.
    Vectorised (pointer jumping to each chain's head).
    """
    skeleton = _check_skeleton(skeleton)
    return _branch_set(skeleton.parent, _continuation_child(skeleton, radii))


def branches_batch(skeletons, radii=None) -> List[BranchSet]:
    """:func:`branches` of many skeletons (``radii`` None or one entry per skeleton), in one vectorised pass.

    The skeletons are joined into one forest; every step works per node, per parent or per
    chain, so each tree gets the :class:`BranchSet` of ``branches(skeleton, radii)``.
    """
    skeletons = [_check_skeleton(sk) for sk in skeletons]
    if not skeletons:
        return []
    nodes, parent, off = _forest(skeletons)
    r = None
    if radii is not None and any(x is not None for x in radii):
        r = np.concatenate([np.zeros(len(sk)) if x is None else np.asarray(x, dtype=np.float64).reshape(-1)
                            for sk, x in zip(skeletons, radii)])
    cont = _continuation_from_cos(len(nodes), *_continuation_cos_arrays(nodes, parent), r)
    return _split_branch_set(_branch_set(parent, cont), off)


def _forest(skeletons):
    """(nodes, parent, node offsets) of skeletons joined into one forest (parents shifted, roots -1)."""
    sizes = np.array([len(sk) for sk in skeletons], dtype=np.int64)
    off = np.r_[0, np.cumsum(sizes)]
    nodes = np.concatenate([sk.nodes for sk in skeletons]).reshape(-1, 3)
    parent = np.concatenate([np.where(sk.parent >= 0, sk.parent + o, -1)
                             for sk, o in zip(skeletons, off[:-1].tolist())]).astype(np.int64)
    return nodes, parent, off


def _split_branch_set(bs: BranchSet, node_off: np.ndarray, trees=None) -> List[BranchSet]:
    """The per-tree BranchSets of a forest's BranchSet (trees = node ranges ``node_off``), or of ``trees`` only."""
    nt = len(node_off) - 1
    sizes = np.diff(node_off)
    # first chain of every tree (its root starts one); empty trees own no chain
    first = np.full(nt + 1, len(bs), dtype=np.int64)
    nonempty = np.flatnonzero(sizes > 0)
    first[nonempty] = bs.node_branch[node_off[nonempty]]
    for t in range(nt - 1, -1, -1):      # an empty tree's range starts where the next tree's starts
        if sizes[t] == 0:
            first[t] = first[t + 1]
    first_l, off_l, noff_l = first.tolist(), bs.offsets.tolist(), np.asarray(node_off).tolist()
    out = []
    for t in (range(nt) if trees is None else trees):
        b0, b1 = first_l[t], first_l[t + 1]
        n0, n1 = noff_l[t], noff_l[t + 1]
        c0, c1 = off_l[b0], off_l[b1]
        bpar = bs.parent[b0:b1]
        att = bs.attach[b0:b1]
        cont = bs.continuation[n0:n1]
        out.append(BranchSet(bs.nodes[c0:c1] - n0, bs.offsets[b0:b1 + 1] - c0, np.where(bpar >= 0, bpar - b0, -1),
                             np.where(att >= 0, att - n0, -1), bs.node_branch[n0:n1] - b0, bs.order[b0:b1],
                             np.where(cont >= 0, cont - n0, -1)))
    return out


def _branch_set(parent: np.ndarray, cont: np.ndarray) -> BranchSet:
    """The :class:`BranchSet` of a tree given each node's continuation child (see :func:`branches`)."""
    m = len(parent)
    if m == 0:
        e = np.zeros(0, dtype=np.int64)
        return BranchSet(e, np.zeros(1, dtype=np.int64), e, e, e, e, e)
    idx = np.arange(m)
    is_start = parent < 0
    is_start[~is_start] = cont[parent[~is_start]] != idx[~is_start]
    head = np.where(is_start, idx, parent)
    while True:  # pointer jumping: each node finds the first node of its chain
        nxt = head[head]
        if np.array_equal(nxt, head):
            break
        head = nxt
    starts = np.flatnonzero(is_start)
    node_branch = np.searchsorted(starts, head)
    order = np.lexsort((idx, node_branch))
    counts = np.bincount(node_branch, minlength=len(starts))
    attach = parent[starts].copy()
    bparent = np.where(attach >= 0, node_branch[np.maximum(attach, 0)], -1)
    has = (attach >= 0).astype(np.int64)
    full_off = np.r_[0, np.cumsum(counts + has)]
    full = np.empty(full_off[-1], dtype=np.int64)
    full[full_off[:-1][has == 1]] = attach[has == 1]
    local = np.arange(m) - np.r_[0, np.cumsum(counts)][:-1][node_branch[order]]
    full[full_off[node_branch[order]] + has[node_branch[order]] + local] = order
    border = _depth(bparent.astype(np.int64))   # parents precede children: order = depth in the branch tree
    return BranchSet(full, full_off.astype(np.int64), bparent.astype(np.int64), attach.astype(np.int64),
                     node_branch.astype(np.int64), border, cont)


# --------------------------------------------------------------------------- batched polylines

def _seg_ids(offsets: np.ndarray) -> np.ndarray:
    """Polyline id of every point of a batch given offsets (n_lines + 1,)."""
    return np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))


def _dedupe(points, radii, offsets, eps=_EPS):
    """Drop points equal to the previous point of the same polyline."""
    n = len(points)
    keep = np.ones(n, dtype=bool)
    if n > 1:
        same = np.ones(n, dtype=bool)
        same[offsets[:-1]] = False  # first point of each line is never a duplicate
        d = np.linalg.norm(np.diff(points, axis=0), axis=1)
        keep[1:] = ~(same[1:] & (d <= eps))
    lid = _seg_ids(offsets)[keep]
    counts = np.bincount(lid, minlength=len(offsets) - 1)
    return points[keep], radii[keep], np.r_[0, np.cumsum(counts)], keep


def _tangents(points: np.ndarray, offsets: np.ndarray, unit: bool = True) -> np.ndarray:
    """Finite-difference tangents per polyline (central inside, one-sided at the ends)."""
    n = len(points)
    t = np.zeros_like(points)
    if n == 0:
        return t
    first = np.zeros(n, dtype=bool)
    last = np.zeros(n, dtype=bool)
    first[offsets[:-1][np.diff(offsets) > 0]] = True
    last[offsets[1:][np.diff(offsets) > 0] - 1] = True
    nxt = np.minimum(np.arange(n) + 1, n - 1)
    prv = np.maximum(np.arange(n) - 1, 0)
    nxt = np.where(last, np.arange(n), nxt)
    prv = np.where(first, np.arange(n), prv)
    t = points[nxt] - points[prv]
    if unit:
        norm = np.linalg.norm(t, axis=1, keepdims=True)
        t = t / np.where(norm > 0, norm, 1.0)
    return t


def _hermite_batch(points, radii, offsets, samples):
    """Cubic Hermite (Catmull-Rom tangents, chord-length scaled) through each polyline.

    Returns sampled points, radii and new offsets: a line of k points becomes
    (k - 1) * samples + 1 points through the original ones.
    """
    samples = int(samples)
    if samples <= 1 or len(points) == 0:
        return points, radii, offsets
    n = len(points)
    lid = _seg_ids(offsets)
    k = np.diff(offsets)
    seg_ok = np.zeros(n, dtype=bool)
    seg_ok[:-1] = lid[:-1] == lid[1:]
    s0 = np.flatnonzero(seg_ok)               # segment s0 -> s0 + 1
    d = np.linalg.norm(points[s0 + 1] - points[s0], axis=1)
    # derivative w.r.t. arc length at every point: (p_{i+1} - p_{i-1}) / (d_{i-1} + d_i)
    dlen = np.zeros(n)       # length of the segment leaving each point
    dlen[s0] = d
    prev_len = np.zeros(n)
    prev_len[s0 + 1] = d
    first = np.zeros(n, dtype=bool)
    first[offsets[:-1][k > 0]] = True
    last = np.zeros(n, dtype=bool)
    last[offsets[1:][k > 0] - 1] = True
    i = np.arange(n)
    nxt = np.where(last, i, np.minimum(i + 1, n - 1))
    prv = np.where(first, i, np.maximum(i - 1, 0))
    denom = np.where(last, 0, dlen) + np.where(first, 0, prev_len)
    deriv = (points[nxt] - points[prv]) / np.where(denom > 0, denom, 1.0)[:, None]
    t = np.arange(samples) / samples
    t2, t3 = t * t, t * t * t
    h00 = 2 * t3 - 3 * t2 + 1
    h10 = t3 - 2 * t2 + t
    h01 = -2 * t3 + 3 * t2
    h11 = t3 - t2
    p0, p1 = points[s0], points[s0 + 1]
    m0 = deriv[s0] * d[:, None]
    m1 = deriv[s0 + 1] * d[:, None]
    h00, h10, h01, h11, t = (h[:, None] for h in (h00, h10, h01, h11, t))
    seg_pts = np.empty((samples, len(s0), 3))   # sample-major: long inner loops
    for c in range(3):
        seg_pts[:, :, c] = h00 * p0[:, c] + h10 * m0[:, c] + h01 * p1[:, c] + h11 * m1[:, c]
    seg_rad = radii[s0] + t * (radii[s0 + 1] - radii[s0])
    new_k = np.where(k > 0, (k - 1) * samples + 1, 0)
    new_off = np.r_[0, np.cumsum(new_k)]
    out_p = np.empty((new_off[-1], 3))
    out_r = np.empty(new_off[-1])
    local = s0 - offsets[lid[s0]]
    pos = (new_off[lid[s0]] + local * samples + np.arange(samples)[:, None]).ravel()
    out_p[pos] = seg_pts.reshape(-1, 3)
    out_r[pos] = seg_rad.ravel()
    ends = np.flatnonzero(k > 0)
    out_p[new_off[ends + 1] - 1] = points[offsets[ends + 1] - 1]
    out_r[new_off[ends + 1] - 1] = radii[offsets[ends + 1] - 1]
    return out_p, out_r, new_off


def hermite_smooth(points: np.ndarray, samples_per_segment: int = 4,
                   radii: Optional[np.ndarray] = None):
    """Cubic Hermite curve through a chain of points, Hu et al. 2017 §5.5.

    Each segment ``p_i -> p_{i+1}`` becomes ``samples_per_segment`` points of
    the cubic Hermite curve with Catmull-Rom tangents taken in chord-length
    parametrisation (``m_i = (p_{i+1} - p_{i-1}) / (d_{i-1} + d_i)``, scaled by
    the segment length; one-sided at the ends), which equals the uniform
    Catmull-Rom spline for evenly spaced points and does not overshoot at
    uneven ones.  The curve passes through every input point; the output has
    ``(k - 1) * samples_per_segment + 1`` points.  With ``radii`` (k,) returns
    ``(points, radii)`` with radii interpolated linearly along each segment.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if samples_per_segment < 1:
        raise InputError(f"samples_per_segment must be >= 1, got {samples_per_segment}")
    r = np.zeros(len(pts)) if radii is None else np.asarray(radii, dtype=np.float64).reshape(-1)
    if len(r) != len(pts):
        raise InputError(f"{len(r)} radii for {len(pts)} centre-line points")
    sp, sr, _ = _hermite_batch(pts, r, np.array([0, len(pts)]), samples_per_segment)
    return sp if radii is None else (sp, sr)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross products of (n, 3) arrays (column arithmetic: faster than np.cross here)."""
    a = np.broadcast_to(a, np.broadcast_shapes(np.shape(a), np.shape(b)))
    b = np.broadcast_to(b, a.shape)
    out = np.empty(a.shape)
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot products of (n, 3) arrays."""
    return np.einsum("ij,ij->i", a, b)


def _initial_normal(t: np.ndarray) -> np.ndarray:
    """A unit normal per tangent: horizontal (z x t) where possible, else x."""
    ref = np.zeros_like(t)
    ref[:, 2] = 1.0
    steep = np.abs(t[:, 2]) > 0.999
    r = _cross(ref, t)
    r[steep] = _cross(np.array([0.0, 1.0, 0.0]), t[steep])
    return r / np.maximum(np.linalg.norm(r, axis=1, keepdims=True), 1e-300)


def _qrotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors (n, 3) by unit quaternions (n, 4)."""
    w, u = q[:, :1], q[:, 1:]
    uv = _cross(u, v)
    return v + 2.0 * w * uv + 2.0 * _cross(u, uv)


def _rmf_batch(points, tangents, offsets, normal0=None):
    """Rotation-minimising frames for a batch of polylines (Wang et al. 2008, double reflection).

    Each step maps ``r_i`` to ``r_{i+1} = H2 H1 r_i``, with H1 the reflection
    in the bisector plane of ``x_i x_{i+1}`` (normal ``v1 = x_{i+1} - x_i``)
    and H2 the reflection with normal ``v2 = t_{i+1} - H1 t_i``.  Both depend
    only on the points and tangents, and a product of two reflections with
    unit normals ``a`` then ``b`` is the rotation by the quaternion ``b a``.
    So the frames are the segmented prefix products of these quaternions
    applied to each line's first normal: a Hillis-Steele scan of log2(k)
    vectorised quaternion products over all lines at once.  Returns (r, s)
    unit normals with (t, r, s) a right-handed orthonormal frame per point.
    """
    n = len(points)
    if n == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    lid = _seg_ids(offsets)
    start = offsets[:-1][lid]
    quat = np.zeros((n, 4))
    quat[:, 0] = 1.0                                  # quat[i] maps frame i-1 -> frame i
    inner = np.flatnonzero(np.arange(n) > start)
    if len(inner):
        v1 = points[inner] - points[inner - 1]
        c1 = _dot(v1, v1)
        ok1 = c1 > 1e-30
        a = v1 / np.sqrt(np.where(ok1, c1, 1.0))[:, None]
        t_prev = tangents[inner - 1]
        t_l = t_prev - 2.0 * _dot(a, t_prev)[:, None] * a
        v2 = tangents[inner] - t_l
        c2 = _dot(v2, v2)
        ok2 = c2 > 1e-30
        b = v2 / np.sqrt(np.where(ok2, c2, 1.0))[:, None]
        q = np.empty((len(inner), 4))
        q[:, 0] = -_dot(a, b)                # b a = (-b.a, b x a)
        q[:, 1:] = _cross(b, a)
        q[~(ok1 & ok2)] = (1.0, 0.0, 0.0, 0.0)        # degenerate step: keep the frame
        quat[inner] = q
    # segmented inclusive scan: P[i] = q[i] q[i-1] ... q[start]
    w, x, y, z = (np.ascontiguousarray(quat[:, c]) for c in range(4))
    idx = np.arange(n)
    off = 1
    while True:
        valid = np.flatnonzero(idx - off >= start)
        if len(valid) == 0:
            break
        src = valid - off
        aw, ax, ay, az = w[valid], x[valid], y[valid], z[valid]
        bw, bx, by, bz = w[src], x[src], y[src], z[src]
        w[valid] = aw * bw - ax * bx - ay * by - az * bz
        x[valid] = aw * bx + ax * bw + ay * bz - az * by
        y[valid] = aw * by - ax * bz + ay * bw + az * bx
        z[valid] = aw * bz + ax * by - ay * bx + az * bw
        off *= 2
    norm = np.sqrt(w * w + x * x + y * y + z * z)
    quat = np.stack([w / norm, x / norm, y / norm, z / norm], axis=1)
    first = offsets[:-1][np.diff(offsets) > 0]
    r0 = np.zeros((len(offsets) - 1, 3))
    if normal0 is None:
        r0[np.diff(offsets) > 0] = _initial_normal(tangents[first])
    else:
        r0[:] = np.asarray(normal0, dtype=np.float64).reshape(-1, 3)
    r = _qrotate(quat, r0[lid])
    r -= _dot(r, tangents)[:, None] * tangents
    norm = np.linalg.norm(r, axis=1, keepdims=True)
    bad = norm[:, 0] < 1e-12
    if bad.any():
        r[bad] = _initial_normal(tangents[bad])
        norm[bad] = 1.0
    r /= norm
    s = _cross(tangents, r)
    return r, s


def rotation_minimizing_frames(points: np.ndarray, tangents: Optional[np.ndarray] = None,
                               normal0: Optional[np.ndarray] = None) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rotation-minimising frames along a polyline by the double reflection method.

    Wang, Jüttler, Zheng & Liu 2008, "Computation of rotation minimizing
    frames", ACM TOG 27(1), Algorithm "double reflection" (as Yan et al. 2009
    §4.2 use for lofting): ``r_{i+1} = H2 H1 r_i`` with H1 the reflection in
    the bisector plane of ``x_i x_{i+1}`` and H2 the reflection that then maps
    the reflected tangent onto ``t_{i+1}``.  ``tangents`` default to
    finite-difference tangents; ``normal0`` (3,) is the first normal
    (default: horizontal).  Returns ``(t, r, s)``, each (k, 3), with ``s = t x r``.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    off = np.array([0, len(pts)])
    if tangents is None:
        t = _tangents(pts, off)
    else:
        t = np.asarray(tangents, dtype=np.float64).reshape(-1, 3)
        t = t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-300)
    if normal0 is not None and len(pts):
        n0 = np.asarray(normal0, dtype=np.float64).reshape(3)
        n0 = n0 - (n0 @ t[0]) * t[0]
        if np.linalg.norm(n0) < 1e-12:
            raise InputError("normal0 must not be parallel to the first tangent")
        normal0 = n0 / np.linalg.norm(n0)
    r, s = _rmf_batch(pts, t, off, normal0)
    return t, r, s


def _tube_batch(points, radii, offsets, sides, cap=True, normal0=None):
    """Vertices and faces of one closed (or open) tube per polyline of the batch.

    Returns (vertices, faces, face_line): ring vertices of all lines, then the
    cap centres; faces wound outwards; ``face_line`` the polyline per face.
    """
    sides = int(sides)
    if sides < 3:
        raise InputError(f"a tube needs at least 3 sides, got {sides}")
    n = len(points)
    nl = len(offsets) - 1
    if n == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), np.zeros(0, dtype=np.int64)
    t = _tangents(points, offsets)
    r, s = _rmf_batch(points, t, offsets, normal0)
    ang = 2.0 * np.pi * np.arange(sides) / sides
    ca, sa = np.cos(ang)[:, None], np.sin(ang)[:, None]
    # vertex j * n + i is corner j of ring i (side-major, so every array
    # operation below runs over the long axis)
    k = np.diff(offsets)
    lines = np.flatnonzero(k >= 2) if cap else np.zeros(0, dtype=np.int64)
    nb = len(lines)
    verts = np.empty((n * sides + 2 * nb, 3))
    for c in range(3):
        verts[:n * sides, c] = (points[:, c] + radii * (ca * r[:, c] + sa * s[:, c])).ravel()
    lid = _seg_ids(offsets)
    # side quads between ring i and i + 1 of the same line, two triangles each
    pair = np.flatnonzero(lid[:-1] == lid[1:]) if n > 1 else np.zeros(0, dtype=np.int64)
    j = np.arange(sides)[:, None]
    a = (j * n + pair).ravel()
    b = (((j + 1) % sides) * n + pair).ravel()
    q = len(a)
    quads = np.empty((2 * q, 3), dtype=np.int64)
    quads[:q, 0], quads[:q, 1], quads[:q, 2] = a, b, b + 1
    quads[q:, 0], quads[q:, 1], quads[q:, 2] = a, b + 1, a + 1
    faces = [quads]
    fl = np.tile(lid[pair], sides)
    face_line = [fl, fl]
    if nb:
        first = offsets[lines]
        last = offsets[lines + 1] - 1
        base = n * sides
        verts[base:base + nb] = points[first]
        verts[base + nb:] = points[last]
        cf = np.broadcast_to(base + np.arange(nb), (sides, nb)).ravel()
        cl = cf + nb
        caps = np.empty((2 * sides * nb, 3), dtype=np.int64)
        h = sides * nb
        caps[:h, 0], caps[:h, 1], caps[:h, 2] = cf, (((j + 1) % sides) * n + first).ravel(), (j * n + first).ravel()
        caps[h:, 0], caps[h:, 1], caps[h:, 2] = cl, (j * n + last).ravel(), (((j + 1) % sides) * n + last).ravel()
        faces.append(caps)
        cfl = np.tile(lines, sides)
        face_line += [cfl, cfl]
    faces = np.concatenate(faces)
    face_line = np.concatenate(face_line).astype(np.int64)
    return verts, faces, face_line


def sweep_tube(centreline: np.ndarray, radii, sides: int = 8, cap: bool = True,
               normal0: Optional[np.ndarray] = None) -> Tuple[np.ndarray, np.ndarray]:
    """A generalised cylinder (Hu et al. 2017 §5.5, Yan et al. 2009 §4.2) along any centre line.

    A regular ``sides``-gon of radius ``radii[i]`` is placed in the normal
    plane at every centre-line point, oriented by rotation-minimising frames
    (double reflection, Wang et al. 2008) so the tube never twists or flips;
    consecutive rings are joined by two triangles per side, and with ``cap``
    both ends are closed by triangle fans, making the tube watertight with
    outward normals.  ``radii`` is a scalar or (k,) metres.  Consecutive
    duplicate points are dropped.  Returns ``(vertices (v, 3), faces (f, 3))``.
    """
    pts = np.asarray(centreline, dtype=np.float64).reshape(-1, 3)
    r = np.broadcast_to(np.asarray(radii, dtype=np.float64), (len(pts),)).astype(np.float64)
    if not np.all(np.isfinite(pts)) or not np.all(np.isfinite(r)) or (r < 0).any():
        raise InputError("centre line and radii must be finite and radii >= 0 m")
    pts, r, off, _ = _dedupe(pts, r, np.array([0, len(pts)]))
    if len(pts) < 2:
        raise InputError("a tube needs a centre line of at least two distinct points")
    n0 = None
    if normal0 is not None:
        _, rr, _ = rotation_minimizing_frames(pts[:2], normal0=normal0)
        n0 = rr[0]
    v, f, _ = _tube_batch(pts, r, off, sides, cap, n0)
    return v, f


# --------------------------------------------------------------------------- tree mesh

@dataclass(frozen=True)
class LevelOfDetail:
    """How finely :func:`tree_mesh` builds the wood.

    ``sides`` polygon sides of every tube; ``samples_per_segment`` Hermite
    samples per skeleton segment (1 = the skeleton polyline, no smoothing);
    ``min_radius_m`` branches whose base radius is below it are left out,
    with all branches they carry.
    """

    sides: int = 8
    samples_per_segment: int = 3
    min_radius_m: float = 0.0


#: The three standard levels: 0 coarse (4 sides, no smoothing, twigs under
#: 3 cm radius pruned), 1 middle, 2 fine (12 sides, 6 Hermite samples, all).
LOD = (
    LevelOfDetail(sides=4, samples_per_segment=1, min_radius_m=0.03),
    LevelOfDetail(sides=8, samples_per_segment=3, min_radius_m=0.01),
    LevelOfDetail(sides=12, samples_per_segment=6, min_radius_m=0.0),
)


def _lod(lod) -> LevelOfDetail:
    if isinstance(lod, LevelOfDetail):
        return lod
    try:
        return LOD[int(lod)]
    except (IndexError, ValueError, TypeError):
        raise InputError(f"lod must be 0, 1, 2 or a LevelOfDetail, got {lod!r}")


@dataclass
class TreeMeshParts:
    """The arrays of a tree's wood mesh before a trimesh is built.

    ``vertices`` (v, 3), ``faces`` (f, 3), ``face_branch`` (f,) the branch of
    each face (index into ``branches``), ``branches`` the decomposition used,
    ``kept`` (n_branches,) which branches were meshed.
    """

    vertices: np.ndarray
    faces: np.ndarray
    face_branch: np.ndarray
    branches: BranchSet
    kept: np.ndarray


def tree_mesh_arrays(skeleton: Skeleton, lod: Union[int, LevelOfDetail] = 1,
                     radii: Optional[np.ndarray] = None, branch_set: Optional[BranchSet] = None) -> TreeMeshParts:
    """The wood of a tree as arrays: one closed generalised cylinder per branch.

    Radii come from ``radii``, else ``skeleton.radius`` if set, else the
    default pipe model.  Each branch chain (see :func:`branches`) is Hermite
    smoothed with ``lod.samples_per_segment`` and swept with ``lod.sides``;
    a side branch starts at its attachment node on the parent's axis with its
    own radius (so it starts inside the parent tube) and ends in a cap at its
    tip.  Branches with a base radius under ``lod.min_radius_m`` (and all
    they carry) are pruned; the trunk is always kept.  All tubes are built in
    one vectorised batch.  ``branch_set`` may pass ``branches(skeleton, radii)``
    when the caller has it already (it is not checked).
    """
    return tree_mesh_arrays_batch([skeleton], lod, None if radii is None else [radii],
                                  None if branch_set is None else [branch_set])[0]


def _tree_polylines(skeleton: Skeleton, lod: LevelOfDetail, radii, branch_set):
    """(points, radii, line lengths, branch set, kept branches) of the tubes of one tree, before smoothing."""
    skeleton = _check_skeleton(skeleton)
    rad = _radii_or_default(skeleton, radii)
    bset = branch_set if branch_set is not None else branches(skeleton, rad)
    nb = len(bset)
    if nb == 0:
        return np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int64), bset, np.zeros(0, bool)
    offsets = bset.offsets
    lengths = np.diff(offsets)
    idx = bset.nodes
    pts = skeleton.nodes[idx]
    r = rad[idx]
    side = bset.attach >= 0
    # a side branch starts with its own (child) radius at the attachment node
    r[offsets[:-1][side & (lengths > 1)]] = r[offsets[:-1][side & (lengths > 1)] + 1]
    base_r = r[offsets[:-1]]
    keep = base_r >= lod.min_radius_m
    keep[0] = True
    # a pruned branch prunes all it carries: AND along the path to the trunk (pointer jumping)
    anc = bset.parent.copy()
    live = np.flatnonzero(anc >= 0)
    while len(live):
        keep[live] &= keep[anc[live]]
        anc[live] = anc[anc[live]]
        live = live[anc[live] >= 0]
    if not keep.all():
        take = keep[np.repeat(np.arange(nb), lengths)]
        pts, r = pts[take], r[take]
        lengths = lengths[keep]
    return pts, r, lengths, bset, keep


def tree_mesh_arrays_batch(skeletons, lod: Union[int, LevelOfDetail] = 1, radii=None,
                           branch_sets=None) -> List[TreeMeshParts]:
    """:func:`tree_mesh_arrays` of many trees, with the tubes of all of them swept in one batch.

    ``radii`` and ``branch_sets`` are None or one entry (array or None) per skeleton.  Every
    step of the sweep works point by point along each polyline, so each tree gets exactly the
    arrays (same values, vertex and face order) a call for it alone gives.
    """
    lod = _lod(lod)
    skeletons = list(skeletons)
    nt = len(skeletons)
    radii = [None] * nt if radii is None else list(radii)
    branch_sets = [None] * nt if branch_sets is None else list(branch_sets)
    prep = [_tree_polylines(sk, lod, r, bs) for sk, r, bs in zip(skeletons, radii, branch_sets)]
    lines_per_tree = np.array([len(p[2]) for p in prep], dtype=np.int64)
    if lines_per_tree.sum() == 0:
        e = np.zeros(0, dtype=np.int64)
        return [TreeMeshParts(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), e, p[3], p[4]) for p in prep]
    pts = np.concatenate([p[0] for p in prep])
    r = np.concatenate([p[1] for p in prep])
    offsets = np.r_[0, np.cumsum(np.concatenate([p[2] for p in prep]))].astype(np.int64)
    pts, r, offsets, _ = _dedupe(pts, r, offsets)
    pts, r, offsets = _hermite_batch(pts, r, offsets, lod.samples_per_segment)
    verts, faces, face_line = _tube_batch(pts, r, offsets, lod.sides, cap=True)
    if nt == 1:
        groups = [(verts, faces, face_line)]
    else:
        groups = _split_tube_batch(verts, faces, face_line, offsets, lines_per_tree, lod.sides)
    out = []
    for (v, f, fl), (_, _, _, bset, keep) in zip(groups, prep):
        out.append(TreeMeshParts(v, f, np.flatnonzero(keep)[fl], bset, keep))
    return out


def _split_tube_batch(verts, faces, face_line, offsets, lines_per_tree, sides):
    """Per tree (vertices, faces, face line within the tree) of a :func:`_tube_batch` over many trees.

    Reorders the vertices into the layout a batch of that tree alone has (ring corner ``j`` of
    point ``i`` at ``j * n + i``, then the first caps, then the last caps) and keeps the faces
    in their batch order, which is the order of the tree alone.
    """
    nt = len(lines_per_tree)
    line_off = np.r_[0, np.cumsum(lines_per_tree)]
    n = int(offsets[-1])
    k = np.diff(offsets)
    capped = k >= 2
    nb = int(capped.sum())
    cap_rank = np.cumsum(capped) - capped            # index of each capped line among the capped lines
    pt_off = offsets[line_off]                       # points of tree t: pt_off[t] .. pt_off[t + 1]
    cap_off = np.r_[0, np.cumsum(capped)][line_off]  # capped lines of tree t: cap_off[t] .. cap_off[t + 1]
    n_t = np.diff(pt_off)
    c_t = np.diff(cap_off)
    v_t = n_t * sides + 2 * c_t
    v_off = np.r_[0, np.cumsum(v_t)]
    # new position of every batch vertex
    new = np.empty(len(verts), dtype=np.int64)
    point = np.arange(n)
    tree_of_point = np.repeat(np.arange(nt), n_t)
    local = point - pt_off[tree_of_point]
    j = np.arange(sides)[:, None]
    new[(j * n + point).ravel()] = (v_off[tree_of_point] + j * n_t[tree_of_point] + local).ravel()
    caps = np.flatnonzero(capped)
    tree_of_cap = np.repeat(np.arange(nt), c_t)
    cap_local = cap_rank[caps] - cap_off[tree_of_cap]
    base = v_off[tree_of_cap] + n_t[tree_of_cap] * sides
    new[n * sides + np.arange(nb)] = base + cap_local
    new[n * sides + nb + np.arange(nb)] = base + c_t[tree_of_cap] + cap_local
    out_v = np.empty_like(verts)
    out_v[new] = verts
    tree_of_line = np.repeat(np.arange(nt), lines_per_tree)
    face_tree = tree_of_line[face_line]
    order = np.argsort(face_tree, kind="stable")
    f_off = np.r_[0, np.cumsum(np.bincount(face_tree, minlength=nt))]
    out_f = new[faces[order]] - v_off[face_tree[order]][:, None]
    out_l = face_line[order] - line_off[face_tree[order]]
    vb, fb = v_off.tolist(), f_off.tolist()
    return [(out_v[vb[t]:vb[t + 1]], out_f[fb[t]:fb[t + 1]], out_l[fb[t]:fb[t + 1]]) for t in range(nt)]


def tree_mesh(skeleton: Skeleton, lod: Union[int, LevelOfDetail] = 1,
              radii: Optional[np.ndarray] = None, per_branch: bool = False,
              branch_set: Optional[BranchSet] = None):
    """The wood of a tree as a :class:`trimesh.Trimesh` (see :func:`tree_mesh_arrays`).

    One mesh holding all branch tubes (each tube is closed; they overlap at
    the joints and are not boolean-merged), built once with ``process=False``;
    ``mesh.metadata["face_branch"]`` gives the branch of each face.  With
    ``per_branch=True`` returns a list of one watertight mesh per meshed branch.
    ``branch_set``: see :func:`tree_mesh_arrays`.
    """
    import trimesh

    parts = tree_mesh_arrays(skeleton, lod, radii, branch_set)
    if not per_branch:
        mesh = trimesh.Trimesh(parts.vertices, parts.faces, process=False)
        mesh.metadata["face_branch"] = parts.face_branch
        return mesh
    out = []
    for b in np.flatnonzero(parts.kept):
        f = parts.faces[parts.face_branch == b]
        if len(f) == 0:
            continue
        used, inv = np.unique(f, return_inverse=True)
        out.append(trimesh.Trimesh(parts.vertices[used], inv.reshape(-1, 3), process=False))
    return out


def tree_meshes(skeletons, lod: Union[int, LevelOfDetail] = 1, radii=None, branch_sets=None) -> list:
    """:func:`tree_mesh` of many trees (one :class:`trimesh.Trimesh` each), the tubes swept in one batch.

    The same meshes as one :func:`tree_mesh` call per tree (see :func:`tree_mesh_arrays_batch`).
    """
    import trimesh

    out = []
    for parts in tree_mesh_arrays_batch(skeletons, lod, radii, branch_sets):
        mesh = trimesh.Trimesh(parts.vertices, parts.faces, process=False)
        mesh.metadata["face_branch"] = parts.face_branch
        out.append(mesh)
    return out


# --------------------------------------------------------------------------- measurements

def wood_volume(skeleton: Skeleton, radii: Optional[np.ndarray] = None,
                branch_set: Optional[BranchSet] = None) -> float:
    """Wood volume in m³: the sum of truncated cones (frusta) between nodes.

    ``V = pi h (r1^2 + r1 r2 + r2^2) / 3`` per segment, with the node radii of
    ``radii`` (default ``skeleton.radius``).  As in :func:`tree_mesh`, a side
    branch's first segment starts with the branch's own radius, not the
    (thicker) radius of the node it leaves; the overlap of a side branch with
    its parent near the joint is not subtracted.  ``branch_set`` may pass
    ``branches(skeleton, radii)`` when the caller has it already.
    """
    skeleton = _check_skeleton(skeleton)
    rad = skeleton.radius if radii is None else _radii_or_default(skeleton, radii)
    child, par = skeleton.segments()
    if len(child) == 0:
        return 0.0
    h = np.linalg.norm(skeleton.nodes[child] - skeleton.nodes[par], axis=1)
    cont = branch_set.continuation if branch_set is not None else _continuation_child(skeleton, rad)
    r2 = rad[child]
    r1 = np.where(cont[par] == child, rad[par], r2)
    return float((np.pi * h * (r1 * r1 + r1 * r2 + r2 * r2) / 3.0).sum())


def _stored_radii(skeleton: Skeleton) -> Optional[np.ndarray]:
    return skeleton.radius if len(skeleton) and np.any(skeleton.radius > 0) else None


def branch_count(skeleton: Skeleton, include_stem: bool = False, branch_set: Optional[BranchSet] = None) -> int:
    """Number of branches (chains of :func:`branches`); the stem is not counted unless asked.

    ``branch_set`` may pass ``branches(skeleton, skeleton.radius)`` when the caller has it already.
    """
    if not len(skeleton):
        n = 0
    else:
        n = len(branch_set if branch_set is not None else branches(skeleton, _stored_radii(skeleton)))
    if n == 0:
        return 0
    return n if include_stem else n - 1


def total_branch_length(skeleton: Skeleton, include_stem: bool = False,
                        branch_set: Optional[BranchSet] = None) -> float:
    """Summed length in metres of all branches (the stem chain left out unless asked).

    ``branch_set`` may pass ``branches(skeleton, skeleton.radius)`` when the caller has it already.
    """
    skeleton = _check_skeleton(skeleton)
    if len(skeleton) < 2:
        return 0.0
    total = skeleton.length()
    if include_stem:
        return total
    bset = branch_set if branch_set is not None else branches(skeleton, _stored_radii(skeleton))
    stem = bset.nodes[bset.offsets[0]:bset.offsets[1]]
    return float(total - np.linalg.norm(np.diff(skeleton.nodes[stem], axis=0), axis=1).sum())


# --------------------------------------------------------------------------- simplification

def simplify_skeleton(skeleton: Skeleton, tolerance_m: float = 0.05, max_passes: int = 8) -> Skeleton:
    """Drop pass-through nodes that lie within ``tolerance_m`` of the segment joining their
    parent and their only child (a Douglas–Peucker-like thinning of every chain).

    Branching nodes, tips and the root stay.  Each pass removes an independent set of
    nodes (no removed node's parent is removed in the same pass, alternating by depth
    parity), so the tolerance holds against the nodes kept; vectorised per pass.
    Radii, when present, are carried by the kept nodes.
    """
    return simplify_skeletons([skeleton], tolerance_m, max_passes)[0]


def simplify_skeletons(skeletons, tolerance_m: float = 0.05, max_passes: int = 8) -> List[Skeleton]:
    """:func:`simplify_skeleton` of many skeletons, each pass vectorised over all of them at once.

    Every tree keeps its own stopping rule (it stops when it has fewer than three nodes or a
    pass after the first drops nothing), so each result equals a call for that tree alone.
    """
    skeletons = [_check_skeleton(sk) for sk in skeletons]
    nt = len(skeletons)
    if nt == 0:
        return []
    nodes, parent, off = _forest(skeletons)
    sizes = np.diff(off)
    radius = np.concatenate([sk.radius for sk in skeletons])
    added = np.concatenate([sk.is_added for sk in skeletons])
    tree = np.repeat(np.arange(nt), sizes)
    active = np.ones(nt, dtype=bool)
    for k in range(max_passes):
        m_t = np.bincount(tree, minlength=nt)
        active &= m_t >= 3
        if not active.any():
            break
        m = len(nodes)
        kids = np.bincount(parent[parent >= 0], minlength=m)
        only_child = np.full(m, -1, dtype=np.int64)
        has_parent = np.flatnonzero(parent >= 0)
        only_child[parent[has_parent]] = has_parent  # valid where kids == 1
        cand = np.flatnonzero((kids == 1) & (parent >= 0) & active[tree])
        depth = _depth(parent)
        cand = cand[depth[cand] % 2 == k % 2]
        if len(cand) == 0:
            continue
        p, c = nodes[parent[cand]], nodes[only_child[cand]]
        seg = c - p
        length2 = np.maximum((seg * seg).sum(axis=1), 1e-18)
        t = np.clip(((nodes[cand] - p) * seg).sum(axis=1) / length2, 0.0, 1.0)
        dist = np.linalg.norm(nodes[cand] - (p + t[:, None] * seg), axis=1)
        drop = cand[dist <= tolerance_m]
        if k >= 1:   # a tree with candidates whose pass drops nothing stops
            tried = np.zeros(nt, dtype=bool)
            tried[tree[cand]] = True
            dropped = np.zeros(nt, dtype=bool)
            dropped[tree[drop]] = True
            active &= ~(tried & ~dropped)
        if len(drop) == 0:
            continue
        new_parent = parent.copy()
        new_parent[only_child[drop]] = parent[drop]
        keep = np.ones(m, dtype=bool)
        keep[drop] = False
        index = np.cumsum(keep) - 1
        kept_parent = new_parent[keep]
        parent = np.where(kept_parent >= 0, index[np.maximum(kept_parent, 0)], -1)
        nodes, radius, added, tree = nodes[keep], radius[keep], added[keep], tree[keep]
    off = np.r_[0, np.cumsum(np.bincount(tree, minlength=nt))].tolist()
    out = []
    for t in range(nt):
        a, b = off[t], off[t + 1]
        par = parent[a:b]
        out.append(Skeleton(nodes[a:b], np.where(par >= 0, par - a, -1), radius[a:b], added[a:b]))
    return out
