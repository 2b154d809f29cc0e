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
minimal stem the reconstruction gives them and ``quality = "noise"``; trees with fewer than
:data:`~sylva.core.tops.MIN_TREE_POINTS` (20) points, which a segmentation keeps only where the scan is
sparse, at the apex of the tallest crown around or at a steep apex beyond its neighbours' crowns, get
``quality = "sparse"`` (their height, crown and model rest on few echoes).

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

import math
import zlib
from dataclasses import dataclass, field
from typing import Any, List

import numpy as np

from .cloud import PointCloud
from .errors import InputError
from .geometry import (DEFAULT_LOD, build_branch_set, continuations, forest_polylines, forest_wood, join_forest,
                       localise_parents, norm3, pipe_model_radii, simplify_forest, split_branch_set, tip_counts,
                       tree_branches, trusted_skeleton)
from .jit import njit
from .leaves import LeafCards, NeedleClusters, forest_tip_sections, grow_leaves, leaves_at_tips
from .measure import TreeMetrics, estimate_dbhs
from .progress import CancelCheck, Progress, check, report
from .qsm import measure_qsm, skeleton_qsms
from .reconstruct import Hybrid, TreePoints, is_dense_scan, reconstruct_tree
from .tops import MIN_TREE_POINTS

LEAVES = ("auto", "broadleaf", "needles", "none")


@dataclass(frozen=True)
class ModelOptions:
    method: Any = Hybrid()
    dense_method: Any = None      # used instead of `method` for trees is_dense_scan() calls dense
    lod: int = DEFAULT_LOD
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
    """(tree ids, point indices of all trees sorted by tree (stable), offsets of each tree's points)."""
    idx = np.flatnonzero(labels > 0)
    order = idx[np.argsort(labels[idx], kind="stable")]
    lab = labels[order]
    cuts = np.flatnonzero(np.diff(lab)) + 1
    ids = lab[np.concatenate([[0], cuts])] if len(lab) else np.zeros(0, int)
    return ids, order, np.r_[0, cuts, len(order)].astype(np.int64) if len(lab) else np.zeros(1, np.int64)


def tree_points(labels: np.ndarray):
    """(tree ids ascending, the point indices of each tree in file order) of per-point ``labels`` (0 = none)."""
    ids, order, off = _groups(np.asarray(labels))
    return ids, [order[a:b] for a, b in zip(off[:-1].tolist(), off[1:].tolist())]


