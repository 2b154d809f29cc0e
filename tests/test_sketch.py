"""Trees from two sketched profiles (the sketch paper §4–§7) and sylva:treefromsketch."""
import json

import numpy as np
import pytest
import shapely
import shapely.affinity
from scipy.spatial import cKDTree

from sylva.core.errors import InputError
from sylva.core.reconstruct import TreePoints, reconstruct_tree
from sylva.core.reconstruct.sketch import (SketchCompletion, SketchTree, crown_silhouettes, depth_retrieval,
                                           grow_small_branches, project_front, project_side, projection_error,
                                           stroke_graph, tree_from_sketch)
from sylva.core.skeleton import Skeleton

H = 20.0
# Hand-made strokes in "pixels" (y up): a trunk, a branch that starts just off the trunk line and crosses
# it, and a branch that crosses the trunk (leaving a short stub on the other side).
FRONT = [shapely.LineString([(100, 0), (100, 300), (102, 500)]),
         shapely.LineString([(101, 250), (60, 330), (20, 420)]),
         shapely.LineString([(90, 380), (160, 460), (180, 480)])]
# The side view: a leaning trunk, a branch starting 1 px off the trunk, one crossing it.
SIDE = [shapely.LineString([(0, 0), (5, 250), (10, 520)]),
        shapely.LineString([(4, 200), (60, 300), (90, 400)]),
        shapely.LineString([(8, 350), (-50, 450)])]


def _dist_to_lines(points, graph):
    """Distance of 2D points (view metres) to the segments of a stroke graph."""
    ok = graph.parent >= 0
    a, b = graph.nodes[graph.parent[ok]], graph.nodes[ok]
    ab = b - a
    p = points[:, None, :] - a[None]
    t = np.clip((p * ab[None]).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-18)[None], 0, 1)
    return np.linalg.norm(p - t[..., None] * ab[None], axis=-1).min(axis=1)


# --------------------------------------------------------------------------- §4 stroke graph

def test_stroke_graph_joins_crossings_and_snapped_ends():
    lines = [np.array([[0, 0], [0, 10.0]]),                  # trunk
             np.array([[-2, 4], [3, 9.0]]),                  # crosses the trunk at (0, 6)
             np.array([[0.1, 7], [-3, 10.0]]),               # ends 0.1 (1 % of the height) off the trunk
             np.array([[20, 20], [21, 22.0]])]               # far away: not connected
    g = stroke_graph(lines, height_m=20.0, name="front")
    assert g.scale == pytest.approx(20.0 / 22.0)             # the drawing (base 0 to top 22) is 20 m tall
    assert np.allclose(g.nodes[0], 0) and g.parent[0] == -1  # the root is the trunk's lowest vertex
    assert np.all(g.parent[1:] < np.arange(1, len(g.nodes)))  # parents before children
    assert g.dropped > 0 and g.nodes[:, 0].max() < 20 * g.scale  # the far stroke is left out
    kids = np.bincount(g.parent[1:], minlength=len(g.nodes))
    degree = kids + (g.parent >= 0)
    cross = np.argmin(np.linalg.norm(g.nodes - np.array([0, 6]) * g.scale, axis=1))
    assert np.linalg.norm(g.nodes[cross] - np.array([0, 6]) * g.scale) < 1e-9  # the crossing is a node
    assert degree[cross] == 4
    snap = np.argmin(np.linalg.norm(g.nodes - np.array([0, 7]) * g.scale, axis=1))
    assert np.linalg.norm(g.nodes[snap] - np.array([0, 7]) * g.scale) < 1e-9   # the snapped end's foot
    assert degree[snap] == 3

    def reaches(start, target):
        i = start
        while i >= 0:
            if i == target:
                return True
            i = g.parent[i]
        return False

    stub = np.argmin(np.linalg.norm(g.nodes - np.array([-2, 4]) * g.scale, axis=1))
    tip = np.argmin(np.linalg.norm(g.nodes - np.array([-3, 10]) * g.scale, axis=1))
    assert reaches(stub, cross) and reaches(tip, snap)
    # resampled: no segment longer than 1 % of the height (the snap link is 0.1 units = 0.09 m)
    seg = np.linalg.norm(g.nodes[1:] - g.nodes[g.parent[1:]], axis=1)
    assert seg.max() <= 0.01 * 20.0 + 1e-9


