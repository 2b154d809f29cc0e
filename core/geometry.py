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

The sequential passes over nodes (subtree tip counts for radii, continuation
children and chains, simplification) are compiled loops (:mod:`sylva.core.jit`),
the rest is vectorised, with one segmented parallel prefix product of the
double-reflection rotations for the frames of all tubes at once.  The batch
forms :func:`branches_batch`, :func:`simplify_skeletons`,
:func:`tree_mesh_arrays_batch` and :func:`tree_meshes` run the same passes over
many trees joined into one forest (every step works per node, per chain or
per polyline), so each tree gets exactly what the single-tree call gives it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterator, List, Optional, Tuple, Union

import numpy as np

from .errors import InputError
from .jit import njit
from .skeleton import Skeleton

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
    number of tips in the subtree of ``i`` — computed with one backward pass
    over the nodes.  Radii are therefore non-increasing from the root to
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
    radii = tip_radius_m * _tip_counts(skeleton.parent) ** (1.0 / exponent)
    if trunk_radius_m is not None:
        if not (np.isfinite(trunk_radius_m) and trunk_radius_m > 0):
            raise InputError(f"{_tree_name(skeleton)}: trunk_radius_m must be > 0 m, got {trunk_radius_m}")
        radii *= trunk_radius_m / radii[skeleton.root]
    if inplace:
        skeleton.radius = radii.copy()
    return radii


def _tip_counts(parent: np.ndarray) -> np.ndarray:
    """Number of tips (nodes without children) in the subtree of every node, as float64.

    For one tree or a forest of concatenated trees (parents precede children).  Sums of whole
    numbers: exact, so equal to any other summation order.
    """
    return _tip_count_kernel(np.ascontiguousarray(parent, dtype=np.int64))


@njit
def _tip_count_kernel(parent):
    """Subtree tip counts by one backward pass (children after parents); see :func:`_tip_counts`."""
    m = parent.shape[0]
    kids = np.zeros(m, np.int64)
    for i in range(m):
        if parent[i] >= 0:
            kids[parent[i]] += 1
    acc = np.zeros(m)
    for i in range(m - 1, -1, -1):
        if kids[i] == 0:
            acc[i] += 1.0
        if parent[i] >= 0:
            acc[parent[i]] += acc[i]
    return acc


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


@njit
def _continuation_kernel(nodes, parent, radii, by_radius):
    """Per node the child its chain continues into (-1 at tips), see :func:`branches`; plain loops for numba.

    The bend cosine of a child is the cosine between the incoming segment (the parent's own
    segment, +z at the root) and the child's segment, rounded to 9 digits (``np.round``) so
    near-equal bends tie; the largest cosine wins, ties go to the larger ``radii`` (when
    ``by_radius``), then to the lower index.  Dot products are written out as 0 + x·x' + y·y' + z·z',
    the order numpy's row sums use, so the cosines are those of the vectorised formulation.
    Needs ``parent[i] < i`` (every Skeleton); NaN cosines rank above all others, as in a sort.
    """
    m = parent.shape[0]
    cont = np.full(m, -1, np.int64)
    best_cos = np.zeros(m)
    best_r = np.zeros(m)
    for i in range(m):
        p = parent[i]
        if p < 0:
            continue
        g = parent[p]
        if g >= 0:
            ix = nodes[p, 0] - nodes[g, 0]
            iy = nodes[p, 1] - nodes[g, 1]
            iz = nodes[p, 2] - nodes[g, 2]
        else:
            ix, iy, iz = 0.0, 0.0, 1.0
        ox = nodes[i, 0] - nodes[p, 0]
        oy = nodes[i, 1] - nodes[p, 1]
        oz = nodes[i, 2] - nodes[p, 2]
        den = math.sqrt(ix * ix + iy * iy + iz * iz) * math.sqrt(ox * ox + oy * oy + oz * oz)
        if den < 1e-12:
            den = 1e-12
        c = np.rint((0.0 + ix * ox + iy * oy + iz * oz) / den * 1e9) / 1e9
        r = radii[i] if by_radius else 0.0
        j = cont[p]
        if j < 0:
            better = True
        else:
            b = best_cos[p]
            if c != c or b != b:                      # NaN sorts last: it beats any number
                better = (c != c) and (b == b)
                same = (c != c) and (b != b)
            else:
                better = c > b
                same = c == b
            if not better and same:
                better = r > best_r[p]
        if better:
            cont[p] = i
            best_cos[p] = c
            best_r[p] = r
    return cont