def is_conical(xyz: np.ndarray, crown_base_z: float) -> bool:
    """A pointed crown: its upper quarter is much narrower than its widest part (conifers).

    The crown is the points at or above ``crown_base_z``; it is pointed when the 90th percentile of
    the horizontal distances to the crown's centre in its top quarter (by height) is under 0.45 times
    that of the whole crown (Sylva, not in the paper).  Needs 20 crown points and 3 in the top quarter.
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    return bool(_conical(xyz, np.array([0, len(xyz)], dtype=np.int64), np.array([crown_base_z], dtype=np.float64))[0])


def _conical(xyz: np.ndarray, off: np.ndarray, crown_base_z: np.ndarray) -> np.ndarray:
    """:func:`is_conical` of the trees whose points are ``xyz[off[t]:off[t + 1]]`` (crown bases ``crown_base_z``)."""
    p_top, p_all = _crown_spread_kernel(np.ascontiguousarray(xyz, dtype=np.float64), off, crown_base_z)
    return p_top < 0.45 * p_all               # NaN (too few points) is never conical


@njit
def _crown_spread_kernel(xyz, off, crown_base_z):
    """Per tree the 90th percentiles of the crown points' horizontal distances to the crown centre, of
    the top quarter and of all (NaN, NaN when there are under 20 crown points or 3 in the top quarter).

    Written as numpy computes them: the centre is the running sum of the crown points in their order
    divided by their number, distances are sqrt(dx² + dy²), ``rel = (z - z0) / max(z1 - z0, 1e-6)``
    and the percentiles numpy's linear interpolation of the order statistics (``b - (b - a)(1 - g)``
    when g >= 0.5, NaN if a value is NaN).
    """
    nt = off.shape[0] - 1
    out = np.full((2, nt), np.nan)
    for t in range(nt):
        a, b = off[t], off[t + 1]
        zc = crown_base_z[t]
        n = 0
        sx = 0.0
        sy = 0.0
        z0 = np.inf
        z1 = -np.inf
        for i in range(a, b):
            if xyz[i, 2] >= zc:
                n += 1
                sx += xyz[i, 0]
                sy += xyz[i, 1]
                z0 = min(z0, xyz[i, 2])
                z1 = max(z1, xyz[i, 2])
        if n < 20:
            continue
        cx = sx / n
        cy = sy / n
        span = z1 - z0
        if not span >= 1e-6 and span == span:    # Python's max(span, 1e-6); NaN stays NaN
            span = 1e-6
        r = np.empty(n)
        top = np.empty(n)
        k = 0
        n_top = 0
        for i in range(a, b):
            if xyz[i, 2] >= zc:
                dx = xyz[i, 0] - cx
                dy = xyz[i, 1] - cy
                r[k] = math.sqrt(dx * dx + dy * dy)
                if (xyz[i, 2] - z0) / span >= 0.75:
                    top[n_top] = r[k]
                    n_top += 1
                k += 1
        if n_top < 3:
            continue
        for j in range(2):
            v = top[:n_top] if j == 0 else r
            m = v.shape[0]
            nan = False
            for x in v:
                nan = nan or x != x
            vi = (m - 1) * 0.9
            lo = int(math.floor(vi))
            if nan:
                out[j, t] = np.nan
            elif vi >= m - 1:
                out[j, t] = v.max()
            else:           # the order statistics lo and lo + 1, interpolated
                v = np.partition(v, lo)
                x0 = v[lo]
                x1 = v[lo + 1:].min()
                g = vi - lo
                d = x1 - x0
                out[j, t] = x1 - d * (1 - g) if g >= 0.5 else x0 + d * g
    return out[0], out[1]


@njit
def _median_kernel(values, off):
    """``np.median`` of every slice ``values[off[t]:off[t + 1]]`` (NaN if it holds one; 0.0 + x as numpy)."""
    nt = off.shape[0] - 1
    out = np.empty(nt)
    for t in range(nt):
        v = values[off[t]:off[t + 1]]
        n = v.shape[0]
        nan = False
        for x in v:
            nan = nan or x != x
        if n == 0 or nan:
            out[t] = np.nan
            continue
        v = np.partition(v, (n - 1) // 2)        # (a copy) the middle value, or the lower of the two
        lo = v[(n - 1) // 2]
        if n % 2:
            out[t] = (0.0 + lo) / 1.0
        else:
            out[t] = ((0.0 + lo) + v[n // 2:].min()) / 2.0
    return out


def dbh_radii(skeleton, dbh_m: float, options: ModelOptions = ModelOptions()) -> np.ndarray:
    """Pipe-model radii (Hu et al. 2017 §5.5, Eq. 6) scaled so the stem has the diameter ``dbh_m``."""
    stem_r = max(dbh_m, 0.02) / 2  # a 1-point "tree" still gets a visible 2 cm stem
    return pipe_model_radii(skeleton, tip_radius_m=min(options.tip_radius_m, stem_r / 2), trunk_radius_m=stem_r)


def _forest_dbh_radii(parent: np.ndarray, off: np.ndarray, trees, dbhs, options: ModelOptions) -> np.ndarray:
    """:func:`dbh_radii` of the forest's ``trees`` (others 0): the pipe model of all of them in one pass."""
    nt = len(off) - 1
    tip = np.ones(nt)         # (the other trees' radii are not used)
    trunk = np.ones(nt)
    for t in trees:
        stem_r = max(dbhs[t], 0.02) / 2
        tip[t] = min(options.tip_radius_m, stem_r / 2)
        trunk[t] = stem_r
        if not (np.isfinite(tip[t]) and tip[t] > 0):
            raise InputError(f"skeleton: tip_radius_m must be > 0 m, got {tip[t]}")
        if not (np.isfinite(stem_r) and stem_r > 0):
            raise InputError(f"skeleton: trunk_radius_m must be > 0 m, got {stem_r}")
    tree = np.repeat(np.arange(nt), np.diff(off))
    radii = tip[tree] * tip_counts(parent) ** (1.0 / 2.0)      # pipe_model_radii, exponent 2
    radii *= (trunk / radii[off[:-1]])[tree]                    # the root is node 0 of every tree
    return radii


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


def _tree_sums(values: np.ndarray, bounds: list) -> list:
    """``values[a:b].sum()`` of every tree's slice (numpy's pairwise sums, so per tree the same bits)."""
    return [values[a:b].sum() for a, b in zip(bounds[:-1], bounds[1:])]


