"""From a segmented cloud to a modelled forest: one skeleton, mesh, leaves and record per tree.

    trees = model_trees(cloud, labels, metrics, ModelOptions())

``cloud`` is height-normalised (attribute ``height``), ``labels`` its
treeID per point and ``metrics`` the :class:`~sylva.core.measure.TreeMetrics`
of that segmentation.  Each tree's points go, in the tile's local metric
frame, to :func:`~sylva.core.reconstruct.reconstruct_tree` (default: the
Hu et al. §6.2 hybrid, greedy skeleton with guided growth as the fallback,
so every tree gets a model); the skeleton gets radii (pipe model, Hu Eq. 6,
scaled so the stem at the base has the tree's DBH) and becomes a mesh and
leaf cards (:mod:`sylva.core.geometry`, :mod:`sylva.core.leaves`).

Trees with fewer than ``min_points`` points are not dropped: they get the
minimal stem the reconstruction gives them and ``quality = "noise"``.

Every tree also gets a quantitative structure model (:class:`~sylva.core.qsm.QSM`,
TreeQSM-like cylinder and branch tables, ``ModelledTree.qsm``): for the
dense-scan method (Yan et al. 2009, :class:`~sylva.core.reconstruct.VariationalKMeans`)
the cylinders of its B-spline branches (§4) with the DBH measured at 1.3 m
above the stem base (``record["qsm_method"] = "bspline_cylinders"``); for
the other methods one cylinder per skeleton edge with the skeleton's radii
(``"skeleton_edges"``), measured by :func:`~sylva.core.qsm.measure_qsm` but
with the DBH of the record.  :func:`qsm_tables` turns them into the
cylinders / branches / trees tables in CRS coordinates.
"""
from __future__ import annotations

import zlib
from dataclasses import dataclass, field
from typing import Any, List

import numpy as np

from .cloud import PointCloud
from .geometry import (branch_count, pipe_model_radii, simplify_skeleton, total_branch_length, tree_mesh,
                       with_radii, wood_volume)
from .leaves import LeafCards, NeedleClusters, grow_leaves
from .measure import TreeMetrics, estimate_dbh
from .progress import CancelCheck, Progress, check, report
from .qsm import cylinders_from_skeleton, measure_qsm
from .reconstruct import Hybrid, TreePoints, is_dense_scan, reconstruct_tree

LEAVES = ("auto", "broadleaf", "needles", "none")


@dataclass(frozen=True)
class ModelOptions:
    method: Any = Hybrid()
    dense_method: Any = None      # used instead of `method` for trees is_dense_scan() calls dense
    lod: int = 1
    leaves: str = "auto"          # auto: needles for conical crowns, leaf cards otherwise
    leaf_shape: str = "ovate"
    tip_radius_m: float = 0.01
    simplify_m: float = 0.05      # skeleton nodes closer than this to a straight run are dropped
    min_points: int = 10


@dataclass(eq=False)
class ModelledTree:
    tree_id: int
    base_local: np.ndarray        # stem base, tile-local metres
    skeleton: Any                 # Skeleton with radii, tile-local metres
    wood: Any                     # trimesh.Trimesh, metres, origin at the base
    leaves: Any                   # LeafMesh (origin at the base) or None
    record: dict = field(default_factory=dict)
    qsm: Any = None               # sylva.core.qsm.QSM, tile-local metres (see qsm_tables)


#: Branch orders counted in the record's ``n_branches_order_<o>`` fields (the
#: full counts are in ``branch_counts``, "order:count" pairs).
QSM_ORDERS = (1, 2, 3)


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


def leaf_mesh(skeleton, kind: str, options: ModelOptions = ModelOptions(), seed: int = 0):
    """Needle clusters or leaf cards (``kind`` "needles" / "broadleaf"; else None) on a skeleton with radii.

    Coarse levels of detail get fewer, larger cards: the crown's look at a fraction of the faces.
    """
    scale = {0: 3.0, 1: 1.5}.get(options.lod, 1.0)
    if kind == "needles":
        return grow_leaves(skeleton, NeedleClusters(clusters_per_tip=max(2, int(8 / scale)),
                                                    cluster_length_m=0.3 * scale), seed=seed)
    if kind == "broadleaf":
        return grow_leaves(skeleton, LeafCards(shape=options.leaf_shape, leaves_per_tip=max(2, int(12 / scale ** 2)),
                                               leaf_length_m=0.1 * scale), seed=seed)
    return None


