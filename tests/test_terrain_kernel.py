"""The compiled kernels of height normalisation (serpentine order, ground thinning, the
visibility walk and its lost queries, the interpolation sum) and of SMRF's disk morphology
against the numpy/scipy code they replaced, kept here verbatim as references; results
must be equal bit for bit (NaN where NaN)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial import Delaunay, QhullError, cKDTree

from sylva.core import terrain
from sylva.core.cloud import PointCloud
from sylva.core.jit import njit
from sylva.core.terrain import SMRF
from sylva.core.terrain import ground as TG
from sylva.core.terrain import interpolation as TI


# --- references: the implementations the kernels replaced ------------------------------

def reference_spatial_order(xy):
    if len(xy) < 2:
        return np.arange(len(xy))
    lo = xy.min(axis=0)
    span = np.maximum(xy.max(axis=0) - lo, 1e-9)
    cell = max(np.sqrt(span[0] * span[1] / len(xy)) * 4.0, 1e-9)
    ij = np.floor((xy - lo) / cell).astype(np.int64)
    serpentine = np.where(ij[:, 1] % 2 == 0, ij[:, 0], -ij[:, 0])
    return np.lexsort((serpentine, ij[:, 1]))


@njit
def reference_walk(points, simplices, neighbors, query, max_steps):
    n = len(query)
    simplex = np.full(n, -1, dtype=np.int64)
    bary = np.zeros((n, 3))
    eps = -1e-12
    start = 0
    for q in range(n):
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
            if low >= eps:
                simplex[q] = cur
                bary[q, 0], bary[q, 1], bary[q, 2] = l0, l1, l2
                start = cur
                break
            nxt = neighbors[cur, worst]
            if nxt < 0:
                break
            cur = nxt
        else:
            simplex[q] = -2
    return simplex, bary


def reference_locate(tri, query, max_steps=500):
    query = np.ascontiguousarray(query, dtype=np.float64)
    order = reference_spatial_order(query)
    simplex = np.full(len(query), -1, dtype=np.int64)
    bary = np.zeros((len(query), 3))
    s, b = reference_walk(np.ascontiguousarray(tri.points), tri.simplices.astype(np.int64),
                          tri.neighbors.astype(np.int64), query[order], max_steps)
    simplex[order], bary[order] = s, b
    lost = np.flatnonzero(simplex == -2)
    if len(lost):
        found = tri.find_simplex(query[lost])
        simplex[lost] = found
        ok = found >= 0
        bary[lost[ok]] = TI._barycentric(tri, found[ok], query[lost[ok]])
    return simplex, bary


def reference_tin_interpolate(xy, values, query, max_edge=None):
    out = np.full(len(query), np.nan)
    if len(xy) < 3 or len(query) == 0:
        return out
    try:
        first = reference_spatial_order(xy)
        tri = Delaunay(xy[first])
        values = values[first]
    except QhullError:
        return out
    simplex, bary = reference_locate(tri, query)
    inside = simplex >= 0
    if max_edge is not None:
        pts = tri.points[tri.simplices]
        edges = np.linalg.norm(pts - np.roll(pts, 1, axis=1), axis=2).max(axis=1)
        inside &= np.where(inside, edges[simplex] <= max_edge, False)
    s = simplex[inside]
    out[inside] = (values[tri.simplices[s]] * bary[inside]).sum(axis=1)
    return out


def reference_thin(g, cell_m):
    if cell_m > 0:
        ij = np.floor(g[:, :2] / cell_m).astype(np.int64)
        order = np.lexsort((g[:, 2], ij[:, 1], ij[:, 0]))
        pos = ij[order]
    else:
        order = np.lexsort((g[:, 2], g[:, 1], g[:, 0]))
        pos = g[order, :2]
    g = g[order]
    first = np.ones(len(g), dtype=bool)
    first[1:] = np.any(pos[1:] != pos[:-1], axis=1)
    return g[first]


def reference_ground_elevation(loc, mask, query, cell_m, k=10, power=2.0):
    g = reference_thin(loc[mask], cell_m)
    query = np.asarray(query, dtype=np.float64)[:, :2]
    tree = cKDTree(g[:, :2])
    out = reference_tin_interpolate(g[:, :2], g[:, 2], query)
    outside = ~np.isfinite(out)
    if outside.any():
        out[outside] = terrain.idw(tree, g[:, 2], query[outside], k, power)
    return out


def reference_progressive_opening(surface, radii, thresholds):
    flagged = np.zeros(surface.shape, dtype=bool)
    last = surface
    for radius, threshold in zip(radii, thresholds):
        opened = ndimage.grey_opening(last, footprint=TG._disk(int(radius)), mode="nearest")
        flagged |= (last - opened) > threshold
        last = opened
    return flagged


def same(a, b):
    """Equal bit for bit (so NaN equals NaN and -0.0 differs from 0.0)."""
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


# --- inputs ---------------------------------------------------------------------------------

def ground_like(n, seed, size=150.0):
    """Centimetre-quantised ground points on rolling terrain (collinear and cocircular
    quadruples happen), as a LAS tile's."""
    rng = np.random.default_rng(seed)
    xy = np.round(rng.uniform(0.0, size, (n, 2)), 2)
    z = np.round(300.0 + 0.1 * xy[:, 0] + 2.0 * np.sin(xy[:, 1] / 9.0) + rng.normal(0, 0.05, n), 2)
    return np.column_stack([xy, z])


