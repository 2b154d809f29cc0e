"""Segmentation on stands made by a second, independent generator: analytic crowns, vertical pulses.

    python benchmarks/analytic_stands.py                  # seeds 0, 1, 2 at 2, 5 and 10 points/m2
    python benchmarks/analytic_stands.py --seeds 0 --densities 5 --stands conifers,plantation

``sylva.testing`` (``synth``, ``crowns``) was written beside the segmenter; a figure from it alone
flatters it.  This generator shares nothing with it but the truth format the scoring reads
(``tree_id``, ``x``, ``y``, ``height``, ``crown_radius_m``): trees stand at random (a hard-core
distance) or in planted rows; a crown is a surface of revolution over its stem, a cone, a
half-ellipsoid, a flat-topped or a columnar dome (the crown forms of Pretzsch 2009, ch. 8), its
radius a share of the tree's height drawn per form, with no crown allometry of Sylva's; a
broadleaf crown is dented by leaf clumps (the surface drops by up to 1.5 m between 6-15 clumps);
each pulse is vertical, at a uniformly random place: its first return lies on the highest crown
surface over it, unless it passes through one of that crown's holes (15 % of the pulses per
crown), 40 % of hits give a second return inside the crown, 35 % a last return on the ground.
No beam, no scan angle, no occlusion beyond the surfaces, ground flat: not a better simulator
than ``sylva.testing``, a different one.

Each row gives, per stand and density, the detection F1 (``metrics.evaluate``: tops within 0.5 x
the true crown radius, heights within 15 %) of the true segmentation itself (``truth``: what the
matching allows at that density, since a sparse scan misses a steep tip and a clumped crown's
highest point is off its stem), of NormalizedCut and of ChmRegionGrowing, all on the cloud the
chain segments (``sylva.core.segment.tile.prepare_tile``).
"""
from __future__ import annotations

import argparse
import importlib.util
import sys
from dataclasses import dataclass
from multiprocessing import Pool
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent

#: stand name: (trees, side m, crown forms, height range m, crown radius / height per form,
#: hard-core distance m (0: rows), share of trees 0.45-0.7 x as high)
STANDS = {
    "conifers": (45, 60.0, ("cone",), (15.0, 30.0), {"cone": (0.10, 0.15)}, 6.0, 0.0),
    "plantation": (64, 60.0, ("cone",), (18.0, 22.0), {"cone": (0.14, 0.18)}, 0.0, 0.0),
    "open-forms": (25, 60.0, ("round", "flat", "column"), (10.0, 22.0),
                   {"round": (0.20, 0.30), "flat": (0.25, 0.35), "column": (0.10, 0.15)}, 8.0, 0.0),
    "dense-mixed": (60, 60.0, ("cone", "round", "flat", "column"), (14.0, 28.0),
                    {"cone": (0.10, 0.15), "round": (0.18, 0.26), "flat": (0.20, 0.30),
                     "column": (0.10, 0.14)}, 4.5, 0.2),
    "dense-broadleaf": (70, 60.0, ("round", "flat"), (15.0, 25.0),
                        {"round": (0.18, 0.25), "flat": (0.20, 0.28)}, 4.0, 0.15),
}
X0, Y0 = 500000.0, 5000000.0


@dataclass
class Tree:
    tree_id: int
    x: float
    y: float
    height: float
    crown_radius_m: float
    base: float
    form: str
    clumps: np.ndarray
    depth: float


def make_stand(name: str, seed: int):
    n, side, forms, (hlo, hhi), share, hard_core, under = STANDS[name]
    rng = np.random.default_rng([seed, sum(map(ord, name))])
    if hard_core > 0:
        xy = []
        for _ in range(200 * n):
            p = rng.uniform(0.0, side, 2)
            if all(np.hypot(*(p - q)) >= hard_core for q in xy):
                xy.append(p)
            if len(xy) == n:
                break
    else:
        k = int(np.ceil(np.sqrt(n)))
        xy = [np.array([(i + 0.5) * side / k, (j + 0.5) * side / k]) + rng.normal(0.0, 0.3, 2)
              for i in range(k) for j in range(k)][:n]
    trees = []
    for i, (x, y) in enumerate(xy, start=1):
        form = forms[rng.integers(len(forms))]
        h = rng.uniform(hlo, hhi) * (rng.uniform(0.45, 0.7) if rng.random() < under else 1.0)
        r = h * rng.uniform(*share[form])
        base = h * (rng.uniform(0.2, 0.5) if form == "cone" else rng.uniform(0.3, 0.6))
        nc = 0 if form == "cone" else int(rng.integers(6, 16))
        a, d = rng.uniform(0, 2 * np.pi, nc), r * np.sqrt(rng.uniform(0, 1, nc))
        trees.append(Tree(i, float(x), float(y), h, r, base, form,
                          np.column_stack([d * np.cos(a), d * np.sin(a)]), rng.uniform(0.5, 1.5) if nc else 0.0))
    return trees, side, rng


