"""Invariants of the export writers (GLB, 3D Tiles, the models_3d layer) on synthetic forests that reach
every branch: lods or none, leaf cards / needles / none, wood-only and leaves-only trees, unreferenced
vertices and degenerate triangles, billboards (alone or with a mesh), a mesh of more than 65535 vertices
(uint32 indices), attributes of every type (bool, int, big int, float, NaN, missing, text, numpy
scalars, clashing names), a geodetic and a local frame:

* golden outputs: the GLB and 3D Tiles content and the models_3d table equal
  ``tests/golden/export_outputs.json`` (integers and texts exactly, floats within a tolerance:
  tests/fingerprints.py);
* a shared cache, batches of vertices, the order of the models and per-tree files change no byte;
* kernels equal their library counterpart (cKDTree) or their definition (unit normals, bounds).

(The numpy / cKDTree / per-tree code these writers replaced was kept here verbatim as a reference
until the outputs were pinned; it is in git history.)  ``python tests/test_export_invariants.py``
says which outputs differ from the golden file; ``--write`` rewrites it, for a change that is meant.
"""
from __future__ import annotations

import importlib.util
import json
import math
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from sylva.core.errors import InputError
from sylva.core.export import georef as georef_mod
from sylva.core.export import gltf, gpkg3d, model as model_mod, tiles3d
from sylva.core.export.georef import Georef, default_origin
from sylva.core.export.model import ExportFrame, TreeModel
from sylva.core.reconstruct.billboard import BillboardMesh

from fingerprints import fingerprint, glb_fingerprint, json_fingerprint, same_outputs, wkb_fingerprint

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("_sylva_bench_export", ROOT / "benchmarks" / "export.py")
_bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_bench)

#: Fingerprints of :func:`compute_outputs`, written by ``python tests/test_export_invariants.py --write``.
GOLDEN = Path(__file__).with_name("golden") / "export_outputs.json"


UTM = ExportFrame("EPSG:32632")
ORIGIN = np.array([500000.0, 5400000.0, 300.0])


def _billboard(seed: int, quads: int = 3) -> BillboardMesh:
    """``quads`` vertical textured quads around the z axis, a random binary-alpha atlas (one column a quad)."""
    rng = np.random.default_rng(seed)
    h, w = 16, 8 * quads
    tex = np.zeros((h, w, 4), dtype=np.uint8)
    tex[..., :3] = rng.integers(0, 256, (h, w, 3))
    tex[..., 3] = np.where(rng.uniform(size=(h, w)) < 0.6, 255, 0)
    verts, uvs, faces = [], [], []
    for q in range(quads):
        a = math.pi * q / quads
        d = np.array([math.cos(a), math.sin(a), 0.0]) * (1.5 + 0.3 * q)
        verts += [-d, d, d + [0, 0, 6.0], -d + [0, 0, 6.0]]
        u0, u1 = q / quads, (q + 1) / quads
        uvs += [[u0, 0.0], [u1, 0.0], [u1, 1.0], [u0, 1.0]]
        faces += [[4 * q, 4 * q + 1, 4 * q + 2], [4 * q, 4 * q + 2, 4 * q + 3]]
    return BillboardMesh(np.array(verts) + [0, 0, 0.5], np.array(faces), np.array(uvs), tex, ("crown",) * quads,
                         False, None, 0.0, 0.0, np.zeros(2), np.zeros((quads, 4)), "procedural")


def _odd_wood(seed: int):
    """A tube with unreferenced vertices and degenerate (zero-area and sub-mm^2) triangles."""
    rng = np.random.default_rng(seed)
    tube = trimesh.creation.cylinder(radius=0.2, height=6.0, sections=7)
    n = len(tube.vertices)
    v = np.vstack([tube.vertices + [0, 0, 3.0], rng.normal(0, 2, (5, 3)),
                   [[0.0, 0.0, 7.0], [1e-4, 0.0, 7.0], [0.0, 1e-4, 7.0], [3e-3, 0.0, 7.0], [0.0, 3e-3, 7.0]]])
    # a zero-area, a 5e-9 m^2 and a 4.5e-6 m^2 triangle (the layer keeps only the last)
    f = np.vstack([tube.faces, [[n + 5, n + 6, n + 5], [n + 5, n + 6, n + 7], [n + 5, n + 8, n + 9]]])
    return trimesh.Trimesh(v, f, process=False)


def _slivers():
    """A mesh of triangles under 1 mm^2 only."""
    return trimesh.Trimesh([[0.0, 0.0, 0.0], [1e-4, 0.0, 0.0], [0.0, 1e-4, 0.0], [0.0, 0.0, 1e-4]],
                           [[0, 1, 2], [0, 1, 3]], process=False)