# --------------------------------------------------------------------------- §5 depth retrieval

def test_depth_retrieval_pairs_points_of_equal_height():
    """Eq. 4–6: front branch x = y − 5 and side branch x = −0.75 (y − 5) give (y − 5, −0.75 (y − 5), y)."""
    front = [np.array([[0, 0], [0, 10.0]]), np.array([[0, 5], [4, 9.0]])]
    side = [np.array([[0, 0], [0, 10.0]]), np.array([[0, 5], [-3, 9.0]])]
    nodes, parent, source = depth_retrieval(stroke_graph(front, 10.0), stroke_graph(side, 10.0))
    trunk = np.abs(nodes[:, 0]) < 1e-9
    assert np.allclose(nodes[trunk, 1], 0)                      # trunk over trunk
    br = nodes[~trunk]
    assert len(br) >= 30 and (source == 0).all()                # nothing left over for §5.3
    assert np.allclose(br[:, 0], br[:, 2] - 5, atol=1e-9)
    assert np.allclose(br[:, 1], -0.75 * (br[:, 2] - 5), atol=1e-9)
    first = np.flatnonzero(~trunk)[0]
    assert nodes[parent[first], 2] == pytest.approx(5.0) and abs(nodes[parent[first], 0]) < 1e-9


def test_branch_extension_follows_the_side_branch_down_to_its_fork():
    """§5.2: the side branch forks at 3 m, the front one at 6 m: the 3D branch leaves the trunk at 3 m,
    runs up the front trunk line (x = 0) while following the side branch, then out along the front branch."""
    front = [np.array([[0, 0], [0, 10.0]]), np.array([[0, 6], [3, 9.0]])]
    side = [np.array([[0, 0], [0, 10.0]]), np.array([[0, 3], [-3, 9.0]])]
    fg, sg = stroke_graph(front, 10.0), stroke_graph(side, 10.0)
    nodes, parent, source = depth_retrieval(fg, sg)
    off = np.abs(nodes[:, 1]) > 1e-9
    ext = off & (nodes[:, 2] < 6 - 1e-9)
    assert ext.sum() >= 10
    assert np.allclose(nodes[ext, 0], 0) and np.allclose(nodes[ext, 1], -0.5 * (nodes[ext, 2] - 3), atol=1e-9)
    lowest = np.flatnonzero(off)[np.argmin(nodes[off, 2])]
    assert nodes[parent[lowest], 2] == pytest.approx(3.0, abs=0.11) and abs(nodes[parent[lowest], 1]) < 1e-9
    # every node lies on both drawings
    assert _dist_to_lines(project_front(nodes), fg).max() < 1e-6
    assert _dist_to_lines(project_side(nodes), sg).max() < 1e-6


def test_complementarity_builds_side_only_branches():
    """§5.3: a side-view branch no front branch matched is built in a second pass: it rises from the
    trunk at its fork and, in the front view, lies over the front stroke passing there (the trunk)."""
    front = [np.array([[0, 0], [0, 10.0]]), np.array([[0, 5], [3, 9.0]])]
    side = [np.array([[0, 0], [0, 10.0]]), np.array([[0, 5], [-3, 9.0]]), np.array([[0, 3], [2, 6.0]])]
    fg, sg = stroke_graph(front, 10.0), stroke_graph(side, 10.0)
    nodes, parent, source = depth_retrieval(fg, sg)
    comp = source == 1
    assert comp.sum() >= 25
    assert np.allclose(nodes[comp, 0], 0) and np.allclose(nodes[comp, 1], 2 / 3 * (nodes[comp, 2] - 3), atol=1e-9)
    first = np.flatnonzero(comp)[0]
    assert nodes[parent[first], 2] == pytest.approx(3.0) and np.allclose(nodes[parent[first], :2], 0)
    assert _dist_to_lines(project_front(nodes), fg).max() < 1e-6
    assert _dist_to_lines(project_side(nodes), sg).max() < 1e-6


