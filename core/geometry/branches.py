"""Branch chains, Hu et al. 2017 §5.5: a chain runs from the root or a branching node to a tip.

At a branching node the chain continues into the child that bends least (:func:`continuations`, a compiled
pass), so the trunk is one chain; :func:`branches` returns a :class:`BranchSet`.  The chains of many trees
are found on their joined forest (:func:`branches_batch`, :func:`build_branch_set`) and cut back per tree
(:func:`tree_branches`, :func:`split_branch_set`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterator, List, Optional

import numpy as np

from ..jit import njit
from ..skeleton import Skeleton
from .passes import check_skeleton, join_forest


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
    the order numpy's row sums use.
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


def continuation_child(skeleton: Skeleton, radii: Optional[np.ndarray] = None) -> np.ndarray:
    """Per node, the child with the smallest bending angle (ties: the thicker one), or -1."""
    return continuations(skeleton.nodes, skeleton.parent, radii)


def continuations(nodes: np.ndarray, parent: np.ndarray, radii: Optional[np.ndarray] = None) -> np.ndarray:
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
    skeleton = check_skeleton(skeleton)
    return build_branch_set(skeleton.parent, continuation_child(skeleton, radii))


def branches_batch(skeletons, radii=None) -> List[BranchSet]:
    """:func:`branches` of many skeletons (``radii`` None or one entry per skeleton), in one vectorised pass.

    The skeletons are joined into one forest; every step works per node, per parent or per
    chain, so each tree gets the :class:`BranchSet` of ``branches(skeleton, radii)``.
    """
    skeletons = [check_skeleton(sk) for sk in skeletons]
    if not skeletons:
        return []
    nodes, parent, off = join_forest(skeletons)
    r = None
    if radii is not None and any(x is not None for x in radii):
        r = np.concatenate([np.zeros(len(sk)) if x is None else np.asarray(x, dtype=np.float64).reshape(-1)
                            for sk, x in zip(skeletons, radii)])
    return split_branch_set(build_branch_set(parent, continuations(nodes, parent, r)), off)


def tree_branches(bs: BranchSet, node_off: np.ndarray) -> np.ndarray:
    """Branch offsets (n_trees + 1,) of a forest's BranchSet: the chains of tree ``t`` are
    ``branch_off[t]:branch_off[t + 1]`` (its root starts the first; an empty tree owns none)."""
    node_off = np.asarray(node_off, dtype=np.int64)
    sizes = np.diff(node_off)
    first = np.full(len(node_off), len(bs), dtype=np.int64)
    nonempty = np.flatnonzero(sizes > 0)
    first[nonempty] = bs.node_branch[node_off[nonempty]]
    # an empty tree's range starts where the next tree's starts
    return np.minimum.accumulate(first[::-1])[::-1]


def split_branch_set(bs: BranchSet, node_off: np.ndarray, branch_off: Optional[np.ndarray] = None) -> List[BranchSet]:
    """The per-tree BranchSets of a forest's BranchSet (trees = node ranges ``node_off``).

    Indices are made local to each tree in one vectorised pass; the trees' arrays are views of it.
    """
    node_off = np.asarray(node_off, dtype=np.int64)
    nt = len(node_off) - 1
    boff = tree_branches(bs, node_off) if branch_off is None else branch_off
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


def build_branch_set(parent: np.ndarray, cont: np.ndarray) -> BranchSet:
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
