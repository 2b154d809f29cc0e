"""Invariants of the batched modelling and export code, on synthetic trees (seeded; no reconstruction
involved, so they do not move when the skeleton methods change):

* golden outputs: the meshes, leaves, chains, QSM tables, skeleton WKB, GLB and 3D Tiles content and
  GeoPackage rows of a small forest equal ``tests/golden/forest_outputs.json`` — integers, indices
  and texts exactly, floats within a tolerance (:func:`same_outputs`), so a last-bit difference of
  another CPU passes and a real change of the outputs does not;
* batch == one at a time: meshes, leaves, simplification and branch chains give every tree the
  arrays of the single-tree path bit for bit, also for degenerate trees (one node, duplicate nodes,
  exact ties); batch sizes and a shared export cache change no output;
* kernels == numpy where numpy has the same function (row norms, medians, percentiles).

(The per-tree code the batched code replaced was kept here verbatim as a reference until the outputs
were pinned; it is in git history.)  ``python tests/test_forest_invariants.py`` says which
outputs differ from the golden file; ``--write`` rewrites it, for a change of the outputs that is meant.
"""
from __future__ import annotations

import json
import sqlite3
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from sylva.core import forest as F
from sylva.core import geometry as G
from sylva.core import leaves as LV
from sylva.core.cloud import PointCloud
from sylva.core.export import ExportFrame, TreeModel, write_glb, write_tileset
from sylva.core.export.georef import Georef
from sylva.core.export.gltf import glb_bytes
from sylva.core.export.tiles3d import coarse_error
from sylva.core.geometry import LevelOfDetail, join_forest, radii_or_default
from sylva.core.geometry.mesh import _lod
from sylva.core.io.gpkg import write_gpkg
from sylva.core.qsm import cylinders_from_skeleton, measure_qsm
from sylva.core.reconstruct.model import Reconstruction
from sylva.core.skeleton import Skeleton
from sylva.core.table import VectorTable

from fingerprints import (fingerprint, glb_fingerprint, json_fingerprint, rows_fingerprint, same_outputs,
                          wkb_fingerprint)

CRS = "EPSG:32632"
ORIGIN = np.array([500100.0, 5400200.0, 0.0])


# --------------------------------------------------------------------------- synthetic trees

def synthetic_skeleton(seed: int, n_branches: int = 9) -> Skeleton:
    """A trunk with side branches and twigs, plus the awkward cases: a duplicate node, a node
    with two children at the same bend angle (a tie), collinear runs (for simplification)."""
    rng = np.random.default_rng(seed)
    nodes, parent = [[0.0, 0.0, 0.0]], [-1]

    def chain(start, direction, n, step):
        prev = start
        for _ in range(n):
            direction = direction + rng.normal(0, 0.15, 3)
            direction /= np.linalg.norm(direction)
            nodes.append(list(np.asarray(nodes[prev]) + step * direction))
            parent.append(prev)
            prev = len(nodes) - 1
        return prev

    trunk = [0]
    for k in range(14):
        nodes.append([rng.normal(0, 0.02), rng.normal(0, 0.02), 0.8 * (k + 1)])
        parent.append(trunk[-1])
        trunk.append(len(nodes) - 1)
    nodes[trunk[-1]][:2] = nodes[trunk[-2]][:2]   # a vertical last trunk segment (for the tie below)
    nodes.append(list(nodes[trunk[5]]))          # a duplicate node (zero-length segment) on the trunk
    parent.append(trunk[5])
    dup = len(nodes) - 1
    chain(dup, np.array([1.0, 0.0, 0.4]), 3, 0.5)
    for b in range(n_branches):
        at = trunk[int(rng.integers(3, 13))]
        az = rng.uniform(0, 2 * np.pi)
        tip = chain(at, np.array([np.cos(az), np.sin(az), 0.5]), int(rng.integers(3, 8)), 0.45)
        if b % 3 == 0:
            chain(tip, np.array([0.0, 0.0, 1.0]), 2, 0.3)
        if b % 4 == 1:                            # a twig off the middle of the branch
            chain(len(nodes) - 2, np.array([np.sin(az), -np.cos(az), 0.3]), 3, 0.25)
    top = trunk[-1]                               # symmetric fork: two children bending equally
    for sx in (1.0, -1.0):
        nodes.append(list(np.asarray(nodes[top]) + [0.3 * sx, 0.0, 0.3]))
        parent.append(top)
    for k in range(4):                            # a collinear run for simplify_skeleton
        nodes.append(list(np.asarray(nodes[trunk[2]]) + [0.2 * (k + 1), 0.1 * (k + 1), 0.0]))
        parent.append(trunk[2] if k == 0 else len(nodes) - 2)
    sk = Skeleton(np.array(nodes), np.array(parent))
    return G.with_radii(sk, G.pipe_model_radii(sk, tip_radius_m=0.01, trunk_radius_m=0.12 + 0.02 * (seed % 3)))