def model_trees(cloud: PointCloud, labels: np.ndarray, metrics: TreeMetrics,
                options: ModelOptions = ModelOptions(), progress: Progress = None,
                cancelled: CancelCheck = None) -> List[ModelledTree]:
    """Model every tree of ``labels`` (see the module docstring), in tree_id order."""
    local = cloud.local_xyz()
    height = np.asarray(cloud.attrs["height"], dtype=np.float64)
    row_of = {int(t): i for i, t in enumerate(metrics.tree_id)}
    ids, groups = _groups(np.asarray(labels))
    out = []
    for k, (tree_id, idx) in enumerate(zip(ids, groups)):
        check(cancelled)
        report(progress, k / max(len(ids), 1), f"tree {k + 1} of {len(ids)}")
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
        skeleton = simplify_skeleton(rec.skeleton, options.simplify_m) if options.simplify_m > 0 else rec.skeleton
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
        if dense_qsm is not None:
            qsm, qsm_method = dense_qsm, "bspline_cylinders"
            qsm.dbh_m, qsm.dbh_source = float(dbh), source
        else:
            cyl, bpar = cylinders_from_skeleton(skeleton)
            qsm = measure_qsm(cyl, bpar, xyz, base_z=ground_z, tree_id=int(tree_id))
            qsm.dbh_m, qsm.dbh_source = float(dbh), source     # the record's DBH, not the pipe model's
            qsm_method = "skeleton_edges"
        base = skeleton.nodes[skeleton.root].copy()
        shifted = with_radii(type(skeleton)(skeleton.nodes - base, skeleton.parent, radii, skeleton.is_added), radii)
        wood = tree_mesh(shifted, lod=options.lod)
        kind = options.leaves
        if kind == "auto":
            kind = "needles" if is_conical(xyz, ground_z + metrics.crown_base_height[i]) else "broadleaf"
        leaves = leaf_mesh(shifted, kind, options, seed=zlib.crc32(f"leaves-{int(tree_id)}".encode()))
        noise = len(idx) < options.min_points
        quality = "noise" if noise else ("fallback" if "fallback" in rec.flags else "ok")
        record = {
            "tree_id": int(tree_id),
            "base_x": 0.0, "base_y": 0.0, "base_z": 0.0,  # filled in CRS units below
            "dbh": float(dbh), "dbh_source": source,
            "n_branches": int(branch_count(skeleton)),
            "total_branch_length": float(total_branch_length(skeleton)),
            "wood_volume": float(wood_volume(skeleton)),
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
        crs_base = cloud.from_local(base[None, :])[0]
        record.update(base_x=float(crs_base[0]), base_y=float(crs_base[1]), base_z=float(crs_base[2]))
        out.append(ModelledTree(int(tree_id), base, skeleton, wood, leaves, record, qsm))
    report(progress, 1.0, "trees modelled")
    return out


def skeleton_table(trees: List[ModelledTree], cloud: PointCloud, crs=None):
    """One MultiLineStringZM per tree: each part a branch chain, M = radius (m), CRS coordinates."""
    from .geometry import branches
    from .table import VectorTable, multilinestring_zm_wkb

    wkb, ids, n_chains = [], [], []
    for t in trees:
        sk = t.skeleton
        chains = [c for c in branches(sk, sk.radius) if len(c) >= 2]
        parts = [np.column_stack([cloud.from_local(sk.nodes[c]), sk.radius[c]]) for c in chains]
        wkb.append(multilinestring_zm_wkb(parts))
        ids.append(t.tree_id)
        n_chains.append(len(parts))
    return VectorTable("skeletons", "line", np.array(wkb, dtype=object),
                       {"tree_id": np.array(ids, dtype=np.int64), "n_chains": np.array(n_chains, dtype=np.int64)},
                       crs if crs is not None else cloud.crs, has_m=True)


def qsm_tables(trees: List[ModelledTree], cloud: PointCloud, crs=None):
    """The QSMs of ``trees`` as (cylinders, branches, trees) VectorTables in CRS coordinates.

    ``cylinders``: a 3-D line from start to end per cylinder with ``tree_id``
    and the TreeQSM fields (:data:`~sylva.core.qsm.CYLINDER_FIELDS`: start in
    CRS units, unit axis, length and radius in metres); ``branches``: no
    geometry (:data:`~sylva.core.qsm.BRANCH_FIELDS` + tree_id, base_height in
    CRS units); ``trees``: one row per tree (DBH, height, volumes, branch
    counts by order, see :func:`~sylva.core.qsm.trees_table`) plus the
    ``qsm_method``.  Trees without a QSM are left out.
    """
    from shapely import linestrings

    from .qsm import branches_table, cylinders_table, trees_table
    from .table import VectorTable

    crs = crs if crs is not None else cloud.crs
    qs = [t.qsm for t in trees if t.qsm is not None]
    cyl = cylinders_table(qs, crs, geometry=False)
    c = cyl.columns
    start = np.stack([c["start_x"], c["start_y"], c["start_z"]], axis=1).astype(float).reshape(-1, 3)
    axis = np.stack([c["axis_x"], c["axis_y"], c["axis_z"]], axis=1).astype(float).reshape(-1, 3)
    end = start + axis * np.asarray(c["length"], dtype=float).reshape(-1, 1)
    s_crs, e_crs = cloud.from_local(start), cloud.from_local(end)
    cols = dict(c)
    cols["start_x"], cols["start_y"], cols["start_z"] = s_crs[:, 0], s_crs[:, 1], s_crs[:, 2]
    geoms = linestrings(np.stack([s_crs, e_crs], axis=1)) if len(s_crs) else np.zeros(0, dtype=object)
    cylinders = VectorTable("cylinders", "line", np.asarray(geoms, dtype=object), cols, crs)
    branches = branches_table(qs, crs)
    bz = np.asarray(branches.columns["base_height"], dtype=float)
    if len(bz):
        branches.columns["base_height"] = cloud.from_local(np.c_[np.zeros((len(bz), 2)), bz])[:, 2]
    trees_t = trees_table(qs, crs)
    method = {t.tree_id: t.record.get("qsm_method", "") for t in trees if t.qsm is not None}
    trees_t.columns["qsm_method"] = np.array([method[int(i)] for i in trees_t.columns["tree_id"]], dtype=object)
    return cylinders, branches, trees_t