def model_trees(cloud: PointCloud, labels: np.ndarray, metrics: TreeMetrics,
                options: ModelOptions = ModelOptions(), progress: Progress = None,
                cancelled: CancelCheck = None) -> List[ModelledTree]:
    """Model every tree of ``labels`` (see the module docstring), in tree_id order.

    Reconstruction and DBH go tree by tree; the rest runs on the forest of all trees of the
    call joined into one skeleton (simplification, radii, branch chains, QSMs and records,
    wood meshes swept in batches of trees, leaves grown in one batch per leaf kind), which
    gives every tree exactly what the per-tree functions (:func:`~sylva.core.geometry.tree_mesh`,
    :func:`leaf_mesh`, :func:`~sylva.core.qsm.measure_qsm`, ...) give it.
    """
    local = cloud.local_xyz()
    height = np.asarray(cloud.attrs["height"], dtype=np.float64)
    row_of = {int(t): i for i, t in enumerate(metrics.tree_id)}
    ids, order, pt_off = _groups(np.asarray(labels))
    pts, h = local[order], height[order]            # the trees' points, tree by tree
    grounds = _median_kernel(pts[:, 2] - h, pt_off).tolist()
    bounds = pt_off.tolist()
    work = []
    dense_models = {}
    for k, tree_id in enumerate(ids.tolist()):
        check(cancelled)
        report(progress, 0.9 * k / max(len(ids), 1), f"tree {k + 1} of {len(ids)}")
        i = row_of[int(tree_id)]
        xyz = pts[bounds[k]:bounds[k + 1]].copy()      # the methods' own copy, as local[idx] was
        ground_z = grounds[k]
        method = options.method
        if options.dense_method is not None and is_dense_scan(xyz):
            method = options.dense_method
        tree_pts = TreePoints(int(tree_id), xyz, ground_z)
        dense_qsm = None
        if hasattr(method, "model") and len(xyz) > 0:
            # Yan et al. 2009: the full model (B-spline branches, §4) gives the cylinders
            dense = method.model(tree_pts)
            rec = dense.reconstruction
            if getattr(method, "fitted_wood", False):
                dense_models[k] = dense
            if len(dense.cylinders["id"]):
                dense_qsm = measure_qsm(dense.cylinders, dense.branch_parent, xyz, base_z=ground_z,
                                        tree_id=int(tree_id))
        else:
            rec = reconstruct_tree(tree_pts, method)
        work.append((int(tree_id), i, ground_z, rec, dense_qsm))
    rows = [w[1] for w in work]
    dbhs = estimate_dbhs(pts, h, pt_off, [float(metrics.height[i]) for i in rows],
                         [float(metrics.crown_diameter[i]) for i in rows])
    work = [w + d for w, d in zip(work, dbhs)]
    check(cancelled)
    report(progress, 0.9, "skeletons, chains and QSMs")
    out, forest = _model_forest(cloud, pts, pt_off, work, metrics, options, set(dense_models))
    report(progress, 0.95, "meshes and leaves")
    _mesh_and_leaf(out, forest, options, cancelled)
    for k, dense in dense_models.items():
        # the wood of a fitted dense model is its own tubes (radii and axes fitted to the points),
        # not the skeleton's generic sweep: what the GLB holds is what was fitted
        out[k].wood = _fitted_wood(dense, out[k].base_local, options.lod)
    report(progress, 1.0, "trees modelled")
    return out


def _fitted_wood(dense, base_local: np.ndarray, lod: int):
    """The tubes of a fitted dense model (:func:`sylva.core.reconstruct.wood_mesh.tube_mesh`) as a trimesh,
    origin at the tree's base; ``lod`` 0 / 1 / 2 sweeps the thickest branches with at most 8 / 10 / 14 sides,
    thinner ones with the fewest sides whose chord error is at most 8 / 4 / 2 mm (at LOD 0 at least the
    model's ``mesh_chord_m``, a share of the scan's point spacing), the polygon's mean distance to the axis
    matched to the fitted radius (so within about half that of the circle); twigs under 8 mm radius start
    at a point inside their parent."""
    import trimesh

    from .reconstruct.wood_mesh import tube_mesh

    sides = {0: 8, 1: 10}.get(int(lod), 14)
    curves, radii = ((dense.curves, dense.curve_radii) if dense.mesh_curves is None
                     else (dense.mesh_curves, dense.mesh_radii))
    tolerance = {0: 0.008, 1: 0.004}.get(int(lod), 0.002)
    if int(lod) == 0:
        tolerance = max(tolerance, float(dense.mesh_chord_m))
    v, f = tube_mesh(curves, radii, sides=sides, tolerance_m=tolerance,
                     match=True, pointed_m=0.008)
    return trimesh.Trimesh(v - base_local, f, process=False)


