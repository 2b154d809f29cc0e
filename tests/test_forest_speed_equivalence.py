"""The batched / vectorised modelling and export code gives the outputs of the per-tree code it replaced.

Two kinds of checks on synthetic trees (seeded; no reconstruction involved, so they do not move
when the skeleton methods change):

* pinned digests: the meshes, leaves, chains, QSM tables, skeleton WKB, GLB and 3D Tiles content
  and GeoPackage rows of a small forest, hashed, must equal the digests the code before the
  speed-up (per-tree loops, ``np.split`` chains, ``np.add.at`` normals) produced.  Floats are
  rounded (1e-8 m for float64 arrays, 1e-5 for float32 GLB data, 7 significant digits in JSON)
  before hashing, so the pins hold across platforms whose last-bit rounding differs; integers,
  indices and texts are hashed exactly.
* batch == one at a time: ``tree_meshes``, ``grow_leaves_batch``, ``simplify_skeletons`` and
  ``branches_batch`` give every tree bit-identical arrays to the single-tree functions, also for
  degenerate trees (one node, duplicate nodes, exact ties), and a shared export cache changes no byte.

Run ``python tests/test_forest_speed_equivalence.py`` to print the digests of the code in place.
"""
import hashlib
import json
import sqlite3
import sys
from types import SimpleNamespace

import numpy as np
import pytest

from sylva.core import forest as F
from sylva.core import geometry as G
from sylva.core import leaves as LV
from sylva.core.cloud import PointCloud
from sylva.core.export import ExportFrame, TreeModel, write_glb, write_tileset
from sylva.core.export.georef import Georef
from sylva.core.export.gltf import accessor_array, glb_bytes, read_glb
from sylva.core.export.tiles3d import coarse_error
from sylva.core.io.gpkg import write_gpkg
from sylva.core.qsm import cylinders_from_skeleton, measure_qsm
from sylva.core.reconstruct.model import Reconstruction, Skeleton
from sylva.core.table import VectorTable

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

def _h(*arrays) -> str:
    m = hashlib.sha256()
    for a in arrays:
        a = np.asarray(a)
        if a.dtype.kind == "f":
            a = np.round(a.astype(np.float64), 8) + 0.0      # + 0.0: no negative zeros
        elif a.dtype.kind == "O":
            a = np.array([str(x) for x in a.ravel()], dtype=object)
            m.update("|".join(a).encode())
            continue
        m.update(str(a.shape).encode())
        m.update(np.ascontiguousarray(a.astype(np.int64) if a.dtype.kind in "iub" else a).tobytes())
    return m.hexdigest()[:16]


