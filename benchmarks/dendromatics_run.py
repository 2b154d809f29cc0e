"""dendromatics (3DFin's engine, Laino et al. 2024) on one plot scan, for benchmarks/stems.py.

    python benchmarks/dendromatics_run.py points.npy result.npz      # with a Python that has dendromatics

3DFin's own processing order (3DFin ``processing/abstract_processing.py``) with its default parameters
(stripe 0.7-3.5 m, sections every 0.2 m from 0.3 m, 5 cm thick), the function defaults of dendromatics
otherwise: cloth-simulation DTM (``generate_dtm``, 0.7 m cloth), heights, verticality clustering of the
stripe, ``individualize_trees``, stem points within 1 m of their axis re-clustered, ``compute_sections``,
``tilt_detection`` and ``tree_locator`` (DBH, 0 where not reliable).  Writes tree positions, DBH, the tree
ID of every point and the time.
"""
from __future__ import annotations

import sys
import time

import numpy as np


def main(src: str, dst: str) -> None:
    import dendromatics as dm

    xyz = np.load(src).astype(np.float64)
    t0 = time.perf_counter()
    cloth = dm.generate_dtm(xyz, cloth_resolution=0.7)
    dtm = dm.clean_cloth(cloth)
    z0 = dm.normalize_heights(xyz, dtm)
    coords = np.c_[xyz, z0]
    stripe = coords[(coords[:, 3] > 0.7) & (coords[:, 3] < 3.5), 0:4]
    clust = dm.verticality_clustering(stripe, 0.1, 0.7, 1000, 2, 0.02, 0.02, 5)
    assigned, tree_vector, heights = dm.individualize_trees(coords, clust, stripe_lower_limit=0.7,
                                                            stripe_upper_limit=3.5, tree_id_field=-1)
    stems_pts = assigned[(assigned[:, 5] < 1.0) & (assigned[:, 3] > 0.3) & (assigned[:, 3] < 25 + 0.05), :]
    stems = dm.verticality_clustering(stems_pts, 0.1, 0.7, 1000, 2, 0.02, 0.02, 5)[:, 0:6]
    sections = np.arange(0.3, 25, 0.2)
    x_c, y_c, r, check, _, sector, n_in = dm.compute_sections(stems, sections, 0.05)
    np.seterr(divide="ignore", invalid="ignore")
    outliers = dm.tilt_detection(x_c, y_c, r, sections, w_1=3, w_2=1)
    dbh, loc = dm.tree_locator(sections, x_c, y_c, tree_vector, sector, r, outliers)
    dt = time.perf_counter() - t0
    # tree ID of every input point (assigned keeps the input order: x, y, z, z0, tree ID, distance to axis)
    same = len(assigned) == len(xyz) and np.allclose(assigned[:, :3], xyz)
    tid = assigned[:, 4].astype(np.int64) if same else np.full(len(xyz), -1)
    np.savez(dst, xy=loc[:, :2], dbh=dbh[:, 0], tree_id=tid, seconds=dt)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