def _attributes(k: int) -> dict:
    """Attributes of every kind the property table and the layer columns distinguish."""
    return {"height": 10.0 + k, "flag": k % 2 == 0, "count": k, "big": 2 ** 40 + k if k % 3 else k,
            "maybe": None if k % 4 == 1 else 0.5 * k, "nan": float("nan") if k % 2 else 1.0,
            "missing_int": None if k == 2 else k, "text": f"baum-{k} \u00e9", "mixed": k if k % 2 else "x",
            "np_f": np.float64(0.1 * k), "np_i": np.int64(-k), "np_s": np.str_(f"s{k}"), "np_b": np.bool_(k % 3 == 0),
            "maybe_flag": True if k % 2 else None, "a b": k, "a_b": -k, "1st": "one",
            "int32_edge": 2 ** 31 - 1 - k, "int32_low": 1 + k - 2 ** 31, "int32_over": 2 ** 31 if k == 3 else -k,
            **({"only_some": k} if k % 3 == 0 else {})}


def forest(billboards: bool = True, big: bool = False):
    """Synthetic TreeModels reaching every branch of the writers (see the module docstring)."""
    with_lods = _bench.synthetic_models(4, seed=3, origin=tuple(ORIGIN), nodes=30, unique=2)
    no_lods = _bench.synthetic_models(3, seed=5, origin=tuple(ORIGIN + [3.0, 40.0, 0.0]), nodes=25, unique=3,
                                      lods=False)
    leafy = no_lods[0].leaves
    models = [TreeModel(10 + k, m.base, m.wood, m.leaves, {**m.attributes, **_attributes(k)}, m.lods)
              for k, m in enumerate(with_lods + no_lods)]
    base = ORIGIN + [-30.0, 20.0, 1.0]
    models += [TreeModel(30, base, no_lods[1].wood, None, _attributes(30)),                          # wood only
               TreeModel(31, base + [4.0, 1.0, 0.0], None, leafy, _attributes(31)),                   # leaves only
               TreeModel(32, base + [8.0, 0.0, 0.2], _odd_wood(1), leafy, _attributes(32), {0: _slivers()}),
               TreeModel(34, base + [12.0, 3.0, 0.1], _odd_wood(2), None, _attributes(34), {1: _odd_wood(3)})]
    if big:
        sphere = trimesh.creation.icosphere(subdivisions=7, radius=3.0)                       # 163842 vertices
        models.append(TreeModel(33, base + [0.0, 9.0, 0.0], sphere, None, _attributes(33)))
    if billboards:
        models += [TreeModel(40, base + [20.0, -5.0, 0.0], None, None, _attributes(40), billboard=_billboard(1)),
                   TreeModel(41, base + [24.0, -9.0, 0.0], no_lods[2].wood, no_lods[2].leaves, _attributes(41),
                             {0: with_lods[0].lods[0]}, billboard=_billboard(2, quads=4))]
    return models


@pytest.fixture(scope="module")
def models():
    return forest()


def _same_tree(a: Path, b: Path):
    fa = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    fb = sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    assert fa == fb
    for p in fa:
        assert (a / p).read_bytes() == (b / p).read_bytes(), p


GLB_OPTIONS = [dict(), dict(lod=0), dict(lod="coarsest", leaves=False), dict(metadata=False),
               dict(content="billboard"), dict(lod=5, texture_size=64, extras={"tile": "t_1", "n": 2})]
TABLE_OPTIONS = [("utm", UTM, False, True), ("utm-leaves", UTM, True, True), ("utm-leaves-full", UTM, True, False),
                 ("feet-leaves", ExportFrame("EPSG:2994"), True, True), ("local", ExportFrame(None), False, True)]
JSON_VALUES = [None, True, False, 0, -3, 2 ** 70, 1.5, float("nan"), float("inf"), -float("inf"), "x", np.str_("y"),
               np.float64(2.5), np.float64("nan"), np.float32(0.1), np.float16(0.3), np.int64(-7), np.int8(3),
               np.uint64(2 ** 63), np.bool_(True), np.datetime64("2020-01-02"), np.longdouble(0.1), 1j, (1, 2)]


def _files(folder: Path) -> dict:
    """Every file under ``folder`` by relative path: GLB content fingerprinted, JSON by its values."""
    out = {}
    for p in sorted(x for x in folder.rglob("*") if x.is_file()):
        key = p.relative_to(folder).as_posix()
        if p.suffix == ".glb":
            out[key] = glb_fingerprint(p.read_bytes())
        elif p.suffix == ".json":
            out[key] = json_fingerprint(json.loads(p.read_text()))
        else:
            out[key] = fingerprint(np.frombuffer(p.read_bytes(), dtype=np.uint8))
    return out