def test_projects_back_onto_both_drawings():
    """Fig. 14: the 3D main skeleton seen from the front and from the side lies on the strokes.

    Tolerance: mean distance under 2 % of the height (measured: 0.02 % front, 0.06 % side), no node
    farther than 5 %."""
    res = tree_from_sketch(FRONT, SIDE, H, SketchTree(grow=False))
    assert res.stats["n_main_nodes"] >= 150 and res.warnings == []
    for graph, proj in ((res.front, project_front), (res.side, project_side)):
        d = _dist_to_lines(proj(res.main_uvz), graph)
        assert d.mean() < 0.02 * H and d.max() < 0.05 * H
        # and the drawing is covered: every stroke node has a projected 3D node nearby
        back, _ = cKDTree(proj(res.main_uvz)).query(graph.nodes)
        assert back.max() < 0.05 * H
    front_err, side_err = projection_error(res)
    assert front_err < 0.02 * H and side_err < 0.02 * H
    # base at the origin, the top at the height, in metres
    assert np.allclose(res.skeleton.nodes[0], 0) and res.skeleton.nodes[:, 2].max() == pytest.approx(H, rel=1e-6)


def test_front_azimuth_turns_the_tree_about_its_base():
    a = tree_from_sketch(FRONT, SIDE, H, SketchTree(grow=False))
    b = tree_from_sketch(FRONT, SIDE, H, SketchTree(grow=False), front_azimuth_deg=90.0)
    # front looking east: its right is south (−y), the side drawing's right is east (+x)
    assert np.allclose(b.skeleton.nodes[:, 0], a.skeleton.nodes[:, 1])
    assert np.allclose(b.skeleton.nodes[:, 1], -a.skeleton.nodes[:, 0])
    assert np.allclose(b.skeleton.nodes[:, 2], a.skeleton.nodes[:, 2])


# --------------------------------------------------------------------------- §6 small branches

def test_small_branches_follow_table_1_angles():
    """On a straight trunk every sub-branch is straight: its angle to the trunk has cos θ in [0.5, 0.9]
    and two successive ones have cos φ in [−0.5, 0.5]; each is σ = 0.3 of the trunk long."""
    z = np.linspace(0, 10, 101)
    trunk = Skeleton(np.column_stack([np.zeros(101), np.zeros(101), z]), np.r_[-1, np.arange(100)])
    grown, level = grow_small_branches(trunk, SketchTree(levels=1, crowd_max=1000), height_m=10.0)
    first = np.flatnonzero((level == 1) & (level[np.maximum(grown.parent, 0)] == 0))
    assert len(first) == 8
    d = grown.nodes[first] - grown.nodes[grown.parent[first]]
    d /= np.linalg.norm(d, axis=1)[:, None]
    assert np.all((d[:, 2] >= 0.5 - 1e-9) & (d[:, 2] <= 0.9 + 1e-9))
    cphi = (d[1:] * d[:-1]).sum(axis=1)
    assert np.all((cphi >= -0.5 - 1e-9) & (cphi <= 0.5 + 1e-9))
    sizes = np.diff(np.r_[first, len(grown)])
    assert np.all(sizes == 29)  # S_1..S_m, m = σk = 0.3 × 101 nodes → 30 nodes, S_1 placed on the bud S_x
    tips = grown.nodes[np.r_[first[1:], len(grown)] - 1]
    length = np.linalg.norm(tips - grown.nodes[grown.parent[first]], axis=1)
    assert np.allclose(length, 2.9)  # 29 segments of 0.1 m


