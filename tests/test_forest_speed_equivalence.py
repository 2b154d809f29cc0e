"""The batched / vectorised modelling and export code gives the outputs of the per-tree code it replaced.

Three kinds of checks on synthetic trees (seeded; no reconstruction involved, so they do not move
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
* compiled kernels / forest passes == the numpy code they replaced (kept below verbatim as the
  reference, ``model_trees`` included): every output bit for bit, compared on this machine.

Run ``python tests/test_forest_speed_equivalence.py`` to print the digests of the code in place.
"""
from __future__ import annotations

import hashlib
import struct
import json
import sqlite3
import sys
import zlib
from types import SimpleNamespace
from typing import List, Optional, Union

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
from sylva.core.errors import InputError
from sylva.core.forest import QSM_ORDERS, ModelledTree, ModelOptions, _leaf_method, _WKB_HEADER
from sylva.core.geometry import (BranchSet, LevelOfDetail, TreeMeshParts, _check_skeleton, _cross, _dedupe,
                                 _forest, _hermite_batch, _lod, _radii_or_default, _tree_name,
                                 _tube_batch, branch_count, total_branch_length, with_radii, wood_volume)
from sylva.core.leaves import LeafCards, LeafMesh, NeedleClusters, _empty, phyllotaxis_azimuths
from sylva.core.measure import estimate_dbh
from sylva.core.progress import check, report
from sylva.core.qsm import cylinders_from_skeleton, measure_qsm
from sylva.core.reconstruct import TreePoints, is_dense_scan
from sylva.core.reconstruct.model import Reconstruction
from sylva.core.skeleton import Skeleton
from sylva.core.table import VectorTable
from sylva.core.textures import leaf_shape_name, leaf_aspect

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


