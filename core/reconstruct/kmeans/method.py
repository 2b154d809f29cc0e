"""The variational k-means method and its dense-scan rule: Yan et al. 2009 §2-§4.

:class:`VariationalKMeans` runs §2 (:mod:`.segmentation`), §3 (:mod:`.branches`) and §4 (:mod:`.bspline`),
with Sylva's refits (:mod:`.refit`), on one tree; :func:`is_dense_scan` (Sylva, not in the papers) is the
rule that sends a tree to it instead of the airborne methods.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ...errors import InputError, SylvaError
from ...progress import CancelCheck, Progress, check, report
from ..model import Reconstruction, TreePoints, screen
from .branches import branch_structure
from .bspline import DenseModel, model_branches, prune_branches
from .refit import (inside_parent_radii, keep_branches, outside_earlier_branches, radii_from_cylinders, recentre,
                    skeleton_from)
from .segmentation import segment


# --------------------------------------------------------------------------- dense rule

#: Median distance (m) from a point to its 8th nearest neighbour at or under
#: which a tree counts as densely sampled.  Airborne scans of 20 / 100 / 400
#: pulses/m² (testing.synth) put it at 0.57–0.81 / 0.27–0.41 / 0.14–0.23 m; the
#: TLS trees of ../shared/data/tls at 0.03–0.19 m.
DENSE_SPACING_M = 0.25
#: Share of the points within ``DENSE_LOW_M`` above the tree's lowest point at
#: or above which the lower stem is seen, as from the ground.  Airborne trees
#: of testing.synth (20–400 pulses/m²): at most 2.2 %; the TLS trees: 3.6–25 %.
DENSE_LOW_SHARE = 0.03
DENSE_LOW_M = 2.0
#: A dense scan also needs this many points (too few points carry no branches).
DENSE_MIN_POINTS = 2000
#: Median distance (m) to the k-th (8th) neighbour above which a dense-scan model is
#: flagged ``sparse_scan``: branches thinner than that spacing get guessed radii, and
#: volumes are not to be trusted (TLS tree13 of ../shared/data/tls: 0.19 m; trees 1
#: and 7: 0.06 / 0.03 m).
SPARSE_SPACING_M = 0.1


def is_dense_scan(xyz: np.ndarray, spacing_m: float = DENSE_SPACING_M, low_share: float = DENSE_LOW_SHARE,
                  min_points: int = DENSE_MIN_POINTS) -> bool:
    """True when a tree's points are dense enough for Yan et al.'s branch reconstruction.

    Rule (all three): at least ``min_points`` points; the median distance
    to the 8th nearest neighbour (k = 8 as Yan §2.1) at most ``spacing_m``
    (0.25 m), so the kNN graph follows branches instead of jumping between
    them; and at least ``low_share`` (3 %) of the points within 2 m above
    the lowest point, i.e. the stem and low branches are visible, as in
    terrestrial, mobile or below-canopy scans, rather than a crown surface
    seen from above (airborne scans, even at 400 pulses/m², put < 2.5 %
    there).
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    if len(xyz) < max(min_points, 9):
        return False
    z = xyz[:, 2] - xyz[:, 2].min()
    if float((z < DENSE_LOW_M).mean()) < low_share:
        return False
    sub = xyz
    if len(xyz) > 50_000:  # the median is stable on a sample; keep it deterministic
        sub = xyz[np.random.default_rng(0).choice(len(xyz), 50_000, replace=False)]
    d, _ = cKDTree(xyz).query(sub, k=9, workers=-1)
    return bool(np.median(d[:, 8]) <= spacing_m)


# --------------------------------------------------------------------------- method

