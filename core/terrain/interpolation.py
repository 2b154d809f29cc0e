"""Interpolation in local metres: linear interpolation in a Delaunay TIN (:func:`tin_interpolate`)
whose point location is a compiled visibility walk in serpentine order (Sylva), the lowest point per
cell (:func:`lowest_per_cell`, a fine DTM's thinning of the ground) and k-nearest inverse-distance
weighting (:func:`idw`).
"""
from __future__ import annotations

from typing import Optional

import numpy as np
from scipy.spatial import Delaunay, QhullError, cKDTree

from ..jit import njit
from ..kernels.buckets import bucket_by_cell
from ..kernels.grid import grid_cells


def _spatial_order(xy: np.ndarray) -> np.ndarray:
    """A permutation visiting points row by row of a coarse grid, alternating direction.

    Qhull's point location walks from the previous answer, so querying (and
    triangulating) in this order instead of at random is hundreds of times faster.
    The permutation is ``np.lexsort((serpentine column, row))``'s, computed by a
    counting sort (:func:`_serpentine_sort`; Sylva, not in the paper).
    """
    if len(xy) < 2:
        return np.arange(len(xy))
    order = _serpentine_sort(np.ascontiguousarray(xy, dtype=np.float64), 4 * len(xy) + 1024)
    if len(order) == len(xy):
        return order
    lo = xy.min(axis=0)                                # a degenerate extent: too many cells
    span = np.maximum(xy.max(axis=0) - lo, 1e-9)
    cell = max(np.sqrt(span[0] * span[1] / len(xy)) * 4.0, 1e-9)
    ij = np.floor((xy - lo) / cell).astype(np.int64)
    serpentine = np.where(ij[:, 1] % 2 == 0, ij[:, 0], -ij[:, 0])
    return np.lexsort((serpentine, ij[:, 1]))


@njit
def _serpentine_sort(xy, max_cells):
    """:func:`_spatial_order`'s permutation: points in square cells of 4 times the mean
    spacing from the lower-left corner, sorted by row, then by column (descending in odd
    rows), then by index (a stable counting sort).  Empty when the grid would have more
    than ``max_cells`` cells."""
    n = len(xy)
    x0, y0, x1, y1 = xy[0, 0], xy[0, 1], xy[0, 0], xy[0, 1]
    for i in range(1, n):
        x0, y0 = min(x0, xy[i, 0]), min(y0, xy[i, 1])
        x1, y1 = max(x1, xy[i, 0]), max(y1, xy[i, 1])
    cell = max(np.sqrt(max(x1 - x0, 1e-9) * max(y1 - y0, 1e-9) / n) * 4.0, 1e-9)
    ix = np.empty(n, dtype=np.int64)
    iy = np.empty(n, dtype=np.int64)
    nx, ny = 0, 0
    for i in range(n):
        fx = np.floor((xy[i, 0] - x0) / cell)
        fy = np.floor((xy[i, 1] - y0) / cell)
        if not (fx >= 0 and fy >= 0 and fx < max_cells and fy < max_cells):
            return np.empty(0, dtype=np.int64)
        ix[i], iy[i] = int(fx), int(fy)
        nx, ny = max(nx, ix[i] + 1), max(ny, iy[i] + 1)
    if nx * ny > max_cells:
        return np.empty(0, dtype=np.int64)
    key = np.empty(n, dtype=np.int64)
    for i in range(n):
        col = ix[i] if iy[i] % 2 == 0 else nx - 1 - ix[i]
        key[i] = iy[i] * nx + col
    return bucket_by_cell(key, nx * ny)[1]


def _int32(index: np.ndarray) -> np.ndarray:
    """Qhull's simplex and neighbour indices as the kernels take them (C int32: no copy)."""
    return np.ascontiguousarray(index, dtype=np.int32)