def _wkb_digest(blobs) -> str:
    """Digest of ISO WKB (multi)linestrings/points: their structure exactly, coordinates as _h
    rounds them (compiled kernels may differ in the last bit from one CPU to another)."""
    ints, coords = [], []
    for blob in blobs:
        blob = bytes(blob)
        pos = 0

        def geom(pos):
            order, kind, count = struct.unpack_from("<BII", blob, pos)
            ints.extend([order, kind, count])
            pos += 9
            dims = {0: 2, 1: 3, 2: 3, 3: 4}[kind // 1000]                 # ISO: +1000 Z, +2000 M
            if kind % 1000 == 1:                                   # a point: no count
                coords.extend(struct.unpack_from(f"<{dims}d", blob, pos - 4))
                return pos - 4 + 8 * dims
            if kind % 1000 == 2:                                   # a linestring
                coords.extend(struct.unpack_from(f"<{count * dims}d", blob, pos))
                return pos + 8 * count * dims
            for _ in range(count):                                 # a multi-geometry
                pos = geom(pos)
            return pos

        assert geom(pos) == len(blob)
    return _h(np.array(ints, dtype=np.int64), np.array(coords, dtype=np.float64))


def _row_repr(row) -> str:
    """A GeoPackage row: floats rounded as _h rounds them, geometry blobs by :func:`_wkb_digest`
    (the GeoPackage header's envelope rounded too)."""
    out = []
    for v in row:
        if isinstance(v, bytes) and v[:2] == b"GP":
            env = {0: 0, 1: 4, 2: 6, 3: 6, 4: 8}[(v[3] >> 1) & 7]
            box = np.round(np.frombuffer(v[8:8 + 8 * env], dtype="<f8"), 8) + 0.0
            out.append(f"GP{v[2:4].hex()}{v[4:8].hex()}{box.tolist()}{_wkb_digest([v[8 + 8 * env:]])}")
        elif isinstance(v, float):
            out.append(repr(round(v, 8) + 0.0))
        else:
            out.append(repr(v))
    return "(" + ", ".join(out) + ")"


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
    out["skeleton_table"] = _wkb_digest(skel.geometries) + _h(skel.columns["n_chains"])
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
        rows.extend(_row_repr(r) for r in con.execute(f'SELECT * FROM "{name}" ORDER BY fid'))
    rows.extend(_row_repr(r) for r in con.execute("SELECT table_name, data_type, identifier, min_x, min_y, max_x, "
                                                       "max_y, srs_id FROM gpkg_contents ORDER BY table_name"))
    con.close()
    out["gpkg_rows"] = hashlib.sha256("\n".join(rows).encode()).hexdigest()[:16]
    return out


#: Digests of the code before the speed-up (per-tree loops), see the module docstring.
#: skeleton_table and gpkg_rows hashed raw WKB bytes at first, which differ in the last bit
#: between CPUs (numba compiles for the host); they now round coordinates like the others,
#: re-pinned from the code before the speed-up (96391d3), which gives them on this machine too.
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
    'skeleton_table': '8f3c9e0579b09e7972ff11819eb0e70f',
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
    'gpkg_rows': '8b938ae044e046e9',
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


# =========================================================================== compiled / forest passes
#
# The per-tree and lexsort / pointer-jumping numpy code that model_trees, the geometry, the leaves
# and the skeleton table used before the forest passes and kernels (core/jit.py) replaced it, kept
# verbatim (docstrings shortened) as the reference.  Every output is compared bit for bit (bytes,
# so signed zeros too) on this machine, on generated skeletons and clouds that reach every branch:
# exact bend ties, zero-length segments, vertical twigs, lone roots, pruned branches, trees of
# fewer than 3 nodes, crowns that are and are not conical, NaN inputs for the kernels' NaN rules.

_BATCH_NODES = F._BATCH_NODES
reconstruct_tree = None          # set by the tests (the synthetic skeletons)


# --------------------------------------------------------------------------- the reference (code before)

def _depth(parent: np.ndarray) -> np.ndarray:
    """Number of segments from the root to each node, by pointer jumping (O(m log depth))."""
    depth = (parent >= 0).astype(np.int64)
    nxt = parent.copy()
    live = np.flatnonzero(nxt >= 0)
    while len(live):   # after step k every node has summed 2^k links up its path
        tgt = nxt[live]
        depth[live] += depth[tgt]
        nxt[live] = nxt[tgt]
        live = live[nxt[live] >= 0]
    return depth


def depth_levels(skeleton: Skeleton) -> List[np.ndarray]:
    """Node indices grouped by depth (root level first), for level-wise vectorised passes."""
    if len(skeleton) == 0:
        return []
    d = _depth(skeleton.parent)
    order = np.argsort(d, kind="stable")
    cuts = np.flatnonzero(np.diff(d[order])) + 1
    return np.split(order, cuts)


def _subtree_sum(parent: np.ndarray, values: np.ndarray, levels: List[np.ndarray]) -> np.ndarray:
    """Sum of ``values`` over each node's subtree (node included): deepest level first."""
    acc = np.array(values, dtype=np.float64, copy=True)
    for idx in reversed(levels[1:]):
        np.add.at(acc, parent[idx], acc[idx])
    return acc


def pipe_model_radii(skeleton: Skeleton, tip_radius_m: float = 0.01, exponent: float = 2.0,
                     trunk_radius_m: Optional[float] = None, inplace: bool = False) -> np.ndarray:
    """Node radii by the pipe model, Hu et al. 2017 §5.5 Eq. 6."""
    skeleton = _check_skeleton(skeleton)
    if not (np.isfinite(tip_radius_m) and tip_radius_m > 0):
        raise InputError(f"{_tree_name(skeleton)}: tip_radius_m must be > 0 m, got {tip_radius_m}")
    if not (np.isfinite(exponent) and exponent > 0):
        raise InputError(f"{_tree_name(skeleton)}: pipe-model exponent must be > 0, got {exponent}")
    m = len(skeleton)
    if m == 0:
        return np.zeros(0)
    tips = (skeleton.n_children() == 0).astype(np.float64)
    n_tips = _subtree_sum(skeleton.parent, tips, depth_levels(skeleton))
    radii = tip_radius_m * n_tips ** (1.0 / exponent)
    if trunk_radius_m is not None:
        if not (np.isfinite(trunk_radius_m) and trunk_radius_m > 0):
            raise InputError(f"{_tree_name(skeleton)}: trunk_radius_m must be > 0 m, got {trunk_radius_m}")
        radii *= trunk_radius_m / radii[skeleton.root]
    if inplace:
        skeleton.radius = radii.copy()
    return radii


def _continuation_cos_arrays(nodes: np.ndarray, parent: np.ndarray):
    """:func:`_continuation_cos` of node / parent arrays (one tree or a forest of concatenated trees)."""
    child = np.flatnonzero(parent >= 0)
    par = parent[child]
    if len(child) == 0:
        return child, par, np.zeros(0)
    gp = parent[par]
    incoming = np.where((gp >= 0)[:, None], nodes[par] - nodes[np.maximum(gp, 0)], [0.0, 0.0, 1.0])
    out = nodes[child] - nodes[par]
    cos = (incoming * out).sum(axis=1) / np.maximum(
        np.linalg.norm(incoming, axis=1) * np.linalg.norm(out, axis=1), 1e-12)
    return child, par, np.round(cos, 9)  # exact ties are decided by radius, then by index


def _continuation_from_cos(m: int, child, par, cos, radii: Optional[np.ndarray] = None) -> np.ndarray:
    cont = np.full(m, -1, dtype=np.int64)
    if len(child) == 0:
        return cont
    r = radii[child] if radii is not None else np.zeros(len(child))
    order = np.lexsort((-child, r, cos, par))
    p_sorted = par[order]
    last = np.r_[np.flatnonzero(np.diff(p_sorted)), len(order) - 1]
    cont[p_sorted[last]] = child[order][last]
    return cont


def _continuation_child(skeleton: Skeleton, radii: Optional[np.ndarray] = None) -> np.ndarray:
    """Per node, the child with the smallest bending angle (ties: the thicker one), or -1."""
    return _continuation_from_cos(len(skeleton), *_continuation_cos_arrays(skeleton.nodes, skeleton.parent), radii)


def branches(skeleton: Skeleton, radii: Optional[np.ndarray] = None) -> BranchSet:
    """Decompose ``skeleton`` into branch chains, Hu et al. 2017 §5.5."""
    skeleton = _check_skeleton(skeleton)
    return _branch_set(skeleton.parent, _continuation_child(skeleton, radii))


def _split_branch_set(bs: BranchSet, node_off: np.ndarray, trees=None) -> List[BranchSet]:
    """The per-tree BranchSets of a forest's BranchSet (trees = node ranges ``node_off``), or of ``trees`` only."""
    nt = len(node_off) - 1
    sizes = np.diff(node_off)
    # first chain of every tree (its root starts one); empty trees own no chain
    first = np.full(nt + 1, len(bs), dtype=np.int64)
    nonempty = np.flatnonzero(sizes > 0)
    first[nonempty] = bs.node_branch[node_off[nonempty]]
    for t in range(nt - 1, -1, -1):      # an empty tree's range starts where the next tree's starts
        if sizes[t] == 0:
            first[t] = first[t + 1]
    first_l, off_l, noff_l = first.tolist(), bs.offsets.tolist(), np.asarray(node_off).tolist()
    out = []
    for t in (range(nt) if trees is None else trees):
        b0, b1 = first_l[t], first_l[t + 1]
        n0, n1 = noff_l[t], noff_l[t + 1]
        c0, c1 = off_l[b0], off_l[b1]
        bpar = bs.parent[b0:b1]
        att = bs.attach[b0:b1]
        cont = bs.continuation[n0:n1]
        out.append(BranchSet(bs.nodes[c0:c1] - n0, bs.offsets[b0:b1 + 1] - c0, np.where(bpar >= 0, bpar - b0, -1),
                             np.where(att >= 0, att - n0, -1), bs.node_branch[n0:n1] - b0, bs.order[b0:b1],
                             np.where(cont >= 0, cont - n0, -1)))
    return out


def _branch_set(parent: np.ndarray, cont: np.ndarray) -> BranchSet:
    """The :class:`BranchSet` of a tree given each node's continuation child (see :func:`branches`)."""
    m = len(parent)
    if m == 0:
        e = np.zeros(0, dtype=np.int64)
        return BranchSet(e, np.zeros(1, dtype=np.int64), e, e, e, e, e)
    idx = np.arange(m)
    is_start = parent < 0
    is_start[~is_start] = cont[parent[~is_start]] != idx[~is_start]
    head = np.where(is_start, idx, parent)
    while True:  # pointer jumping: each node finds the first node of its chain
        nxt = head[head]
        if np.array_equal(nxt, head):
            break
        head = nxt
    starts = np.flatnonzero(is_start)
    node_branch = np.searchsorted(starts, head)
    order = np.lexsort((idx, node_branch))
    counts = np.bincount(node_branch, minlength=len(starts))
    attach = parent[starts].copy()
    bparent = np.where(attach >= 0, node_branch[np.maximum(attach, 0)], -1)
    has = (attach >= 0).astype(np.int64)
    full_off = np.r_[0, np.cumsum(counts + has)]
    full = np.empty(full_off[-1], dtype=np.int64)
    full[full_off[:-1][has == 1]] = attach[has == 1]
    local = np.arange(m) - np.r_[0, np.cumsum(counts)][:-1][node_branch[order]]
    full[full_off[node_branch[order]] + has[node_branch[order]] + local] = order
    border = _depth(bparent.astype(np.int64))   # parents precede children: order = depth in the branch tree
    return BranchSet(full, full_off.astype(np.int64), bparent.astype(np.int64), attach.astype(np.int64),
                     node_branch.astype(np.int64), border, cont)


def _tree_polylines(skeleton: Skeleton, lod: LevelOfDetail, radii, branch_set):
    """(points, radii, line lengths, branch set, kept branches) of the tubes of one tree, before smoothing."""
    skeleton = _check_skeleton(skeleton)
    rad = _radii_or_default(skeleton, radii)
    bset = branch_set if branch_set is not None else branches(skeleton, rad)
    nb = len(bset)
    if nb == 0:
        return np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int64), bset, np.zeros(0, bool)
    offsets = bset.offsets
    lengths = np.diff(offsets)
    idx = bset.nodes
    pts = skeleton.nodes[idx]
    r = rad[idx]
    side = bset.attach >= 0
    # a side branch starts with its own (child) radius at the attachment node
    r[offsets[:-1][side & (lengths > 1)]] = r[offsets[:-1][side & (lengths > 1)] + 1]
    base_r = r[offsets[:-1]]
    keep = base_r >= lod.min_radius_m
    keep[0] = True
    # a pruned branch prunes all it carries: AND along the path to the trunk (pointer jumping)
    anc = bset.parent.copy()
    live = np.flatnonzero(anc >= 0)
    while len(live):
        keep[live] &= keep[anc[live]]
        anc[live] = anc[anc[live]]
        live = live[anc[live] >= 0]
    if not keep.all():
        take = keep[np.repeat(np.arange(nb), lengths)]
        pts, r = pts[take], r[take]
        lengths = lengths[keep]
    return pts, r, lengths, bset, keep


