"""The compiled kernels of height normalisation (serpentine order, ground thinning, the visibility walk
and its lost queries, the interpolation sum) and of SMRF's disk morphology, against what they stand for:

* the serpentine order and the lowest point per cell: the kernels give what the functions' own sorting
  paths (for extents too sparse for a grid, ``np.lexsort``) give, and each cell keeps its lowest point;
* point location: the triangles and barycentric coordinates of scipy's ``Delaunay.find_simplex`` (any
  triangle around a query on an edge or vertex), whatever the walk length;
* the TIN: scipy's ``LinearNDInterpolator`` on the same triangulation, within 1e-9 m (a query on an edge
  or vertex may fall either side of a ``max_edge`` cut);
* ground elevation of a tile-sized ground: exact at the thinned ground points, within centimetres of
  the true surface, finite everywhere;
* SMRF's openings: ``ndimage.grey_erosion`` / ``grey_dilation`` / ``grey_opening`` bit for bit, the same
  classification with them, and the ground of a synthetic slope found;
* Python form == compiled form on ties and duplicates.

(The numpy/scipy implementations the kernels replaced were kept here as bit-for-bit references; they are
in git history.)"""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage
from scipy.interpolate import LinearNDInterpolator
from scipy.spatial import Delaunay

from sylva.core import terrain
from sylva.core.cloud import PointCloud
from sylva.core.terrain import SMRF
from sylva.core.terrain import ground as TG
from sylva.core.terrain import interpolation as TI


def ndimage_progressive_opening(surface, radii, thresholds):
    """SMRF's progressive opening with ``ndimage.grey_opening`` and the same disks."""
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

def _no_kernel(*args):
    return np.empty(0, dtype=np.int64)


@pytest.mark.parametrize("case", ["uniform", "quantised", "row", "same", "line", "two"])
def test_spatial_order_kernel_equals_the_sorting_path(case, monkeypatch):
    rng = np.random.default_rng(3)
    xy = {"uniform": rng.uniform(0, 100, (20000, 2)),
          "quantised": np.round(rng.uniform(-20, 80, (20000, 2)), 0),     # duplicates
          "row": np.column_stack([rng.uniform(0, 50, 3000), np.full(3000, 7.0)]),
          "same": np.full((100, 2), 3.25),
          "line": np.column_stack([np.arange(5000.0), np.arange(5000.0) * 1e-13]),  # far too many cells
          "two": np.array([[1.0, 2.0], [0.5, 2.0]])}[case]
    got = TI._spatial_order(xy)
    assert np.array_equal(np.sort(got), np.arange(len(xy)))                  # a permutation
    if case == "line":
        assert len(TI._serpentine_sort(np.ascontiguousarray(xy), 4 * len(xy) + 1024)) == 0
    monkeypatch.setattr(TI, "_serpentine_sort", _no_kernel)                  # the lexsort path
    assert same(got, TI._spatial_order(xy))


def assert_lowest_of_each_cell(g, cell_m, pick):
    """``pick`` holds one point per occupied cell, cells by ascending (column, row), each the cell's lowest
    point (NaN only when all are, -0.0 equal to 0.0), the first of equals."""
    pos = np.floor(g[:, :2] / cell_m).astype(np.int64) if cell_m > 0 else g[:, :2]
    cells, inv = np.unique(pos, axis=0, return_inverse=True)                 # ascending (column, row)
    inv = inv.ravel()
    z = np.where(np.isnan(g[:, 2]), np.inf, g[:, 2])
    low = np.full(len(cells), np.inf)
    np.minimum.at(low, inv, z)
    first = np.full(len(cells), len(g))
    np.minimum.at(first, inv, np.where(z == low[inv], np.arange(len(g)), len(g)))
    assert np.array_equal(pick, first)


@pytest.mark.parametrize("cell_m", [0.5, 1.0, 0.0])
def test_lowest_per_cell_keeps_the_lowest_of_each_cell(cell_m, monkeypatch):
    rng = np.random.default_rng(5)
    g = np.round(rng.uniform([-30, -20, 100], [70, 80, 102], (30000, 3)), 1)   # ties in z and x, y
    g[::97, 2] = np.nan
    g[::89, 2] = -0.0 * g[::89, 2]                                             # -0.0 ties with 0.0
    pos = np.floor(g[:, :2] / cell_m) if cell_m > 0 else g[:, :2]
    g[np.all(pos == pos[0], axis=1), 2] = np.nan                               # a cell whose points are all NaN
    pick = terrain.lowest_per_cell(g, cell_m)
    assert_lowest_of_each_cell(g, cell_m, pick)
    monkeypatch.setattr(TI, "_lowest_per_cell_kernel", _no_kernel)           # the lexsort path
    assert same(pick, terrain.lowest_per_cell(g, cell_m))