def _barycentric(tri: Delaunay, simplex: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (n, 3) of ``query`` in triangles ``simplex`` (no qhull transform)."""
    p = tri.points[tri.simplices[simplex]]                    # (n, 3, 2)
    v0, v1, v2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], query - p[:, 0]
    det = v0[:, 0] * v1[:, 1] - v0[:, 1] * v1[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        l1 = (v2[:, 0] * v1[:, 1] - v2[:, 1] * v1[:, 0]) / det
        l2 = (v0[:, 0] * v2[:, 1] - v0[:, 1] * v2[:, 0]) / det
    bary = np.column_stack([1.0 - l1 - l2, l1, l2])
    return np.where(np.isfinite(bary), bary, -np.inf)


def _locate(tri: Delaunay, query: np.ndarray, max_steps: int = 500,
            at_vertex: Optional[np.ndarray] = None):
    """Triangle holding each query point (-1 outside the hull) and its barycentric coordinates.

    A visibility walk (which terminates on Delaunay triangulations), compiled:
    the queries are visited in a serpentine order (:func:`_spatial_order`) and
    each walk starts in the triangle of the previous one, stepping across the
    edge facing the most negative barycentric coordinate, so a walk is a few
    steps.  Faster than ``Delaunay.find_simplex``, whose per-simplex
    transforms dominate the cost on large ground sets.

    A walk longer than ``max_steps`` is *lost* (the first queries, walking from
    triangle 0, usually are); lost queries get ``find_simplex``'s answers
    (:func:`_settle_lost`).  ``at_vertex``: optional mask of ``tri.points``;
    see :func:`_settle_lost`.
    """
    query = np.ascontiguousarray(query, dtype=np.float64)
    order = _spatial_order(query)
    points = np.ascontiguousarray(tri.points)
    simplices, neighbors = _int32(tri.simplices), _int32(tri.neighbors)
    simplex, bary, _ = _walk(points, simplices, neighbors, query, order, max_steps)
    lost = np.flatnonzero(simplex == -2)
    if len(lost) and not _settle_lost(tri, query, order[simplex[order] == -2], simplex, bary, at_vertex):
        found = tri.find_simplex(query[lost])
        simplex[lost] = found
        ok = found >= 0
        bary[lost[ok]] = _barycentric(tri, found[ok], query[lost[ok]])
    return simplex, bary


# a lost query this far inside its triangle or outside a hull edge (in barycentric coordinates)
# has one answer, whichever exact-enough method finds it (Sylva, not in the paper)
_CLEAR = 1e-9


def _settle_lost(tri: Delaunay, query: np.ndarray, lost: np.ndarray, simplex: np.ndarray,
                 bary: np.ndarray, at_vertex: Optional[np.ndarray]) -> bool:
    """Answer the lost queries (indices, in walk order) as ``Delaunay.find_simplex`` would, in place;
    False (nothing changed) when one of them is ambiguous.

    Sylva, not in the paper.  The lost queries walk again, without a step limit, each
    from the previous one's triangle.  A query clearly inside its triangle (every
    barycentric coordinate >= ``_CLEAR``) lies in no other; one clearly outside a hull
    edge, or outside the points' bounding box, in none: ``find_simplex`` finds the same.
    With ``at_vertex``, a query exactly on a vertex flagged there may keep any triangle
    around it: each gives it the coordinates (1, 0, 0) up to order and sign of zero, so
    a finite interpolated value that is not zero at that vertex comes out the same.
    Anything else (on or near an edge) is ambiguous: the caller asks ``find_simplex``
    about all lost queries in one call, as it would without this step.
    """
    q = query[lost]
    points = np.ascontiguousarray(tri.points)
    simplices = _int32(tri.simplices)
    s, _, low = _walk(points, simplices, _int32(tri.neighbors), q, np.arange(len(q)),
                      len(simplices) + 1)
    found = s >= 0
    clear = np.where(found, low >= _CLEAR, (s == -1) & (low <= -_CLEAR))
    eps = 100 * np.finfo(np.float64).eps      # find_simplex's own bounding-box test
    clear |= (s == -1) & np.any((q < tri.min_bound - eps) | (q > tri.max_bound + eps), axis=1)
    if at_vertex is not None:
        corners = simplices[np.where(found, s, 0)]                          # (n, 3)
        on = np.all(points[corners] == q[:, None, :], axis=2) & at_vertex[corners]
        clear |= found & on.any(axis=1)
    if not clear.all():
        return False
    simplex[lost] = s
    bary[lost] = 0.0
    bary[lost[found]] = _barycentric(tri, s[found], q[found])
    return True


@njit
def _walk(points, simplices, neighbors, query, order, max_steps):
    """:func:`_locate`'s walks, queries visited in ``order``; triangle of each query
    (-1 outside the hull, -2 lost), its barycentric coordinates, and the lowest
    coordinate where its walk stopped (>= -1e-12 in the triangle found; below when
    it left the hull)."""
    n = len(query)
    simplex = np.full(n, -1, dtype=np.int64)
    bary = np.zeros((n, 3))
    margin = np.zeros(n)
    eps = -1e-12
    start = 0
    for q in order:
        qx, qy = query[q, 0], query[q, 1]
        cur = start
        for _ in range(max_steps):
            a, b, c = simplices[cur, 0], simplices[cur, 1], simplices[cur, 2]
            v0x, v0y = points[b, 0] - points[a, 0], points[b, 1] - points[a, 1]
            v1x, v1y = points[c, 0] - points[a, 0], points[c, 1] - points[a, 1]
            v2x, v2y = qx - points[a, 0], qy - points[a, 1]
            det = v0x * v1y - v0y * v1x
            l1 = (v2x * v1y - v2y * v1x) / det
            l2 = (v0x * v2y - v0y * v2x) / det
            l0 = 1.0 - l1 - l2
            if not (np.isfinite(l0) and np.isfinite(l1) and np.isfinite(l2)):
                l0 = l1 = l2 = -np.inf
            worst, low = 0, l0
            if l1 < low:
                worst, low = 1, l1
            if l2 < low:
                worst, low = 2, l2
            margin[q] = low
            if low >= eps:
                simplex[q] = cur
                bary[q, 0], bary[q, 1], bary[q, 2] = l0, l1, l2
                start = cur
                break
            nxt = neighbors[cur, worst]
            if nxt < 0:          # crossed the hull: outside it
                break
            cur = nxt
        else:
            simplex[q] = -2
    return simplex, bary, margin


def tin_interpolate(xy: np.ndarray, values: np.ndarray, query: np.ndarray,
                     max_edge: Optional[float] = None, max_radius: Optional[float] = None) -> np.ndarray:
    """Linear interpolation in the Delaunay triangulation of ``xy``; NaN outside the hull
    and, when ``max_edge`` / ``max_radius`` is given, inside triangles with an edge longer
    than it / with a circumradius larger than it."""
    out = np.full(len(query), np.nan)
    if len(xy) < 3 or len(query) == 0:
        return out
    try:
        first = _spatial_order(xy)
        tri = Delaunay(xy[first])
        values = values[first]
    except QhullError:  # all points collinear or coincident
        return out
    # without max_edge only the values matter: on a vertex, any triangle around it gives its value
    at_vertex = (values != 0) if max_edge is None and np.isfinite(values).all() else None
    simplex, bary = _locate(tri, query, at_vertex=at_vertex)
    inside = simplex >= 0
    if max_edge is not None or max_radius is not None:
        pts = tri.points[tri.simplices]                       # (m, 3, 2)
        sides = np.linalg.norm(pts - np.roll(pts, 1, axis=1), axis=2)
        ok = np.ones(len(pts), dtype=bool)
        if max_edge is not None:
            ok &= sides.max(axis=1) <= max_edge
        if max_radius is not None:                            # R = abc / (4 area)
            u, v = pts[:, 1] - pts[:, 0], pts[:, 2] - pts[:, 0]
            area4 = 2.0 * np.abs(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0])
            ok &= sides.prod(axis=1) <= max_radius * area4
        inside &= np.where(inside, ok[np.maximum(simplex, 0)], False)
    return _tin_values(np.ascontiguousarray(values, dtype=np.float64), _int32(tri.simplices),
                       np.where(inside, simplex, -1), bary)


@njit
def _tin_values(values, simplices, simplex, bary):
    """Interpolated value in each query's triangle (NaN where ``simplex`` < 0), summed as
    numpy's ``(values[corners] * bary).sum(axis=1)`` does: left to right."""
    out = np.full(len(simplex), np.nan)
    for q in range(len(simplex)):
        s = simplex[q]
        if s >= 0:
            out[q] = (values[simplices[s, 0]] * bary[q, 0] + values[simplices[s, 1]] * bary[q, 1]) \
                + values[simplices[s, 2]] * bary[q, 2]
    return out