def _split_tube_batch(verts, faces, face_line, offsets, lines_per_tree, sides):
    """Per tree (vertices, faces, face line within the tree) of a :func:`_tube_batch` over many trees."""
    nt = len(lines_per_tree)
    line_off = np.r_[0, np.cumsum(lines_per_tree)]
    n = int(offsets[-1])
    k = np.diff(offsets)
    capped = k >= 2
    nb = int(capped.sum())
    cap_rank = np.cumsum(capped) - capped            # index of each capped line among the capped lines
    pt_off = offsets[line_off]                       # points of tree t: pt_off[t] .. pt_off[t + 1]
    cap_off = np.r_[0, np.cumsum(capped)][line_off]  # capped lines of tree t: cap_off[t] .. cap_off[t + 1]
    n_t = np.diff(pt_off)
    c_t = np.diff(cap_off)
    v_t = n_t * sides + 2 * c_t
    v_off = np.r_[0, np.cumsum(v_t)]
    # new position of every batch vertex
    new = np.empty(len(verts), dtype=np.int64)
    point = np.arange(n)
    tree_of_point = np.repeat(np.arange(nt), n_t)
    local = point - pt_off[tree_of_point]
    j = np.arange(sides)[:, None]
    new[(j * n + point).ravel()] = (v_off[tree_of_point] + j * n_t[tree_of_point] + local).ravel()
    caps = np.flatnonzero(capped)
    tree_of_cap = np.repeat(np.arange(nt), c_t)
    cap_local = cap_rank[caps] - cap_off[tree_of_cap]
    base = v_off[tree_of_cap] + n_t[tree_of_cap] * sides
    new[n * sides + np.arange(nb)] = base + cap_local
    new[n * sides + nb + np.arange(nb)] = base + c_t[tree_of_cap] + cap_local
    out_v = np.empty_like(verts)
    out_v[new] = verts
    tree_of_line = np.repeat(np.arange(nt), lines_per_tree)
    face_tree = tree_of_line[face_line]
    order = np.argsort(face_tree, kind="stable")
    f_off = np.r_[0, np.cumsum(np.bincount(face_tree, minlength=nt))]
    out_f = new[faces[order]] - v_off[face_tree[order]][:, None]
    out_l = face_line[order] - line_off[face_tree[order]]
    vb, fb = v_off.tolist(), f_off.tolist()
    return [(out_v[vb[t]:vb[t + 1]], out_f[fb[t]:fb[t + 1]], out_l[fb[t]:fb[t + 1]]) for t in range(nt)]


def tree_mesh_arrays_batch(skeletons, lod: Union[int, LevelOfDetail] = 1, radii=None,
                           branch_sets=None) -> List[TreeMeshParts]:
    """:func:`tree_mesh_arrays` of many trees, with the tubes of all of them swept in one batch."""
    lod = _lod(lod)
    skeletons = list(skeletons)
    nt = len(skeletons)
    radii = [None] * nt if radii is None else list(radii)
    branch_sets = [None] * nt if branch_sets is None else list(branch_sets)
    prep = [_tree_polylines(sk, lod, r, bs) for sk, r, bs in zip(skeletons, radii, branch_sets)]
    lines_per_tree = np.array([len(p[2]) for p in prep], dtype=np.int64)
    if lines_per_tree.sum() == 0:
        e = np.zeros(0, dtype=np.int64)
        return [TreeMeshParts(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), e, p[3], p[4]) for p in prep]
    pts = np.concatenate([p[0] for p in prep])
    r = np.concatenate([p[1] for p in prep])
    offsets = np.r_[0, np.cumsum(np.concatenate([p[2] for p in prep]))].astype(np.int64)
    pts, r, offsets, _ = _dedupe(pts, r, offsets)
    pts, r, offsets = _hermite_batch(pts, r, offsets, lod.samples_per_segment)
    verts, faces, face_line = _tube_batch(pts, r, offsets, lod.sides, cap=True)
    if nt == 1:
        groups = [(verts, faces, face_line)]
    else:
        groups = _split_tube_batch(verts, faces, face_line, offsets, lines_per_tree, lod.sides)
    out = []
    for (v, f, fl), (_, _, _, bset, keep) in zip(groups, prep):
        out.append(TreeMeshParts(v, f, np.flatnonzero(keep)[fl], bset, keep))
    return out


def tree_meshes(skeletons, lod: Union[int, LevelOfDetail] = 1, radii=None, branch_sets=None) -> list:
    """:func:`tree_mesh` of many trees (one :class:`trimesh.Trimesh` each), the tubes swept in one batch."""
    import trimesh

    out = []
    for parts in tree_mesh_arrays_batch(skeletons, lod, radii, branch_sets):
        mesh = trimesh.Trimesh(parts.vertices, parts.faces, process=False)
        mesh.metadata["face_branch"] = parts.face_branch
        out.append(mesh)
    return out


def simplify_skeletons(skeletons, tolerance_m: float = 0.05, max_passes: int = 8) -> List[Skeleton]:
    """:func:`simplify_skeleton` of many skeletons, each pass vectorised over all of them at once."""
    skeletons = [_check_skeleton(sk) for sk in skeletons]
    nt = len(skeletons)
    if nt == 0:
        return []
    nodes, parent, off = _forest(skeletons)
    sizes = np.diff(off)
    radius = np.concatenate([sk.radius for sk in skeletons])
    added = np.concatenate([sk.is_added for sk in skeletons])
    tree = np.repeat(np.arange(nt), sizes)
    active = np.ones(nt, dtype=bool)
    for k in range(max_passes):
        m_t = np.bincount(tree, minlength=nt)
        active &= m_t >= 3
        if not active.any():
            break
        m = len(nodes)
        kids = np.bincount(parent[parent >= 0], minlength=m)
        only_child = np.full(m, -1, dtype=np.int64)
        has_parent = np.flatnonzero(parent >= 0)
        only_child[parent[has_parent]] = has_parent  # valid where kids == 1
        cand = np.flatnonzero((kids == 1) & (parent >= 0) & active[tree])
        depth = _depth(parent)
        cand = cand[depth[cand] % 2 == k % 2]
        if len(cand) == 0:
            continue
        p, c = nodes[parent[cand]], nodes[only_child[cand]]
        seg = c - p
        length2 = np.maximum((seg * seg).sum(axis=1), 1e-18)
        t = np.clip(((nodes[cand] - p) * seg).sum(axis=1) / length2, 0.0, 1.0)
        dist = np.linalg.norm(nodes[cand] - (p + t[:, None] * seg), axis=1)
        drop = cand[dist <= tolerance_m]
        if k >= 1:   # a tree with candidates whose pass drops nothing stops
            tried = np.zeros(nt, dtype=bool)
            tried[tree[cand]] = True
            dropped = np.zeros(nt, dtype=bool)
            dropped[tree[drop]] = True
            active &= ~(tried & ~dropped)
        if len(drop) == 0:
            continue
        new_parent = parent.copy()
        new_parent[only_child[drop]] = parent[drop]
        keep = np.ones(m, dtype=bool)
        keep[drop] = False
        index = np.cumsum(keep) - 1
        kept_parent = new_parent[keep]
        parent = np.where(kept_parent >= 0, index[np.maximum(kept_parent, 0)], -1)
        nodes, radius, added, tree = nodes[keep], radius[keep], added[keep], tree[keep]
    off = np.r_[0, np.cumsum(np.bincount(tree, minlength=nt))].tolist()
    out = []
    for t in range(nt):
        a, b = off[t], off[t + 1]
        par = parent[a:b]
        out.append(Skeleton(nodes[a:b], np.where(par >= 0, par - a, -1), radius[a:b], added[a:b]))
    return out


def _groups(labels: np.ndarray):
    idx = np.flatnonzero(labels > 0)
    order = idx[np.argsort(labels[idx], kind="stable")]
    lab = labels[order]
    cuts = np.flatnonzero(np.diff(lab)) + 1
    return lab[np.concatenate([[0], cuts])] if len(lab) else np.zeros(0, int), np.split(order, cuts)