def _round_json(obj):
    if isinstance(obj, float):
        return float(f"{obj:.7g}")
    if isinstance(obj, dict):
        return {k: _round_json(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_round_json(v) for v in obj]
    return obj


def glb_digest(data: bytes) -> str:
    """The content of a GLB: its JSON (floats rounded) and every accessor (float32 rounded to 1e-5)."""
    doc, binary = read_glb(data)
    parts = [json.dumps(_round_json(doc), sort_keys=True)]
    for k in range(len(doc.get("accessors", []))):
        a = accessor_array(doc, binary, k)
        parts.append(_h(np.round(a.astype(np.float64), 5)) if a.dtype.kind == "f" else _h(a))
    for im in doc.get("images", []):
        v = doc["bufferViews"][im["bufferView"]]
        parts.append(hashlib.sha256(binary[v["byteOffset"]:v["byteOffset"] + v["byteLength"]]).hexdigest()[:16])
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()[:16]


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
    from pathlib import Path

    tmp_dir = Path(tmp_dir)
    out = {}
    sks = [synthetic_skeleton(s) for s in range(4)]
    for s, sk in enumerate(sks):
        bs = G.branches(sk, sk.radius)
        out[f"branches_{s}"] = _h(np.concatenate(bs.chains), [len(c) for c in bs.chains], bs.parent, bs.attach,
                                  bs.node_branch, bs.order, bs.continuation)
        bs0 = G.branches(sk)
        out[f"branches_noradii_{s}"] = _h(np.concatenate(bs0.chains), bs0.continuation)
        for lod in (0, 1, 2):
            mesh = G.tree_mesh(sk, lod)
            out[f"mesh_{s}_lod{lod}"] = _h(mesh.vertices, mesh.faces, mesh.metadata["face_branch"])
        for name, method in (("cards", LV.LeafCards()), ("needles", LV.NeedleClusters()),
                             ("distichy", LV.LeafCards(pattern="distichy", leaves_per_tip=4)),
                             ("decussation", LV.LeafCards(pattern="decussation", face_up=0.0))):
            lm = LV.grow_leaves(sk, method, seed=s)
            out[f"leaves_{s}_{name}"] = _h(lm.vertices, lm.faces, lm.uvs, lm.tip, lm.base, lm.axis, lm.twig,
                                           lm.azimuth_deg, lm.node)
        simple = G.simplify_skeleton(sk, 0.05)
        out[f"simplify_{s}"] = _h(simple.nodes, simple.parent, simple.radius)
        cyl, bpar = cylinders_from_skeleton(sk)
        q = measure_qsm(cyl, bpar, sk.nodes, base_z=0.0, tree_id=s)
        out[f"qsm_{s}"] = _h(*[cyl[k] for k in sorted(cyl)], *[q.branches[k] for k in sorted(q.branches)],
                             [q.height_m, q.trunk_volume_m3, q.total_volume_m3, q.dbh_m])
        out[f"measures_{s}"] = _h([G.wood_volume(sk), G.branch_count(sk), G.total_branch_length(sk)])
    # the whole modelling step (reconstruction replaced by the synthetic skeletons)
    cloud, trees = model_forest(monkeypatch)
    for t in trees:
        lv = t.leaves
        out[f"forest_tree_{t.tree_id}"] = _h(t.skeleton.nodes, t.skeleton.parent, t.skeleton.radius, t.wood.vertices,
                                             t.wood.faces, t.wood.metadata["face_branch"], lv.vertices, lv.faces,
                                             lv.uvs, lv.tip, lv.azimuth_deg, t.base_local)
        rec = {k: v for k, v in t.record.items() if k not in ("dbh", "dbh_source")}
        out[f"forest_record_{t.tree_id}"] = _h(np.array([f"{k}={v:.8g}" if isinstance(v, float) else f"{k}={v}"
                                                         for k, v in sorted(rec.items())], dtype=object))
    skel = F.skeleton_table(trees, cloud)
    out["skeleton_table"] = hashlib.sha256(b"".join(skel.geometries)).hexdigest()[:16] + _h(skel.columns["n_chains"])
    cyl_t, br_t, tr_t = F.qsm_tables(trees, cloud)
    out["qsm_tables"] = _h(*[np.asarray(v) for tb in (cyl_t, br_t) for v in tb.columns.values()],
                           tr_t.columns["n_cylinders"], tr_t.columns["total_volume_m3"])
    # exports
    frame = ExportFrame(CRS)
    models = [TreeModel(t.tree_id, ORIGIN + [5.0 * t.tree_id, 3.0, 0.0], t.wood, t.leaves,
                        {"height": float(t.record["total_branch_length"]), "kind": t.record["leaves"]})
              for t in trees]
    georef = Georef(frame, ORIGIN + [10.0, 10.0, 0.0])
    out["glb"] = glb_digest(glb_bytes(models, georef))
    out["glb_coarse_noleaves"] = glb_digest(glb_bytes(models, georef, lod="coarsest", leaves=False))
    out["coarse_error"] = _h([coarse_error(m) for m in models])
    write_tileset(models, tmp_dir / "ts", frame, tile_size_m=12.0)
    ts = json.loads((tmp_dir / "ts" / "tileset.json").read_text())
    out["tileset_json"] = hashlib.sha256(json.dumps(_round_json(ts), sort_keys=True).encode()).hexdigest()[:16]
    for f in sorted((tmp_dir / "ts" / "content").glob("*.glb")):
        out[f"tileset_{f.stem}"] = glb_digest(f.read_bytes())
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
        rows.extend(repr(r) for r in con.execute(f'SELECT * FROM "{name}" ORDER BY fid'))
    rows.extend(repr(r) for r in con.execute("SELECT table_name, data_type, identifier, min_x, min_y, max_x, "
                                                  "max_y, srs_id FROM gpkg_contents ORDER BY table_name"))
    con.close()
    out["gpkg_rows"] = hashlib.sha256("\n".join(rows).encode()).hexdigest()[:16]
    return out


#: Digests of the code before the speed-up (per-tree loops), see the module docstring.
PINNED = {
    'branches_0': '5a7f41a58dac0ab7',
    'branches_noradii_0': 'ca956259519ca82e',
    'mesh_0_lod0': 'b05f713efa7b360e',
    'mesh_0_lod1': '3315d095259f1a44',
    'mesh_0_lod2': '3acbe772628654e1',
    'leaves_0_cards': 'fe18590737c9ae5a',
    'leaves_0_needles': 'ef68f59e7021ea43',
    'leaves_0_distichy': '50c6a7745545c404',
    'leaves_0_decussation': '53755e238c77c633',
    'simplify_0': 'e54ffeb14155aaab',
    'qsm_0': '5a265d833cc46a8b',
    'measures_0': '50965b0e383360c2',
    'branches_1': 'e004a4b080e720f6',
    'branches_noradii_1': 'efad3e68383b5236',
    'mesh_1_lod0': '6b40c61447ea0fdb',
    'mesh_1_lod1': '27b0328c75a0af3f',
    'mesh_1_lod2': '647854c61885f860',
    'leaves_1_cards': '09b568a2e380eb0b',
    'leaves_1_needles': 'a95dd12738c384c5',
    'leaves_1_distichy': 'baa988447bbf2730',
    'leaves_1_decussation': '81c3b6757e3d5cd5',
    'simplify_1': 'b9aaef8eda0e2e72',
    'qsm_1': '9bd44bdc94818bb2',
    'measures_1': '00651a8b82da61be',
    'branches_2': '941c7c8cab65afa6',
    'branches_noradii_2': '1b720850b0b332c0',
    'mesh_2_lod0': 'b9a7a0f6d6f386c4',
    'mesh_2_lod1': 'f84c7915612815f5',
    'mesh_2_lod2': 'd47a7d358c254d6b',
    'leaves_2_cards': '0d79b109a6b32298',
    'leaves_2_needles': 'ada737c92fb22b1a',
    'leaves_2_distichy': 'b811a33b8d697b5c',
    'leaves_2_decussation': 'f8686504f04101b2',
    'simplify_2': '21101d76062609af',
    'qsm_2': 'b40df5a3613f133a',
    'measures_2': '17936d51464de609',
    'branches_3': '979dd8a49a1b66f5',
    'branches_noradii_3': 'a19cb971a767f363',
    'mesh_3_lod0': '3cebe85fcdcada8b',
    'mesh_3_lod1': '384724fea8b40e65',
    'mesh_3_lod2': 'c7b6c8348533f5a6',
    'leaves_3_cards': '7f2ec3eb9ad14dcf',
    'leaves_3_needles': '963cbe0f6c13779c',
    'leaves_3_distichy': 'ef61bc3ce9791c6e',
    'leaves_3_decussation': 'e01d0ebf2b9ccda8',
    'simplify_3': '4882d468f9a6b18c',
    'qsm_3': '5bd82ac2569d7c15',
    'measures_3': '13ce8cfeeded03a0',
    'forest_tree_1': '7a51f9f9f4084b7e',
    'forest_record_1': '9cb677700be3f83d',
    'forest_tree_2': 'bd21b70e76bd14d1',
    'forest_record_2': 'fd699d277d18c1f0',
    'forest_tree_3': '140bf3b142dc183c',
    'forest_record_3': '8d4a833438ed71f2',
    'forest_tree_4': '5cf31a18b67e29bd',
    'forest_record_4': 'aa68949573fb2a71',
    'forest_tree_5': 'b3369207add6592d',
    'forest_record_5': 'a32e86474ed317e0',
    'forest_tree_6': '22f968c062c2208d',
    'forest_record_6': '9244f82475c2bf59',
    'skeleton_table': 'dc01a472640ade2872ff11819eb0e70f',
    'qsm_tables': 'f64b5fc6ab7f69c2',
    'glb': '4f3ae3f258a7082c',
    'glb_coarse_noleaves': '924973aad527e1b4',
    'coarse_error': 'e76ff17142f37527',
    'tileset_json': '907a8a8adacdd790',
    'tileset_root': '6203564cedc9f2d0',
    'tileset_tile_-1_0': 'b29bfc3af07ecfb4',
    'tileset_tile_-2_0': 'b9e4ef662b3ef89d',
    'tileset_tile_0_-1': '8dc60c83be89fccc',
    'tileset_tile_1_-1': 'ca7b6d250732a77f',
    'gpkg_rows': '483f600e47f656c2',
}


def test_outputs_match_the_code_before_the_speed_up(tmp_path, monkeypatch):
    got = compute_digests(tmp_path, monkeypatch)
    assert set(got) == set(PINNED)
    changed = sorted(k for k in PINNED if got[k] != PINNED[k])
    assert not changed, f"outputs changed: {changed}"


def test_small_batches_give_the_same_outputs(tmp_path, monkeypatch):
    """model_trees meshes trees in batches of ~50 000 skeleton nodes and glb_bytes computes normals
    in batches of ~1e6 vertices; batches of a few trees / meshes change nothing."""
    from sylva.core.export import gltf

    monkeypatch.setattr(F, "_BATCH_NODES", 100)
    monkeypatch.setattr(gltf, "_BATCH_VERTICES", 3000)
    assert compute_digests(tmp_path, monkeypatch) == PINNED


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


if __name__ == "__main__":
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        digests = compute_digests(tmp)
    print("PINNED = {")
    for k, v in digests.items():
        print(f"    {k!r}: {v!r},")
    print("}")
    if len(sys.argv) > 1:
        print("differences from PINNED:", sorted(k for k in digests if PINNED.get(k) != digests[k]))