def tiny_skeletons():
    """Degenerate trees: a lone root, a two-node stem, a stem with a duplicate tip."""
    one = Skeleton(np.array([[0.0, 0.0, 0.0]]), np.array([-1]), np.array([0.05]))
    two = Skeleton(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 2.0]]), np.array([-1, 0]), np.array([0.05, 0.02]))
    dup = Skeleton(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 2.0], [0.0, 0.0, 2.0]]), np.array([-1, 0, 1]),
                   np.array([0.05, 0.02, 0.01]))
    return [one, two, dup]


# --------------------------------------------------------------------------- digests

def _fake_reconstruct(skeletons):
    def reconstruct(tree_points, method):
        sk = skeletons[tree_points.tree_id]
        base = np.array([np.median(tree_points.xyz[:, 0]), np.median(tree_points.xyz[:, 1]), tree_points.ground_z])
        radius = sk.radius if tree_points.tree_id % 2 else None     # measured radii for odd trees
        return Reconstruction(Skeleton(sk.nodes + base, sk.parent.copy(), radius), "synthetic", 0.97, True,
                              flags=["fallback"] if tree_points.tree_id % 5 == 0 else [])
    return reconstruct


def forest_inputs(n_trees: int = 6):
    """A point cloud of ``n_trees`` synthetic trees (points around the skeleton nodes), labels and metrics."""
    rng = np.random.default_rng(11)
    skeletons, xyz, labels = {}, [], []
    for t in range(1, n_trees + 1):
        sk = synthetic_skeleton(100 + t)
        skeletons[t] = sk
        centre = np.array([20.0 * (t % 3), 25.0 * (t // 3), 0.0])
        pts = np.repeat(sk.nodes, 6, axis=0) + rng.normal(0, 0.08, (6 * len(sk.nodes), 3))
        if t % 2 == 0:                                 # a conical crown for some: needles
            pts[:, :2] *= np.clip(1.2 - pts[:, 2:3] / 12.0, 0.05, None)
        ground = rng.normal(0, 0.02, (60, 3)) + [0, 0, 0]
        ground[:, :2] = rng.uniform(-2, 2, (60, 2))
        for p, lab in ((pts, t), (ground, 0)):
            xyz.append(p + centre + ORIGIN)
            labels.append(np.full(len(p), lab))
    xyz = np.concatenate(xyz)
    labels = np.concatenate(labels)
    height = xyz[:, 2] - ORIGIN[2]
    cloud = PointCloud(xyz, {"height": height}, crs=None)
    ids = np.arange(1, n_trees + 1)
    metrics = SimpleNamespace(tree_id=ids, height=np.array([height[labels == t].max() for t in ids]),
                              crown_diameter=np.full(n_trees, 4.0), crown_base_height=np.full(n_trees, 3.0))
    return cloud, labels, metrics, skeletons


def model_forest(monkeypatch=None, lod: int = 1):
    cloud, labels, metrics, skeletons = forest_inputs()
    fake = _fake_reconstruct(skeletons)
    if monkeypatch is not None:
        monkeypatch.setattr(F, "reconstruct_tree", fake)
        trees = F.model_trees(cloud, labels, metrics, F.ModelOptions(method=object(), lod=lod))
    else:
        saved, F.reconstruct_tree = F.reconstruct_tree, fake
        try:
            trees = F.model_trees(cloud, labels, metrics, F.ModelOptions(method=object(), lod=lod))
        finally:
            F.reconstruct_tree = saved
    return cloud, trees


def compute_digests(tmp_dir, monkeypatch=None) -> dict:
    """Fingerprints (:func:`_h`) of every output of a small synthetic forest, by name."""
    from pathlib import Path

    tmp_dir = Path(tmp_dir)
    out = {}
    sks = [synthetic_skeleton(s) for s in range(4)]
    for s, sk in enumerate(sks):
        bs = G.branches(sk, sk.radius)
        out[f"branches_{s}"] = fingerprint(np.concatenate(bs.chains), [len(c) for c in bs.chains], bs.parent, bs.attach,
                                  bs.node_branch, bs.order, bs.continuation)
        bs0 = G.branches(sk)
        out[f"branches_noradii_{s}"] = fingerprint(np.concatenate(bs0.chains), bs0.continuation)
        for lod in (0, 1, 2):
            mesh = G.tree_mesh(sk, lod)
            out[f"mesh_{s}_lod{lod}"] = fingerprint(mesh.vertices, mesh.faces, mesh.metadata["face_branch"])
        for name, method in (("cards", LV.LeafCards()), ("needles", LV.NeedleClusters()),
                             ("distichy", LV.LeafCards(pattern="distichy", leaves_per_tip=4)),
                             ("decussation", LV.LeafCards(pattern="decussation", face_up=0.0))):
            lm = LV.grow_leaves(sk, method, seed=s)
            out[f"leaves_{s}_{name}"] = fingerprint(lm.vertices, lm.faces, lm.uvs, lm.tip, lm.base, lm.axis, lm.twig,
                                           lm.azimuth_deg, lm.node)
        simple = G.simplify_skeleton(sk, 0.05)
        out[f"simplify_{s}"] = fingerprint(simple.nodes, simple.parent, simple.radius)
        cyl, bpar = cylinders_from_skeleton(sk)
        q = measure_qsm(cyl, bpar, sk.nodes, base_z=0.0, tree_id=s)
        out[f"qsm_{s}"] = fingerprint(*[cyl[k] for k in sorted(cyl)], *[q.branches[k] for k in sorted(q.branches)],
                             [q.height_m, q.trunk_volume_m3, q.total_volume_m3, q.dbh_m])
        out[f"measures_{s}"] = fingerprint([G.wood_volume(sk), G.branch_count(sk), G.total_branch_length(sk)])
    # the whole modelling step (reconstruction replaced by the synthetic skeletons)
    cloud, trees = model_forest(monkeypatch)
    for t in trees:
        lv = t.leaves
        out[f"forest_tree_{t.tree_id}"] = fingerprint(t.skeleton.nodes, t.skeleton.parent, t.skeleton.radius, t.wood.vertices,
                                             t.wood.faces, t.wood.metadata["face_branch"], lv.vertices, lv.faces,
                                             lv.uvs, lv.tip, lv.azimuth_deg, t.base_local)
        rec = {k: v for k, v in t.record.items() if k not in ("dbh", "dbh_source")}
        out[f"forest_record_{t.tree_id}"] = fingerprint(np.array([k if isinstance(v, float) else f"{k}={v}"
                                                         for k, v in sorted(rec.items())], dtype=object),
                                               np.array([v for _, v in sorted(rec.items()) if isinstance(v, float)]))
    skel = F.skeleton_table(trees, cloud)
    out["skeleton_table"] = fingerprint(wkb_fingerprint(skel.geometries), skel.columns["n_chains"])
    cyl_t, br_t, tr_t = F.qsm_tables(trees, cloud)
    out["qsm_tables"] = fingerprint(*[np.asarray(v) for tb in (cyl_t, br_t) for v in tb.columns.values()],
                           tr_t.columns["n_cylinders"], tr_t.columns["total_volume_m3"])
    # exports
    frame = ExportFrame(CRS)
    models = [TreeModel(t.tree_id, ORIGIN + [5.0 * t.tree_id, 3.0, 0.0], t.wood, t.leaves,
                        {"height": float(t.record["total_branch_length"]), "kind": t.record["leaves"]})
              for t in trees]
    georef = Georef(frame, ORIGIN + [10.0, 10.0, 0.0])
    out["glb"] = glb_fingerprint(glb_bytes(models, georef))
    out["glb_coarse_noleaves"] = glb_fingerprint(glb_bytes(models, georef, lod="coarsest", leaves=False))
    out["coarse_error"] = fingerprint([coarse_error(m) for m in models])
    write_tileset(models, tmp_dir / "ts", frame, tile_size_m=12.0)
    ts = json.loads((tmp_dir / "ts" / "tileset.json").read_text())
    out["tileset_json"] = json_fingerprint(ts)
    for f in sorted((tmp_dir / "ts" / "content").glob("*.glb")):
        out[f"tileset_{f.stem}"] = glb_fingerprint(f.read_bytes())
    # GeoPackage rows
    pts = np.flatnonzero(np.arange(len(cloud)) % 7 == 0)
    import shapely
    tables = [skel, VectorTable("pts", "point", shapely.points(cloud.xyz[pts]),
                                {"i": pts.astype(np.int64), "h": np.where(pts % 3 == 0, np.nan, cloud.xyz[pts, 2]),
                                 "flag": pts % 2 == 0, "txt": np.array([f"p{i}" for i in pts], dtype=object)}, None)]
    write_gpkg(tmp_dir / "t.gpkg", tables)
    con = sqlite3.connect(tmp_dir / "t.gpkg")
    rows = []
    for name in ("skeletons", "pts"):
        rows.extend(con.execute(f'SELECT * FROM "{name}" ORDER BY fid'))
    rows.extend(con.execute("SELECT table_name, data_type, identifier, min_x, min_y, max_x, "
                            "max_y, srs_id FROM gpkg_contents ORDER BY table_name"))
    con.close()
    out["gpkg_rows"] = rows_fingerprint(rows)
    return out


#: The fingerprints of :func:`compute_digests` (written by ``python tests/test_forest_invariants.py
#: --write``, to be rewritten only for a change of the outputs that is meant, and said in its commit).
GOLDEN = Path(__file__).with_name("golden") / "forest_outputs.json"


def test_outputs_match_the_golden_fingerprints(tmp_path, monkeypatch):
    got = compute_digests(tmp_path, monkeypatch)
    want = json.loads(GOLDEN.read_text())
    assert set(got) == set(want)
    changed = same_outputs(got, want)
    assert not changed, f"outputs changed: {changed}"


def test_small_batches_give_the_same_outputs(tmp_path, monkeypatch):
    """model_trees meshes trees in batches of ~50 000 skeleton nodes and glb_bytes computes normals
    in batches of ~1e6 vertices; batches of a few trees / meshes change no output."""
    from sylva.core.export import gltf

    (tmp_path / "whole").mkdir()
    (tmp_path / "small").mkdir()
    whole = compute_digests(tmp_path / "whole", monkeypatch)
    monkeypatch.setattr(F, "_BATCH_NODES", 100)
    monkeypatch.setattr(gltf, "_BATCH_VERTICES", 3000)
    assert compute_digests(tmp_path / "small", monkeypatch) == whole


# --------------------------------------------------------------------------- batch == one at a time

def _all_skeletons():
    return [synthetic_skeleton(s) for s in range(5)] + tiny_skeletons()


@pytest.mark.parametrize("lod", [0, 1, 2])
def test_tree_meshes_batch_equals_one_at_a_time(lod):
    sks = _all_skeletons()
    batch = G.tree_mesh_arrays_batch(sks, lod)
    for sk, parts in zip(sks, batch):
        one = G.tree_mesh_arrays(sk, lod)
        assert np.array_equal(parts.vertices, one.vertices) and np.array_equal(parts.faces, one.faces)
        assert np.array_equal(parts.face_branch, one.face_branch) and np.array_equal(parts.kept, one.kept)
    meshes = G.tree_meshes(sks, lod)
    assert all(np.array_equal(m.vertices, p.vertices) and np.array_equal(m.faces, p.faces)
               for m, p in zip(meshes, batch))
    # a real tree gives a closed tube per kept branch: every edge is shared by exactly two faces
    f = meshes[0].faces
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert counts.min() == 2 and counts.max() == 2


@pytest.mark.parametrize("method", [LV.LeafCards(), LV.NeedleClusters(), LV.LeafCards(pattern="distichy")])
def test_grow_leaves_batch_equals_one_at_a_time(method):
    sks = _all_skeletons()
    seeds = [7 * k + 1 for k in range(len(sks))]
    batch = LV.grow_leaves_batch(sks, method, seeds)
    for sk, seed, lm in zip(sks, seeds, batch):
        one = LV.grow_leaves(sk, method, seed=seed)
        for name in ("vertices", "faces", "uvs", "tip", "base", "axis", "twig", "azimuth_deg", "node"):
            assert np.array_equal(getattr(lm, name), getattr(one, name)), name
        assert (lm.texture, lm.material, lm.extras) == (one.texture, one.material, one.extras)
    assert batch[0].n_leaves > 0 and batch[len(sks) - 3].n_leaves == 0   # the lone root has no tips


def test_simplify_and_branches_batch_equal_one_at_a_time():
    sks = _all_skeletons()
    for sk, simple in zip(sks, G.simplify_skeletons(sks, 0.05)):
        one = G.simplify_skeleton(sk, 0.05)
        assert np.array_equal(simple.nodes, one.nodes) and np.array_equal(simple.parent, one.parent)
        assert np.array_equal(simple.radius, one.radius) and np.array_equal(simple.is_added, one.is_added)
    assert len(G.simplify_skeleton(sks[0], 0.05)) < len(sks[0])          # the collinear run went
    for radii in (None, [sk.radius for sk in sks]):
        batch = G.branches_batch(sks, radii)
        for k, (sk, bs) in enumerate(zip(sks, batch)):
            one = G.branches(sk, None if radii is None else radii[k])
            assert [c.tolist() for c in bs.chains] == [c.tolist() for c in one.chains]
            for name in ("parent", "attach", "node_branch", "order", "continuation", "offsets", "nodes"):
                assert np.array_equal(getattr(bs, name), getattr(one, name)), name


def test_tie_is_broken_by_radius_then_index():
    """The symmetric fork at the top: equal bend, so the thicker child continues the trunk, else the first."""
    sk = synthetic_skeleton(0)
    top_children = np.flatnonzero(sk.parent == sk.parent[-5])[-2:]      # the fork's two children
    fork = sk.parent[top_children[0]]
    r = sk.radius.copy()
    r[top_children[1]] = r[top_children[0]] * 2
    assert G.branches(sk, r).continuation[fork] == top_children[1]
    assert G.branches(sk).continuation[fork] == top_children[0]


def test_shared_export_cache_changes_no_byte(tmp_path, monkeypatch):
    cloud, trees = model_forest(monkeypatch, lod=0)
    frame = ExportFrame(CRS)
    models = [TreeModel(t.tree_id, ORIGIN + [4.0 * t.tree_id, 0.0, 0.0], t.wood, t.leaves, {"n": k})
              for k, t in enumerate(trees)]
    cache = {}
    write_glb(models, tmp_path / "a.glb", frame, cache=cache)
    write_tileset(models, tmp_path / "ta", frame, tile_size_m=10.0, cache=cache)
    assert cache
    write_glb(models, tmp_path / "b.glb", frame)
    write_tileset(models, tmp_path / "tb", frame, tile_size_m=10.0)
    assert (tmp_path / "a.glb").read_bytes() == (tmp_path / "b.glb").read_bytes()
    for f in sorted((tmp_path / "ta").rglob("*")):
        if f.is_file():
            assert f.read_bytes() == (tmp_path / "tb" / f.relative_to(tmp_path / "ta")).read_bytes(), f.name
    # a model replaced by another object is not served from the cache of the old one
    models[0] = TreeModel(models[0].tree_id, models[0].base, trees[1].wood, None, {"n": 0})
    fresh = glb_bytes(models, Georef(frame, ORIGIN))
    assert glb_bytes(models, Georef(frame, ORIGIN), cache=cache) == fresh


# =========================================================================== compiled / forest passes
#
# The forest passes and kernels (core/jit.py) against the single-tree path and numpy, on generated
# skeletons and clouds that reach every branch: exact bend ties, zero-length segments, vertical twigs,
# lone roots, pruned branches, trees of fewer than 3 nodes, crowns that are and are not conical, NaN
# inputs for the kernels' NaN rules; outputs compared bit for bit (bytes, so signed zeros too).

_BATCH_NODES = F._BATCH_NODES
reconstruct_tree = None          # set by the tests (the synthetic skeletons)


# --------------------------------------------------------------------------- bit-for-bit helpers

def _bits(x):
    """Everything of an output that a byte could differ in, as a nested structure of bytes / scalars."""
    import dataclasses

    if isinstance(x, np.ndarray):
        if x.dtype == object:
            return ("O", x.shape, [_bits(v) for v in x.ravel()])
        return (str(x.dtype), x.shape, np.ascontiguousarray(x).tobytes())
    if isinstance(x, dict):
        return ("dict", [(k, _bits(v)) for k, v in x.items()])
    if isinstance(x, (list, tuple)):
        return (type(x).__name__, [_bits(v) for v in x])
    if isinstance(x, float):
        return ("float", np.float64(x).tobytes())
    if dataclasses.is_dataclass(x):
        return (type(x).__name__, [(f.name, _bits(getattr(x, f.name))) for f in dataclasses.fields(x)])
    if type(x).__name__ == "Trimesh":
        return ("Trimesh", _bits(np.asarray(x.vertices)), _bits(np.asarray(x.faces)), _bits(dict(x.metadata)))
    if isinstance(x, (np.floating,)):
        return (str(x.dtype), x.tobytes())
    return (type(x).__name__, repr(x))


def assert_same(a, b, what=""):
    assert _bits(a) == _bits(b), what


def random_skeleton(rng, m: int, grid: float = 0.25, vertical: float = 0.3) -> Skeleton:
    """A random tree on a coarse grid: many exact bend ties, collinear runs, duplicate (zero-length)
    segments and vertical runs; parents among the few previous nodes, so chains are long."""
    parent = np.full(m, -1, dtype=np.int64)
    nodes = np.zeros((m, 3))
    for i in range(1, m):
        p = int(rng.integers(max(0, i - 4), i))
        parent[i] = p
        step = rng.integers(-2, 3, 3) * grid
        step[2] = abs(step[2]) + grid * (rng.random() < 0.7)
        if rng.random() < vertical:
            step[:2] = 0.0                       # a vertical segment
        if rng.random() < 0.05:
            step[:] = 0.0                        # a duplicate node
        nodes[i] = nodes[p] + step
    return Skeleton(nodes + rng.normal(0, 1e-3, 3) * (rng.random() < 0.5), parent)


def _skeleton_zoo(seed: int = 0, n: int = 12):
    rng = np.random.default_rng(seed)
    sks = [synthetic_skeleton(s) for s in range(4)] + tiny_skeletons()
    sks += [random_skeleton(rng, int(rng.integers(3, 60))) for _ in range(n)]
    sks.append(Skeleton(np.c_[np.zeros((6, 2)), np.arange(6.0)], np.arange(-1, 5)))    # a vertical stem
    return sks


def _with_pipe_radii(sk):
    return G.with_radii(sk, G.pipe_model_radii(sk, tip_radius_m=0.01, trunk_radius_m=0.1))


# --------------------------------------------------------------------------- kernels == numpy

def test_norm3_is_numpys_row_norm():
    rng = np.random.default_rng(3)
    v = rng.standard_normal((5000, 3)) * 10.0 ** rng.integers(-200, 200, (5000, 3))
    v[:10] = [[0.0, -0.0, 0.0], [-0.0, -0.0, -0.0], [np.inf, 1, 1], [np.nan, 0, 0], [1e-320, 0, 0],
              [1e200, 1e200, 1e200], [-3.0, 4.0, 0.0], [0, 0, -1.0], [np.nan, np.inf, 0], [-np.inf, 0, 0]]
    with np.errstate(over="ignore", invalid="ignore"):
        assert_same(G.norm3(v), np.linalg.norm(v, axis=1))
        w = v[:4995].reshape(-1, 3, 3, 3)[..., 0, :]            # strided (t, K, 3), as the leaves use it
        assert_same(G.norm3(w), np.linalg.norm(w, axis=-1))


def _tip_radii(sk):
    return G.pipe_model_radii(sk) if len(sk) else np.zeros(0)


def test_skeleton_qsms_are_the_per_tree_measure_qsm():
    sks = [_with_pipe_radii(sk) for sk in _skeleton_zoo(8)] + tiny_skeletons()
    nodes, parent, off = join_forest(sks)
    radii = np.concatenate([sk.radius for sk in sks])
    bs = G.build_branch_set(parent, G.continuations(nodes, parent, radii))
    boff = G.tree_branches(bs, off)
    rng = np.random.default_rng(9)
    base = rng.normal(0, 0.5, len(sks)).tolist()
    xyz = [sk.nodes + rng.normal(0, 0.3, sk.nodes.shape) for sk in sks]
    dbh = rng.uniform(0.05, 0.5, len(sks)).tolist()
    src = ["measured" if k % 2 else "allometric" for k in range(len(sks))]
    top = [x[:, 2].max() for x in xyz]
    got = skeleton_qsms_of(nodes, parent, radii, bs, off, boff, base, top, dbh, src)
    for k, (sk, q, bset) in enumerate(zip(sks, got, G.split_branch_set(bs, off, boff))):
        cyl, bpar = cylinders_from_skeleton(sk, branch_set=bset)
        want = measure_qsm(cyl, bpar, xyz[k], base_z=base[k], tree_id=k)
        want.dbh_m, want.dbh_source = float(dbh[k]), src[k]
        assert_same(q, want, k)


def skeleton_qsms_of(nodes, parent, radii, bs, off, boff, base, top, dbh, src):
    from sylva.core.qsm import skeleton_qsms

    return skeleton_qsms(nodes, parent, radii, bs, off, boff, list(range(len(base))), base, top, dbh, src)


def _crowns(rng):
    """Clouds of single trees: cones (conical), cylinders and spheres (not), small and flat ones."""
    out = []
    for k in range(60):
        n = int(rng.integers(5, 400))
        z = rng.uniform(0, 10, n)
        shape = k % 4
        r = {0: (10 - z) * 0.4, 1: np.full(n, 2.0), 2: np.sqrt(np.maximum(25 - (z - 5) ** 2, 0)), 3: z * 0.3}[shape]
        a = rng.uniform(0, 2 * np.pi, n)
        xyz = np.c_[r * np.cos(a) + rng.normal(0, 0.1, n), r * np.sin(a), z]
        if k % 7 == 0:
            xyz[:, 2] = np.round(xyz[:, 2])                       # ties in height
        if k % 11 == 0:
            xyz[:, 2] = 4.0                                       # a flat crown: the 1e-6 span
        out.append((np.round(xyz, 2) if k % 5 == 0 else xyz, float(rng.uniform(-1, 6))))
    for xyz, zb in out[:8]:
        if len(xyz) > 100:
            nan = xyz.copy()
            nan[-1, 0] = np.nan                                   # NaN percentiles: never conical
            out.append((nan, zb))
    return out


def test_median_kernel_is_np_median():
    rng = np.random.default_rng(11)
    parts = [rng.normal(0, 1, int(rng.integers(1, 50))) for _ in range(40)]
    parts += [np.array([-0.0]), np.array([-0.0, -0.0]), np.round(rng.normal(0, 1, 20)), np.array([1.0, np.nan, 2.0])]
    values = np.concatenate(parts)
    off = np.r_[0, np.cumsum([len(p) for p in parts])].astype(np.int64)
    assert_same(F._median_kernel(values, off), np.array([np.median(p) for p in parts]))


# --------------------------------------------------------------------------- batch == single, kernels == numpy

@pytest.mark.parametrize("tol, passes", [(0.05, 8), (0.0, 8), (0.3, 2), (1.0, 8), (0.12, 1)])
def test_simplify_batch_is_one_tree_at_a_time(tol, passes):
    sks = [_with_pipe_radii(sk) for sk in _skeleton_zoo(4)]
    rng = np.random.default_rng(8)
    for sk in sks:
        sk.is_added = rng.random(len(sk)) < 0.3
    assert_same(G.simplify_skeletons(sks, tol, passes), [G.simplify_skeleton(sk, tol, passes) for sk in sks])


def test_branches_batch_is_one_tree_at_a_time_on_the_zoo():
    sks = _skeleton_zoo(3)
    for radii in (None, [_tip_radii(sk) if k % 2 else None for k, sk in enumerate(sks)]):
        for k, (sk, bs) in enumerate(zip(sks, G.branches_batch(sks, radii))):
            r = None if radii is None else (np.zeros(len(sk)) if radii[k] is None else radii[k])
            assert_same(bs, G.branches(sk, r), k)


@pytest.mark.parametrize("lod", [0, 1, 2, LevelOfDetail(sides=5, samples_per_segment=2, min_radius_m=0.02)])
def test_tube_batch_is_one_tree_at_a_time(lod):
    sks = _skeleton_zoo(6)
    radii = [None if k % 3 == 0 else _tip_radii(sk) * (1 + k % 4) for k, sk in enumerate(sks)]
    bsets = [None if k % 2 else G.branches(sk, radii_or_default(sk, r)) for k, (sk, r) in enumerate(zip(sks, radii))]
    got = G.tree_mesh_arrays_batch(sks, lod, radii, bsets)
    assert_same(got, [G.tree_mesh_arrays_batch([sk], lod, [r], [b])[0] for sk, r, b in zip(sks, radii, bsets)])
    if _lod(lod).min_radius_m >= 0.02:
        assert any(not p.kept.all() for p in got if len(p.kept))             # some branches were pruned


@pytest.mark.parametrize("method", [LV.LeafCards(), LV.NeedleClusters(), LV.LeafCards(pattern="distichy"),
                                    LV.LeafCards(pattern="decussation", face_up=0.0, leaves_per_tip=5),
                                    LV.LeafCards(tip_segments=1, leaves_per_tip=3, leaf_width_m=0.02),
                                    LV.NeedleClusters(tip_segments=9, clusters_per_tip=2, azimuth_jitter_deg=0.0),
                                    LV.LeafCards(leaves_per_tip=0), LV.LeafCards(leaves_per_tip=1, face_up=1.0)])
def test_leaves_batch_is_one_tree_at_a_time(method):
    sks = [_with_pipe_radii(sk) for sk in _skeleton_zoo(7) if len(sk) > 1] + tiny_skeletons()
    seeds = [3 * k + 1 for k in range(len(sks))]
    bsets = [None if k % 2 else G.branches(sk) for k, sk in enumerate(sks)]
    got = LV.grow_leaves_batch(sks, method, seeds, branch_sets=bsets)
    assert_same(got, [LV.grow_leaves_batch([sk], method, [seed], branch_sets=[b])[0]
                      for sk, seed, b in zip(sks, seeds, bsets)])


def test_leaves_of_vertical_and_degenerate_tips():
    """Vertical twigs (the y x d normal), zero-length tip segments (padding), a 180° turn (no transport),
    a near reversal (transported) and -0.0 coordinates: finite leaves, the same in a batch as alone."""
    t = 0.004
    nodes = np.array([[0, 0, 0], [0, 0, 1.0], [0, 0, 2.0], [0, 0, 2.0], [0, 0, 3.0], [0, 0, 2.5], [1, 0, 1.0],
                      [1, 0, 1.0], [2, 0, 1.0], [0, 0, 4.0], [np.sin(t), 0, 4.0 - np.cos(t)], [-1.0, 0, 1.0],
                      [0.0, 0, 1.0], [-0.0, -1.0, 0.0], [-0.0, -2.0, -0.0]])
    parent = [-1, 0, 1, 2, 3, 4, 1, 6, 7, 4, 9, 0, 11, 12, 13]
    sk = _with_pipe_radii(Skeleton(nodes, parent))
    for method in (LV.LeafCards(), LV.NeedleClusters(), LV.LeafCards(tip_segments=5, pattern="distichy"),
                   LV.LeafCards(tip_segments=2, face_up=0.0)):
        pair = LV.grow_leaves_batch([sk, sk], method, [1, 2])
        assert all(lm.n_leaves > 0 and np.isfinite(lm.vertices).all() for lm in pair)
        assert_same(pair[1], LV.grow_leaves(sk, method, seed=2))


def test_crown_spread_kernel_is_the_numpy_percentiles():
    rng = np.random.default_rng(10)
    crowns = _crowns(rng)
    want = [F.is_conical(xyz, zb) for xyz, zb in crowns]
    assert 5 < sum(want) < len(want) - 5
    xyz = np.concatenate([c[0] for c in crowns])
    off = np.r_[0, np.cumsum([len(c[0]) for c in crowns])].astype(np.int64)
    zb = np.array([c[1] for c in crowns])
    assert F._conical(xyz, off, zb).tolist() == want                # the batch is one crown at a time
    p_top, p_all = F._crown_spread_kernel(xyz, off, zb)
    for k, (pts, z) in enumerate(crowns):         # the percentiles themselves, as numpy computes them
        crown = pts[pts[:, 2] >= z]
        if len(crown) < 20:
            assert np.isnan(p_top[k]) and np.isnan(p_all[k])
            continue
        r = np.linalg.norm(crown[:, :2] - crown[:, :2].mean(axis=0), axis=1)
        rel = (crown[:, 2] - crown[:, 2].min()) / max(crown[:, 2].max() - crown[:, 2].min(), 1e-6)
        if (rel >= 0.75).sum() < 3:
            assert np.isnan(p_top[k]) and np.isnan(p_all[k])
            continue
        np.testing.assert_allclose([p_top[k], p_all[k]], [np.percentile(r[rel >= 0.75], 90), np.percentile(r, 90)],
                                   rtol=1e-12, err_msg=str(k))


def test_quality_says_sparse_or_noise_by_the_points_of_a_tree(monkeypatch):
    """A tree under MIN_TREE_POINTS (20) points is "sparse" in the trees table, under min_points (10) "noise"."""
    cloud, labels, metrics, skeletons = forest_inputs()
    for tree, keep in ((1, 15), (2, 5)):
        labels[np.flatnonzero(labels == tree)[keep:]] = 0
    monkeypatch.setattr(F, "reconstruct_tree", _fake_reconstruct(skeletons))
    quality = {t.tree_id: t.record["quality"] for t in F.model_trees(cloud, labels, metrics,
                                                                      F.ModelOptions(method=object(), lod=0))}
    assert quality[1] == "sparse" and quality[2] == "noise"
    assert len(quality) > 2 and {q for t, q in quality.items() if t > 2} <= {"ok", "fallback"}


if __name__ == "__main__":
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        digests = compute_digests(tmp)
    if "--write" in sys.argv:
        GOLDEN.parent.mkdir(exist_ok=True)
        GOLDEN.write_text(json.dumps(digests, indent=1, sort_keys=True) + "\n")
        print(f"wrote {len(digests)} fingerprints")
    else:
        print("changed:", same_outputs(digests, json.loads(GOLDEN.read_text())))