def is_conical(xyz: np.ndarray, crown_base_z: float) -> bool:
    """A pointed crown: its upper quarter is much narrower than its widest part (conifers)."""
    crown = xyz[xyz[:, 2] >= crown_base_z]
    if len(crown) < 20:
        return False
    centre = crown[:, :2].mean(axis=0)
    r = np.linalg.norm(crown[:, :2] - centre, axis=1)
    z0, z1 = crown[:, 2].min(), crown[:, 2].max()
    rel = (crown[:, 2] - z0) / max(z1 - z0, 1e-6)
    top = r[rel >= 0.75]
    if len(top) < 3:
        return False
    return bool(np.percentile(top, 90) < 0.45 * np.percentile(r, 90))


def dbh_radii(skeleton, dbh_m: float, options: ModelOptions = ModelOptions()) -> np.ndarray:
    """Pipe-model radii (Hu et al. 2017 §5.5, Eq. 6) scaled so the stem has the diameter ``dbh_m``."""
    stem_r = max(dbh_m, 0.02) / 2  # a 1-point "tree" still gets a visible 2 cm stem
    return pipe_model_radii(skeleton, tip_radius_m=min(options.tip_radius_m, stem_r / 2), trunk_radius_m=stem_r)


def _branch_sets(skeletons, shifted, radii) -> list:
    """Per tree the three branch decompositions its outputs use (see :func:`geometry.branches`)."""
    if not skeletons:
        return []
    nodes, parent, off = _forest(skeletons)
    nodes_b, _, _ = _forest(shifted)
    m = len(nodes)
    r_a = np.concatenate([np.asarray(r, dtype=np.float64) for r in radii])
    r_b = np.concatenate([_radii_or_default(sk, None) for sk in shifted])
    child, par, cos_a = _continuation_cos_arrays(nodes, parent)
    _, _, cos_b = _continuation_cos_arrays(nodes_b, parent)
    cont_a = _continuation_from_cos(m, child, par, cos_a, r_a)
    cont_b = cont_a if (np.array_equal(cos_a, cos_b) and np.array_equal(r_a, r_b)) else \
        _continuation_from_cos(m, child, par, cos_b, r_b)
    cont_c = _continuation_from_cos(m, child, par, cos_b, None)
    bs_a = _split_branch_set(_branch_set(parent, cont_a), off)
    out = [[bs, bs, bs] for bs in bs_a]
    bounds = off.tolist()
    for col, cont, earlier in ((1, cont_b, (0,)), (2, cont_c, (1, 0))):
        differ = []
        for t in range(len(skeletons)):
            sl = slice(bounds[t], bounds[t + 1])
            same = next((e for e in earlier if np.array_equal(cont[sl], [cont_a, cont_b][e][sl])), None)
            if same is None:
                differ.append(t)
            else:
                out[t][col] = out[t][same]
        if differ:
            for t, bs in zip(differ, _split_branch_set(_branch_set(parent, cont), off, differ)):
                out[t][col] = bs
    return [tuple(x) for x in out]