def test_small_branches_stay_inside_the_silhouettes():
    fsil = [shapely.Point(100, 330).buffer(150).intersection(shapely.box(-1000, 120, 1000, 500))]
    ssil = [shapely.box(-80, 150, 100, 520)]
    res = tree_from_sketch(FRONT, SIDE, H, SketchTree(), front_silhouette=fsil, side_silhouette=ssil)
    small = res.level > 0
    assert small.sum() > 200 and set(np.unique(res.level)) == {0, 1, 2}
    uvz = res.skeleton.nodes  # azimuth 0: x = u, y = v
    fm = shapely.affinity.affine_transform(fsil[0], [res.front.scale, 0, 0, res.front.scale,
                                                     -100 * res.front.scale, 0])
    sm = shapely.affinity.affine_transform(ssil[0], [res.side.scale, 0, 0, res.side.scale, 0, 0])
    inside_f = shapely.contains_xy(fm.buffer(1e-9), uvz[small, 0], uvz[small, 2])
    inside_s = shapely.contains_xy(sm.buffer(1e-9), uvz[small, 1], uvz[small, 2])
    assert inside_f.all() and inside_s.all()
    # the silhouettes cut: without them the crown reaches farther out
    free = tree_from_sketch(FRONT, SIDE, H, SketchTree(), front_silhouette=[shapely.box(-1e4, -1e4, 1e4, 1e4)],
                            side_silhouette=[shapely.box(-1e4, -1e4, 1e4, 1e4)])
    assert np.abs(free.skeleton.nodes[:, 1]).max() > np.abs(uvz[:, 1]).max()


def test_same_seed_same_tree():
    a = tree_from_sketch(FRONT, SIDE, H, SketchTree(seed=3))
    b = tree_from_sketch(FRONT, SIDE, H, SketchTree(seed=3))
    c = tree_from_sketch(FRONT, SIDE, H, SketchTree(seed=4))
    assert np.array_equal(a.skeleton.nodes, b.skeleton.nodes) and np.array_equal(a.skeleton.parent, b.skeleton.parent)
    n = a.stats["n_main_nodes"]
    assert np.array_equal(a.skeleton.nodes[:n], c.skeleton.nodes[:n])   # drawn branches do not depend on the seed
    assert len(a.skeleton) != len(c.skeleton) or not np.array_equal(a.skeleton.nodes, c.skeleton.nodes)


# --------------------------------------------------------------------------- bad input

@pytest.mark.parametrize("front, side, height, words", [
    ([], SIDE, H, ["front", "no stroke"]),
    ([shapely.LineString()], SIDE, H, ["front", "no stroke"]),
    (FRONT, [shapely.LineString([(0, 5), (10, 5)]), shapely.LineString([(3, 5), (8, 5)])], H, ["side", "no trunk"]),
    (FRONT, None, H, ["side", "missing"]),
    (FRONT, SIDE, 0.0, ["height", "positive"]),
    (FRONT, SIDE, -3.0, ["height", "positive"]),
])
def test_bad_input_names_the_layer(front, side, height, words):
    with pytest.raises(InputError) as err:
        tree_from_sketch(front, side, height, names=("front", "side"))
    assert all(w in str(err.value) for w in words), str(err.value)


# --------------------------------------------------------------------------- airborne completion

def _airborne_tree(seed=0):
    rng = np.random.default_rng(seed)
    n = 1500
    th = rng.uniform(0, 2 * np.pi, n)
    r = 3.0 * np.sqrt(rng.uniform(0, 1, n))
    z = 6.0 + 8.0 * rng.uniform(0, 1, n) ** 0.7
    crown = np.column_stack([r * np.cos(th), r * np.sin(th) * 0.6, z])  # narrower north-south
    stem = np.column_stack([rng.normal(0, 0.05, 60), rng.normal(0, 0.05, 60), rng.uniform(0, 6, 60)])
    return TreePoints(1, np.vstack([crown, stem]), ground_z=0.0)


def test_sketch_completion_adds_small_branches_inside_the_crown():
    from sylva.core.reconstruct import GreedySkeleton

    tree = _airborne_tree()
    base = reconstruct_tree(tree, GreedySkeleton())
    rec = reconstruct_tree(tree, SketchCompletion())
    assert rec.method == "sketch_completion"
    n0 = len(base.skeleton)
    assert np.array_equal(rec.skeleton.nodes[:n0], base.skeleton.nodes)   # the greedy skeleton is kept
    added = rec.skeleton.nodes[n0:]
    assert len(added) > 50 and rec.stats["n_small_nodes"] == len(added)
    forks = base.skeleton.nodes[base.skeleton.n_children() >= 2, 2]
    xz, yz = crown_silhouettes(tree.xyz, forks.min())
    assert shapely.contains_xy(xz.buffer(1e-9), added[:, 0], added[:, 2]).all()
    assert shapely.contains_xy(yz.buffer(1e-9), added[:, 1], added[:, 2]).all()
    assert np.abs(added[:, 1]).max() < 0.6 * 3.0 + 0.3 + 1e-9                # the narrow side holds
    again = reconstruct_tree(tree, SketchCompletion())
    assert np.array_equal(again.skeleton.nodes, rec.skeleton.nodes)
    # too few points: the greedy skeleton's minimal stem comes back, flagged, without small branches
    tiny = reconstruct_tree(TreePoints(2, tree.xyz[:5], 0.0), SketchCompletion())
    assert len(tiny.skeleton) <= 2 and "not_completed" in tiny.flags