def surface(t: Tree, dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """Height of the crown surface of ``t`` over offsets (dx, dy) from its stem (-inf outside)."""
    r = np.hypot(dx, dy) / t.crown_radius_m
    u = np.clip(r, 0.0, 1.0)
    length = t.height - t.base
    if t.form == "cone":
        z = t.height - length * u
    elif t.form == "round":
        z = t.base + 0.5 * length * (1.0 + np.sqrt(1.0 - u ** 2))
    elif t.form == "flat":
        z = t.base + length * (0.75 + 0.25 * (1.0 - u ** 4) ** 0.25)
    else:
        z = t.base + length * (0.85 + 0.15 * (1.0 - u ** 6) ** (1.0 / 6.0))
    if len(t.clumps):
        d2 = (dx[:, None] - t.clumps[:, 0]) ** 2 + (dy[:, None] - t.clumps[:, 1]) ** 2
        s = 0.28 * t.crown_radius_m
        z = z - t.depth * (1.0 - np.exp(-d2 / (2.0 * s * s)).max(axis=1))
    return np.where(r < 1.0, z, -np.inf)


def scan(trees, side: float, density: float, rng):
    """(xyz, true tree per point (0 ground), return number) of vertical pulses at ``density`` per m2."""
    n = rng.poisson(density * side * side)
    px, py = rng.uniform(0.0, side, n), rng.uniform(0.0, side, n)
    z = np.full((n, len(trees)), -np.inf)
    for j, t in enumerate(trees):
        z[:, j] = surface(t, px - t.x, py - t.y)
        z[rng.random(n) < 0.15, j] = -np.inf
    first = z.argmax(axis=1)
    top = z[np.arange(n), first]
    hit = np.isfinite(top)
    second = hit & (rng.random(n) < 0.4)
    base = np.array([trees[k].base for k in first[second]])
    ground = hit & (rng.random(n) < 0.35)
    parts = [(px, py, np.where(hit, top, 0.0), np.where(hit, first + 1, 0), 1),
             (px[second], py[second], rng.uniform(base, top[second]), first[second] + 1, 2),
             (px[ground], py[ground], np.zeros(ground.sum()), np.zeros(ground.sum(), int), 3)]
    x, y, zz, tid, rn = (np.concatenate([np.broadcast_to(np.asarray(p[i]), p[0].shape) for p in parts])
                         for i in range(5))
    zz = zz + rng.normal(0.0, 0.05, len(zz))
    return np.column_stack([x + X0, y + Y0, zz]), tid.astype(np.int32), rn.astype(np.uint8)


def _metrics():
    """benchmarks/metrics.py (the scoring of benchmarks/segmentation.py), loaded by path."""
    name = "sylva_bench_metrics"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, HERE / "metrics.py")
        sys.modules[name] = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(sys.modules[name])
    return sys.modules[name]


def run(job):
    """(stand, density, seed, trees, [(F1, trees found)] of the truth, NormalizedCut, ChmRegionGrowing)."""
    name, density, seed = job
    from sylva.core.cloud import PointCloud
    from sylva.core.segment import ChmRegionGrowing, NormalizedCut, segment_trees
    from sylva.core.segment.tile import prepare_tile

    M = _metrics()

    trees, side, rng = make_stand(name, seed)
    xyz, truth, rn = scan(trees, side, density, rng)
    cloud = PointCloud(xyz=xyz, attrs={"classification": np.where(truth == 0, 2, 1).astype(np.uint8),
                                       "return_number": rn}, crs="EPSG:32632")
    for t in trees:
        t.x, t.y = t.x + X0, t.y + Y0
    work, keep = prepare_tile(cloud)
    truth = truth[keep]
    out = []
    for labels in (truth, segment_trees(work, NormalizedCut()), segment_trees(work, ChmRegionGrowing())):
        r = M.evaluate(work.xyz, work.attrs["height"], labels, truth, trees)
        out.append((r["f1"], r["n_detected"]))
    return name, density, seed, len(trees), out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--stands", default=",".join(STANDS))
    ap.add_argument("--densities", default="2,5,10")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--workers", type=int, default=2)
    a = ap.parse_args(argv)
    jobs = [(s, float(d), int(k)) for k in a.seeds.split(",") for s in a.stands.split(",")
            for d in a.densities.split(",")]
    print(f"{'stand':16s} {'p/m2':>4s} {'seed':>4s} {'trees':>5s} | {'truth':>11s} | {'ncut':>11s} | {'chm':>11s}")
    f1 = {"truth": [], "ncut": [], "chm": []}
    with Pool(a.workers) as pool:
        for name, density, seed, n, out in pool.imap(run, jobs):
            print(f"{name:16s} {density:4g} {seed:4d} {n:5d} | "
                  + " | ".join(f"{f:.3f} ({k:3d})" for f, k in out), flush=True)
            for key, (f, _) in zip(f1, out):
                f1[key].append(f)
    print("mean F1: " + ", ".join(f"{k} {np.mean(v):.3f}" for k, v in f1.items()))


if __name__ == "__main__":
    main()