def test_lowest_per_cell_sparse_extent_sorts():
    g = np.array([[0.0, 0.0, 5.0], [1e7, 3.0, 1.0], [0.2, 0.1, 4.0], [1e7, 3.2, 0.5]])
    assert len(TI._lowest_per_cell_kernel(g, 0.5, 4 * len(g) + 1024)) == 0
    assert terrain.lowest_per_cell(g, 0.5).tolist() == [2, 3]


# --- point location -------------------------------------------------------------------------

def _tri(seed=2, n=4000):
    g = ground_like(n, seed, size=60.0)
    g = g[terrain.lowest_per_cell(g, 0.0)]
    return Delaunay(g[TI._spatial_order(g[:, :2]), :2]), g


def scipy_location(tri, q):
    """find_simplex's triangle of every query, and whether the query is clearly inside it or clearly
    outside the hull (not within 1e-9, in barycentric coordinates, of an edge: then it has one answer)."""
    s = tri.find_simplex(q)
    t = tri.transform[np.maximum(s, 0)]
    b = np.einsum("nij,nj->ni", t[:, :2], q - t[:, 2])
    low = np.minimum(b.min(axis=1), 1.0 - b.sum(axis=1))
    return s, np.where(s >= 0, low > 1e-9, True)


def assert_locations(tri, q, simplex, bary):
    """The walk's answers are find_simplex's, up to the triangle of a query on an edge or vertex."""
    expected, clear = scipy_location(tri, q)
    assert np.array_equal(simplex < 0, expected < 0)
    assert np.array_equal(simplex[clear], expected[clear])
    inside = simplex >= 0
    corners = tri.points[tri.simplices[simplex[inside]]]
    np.testing.assert_allclose((corners * bary[inside, :, None]).sum(axis=1), q[inside], rtol=0, atol=1e-9)
    assert (bary[inside] >= -1e-12).all()
    np.testing.assert_allclose(bary[inside].sum(axis=1), 1.0, rtol=0, atol=1e-12)
    return clear


def test_lost_queries_clear_of_edges_get_find_simplex_answers():
    """With a short walk most queries are lost; those clearly inside a triangle or outside
    the hull are settled by the second walk with find_simplex's answers."""
    tri, _ = _tri()
    rng = np.random.default_rng(4)
    q = np.vstack([rng.uniform(tri.min_bound, tri.max_bound, (3000, 2)), tri.max_bound + [[1.0, 2.0]]])
    order = TI._spatial_order(q)
    main, _, _ = TI._walk(np.ascontiguousarray(tri.points), TI._int32(tri.simplices),
                          TI._int32(tri.neighbors), q, order, 3)
    lost = order[main[order] == -2]
    expected, clear = scipy_location(tri, q)
    assert len(lost) > 1000 and (expected[lost] == -1).sum() > 5 and clear.all()
    s2, b2 = main.copy(), np.zeros((len(q), 3))
    assert TI._settle_lost(tri, q, lost, s2, b2, None)          # every lost query is clear
    simplex, bary = TI._locate(tri, q, max_steps=3)
    assert_locations(tri, q, simplex, bary)
    assert np.array_equal(simplex, expected)


