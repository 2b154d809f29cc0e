"""Thinning in voxel space (Hu et al. 2017, §5.1).

The tree's points are binned into voxels of pitch d_l (``voxel_m``, 0.2 m by
default, Table 1: 0.15–0.25 m) laid over the bounding box of the points.  A
black voxel holds at least one point and is represented by the mean of its
points (downsampling).  A topology-preserving thinning then deletes black
voxels "that do not alter the topology of the tree structure" — Hu et al.
cite the sequential 3D thinning of Palágyi et al. (2001): repeated passes of
six directional sub-iterations (up, down, north, south, east, west), each
deleting border voxels of that direction that are *simple* and are not
curve end points.

Sylva tests simplicity with the usual (26, 6) characterisation: a black voxel
p is simple iff the black voxels of its 26-neighbourhood (p excluded) form
exactly one 26-connected component and the white voxels of its 18-
neighbourhood that are 6-adjacent to p form exactly one 6-connected
component.  An end point has exactly one black 26-neighbour.  To vectorise
the sequential sweep, each directional sub-iteration deletes, in rounds, sets
of simple voxels no two of which are 26-adjacent: the neighbourhood of each
is untouched by the others, so this equals deleting them one after the other
(a sequential order), and the voxels left are re-tested.  The result is
deterministic.

Voxels marked ``keep`` (Sylva marks the ones holding added trunk points) are
never deleted.

The sub-iterations run as a compiled kernel (:mod:`sylva.core.jit`, numba)
that tests simplicity on 26-bit neighbourhood masks by flood fill;
:func:`is_simple` is the vectorised numpy form of the same test.  The
voxelisation (voxel of each point, voxel means, the table of the 26
neighbours) is a kernel as well.  tests/test_skeleton_kernel.py checks the
voxels against numpy's unique and bincount and the thinning's result:
protected voxels kept, the 26-connected components unchanged, and a fixed
point (thinning it again deletes nothing).
"""
from __future__ import annotations

import math
from itertools import product
from typing import NamedTuple, Optional

import numpy as np

from ..jit import njit

# --- the 3x3x3 neighbourhood --------------------------------------------
_OFFSETS = np.array([o for o in product((-1, 0, 1), repeat=3) if o != (0, 0, 0)], dtype=np.int64)
_L1 = np.abs(_OFFSETS).sum(axis=1)
_FACE = np.flatnonzero(_L1 == 1)           # the six 6-neighbours
_N18 = np.flatnonzero(_L1 <= 2)            # 18-neighbourhood
_SENTINEL = 26                              # label column that is never black/white


def _adjacency(positions: np.ndarray, connectivity: int) -> np.ndarray:
    """Padded neighbour lists among ``positions`` (indices into _OFFSETS)."""
    p = _OFFSETS[positions]
    diff = np.abs(p[:, None, :] - p[None, :, :])
    if connectivity == 26:
        adj = diff.max(axis=2) == 1
    else:
        adj = diff.sum(axis=2) == 1
    deg = adj.sum(axis=1).max()
    out = np.full((26, deg), _SENTINEL, dtype=np.int64)
    for a, row in zip(positions, adj):
        nb = positions[row]
        out[a, :len(nb)] = nb
    return out


_ADJ26 = _adjacency(np.arange(26), 26)
_ADJ6_N18 = _adjacency(_N18, 6)
_DIRECTIONS = [np.flatnonzero((_OFFSETS == d).all(axis=1))[0] for d in
               ([0, 0, 1], [0, 0, -1], [0, 1, 0], [0, -1, 0], [1, 0, 0], [-1, 0, 0])]