def _continuation_child(skeleton: Skeleton, radii: Optional[np.ndarray] = None) -> np.ndarray:
    """Per node, the child with the smallest bending angle (ties: the thicker one), or -1."""
    return _continuations(skeleton.nodes, skeleton.parent, radii)


def _continuations(nodes: np.ndarray, parent: np.ndarray, radii: Optional[np.ndarray] = None) -> np.ndarray:
    """:func:`_continuation_kernel` of one tree or of a forest of concatenated trees (``radii`` None: by index)."""
    r = np.zeros(len(parent)) if radii is None else np.ascontiguousarray(radii, dtype=np.float64)
    return _continuation_kernel(np.ascontiguousarray(nodes, dtype=np.float64).reshape(-1, 3),
                                np.ascontiguousarray(parent, dtype=np.int64), r, radii is not None)


def branches(skeleton: Skeleton, radii: Optional[np.ndarray] = None) -> BranchSet:
    """Decompose ``skeleton`` into branch chains, Hu et al. 2017 §5.5.

    Every chain runs from the root or a branching node to a tip; at each
    branching node it continues into the child whose direction bends least
    from the incoming segment (the root's incoming direction is +z; exact
    ties go to the thicker child by ``radii``), so the trunk is one chain and
    every segment belongs to exactly one chain.  Chains are numbered by their
    first own node, so a parent branch always precedes its children.
    One compiled pass for the continuation children, one for the chains.
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
    return _split_branch_set(_branch_set(parent, _continuations(nodes, parent, r)), off)


def _forest(skeletons):
    """(nodes, parent, node offsets) of skeletons joined into one forest (parents shifted, roots -1)."""
    sizes = np.array([len(sk) for sk in skeletons], dtype=np.int64)
    off = np.r_[0, np.cumsum(sizes)]
    nodes = np.concatenate([sk.nodes for sk in skeletons]).reshape(-1, 3)
    parent = np.concatenate([sk.parent for sk in skeletons]).astype(np.int64)
    return nodes, np.where(parent >= 0, parent + np.repeat(off[:-1], sizes), -1), off


def _tree_branches(bs: BranchSet, node_off: np.ndarray) -> np.ndarray:
    """Branch offsets (n_trees + 1,) of a forest's BranchSet: the chains of tree ``t`` are
    ``branch_off[t]:branch_off[t + 1]`` (its root starts the first; an empty tree owns none)."""
    node_off = np.asarray(node_off, dtype=np.int64)
    sizes = np.diff(node_off)
    first = np.full(len(node_off), len(bs), dtype=np.int64)
    nonempty = np.flatnonzero(sizes > 0)
    first[nonempty] = bs.node_branch[node_off[nonempty]]
    # an empty tree's range starts where the next tree's starts
    return np.minimum.accumulate(first[::-1])[::-1]


def _split_branch_set(bs: BranchSet, node_off: np.ndarray, branch_off: Optional[np.ndarray] = None) -> List[BranchSet]:
    """The per-tree BranchSets of a forest's BranchSet (trees = node ranges ``node_off``).

    Indices are made local to each tree in one vectorised pass; the trees' arrays are views of it.
    """
    node_off = np.asarray(node_off, dtype=np.int64)
    nt = len(node_off) - 1
    boff = _tree_branches(bs, node_off) if branch_off is None else branch_off
    nb_t = np.diff(boff)
    tree_of_node = np.repeat(np.arange(nt), np.diff(node_off))
    tree_of_branch = np.repeat(np.arange(nt), nb_t)
    n0_b = node_off[:-1][tree_of_branch]
    nodes = bs.nodes - np.repeat(n0_b, np.diff(bs.offsets))
    # tree t's offsets are branch_off[t] .. branch_off[t + 1] (one more than its chains)
    tree_of_off = np.repeat(np.arange(nt), nb_t + 1)
    offsets = bs.offsets[np.arange(len(tree_of_off)) - tree_of_off] - bs.offsets[boff[:-1]][tree_of_off]
    bparent = np.where(bs.parent >= 0, bs.parent - boff[:-1][tree_of_branch], -1)
    attach = np.where(bs.attach >= 0, bs.attach - n0_b, -1)
    node_branch = bs.node_branch - boff[:-1][tree_of_node]
    cont = np.where(bs.continuation >= 0, bs.continuation - node_off[:-1][tree_of_node], -1)
    b_l, n_l, c_l = boff.tolist(), node_off.tolist(), bs.offsets[boff].tolist()
    out = []
    for t in range(nt):
        b0, b1, n0, n1 = b_l[t], b_l[t + 1], n_l[t], n_l[t + 1]
        out.append(BranchSet(nodes[c_l[t]:c_l[t + 1]], offsets[b0 + t:b1 + t + 1], bparent[b0:b1], attach[b0:b1],
                             node_branch[n0:n1], bs.order[b0:b1], cont[n0:n1]))
    return out


def _branch_set(parent: np.ndarray, cont: np.ndarray) -> BranchSet:
    """The :class:`BranchSet` of a tree (or forest) given each node's continuation child (see :func:`branches`)."""
    if len(parent) == 0:
        e = np.zeros(0, dtype=np.int64)
        return BranchSet(e, np.zeros(1, dtype=np.int64), e, e, e, e, e)
    full, full_off, bparent, attach, node_branch, border = _chains_kernel(
        np.ascontiguousarray(parent, dtype=np.int64), np.ascontiguousarray(cont, dtype=np.int64))
    return BranchSet(full, full_off, bparent, attach, node_branch, border, cont)


