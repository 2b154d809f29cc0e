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
from .geometry import (_branch_set, _continuation_cos_arrays, _continuation_from_cos, _forest, _radii_or_default,
                       _split_branch_set, branch_count, pipe_model_radii, simplify_skeletons,
                       total_branch_length, tree_meshes, with_radii, wood_volume)
from .leaves import LeafCards, NeedleClusters, grow_leaves, grow_leaves_batch
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
    branches: Any = None          # geometry.BranchSet of ``skeleton`` with its radii (reused by skeleton_table)


#: Trees are meshed and leaved in batches of about this many skeleton nodes (a few MB of temporaries).
_BATCH_NODES = 50_000

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


def leaf_mesh(skeleton, kind: str, options: ModelOptions = ModelOptions(), seed: int = 0, branch_set=None):
    """Needle clusters or leaf cards (``kind`` "needles" / "broadleaf"; else None) on a skeleton with radii.

    Coarse levels of detail get fewer, larger cards: the crown's look at a fraction of the faces.
    ``branch_set``: ``branches(skeleton)`` (no radii) when the caller has it already.
    """
    method = _leaf_method(kind, options)
    return None if method is None else grow_leaves(skeleton, method, seed=seed, branch_set=branch_set)


def _leaf_method(kind: str, options: ModelOptions):
    """The NeedleClusters / LeafCards of :func:`leaf_mesh` for ``kind`` (None for no leaves)."""
    scale = {0: 3.0, 1: 1.5}.get(options.lod, 1.0)
    if kind == "needles":
        return NeedleClusters(clusters_per_tip=max(2, int(8 / scale)), cluster_length_m=0.3 * scale)
    if kind == "broadleaf":
        return LeafCards(shape=options.leaf_shape, leaves_per_tip=max(2, int(12 / scale ** 2)),
                         leaf_length_m=0.1 * scale)
    return None


def _branch_sets(skeletons, shifted, radii) -> list:
    """Per tree the three branch decompositions its outputs use (see :func:`geometry.branches`), for all trees
    in one vectorised pass over the forest of their skeletons.

    ``(of the skeleton with radii, of the shifted skeleton with the mesh radii, of the shifted skeleton
    without radii)`` for the records / QSM / skeleton table, the wood mesh and the leaves.  They differ only
    where the shift rounds a bend cosine differently or a tie is broken by radius instead of index, so a
    tree reuses the previous one when its continuation children are equal.
    """
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
    """Model every tree of ``labels`` (see the module docstring), in tree_id order.

    Reconstruction and DBH go tree by tree; the rest runs batched over all trees of the
    call (skeleton simplification, branch chains, wood meshes swept in one batch by
    :func:`~sylva.core.geometry.tree_meshes`, leaves grown in one batch per leaf kind by
    :func:`~sylva.core.leaves.grow_leaves_batch`), which gives every tree exactly what the
    per-tree functions (:func:`~sylva.core.geometry.tree_mesh`, :func:`leaf_mesh`, ...) give it.
    """
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


def skeleton_table(trees: List[ModelledTree], cloud: PointCloud, crs=None):
    """One MultiLineStringZM per tree: each part a branch chain, M = radius (m), CRS coordinates.

    The chains are those of :func:`~sylva.core.geometry.branches` (``ModelledTree.branches`` when
    set); the chains of all trees are converted to CRS units in one call and encoded in one
    vectorised pass (the same bytes as :func:`~sylva.core.table.multilinestring_zm_wkb`).
    """
    from .geometry import branches
    from .table import VectorTable

    ids, n_chains, radius, part_len = [], [], [], []
    local = []
    for t in trees:
        sk = t.skeleton
        bset = t.branches if t.branches is not None else branches(sk, sk.radius)
        off = bset.offsets
        lens = np.diff(off)
        real = np.flatnonzero(lens >= 2)
        if len(real) == len(lens):
            nodes = bset.nodes
        else:
            keep = np.repeat(lens >= 2, lens)
            nodes = bset.nodes[keep]
        local.append(sk.nodes[nodes])
        radius.append(sk.radius[nodes])
        part_len.append(lens[real])
        ids.append(t.tree_id)
        n_chains.append(len(real))
    n_chains = np.array(n_chains, dtype=np.int64)
    if trees:
        coords = np.column_stack([cloud.from_local(np.concatenate(local).reshape(-1, 3)), np.concatenate(radius)])
        wkb = _multilinestring_zm_wkbs(coords, np.concatenate(part_len).astype(np.int64), n_chains)
    else:
        wkb = []
    return VectorTable("skeletons", "line", np.array(wkb, dtype=object),
                       {"tree_id": np.array(ids, dtype=np.int64), "n_chains": n_chains},
                       crs if crs is not None else cloud.crs, has_m=True)


_WKB_HEADER = np.dtype([("order", "u1"), ("type", "<u4"), ("count", "<u4")])  # packed: 9 bytes


def _multilinestring_zm_wkbs(coords: np.ndarray, part_len: np.ndarray, n_parts: np.ndarray) -> list:
    """ISO WKB MultiLineString ZM per feature (little endian, types 3005 / 3002), vectorised.

    ``coords`` (n, 4) x, y, z, m of all parts of all features in order; ``part_len`` (p,) points
    per part; ``n_parts`` (f,) parts per feature.  Byte for byte what
    :func:`sylva.core.table.multilinestring_zm_wkb` gives per feature.
    """
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