def model_trees(cloud: PointCloud, labels: np.ndarray, metrics: TreeMetrics,
                options: ModelOptions = ModelOptions(), progress: Progress = None,
                cancelled: CancelCheck = None) -> List[ModelledTree]:
    """Model every tree of ``labels`` (see the module docstring), in tree_id order."""
    local = cloud.local_xyz()
    height = np.asarray(cloud.attrs["height"], dtype=np.float64)
    row_of = {int(t): i for i, t in enumerate(metrics.tree_id)}
    ids, groups = _groups(np.asarray(labels))
    work = []
    for k, (tree_id, idx) in enumerate(zip(ids, groups)):
        check(cancelled)
        report(progress, 0.9 * k / max(len(ids), 1), f"tree {k + 1} of {len(ids)}")
        i = row_of[int(tree_id)]
        xyz = local[idx]
        ground_z = float(np.median(xyz[:, 2] - height[idx]))
        method = options.method
        if options.dense_method is not None and is_dense_scan(xyz):
            method = options.dense_method
        tree_pts = TreePoints(int(tree_id), xyz, ground_z)
        dense_qsm = None
        if hasattr(method, "model") and len(xyz) > 0:
            # Yan et al. 2009: the full model (B-spline branches, §4) gives the cylinders
            dense = method.model(tree_pts)
            rec = dense.reconstruction
            if len(dense.cylinders["id"]):
                dense_qsm = measure_qsm(dense.cylinders, dense.branch_parent, xyz, base_z=ground_z,
                                        tree_id=int(tree_id))
        else:
            rec = reconstruct_tree(tree_pts, method)
        tree_h, crown_d = float(metrics.height[i]), float(metrics.crown_diameter[i])
        dbh, source = estimate_dbh(xyz, height[idx], tree_h, crown_d)
        work.append((int(tree_id), idx, i, ground_z, rec, dense_qsm, dbh, source))   # not xyz: memory
    check(cancelled)
    report(progress, 0.9, "skeletons, chains and QSMs")
    raw = [w[4].skeleton for w in work]
    simple = simplify_skeletons(raw, options.simplify_m) if options.simplify_m > 0 else raw
    skeletons, shifted_all, radii_all, dbhs = [], [], [], []
    for (tree_id, idx, i, ground_z, rec, dense_qsm, dbh, source), skeleton in zip(work, simple):
        if skeleton.radius.max() > 0:
            # Dense-scan methods measure radii from fitted cylinders (Yan et al. §4): keep them.
            radii = skeleton.radius
            if dense_qsm is not None and dense_qsm.dbh_source == "measured":
                dbh, source = dense_qsm.dbh_m, "measured"    # circle fit around the stem cylinder at 1.3 m
            elif source != "measured":
                if dense_qsm is not None and np.isfinite(dense_qsm.dbh_m):
                    dbh, source = dense_qsm.dbh_m, "cylinder"
                else:
                    dbh, source = 2.0 * float(radii[skeleton.root]), "cylinder"
        else:
            radii = dbh_radii(skeleton, dbh, options)
        skeleton = with_radii(skeleton, radii)
        base = skeleton.nodes[skeleton.root].copy()
        shifted = with_radii(type(skeleton)(skeleton.nodes - base, skeleton.parent, radii, skeleton.is_added), radii)
        skeletons.append(skeleton)
        shifted_all.append(shifted)
        radii_all.append(radii)
        dbhs.append((dbh, source))
    bsets = _branch_sets(skeletons, shifted_all, radii_all)
    out, leaf_jobs = [], []
    for (tree_id, idx, i, ground_z, rec, dense_qsm, _, _), skeleton, shifted, (dbh, source), \
            (bset, _, bs_leaves) in zip(work, skeletons, shifted_all, dbhs, bsets):
        xyz = local[idx]
        if dense_qsm is not None:
            qsm, qsm_method = dense_qsm, "bspline_cylinders"
            qsm.dbh_m, qsm.dbh_source = float(dbh), source
        else:
            cyl, bpar = cylinders_from_skeleton(skeleton, branch_set=bset)
            qsm = measure_qsm(cyl, bpar, xyz, base_z=ground_z, tree_id=int(tree_id))
            qsm.dbh_m, qsm.dbh_source = float(dbh), source     # the record's DBH, not the pipe model's
            qsm_method = "skeleton_edges"
        kind = options.leaves
        if kind == "auto":
            kind = "needles" if is_conical(xyz, ground_z + metrics.crown_base_height[i]) else "broadleaf"
        leaf_jobs.append((kind, zlib.crc32(f"leaves-{int(tree_id)}".encode()), bs_leaves))
        noise = len(idx) < options.min_points
        quality = "noise" if noise else ("fallback" if "fallback" in rec.flags else "ok")
        record = {
            "tree_id": int(tree_id),
            "base_x": 0.0, "base_y": 0.0, "base_z": 0.0,  # filled in CRS units below
            "dbh": float(dbh), "dbh_source": source,
            "n_branches": int(branch_count(skeleton, branch_set=bset)),
            "total_branch_length": float(total_branch_length(skeleton, branch_set=bset)),
            "wood_volume": float(wood_volume(skeleton, branch_set=bset)),
            "method": rec.method,
            "visited_fraction": float(rec.visited_fraction),
            "quality": quality,
            "leaves": kind,
            "flags": ",".join(rec.flags),
            "qsm_method": qsm_method,
            "n_cylinders": int(len(qsm.cylinders["id"])),
            "trunk_volume": float(qsm.trunk_volume_m3),
            "total_volume": float(qsm.total_volume_m3),
            **{f"n_branches_order_{o}": int(qsm.branch_counts.get(o, 0)) for o in QSM_ORDERS},
            "branch_counts": ",".join(f"{o}:{c}" for o, c in sorted(qsm.branch_counts.items())),
        }
        base = skeleton.nodes[skeleton.root].copy()
        crs_base = cloud.from_local(base[None, :])[0]
        record.update(base_x=float(crs_base[0]), base_y=float(crs_base[1]), base_z=float(crs_base[2]))
        out.append(ModelledTree(int(tree_id), base, skeleton, None, None, record, qsm, bset))
    report(progress, 0.95, "meshes and leaves")
    # batches of trees of about _BATCH_NODES skeleton nodes: the temporaries stay small on large tiles
    sizes = np.array([len(sk) for sk in shifted_all], dtype=np.int64)
    cuts = np.r_[0, np.flatnonzero(np.diff(np.cumsum(sizes) // _BATCH_NODES)) + 1, len(out)]
    for a, b in zip(cuts[:-1].tolist(), cuts[1:].tolist()):
        check(cancelled)
        for t, wood in zip(out[a:b], tree_meshes(shifted_all[a:b], lod=options.lod,
                                                 branch_sets=[x[1] for x in bsets[a:b]])):
            t.wood = wood
        for kind in sorted({job[0] for job in leaf_jobs[a:b]}):
            method = _leaf_method(kind, options)
            if method is None:
                continue
            which = [k for k in range(a, b) if leaf_jobs[k][0] == kind]
            grown = grow_leaves_batch([shifted_all[k] for k in which], method, [leaf_jobs[k][1] for k in which],
                                      branch_sets=[leaf_jobs[k][2] for k in which])
            for k, leaves in zip(which, grown):
                out[k].leaves = leaves
    report(progress, 1.0, "trees modelled")
    return out


def _multilinestring_zm_wkbs(coords: np.ndarray, part_len: np.ndarray, n_parts: np.ndarray) -> list:
    """ISO WKB MultiLineString ZM per feature (little endian, types 3005 / 3002), vectorised."""
    nf, npart = len(n_parts), len(part_len)
    feat_of_part = np.repeat(np.arange(nf), n_parts)
    # items in buffer order: feature header, then its parts (header + coordinates)
    part_item = feat_of_part + 1 + np.arange(npart)
    feat_item = np.arange(nf) + np.r_[0, np.cumsum(n_parts)[:-1]]
    size = np.empty(nf + npart, dtype=np.int64)
    size[feat_item] = 9
    size[part_item] = 9 + 32 * part_len
    start = np.r_[0, np.cumsum(size)]
    buf = np.empty(int(start[-1]), dtype=np.uint8)
    hdr = np.empty(nf + npart, dtype=_WKB_HEADER)
    hdr["order"] = 1
    hdr["type"][feat_item], hdr["count"][feat_item] = 3005, n_parts
    hdr["type"][part_item], hdr["count"][part_item] = 3002, part_len
    buf[start[:-1, None] + np.arange(9)] = hdr.view(np.uint8).reshape(-1, 9)
    if len(coords):
        row_part = np.repeat(np.arange(npart), part_len)
        row_local = np.arange(len(coords)) - np.repeat(np.r_[0, np.cumsum(part_len)[:-1]], part_len)
        row_off = start[part_item][row_part] + 9 + 32 * row_local
        buf[row_off[:, None] + np.arange(32)] = np.ascontiguousarray(coords, dtype="<f8").view(np.uint8).reshape(-1, 32)
    ends = start[feat_item + 1 + n_parts].tolist()
    begins = start[feat_item].tolist()
    return [buf[a:b].tobytes() for a, b in zip(begins, ends)]


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


def _horizontal_normal(d: np.ndarray) -> np.ndarray:
    """Unit vectors perpendicular to ``d``: horizontal (z x d) unless ``d`` is vertical."""
    r = np.cross(np.array([0.0, 0.0, 1.0]), d)
    steep = np.linalg.norm(r, axis=1) < 1e-6
    r[steep] = np.cross(np.array([0.0, 1.0, 0.0]), d[steep])
    return _unit(r)


def _transport(v: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotate ``v`` by the minimal rotation taking unit ``a`` to unit ``b`` (row-wise)."""
    c = (a * b).sum(axis=1, keepdims=True)
    k = np.cross(a, b)
    ok = c[:, 0] > -0.999999
    out = v.copy()
    kv = np.cross(k[ok], v[ok])
    out[ok] = v[ok] * c[ok] + kv + k[ok] * ((k[ok] * v[ok]).sum(axis=1, keepdims=True) / (1.0 + c[ok]))
    return out


def _tip_sections(skeleton: Skeleton, tip_segments: int, branch_set=None):
    """Node indices (t, K + 1) of the last K segments of every branch (padded at the start)."""
    bset = branch_set if branch_set is not None else branches(skeleton)
    off = bset.offsets
    real = np.flatnonzero(np.diff(off) >= 2)
    if len(real) == 0:
        return np.zeros((0, tip_segments + 1), dtype=np.int64)
    ends, starts = off[real + 1], off[real]
    k = np.arange(tip_segments + 1)[None, :]
    pos = ends[:, None] - 1 - (tip_segments - k)
    pos = np.maximum(pos, starts[:, None])
    return bset.nodes[pos]


def grow_leaves_batch(skeletons, method: Union[LeafCards, NeedleClusters] = LeafCards(), seeds=None,
                      radii=None, branch_sets=None) -> list:
    """:func:`grow_leaves` of many trees with one method, all tips computed in one vectorised pass."""
    skeletons = list(skeletons)
    ntree = len(skeletons)
    for skeleton in skeletons:
        if not isinstance(skeleton, Skeleton):
            raise InputError(f"expected a Skeleton, got {type(skeleton).__name__}")
    if not isinstance(method, (LeafCards, NeedleClusters)):
        raise InputError(f"unknown leaf method {method!r}: use LeafCards(...) or NeedleClusters(...)")
    seeds = [0] * ntree if seeds is None else list(seeds)
    radii = [None] * ntree if radii is None else list(radii)
    branch_sets = [None] * ntree if branch_sets is None else list(branch_sets)
    needles = isinstance(method, NeedleClusters)
    per_tip = int(method.clusters_per_tip if needles else method.leaves_per_tip)
    length_m = float(method.cluster_length_m if needles else method.leaf_length_m)
    width_m = method.cluster_width_m if needles else method.leaf_width_m
    shape = leaf_shape_name(method.shape)
    if width_m is None:
        width_m = length_m * leaf_aspect(shape)
    ksegs = int(method.tip_segments)
    if per_tip < 0 or ksegs < 1 or not (length_m > 0) or not (width_m > 0):
        raise InputError("leaves: need leaves_per_tip >= 0, tip_segments >= 1 and positive leaf sizes "
                         f"(got {per_tip}, {ksegs}, {length_m} m, {width_m} m)")
    base_az, node_rank = phyllotaxis_azimuths(method.pattern, per_tip)
    # tip sections of all trees; node indices made global over the concatenated skeletons
    sects, nodes_all, rad_all = [], [], []
    n_off = 0
    for skeleton, r, bs in zip(skeletons, radii, branch_sets):
        rad = skeleton.radius if r is None else np.asarray(r, dtype=np.float64).reshape(-1)
        if len(rad) != len(skeleton):
            raise InputError(f"leaves: {len(rad)} radii for {len(skeleton)} skeleton nodes")
        sect = (_tip_sections(skeleton, ksegs, bs) if len(skeleton)
                else np.zeros((0, ksegs + 1), np.int64))
        sects.append(sect + n_off)
        nodes_all.append(skeleton.nodes)
        rad_all.append(rad)
        n_off += len(skeleton)
    nodes_all = np.concatenate(nodes_all) if ntree else np.zeros((0, 3))
    rad_all = np.concatenate(rad_all) if ntree else np.zeros(0)
    sect_all = np.concatenate(sects) if ntree else np.zeros((0, ksegs + 1), np.int64)
    pts = nodes_all[sect_all]                                    # (t, K+1, 3)
    seg = pts[:, 1:] - pts[:, :-1]
    seglen = np.linalg.norm(seg, axis=2)                         # (t, K)
    total = seglen.sum(axis=1)
    live = total > 1e-9
    tip_tree = np.repeat(np.arange(ntree), [len(x) for x in sects])[live]
    nt_of = np.bincount(tip_tree, minlength=ntree)
    sect_all, pts, seg, seglen, total = sect_all[live], pts[live], seg[live], seglen[live], total[live]
    nt = len(sect_all)
    n_nodes = int(node_rank.max()) + 1 if per_tip else 0
    if nt == 0 or per_tip == 0:
        return [_empty(shape, needles) for _ in range(ntree)]
    # random draws, per tree from its own generator, always in the same order
    draws = [[], [], [], [], []]
    for t in np.flatnonzero(nt_of):
        rng = np.random.default_rng(seeds[t])
        n_t = int(nt_of[t])
        draws[0].append(np.zeros(n_t) if method.pattern == "distichy" else rng.uniform(0.0, 360.0, n_t))
        draws[1].append(rng.normal(0.0, method.azimuth_jitter_deg, (n_t, per_tip)))
        draws[2].append(rng.normal(0.0, method.angle_jitter_deg, (n_t, per_tip)))
        draws[3].append(rng.normal(0.0, method.roll_jitter_deg, (n_t, per_tip)))
        draws[4].append(rng.standard_normal((n_t, per_tip)))
    start, az_jit, ins_jit, roll, size_jit = (np.concatenate(d) for d in draws)
    # unit directions per segment; zero-length (padding) segments take the next real one
    d = seg / np.where(seglen > 0, seglen, 1.0)[..., None]
    for q in range(ksegs - 2, -1, -1):
        zero = seglen[:, q] <= 0
        d[zero, q] = d[zero, q + 1]
    # reference normal per segment: horizontal at the first, carried by minimal rotations
    ref = np.empty_like(d)
    ref[:, 0] = _horizontal_normal(d[:, 0])
    for q in range(1, ksegs):
        ref[:, q] = _unit(_transport(ref[:, q - 1], d[:, q - 1], d[:, q]))
    # leaf positions along the tip section
    cum = np.concatenate([np.zeros((nt, 1)), np.cumsum(seglen, axis=1)], axis=1)   # (t, K+1)
    frac = (node_rank + 0.5) / n_nodes                                               # (L,)
    s = total[:, None] * frac[None, :]                                               # (t, L)
    q = np.clip((cum[:, None, 1:-1] <= s[..., None]).sum(axis=2), 0, ksegs - 1)       # (t, L)
    ti = np.arange(nt)[:, None]
    local = (s - cum[ti, q]) / np.where(seglen[ti, q] > 0, seglen[ti, q], 1.0)
    pos = pts[ti, q] + local[..., None] * seg[ti, q]
    twig = d[ti, q]                                                                  # (t, L, 3)
    r_ = ref[ti, q]
    r_ = _unit(r_ - (r_ * twig).sum(axis=2, keepdims=True) * twig)
    s_ = _cross(twig, r_)
    # radii along the twig (linear between nodes)
    rn = rad_all[sect_all]
    rad_at = rn[ti, q] + local * (rn[ti, q + 1] - rn[ti, q])
    az = start[:, None] + base_az[None, :] + az_jit
    ins = method.insertion_angle_deg + ins_jit
    scale = np.clip(1.0 + method.size_jitter * size_jit, 0.5, 1.5)
    phi = np.deg2rad(az)[..., None]
    out_dir = np.cos(phi) * r_ + np.sin(phi) * s_            # radial direction of the leaf
    wdir = -np.sin(phi) * r_ + np.cos(phi) * s_              # across the blade
    ia = np.deg2rad(ins)[..., None]
    axis = np.cos(ia) * twig + np.sin(ia) * out_dir
    ro = np.deg2rad(roll)[..., None]
    wdir = np.cos(ro) * wdir + np.sin(ro) * _cross(axis, wdir)
    if method.face_up > 0:
        horiz = _cross(axis, np.array([0.0, 0.0, 1.0]))
        hn = np.linalg.norm(horiz, axis=2, keepdims=True)
        horiz = np.where(hn > 1e-6, horiz / np.where(hn > 0, hn, 1.0), wdir)
        horiz *= np.sign((horiz * wdir).sum(axis=2, keepdims=True) + 1e-12)
        wdir = (1.0 - method.face_up) * wdir + method.face_up * horiz
        wdir = _unit(wdir - (wdir * axis).sum(axis=2, keepdims=True) * axis)
    base = pos + rad_at[..., None] * out_dir
    length = (length_m * scale)[..., None]
    half_w = (0.5 * width_m * scale)[..., None]
    # flatten leaves
    L = nt * per_tip
    base, axis, wdir, twig = (x.reshape(L, 3) for x in (base, axis, wdir, twig))
    length, half_w = length.reshape(L, 1), half_w.reshape(L, 1)
    dirs = [wdir, _cross(axis, wdir)] if method.crossed else [wdir]
    tip_pt = base + length * axis
    corners = [np.stack([base - half_w * w, base + half_w * w,
                         tip_pt + half_w * w, tip_pt - half_w * w], axis=1) for w in dirs]     # (L, 4, 3)
    az = az.reshape(L)
    tips_local = sect_all[:, -1] - np.repeat(np.r_[0, np.cumsum([len(sk) for sk in skeletons])][:-1], nt_of)
    quad_uv = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    material = f"sylva_{'needles' if needles else 'leaf'}_{shape}"
    out = []
    t_off = np.r_[0, np.cumsum(nt_of)].tolist()
    for t in range(ntree):
        a, b = t_off[t], t_off[t + 1]
        if a == b:
            out.append(_empty(shape, needles))
            continue
        la, lb = a * per_tip, b * per_tip
        Lt = lb - la
        verts, uvs, faces = [], [], []
        nv = 0
        for c in corners:
            verts.append(c[la:lb].reshape(-1, 3))
            uvs.append(np.tile(quad_uv, (Lt, 1)))
            v0 = nv + 4 * np.arange(Lt)[:, None]
            faces.append(np.concatenate([v0 + [0, 1, 2], v0 + [0, 2, 3]], axis=1).reshape(-1, 3))
            nv += 4 * Lt
        out.append(LeafMesh(np.concatenate(verts), np.concatenate(faces).astype(np.int64), np.concatenate(uvs),
                            shape, material, np.repeat(tips_local[a:b], per_tip), base[la:lb], axis[la:lb],
                            twig[la:lb], az[la:lb], np.tile(node_rank, b - a), {"pattern": method.pattern}))
    return out


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


# --------------------------------------------------------------------------- kernels == reference

def test_norm3_is_numpys_row_norm():
    rng = np.random.default_rng(3)
    v = rng.standard_normal((5000, 3)) * 10.0 ** rng.integers(-200, 200, (5000, 3))
    v[:10] = [[0.0, -0.0, 0.0], [-0.0, -0.0, -0.0], [np.inf, 1, 1], [np.nan, 0, 0], [1e-320, 0, 0],
              [1e200, 1e200, 1e200], [-3.0, 4.0, 0.0], [0, 0, -1.0], [np.nan, np.inf, 0], [-np.inf, 0, 0]]
    with np.errstate(over="ignore", invalid="ignore"):
        assert_same(G._norm3(v), np.linalg.norm(v, axis=1))
        w = v[:4995].reshape(-1, 3, 3, 3)[..., 0, :]            # strided (t, K, 3), as the leaves use it
        assert_same(G._norm3(w), np.linalg.norm(w, axis=-1))


def test_continuation_kernel_is_the_lexsort():
    rng = np.random.default_rng(5)
    sks = _skeleton_zoo()
    nan_sk = random_skeleton(rng, 30)
    nan_sk.nodes[7, 1] = np.nan                                  # NaN bends rank above all others
    for sk in sks + [nan_sk]:
        for radii in (None, sk.radius, np.round(rng.random(len(sk)), 1), _tip_radii(sk)):
            want = _continuation_from_cos(len(sk), *_continuation_cos_arrays(sk.nodes, sk.parent), radii)
            assert_same(G._continuations(sk.nodes, sk.parent, radii), want)
            assert_same(G._continuation_child(sk, radii), want)
    nodes, parent, _ = _forest(sks)
    r = np.concatenate([_tip_radii(sk) for sk in sks])
    assert_same(G._continuations(nodes, parent, r),
                _continuation_from_cos(len(nodes), *_continuation_cos_arrays(nodes, parent), r))


def _tip_radii(sk):
    return G.pipe_model_radii(sk) if len(sk) else np.zeros(0)


def test_chains_kernel_is_the_pointer_jumping():
    rng = np.random.default_rng(6)
    cases = []
    for sk in _skeleton_zoo(1):
        cases.append((sk.parent, _continuation_child(sk, None)))
        cont = np.full(len(sk), -1, dtype=np.int64)              # arbitrary continuations: any node, or none
        has = rng.random(len(sk)) < 0.7
        cont[has] = rng.integers(0, len(sk), has.sum())
        cases.append((sk.parent, cont))
    nodes, parent, off = _forest(_skeleton_zoo(2))
    cases.append((parent, _continuation_from_cos(len(parent), *_continuation_cos_arrays(nodes, parent))))
    for par, cont in cases:
        assert_same(G._branch_set(par, cont), _branch_set(par, cont))
    bs = G._branch_set(*cases[-1])
    assert_same(G._split_branch_set(bs, off), _split_branch_set(_branch_set(*cases[-1]), off))
    empty = np.array([0, 0, 3, 3, 3])                  # empty trees between others
    p = np.array([-1, 0, 1])
    assert_same(G._split_branch_set(G._branch_set(p, np.array([1, 2, -1])), empty),
                _split_branch_set(_branch_set(p, np.array([1, 2, -1])), empty))


def test_branches_batch_and_one_tree_are_the_reference():
    sks = _skeleton_zoo(3)
    for radii in (None, [_tip_radii(sk) if k % 2 else None for k, sk in enumerate(sks)]):
        for k, (sk, bs) in enumerate(zip(sks, G.branches_batch(sks, radii))):
            r = None if radii is None else (np.zeros(len(sk)) if radii[k] is None else radii[k])
            assert_same(bs, branches(sk, r))
            assert_same(G.branches(sk, r), branches(sk, r))


@pytest.mark.parametrize("tol, passes", [(0.05, 8), (0.0, 8), (0.3, 2), (1.0, 8), (0.12, 1)])
def test_simplify_kernel_is_the_numpy_passes(tol, passes):
    sks = [_with_pipe_radii(sk) for sk in _skeleton_zoo(4)]
    rng = np.random.default_rng(8)
    for sk in sks:
        sk.is_added = rng.random(len(sk)) < 0.3
    assert_same(G.simplify_skeletons(sks, tol, passes), simplify_skeletons(sks, tol, passes))
    assert_same(G.simplify_skeleton(sks[0], tol, passes), simplify_skeletons([sks[0]], tol, passes)[0])


@pytest.mark.parametrize("exponent, trunk", [(2.0, None), (2.0, 0.2), (3.0, 0.15), (2.5, None)])
def test_pipe_model_tip_counts_are_the_level_sums(exponent, trunk):
    for sk in _skeleton_zoo(5):
        if len(sk):
            assert_same(G.pipe_model_radii(sk, 0.01, exponent, trunk), pipe_model_radii(sk, 0.01, exponent, trunk))


@pytest.mark.parametrize("lod", [0, 1, 2, LevelOfDetail(sides=5, samples_per_segment=2, min_radius_m=0.02)])
def test_forest_polylines_and_tubes_are_the_per_tree_code(lod):
    sks = _skeleton_zoo(6)
    radii = [None if k % 3 == 0 else _tip_radii(sk) * (1 + k % 4) for k, sk in enumerate(sks)]
    bsets = [None if k % 2 else branches(sk, _radii_or_default(sk, r)) for k, (sk, r) in enumerate(zip(sks, radii))]
    got, want = G.tree_mesh_arrays_batch(sks, lod, radii, bsets), tree_mesh_arrays_batch(sks, lod, radii, bsets)
    assert_same(got, want)
    if _lod(lod).min_radius_m >= 0.02:
        assert any(not p.kept.all() for p in want if len(p.kept))             # some branches were pruned
    assert_same(G.tree_meshes(sks[:3], lod), tree_meshes(sks[:3], lod))
    assert_same(G.tree_mesh_arrays_batch(sks[4:5], lod), tree_mesh_arrays_batch(sks[4:5], lod))   # lone root


@pytest.mark.parametrize("method", [LV.LeafCards(), LV.NeedleClusters(), LV.LeafCards(pattern="distichy"),
                                    LV.LeafCards(pattern="decussation", face_up=0.0, leaves_per_tip=5),
                                    LV.LeafCards(tip_segments=1, leaves_per_tip=3, leaf_width_m=0.02),
                                    LV.NeedleClusters(tip_segments=9, clusters_per_tip=2, azimuth_jitter_deg=0.0),
                                    LV.LeafCards(leaves_per_tip=0), LV.LeafCards(leaves_per_tip=1, face_up=1.0)])
def test_leaf_kernel_is_the_numpy_formulation(method):
    sks = [_with_pipe_radii(sk) for sk in _skeleton_zoo(7) if len(sk) > 1] + tiny_skeletons()
    seeds = [3 * k + 1 for k in range(len(sks))]
    bsets = [None if k % 2 else branches(sk) for k, sk in enumerate(sks)]
    got = LV.grow_leaves_batch(sks, method, seeds, branch_sets=bsets)
    assert_same(got, grow_leaves_batch(sks, method, seeds, branch_sets=bsets))
    assert_same(LV.grow_leaves(sks[0], method, seed=5), grow_leaves_batch([sks[0]], method, [5])[0])


def test_leaves_of_vertical_and_degenerate_tips():
    """Vertical twigs (the y x d normal), zero-length tip segments (padding), a 180° turn (no transport),
    a near reversal (transported) and -0.0 coordinates (a dot product of -0.0 terms is +0.0 in numpy)."""
    t = 0.004
    nodes = np.array([[0, 0, 0], [0, 0, 1.0], [0, 0, 2.0], [0, 0, 2.0], [0, 0, 3.0], [0, 0, 2.5], [1, 0, 1.0],
                      [1, 0, 1.0], [2, 0, 1.0], [0, 0, 4.0], [np.sin(t), 0, 4.0 - np.cos(t)], [-1.0, 0, 1.0],
                      [0.0, 0, 1.0], [-0.0, -1.0, 0.0], [-0.0, -2.0, -0.0]])
    parent = [-1, 0, 1, 2, 3, 4, 1, 6, 7, 4, 9, 0, 11, 12, 13]
    sk = _with_pipe_radii(Skeleton(nodes, parent))
    for method in (LV.LeafCards(), LV.NeedleClusters(), LV.LeafCards(tip_segments=5, pattern="distichy"),
                   LV.LeafCards(tip_segments=2, face_up=0.0)):
        assert_same(LV.grow_leaves_batch([sk, sk], method, [1, 2]), grow_leaves_batch([sk, sk], method, [1, 2]))


def test_skeleton_qsms_are_the_per_tree_measure_qsm():
    sks = [_with_pipe_radii(sk) for sk in _skeleton_zoo(8)] + tiny_skeletons()
    nodes, parent, off = _forest(sks)
    radii = np.concatenate([sk.radius for sk in sks])
    bs = G._branch_set(parent, G._continuations(nodes, parent, radii))
    boff = G._tree_branches(bs, off)
    rng = np.random.default_rng(9)
    base = rng.normal(0, 0.5, len(sks)).tolist()
    xyz = [sk.nodes + rng.normal(0, 0.3, sk.nodes.shape) for sk in sks]
    dbh = rng.uniform(0.05, 0.5, len(sks)).tolist()
    src = ["measured" if k % 2 else "allometric" for k in range(len(sks))]
    top = [x[:, 2].max() for x in xyz]
    got = skeleton_qsms_of(nodes, parent, radii, bs, off, boff, base, top, dbh, src)
    for k, (sk, q, bset) in enumerate(zip(sks, got, G._split_branch_set(bs, off, boff))):
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


def test_crown_spread_kernel_is_the_numpy_percentiles():
    rng = np.random.default_rng(10)
    crowns = _crowns(rng)
    want = [is_conical(xyz, zb) for xyz, zb in crowns]
    assert [F.is_conical(xyz, zb) for xyz, zb in crowns] == want
    assert 5 < sum(want) < len(want) - 5
    xyz = np.concatenate([c[0] for c in crowns])
    off = np.r_[0, np.cumsum([len(c[0]) for c in crowns])].astype(np.int64)
    zb = np.array([c[1] for c in crowns])
    assert F._conical(xyz, off, zb).tolist() == want
    p_top, p_all = F._crown_spread_kernel(xyz, off, zb)
    for k, (pts, z) in enumerate(crowns):         # the percentiles themselves, as is_conical computed them
        crown = pts[pts[:, 2] >= z]
        if len(crown) < 20:
            assert np.isnan(p_top[k]) and np.isnan(p_all[k])
            continue
        r = np.linalg.norm(crown[:, :2] - crown[:, :2].mean(axis=0), axis=1)
        rel = (crown[:, 2] - crown[:, 2].min()) / max(crown[:, 2].max() - crown[:, 2].min(), 1e-6)
        if (rel >= 0.75).sum() < 3:
            assert np.isnan(p_top[k]) and np.isnan(p_all[k])
            continue
        assert_same([p_top[k], p_all[k]], [np.percentile(r[rel >= 0.75], 90), np.percentile(r, 90)], k)


def test_median_kernel_is_np_median():
    rng = np.random.default_rng(11)
    parts = [rng.normal(0, 1, int(rng.integers(1, 50))) for _ in range(40)]
    parts += [np.array([-0.0]), np.array([-0.0, -0.0]), np.round(rng.normal(0, 1, 20)), np.array([1.0, np.nan, 2.0])]
    values = np.concatenate(parts)
    off = np.r_[0, np.cumsum([len(p) for p in parts])].astype(np.int64)
    assert_same(F._median_kernel(values, off), np.array([np.median(p) for p in parts]))


def test_wkb_pack_is_the_vectorised_scatter():
    rng = np.random.default_rng(12)
    n_parts = np.array([3, 1, 0, 5, 2])
    part_len = rng.integers(1, 6, n_parts.sum())
    coords = rng.normal(0, 100, (part_len.sum(), 4))
    assert F._multilinestring_zm_wkbs(coords, part_len, n_parts) == _multilinestring_zm_wkbs(coords, part_len, n_parts)


# --------------------------------------------------------------------------- model_trees == reference

def forest_of(skeletons, seed: int = 21):
    """A cloud with the points of ``skeletons`` (dict tree id -> skeleton) around their nodes, labels, metrics."""
    rng = np.random.default_rng(seed)
    xyz, labels = [], []
    for t, sk in skeletons.items():
        centre = np.array([20.0 * (t % 4), 25.0 * (t // 4), 0.0])
        pts = np.repeat(sk.nodes, 6, axis=0) + rng.normal(0, 0.08, (6 * len(sk.nodes), 3))
        if t % 2 == 0:
            pts[:, :2] *= np.clip(1.2 - pts[:, 2:3] / 12.0, 0.05, None)
        ground = rng.normal(0, 0.02, (30, 3))
        ground[:, :2] = rng.uniform(-2, 2, (30, 2))
        for p, lab in ((pts, t), (ground, 0)):
            xyz.append(p + centre + ORIGIN)
            labels.append(np.full(len(p), lab))
    xyz, labels = np.concatenate(xyz), np.concatenate(labels)
    height = xyz[:, 2] - ORIGIN[2] - 0.01 * (labels % 3)
    ids = np.array(sorted(skeletons))
    metrics = SimpleNamespace(tree_id=ids, height=np.array([height[labels == t].max() for t in ids]),
                              crown_diameter=np.full(len(ids), 4.0), crown_base_height=np.linspace(1, 4, len(ids)))
    return PointCloud(xyz, {"height": height}, crs=None), labels, metrics


@pytest.mark.parametrize("options, batch", [
    (F.ModelOptions(method=object(), lod=1), 50_000),
    (F.ModelOptions(method=object(), lod=0), 150),
    (F.ModelOptions(method=object(), lod=2, leaves="needles", simplify_m=0.0), 50_000),
    (F.ModelOptions(method=object(), lod=1, leaves="none", simplify_m=0.3, min_points=40, tip_radius_m=0.03), 60),
])
def test_model_trees_is_the_per_tree_code(monkeypatch, options, batch):
    rng = np.random.default_rng(13)
    sks = {t: synthetic_skeleton(100 + t) for t in range(1, 5)}
    sks.update({t: random_skeleton(rng, int(rng.integers(8, 70))) for t in range(5, 12)})
    sks[12] = tiny_skeletons()[0]
    sks[13] = tiny_skeletons()[1]
    cloud, labels, metrics = forest_of(sks)
    fake = _fake_reconstruct(sks)
    monkeypatch.setattr(F, "reconstruct_tree", fake)
    monkeypatch.setattr(sys.modules[__name__], "reconstruct_tree", fake)
    monkeypatch.setattr(F, "_BATCH_NODES", batch)
    monkeypatch.setattr(sys.modules[__name__], "_BATCH_NODES", batch)
    got, want = F.model_trees(cloud, labels, metrics, options), model_trees(cloud, labels, metrics, options)
    assert len(got) == len(sks)
    for a, b in zip(got, want):
        assert_same(a, b, a.tree_id)
    assert_same(F.skeleton_table(got, cloud).geometries, F.skeleton_table(want, cloud).geometries)
    assert {t.record["leaves"] for t in got} == ({"needles", "broadleaf"} if options.leaves == "auto" else
                                                 {options.leaves})

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