def _model_forest(cloud, pts, pt_off, work, metrics, options: ModelOptions, fitted=frozenset()):
    """Skeletons, radii, chains, QSMs and records of the trees of :func:`model_trees` on their joined forest.

    ``pts`` the trees' points (tile-local, tree by tree: ``pt_off``), ``work`` per tree (tree_id, metrics
    row, ground z, reconstruction, dense QSM or None, DBH, DBH source).  Returns the ModelledTrees
    (``wood`` / ``leaves`` not set yet) and what :func:`_mesh_and_leaf` needs: (nodes relative to each
    tree's root, radii, node offsets, branch sets of the wood mesh and of the leaves).
    """
    if not work:
        return [], None
    raw = [w[3].skeleton for w in work]
    nodes, parent, off = join_forest(raw)
    radius = np.concatenate([sk.radius for sk in raw])
    added = np.concatenate([sk.is_added for sk in raw])
    if options.simplify_m > 0:
        nodes, parent, radius, added, off = simplify_forest(nodes, parent, radius, added, off, options.simplify_m)
    radii, dbhs = _forest_radii(parent, radius, off, work, options)
    shifted = nodes - np.repeat(nodes[off[:-1]], np.diff(off), axis=0)   # relative to each root (node 0)
    # the three branch decompositions (geometry.branches): of the skeleton with radii (records, QSM,
    # skeleton table), of the shifted skeleton with radii (wood mesh) and without radii (leaves)
    bs_a = build_branch_set(parent, continuations(nodes, parent, radii))
    bs_b = build_branch_set(parent, continuations(shifted, parent, radii))
    bs_c = build_branch_set(parent, continuations(shifted, parent, None))
    boff = tree_branches(bs_a, off)
    bounds = pt_off.tolist()
    top_z = [pts[a:b, 2].max() for a, b in zip(bounds[:-1], bounds[1:])]
    qsms = skeleton_qsms(nodes, parent, radii, bs_a, off, boff, [w[0] for w in work], [w[2] for w in work],
                         top_z, [d for d, _ in dbhs], [s for _, s in dbhs])
    lengths, volumes = _forest_measures(nodes, parent, radii, bs_a, off, boff)
    kinds = [options.leaves] * len(work)
    if options.leaves == "auto":
        conical = _conical(pts, pt_off, np.array([w[2] + metrics.crown_base_height[w[1]] for w in work]))
        kinds = ["needles" if c else "broadleaf" for c in conical.tolist()]
        # a wood model fitted to a dense scan gets no leaf cards unless they are asked for
        kinds = ["none" if t in fitted else kd for t, kd in enumerate(kinds)]
    local_parent = localise_parents(parent, off)
    bases = cloud.from_local(nodes[off[:-1]]).tolist()
    nb = off.tolist()
    out = []
    for t, (w, (dbh, source), qsm, bset) in enumerate(zip(work, dbhs, qsms, split_branch_set(bs_a, off, boff))):
        a, b = nb[t], nb[t + 1]
        qsm_method = "skeleton_edges"
        if w[4] is not None:
            qsm, qsm_method = w[4], ("fitted_cylinders" if t in fitted else "bspline_cylinders")
            qsm.dbh_m, qsm.dbh_source = float(dbh), source
        record = _record(w, dbh, source, bases[t], len(bset) - 1, lengths[t], volumes[t], kinds[t], qsm, qsm_method,
                         bounds[t + 1] - bounds[t], options.min_points)
        out.append(ModelledTree(w[0], nodes[a].copy(), trusted_skeleton(nodes[a:b], local_parent[a:b], radii[a:b],
                                                                        added[a:b]), None, None, record, qsm, bset))
    return out, (shifted, radii, off, bs_b, bs_c)