@njit
def _chains_kernel(parent, cont):
    """Branch chains from continuation children in one forward pass (parents precede children).

    A chain starts at the root and at every node its parent does not continue into, chains are
    numbered by their first own node, and a chain lists its attachment node (the parent of its
    first node, if any) then its nodes by index.  Returns (nodes, offsets, parent branch,
    attachment node, branch of every node, branch order = depth in the branch tree).
    """
    m = parent.shape[0]
    node_branch = np.empty(m, np.int64)
    nb = 0
    for i in range(m):
        p = parent[i]
        if p < 0 or cont[p] != i:
            node_branch[i] = nb
            nb += 1
        else:
            node_branch[i] = node_branch[p]
    start = np.empty(nb, np.int64)
    count = np.zeros(nb, np.int64)
    for i in range(m):
        b = node_branch[i]
        if count[b] == 0:
            start[b] = i
        count[b] += 1
    attach = np.empty(nb, np.int64)
    bparent = np.empty(nb, np.int64)
    border = np.empty(nb, np.int64)
    offsets = np.empty(nb + 1, np.int64)
    offsets[0] = 0
    for b in range(nb):
        a = parent[start[b]]
        attach[b] = a
        if a >= 0:
            bparent[b] = node_branch[a]
            border[b] = border[bparent[b]] + 1        # the parent branch starts before b
        else:
            bparent[b] = -1
            border[b] = 0
        offsets[b + 1] = offsets[b] + count[b] + (1 if a >= 0 else 0)
    nodes = np.empty(offsets[nb], np.int64)
    fill = np.empty(nb, np.int64)
    for b in range(nb):
        fill[b] = offsets[b]
        if attach[b] >= 0:
            nodes[fill[b]] = attach[b]
            fill[b] += 1
    for i in range(m):
        b = node_branch[i]
        nodes[fill[b]] = i
        fill[b] += 1
    return nodes, offsets, bparent, attach, node_branch, border


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
        d = _norm3(np.diff(points, axis=0))
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
        norm = _norm3(t)[:, None]
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
    d = _norm3(points[s0 + 1] - points[s0])
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


