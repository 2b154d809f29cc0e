"""Speed and size of the 3D exports: GLB, 3D Tiles, CityGML, OBJ.

Run: ``python benchmarks/export.py`` (from the repository root, in the venv,
with ``PROJ_DATA`` set if PROJ needs it).  Writes N = 100 and 1,000
synthetic tree models (random skeletons, pipe-model radii, LOD 1 wood, leaf
cards; a coarse LOD 0 for the 3D Tiles parent level) in EPSG:32632 to a
temporary folder and prints, per format, the wall time, the time per tree
and the bytes per tree.  No assertions.

:func:`synthetic_models` is also used by tests/test_export.py and
tests/test_viewers.py (loaded with importlib; benchmarks/ is not a package).
"""
from __future__ import annotations

import importlib.util
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

_HERE = Path(__file__).resolve().parent


def _random_skeleton():
    spec = importlib.util.spec_from_file_location("_sylva_bench_geometry", _HERE / "geometry.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.random_skeleton


def synthetic_models(n: int, seed: int = 0, origin=(500000.0, 5400000.0, 300.0), spacing_m: float = 8.0,
                     nodes: int = 80, leaves: bool = True, lods: bool = True, unit_m: float = 1.0,
                     unique: int = 8):
    """``n`` TreeModels on a jittered grid around ``origin`` (source CRS units, metres per unit ``unit_m``).

    Meshes of ``unique`` random skeletons (``nodes`` nodes each) are reused
    round-robin, so building many models stays cheap; bases, ids and
    attributes differ per tree.  Ground z varies by a gentle slope.
    """
    from sylva.core import geometry as G
    from sylva.core.export.model import TreeModel
    from sylva.core.leaves import LeafCards, NeedleClusters, grow_leaves

    random_skeleton = _random_skeleton()
    rng = np.random.default_rng(seed)
    protos = []
    for k in range(min(unique, n)):
        sk = random_skeleton(nodes, seed=seed * 1000 + k)
        sk = G.with_radii(sk, G.pipe_model_radii(sk))
        wood = G.tree_mesh(sk, 1)
        coarse = G.tree_mesh(sk, 0)
        conifer = k % 2 == 1
        lm = None
        if leaves:
            method = NeedleClusters(clusters_per_tip=4) if conifer else LeafCards(leaves_per_tip=6)
            lm = grow_leaves(sk, method, seed=k)
        height = float(sk.nodes[:, 2].max())
        crown = float(np.ptp(sk.nodes[:, :2], axis=0).max())
        protos.append((wood, coarse, lm, height, crown, "pine" if conifer else "apple",
                       float(2 * sk.radius[0])))
    side = int(np.ceil(np.sqrt(n)))
    out = []
    for i in range(n):
        wood, coarse, lm, height, crown, species, dbh = protos[i % len(protos)]
        gx, gy = i % side, i // side
        dx, dy = (np.array([gx, gy]) - side / 2) * spacing_m + rng.uniform(-1.5, 1.5, 2)
        ground = 0.02 * dx + 0.01 * dy + rng.normal(0, 0.05)
        base = np.array(origin, float) + np.array([dx, dy, ground]) / unit_m
        attrs = {"tree_id": i + 1, "height": round(height, 3), "crown_diameter": round(crown, 3),
                 "crown_base_height": round(0.3 * height, 3), "dbh": round(dbh, 4), "dbh_source": "model",
                 "species": species, "method": "synthetic"}
        out.append(TreeModel(i + 1, base, wood, lm, attrs, {0: coarse} if lods else {}))
    return out


def _size(paths) -> int:
    total = 0
    for p in paths:
        p = Path(p)
        total += sum(f.stat().st_size for f in p.rglob("*") if f.is_file()) if p.is_dir() else p.stat().st_size
    return total


def main(sizes=(100, 1000)):
    from sylva.core.export import ExportFrame, write_citygml, write_glb, write_obj, write_tileset

    frame = ExportFrame("EPSG:32632")
    print("Sylva export benchmark (synthetic trees, 80-node skeletons, LOD 1 wood + leaf cards, EPSG:32632)")
    print("CityGML: explicit lod1 + lod2 MultiSurfaces (wood only); CityGML-i: ImplicitGeometry prototypes")
    print(f"{'trees':>6} {'format':>10} {'seconds':>8} {'ms/tree':>8} {'bytes/tree':>11} {'files':>6}")
    with tempfile.TemporaryDirectory() as tmp:   # warm-up: imports, PROJ database, leaf textures
        warm = synthetic_models(4, seed=1)
        write_glb(warm, Path(tmp) / "w.glb", frame)
        write_tileset(warm, Path(tmp) / "w", frame)
        write_citygml(warm, Path(tmp) / "w.gml", frame)
        write_obj(warm, Path(tmp) / "w.obj", frame)
    for n in sizes:
        t0 = time.perf_counter()
        models = synthetic_models(n, seed=1)
        t_build = time.perf_counter() - t0
        verts = sum(len(m.wood.vertices) + len(m.leaves.vertices) for m in models)
        print(f"{n:>6} {'(models)':>10} {t_build:>8.2f} {t_build / n * 1e3:>8.2f} "
              f"{'':>11} {'':>6}   {verts / n:.0f} vertices/tree")
        with tempfile.TemporaryDirectory() as tmp:
            tmp = Path(tmp)
            jobs = [
                ("GLB", lambda: write_glb(models, tmp / "trees.glb", frame)),
                ("3D Tiles", lambda: write_tileset(models, tmp / "tiles", frame)),
                ("CityGML", lambda: write_citygml(models, tmp / "trees.gml", frame)),
                ("CityGML-i", lambda: write_citygml(models, tmp / "trees_i.gml", frame, implicit=True)),
                ("OBJ", lambda: write_obj(models, tmp / "trees.obj", frame)),
            ]
            for name, job in jobs:
                t0 = time.perf_counter()
                paths = job()
                dt = time.perf_counter() - t0
                size = _size(paths if name != "3D Tiles" else [tmp / "tiles"])
                print(f"{n:>6} {name:>10} {dt:>8.2f} {dt / n * 1e3:>8.2f} {size / n:>11.0f} {len(paths):>6}")
            sys.stdout.flush()


if __name__ == "__main__":
    main()