# --------------------------------------------------------------------------- the algorithm

def _tables(crs_epsg=25832, location=(500123.0, 5700456.0, 80.0)):
    import pyproj

    from sylva.core.table import VectorTable

    crs = pyproj.CRS.from_epsg(crs_epsg)
    front = VectorTable("front", "line", np.array(FRONT, dtype=object), {"id": np.arange(3)}, None)
    side = VectorTable("side", "line", np.array(SIDE, dtype=object), {"id": np.arange(3)}, None)
    loc = VectorTable("location", "point", np.array([shapely.Point(*location)], dtype=object), {"id": np.arange(1)},
                      crs)
    return front, side, loc


def _args(**kw):
    from sylva.algorithms import MODULES
    from sylva.algorithms.sketch import ALGORITHMS

    assert "sketch" in MODULES  # registered for the provider and the CLI
    (alg,) = ALGORITHMS
    assert alg.id == "treefromsketch"
    args = {p.name: (None if p.is_output else p.default) for p in alg.params}
    args.update(kw)
    return alg, args


def _check_outputs(glb, skel, trees, location):
    from sylva.core.export.georef import Georef
    from sylva.core.export.gltf import node_world_positions, read_glb
    from sylva.core.export.model import ExportFrame

    doc, binary = read_glb(glb)
    origin = json.loads(glb.with_name(glb.stem + ".origin.json").read_text())
    georef = Georef(ExportFrame("EPSG:25832"), origin["origin_source"])
    src = georef.enu_to_source(node_world_positions(doc, binary, "tree_1"))
    assert np.abs(src[:, :2].min(axis=0) + src[:, :2].max(axis=0) - 2 * np.array(location[:2])).max() < 20
    low = src[np.argmin(src[:, 2])]
    assert abs(low[2] - location[2]) < 0.2 and np.linalg.norm(low[:2] - location[:2]) < 1.0  # the stem's foot
    assert src[:, 2].max() == pytest.approx(location[2] + H, abs=1.0)
    xyz = np.concatenate([np.asarray(g.coords) for g in shapely.get_parts(skel)]) if not isinstance(skel, np.ndarray) \
        else skel
    root = xyz[np.argmin(xyz[:, 2])]
    assert np.allclose(root, location, atol=1e-6)            # the skeleton starts at the location
    assert xyz[:, 2].max() == pytest.approx(location[2] + H, abs=0.5)
    assert trees["tree_id"][0] == 1 and trees["height"][0] == pytest.approx(H, abs=0.5)
    assert trees["wood_volume"][0] > 0 and trees["n_branches"][0] > 10


def _zm_coords(wkb: bytes) -> np.ndarray:
    import struct

    (n,) = struct.unpack_from("<I", wkb, 5)
    off, out = 9, []
    for _ in range(n):
        (k,) = struct.unpack_from("<I", wkb, off + 5)
        out.append(np.frombuffer(wkb, "<f8", 4 * k, off + 9).reshape(k, 4))
        off += 9 + 32 * k
    return np.vstack(out)