@pytest.mark.parametrize("max_steps", [3, 500])
def test_lost_queries_on_vertices_and_edges(max_steps):
    """Vertices and edge midpoints are ambiguous: without ``at_vertex`` the lost queries go to
    find_simplex all at once; with it, vertices are settled; either way the triangles are find_simplex's
    (or another around the query) and the interpolated values are scipy's."""
    tri, g = _tri()
    values = g[TI._spatial_order(g[:, :2]), 2]
    rng = np.random.default_rng(6)
    q = queries_reaching_every_case(tri, rng, 3000)
    expected = LinearNDInterpolator(tri, values)(q)
    for at_vertex in (None, values != 0):
        simplex, bary = TI._locate(tri, q, max_steps=max_steps, at_vertex=at_vertex)
        clear = assert_locations(tri, q, simplex, bary)
        assert (~clear).sum() > len(tri.points)                # the vertices and midpoints are there
        got = TI._tin_values(values, TI._int32(tri.simplices), simplex, bary)
        assert same(np.isnan(got), np.isnan(expected))
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9)


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
def test_tin_interpolate_is_scipys_linear_interpolation(kind, max_edge):
    rng = np.random.default_rng(9)
    if kind == "ground":
        g = ground_like(6000, 1, size=80.0)
        g = g[terrain.lowest_per_cell(g, 0.5)]
        xy, values = g[:, :2], g[:, 2]
    else:   # SMRF's fill: integer cell centres, cocircular everywhere, holes to fill
        known = rng.random((90, 90)) < 0.6
        rows, cols = np.nonzero(known)
        xy = np.column_stack([cols, rows]).astype(np.float64)
        values = np.round(rng.normal(200.0, 3.0, len(xy)), 2)
    q = np.vstack([rng.uniform(xy.min(axis=0) - 2, xy.max(axis=0) + 2, (20000, 2)), xy,
                   np.round(rng.uniform(xy.min(axis=0), xy.max(axis=0), (5000, 2)))])
    got = terrain.tin_interpolate(xy, values, q, max_edge=max_edge)
    order = TI._spatial_order(xy)                     # the triangulation tin_interpolate builds
    tri = Delaunay(xy[order])
    expected = LinearNDInterpolator(tri, values[order])(q)
    simplex, clear = scipy_location(tri, q)
    if max_edge is not None:                          # NaN in triangles with an edge longer than max_edge
        pts = tri.points[tri.simplices]
        long = np.linalg.norm(pts - np.roll(pts, 1, axis=1), axis=2).max(axis=1) > max_edge
        expected[(simplex >= 0) & long[np.maximum(simplex, 0)]] = np.nan
    differ = np.isnan(got) != np.isnan(expected)
    assert not (differ & clear).any()                 # only a query on an edge or vertex may fall either side
    if max_edge is None:
        assert not differ.any()
    both = ~np.isnan(got) & ~np.isnan(expected)
    np.testing.assert_allclose(got[both], expected[both], rtol=0, atol=1e-9)
    assert np.isnan(got).any() and np.isfinite(got).mean() > 0.2


def test_ground_elevation_on_a_tile_sized_ground(monkeypatch):
    """A tile's worth of ground (50 k thinned points, 150 k queries including every ground point): the
    first queries' walks from triangle 0 are lost and settled; the TIN passes through the thinned ground
    points, lies within centimetres of the true surface, and IDW fills the queries outside its hull."""
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
    assert settled[0] is True
    assert np.isfinite(got).all()
    kept = loc[mask][terrain.lowest_per_cell(loc[mask], 0.5)]
    np.testing.assert_allclose(terrain.ground_elevation(cloud, kept, cell_m=0.5), kept[:, 2], rtol=0, atol=1e-9)
    xy = cloud.xyz[:, :2]
    err = got + (cloud.xyz[:, 2] - loc[:, 2]) - (300.0 + 0.1 * xy[:, 0] + 2.0 * np.sin(xy[:, 1] / 9.0))
    inside = np.all((xy > 1.0) & (xy < 149.0), axis=1)
    assert np.median(np.abs(err)) < 0.05 and np.abs(err[inside]).max() < 0.3      # 0.030 and 0.20 when written
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


def test_progressive_opening_is_ndimage_openings():
    rng = np.random.default_rng(1)
    surface = np.round(300 + np.cumsum(rng.normal(0, 0.3, (120, 130)), axis=1)
                       + 25.0 * (rng.random((120, 130)) < 0.3), 2)
    radii = np.arange(1, 19)
    flags = TG._progressive_opening(surface, radii, 0.15 * radii)
    assert same(flags, ndimage_progressive_opening(surface, radii, 0.15 * radii))
    assert 0.05 < flags.mean() < 0.95
    low = TG._progressive_opening(-surface, [1], [5.0])
    assert same(low, ndimage_progressive_opening(-surface, [1], [5.0]))


def test_smrf_finds_the_ground_of_a_slope_and_ndimage_openings_change_nothing(monkeypatch):
    from sylva.testing import synth

    stand = synth.make_stand(synth.StandSpec(width_m=60, depth_m=60, slope_deg=15, seed=2))
    scan = synth.simulate_scan(stand, synth.ScanSpec(pulse_density=10, seed=2))
    cloud = PointCloud(scan.cloud.xyz)                              # no classes: SMRF decides
    got = SMRF().classify(cloud)
    truth = scan.truth_kind == synth.GROUND
    assert (got & truth).sum() / got.sum() > 0.99 and (got & truth).sum() / truth.sum() > 0.99   # 0.999, 0.998
    monkeypatch.setattr(TG, "_progressive_opening", ndimage_progressive_opening)
    assert same(got, SMRF().classify(cloud))


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