def lowest_per_cell(g: np.ndarray, cell_m: float) -> np.ndarray:
    """Indices of the lowest point (first of equals) of each ``cell_m`` square cell of local
    points ``g`` (0: of each distinct (x, y) position), cells in ascending (column, row) order."""
    if cell_m > 0:
        pick = _lowest_per_cell_kernel(np.ascontiguousarray(g, dtype=np.float64), float(cell_m),
                                       4 * len(g) + 1024)
        if len(pick):
            return pick
        ij = np.floor(g[:, :2] / cell_m).astype(np.int64)   # a sparse extent: sort instead
        order = np.lexsort((g[:, 2], ij[:, 1], ij[:, 0]))
        pos = ij[order]
    else:
        order = np.lexsort((g[:, 2], g[:, 1], g[:, 0]))
        pos = g[order, :2]
    first = np.ones(len(g), dtype=bool)
    first[1:] = np.any(pos[1:] != pos[:-1], axis=1)
    return order[first]


@njit
def _lowest_per_cell_kernel(g, cell, max_cells):
    """:func:`lowest_per_cell` with cells, on a dense grid of cells (Sylva, not in the paper):
    what ``np.lexsort((z, row, column))`` keeps (lowest z, NaN last, first of equals).
    Empty when the grid would have more than ``max_cells`` cells."""
    n = len(g)
    ix, iy, x0, y0, nx, ny = grid_cells(g, cell, max_cells)
    if nx == 0:
        return np.empty(0, dtype=np.int64)
    best = np.full(nx * ny, -1, dtype=np.int64)
    kept = 0
    for i in range(n):
        c = (ix[i] - x0) * ny + (iy[i] - y0)
        b = best[c]
        if b < 0:
            best[c] = i
            kept += 1
        elif g[i, 2] < g[b, 2] or (g[b, 2] != g[b, 2] and g[i, 2] == g[i, 2]):
            best[c] = i
    out = np.empty(kept, dtype=np.int64)
    j = 0
    for c in range(nx * ny):
        if best[c] >= 0:
            out[j] = best[c]
            j += 1
    return out


def idw(tree: cKDTree, values: np.ndarray, query: np.ndarray, k: int, power: float) -> np.ndarray:
    """Inverse-distance weighting of the ``k`` nearest samples (exact at a sample)."""
    k = int(min(k, tree.n))
    dist, idx = tree.query(query, k=k, workers=-1)
    if k == 1:
        return values[idx]
    exact = dist[:, 0] <= 1e-12
    with np.errstate(divide="ignore"):
        w = 1.0 / np.maximum(dist, 1e-12) ** power
    out = (w * values[idx]).sum(axis=1) / w.sum(axis=1)
    out[exact] = values[idx[exact, 0]]
    return out