def _table(table) -> dict:
    columns = []
    for key, values in table.columns.items():
        values = np.asarray(values)
        columns.append(fingerprint(np.array([key, str(values.dtype)], dtype=object),
                                   values if values.dtype.kind != "O" else np.array([repr(v) for v in values], dtype=object)))
    return fingerprint(np.array([table.name, table.geometry_type, str(table.has_z), str(table.crs)], dtype=object),
                       wkb_fingerprint(table.geometries), np.array(table.extent, dtype=np.float64), *columns)


def compute_outputs(tmp: Path) -> dict:
    """Fingerprints of every writer's output on the synthetic forests, by name."""
    models = forest()
    out = {}
    for fname, frame in (("utm", UTM), ("local", ExportFrame(None))):
        georef = Georef(frame, ORIGIN + [2.0, -3.0, 0.0])
        for k, options in enumerate(GLB_OPTIONS):
            out[f"glb_{fname}_{k}"] = glb_fingerprint(gltf.glb_bytes(models, georef, **options))
    big = forest(billboards=False, big=True)[-1:] + models[:2]
    out["glb_big"] = glb_fingerprint(gltf.glb_bytes(big, Georef(UTM, ORIGIN)))
    out["table_big"] = _table(gpkg3d.models_table(big, UTM))
    (tmp / "per_tree").mkdir()
    gltf.write_glb(models[:6], tmp / "per_tree", UTM, per_tree=True, lod="coarsest")
    out.update({f"per_tree/{k}": v for k, v in _files(tmp / "per_tree").items()})
    for billboards in (True, False):
        folder = tmp / f"tiles_{billboards}"
        tiles3d.write_tileset(forest(billboards=billboards), folder, UTM, tile_size_m=20.0)
        out.update({f"tiles_{billboards}/{k}": v for k, v in _files(folder).items()})
    out["coarse_error"] = fingerprint(np.array([tiles3d.coarse_error(m) for m in models]))
    for name, frame, leaves, coarsest in TABLE_OPTIONS:
        out[f"table_{name}"] = _table(gpkg3d.models_table(models, frame, leaves=leaves, coarsest=coarsest))
    out["json_scalars"] = fingerprint(np.array([f"{type(v).__name__}:{v!r}" for v in
                                                map(model_mod.json_scalar, JSON_VALUES)], dtype=object))
    columns = gpkg3d.attribute_columns([m.json_attributes() for m in models])
    out["attribute_columns"] = fingerprint(*[fingerprint(np.array([k, str(v.dtype)], dtype=object),
                                                          v if v.dtype.kind != "O" else np.array([repr(x) for x in v],
                                                                                                 dtype=object))
                                             for k, v in columns.items()])
    return out


def test_outputs_match_the_golden_fingerprints(tmp_path):
    got = compute_outputs(tmp_path)
    want = json.loads(GOLDEN.read_text())
    assert sorted(got) == sorted(want)
    changed = same_outputs(got, want)
    assert not changed, f"outputs changed: {changed}"


# =========================================================================== GLB

@pytest.mark.parametrize("options", GLB_OPTIONS, ids=lambda o: ",".join(o) or "default")
def test_a_shared_cache_and_the_order_change_no_byte(models, options):
    georef = Georef(UTM, ORIGIN + [2.0, -3.0, 0.0])
    expected = gltf.glb_bytes(models, georef, **options)
    cache = {}   # a shared cache: the same bytes on the first and on a cached call
    assert gltf.glb_bytes(models, georef, cache=cache, **options) == expected
    assert gltf.glb_bytes(models, georef, cache=cache, **options) == expected
    assert gltf.glb_bytes(models[::-1], georef, cache=cache, **options) == gltf.glb_bytes(models[::-1], georef,
                                                                                          **options)


def test_vertex_batches_change_no_byte(models, monkeypatch):
    georef = Georef(UTM, ORIGIN)
    whole = gltf.glb_bytes(models, georef)
    monkeypatch.setattr(gltf, "_BATCH_VERTICES", 2000)
    assert gltf.glb_bytes(models, georef) == whole