def _norm3(v: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(v, axis=-1)`` of (..., 3) vectors, the same bits (sqrt((x² + y²) + z²)), without
    numpy's slow reduction over a length-3 axis."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return np.sqrt((x * x + y * y) + z * z)


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
    return r / np.maximum(_norm3(r)[:, None], 1e-300)


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
    norm = _norm3(r)[:, None]
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


#: The level of detail models get unless asked otherwise (light: a forest of them stays small).
DEFAULT_LOD = 0

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


def tree_mesh_arrays(skeleton: Skeleton, lod: Union[int, LevelOfDetail] = DEFAULT_LOD,
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


@dataclass
class _Polylines:
    """The tube centre lines of a forest's trees before smoothing (see :func:`_forest_polylines`).

    ``points``/``radii`` of all kept lines, ``lengths`` points per kept line, ``kept`` (n_branches,)
    which chains are meshed, ``line_off`` / ``point_off`` (n_trees + 1,) each tree's kept lines and
    their points, ``branch_off`` each tree's chains.
    """

    points: np.ndarray
    radii: np.ndarray
    lengths: np.ndarray
    kept: np.ndarray
    line_off: np.ndarray
    point_off: np.ndarray
    branch_off: np.ndarray


def _forest_polylines(nodes: np.ndarray, radii: np.ndarray, bs: BranchSet, branch_off: np.ndarray,
                      lod: Union[int, LevelOfDetail]) -> _Polylines:
    """The tube centre lines of every tree of a forest (its BranchSet ``bs``, tree ``t`` owning chains
    ``branch_off[t]:branch_off[t + 1]``), as :func:`tree_mesh_arrays` builds them for each tree.

    A side branch starts with its own (child) radius at the attachment node; chains whose base
    radius is under ``lod.min_radius_m`` are pruned with all they carry, a tree's trunk never.
    """
    lod = _lod(lod)
    pts, r, lengths, kept, line_off = _polyline_kernel(
        np.ascontiguousarray(nodes, dtype=np.float64), np.ascontiguousarray(radii, dtype=np.float64), bs.nodes,
        bs.offsets, bs.parent, bs.attach, np.asarray(branch_off, dtype=np.int64), float(lod.min_radius_m))
    point_off = np.r_[0, np.cumsum(lengths)][line_off]
    return _Polylines(pts, r, lengths, kept, line_off, point_off, np.asarray(branch_off))


@njit
def _polyline_kernel(nodes, radii, chain, offsets, bparent, attach, branch_off, min_radius):
    """The kept chains' points and radii of :func:`_forest_polylines` in one pass over the chains
    (parents before children): a chain is kept when its base radius (its own, for a side branch) is
    at least ``min_radius`` and its parent chain is kept, a tree's trunk always.  Returns (points,
    radii, points per kept chain, kept (n_branches,), kept chains per tree as offsets)."""
    nb = offsets.shape[0] - 1
    nt = branch_off.shape[0] - 1
    kept = np.zeros(nb, np.bool_)
    n_pts = 0
    n_lines = 0
    line_off = np.zeros(nt + 1, np.int64)
    for t in range(nt):
        for b in range(branch_off[t], branch_off[t + 1]):
            a, e = offsets[b], offsets[b + 1]
            first = a + 1 if attach[b] >= 0 and e - a > 1 else a      # a side branch starts with its own radius
            keep = b == branch_off[t] or radii[chain[first]] >= min_radius
            if bparent[b] >= 0:
                keep = keep and kept[bparent[b]]
            kept[b] = keep
            if keep:
                n_pts += e - a
                n_lines += 1
        line_off[t + 1] = n_lines
    pts = np.empty((n_pts, 3))
    r = np.empty(n_pts)
    lengths = np.empty(n_lines, np.int64)
    k = 0
    line = 0
    for b in range(nb):
        if kept[b]:
            a, e = offsets[b], offsets[b + 1]
            lengths[line] = e - a
            line += 1
            for j in range(a, e):
                for c in range(3):
                    pts[k, c] = nodes[chain[j], c]
                r[k] = radii[chain[j]]
                k += 1
            if attach[b] >= 0 and e - a > 1:
                r[k - (e - a)] = radii[chain[a + 1]]
    return pts, r, lengths, kept, line_off


def _forest_wood_arrays(lines: _Polylines, a: int, b: int, lod: Union[int, LevelOfDetail]) -> list:
    """(vertices, faces, face branch) of the wood of trees ``a:b`` of :func:`_forest_polylines`, swept in one batch."""
    lod = _lod(lod)
    l0, l1 = lines.line_off[a], lines.line_off[b]
    p0, p1 = lines.point_off[a], lines.point_off[b]
    lines_per_tree = np.diff(lines.line_off[a:b + 1])
    kept = [np.flatnonzero(lines.kept[b0:b1]) for b0, b1 in
            zip(lines.branch_off[a:b].tolist(), lines.branch_off[a + 1:b + 1].tolist())]
    if l1 == l0:
        e = np.zeros(0, dtype=np.int64)
        return [(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), e) for _ in range(b - a)]
    offsets = np.r_[0, np.cumsum(lines.lengths[l0:l1])].astype(np.int64)
    pts, r, offsets, _ = _dedupe(lines.points[p0:p1], lines.radii[p0:p1], offsets)
    pts, r, offsets = _hermite_batch(pts, r, offsets, lod.samples_per_segment)
    verts, faces, face_line = _tube_batch(pts, r, offsets, lod.sides, cap=True)
    if b - a == 1:
        groups = [(verts, faces, face_line)]
    else:
        groups = _split_tube_batch(verts, faces, face_line, offsets, lines_per_tree, lod.sides)
    return [(v, f, k[fl]) for (v, f, fl), k in zip(groups, kept)]


def _forest_wood(lines: _Polylines, a: int, b: int, lod: Union[int, LevelOfDetail]) -> list:
    """:func:`tree_meshes` of trees ``a:b`` of :func:`_forest_polylines` (one trimesh each)."""
    import trimesh

    out = []
    for v, f, fb in _forest_wood_arrays(lines, a, b, lod):
        mesh = trimesh.Trimesh(v, f, process=False)
        mesh.metadata["face_branch"] = fb
        out.append(mesh)
    return out


def _join_branch_sets(bsets: List[BranchSet], node_off: np.ndarray):
    """One forest BranchSet of per-tree BranchSets (trees = node ranges ``node_off``) and its branch offsets."""
    nb = np.array([len(bs) for bs in bsets], dtype=np.int64)
    boff = np.r_[0, np.cumsum(nb)]
    coff = np.r_[0, np.cumsum([len(bs.nodes) for bs in bsets])].astype(np.int64)
    n0, b0, c0 = node_off[:-1].tolist(), boff[:-1].tolist(), coff[:-1].tolist()

    def cat(arrays):
        return np.concatenate(arrays).astype(np.int64) if arrays else np.zeros(0, dtype=np.int64)

    def shift(x, d):
        return np.where(x >= 0, x + d, -1)

    nodes = cat([bs.nodes + n for bs, n in zip(bsets, n0)])
    offsets = cat([bs.offsets[:-1] + c for bs, c in zip(bsets, c0)] + [coff[-1:]])
    joined = BranchSet(nodes, offsets, cat([shift(bs.parent, b) for bs, b in zip(bsets, b0)]),
                       cat([shift(bs.attach, n) for bs, n in zip(bsets, n0)]),
                       cat([bs.node_branch + b for bs, b in zip(bsets, b0)]), cat([bs.order for bs in bsets]),
                       cat([shift(bs.continuation, n) for bs, n in zip(bsets, n0)]))
    return joined, boff


def tree_mesh_arrays_batch(skeletons, lod: Union[int, LevelOfDetail] = DEFAULT_LOD, radii=None,
                           branch_sets=None) -> List[TreeMeshParts]:
    """:func:`tree_mesh_arrays` of many trees, with the tubes of all of them swept in one batch.

    ``radii`` and ``branch_sets`` are None or one entry (array or None) per skeleton.  Every
    step of the sweep works point by point along each polyline, so each tree gets exactly the
    arrays (same values, vertex and face order) a call for it alone gives.
    """
    lod = _lod(lod)
    skeletons = [_check_skeleton(sk) for sk in skeletons]
    nt = len(skeletons)
    if nt == 0:
        return []
    radii = [None] * nt if radii is None else list(radii)
    branch_sets = [None] * nt if branch_sets is None else list(branch_sets)
    rad = [_radii_or_default(sk, r) for sk, r in zip(skeletons, radii)]
    bsets = [bs if bs is not None else branches(sk, r) for sk, r, bs in zip(skeletons, rad, branch_sets)]
    nodes, _, off = _forest(skeletons)
    joined, boff = _join_branch_sets(bsets, off)
    lines = _forest_polylines(nodes, np.concatenate(rad), joined, boff, lod)
    return [TreeMeshParts(v, f, fb, bs, lines.kept[b0:b1])
            for (v, f, fb), bs, b0, b1 in zip(_forest_wood_arrays(lines, 0, nt, lod), bsets,
                                              boff[:-1].tolist(), boff[1:].tolist())]


def _split_tube_batch(verts, faces, face_line, offsets, lines_per_tree, sides):
    """Per tree (vertices, faces, face line within the tree) of a :func:`_tube_batch` over many trees.

    Reorders the vertices into the layout a batch of that tree alone has (ring corner ``j`` of
    point ``i`` at ``j * n + i``, then the first caps, then the last caps) and keeps the faces
    in their batch order, which is the order of the tree alone.
    """
    line_off = np.r_[0, np.cumsum(lines_per_tree)].astype(np.int64)
    out_v, out_f, out_l, v_off, f_off = _split_tube_kernel(
        np.ascontiguousarray(verts, dtype=np.float64), np.ascontiguousarray(faces, dtype=np.int64),
        np.ascontiguousarray(face_line, dtype=np.int64), np.asarray(offsets, dtype=np.int64), line_off, int(sides))
    vb, fb = v_off.tolist(), f_off.tolist()
    return [(out_v[vb[t]:vb[t + 1]], out_f[fb[t]:fb[t + 1]], out_l[fb[t]:fb[t + 1]])
            for t in range(len(lines_per_tree))]


@njit
def _split_tube_kernel(verts, faces, face_line, offsets, line_off, sides):
    """The reordering of :func:`_split_tube_batch` in one pass over points, caps and faces (a stable
    counting sort of the faces by tree); returns (vertices, faces, face lines, vertex and face offsets)."""
    n = offsets[offsets.shape[0] - 1]
    nt = line_off.shape[0] - 1
    nl = offsets.shape[0] - 1
    tree_of_line = np.empty(nl, np.int64)
    for t in range(nt):
        for line in range(line_off[t], line_off[t + 1]):
            tree_of_line[line] = t
    nb = 0
    for line in range(nl):
        if offsets[line + 1] - offsets[line] >= 2:
            nb += 1
    n_t = np.zeros(nt, np.int64)           # points and capped lines of every tree
    c_t = np.zeros(nt, np.int64)
    for line in range(nl):
        t = tree_of_line[line]
        n_t[t] += offsets[line + 1] - offsets[line]
        if offsets[line + 1] - offsets[line] >= 2:
            c_t[t] += 1
    v_off = np.zeros(nt + 1, np.int64)
    for t in range(nt):
        v_off[t + 1] = v_off[t] + n_t[t] * sides + 2 * c_t[t]
    new = np.empty(verts.shape[0], np.int64)
    cap = 0
    for t in range(nt):
        p0 = offsets[line_off[t]]
        base = v_off[t] + n_t[t] * sides
        c0 = cap
        for line in range(line_off[t], line_off[t + 1]):
            for i in range(offsets[line], offsets[line + 1]):
                for j in range(sides):
                    new[j * n + i] = v_off[t] + j * n_t[t] + (i - p0)
            if offsets[line + 1] - offsets[line] >= 2:
                new[n * sides + cap] = base + (cap - c0)
                new[n * sides + nb + cap] = base + c_t[t] + (cap - c0)
                cap += 1
    out_v = np.empty_like(verts)
    for v in range(verts.shape[0]):
        for c in range(3):
            out_v[new[v], c] = verts[v, c]
    nf = faces.shape[0]
    f_off = np.zeros(nt + 1, np.int64)
    for f in range(nf):
        f_off[tree_of_line[face_line[f]] + 1] += 1
    for t in range(nt):
        f_off[t + 1] += f_off[t]
    fill = f_off[:nt].copy()
    out_f = np.empty((nf, 3), np.int64)
    out_l = np.empty(nf, np.int64)
    for f in range(nf):
        t = tree_of_line[face_line[f]]
        pos = fill[t]
        fill[t] += 1
        for c in range(3):
            out_f[pos, c] = new[faces[f, c]] - v_off[t]
        out_l[pos] = face_line[f] - line_off[t]
    return out_v, out_f, out_l, v_off, f_off


def tree_mesh(skeleton: Skeleton, lod: Union[int, LevelOfDetail] = DEFAULT_LOD,
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


def tree_meshes(skeletons, lod: Union[int, LevelOfDetail] = DEFAULT_LOD, radii=None, branch_sets=None) -> list:
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
    parity), so the tolerance holds against the nodes kept; one compiled loop.
    Radii, when present, are carried by the kept nodes.
    """
    return simplify_skeletons([skeleton], tolerance_m, max_passes)[0]


def simplify_skeletons(skeletons, tolerance_m: float = 0.05, max_passes: int = 8) -> List[Skeleton]:
    """:func:`simplify_skeleton` of many skeletons, all passes in one compiled loop over all of them.

    Every tree keeps its own stopping rule (it stops when it has fewer than three nodes or a
    pass after the first drops nothing), so each result equals a call for that tree alone.
    """
    skeletons = [_check_skeleton(sk) for sk in skeletons]
    if not skeletons:
        return []
    nodes, parent, off = _forest(skeletons)
    radius = np.concatenate([sk.radius for sk in skeletons])
    added = np.concatenate([sk.is_added for sk in skeletons])
    nodes, parent, radius, added, off = _simplify_forest(nodes, parent, radius, added, off, tolerance_m, max_passes)
    local = _local_parent(parent, off)
    bounds = off.tolist()
    return [_trusted_skeleton(nodes[a:b], local[a:b], radius[a:b], added[a:b]) for a, b in zip(bounds[:-1], bounds[1:])]


def _trusted_skeleton(nodes: np.ndarray, parent: np.ndarray, radius: np.ndarray, is_added: np.ndarray) -> Skeleton:
    """A :class:`Skeleton` of arrays that are valid by construction (a slice of a forest of valid
    skeletons: float64 (m, 3) nodes, int64 parents before their children and one root, float64
    radii, bool flags), without ``Skeleton``'s checks and conversions (Sylva, not in the paper)."""
    sk = object.__new__(Skeleton)
    sk.nodes, sk.parent, sk.radius, sk.is_added = nodes, parent, radius, is_added
    return sk


def _local_parent(parent: np.ndarray, off: np.ndarray) -> np.ndarray:
    """Forest parents (global indices, -1 at roots) made relative to each tree's first node."""
    tree = np.repeat(np.arange(len(off) - 1), np.diff(off))
    return np.where(parent >= 0, parent - off[:-1][tree], -1)


def _simplify_forest(nodes, parent, radius, added, off, tolerance_m: float, max_passes: int = 8):
    """:func:`simplify_skeletons` of a forest (see :func:`_forest`): its kept nodes as a forest
    (nodes, parents, radii, added flags, node offsets)."""
    return _simplify_kernel(np.ascontiguousarray(nodes, dtype=np.float64), np.ascontiguousarray(parent, dtype=np.int64),
                            np.ascontiguousarray(radius, dtype=np.float64), np.ascontiguousarray(added, dtype=np.bool_),
                            np.asarray(off, dtype=np.int64), float(tolerance_m), int(max_passes))


@njit
def _simplify_kernel(nodes, parent, radius, added, off, tol, max_passes):
    """The passes of :func:`simplify_skeleton` over a forest, tree by tree; returns the kept nodes as a
    forest (nodes, parents, radii, added flags, node offsets).

    Pass ``k`` looks at the pass-through nodes (one child, a parent) of depth parity ``k % 2`` of the
    trees still active and drops those within ``tol`` of the segment parent -> child, the child
    taking the dropped node's parent (no dropped node is the parent or child of another, so the
    pass is independent of the order).  A tree stops when it has fewer than three nodes, or when a
    pass after the first finds candidates but drops none.  Sums are written out as 0 + x + y + z,
    the order of numpy's row sums.
    """
    m = parent.shape[0]
    alive = np.ones(m, np.bool_)
    par = parent.copy()
    kids = np.zeros(m, np.int64)
    only = np.full(m, -1, np.int64)
    depth = np.zeros(m, np.int64)
    drop = np.zeros(m, np.bool_)
    for t in range(off.shape[0] - 1):          # the trees are independent: one after the other
        a, b = off[t], off[t + 1]
        size = b - a
        for k in range(max_passes):
            if size < 3:
                break
            for i in range(a, b):
                kids[i] = 0
            for i in range(a, b):
                if alive[i]:
                    p = par[i]
                    if p >= 0:
                        kids[p] += 1
                        only[p] = i
                        depth[i] = depth[p] + 1
                    else:
                        depth[i] = 0
            tried = False
            n_drop = 0
            for i in range(a, b):
                drop[i] = False
                if not alive[i] or kids[i] != 1 or par[i] < 0 or depth[i] % 2 != k % 2:
                    continue
                p = par[i]
                c = only[i]
                sx = nodes[c, 0] - nodes[p, 0]
                sy = nodes[c, 1] - nodes[p, 1]
                sz = nodes[c, 2] - nodes[p, 2]
                length2 = sx * sx + sy * sy + sz * sz
                if length2 < 1e-18:
                    length2 = 1e-18
                u = (0.0 + (nodes[i, 0] - nodes[p, 0]) * sx + (nodes[i, 1] - nodes[p, 1]) * sy
                     + (nodes[i, 2] - nodes[p, 2]) * sz) / length2
                if u == u:                                 # np.clip(u, 0, 1); NaN stays NaN
                    if not u > 0.0:
                        u = 0.0
                    if not u < 1.0:
                        u = 1.0
                dx = nodes[i, 0] - (nodes[p, 0] + u * sx)
                dy = nodes[i, 1] - (nodes[p, 1] + u * sy)
                dz = nodes[i, 2] - (nodes[p, 2] + u * sz)
                tried = True
                if math.sqrt(dx * dx + dy * dy + dz * dz) <= tol:
                    drop[i] = True
                    n_drop += 1
            if n_drop == 0:
                if k >= 1 and tried:     # a pass after the first with candidates that drops nothing stops
                    break
                continue
            for i in range(a, b):
                if drop[i]:
                    par[only[i]] = par[i]
                    alive[i] = False
            size -= n_drop
    index = np.cumsum(alive) - 1
    mk = index[m - 1] + 1 if m else 0
    out_nodes = np.empty((mk, 3))
    out_parent = np.empty(mk, np.int64)
    out_radius = np.empty(mk)
    out_added = np.empty(mk, np.bool_)
    out_off = np.zeros(off.shape[0], np.int64)
    for t in range(off.shape[0] - 1):
        out_off[t + 1] = out_off[t]
        for i in range(off[t], off[t + 1]):
            if alive[i]:
                k = index[i]
                out_nodes[k, 0], out_nodes[k, 1], out_nodes[k, 2] = nodes[i, 0], nodes[i, 1], nodes[i, 2]
                out_parent[k] = index[par[i]] if par[i] >= 0 else -1
                out_radius[k] = radius[i]
                out_added[k] = added[i]
                out_off[t + 1] += 1
    return out_nodes, out_parent, out_radius, out_added, out_off