def _forest_radii(parent: np.ndarray, radius: np.ndarray, off: np.ndarray, work, options: ModelOptions):
    """Per node the radii of :func:`model_trees` and per tree its (DBH, source).

    A tree whose skeleton has radii keeps them (dense-scan methods measure them from fitted cylinders,
    Yan et al. §4) and, unless its DBH was measured on the points, takes the DBH of its stem cylinder;
    the others get the pipe model scaled to their DBH (:func:`dbh_radii`).
    """
    bounds = off.tolist()
    r_max = [radius[a:b].max() for a, b in zip(bounds[:-1], bounds[1:])]   # (raises on an empty skeleton)
    pipe, dbhs = [], []
    for t, ((_, _, _, _, dense_qsm, dbh, source), rm) in enumerate(zip(work, r_max)):
        if rm > 0:
            if dense_qsm is not None and dense_qsm.dbh_source == "measured":
                dbh, source = dense_qsm.dbh_m, "measured"    # circle fit around the stem cylinder at 1.3 m
            elif source != "measured":
                if dense_qsm is not None and np.isfinite(dense_qsm.dbh_m):
                    dbh, source = dense_qsm.dbh_m, "cylinder"
                else:
                    dbh, source = 2.0 * float(radius[bounds[t]]), "cylinder"
        else:
            pipe.append(t)
        dbhs.append((dbh, source))
    radii = radius
    if pipe:
        is_pipe = np.zeros(len(work), dtype=bool)
        is_pipe[pipe] = True
        radii = np.where(np.repeat(is_pipe, np.diff(off)), _forest_dbh_radii(parent, off, pipe, [d for d, _ in dbhs],
                                                                            options), radius)
    if not np.all(np.isfinite(radii)) or (radii < 0).any():
        raise InputError("skeleton: radii must be finite and >= 0 m")
    return radii, dbhs


def _forest_measures(nodes, parent, radii, bs, off, branch_off):
    """Per tree :func:`~sylva.core.geometry.total_branch_length` and :func:`~sylva.core.geometry.wood_volume`
    of its skeleton with radii and branch set ``bs`` (a forest's), as those functions compute them."""
    nt = len(off) - 1
    child = np.flatnonzero(parent >= 0)
    par = parent[child]
    seg = norm3(nodes[child] - nodes[par])
    r2 = radii[child]
    r1 = np.where(bs.continuation[par] == child, radii[par], r2)
    frusta = np.pi * seg * (r1 * r1 + r1 * r2 + r2 * r2) / 3.0
    seg_bounds = (off - np.arange(nt + 1)).tolist()                  # one segment per non-root node
    seg_of = np.zeros(len(parent))
    seg_of[child] = seg
    stem_len, stem_bounds = _trunk_values(seg_of, bs, branch_off)
    total, volume = _tree_sums(seg, seg_bounds), _tree_sums(frusta, seg_bounds)
    stem = _tree_sums(stem_len, stem_bounds)
    two = (np.diff(off) >= 2).tolist()
    return ([float(total[t] - stem[t]) if two[t] else 0.0 for t in range(nt)],
            [float(volume[t]) if two[t] else 0.0 for t in range(nt)])