def queries_reaching_every_case(tri, rng, n):
    """Random points, every vertex, edge midpoints, points outside the hull but inside the
    bounding box, and beyond the bounding box."""
    pts = tri.points
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    s = tri.simplices[rng.integers(0, len(tri.simplices), n // 4)]
    mids = (pts[s[:, 0]] + pts[s[:, 1]]) / 2.0
    corner = lo + np.array([0.1, 0.1]) * (hi - lo)           # a hull of a disc leaves corners empty
    beyond = hi + rng.uniform(0.5, 3.0, (50, 2))
    return np.vstack([rng.uniform(lo, hi, (n, 2)), pts, mids,
                      lo + rng.uniform(0, 0.02, (30, 2)) * (hi - lo), corner[None, :], beyond])


# --- serpentine order and thinning ------------------------------------------------------------

@pytest.mark.parametrize("case", ["uniform", "quantised", "row", "same", "line", "two"])
def test_spatial_order_is_the_lexsort(case):
    rng = np.random.default_rng(3)
    xy = {"uniform": rng.uniform(0, 100, (20000, 2)),
          "quantised": np.round(rng.uniform(-20, 80, (20000, 2)), 0),     # duplicates
          "row": np.column_stack([rng.uniform(0, 50, 3000), np.full(3000, 7.0)]),
          "same": np.full((100, 2), 3.25),
          "line": np.column_stack([np.arange(5000.0), np.arange(5000.0) * 1e-13]),  # far too many cells
          "two": np.array([[1.0, 2.0], [0.5, 2.0]])}[case]
    got = TI._spatial_order(xy)
    assert same(got, reference_spatial_order(xy))
    if case == "line":
        assert len(TI._serpentine_sort(np.ascontiguousarray(xy), 4 * len(xy) + 1024)) == 0


@pytest.mark.parametrize("cell_m", [0.5, 1.0, 0.0])
def test_lowest_per_cell_is_the_lexsort(cell_m):
    rng = np.random.default_rng(5)
    g = np.round(rng.uniform([-30, -20, 100], [70, 80, 102], (30000, 3)), 1)   # ties in z and x, y
    g[::97, 2] = np.nan
    g[::89, 2] = -0.0 * g[::89, 2]                                             # -0.0 ties with 0.0
    assert same(g[terrain.lowest_per_cell(g, cell_m)], reference_thin(g, cell_m))


def test_lowest_per_cell_sparse_extent_sorts():
    g = np.array([[0.0, 0.0, 5.0], [1e7, 3.0, 1.0], [0.2, 0.1, 4.0], [1e7, 3.2, 0.5]])
    assert len(TI._lowest_per_cell_kernel(g, 0.5, 4 * len(g) + 1024)) == 0
    assert same(g[terrain.lowest_per_cell(g, 0.5)], reference_thin(g, 0.5))


# --- point location -------------------------------------------------------------------------

def _tri(seed=2, n=4000):
    g = ground_like(n, seed, size=60.0)
    g = reference_thin(g, 0.0)
    return Delaunay(g[reference_spatial_order(g[:, :2]), :2]), g


def test_lost_queries_clear_of_edges_get_find_simplex_answers():
    """With a short walk most queries are lost; those clearly inside a triangle or outside
    the hull are settled by the second walk with find_simplex's answers."""
    tri, _ = _tri()
    rng = np.random.default_rng(4)
    q = np.vstack([rng.uniform(tri.min_bound, tri.max_bound, (3000, 2)), tri.max_bound + [[1.0, 2.0]]])
    simplex, bary = TI._locate(tri, q, max_steps=3)
    ref_s, ref_b = reference_locate(tri, q, max_steps=3)
    order = TI._spatial_order(q)
    main, _, _ = TI._walk(np.ascontiguousarray(tri.points), TI._int32(tri.simplices),
                          TI._int32(tri.neighbors), q, order, 3)
    lost = order[main[order] == -2]
    assert len(lost) > 1000 and (ref_s[lost] == -1).sum() > 5
    s2, b2 = ref_s.copy(), ref_b.copy()
    assert TI._settle_lost(tri, q, lost, s2, b2, None)          # every lost query is clear
    assert same(simplex, ref_s) and same(bary, ref_b)


@pytest.mark.parametrize("max_steps", [3, 500])
def test_lost_queries_on_vertices_and_edges(max_steps):
    """Vertices and edge midpoints are ambiguous: without ``at_vertex`` the lost queries go
    to find_simplex all at once (same answers as before); with it, vertices are settled and
    the interpolated values are the same."""
    tri, g = _tri()
    values = g[reference_spatial_order(g[:, :2]), 2]
    rng = np.random.default_rng(6)
    q = queries_reaching_every_case(tri, rng, 3000)
    simplex, bary = TI._locate(tri, q, max_steps=max_steps)
    ref_s, ref_b = reference_locate(tri, q, max_steps=max_steps)
    assert same(simplex, ref_s) and same(bary, ref_b)
    s, b = TI._locate(tri, q, max_steps=max_steps, at_vertex=values != 0)
    inside = ref_s >= 0
    assert same(s >= 0, inside)
    ref_v = (values[tri.simplices[ref_s[inside]]] * ref_b[inside]).sum(axis=1)
    got_v = TI._tin_values(values, TI._int32(tri.simplices), s, b)[inside]
    assert same(got_v, ref_v)


def test_vertex_rule_needs_a_value_other_than_zero():
    tri, g = _tri()
    q = tri.points[:200]
    order = np.arange(len(q))
    s, b = np.full(len(q), -2, dtype=np.int64), np.zeros((len(q), 3))
    assert not TI._settle_lost(tri, q, order, s.copy(), b.copy(), None)
    assert not TI._settle_lost(tri, q, order, s.copy(), b.copy(), np.zeros(len(tri.points), bool))
    assert TI._settle_lost(tri, q, order, s, b, np.ones(len(tri.points), bool))
    assert (s >= 0).all() and np.isin(b, [0.0, 1.0]).all() and (b.sum(axis=1) == 1.0).all()


@pytest.mark.parametrize("max_edge", [None, 1.5])
@pytest.mark.parametrize("kind", ["ground", "grid"])
def test_tin_interpolate_matches_the_reference(kind, max_edge):
    rng = np.random.default_rng(9)
    if kind == "ground":
        g = reference_thin(ground_like(6000, 1, size=80.0), 0.5)
        xy, values = g[:, :2], g[:, 2]
    else:   # SMRF's fill: integer cell centres, cocircular everywhere, holes to fill
        known = rng.random((90, 90)) < 0.6
        rows, cols = np.nonzero(known)
        xy = np.column_stack([cols, rows]).astype(np.float64)
        values = np.round(rng.normal(200.0, 3.0, len(xy)), 2)
    q = np.vstack([rng.uniform(xy.min(axis=0) - 2, xy.max(axis=0) + 2, (20000, 2)), xy,
                   np.round(rng.uniform(xy.min(axis=0), xy.max(axis=0), (5000, 2)))])
    got = terrain.tin_interpolate(xy, values, q, max_edge=max_edge)
    assert same(got, reference_tin_interpolate(xy, values, q, max_edge=max_edge))
    assert np.isnan(got).any() and np.isfinite(got).mean() > 0.2


def test_ground_elevation_on_a_tile_sized_ground(monkeypatch):
    """A tile's worth of ground (50 k thinned points, 150 k queries including every ground
    point): the first queries' walks from triangle 0 are lost and settled, heights are
    the reference's bit for bit."""
    settled = []
    real = TI._settle_lost

    def spy(*args):
        settled.append(real(*args))
        return settled[-1]

    monkeypatch.setattr(TI, "_settle_lost", spy)
    rng = np.random.default_rng(12)
    ground = ground_like(60_000, 7)
    canopy = np.column_stack([rng.uniform(-3, 153, (30_000, 2)), rng.uniform(300, 340, 30_000)])
    loc = np.vstack([ground, canopy])
    mask = np.r_[np.ones(len(ground), bool), np.zeros(len(canopy), bool)]
    cloud = PointCloud(loc, {"classification": np.where(mask, 2, 1).astype(np.uint8)})
    loc = cloud.local_xyz()
    got = terrain.ground_elevation(cloud, loc, cell_m=0.5)
    assert settled == [True]
    assert same(got, reference_ground_elevation(loc, mask, loc, 0.5))
    h = terrain.height_above_ground(cloud, cell_m=0.5)
    assert same(h, loc[:, 2] - got)


# --- SMRF morphology ------------------------------------------------------------------------

@pytest.mark.parametrize("shape", [(1, 1), (1, 9), (9, 1), (3, 40), (40, 2), (25, 19), (70, 64)])
def test_disk_filter_is_ndimage(shape):
    """Same values; a tie of 0.0 and -0.0 may keep the other zero (no comparison sees it)."""
    rng = np.random.default_rng(sum(shape))
    signed = np.round(rng.normal(size=shape), 1)                  # ties, and -0.0
    g = signed + 0.0                                              # ties, no -0.0
    for r in [0, 1, 2, 3, 5, 8, 13, 18, 30]:
        fp = TG._disk(r)
        assert same(TG._disk_filter(g, r, False), ndimage.grey_erosion(g, footprint=fp, mode="nearest"))
        assert same(TG._disk_filter(g, r, True), ndimage.grey_dilation(g, footprint=fp, mode="nearest"))
        assert np.array_equal(TG._disk_filter(signed, r, False),
                              ndimage.grey_erosion(signed, footprint=fp, mode="nearest"))


def test_progressive_opening_is_the_reference():
    rng = np.random.default_rng(1)
    surface = np.round(300 + np.cumsum(rng.normal(0, 0.3, (120, 130)), axis=1)
                       + 25.0 * (rng.random((120, 130)) < 0.3), 2)
    radii = np.arange(1, 19)
    flags = TG._progressive_opening(surface, radii, 0.15 * radii)
    assert same(flags, reference_progressive_opening(surface, radii, 0.15 * radii))
    assert 0.05 < flags.mean() < 0.95
    low = TG._progressive_opening(-surface, [1], [5.0])
    assert same(low, reference_progressive_opening(-surface, [1], [5.0]))


def test_smrf_classification_is_unchanged(monkeypatch):
    from sylva.testing import synth

    stand = synth.make_stand(synth.StandSpec(width_m=60, depth_m=60, slope_deg=15, seed=2))
    scan = synth.simulate_scan(stand, synth.ScanSpec(pulse_density=10, seed=2))
    cloud = PointCloud(scan.cloud.xyz)                              # no classes: SMRF decides
    got = SMRF().classify(cloud)
    monkeypatch.setattr(TG, "_progressive_opening", reference_progressive_opening)
    monkeypatch.setattr(TG, "tin_interpolate", reference_tin_interpolate)
    assert same(got, SMRF().classify(cloud)) and 0.1 < got.mean() < 0.9


# --- without numba ----------------------------------------------------------------------------

def test_kernels_run_as_python():
    """``SYLVA_NO_JIT``: the kernels are plain Python with the same results."""
    rng = np.random.default_rng(0)
    xy = np.round(rng.uniform(0, 20, (300, 2)), 1)
    assert same(TI._serpentine_sort.py_func(xy, 2000), TI._serpentine_sort(xy, 2000))
    g = np.column_stack([xy, np.round(rng.normal(size=300), 1)])
    assert same(TI._lowest_per_cell_kernel.py_func(g, 0.5, 2000), TI._lowest_per_cell_kernel(g, 0.5, 2000))
    grid = np.round(rng.normal(size=(12, 15)), 1)
    half = np.array([3, 2, 2, 0])
    for dilate in (False, True):
        assert same(TG._chord_filter.py_func(grid, half, dilate), TG._chord_filter(grid, half, dilate))
    tri = Delaunay(xy[TI._spatial_order(xy)] + rng.normal(0, 1e-3, xy.shape))
    q = rng.uniform(-1, 21, (400, 2))
    args = (np.ascontiguousarray(tri.points), TI._int32(tri.simplices), TI._int32(tri.neighbors),
            q, TI._spatial_order(q), 500)
    for a, b in zip(TI._walk.py_func(*args), TI._walk(*args)):
        assert same(a, b)
    s, b, _ = TI._walk(*args)
    v = rng.normal(size=len(tri.points))
    simplices = TI._int32(tri.simplices)
    assert same(TI._tin_values.py_func(v, simplices, s, b), TI._tin_values(v, simplices, s, b))
