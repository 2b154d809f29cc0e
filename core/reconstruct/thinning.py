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
:func:`is_simple` is the vectorised numpy form of the same test.
"""
from __future__ import annotations

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


@njit
def _thin_kernel(nbr, keep, directions, adj26, adj6, n18, faces, max_passes):
    """The directional sub-iterations of :func:`thin_voxels` (see there); plain loops for numba.

    ``nbr`` (v, 26) neighbour voxel ids (v = white), ``keep`` protected
    voxels; simplicity as :func:`is_simple`, on 26-bit masks.  Returns the
    black flags (v + 1, the last one the white sentinel) and the passes.
    """
    v = nbr.shape[0]
    black = np.empty(v + 1, np.bool_)
    for x in range(v):
        black[x] = True
    black[v] = False
    ids = np.empty(v, np.int64)
    go = np.empty(v, np.int64)
    is_cand = np.zeros(v + 1, np.bool_)
    passes = 0
    while passes < max_passes:
        passes += 1
        deleted = 0
        for dd in range(directions.shape[0]):
            d = directions[dd]
            m = 0
            for x in range(v):
                if black[x] and not keep[x] and not black[nbr[x, d]]:
                    ids[m] = x
                    m += 1
            while m > 0:
                # border voxels of direction d that are not end points and are simple
                m2 = 0
                for t in range(m):
                    x = ids[t]
                    if black[nbr[x, d]]:
                        continue
                    cfg = 0
                    cnt = 0
                    for q in range(26):
                        if black[nbr[x, q]]:
                            cfg |= 1 << q
                            cnt += 1
                    if cnt < 2:
                        continue
                    # black 26-neighbours: exactly one 26-connected component
                    rem = cfg
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
                    if comp != cfg:
                        continue
                    # white 18-neighbours: exactly one 6-connected component holding a face
                    rem = ~cfg & n18
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
                    if ncomp != 1:
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
                    is_cand[go[t]] = False
                    black[go[t]] = False
                deleted += ngo
                m = m3
        if deleted == 0:
            break
    return black, passes



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
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    n = len(xyz)
    origin = xyz.min(axis=0)
    ijk = np.floor((xyz - origin) / voxel_m).astype(np.int64) + 1   # +1: room for -1 offsets
    dims = ijk.max(axis=0) + 2
    key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    ukey, inv = np.unique(key, return_inverse=True)
    v = len(ukey)
    counts = np.bincount(inv, minlength=v).astype(np.float64)
    means = np.stack([np.bincount(inv, weights=xyz[:, c], minlength=v) for c in range(3)], axis=1)
    means /= counts[:, None]
    vkeep = np.zeros(v, dtype=bool)
    if keep is not None:
        vkeep[inv[np.asarray(keep, dtype=bool)]] = True

    # Neighbour table: voxel id of each of the 26 neighbours, v where white.
    nkey = ukey[:, None] + ((_OFFSETS[:, 0] * dims[1] + _OFFSETS[:, 1]) * dims[2] + _OFFSETS[:, 2])[None, :]
    cells = int(np.prod(dims))
    if cells <= 16_000_000:
        grid = np.full(cells, v, dtype=np.int32)
        grid[ukey] = np.arange(v, dtype=np.int32)
        nbr = grid[nkey].astype(np.int64)                               # (v, 26), v = white
    else:
        pos = np.minimum(np.searchsorted(ukey, nkey), v - 1)
        nbr = np.where(ukey[pos] == nkey, pos, v)

    black, passes = _thin_kernel(nbr, vkeep, _DIRECTIONS_ARR, _ADJ26_MASK, _ADJ6_MASK, _N18_MASK, _FACE_MASK,
                                 int(max_passes))
    survivors = np.flatnonzero(black[:v])
    return Thinned(means[survivors], survivors, means, inv, vkeep, passes)