@dataclass(frozen=True)
class VariationalKMeans:
    """Yan et al. 2009 on one dense tree: §2 segmentation, §3 branches, §4 B-spline model.

    ``k`` neighbours (§2.1, 8); ``n_seeds`` initial clusters (§2.2 user input;
    0 = one per 250 points, at least 20);
    ``delta_m`` RMS tightness δ of a fixed cluster's bounding cylinder in
    metres (§2.3; the paper's 1e-3..1e-2 of the unit cube); ``max_clusters``
    cluster budget and ``min_cluster_points`` smallest cluster still split
    (§2.4); ``max_iter`` / ``epsilon_rel`` Lloyd stop (§5: 30 iterations,
    ε = 1e-5, here relative to the energy); ``samples`` B-spline samples per
    branch (§5: 30); ``sides`` of the lofted polygon (§4.2: n2 = 10);
    ``min_points`` fewer points give a flagged minimal skeleton;
    ``prune_factor`` drops branches that do not reach farther than this
    many parent radii from the parent's centre line (:func:`prune_branches`,
    not in the paper; 0 keeps all); ``metric`` of region growing on the kNN
    graph (``"hops"`` breadth-first, ``"metres"`` Dijkstra); ``axis``
    ``"pca"`` (§2.3) or ``"normals"`` (surface normals, for thick stems);
    ``radius`` ``"bounding"`` (§2.3 enclosing circle, biased up by noise)
    or ``"fit"`` (least-squares circle, also used for the δ test, and
    skeleton vertices of fixed clusters on their axes, see
    :func:`branch_structure`); ``refit`` replaces the radii of the final
    cylinders by circle fits to the points nearest each
    (:func:`sylva.core.qsm.refit_radii`, not in the paper); ``seed`` of the
    random initial seeds.
    """

    k: int = 8
    n_seeds: int = 0
    delta_m: float = 0.03
    max_clusters: int = 2000
    min_cluster_points: int = 150
    max_iter: int = 30
    epsilon_rel: float = 1e-5
    samples: int = 30
    sides: int = 10
    min_points: int = 50
    prune_factor: float = 1.5
    metric: str = "hops"
    axis: str = "pca"
    radius: str = "bounding"
    refit: bool = False
    seed: int = 0

    name = "variational_kmeans"

    @classmethod
    def dense_scan(cls) -> "VariationalKMeans":
        """The preset measured best on thick, densely scanned stems (``benchmarks/dense.py``): cluster axes
        from surface normals, least-squares circle radii, clusters split down to 30 points, radii and axes
        refitted to the points (Sylva, not in the paper; the paper's own settings are the defaults)."""
        return cls(axis="normals", radius="fit", refit=True, min_cluster_points=30)

    def __post_init__(self):
        if self.k < 2 or self.n_seeds < 0 or self.max_clusters < 1 or self.max_iter < 1:
            raise InputError("VariationalKMeans: k >= 2, n_seeds >= 0, max_clusters >= 1 and max_iter >= 1")
        if not self.delta_m > 0:
            raise InputError(f"VariationalKMeans: delta_m must be > 0 metres, got {self.delta_m!r}")
        if self.samples < 2 or self.sides < 3:
            raise InputError("VariationalKMeans: samples >= 2 and sides >= 3")
        for name, val, allowed in (("metric", self.metric, ("hops", "metres")), ("axis", self.axis, ("pca", "normals")),
                                   ("radius", self.radius, ("bounding", "fit"))):
            if val not in allowed:
                raise InputError(f"VariationalKMeans: {name} must be one of {allowed}, got {val!r}")


    def model(self, tree: TreePoints, progress: Progress = None,
              cancelled: CancelCheck = None) -> DenseModel:
        """Run Yan §2–§4 on one tree; the full :class:`DenseModel`."""
        from ...qsm import cylinders_from_curves, refit_radii, taper_radii
        t_all = time.perf_counter()
        xyz = tree.xyz
        ground_z, flags, rec = screen(tree, self.min_points, self.name, progress)
        stats = {"n_points": int(len(xyz))}
        if rec is not None:
            skel = rec.skeleton
            curves = [skel.nodes] if len(skel) > 1 else []
            radii = [np.zeros(len(skel))] if len(skel) > 1 else []
            return DenseModel(rec, None, None, curves, radii, np.array([-1][:len(curves)]),
                              np.array([0][:len(curves)]), cylinders_from_curves(curves, radii,
                                                                                 np.array([-1][:len(curves)])))
        check(cancelled)
        t0 = time.perf_counter()
        seg = segment(xyz, self.k, self.n_seeds, self.delta_m, self.max_clusters, self.min_cluster_points,
                      self.max_iter, self.epsilon_rel, seed=self.seed, metric=self.metric, axis=self.axis,
                      tightness="fit" if self.radius == "fit" else "bounding",
                      cancelled=cancelled,
                      progress=None if progress is None else (lambda f, m="": report(progress, 0.8 * f, m)))
        stats.update(t_segmentation_s=time.perf_counter() - t0, n_clusters=seg.n_clusters,
                     n_fixed=int(seg.fixed.sum()), rounds=seg.rounds, stop_reason=seg.reason,
                     n_unlabelled=int((seg.labels < 0).sum()))
        check(cancelled)
        t0 = time.perf_counter()
        try:
            st = branch_structure(xyz, seg, on_axis=self.radius == "fit")
            n_raw = len(st.branches)
            if self.prune_factor > 0:
                st = prune_branches(seg, st, self.prune_factor, self.radius)
            stats["n_pruned_branches"] = n_raw - len(st.branches)
        except (ValueError, IndexError) as exc:
            raise SylvaError(f"tree {tree.tree_id}: branch reconstruction failed ({exc})") from None
        stats.update(t_branching_s=time.perf_counter() - t0, n_branches=len(st.branches),
                     n_adjacency_edges=st.n_edges, n_bridged=st.bridged)
        report(progress, 0.9, "branches")
        check(cancelled)
        t0 = time.perf_counter()
        curves, radii, verts, vrad = model_branches(seg, st, self.samples, self.radius)
        cyl = cylinders_from_curves(curves, radii, st.branch_parent)
        if self.refit:
            cyl, refit, shift = refit_radii(xyz, cyl, return_shift=True)
            curves, cyl = recentre(curves, cyl, shift, np.any(shift != 0, axis=1), st.branch_parent)
            cyl, refit = refit_radii(xyz, cyl)
            cyl = taper_radii(inside_parent_radii(cyl, st.branch_parent))
            stats["n_refit_cylinders"] = int(refit.sum())
            radii, vrad = radii_from_cylinders(cyl, curves, radii, verts, vrad)
        if self.prune_factor > 0 and len(curves) > 1:
            keep = outside_earlier_branches(curves, radii, st.branch_parent, self.prune_factor)
            stats["n_pruned_branches"] = stats.get("n_pruned_branches", 0) + int((~keep).sum())
            if not keep.all():
                st, cyl = keep_branches(st, cyl, keep)
                curves = [c for c, k in zip(curves, keep) if k]
                radii = [r for r, k in zip(radii, keep) if k]
                verts = [v for v, k in zip(verts, keep) if k]
                vrad = [r for r, k in zip(vrad, keep) if k]
                stats["n_branches"] = len(st.branches)
                if self.refit:   # the points of the dropped branches go to the kept cylinders
                    cyl, refit = refit_radii(xyz, cyl)
                    cyl = taper_radii(inside_parent_radii(cyl, st.branch_parent))
                    stats["n_refit_cylinders"] = int(refit.sum())
                    radii, vrad = radii_from_cylinders(cyl, curves, radii, verts, vrad)
        skel = skeleton_from(st, verts, vrad)
        stats["t_modelling_s"] = time.perf_counter() - t0
        stats["n_nodes"] = int(len(skel))
        if st.bridged:
            flags.append("graph_disconnected")
        if seg.reason == "budget":
            flags.append("cluster_budget_reached")
        spacing = float(np.median(np.linalg.norm(xyz[seg.nbr[:, -1]] - xyz, axis=1))) if len(seg.nbr) else 0.0
        stats["spacing_k_m"] = spacing
        if spacing > SPARSE_SPACING_M:
            # branches thinner than the point spacing: their radii are guesses
            flags.append("sparse_scan")
        if seg.n_clusters and seg.fixed.mean() < 0.25:
            # most clusters are not cylinders within delta (sparse or very noisy
            # points): their radii are loose and volumes are not to be trusted
            flags.append("few_fixed_clusters")
        labelled = float((seg.labels >= 0).mean())
        stats["t_total_s"] = time.perf_counter() - t_all
        report(progress, 1.0, "model")
        rec = Reconstruction(skel, self.name, labelled, st.bridged == 0, stats, flags, tree.tree_id)
        return DenseModel(rec, seg, st, curves, radii, st.branch_parent, st.branch_order, cyl)

    def reconstruct(self, tree: TreePoints, progress: Progress = None,
                    cancelled: CancelCheck = None) -> Reconstruction:
        """Run Yan §2–§4 on one tree; see :func:`sylva.core.reconstruct.reconstruct_tree`."""
        return self.model(tree, progress, cancelled).reconstruction