def test_write_glb_writes_glb_bytes(models, tmp_path):
    """A tile is glb_bytes at the default origin; per tree, each file is that tree alone at its base."""
    gltf.write_glb(models, tmp_path / "tile.glb", UTM)
    assert (tmp_path / "tile.glb").read_bytes() == gltf.glb_bytes(models, Georef(UTM, default_origin(models)))
    (tmp_path / "trees").mkdir()
    gltf.write_glb(models[:3], tmp_path / "trees", UTM, per_tree=True)
    for m in models[:3]:
        assert (tmp_path / "trees" / f"tree_{m.tree_id}.glb").read_bytes() == gltf.glb_bytes([m], Georef(UTM, m.base))


def test_glb_errors_name_the_tree_and_the_level(models):
    georef = Georef(UTM, ORIGIN)
    bad = TreeModel(99, ORIGIN, None, None)
    with pytest.raises(InputError, match="tree 99 has an empty mesh"):
        gltf.glb_bytes(models[:2] + [bad], georef)
    with pytest.raises(InputError, match="content must be one of"):
        gltf.glb_bytes(models[:2], georef, content="photo")
    broken = TreeModel(98, ORIGIN, models[0].wood, models[0].leaves, lods={0: trimesh.Trimesh(
        [[0, 0, 0], [1, 0, 0], [0, np.inf, 0]], [[0, 1, 2]], process=False)})
    with pytest.raises(InputError, match="lod 0"):
        gltf.glb_bytes([broken], georef, lod=0)


# =========================================================================== 3D Tiles

def test_a_shared_cache_changes_no_tile(tmp_path):
    models = forest()
    tiles3d.write_tileset(models, tmp_path / "a", UTM, tile_size_m=20.0)
    cache = {}   # the pipeline's order: the tile GLB, then its tileset, sharing one cache
    gltf.write_glb(models, tmp_path / "b.glb", UTM, cache=cache)
    tiles3d.write_tileset(models, tmp_path / "c", UTM, tile_size_m=20.0, cache=cache)
    fa = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*") if p.is_file())
    assert fa == sorted(p.relative_to(tmp_path / "c") for p in (tmp_path / "c").rglob("*") if p.is_file())
    assert all((tmp_path / "a" / p).read_bytes() == (tmp_path / "c" / p).read_bytes() for p in fa)


def test_coarse_error(models):
    errors = [tiles3d.coarse_error(m) for m in models]
    assert tiles3d.max_coarse_error(models) == max(errors)
    assert tiles3d.max_coarse_error(models[::-1], {}) == max(errors)
    assert min(errors) == 0.0 and 0.0 < max(errors) < math.inf   # the billboard-only tree, and real distances


def _sets(seed: int, n_sets: int = 6):
    """Random point sets of very different sizes and spreads (some without queries)."""
    rng = np.random.default_rng(seed)
    qs, ts = [], []
    for s in range(n_sets):
        nq, nt = int(rng.integers(0, 400)) * (s % 4 != 1), int(rng.integers(1, 300))
        scale = 10 ** rng.uniform(-2, 2)
        qs.append(rng.normal(0, scale, (nq, 3)) + rng.normal(0, 50, 3))
        ts.append(rng.normal(0, scale, (nt, 3)) + rng.normal(0, 50, 3))
    return qs, ts


def _kernel_args(qs, ts):
    qoff = np.r_[0, np.cumsum([len(q) for q in qs])].astype(np.int64)
    toff = np.r_[0, np.cumsum([len(t) for t in ts])].astype(np.int64)
    return np.concatenate(qs), qoff, np.concatenate(ts), toff


@pytest.mark.parametrize("seed", range(6))
def test_max_nearest_kernel_equals_ckdtree(seed):
    qs, ts = _sets(seed)
    expected = max([float(cKDTree(t).query(q)[0].max()) for q, t in zip(qs, ts) if len(q)] + [0.0])
    args = _kernel_args(qs, ts)
    for stride in (1, 7, 64, 10 ** 9):
        assert float(np.sqrt(tiles3d._max_nearest_sq(*args, stride))) == expected
    # a set with queries and no target: cKDTree's inf
    qs.append(np.zeros((2, 3)))
    ts.append(np.zeros((0, 3)))
    assert tiles3d._max_nearest_sq(*_kernel_args(qs, ts), 64) == np.inf
    assert float(cKDTree(ts[-1]).query(qs[-1])[0].max()) == np.inf


# =========================================================================== models_3d layer

@pytest.mark.parametrize("name,frame,leaves,coarsest", TABLE_OPTIONS, ids=[t[0] for t in TABLE_OPTIONS])
def test_models_table_with_a_cache_is_the_same(models, name, frame, leaves, coarsest):
    expected = gpkg3d.models_table(models, frame, leaves=leaves, coarsest=coarsest)
    got = gpkg3d.models_table(models, frame, leaves=leaves, coarsest=coarsest, cache={})
    assert list(got.geometries) == list(expected.geometries) and got.extent == expected.extent
    for key, values in expected.columns.items():
        assert np.array_equal(got.columns[key], values, equal_nan=values.dtype.kind == "f"), key
    slivers = [m.tree_id for m in models].index(32)                            # its coarse wood: slivers only
    assert (expected.geometries[slivers] is None) == (coarsest and not leaves)