def _record(w, dbh, source, base, n_branches, length, volume, kind, qsm, qsm_method, n_points, min_points) -> dict:
    """The record (trees table row) of one tree of :func:`model_trees` (``n_points``: its points)."""
    tree_id, rec = w[0], w[3]
    quality = ("noise" if n_points < min_points else "sparse" if n_points < MIN_TREE_POINTS
               else "fallback" if "fallback" in rec.flags else "ok")
    return {
        "tree_id": int(tree_id),
        "base_x": float(base[0]), "base_y": float(base[1]), "base_z": float(base[2]),
        "dbh": float(dbh), "dbh_source": source,
        "n_branches": int(n_branches),
        "total_branch_length": length,
        "wood_volume": volume,
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


def _trunk_values(values: np.ndarray, bs, branch_off: np.ndarray):
    """``values`` of the trunk nodes of every tree but its root (chain order) and their per-tree bounds."""
    trunks = branch_off[:-1]
    first = bs.offsets[trunks] + 1
    n = np.diff(bs.offsets)[trunks] - 1
    bounds = np.r_[0, np.cumsum(n)]
    pos = np.repeat(first - bounds[:-1], n) + np.arange(bounds[-1])
    return values[bs.nodes[pos]], bounds.tolist()


def _mesh_and_leaf(out: List[ModelledTree], forest, options: ModelOptions, cancelled: CancelCheck) -> None:
    """Wood meshes (Hu et al. 2017 §5.5) and leaves (§5.6) of :func:`model_trees`' trees, in batches of
    about ``_BATCH_NODES`` skeleton nodes.

    ``forest`` = (nodes relative to each tree's root, radii, node offsets, branch sets of the mesh
    and of the leaves) from :func:`_model_forest`.  The centre lines and tip sections are cut for all
    trees at once; the tubes of a batch are swept together, its leaves grown in one call per kind.
    """
    if not out:
        return
    shifted, radii, off, bs_mesh, bs_leaf = forest
    lod = options.lod
    lines = forest_polylines(shifted, radii, bs_mesh, tree_branches(bs_mesh, off), lod)
    leaf_boff = tree_branches(bs_leaf, off)
    kinds = [t.record["leaves"] for t in out]
    seeds = [zlib.crc32(f"leaves-{t.tree_id}".encode()) for t in out]
    sections = {}
    # batches of trees of about _BATCH_NODES skeleton nodes: the temporaries stay small on large tiles
    sizes = np.diff(off)
    cuts = np.r_[0, np.flatnonzero(np.diff(np.cumsum(sizes) // _BATCH_NODES)) + 1, len(out)]
    for a, b in zip(cuts[:-1].tolist(), cuts[1:].tolist()):
        check(cancelled)
        for t, wood in zip(out[a:b], forest_wood(lines, a, b, lod)):
            t.wood = wood
        for kind in sorted(set(kinds[a:b])):
            method = _leaf_method(kind, options)
            if method is None:
                continue
            ksegs = int(method.tip_segments)
            if ksegs not in sections:
                sections[ksegs] = forest_tip_sections(bs_leaf, leaf_boff, ksegs)
            sect, tip_tree = sections[ksegs]
            which = np.array([k for k in range(a, b) if kinds[k] == kind], dtype=np.int64)
            chosen = np.zeros(len(out), dtype=bool)
            chosen[which] = True
            pick = chosen[tip_tree]
            grown = leaves_at_tips(shifted, radii, sect[pick], np.searchsorted(which, tip_tree[pick]),
                                   off[which], method, [seeds[k] for k in which])
            for k, leaves in zip(which.tolist(), grown):
                out[k].leaves = leaves


def skeleton_table(trees: List[ModelledTree], cloud: PointCloud, crs=None):
    """One MultiLineStringZM per tree: each part a branch chain, M = radius (m), CRS coordinates.

    The chains are those of :func:`~sylva.core.geometry.branches` (``ModelledTree.branches`` when
    set); the chains of all trees are converted to CRS units in one call and encoded in one
    vectorised pass (:func:`~sylva.core.table.multilinestring_zm_wkbs`).
    """
    from .geometry import branches
    from .table import VectorTable, multilinestring_zm_wkbs

    bsets = [t.branches if t.branches is not None else branches(t.skeleton, t.skeleton.radius) for t in trees]
    ids = [t.tree_id for t in trees]
    n_chains = np.zeros(len(trees), dtype=np.int64)
    if trees:
        # all trees' chains at once: node indices into the joined skeletons, chain lengths per tree
        node_off = np.r_[0, np.cumsum([len(t.skeleton) for t in trees])]
        nodes = np.concatenate([bs.nodes for bs in bsets]) + np.repeat(node_off[:-1], [len(bs.nodes) for bs in bsets])
        offsets = np.concatenate([bs.offsets for bs in bsets])
        last = np.cumsum([len(bs.offsets) for bs in bsets]) - 1          # each tree's closing offset
        lens = np.delete(np.diff(offsets), last[:-1])
        real = lens >= 2
        chain_tree = np.repeat(np.arange(len(trees)), [len(bs) for bs in bsets])
        n_chains = np.bincount(chain_tree[real], minlength=len(trees)).astype(np.int64)
        nodes = nodes[np.repeat(real, lens)]
        local = np.concatenate([t.skeleton.nodes for t in trees])[nodes]
        radius = np.concatenate([t.skeleton.radius for t in trees])[nodes]
        part_len = lens[real]
        coords = np.column_stack([cloud.from_local(local.reshape(-1, 3)), radius])
        wkb = multilinestring_zm_wkbs(coords, part_len.astype(np.int64), n_chains)
    else:
        wkb = []
    return VectorTable("skeletons", "line", np.array(wkb, dtype=object),
                       {"tree_id": np.array(ids, dtype=np.int64), "n_chains": n_chains},
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
