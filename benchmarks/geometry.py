"""Speed of tree geometry and leaves: radii, branch chains, meshes per level of detail, leaf cards.

Run: ``python benchmarks/geometry.py`` (from the repository root, in the venv).
Prints, for random skeletons of 100, 300, 1000 and 3000 nodes, the best-of-N
wall time of each step, the faces and vertices produced per LOD, and leaves
per second for leaf cards and needle clusters.  No assertions on timings.

:func:`random_skeleton` is also used by tests/test_geometry.py and
tests/test_leaves.py (loaded with importlib; benchmarks/ is not a package).
"""
from __future__ import annotations

import time

import numpy as np


def random_skeleton(m: int, seed: int = 0, step_m=(0.2, 0.6)):
    """A random tree-like skeleton of ``m`` nodes: a stem, then branches that fork off.

    Node 0 is the root at the origin; ``parent[i] < i``; the first m/10 nodes
    form a near-vertical stem, later nodes mostly extend the previous node
    (a growing branch) and sometimes fork from an earlier node of the crown.
    """
    from sylva.core.skeleton import Skeleton

    rng = np.random.default_rng(seed)
    nodes = np.zeros((m, 3))
    parent = np.full(m, -1, dtype=np.int64)
    dirs = np.zeros((m, 3))
    dirs[0] = (0.0, 0.0, 1.0)
    stem = max(2, m // 10)
    for i in range(1, m):
        if i < stem:
            p = i - 1
            d = dirs[p] + rng.normal(0.0, 0.05, 3)
        else:
            p = i - 1 if (i == stem or rng.random() < 0.8) else int(rng.integers(stem // 2, i))
            d = dirs[p] + rng.normal(0.0, 0.3, 3)
            if p != i - 1:  # a new branch leaves sideways and upwards
                d = d + np.r_[rng.normal(0.0, 1.0, 2), 0.3]
        d /= np.linalg.norm(d)
        dirs[i] = d
        parent[i] = p
        nodes[i] = nodes[p] + d * rng.uniform(*step_m)
    return Skeleton(nodes, parent)


def _best(fn, repeat=7, number=3):
    best = np.inf
    out = None
    for _ in range(repeat):
        t0 = time.perf_counter()
        for _ in range(number):
            out = fn()
        best = min(best, (time.perf_counter() - t0) / number)
    return best, out


def main():
    from sylva.core import geometry as G
    from sylva.core import leaves as LV
    from sylva.core import textures as TX

    print("Sylva geometry benchmark (best of 7 x 3 runs, wall time)")
    print(f"{'nodes':>6} {'branches':>8} {'radii ms':>9} {'chains ms':>9} "
          f"{'lod':>3} {'sides':>5} {'samples':>7} {'mesh ms':>8} {'faces':>8} {'vertices':>8}")
    for m in (100, 300, 1000, 3000):
        sk = random_skeleton(m, seed=1)
        t_r, radii = _best(lambda: G.pipe_model_radii(sk))
        sk = G.with_radii(sk, radii)
        t_b, bset = _best(lambda: G.branches(sk, radii))
        for lod in range(3):
            spec = G.LOD[lod]
            t_m, mesh = _best(lambda: G.tree_mesh(sk, lod))
            print(f"{m:>6} {len(bset):>8} {t_r * 1e3:>9.2f} {t_b * 1e3:>9.2f} {lod:>3} {spec.sides:>5} "
                  f"{spec.samples_per_segment:>7} {t_m * 1e3:>8.2f} {len(mesh.faces):>8} {len(mesh.vertices):>8}")
    print()
    print(f"{'nodes':>6} {'method':>16} {'tips':>5} {'leaves':>7} {'ms':>8} {'leaves/s':>10} {'faces':>7}")
    for m in (300, 1000, 3000):
        sk = random_skeleton(m, seed=1)
        sk = G.with_radii(sk, G.pipe_model_radii(sk))
        for name, method in (("LeafCards", LV.LeafCards()), ("NeedleClusters", LV.NeedleClusters())):
            t_l, lm = _best(lambda: LV.grow_leaves(sk, method, seed=3))
            print(f"{m:>6} {name:>16} {len(sk.tips()):>5} {lm.n_leaves:>7} {t_l * 1e3:>8.2f} "
                  f"{lm.n_leaves / t_l:>10.0f} {len(lm.faces):>7}")
    print()
    for shape in TX.LEAF_SHAPES:
        t_t, _ = _best(lambda: TX.leaf_texture(shape, 256), repeat=3, number=1)
        print(f"leaf_texture({shape!r}, 256): {t_t * 1e3:.0f} ms")
    # wood volume / measurements of the 1000-node tree
    sk = random_skeleton(1000, seed=1)
    sk = G.with_radii(sk, G.pipe_model_radii(sk))
    t_v, vol = _best(lambda: G.wood_volume(sk))
    print(f"\nwood_volume (1000 nodes): {vol:.4f} m3 in {t_v * 1e3:.2f} ms; "
          f"branch_count {G.branch_count(sk)}, total_branch_length {G.total_branch_length(sk):.1f} m")


if __name__ == "__main__":
    main()