def _count_components(member: np.ndarray, adj: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """Per row, number of connected components of ``member`` positions that hold a seed.

    ``member`` is (N, 26) bool, ``adj`` a padded adjacency table, ``seeds``
    the positions whose components count.  Min-label propagation, vectorised
    over rows.
    """
    n = len(member)
    big = 10_000
    labels = np.where(member, np.arange(26)[None, :], big)
    labels = np.concatenate([labels, np.full((n, 1), big)], axis=1)
    while True:
        nb = labels[:, adj].min(axis=2)                       # (N, 26)
        new = np.where(member, np.minimum(labels[:, :26], nb), big)
        if np.array_equal(new, labels[:, :26]):
            break
        labels[:, :26] = new
    lab = np.sort(labels[:, seeds], axis=1)
    distinct = (lab[:, :1] < big).astype(np.int64).ravel()
    distinct += ((lab[:, 1:] != lab[:, :-1]) & (lab[:, 1:] < big)).sum(axis=1)
    return distinct


_BITS = (1 << np.arange(26, dtype=np.int64))
_SIMPLE_CACHE: dict = {}     # 26-bit configuration -> simple?  (a memo of a pure function)
_CACHE_LIMIT = 250_000     # entries (~25 MB); cleared when full


def _is_simple_uncached(config: np.ndarray) -> np.ndarray:
    black = _count_components(config, _ADJ26, np.arange(26))
    white = np.zeros_like(config)
    white[:, _N18] = ~config[:, _N18]
    white_faces = _count_components(white, _ADJ6_N18, _FACE)
    return (black == 1) & (white_faces == 1)


def is_simple(config: np.ndarray) -> np.ndarray:
    """(26, 6) simplicity of the centre voxel for each row of ``config``.

    ``config`` is (N, 26) bool: which of the 26 neighbours (ordered as
    ``itertools.product((-1, 0, 1), repeat=3)`` without the centre) are black.
    Results are memoised per configuration (the test is a pure function of
    the 26 bits), which makes thinning many trees cheap.
    """
    config = np.asarray(config, dtype=bool).reshape(-1, 26)
    if len(config) == 0:
        return np.zeros(0, dtype=bool)
    codes = config.astype(np.int64) @ _BITS
    ucodes, inv = np.unique(codes, return_inverse=True)
    cache = _SIMPLE_CACHE
    known = np.array([cache.get(c, 2) for c in ucodes.tolist()], dtype=np.int8)
    missing = np.flatnonzero(known == 2)
    if len(missing):
        first = np.full(len(ucodes), -1, dtype=np.int64)
        first[inv[::-1]] = np.arange(len(inv))[::-1]
        rows = first[missing]
        res = _is_simple_uncached(config[rows])
        known[missing] = res
        if len(cache) > _CACHE_LIMIT:
            cache.clear()
        cache.update(zip(ucodes[missing].tolist(), res.tolist()))
    return known[inv].astype(bool)


# Bit masks of the same neighbourhoods for the kernel (bit q = _OFFSETS[q]).
_ADJ26_MASK = np.array([sum(1 << int(q) for q in row if q != _SENTINEL) for row in _ADJ26], dtype=np.int64)
_ADJ6_MASK = np.array([sum(1 << int(q) for q in row if q != _SENTINEL) for row in _ADJ6_N18], dtype=np.int64)
_N18_MASK = np.int64(sum(1 << int(q) for q in _N18))
_FACE_MASK = np.int64(sum(1 << int(q) for q in _FACE))
_DIRECTIONS_ARR = np.array(_DIRECTIONS, dtype=np.int64)
# The forward half of the 3x3x3 neighbourhood (offsets after the centre, ``_OFFSETS[13:]``, the
# mirror image of ``_OFFSETS[12::-1]``) by columns (dx, dy): dx, dy and the numbers of their
# dz = -1, 0, 1 neighbours, -1 for the centre and the offset before it.
_COLUMNS = np.array([[dx, dy] + [int(np.flatnonzero((_OFFSETS == (dx, dy, dz)).all(axis=1))[0])
                                 if (dx, dy, dz) > (0, 0, 0) else -1 for dz in (-1, 0, 1)]
                     for dx, dy in product((-1, 0, 1), repeat=2) if (dx, dy) >= (0, 0)], dtype=np.int64)


@njit
def _thin_kernel(nbr, keep, directions, adj26, adj6, n18, faces, max_passes):
    """The directional sub-iterations of :func:`thin_voxels` (see there); plain loops for numba.

    ``nbr`` (v, 26) neighbour voxel ids (v = white), ``keep`` protected
    voxels; simplicity as :func:`is_simple`, on 26-bit masks.  Returns the
    black flags (v + 1, the last one the white sentinel) and the passes.
    Each voxel's mask of black neighbours is kept up to date as voxels are
    deleted (neighbour q of y sees y as its neighbour 25 - q), and whether
    it is deletable (simple, not an end point) is remembered until its mask
    changes: the test is a pure function of the mask (Sylva, not in the paper).
    """
    v = nbr.shape[0]
    black = np.empty(v + 1, np.bool_)
    for x in range(v):
        black[x] = True
    black[v] = False
    cfg = np.zeros(v, np.int64)                 # bit q: neighbour q is black
    for x in range(v):
        c = 0
        for q in range(26):
            if nbr[x, q] < v:
                c |= 1 << q
        cfg[x] = c
    state = np.zeros(v, np.int8)                # 0 not known, 1 deletable, 2 not deletable
    ids = np.empty(v, np.int64)
    go = np.empty(v, np.int64)
    is_cand = np.zeros(v + 1, np.bool_)
    passes = 0
    while passes < max_passes:
        passes += 1
        deleted = 0
        for dd in range(directions.shape[0]):
            bit = 1 << directions[dd]
            m = 0
            for x in range(v):
                if black[x] and not keep[x] and (cfg[x] & bit) == 0:
                    ids[m] = x
                    m += 1
            while m > 0:
                # border voxels of direction d that are not end points and are simple
                m2 = 0
                for t in range(m):
                    x = ids[t]
                    c = cfg[x]
                    if c & bit:
                        continue
                    if state[x] == 0:
                        state[x] = 2
                        if c & (c - 1):             # at least two black neighbours
                            # black 26-neighbours: exactly one 26-connected component
                            rem = c
                            low = rem & -rem
                            comp = low
                            front = low
                            while front != 0:
                                p = 0
                                while ((front >> p) & 1) == 0:
                                    p += 1
                                front &= front - 1
                                new = adj26[p] & rem & ~comp
                                comp |= new
                                front |= new
                            if comp == c:
                                # white 18-neighbours: exactly one 6-connected component holding a face
                                rem = ~c & n18
                                ncomp = 0
                                while rem != 0 and ncomp < 2:
                                    low = rem & -rem
                                    comp = low
                                    front = low
                                    while front != 0:
                                        p = 0
                                        while ((front >> p) & 1) == 0:
                                            p += 1
                                        front &= front - 1
                                        new = adj6[p] & rem & ~comp
                                        comp |= new
                                        front |= new
                                    rem &= ~comp
                                    if comp & faces:
                                        ncomp += 1
                                if ncomp == 1:
                                    state[x] = 1
                    if state[x] != 1:
                        continue
                    ids[m2] = x
                    m2 += 1
                m = m2
                if m == 0:
                    break
                # delete those without a simple neighbour of lower index (an
                # independent set, as good as one after the other); re-test the rest
                for t in range(m):
                    is_cand[ids[t]] = True
                m3 = 0
                ngo = 0
                for t in range(m):
                    x = ids[t]
                    lower = False
                    for q in range(26):
                        y = nbr[x, q]
                        if y < x and is_cand[y]:
                            lower = True
                            break
                    if lower:
                        ids[m3] = x
                        m3 += 1
                    else:
                        go[ngo] = x
                        ngo += 1
                for t in range(m3):
                    is_cand[ids[t]] = False
                for t in range(ngo):
                    y = go[t]
                    is_cand[y] = False
                    black[y] = False
                    for q in range(26):
                        x = nbr[y, q]
                        if x < v:
                            cfg[x] &= ~(1 << (25 - q))
                            state[x] = 0
                deleted += ngo
                m = m3
        if deleted == 0:
            break
    return black, passes


@njit
def _voxel_grid(xyz, voxel_m, keep, columns):
    """Black voxels of ``xyz`` (see :func:`thin_voxels`); plain loops for numba.

    Returns the black voxel of each point, the voxel means, the protected
    voxels and the (v, 26) neighbour table (v = white).  Voxels are numbered
    by key (x, then y, then z), as ``np.unique`` numbers them; the means add
    the points in their order, as ``np.bincount`` does.  Neighbours are found
    without a dense grid: per column of neighbours (dx, dy) (``columns``:
    dx, dy and the neighbour numbers of dz = -1, 0, 1, -1 where none), one
    pointer walks the sorted keys (the key of a voxel's neighbour grows with
    the voxel's key), the three dz being consecutive keys.  The columns are
    the forward half of the neighbourhood (offsets after the centre in
    ``_OFFSETS``); the backward half follows by symmetry (offset q of x is
    offset 25 - q of its neighbour).
    """
    n = xyz.shape[0]
    origin = np.empty(3)
    for a in range(3):
        origin[a] = xyz[0, a]
    for p in range(1, n):
        for a in range(3):
            origin[a] = min(origin[a], xyz[p, a])
    ijk = np.empty((n, 3), np.int64)
    dims = np.zeros(3, np.int64)
    for p in range(n):
        for a in range(3):
            c = int(math.floor((xyz[p, a] - origin[a]) / voxel_m)) + 1   # +1: room for -1 offsets
            ijk[p, a] = c
            dims[a] = max(dims[a], c)
    for a in range(3):
        dims[a] += 2
    key = np.empty(n, np.int64)
    for p in range(n):
        key[p] = (ijk[p, 0] * dims[1] + ijk[p, 1]) * dims[2] + ijk[p, 2]
    order = np.argsort(key)
    inv = np.empty(n, np.int64)
    ukey = np.empty(n, np.int64)
    v = 0
    for t in range(n):
        p = order[t]
        if v == 0 or key[p] != ukey[v - 1]:
            ukey[v] = key[p]
            v += 1
        inv[p] = v - 1
    counts = np.zeros(v)
    means = np.zeros((v, 3))
    for p in range(n):
        x = inv[p]
        counts[x] += 1.0
        for a in range(3):
            means[x, a] += xyz[p, a]
    for x in range(v):
        for a in range(3):
            means[x, a] /= counts[x]
    vkeep = np.zeros(v, np.bool_)
    for p in range(n):
        if keep[p]:
            vkeep[inv[p]] = True
    nbr = np.full((v, 26), v, np.int64)
    for col in range(columns.shape[0]):
        off = (columns[col, 0] * dims[1] + columns[col, 1]) * dims[2] - 1     # the key of dz = -1
        ptr = 0
        for x in range(v):
            target = ukey[x] + off
            while ptr < v and ukey[ptr] < target:
                ptr += 1
            p = ptr
            for dz in range(3):
                q = columns[col, 2 + dz]
                while p < v and ukey[p] < target + dz:
                    p += 1
                if q >= 0 and p < v and ukey[p] == target + dz:
                    nbr[x, q] = p
                    nbr[p, 25 - q] = x          # x is p's neighbour -offset
    return inv, means, vkeep, nbr


class Thinned(NamedTuple):
    """Result of :func:`thin_voxels`."""

    points: np.ndarray          # (c, 3) candidate skeleton points: means of the surviving voxels
    voxel_index: np.ndarray     # (c,) index of each candidate in the black-voxel arrays
    voxel_means: np.ndarray     # (v, 3) mean point of every black voxel (downsampled cloud)
    voxel_of_point: np.ndarray  # (n,) black voxel of each input point
    voxel_keep: np.ndarray      # (v,) voxels protected from deletion
    passes: int                 # thinning passes until nothing more was deletable


def thin_voxels(xyz: np.ndarray, voxel_m: float = 0.2, keep: Optional[np.ndarray] = None,
                max_passes: int = 100) -> Thinned:
    """Downsample ``xyz`` to voxel means and thin the black voxels (Hu et al. §5.1).

    ``keep`` (n,) bool marks points whose voxels must survive.  Returns the
    candidate skeleton points (means of the surviving voxels, ordered by
    voxel index x, then y, then z) and the bookkeeping to map points to voxels.
    Pure function of its inputs.
    """
    xyz = np.ascontiguousarray(xyz, dtype=np.float64).reshape(-1, 3)
    keep = np.zeros(len(xyz), dtype=bool) if keep is None else np.asarray(keep, dtype=bool)
    inv, means, vkeep, nbr = _voxel_grid(xyz, float(voxel_m), keep, _COLUMNS)
    v = len(means)
    black, passes = _thin_kernel(nbr, vkeep, _DIRECTIONS_ARR, _ADJ26_MASK, _ADJ6_MASK, _N18_MASK, _FACE_MASK,
                                 int(max_passes))
    survivors = np.flatnonzero(black[:v])
    return Thinned(means[survivors], survivors, means, inv, vkeep, passes)