# =========================================================================== kernels and helpers

#: Nearly opposite face normals at vertex 0, met at corners 2, 0 and 1: the sum's order shows in float32.
_CANCELLING = (np.array([[0, 0, 0], [1000, 0, 0], [0, 1000, 0], [0.001, 1000, 0], [1000, 0.002, 0.003],
                         [0.01, 0.003, 0], [0.002, 0.011, 0.004]], dtype=np.float32),
               np.array([[1, 2, 0], [0, 3, 4], [5, 0, 6]]))


def _random_meshes(seed: int):
    """float32 meshes with degenerate faces (repeated and collinear corners), unreferenced vertices,
    tiny triangles (normals under the 1e-12 threshold) and cancelling face normals."""
    rng = np.random.default_rng(seed)
    out = [_CANCELLING, (_CANCELLING[0] * np.float32(1e-7), _CANCELLING[1])]
    for k in range(5):
        nv = int(rng.integers(0, 60)) if k else 0
        pos = (rng.normal(0, 10 ** rng.uniform(-3, 3), (nv, 3))).astype(np.float32)
        if nv > 2:
            pos[1] = pos[0]
            pos[2] = 2 * pos[0] - pos[3 % nv]
        nf = int(rng.integers(0, 80)) if nv else 0
        faces = rng.integers(0, max(nv - 3, 1), (nf, 3)) if nv else np.zeros((0, 3), np.int64)
        if nf and nv > 2:
            faces[0] = [0, 1, 2]
        out.append((pos, faces.astype(np.int64)))
    return out


@pytest.mark.parametrize("seed", range(4))
def test_normals_are_unit_and_bounds_are_the_vertices(seed):
    """Unit normals (up where a vertex has no face or only degenerate ones), the right-hand rule's side,
    and per-mesh bounds that are the vertices' own."""
    meshes = _random_meshes(seed) + [(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5]], np.float32),
                                      np.array([[0, 1, 2]]))]
    normals, lo, hi = gltf._normals_and_bounds([p for p, _ in meshes], [f for _, f in meshes])
    for n, (p, f) in zip(normals, meshes):
        assert n.dtype == np.float32 and n.shape == p.shape
        assert np.allclose(np.linalg.norm(n.astype(np.float64), axis=1), 1.0, atol=1e-6)
        used = np.zeros(len(p), bool)
        used[f.ravel()] = True
        assert np.array_equal(n[~used], np.tile(np.float32([0, 0, 1]), ((~used).sum(), 1)))
    assert np.array_equal(normals[-1][:3], np.tile(np.float32([0, 0, 1]), (3, 1)))   # counter-clockwise: up
    for k, (p, _) in enumerate(meshes):
        if len(p):
            assert np.array_equal(lo[k], p.min(axis=0)) and np.array_equal(hi[k], p.max(axis=0))


def test_memoised_pyproj_objects_give_the_same_frames(models, monkeypatch):
    """Georef's thread-local memo of CRSs and transformers changes no number (fresh objects as before)."""
    def outputs(frame):
        g = Georef(frame, ORIGIN)
        frames = g.tree_frames([m.base for m in models])
        enu = g.source_to_enu(np.array([m.base for m in models]))
        return g.describe(), frames[0], frames[1], enu, g.enu_to_source(enu)

    frames = [UTM, ExportFrame("EPSG:2994"), ExportFrame("EPSG:32632+5773")]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")   # no geoid grid installed
        memoised = [outputs(f) for f in frames] + [outputs(frames[0])]
        monkeypatch.setattr(georef_mod, "_memo", lambda key, make: make())
        fresh = [outputs(f) for f in frames] + [outputs(frames[0])]
    for a, b in zip(memoised, fresh):
        assert a[0] == b[0]
        assert all(np.array_equal(x, y) for x, y in zip(a[1:], b[1:]))


if __name__ == "__main__":
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        outputs = compute_outputs(Path(tmp))
    if "--write" in sys.argv:
        GOLDEN.parent.mkdir(exist_ok=True)
        GOLDEN.write_text(json.dumps(outputs, indent=1, sort_keys=True) + "\n")
        print(f"wrote {len(outputs)} fingerprints")
    else:
        print("changed:", same_outputs(outputs, json.loads(GOLDEN.read_text())))
