"""The voxel graph of the normalised cut: Hu et al. 2017 §4.1.

Voxels of the crown points with their mean, height and attributes, and the lattice edges between voxels
within the search radius weighted by Eq. 2 (:func:`voxel_graph`, :class:`VoxelGraph`); the column maxima
the tree tops are searched among, and the voxels the tops fall in.  The canopy density that widens the
top windows where the scan is sparse is Sylva's, not in the paper.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from ...cloud import PointCloud
from ...jit import njit
from ...kernels.grid import grid_cells


# --------------------------------------------------------------------------- voxel graph

@dataclass(eq=False)
class VoxelGraph:
    """Voxels of the crown points and their Eq. 2 affinities.

    ``xyz`` (m, 3) mean local x, y and height of each voxel; ``ijk`` integer
    voxel indices (relative to ``ij0``); ``point_voxel`` the voxel of each
    crown point; ``W`` the symmetric sparse affinity matrix (CSR);
    ``edges`` (e, 2) and ``weights`` (e,) the same as an edge list (i < j).
    """

    xyz: np.ndarray
    ijk: np.ndarray
    ij0: np.ndarray
    point_voxel: np.ndarray
    W: sp.csr_matrix
    edges: np.ndarray
    weights: np.ndarray

    @property
    def n(self) -> int:
        return len(self.xyz)


def voxel_graph(cloud: PointCloud, local: np.ndarray, height: np.ndarray,
                crown: np.ndarray, params: "NormalizedCut") -> VoxelGraph:
    """Voxelise the crown points and build the sparse Eq. 2 affinity graph."""
    idx = np.flatnonzero(crown)
    pitch = params.voxel_m
    x = local[idx, 0]
    y = local[idx, 1]
    z = height[idx]
    ix, iy, iz, i0, j0 = _voxel_cells(x, y, z, float(pitch))
    ij0 = np.array([i0, j0])
    nx, ny, nz = int(ix.max()) + 1, int(iy.max()) + 1, int(iz.max()) + 1
    if grid_fits((nx, ny), len(idx)):
        ukey, inv = _voxel_keys(ix, iy, iz, nx, ny, nz)
    else:     # a sparse extent: a sort instead of the column grid
        ukey, inv = np.unique((ix * ny + iy) * nz + iz, return_inverse=True)
    m = len(ukey)
    count = np.bincount(inv, minlength=m).astype(np.float64)

    def mean(values):
        return np.bincount(inv, weights=values, minlength=m) / count

    vxyz = np.column_stack([mean(x), mean(y), mean(z)])
    ijk = np.column_stack([ukey // (ny * nz), (ukey // nz) % ny, ukey % nz])

    features = []  # per-voxel I and C features, already divided by their scales
    intensity = cloud.attr("intensity")
    if intensity is not None:
        # ln I: differences are ratios, free of the sensor's units and of any statistic of
        # the tile, so a tree gets the same weights in any tiling (no per-tile scale)
        vals = np.log(np.maximum(np.asarray(intensity, dtype=np.float64)[idx], 1.0))
        features.append(mean(vals)[:, None] / params.sigma_intensity)
    rgb = [cloud.attr(c) for c in ("red", "green", "blue")]
    if all(c is not None for c in rgb):
        cols = np.column_stack([np.asarray(c, dtype=np.float64)[idx] for c in rgb])
        top = 65535.0 if cols.max(initial=0) > 255 else 255.0
        vcol = np.column_stack([mean(cols[:, j]) for j in range(3)]) / top
        features.append(vcol / params.sigma_colour)

    # the cylinder of Eq. 2 (horizontal distance <= radius_m), cut at +-height_m
    # vertically: an ellipsoid, i.e. a ball in coordinates with z scaled
    feat = np.hstack(features) if features else np.zeros((m, 0))
    groups = np.cumsum([0] + [f.shape[1] for f in features]).astype(np.int64)
    col = ukey // nz
    ucol, cstart = np.unique(col, return_index=True)
    indptr, indices, data, edges, w = _lattice_graph(
        vxyz, np.ascontiguousarray(feat), groups, ijk[:, 2], ucol, np.r_[cstart, m].astype(np.int64),
        int(ny), float(pitch), float(params.radius_m), float(params.height_m),
        float(params.sigma_h_m), float(params.sigma_v_m))
    if len(indices) < np.iinfo(np.int32).max:
        indptr = indptr.astype(np.int32)
    else:
        indices = indices.astype(np.int64)
    W = sp.csr_matrix((data, indices, indptr), shape=(m, m))
    W.has_sorted_indices = True
    return VoxelGraph(xyz=vxyz, ijk=ijk, ij0=ij0, point_voxel=inv, W=W,
                      edges=edges, weights=w)


@njit
def _voxel_cells(x, y, z, pitch):
    """(ix, iy, iz, i0, j0): every point's voxel (floor of its coordinates / ``pitch``), columns
    counted from the lowest (i0, j0)."""
    n = len(x)
    ix = np.empty(n, dtype=np.int64)
    iy = np.empty(n, dtype=np.int64)
    iz = np.empty(n, dtype=np.int64)
    i0 = j0 = 0
    for k in range(n):
        ix[k] = int(np.floor(x[k] / pitch))
        iy[k] = int(np.floor(y[k] / pitch))
        iz[k] = int(np.floor(z[k] / pitch))
        if k == 0 or ix[k] < i0:
            i0 = ix[k]
        if k == 0 or iy[k] < j0:
            j0 = iy[k]
    for k in range(n):
        ix[k] -= i0
        iy[k] -= j0
    return ix, iy, iz, i0, j0


@njit
def _voxel_keys(ix, iy, iz, nx, ny, nz):
    """``np.unique((ix * ny + iy) * nz + iz, return_inverse=True)`` by two counting sorts (by layer,
    then by column, stable): O(n) on the column grid instead of a sort of every point."""
    n = len(ix)
    by_z = np.zeros(nz + 1, dtype=np.int64)
    for k in range(n):
        by_z[iz[k] + 1] += 1
    for c in range(nz):
        by_z[c + 1] += by_z[c]
    order_z = np.empty(n, dtype=np.int64)
    for k in range(n):
        order_z[by_z[iz[k]]] = k
        by_z[iz[k]] += 1
    by_col = np.zeros(nx * ny + 1, dtype=np.int64)
    for k in range(n):
        by_col[ix[k] * ny + iy[k] + 1] += 1
    for c in range(nx * ny):
        by_col[c + 1] += by_col[c]
    order = np.empty(n, dtype=np.int64)
    for t in range(n):
        k = order_z[t]
        c = ix[k] * ny + iy[k]
        order[by_col[c]] = k
        by_col[c] += 1
    inv = np.empty(n, dtype=np.int64)
    ukey = np.empty(n, dtype=np.int64)
    m = -1
    last = -1
    for t in range(n):
        k = order[t]
        key = (ix[k] * ny + iy[k]) * nz + iz[k]
        if key != last:
            m += 1
            ukey[m] = key
            last = key
        inv[k] = m
    return ukey[:m + 1].copy(), inv


@njit
def _lattice_graph(xyz, feat, groups, iz, ucol, cstart, ny, pitch, radius, height, sigma_h, sigma_v):
    """Eq. 2 affinities of every voxel pair within the ellipsoid (horizontal
    distance² + (vertical distance x radius/height)² <= radius²) of their mean
    positions, found on the voxel lattice: a voxel's mean lies in its voxel,
    so its partners lie within ``reach`` columns and ``zreach`` layers.

    Voxels come sorted by (column, layer).  The edges (a < b) are found in
    that order, then the symmetric CSR is filled row by row (the partners
    before a voxel, then those after it), so no sort is needed.  Returns
    (indptr, indices, data) and the edge list (e, 2) with its weights w.
    ``feat``: per-voxel I and C features already divided by their scales,
    columns ``groups[g]:groups[g + 1]`` for feature g (the L2 norm of each
    feature's difference adds to the exponent, Eq. 2)."""
    m = len(xyz)
    reach = int(np.floor(radius / pitch)) + 1
    zreach = int(np.floor(height / pitch)) + 1
    squeeze = radius / height
    r2 = radius * radius
    ng = len(groups) - 1
    cap = max(16, 8 * m)
    ed = np.empty((cap, 2), dtype=np.int32)      # voxel ids < 2**31, as in the CSR indices
    ew = np.empty(cap, dtype=np.float64)
    ne = 0
    side = 2 * reach + 1
    half = side * side // 2          # offsets o >= half: the own column and those after it
    lo = np.empty(side * side, dtype=np.int64)    # voxel ranges of the
    hi = np.empty(side * side, dtype=np.int64)    # neighbouring columns
    seek = np.zeros(side * side, dtype=np.int64)  # per offset: the target only grows with c
    ncol = len(ucol)
    for c in range(ncol):
        key = ucol[c]
        cx = key // ny
        cy = key - cx * ny
        nc = 0
        for o in range(half, side * side):
            dx = o // side - reach
            ty = cy + o % side - reach
            if ty < 0 or ty >= ny:
                continue
            target = (cx + dx) * ny + ty
            k = seek[o]
            while k < ncol and ucol[k] < target:
                k += 1
            seek[o] = k
            if k < ncol and ucol[k] == target:
                lo[nc] = cstart[k]
                hi[nc] = cstart[k + 1]
                nc += 1
        for i in range(cstart[c], cstart[c + 1]):
            xi, yi, zi = xyz[i, 0], xyz[i, 1], xyz[i, 2]
            for t in range(nc):
                # layers ascend within a column and with i: the window only moves up
                if t == 0:
                    lo[0] = i + 1            # own column: the voxels after i
                while lo[t] < hi[t] and iz[lo[t]] < iz[i] - zreach:
                    lo[t] += 1
                for j in range(lo[t], hi[t]):
                    if iz[j] > iz[i] + zreach:
                        break
                    ex = xyz[j, 0] - xi
                    ey = xyz[j, 1] - yi
                    ez = xyz[j, 2] - zi
                    h2 = ex * ex + ey * ey
                    if h2 + (ez * squeeze) ** 2 > r2:
                        continue
                    expo = np.sqrt(h2) / sigma_h + abs(ez) / sigma_v
                    for g in range(ng):
                        f2 = 0.0
                        for q in range(groups[g], groups[g + 1]):
                            df = feat[j, q] - feat[i, q]
                            f2 += df * df
                        expo += np.sqrt(f2)
                    if ne == cap:
                        cap *= 2
                        grown = np.empty((cap, 2), dtype=np.int32)
                        grown[:ne] = ed[:ne]
                        ed = grown
                        grown_w = np.empty(cap, dtype=np.float64)
                        grown_w[:ne] = ew[:ne]
                        ew = grown_w
                    ed[ne, 0] = i
                    ed[ne, 1] = j
                    ew[ne] = np.exp(-expo)
                    ne += 1
    ed, ew = ed[:ne], ew[:ne]
    indptr = np.zeros(m + 1, dtype=np.int64)
    for e in range(ne):
        indptr[ed[e, 0] + 1] += 1
        indptr[ed[e, 1] + 1] += 1
    for i in range(m):
        indptr[i + 1] += indptr[i]
    fill = indptr[:-1].copy()
    indices = np.empty(2 * ne, dtype=np.int32)
    data = np.empty(2 * ne, dtype=np.float64)
    for e in range(ne):                  # partners before the row's voxel, ascending
        r = ed[e, 1]
        indices[fill[r]] = ed[e, 0]
        data[fill[r]] = ew[e]
        fill[r] += 1
    for e in range(ne):                  # then those after it, ascending
        r = ed[e, 0]
        indices[fill[r]] = ed[e, 1]
        data[fill[r]] = ew[e]
        fill[r] += 1
    return indptr, indices, data, ed, ew


def coord_min(a: np.ndarray) -> np.ndarray:
    """Minimum of each coordinate of (n, k) points, one 1-D reduction per coordinate (numpy's
    ``min(axis=0)`` on a tall narrow array is several times slower)."""
    return np.array([a[:, k].min() for k in range(a.shape[1])])


def coord_max(a: np.ndarray) -> np.ndarray:
    """Maximum of each coordinate of (n, k) points (see :func:`coord_min`)."""
    return np.array([a[:, k].max() for k in range(a.shape[1])])


def grid_fits(shape, n: int) -> bool:
    """Whether a 2-D grid of ``shape`` cells is small enough beside ``n`` points to be allocated
    (at most 8 cells per point plus 4 M); a sparser extent is handled without one."""
    return int(shape[0]) * int(shape[1]) <= 8 * n + 4_000_000


def column_maxima(xy: np.ndarray, z: np.ndarray, cell_m: float) -> np.ndarray:
    """Indices of the highest point of every ``cell_m`` column (ties: the lowest index), ascending.

    A tree top is always such a point, so the local-maximum search only needs
    these (a canopy-surface thinning; cells narrower than the window keep the
    window maximum nearly exact).  Cells are whole multiples of ``cell_m`` in the
    local frame (anchored on a global grid by the pipeline), never relative to
    the points' extent, so any tiling gives the same columns."""
    if len(xy) == 0:
        return np.zeros(0, dtype=np.int64)
    pick = _column_maxima_grid(xy, z, float(cell_m), 8 * len(xy) + 1_000_000)
    if len(pick):           # a grid of cells is cheaper than two sorts
        return pick
    ij = np.floor(xy / cell_m).astype(np.int64)
    ij -= coord_min(ij)
    key = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
    order = np.argsort(-z, kind="stable")
    _, first = np.unique(key[order], return_index=True)
    return np.sort(order[first])


@njit
def _column_maxima_grid(xy, z, cell, max_cells):
    """:func:`column_maxima` on a dense grid of cells; empty when it would exceed ``max_cells``
    cells (:func:`~sylva.core.kernels.grid.grid_cells`)."""
    ix, iy, x0, y0, nx, ny = grid_cells(xy, cell, max_cells)
    best = np.full(nx * ny, -1, dtype=np.int64)
    kept = 0
    for i in range(len(ix)):
        c = (ix[i] - x0) * ny + (iy[i] - y0)
        b = best[c]
        if b < 0:
            kept += 1
        if b < 0 or z[i] > z[b]:
            best[c] = i
    out = np.empty(kept, dtype=np.int64)
    k = 0
    for c in range(nx * ny):
        if best[c] >= 0:
            out[k] = best[c]
            k += 1
    return np.sort(out)


#: Half width (m) of the square neighbourhood of :func:`local_canopy_density`.
DENSITY_HALF_WIDTH_M = 5


def local_canopy_density(cloud: PointCloud, local: np.ndarray, crown: np.ndarray) -> np.ndarray:
    """Per point: canopy first returns per m² of canopy within the 1 m columns of the
    (2 x DENSITY_HALF_WIDTH_M + 1) m square around its own column (first returns of
    the crown points, all crown points without ``return_number``, over the occupied
    columns); 1 where there is no canopy.  Columns are whole metres of the local
    frame (anchored on a global grid by the pipeline), so the value depends on the
    neighbourhood only.  Sylva, not in Hu et al."""
    from scipy import ndimage

    n = len(local)
    out = np.ones(n)
    rn = cloud.attr("return_number")
    sel = crown if rn is None else crown & (np.asarray(rn) <= 1)
    if not sel.any():
        sel = crown
    if not sel.any():
        return out
    sel = np.flatnonzero(sel)
    lo, hi = (np.array(v) for v in _column_range(local, sel))
    lo, hi = lo - DENSITY_HALF_WIDTH_M, hi + DENSITY_HALF_WIDTH_M
    shape = tuple((hi - lo + 1).tolist())
    if not grid_fits(shape, n):      # a sparse extent: the whole cloud's mean
        out[:] = canopy_density(cloud, local, crown)
        return out
    i0, j0 = lo.tolist()
    counts = _column_counts(local, sel, i0, j0, *shape)
    occupied = (counts > 0).astype(np.float64)
    size = 2 * DENSITY_HALF_WIDTH_M + 1
    # box sums as exact integers (uniform_filter of 0/1 and counts, times the box area)
    csum = np.rint(ndimage.uniform_filter(counts, size=size, mode="constant") * size * size)
    osum = np.rint(ndimage.uniform_filter(occupied, size=size, mode="constant") * size * size)
    dens = np.where(osum > 0, csum / np.maximum(osum, 1.0), 1.0)
    return np.maximum(_at_columns(local, dens, i0, j0), 1e-3)


@njit
def _column_range(local, sel):
    """(lowest, highest) 1 m column (floor of x, of y) of the points ``sel``, as two integers each."""
    i0 = i1 = int(np.floor(local[sel[0], 0]))
    j0 = j1 = int(np.floor(local[sel[0], 1]))
    for k in sel:
        i = int(np.floor(local[k, 0]))
        j = int(np.floor(local[k, 1]))
        i0, i1, j0, j1 = min(i0, i), max(i1, i), min(j0, j), max(j1, j)
    return (i0, j0), (i1, j1)


@njit
def _column_counts(local, sel, i0, j0, nx, ny):
    """The number of the points ``sel`` in every 1 m column of the nx x ny grid from (i0, j0)."""
    counts = np.zeros((nx, ny))
    for k in sel:
        counts[int(np.floor(local[k, 0])) - i0, int(np.floor(local[k, 1])) - j0] += 1.0
    return counts


@njit
def _at_columns(local, grid, i0, j0):
    """Per point: the value of ``grid`` (from column (i0, j0)) at its 1 m column; 1 off the grid."""
    out = np.ones(len(local))
    nx, ny = grid.shape
    for k in range(len(local)):
        i = int(np.floor(local[k, 0])) - i0
        j = int(np.floor(local[k, 1])) - j0
        if 0 <= i < nx and 0 <= j < ny:
            out[k] = grid[i, j]
    return out


def canopy_density(cloud: PointCloud, local: np.ndarray, crown: np.ndarray) -> float:
    """Canopy first returns per m² of canopy: the crown points' first returns (all
    crown points when the cloud has no ``return_number``) over the number of
    occupied 1 m columns."""
    rn = cloud.attr("return_number")
    sel = crown if rn is None else crown & (np.asarray(rn) <= 1)
    if not sel.any():
        sel = crown
    xy = local[sel, :2]
    if len(xy) == 0:
        return 1.0
    ij = np.floor(xy - coord_min(xy)).astype(np.int64)
    ny = int(ij[:, 1].max()) + 1
    key = ij[:, 0] * ny + ij[:, 1]
    size = int(ij[:, 0].max() + 1) * ny
    if size <= 8 * len(key) + 1_000_000:      # an occupancy grid is cheaper than a sort
        occupied = np.zeros(size, dtype=bool)
        occupied[key] = True
        cells = int(occupied.sum())
    else:
        cells = len(np.unique(key))
    return len(xy) / cells


def _voxels_near(graph: VoxelGraph, xyz: np.ndarray, limit: float, pitch: float) -> np.ndarray:
    """Indices of the voxels in a column within ``limit`` of a point of ``xyz`` (local metres, z the
    height) and at most ``limit`` below the lowest such point, ascending: a superset of the voxels
    within ``limit`` of a point (a k-d tree of these, not of millions of voxels).  All voxels when
    the voxel grid's extent is too sparse for a column grid."""
    ij = graph.ijk[:, :2]
    if graph.n == 0 or len(xyz) == 0:
        return np.arange(graph.n)
    shape = coord_max(ij) + 1
    if not grid_fits(shape, graph.n):
        return np.arange(graph.n)
    r = int(np.ceil(limit / pitch)) + 1          # columns within limit (+1: a point anywhere in its cell)
    col = np.floor(xyz[:, :2] / pitch).astype(np.int64) - graph.ij0
    keep = ((col >= -r) & (col < shape + r)).all(axis=1)
    col, low = col[keep] + 2 * r, xyz[keep, 2] - limit
    lowest = np.full((int(shape[0]) + 4 * r, int(shape[1]) + 4 * r), np.inf)   # per column, padded
    for dx in range(-r, r + 1):
        for dy in range(-r, r + 1):
            np.minimum.at(lowest, (col[:, 0] + dx, col[:, 1] + dy), low)
    return np.flatnonzero(graph.xyz[:, 2] >= lowest[ij[:, 0] + 2 * r, ij[:, 1] + 2 * r])


def top_voxels(graph: VoxelGraph, tops, params: "NormalizedCut"):
    """The voxel of each tree top (nearest voxel mean, 3-D); tops without one are dropped.

    When several tops fall on one voxel, the first (highest, by TreeTops order) keeps it.
    """
    q = np.column_stack([tops.xy, tops.height])
    limit = max(params.radius_m, 2.0 * params.voxel_m)
    near = _voxels_near(graph, q, limit, params.voxel_m)
    dist, vox = cKDTree(graph.xyz[near]).query(q, distance_upper_bound=limit)
    ok = np.isfinite(dist)
    vox[ok] = near[vox[ok]]
    order = np.lexsort((np.arange(len(q)), -tops.height))
    order = order[ok[order]]
    vox_sorted = vox[order]
    _, first = np.unique(vox_sorted, return_index=True)
    keep = order[np.sort(first)]
    return (vox[keep].astype(np.int64), tops.tree_id[keep].astype(np.int64),
            tops.height[keep])


#: A crown's highest point lies within this fraction of its horizontal extent from the centroid of
#: its points (a suppressed tree's crown is centred on its apex; a lower piece of a taller tree's
#: crown, cut off by a sparse scan, is not).
APEX_CENTRED = 0.25

#: A topless crown centred within this many crown radii of a taller tree's apex is that tree's lower
#: crown (the skirt of a steep conifer crown that a sparse scan left apart from its top), not a tree
#: (``NormalizedCut.lower_crown_reach``'s default).
LOWER_CROWN_REACH = 0.6


def topless_crowns(graph: VoxelGraph, height: np.ndarray, xy: np.ndarray, top_voxel: np.ndarray,
                   min_points: int, min_extent_m: float, top_height: np.ndarray = None,
                   top_radius: np.ndarray = None, lower_reach: float = LOWER_CROWN_REACH):
    """(voxel, height) of the highest point of every connected component of the graph that holds no top,
    at least ``min_points`` crown points, spans at least ``min_extent_m`` horizontally, has
    its highest point near its centre (:data:`APEX_CENTRED`) and, given the tops' heights and
    crown radii, is not centred under a taller tree's apex (``lower_reach``).

    ``height`` and ``xy`` are those of the crown points (``graph.point_voxel`` order).  The tops
    are maxima of the canopy surface; a crown the graph joins to none of them (no edge within
    ``radius_m`` across, ``height_m`` up) lies under the canopy: a suppressed tree, segmented apart
    from the overstory as Hamraz et al. (2017, ISPRS J. 130) segment understory trees.  Smaller
    pieces stay crown fragments (attached to a tree within ``attach_m`` by the clean-up).  Ordered
    by height, then x, y (deterministic).  Sylva, not in Hu et al.

    The skirt of a steep crown is centred on its stem too: where the scan's returns lie farther
    apart up the flank than the graph's ``height_m`` (a conifer crown rising 4-7 m per metre
    out, 5 points/m2), the crown's lower part is a component of its own, as wide as a tree and
    highest at its inner rim.  A topless component whose points' centroid lies within
    ``lower_reach`` (:data:`LOWER_CROWN_REACH`) x ``top_radius`` of a taller tree's apex (a top higher than the
    component and than every other top within its own crown radius: not a bump on a crown's
    flank) is therefore that tree's lower crown, left to the clean-up; a suppressed tree stands
    beside its dominant, its crown centred about one crown radius from the dominant's apex."""
    from scipy.sparse.csgraph import connected_components

    none = (np.zeros(0, dtype=np.int64), np.zeros(0))
    if graph.n == 0:
        return none
    n_comp, comp = connected_components(graph.W, directed=False)
    has_top = np.zeros(n_comp, dtype=bool)
    has_top[comp[top_voxel]] = True
    pc = comp[graph.point_voxel]
    count = np.bincount(pc, minlength=n_comp)
    sel = np.flatnonzero((~has_top & (count >= min_points))[pc])
    if len(sel) == 0:
        return none
    # per candidate component: its points, highest first (ties: lowest x, then y)
    order = sel[np.lexsort((xy[sel, 1], xy[sel, 0], -height[sel], pc[sel]))]
    starts = np.flatnonzero(np.r_[True, pc[order][1:] != pc[order][:-1]])
    first = order[starts]
    p = xy[order]
    extent = (np.maximum.reduceat(p, starts) - np.minimum.reduceat(p, starts)).max(axis=1)
    centre = np.add.reduceat(p, starts) / count[pc[first], None]
    keep = (extent >= min_extent_m) & (np.hypot(*(xy[first] - centre).T) <= APEX_CENTRED * extent)
    if top_radius is not None and lower_reach > 0 and keep.any() and len(top_voxel):
        keep[keep] = ~_under_apex(centre[keep], height[first[keep]], graph.xyz[top_voxel, :2],
                                  top_height, top_radius, lower_reach)
    first = first[keep]
    first = first[np.lexsort((xy[first, 1], xy[first, 0], -height[first]))]
    return graph.point_voxel[first].astype(np.int64), height[first]


def _under_apex(centre: np.ndarray, apex_height: np.ndarray, top_xy: np.ndarray,
                top_height: np.ndarray, top_radius: np.ndarray, reach: float) -> np.ndarray:
    """Per component (centroid, highest point): whether it is centred within ``reach`` crown radii
    of a taller tree's apex (a top higher than every other top within its crown radius, and higher
    than the component)."""
    tops = cKDTree(top_xy)
    pairs = tops.sparse_distance_matrix(tops, float(top_radius.max()), output_type="ndarray")
    k, j, d = pairs["i"], pairs["j"], pairs["v"]
    bump = (top_height[j] < top_height[k]) & (d < top_radius[k])     # j lies in the crown of k, lower
    apex = np.ones(len(top_xy), dtype=bool)
    apex[j[bump]] = False
    near = cKDTree(centre).sparse_distance_matrix(tops, reach * float(top_radius.max()), output_type="ndarray")
    c, t, d = near["i"], near["j"], near["v"]
    hit = apex[t] & (top_height[t] > apex_height[c]) & (d < reach * top_radius[t])
    out = np.zeros(len(centre), dtype=bool)
    out[c[hit]] = True
    return out


@dataclass(frozen=True)
class CanopyColumns:
    """The 1 m columns of a tile for :func:`canopy_cover`: ``observed`` (any point, ground too, falls
    in it) and ``canopy`` (the height of its highest crown point, 0 for none), cell (i, j) being the
    column of local metres ``lo + (i, j)``."""

    lo: np.ndarray
    observed: np.ndarray
    canopy: np.ndarray


def canopy_columns(local: np.ndarray, height: np.ndarray, crown: np.ndarray):
    """The :class:`CanopyColumns` of the points, gridded in one pass; None when they hold no crown
    point or their extent is too sparse for a grid (:func:`grid_fits`), where every cover is 1."""
    if not crown.any():
        return None
    lo = np.floor(coord_min(local[:, :2])).astype(np.int64)
    shape = tuple((np.floor(coord_max(local[:, :2])).astype(np.int64) - lo + 1).tolist())
    if not grid_fits(shape, len(local)):     # a sparse extent: taken as closed
        return None
    observed, canopy = _grid_columns(local, height, crown, int(lo[0]), int(lo[1]), *shape)
    return CanopyColumns(lo, observed, canopy)


@njit
def _grid_columns(local, height, crown, i0, j0, nx, ny):
    """(observed, canopy) grids of :class:`CanopyColumns` (floor(x) - i0, floor(y) - j0 per point)."""
    observed = np.zeros((nx, ny), dtype=np.bool_)
    canopy = np.zeros((nx, ny))
    for k in range(len(height)):
        i = int(np.floor(local[k, 0])) - i0
        j = int(np.floor(local[k, 1])) - j0
        observed[i, j] = True
        if crown[k] and height[k] > canopy[i, j]:
            canopy[i, j] = height[k]
    return observed, canopy


def canopy_cover(columns, top_xy: np.ndarray, top_height: np.ndarray, reach_m: np.ndarray) -> np.ndarray:
    """Per top: the share of the observed 1 m columns within ``reach_m`` of it whose canopy
    reaches half the top's height (``columns``: :func:`canopy_columns`, None: 1).  Columns are
    whole metres of the local frame (anchored on a global grid by the pipeline), so the value
    depends on the neighbourhood only, never on the tile.  Sylva, not in Hu et al."""
    out = np.ones(len(top_xy))
    if len(top_xy) == 0 or columns is None:
        return out
    observed, canopy = columns.observed, columns.canopy
    shape = observed.shape
    centre = np.floor(top_xy).astype(np.int64) - columns.lo
    radius = np.ceil(reach_m).astype(np.int64)
    for r in np.unique(radius):
        g = np.arange(-r, r + 1)
        dx, dy = np.meshgrid(g, g, indexing="ij")
        disc = dx * dx + dy * dy <= r * r
        which = np.flatnonzero(radius == r)
        x = centre[which, 0][:, None] + dx[disc][None, :]
        y = centre[which, 1][:, None] + dy[disc][None, :]
        inside = (x >= 0) & (y >= 0) & (x < shape[0]) & (y < shape[1])
        x, y = np.where(inside, x, 0), np.where(inside, y, 0)
        seen = inside & observed[x, y]
        high = seen & (canopy[x, y] >= 0.5 * top_height[which][:, None])
        n_seen = seen.sum(axis=1)
        out[which] = np.where(n_seen > 0, high.sum(axis=1) / np.maximum(n_seen, 1), 1.0)
    return out