def test_run_writes_a_georeferenced_tree(tmp_path):
    front, side, loc = _tables()
    location = (500123.0, 5700456.0, 80.0)
    alg, args = _args(FRONT=front, SIDE=side, LOCATION=loc, HEIGHT_M=H, MODEL=str(tmp_path / "tree.glb"))
    res = alg.run(args, __import__("sylva.algorithms.spec", fromlist=["Feedback"]).Feedback())
    glb = tmp_path / "tree.glb"
    assert res.files["MODEL"] == str(glb) and glb.exists() and (tmp_path / "tree.prj").exists()
    skel = res.vectors["SKELETON"]
    assert skel.has_m and skel.crs.to_epsg() == 25832
    xyzm = _zm_coords(skel.geometries[0])
    assert (xyzm[:, 3] > 0).all()                            # M = radius
    trees = res.vectors["TREES"]
    assert trees.geometry_type == "point" and trees.geometries[0].equals(shapely.Point(*location))
    _check_outputs(glb, xyzm[:, :3], trees.columns, location)
    # it exports like any other tree: exportmodels reads it back
    from sylva.core.export.read import read_models

    models, frame = read_models(glb)
    assert len(models) == 1 and np.allclose(models[0].base, location) and frame.pyproj_crs().to_epsg() == 25832
    assert models[0].attributes["method"] == "sketch" and models[0].leaves is not None


@pytest.mark.parametrize("which, words", [("FRONT", ["FRONT (front)", "empty"]), ("SIDE", ["SIDE", "missing"]),
                                           ("HEIGHT_M", ["HEIGHT_M", "positive"])])
def test_run_bad_input_names_the_parameter(which, words):
    from sylva.algorithms.spec import Feedback
    from sylva.core.table import VectorTable

    front, side, loc = _tables()
    kw = dict(FRONT=front, SIDE=side, LOCATION=loc, HEIGHT_M=H)
    if which == "FRONT":
        kw["FRONT"] = VectorTable("front", "line", np.array([], dtype=object), {}, None)
    elif which == "SIDE":
        kw["SIDE"] = None
    else:
        kw["HEIGHT_M"] = 0.0
    alg, args = _args(**kw)
    with pytest.raises(InputError) as err:
        alg.run(args, Feedback())
    assert all(w in str(err.value) for w in words), str(err.value)


def test_several_location_points_use_the_first_and_warn():
    from sylva.algorithms.spec import Feedback
    from sylva.core.table import VectorTable

    front, side, loc = _tables()
    two = VectorTable("location", "point", np.array([shapely.Point(1000, 2000), shapely.Point(5, 5)], dtype=object),
                      {}, loc.crs)
    warnings = []

    class F(Feedback):
        def warn(self, message):
            warnings.append(message)

    alg, args = _args(FRONT=front, SIDE=side, LOCATION=two, HEIGHT_M=H, SKELETON=None)
    res = alg.run(args, F())
    assert any("2 points" in w for w in warnings)
    assert res.vectors["TREES"].geometries[0].x == 1000


@pytest.mark.qgis
def test_treefromsketch_with_qgis_process(tmp_path):
    from conftest import qgis_process
    from sylva.core.io.gpkg import read_gpkg, write_gpkg

    front, side, loc = _tables()
    location = (500123.0, 5700456.0, 80.0)
    src = tmp_path / "sketch.gpkg"
    write_gpkg(src, [front, side, loc])
    glb, sk, tr = tmp_path / "tree.glb", tmp_path / "skel.gpkg", tmp_path / "trees.gpkg"
    out = qgis_process("run", "sylva:treefromsketch", f"--FRONT={src}|layername=front",
                       f"--SIDE={src}|layername=side", f"--LOCATION={src}|layername=location", f"--HEIGHT_M={H}",
                       f"--MODEL={glb}", f"--SKELETON={sk}", f"--TREES={tr}")
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
    skel = read_gpkg(sk, layer_name(sk))
    trees = read_gpkg(tr, layer_name(tr))
    first = skel.geometries[0]
    if isinstance(first, bytes):   # layers with M are read as ISO WKB (read_gpkg keeps M that GEOS 3.11 drops)
        first = shapely.from_wkb(first)
    xyz = np.concatenate([np.asarray(g.coords) for g in shapely.get_parts(first)])
    assert skel.crs.to_epsg() == 25832
    assert trees.geometries[0].distance(shapely.Point(location[:2])) < 1e-6
    _check_outputs(glb, xyz[:, :3], trees.columns, location)


def layer_name(path):
    from sylva.core.io.gpkg import layer_names

    (name,) = layer_names(path)
    return name
