"""Normalised-cut tree segmentation on a voxel graph (Hu et al. 2017, §4.1).

Hu, Li, Zhang, Xie, Wang, Guo, Xiao, Su (2017), "Efficient tree modeling from
airborne LiDAR point clouds", Computers & Graphics 67, §4.1 and §6.1.

Steps
-----
1. **Voxels.** Points at least ``min_height_m`` above ground are binned into
   cubes of pitch ``voxel_m`` (the paper's d_s; 0.7 m for 36 k points, 0.9 m
   for 3.7 M points, §6.1) in the local metric frame, z = height above ground
   (so huge UTM coordinates and sloping terrain do not matter).  A voxel's
   features are the mean local (x, y, height), the mean intensity and the
   mean RGB colour when the cloud has them.
2. **Graph (Eq. 2).** The paper writes ``w_ij = e^{-H} e^{-V} e^{-I} e^{-C}``
   without scales; we use

       w_ij = exp(-H/σ_h) · exp(-V/σ_v) · exp(-I/σ_i) · exp(-C/σ_c)

   with H, V the horizontal and vertical distances of the voxel means
   (metres), I the absolute difference of the voxels' mean natural-log
   intensities (a ratio of intensities: free of the sensor's units and of any
   statistic of the tile, so tiling does not change the weights; the
   inter-quartile range of ln I is about 1 on lidR's MixedConifer and on the
   synthetic stands), and C the Euclidean distance of mean colours scaled to
   [0, 1].  The exponent stays linear in the distance
   as Eq. 2 writes it (not squared as in Shi & Malik's Gaussian kernel); the
   σ's carry the units the paper leaves implicit (``sigma_h_m``,
   ``sigma_v_m``, ``sigma_intensity``, ``sigma_colour``).  w_ij = 0 beyond
   r^xz = ``radius_m``; to keep the graph sparse the cylinder of Eq. 2 is
   cut to the inscribed ellipsoid of half height ``height_m``
   (``cKDTree.query_pairs`` on z-scaled coordinates); steep conifer apices
   stay connected, far-apart layers are not joined.  No dense
   matrix is ever built.
3. **Tops and start.** Unless given, tree tops are the local maxima of
   :func:`sylva.core.tops.find_tree_tops` (fixed window ``top_window_m``,
   small on purpose: surplus tops are merged in step 4) searched among the
   highest point of each ``TOP_CELL_M`` column only (every top is such a
   point; a canopy-surface thinning that makes the search several times
   faster).  Two Sylva additions (not in Hu et al.), measured with
   ``benchmarks/segmentation.py``: at low point density the window is
   widened until it holds ``top_window_points`` canopy points (first returns
   per m² of canopy, so a local maximum is not a sampling accident: 2.7 m on
   lidR's MixedConifer at 4.3 points/m²), and the steep-apex rule
   (:class:`sylva.core.tops.SteepApex`: ``apex_window_m``, ``apex_slope``,
   ``apex_sectors``) adds the tips of narrow conifers that a taller
   neighbour overtops within the window, the main loss of recall in dense
   stands.  Every voxel gets the tree top nearest to it along the graph
   (multi-source Dijkstra); a step costs the Eq. 2 dissimilarity -log w_ij
   plus ``climb`` x the height it gains, so a region runs down its own crown
   and stops at the crease where the neighbouring crown rises again.  Voxels
   of components without a top are not reached (isolated noise).
4. **Cuts (Eq. 1).** The problem is split into independent two-tree
   sub-problems.  The NCut of the start boundary of every pair of touching
   regions is computed at once (edge sums); pairs whose start boundary
   already costs less than ``SETTLED_NCUT`` are clearly separate crowns and
   are left as they are.  For the others, the generalised eigenproblem
   (D − W) x = λ D x of their union (normalised Laplacian, LOBPCG from the
   current boundary, ``scipy.linalg.eigh`` for tiny problems) gives the
   Fiedler vector, and Shi & Malik's threshold search finds the split with
   the smallest NCut(A, B) that keeps each top on its own side.  The new
   boundary replaces the old one only if its NCut is lower.  The best cut of
   a pair (the lower of the Fiedler split and the start boundary) says
   whether the two regions are one tree with two local maxima: the lower top
   is merged into the higher one (which keeps its id) when it costs more than
   ``always_merge_ncut``, or more than ``merge_ncut`` while the crowns dip
   between the two tops by less than ``merge_dip`` x the lower top's height
   (the dip is measured to the saddle, the highest voxel edge across their
   boundary).  Hu §4.1 lets the cut, not a root point per tree, decide the
   number of trees; the NCut value alone does not separate a surplus top on
   one crown (its cut is expensive, but so is the cut between two trees of
   a dense, interlocking canopy), the saddle depth does (a Sylva addition,
   not in Hu et al.): measured on the
   synthetic stands, the dip of a surplus top is 0.6–3.4 % of the lower top
   (10th–90th percentile), that of two trees 3–33 %.  A lower top that
   qualifies for merging with several neighbours joins only the one across
   the highest saddle (smallest dip), so a surplus top lying between two
   trees does not chain them into one.  Each sub-problem holds
   two crowns, so time and memory grow linearly with the tile.
   **Crown-reach merge** (issue 16; Sylva, not in Hu et al.): the cut
   cannot tell a leaf clump, a second leader or a flat crown's bump from a
   tree, as its crown is wide and the cut between its halves cheap.  A pair
   of touching regions (settled or not) is one tree when the lower top lies
   within ``merge_reach`` x the crown radius the higher top's height implies
   (half the crown width of Popescu & Wynne 2004, CW = 2.51503 + 0.00901 h²,
   :func:`crown_radius_m`) and rises less than ``merge_prominence`` x its
   height above their saddle (the prominence of the EBImage/lidR watershed's
   ``tol``, relative to height).  Measured on 2,530 pairs of the extended
   suite (``sylva/testing/crowns.py``) and testing/synth's dense conifers: pairs
   of one tree lie at 0.06-0.17 x the higher top's height (10th-90th
   percentile), pairs of two trees at 0.13-0.33; reach 0.7 and prominence 0.15
   merge 1,599 of 2,022 same-tree pairs and 123 of 508 two-tree pairs (the
   old rule alone: 1,359 and 103); a reach of 1.0 merges more on broadleaves
   but joins dense conifers (net gain there 55 -> 16 pairs).  Two tops of
   nearly one height (differing by less than ``merge_plateau`` x the higher)
   whose saddle dips less than half ``merge_prominence`` are the plateau of a
   flat-topped crown up to ``PLATEAU_REACH`` (1.3) x the crown radius: net
   gain 1,476 -> 1,634 pairs, dense conifers 55 -> 50.
5. **Clean-up and points.** Nothing of a tree lies above its top; voxels cut
   off from their top go to the neighbour they are most strongly joined to;
   crown pieces a sparse scan left unconnected join the nearest tree within
   ``attach_m``.  Points take their voxel's label; a point farther from its
   tree's top than ``crown_reach`` x that tree's allometric crown radius goes
   to a tree whose top is within reach (Dalponte & Coomes's maximum crown
   size, scaled by height; a stray carried across a neighbour's crown by the
   graph; MixedConifer crown IoU with lidR 0.489 -> 0.587); last, a tree of
   fewer than ``min_tree_points`` points (or, where the scan is sparse, the
   first returns of ``MIN_TREE_AREA_M2`` of canopy around its top) is merged
   into the tree within crown reach whose top is nearest, or is no tree
   (never reported as one); points below
   ``min_height_m`` take the label of the crown right above them (stems),
   see :mod:`sylva.core.segment`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import scipy.linalg
import scipy.sparse as sp
from scipy.spatial import cKDTree

from ..errors import ParameterError
from ..cloud import PointCloud
from ..jit import njit
from ..kernels.buckets import bucket_by_cell
from ..kernels.unionfind import uf_union
from ..progress import CancelCheck, Progress, check, report, scaled
from ..tops import MIN_TREE_HEIGHT_M
from .base import column_keys, ground_mask, label_columns_below, resolve_tops

__all__ = ["NormalizedCut", "VoxelGraph", "voxel_graph"]

#: LOBPCG iterations per two-way cut; started from the current boundary, the
#: threshold search only needs the vector's ordering, not full convergence
#: (4 and 8 gave the same detection F1 on the synthetic stands).
FIEDLER_ITERATIONS = 4

#: Pairs whose start boundary already costs less than this (Eq. 1) are left as
#: they are: clearly separate crowns, a cut could only move a few weak edges.
SETTLED_NCUT = 0.05

#: Tops are searched among the highest points of columns this wide (d_s / 2).
TOP_CELL_M = 0.35

#: Rounds of attaching unconnected crown pieces (each reaches attach_m farther).
ATTACH_ROUNDS = 5

#: A point higher than its tree's top by more than this is not that tree's.
TOP_TOLERANCE_M = 0.02

#: A tree holds at least min_tree_points points, or the canopy first returns of this many m²
#: at the scan's density around its top when fewer (a 1.25 m crown radius: 10 points at 2 per m²).
MIN_TREE_AREA_M2 = 5.0

#: Reach (x the allometric crown radius) of the plateau merge (two tops of nearly one height).
PLATEAU_REACH = 1.3

#: At low density the steep-apex window is widened to hold this many canopy
#: first returns (0.8 m at about 19 points/m², 1.6 m at 5 points/m²).
APEX_WINDOW_POINTS = 10.0


@dataclass(frozen=True)
class NormalizedCut:
    """Hu et al. (2017) §4.1 normalised cut on a voxel graph, guided by tree tops.

    ``voxel_m``: voxel pitch d_s (paper default 0.7 m, §6.1).
    ``radius_m``: r^xz of Eq. 2, voxels farther apart horizontally are not joined.
    ``height_m``: vertical reach of the neighbourhood (the cylinder's half height).
    ``sigma_h_m``, ``sigma_v_m``: scales of the horizontal / vertical distance in Eq. 2.
    ``sigma_intensity``: scale of the intensity difference, in natural-log units (ln I).
    ``sigma_colour``: scale of the RGB distance (colours scaled to [0, 1]).
    ``min_height_m``: crown points are at least this high (and tops too).
    ``top_window_m``: fixed window of the local-maximum tree-top search when
    no tops are given (small on purpose: the cuts merge surplus tops); None
    means the default.
    ``top_window_points``: at low point density the window is widened so that
    it holds at least this many canopy first returns (0 keeps ``top_window_m``).
    ``apex_window_m``, ``apex_slope``, ``apex_sectors``: the steep-apex rule
    (:class:`sylva.core.tops.SteepApex`): a maximum of this narrow window is a
    top too when the canopy drops at least ``apex_slope`` m per m from it in
    ``apex_sectors`` of 8 directions (conifer tips overtopped on one side by
    a neighbour); ``apex_window_m`` 0 turns the rule off.
    ``merge_ncut``, ``merge_dip``: two regions whose best two-way cut costs more
    than ``merge_ncut`` (Eq. 1) *and* whose crowns dip between their tops by less
    than ``merge_dip`` x the lower top's height are one tree.
    ``always_merge_ncut``: regions whose best cut costs more than this are one
    tree whatever the dip.
    ``merge_reach``, ``merge_prominence``: the crown-reach merge of step 4 (a
    lower top within ``merge_reach`` x the higher tree's allometric crown
    radius, rising less than ``merge_prominence`` x its height above the
    saddle, is a bump of that crown); ``merge_plateau``: two such tops whose
    heights differ by less than this fraction are one flat crown up to
    ``PLATEAU_REACH`` crown radii apart.
    ``min_tree_points``: smaller trees are merged into their neighbours (where
    the scan is sparse, the first returns of ``MIN_TREE_AREA_M2`` of canopy
    around the top, if fewer).
    ``crown_reach``: points farther from their top than this many allometric
    crown radii move to a tree within reach (0: off).
    ``climb``: cost per metre climbed of the geodesic start partition.
    ``attach_m``: reach of unconnected crown pieces to the nearest tree.
    """

    voxel_m: float = 0.7
    radius_m: float = 1.0
    height_m: float = 2.0
    sigma_h_m: float = 1.0
    sigma_v_m: float = 1.0
    sigma_intensity: float = 1.0
    sigma_colour: float = 0.25
    min_height_m: float = MIN_TREE_HEIGHT_M
    top_window_m: float = 2.0
    top_window_points: float = 25.0
    apex_window_m: float = 0.8
    apex_slope: float = 3.0
    apex_sectors: int = 5
    merge_ncut: float = 0.05
    merge_dip: float = 0.04
    always_merge_ncut: float = 0.15
    merge_reach: float = 0.7
    merge_prominence: float = 0.15
    merge_plateau: float = 0.05
    min_tree_points: int = 20
    crown_reach: float = 1.25
    climb: float = 100.0
    attach_m: float = 2.0

    def __post_init__(self):
        if self.top_window_m is None:   # "not given" (an optional GUI/CLI parameter)
            object.__setattr__(self, "top_window_m", 2.0)
        for name in ("voxel_m", "radius_m", "height_m", "sigma_h_m", "sigma_v_m", "sigma_intensity",
                     "sigma_colour", "merge_ncut", "always_merge_ncut"):
            if not 0 < getattr(self, name) < float("inf"):
                raise ParameterError(f"NormalizedCut.{name} must be a positive finite number, "
                                     f"not {getattr(self, name)}")
        if not 0 <= self.min_height_m < float("inf"):
            raise ParameterError(f"NormalizedCut: min_height_m must be >= 0 and finite, not {self.min_height_m}")
        if not 0 <= self.merge_dip < float("inf"):
            raise ParameterError("NormalizedCut: merge_dip must be >= 0")
        if not all(0 <= v < float("inf") for v in (self.merge_reach, self.merge_prominence, self.crown_reach,
                                                   self.min_tree_points)):
            raise ParameterError("NormalizedCut: merge_reach, merge_prominence, crown_reach and min_tree_points "
                                 "must be >= 0 and finite")
        if not (0 <= self.top_window_points and 0 <= self.apex_window_m < float("inf")
                and 0 < self.top_window_m < float("inf")):
            raise ParameterError("NormalizedCut: top_window_points and apex_window_m must be >= 0, "
                                 "top_window_m positive and finite")
        if self.apex_window_m > 0 and not (0 < self.apex_slope < float("inf") and 1 <= self.apex_sectors <= 8):
            raise ParameterError("NormalizedCut: apex_slope must be > 0 and finite and apex_sectors in 1..8")

    def windows(self, cloud: PointCloud, local: np.ndarray, height: np.ndarray,
                crown: np.ndarray, density: np.ndarray = None):
        """(top window, apex window) diameters in metres, one per point of the cloud.

        Each is widened where the scan is sparse to hold ``top_window_points`` /
        ``APEX_WINDOW_POINTS`` canopy first returns, by the canopy density
        around the point (:func:`local_canopy_density`: a neighbourhood of
        fixed size, never a statistic of the tile, so any tiling gives the same
        windows).  An apex window as wide as the top window adds nothing."""
        if density is None:
            density = local_canopy_density(cloud, local, crown)
        wide = np.full(len(local), float(self.top_window_m))
        if self.top_window_points > 0:
            wide = np.maximum(wide, 2.0 * np.sqrt(self.top_window_points / (np.pi * density)))
        apex = np.zeros(len(local))
        if self.apex_window_m > 0:
            apex = np.maximum(float(self.apex_window_m),
                              2.0 * np.sqrt(APEX_WINDOW_POINTS / (np.pi * density)))
            apex = np.minimum(apex, wide)
        return wide, apex

    def _find_tops(self, cloud, local, height, crown, progress, cancelled, density=None):
        """Tree tops among the highest point of every TOP_CELL_M column (see step 3)."""
        from ..tops import FixedWindow, SteepApex, find_tree_tops

        wide, apex = self.windows(cloud, local, height, crown, density)
        sel = np.flatnonzero(crown)
        search = sel[_column_maxima(local[sel, :2], height[sel], TOP_CELL_M)]
        rule = None
        if self.apex_window_m > 0 and self.apex_window_m < self.top_window_m:
            rule = SteepApex(float(self.apex_window_m), self.apex_slope, int(self.apex_sectors))
        return find_tree_tops(cloud.subset(search), window=FixedWindow(float(self.top_window_m)),
                              min_height_m=self.min_height_m, progress=progress,
                              cancelled=cancelled, apex=rule, diameters=wide[search],
                              apex_diameters=apex[search] if rule is not None else None)

    def segment(self, cloud: PointCloud, tops=None, progress: Progress = None,
                cancelled: CancelCheck = None) -> np.ndarray:
        """Per-point tree IDs (int32, 0 = none) of a height-normalised cloud."""
        n = len(cloud)
        labels = np.zeros(n, dtype=np.int32)
        height = np.asarray(cloud.attr("height"), dtype=np.float64)
        ground = ground_mask(cloud, height)
        crown = (height >= self.min_height_m) & ~ground
        if not crown.any():
            return labels
        check(cancelled)
        report(progress, 0.0, "building the voxel graph")
        local = cloud.local_xyz()
        graph = voxel_graph(cloud, local, height, crown, self)
        check(cancelled)
        report(progress, 0.1, "finding tree tops")
        # canopy first returns per m2 around every point (top windows, minimum tree size)
        rho = local_canopy_density(cloud, local, crown)
        if tops is None and graph.n:
            tops = self._find_tops(cloud, local, height, crown, scaled(progress, 0.1, 0.2),
                                   cancelled, rho)
        local_tops = resolve_tops(cloud, tops, self.min_height_m, self.top_window_m,
                                  scaled(progress, 0.1, 0.2), cancelled)
        check(cancelled)
        if len(local_tops) == 0 or graph.n == 0:
            return labels
        top_voxel, top_id, top_height = _top_voxels(graph, local_tops, self)
        # the minimum size of a tree, in points, at the scan's density around its top
        voxel_rho = np.zeros(graph.n)
        np.maximum.at(voxel_rho, graph.point_voxel, rho[crown])
        min_points = np.minimum(float(self.min_tree_points), MIN_TREE_AREA_M2 * voxel_rho[top_voxel])
        report(progress, 0.2, "normalised cuts")
        vlabel = _cut_graph(graph, top_voxel, top_id, top_height, self,
                            scaled(progress, 0.2, 0.95), cancelled)
        # points: crown points take their voxel's label, low points the crown above them
        labels[crown] = vlabel[graph.point_voxel]
        # nothing of a tree is higher than its top (points of a taller neighbour)
        top_h = np.zeros(int(top_id.max()) + 1)
        top_h[top_id] = top_height
        above = labels > 0
        above[above] = height[above] > top_h[labels[above]] + TOP_TOLERANCE_M
        labels[above] = 0
        if self.crown_reach > 0:
            labels = _within_crown_reach(local[:, :2], height, labels, self.crown_reach)
        # stems and low branches (below min_height_m, or crown points no top
        # reached): the label of the crown right above them in their column
        low = np.flatnonzero((labels == 0) & ~ground)
        if len(low):
            has = vlabel > 0
            ixv, iyv, izv = graph.ijk[has].T
            lx = np.floor(local[low, 0] / self.voxel_m).astype(np.int64) - graph.ij0[0]
            ly = np.floor(local[low, 1] / self.voxel_m).astype(np.int64) - graph.ij0[1]
            inside = (lx >= 0) & (ly >= 0)
            q = np.full(len(low), -1, dtype=np.int64)
            q[inside] = column_keys(lx[inside], ly[inside])
            labels[low] = label_columns_below(
                column_keys(ixv, iyv), izv * self.voxel_m, vlabel[has].astype(np.int32),
                q, height[low])
        if self.min_tree_points > 1:
            need = np.zeros(int(top_id.max()) + 1)
            need[top_id] = min_points
            labels = _merge_small(local[:, :2], height, labels, need, max(self.crown_reach, 1.0))
        return labels


# --------------------------------------------------------------------------- voxel graph

@dataclass(eq=False)
class VoxelGraph:
    """Voxels of the crown points and their Eq. 2 affinities.

    ``xyz`` (m, 3) mean local x, y and height of each voxel; ``ijk`` integer
    voxel indices (relative to ``ij0``); ``point_voxel`` the voxel of each
    crown point; ``W`` the symmetric sparse affinity matrix (CSR);
    ``edges`` (e, 2) and ``weights`` (e,) the same as an edge list (i < j).
    """

    xyz: np.ndarray
    ijk: np.ndarray
    ij0: np.ndarray
    point_voxel: np.ndarray
    W: sp.csr_matrix
    edges: np.ndarray
    weights: np.ndarray

    @property
    def n(self) -> int:
        return len(self.xyz)


def voxel_graph(cloud: PointCloud, local: np.ndarray, height: np.ndarray,
                crown: np.ndarray, params: NormalizedCut) -> VoxelGraph:
    """Voxelise the crown points and build the sparse Eq. 2 affinity graph."""
    idx = np.flatnonzero(crown)
    pitch = params.voxel_m
    x = local[idx, 0]
    y = local[idx, 1]
    z = height[idx]
    ix = np.floor(x / pitch).astype(np.int64)
    iy = np.floor(y / pitch).astype(np.int64)
    iz = np.floor(z / pitch).astype(np.int64)
    ij0 = np.array([ix.min(), iy.min()])
    ix -= ij0[0]
    iy -= ij0[1]
    ny = int(iy.max()) + 1
    nz = int(iz.max()) + 1
    key = (ix * ny + iy) * nz + iz
    ukey, inv = np.unique(key, return_inverse=True)
    m = len(ukey)
    count = np.bincount(inv, minlength=m).astype(np.float64)

    def mean(values):
        return np.bincount(inv, weights=values, minlength=m) / count

    vxyz = np.column_stack([mean(x), mean(y), mean(z)])
    ijk = np.column_stack([ukey // (ny * nz), (ukey // nz) % ny, ukey % nz])

    features = []  # per-voxel I and C features, already divided by their scales
    intensity = cloud.attr("intensity")
    if intensity is not None:
        # ln I: differences are ratios, free of the sensor's units and of any statistic of
        # the tile, so a tree gets the same weights in any tiling (no per-tile scale)
        vals = np.log(np.maximum(np.asarray(intensity, dtype=np.float64)[idx], 1.0))
        features.append(mean(vals)[:, None] / params.sigma_intensity)
    rgb = [cloud.attr(c) for c in ("red", "green", "blue")]
    if all(c is not None for c in rgb):
        cols = np.column_stack([np.asarray(c, dtype=np.float64)[idx] for c in rgb])
        top = 65535.0 if cols.max(initial=0) > 255 else 255.0
        vcol = np.column_stack([mean(cols[:, j]) for j in range(3)]) / top
        features.append(vcol / params.sigma_colour)

    # the cylinder of Eq. 2 (horizontal distance <= radius_m), cut at +-height_m
    # vertically: an ellipsoid, i.e. a ball in coordinates with z scaled
    feat = np.hstack(features) if features else np.zeros((m, 0))
    groups = np.cumsum([0] + [f.shape[1] for f in features]).astype(np.int64)
    col = ukey // nz
    ucol, cstart = np.unique(col, return_index=True)
    indptr, indices, data, a, b, w = _lattice_graph(
        vxyz, np.ascontiguousarray(feat), groups, ijk[:, 2], ucol, np.r_[cstart, m].astype(np.int64),
        int(ny), float(pitch), float(params.radius_m), float(params.height_m),
        float(params.sigma_h_m), float(params.sigma_v_m))
    if len(indices) < np.iinfo(np.int32).max:
        indptr = indptr.astype(np.int32)
    else:
        indices = indices.astype(np.int64)
    W = sp.csr_matrix((data, indices, indptr), shape=(m, m))
    W.has_sorted_indices = True
    return VoxelGraph(xyz=vxyz, ijk=ijk, ij0=ij0, point_voxel=inv, W=W,
                      edges=np.column_stack([a, b]), weights=w)


@njit
def _lattice_graph(xyz, feat, groups, iz, ucol, cstart, ny, pitch, radius, height, sigma_h, sigma_v):
    """Eq. 2 affinities of every voxel pair within the ellipsoid (horizontal
    distance² + (vertical distance x radius/height)² <= radius²) of their mean
    positions, found on the voxel lattice: a voxel's mean lies in its voxel,
    so its partners lie within ``reach`` columns and ``zreach`` layers.

    Voxels come sorted by (column, layer).  The edges (a < b) are found in
    that order, then the symmetric CSR is filled row by row (the partners
    before a voxel, then those after it), so no sort is needed.  Returns
    (indptr, indices, data) and the edge list a, b with its weights w.
    ``feat``: per-voxel I and C features already divided by their scales,
    columns ``groups[g]:groups[g + 1]`` for feature g (the L2 norm of each
    feature's difference adds to the exponent, Eq. 2)."""
    m = len(xyz)
    reach = int(np.floor(radius / pitch)) + 1
    zreach = int(np.floor(height / pitch)) + 1
    squeeze = radius / height
    r2 = radius * radius
    ng = len(groups) - 1
    cap = max(16, 8 * m)
    ea = np.empty(cap, dtype=np.int64)
    eb = np.empty(cap, dtype=np.int64)
    ew = np.empty(cap, dtype=np.float64)
    ne = 0
    side = 2 * reach + 1
    half = side * side // 2          # offsets o >= half: the own column and those after it
    lo = np.empty(side * side, dtype=np.int64)    # voxel ranges of the
    hi = np.empty(side * side, dtype=np.int64)    # neighbouring columns
    seek = np.zeros(side * side, dtype=np.int64)  # per offset: the target only grows with c
    ncol = len(ucol)
    for c in range(ncol):
        key = ucol[c]
        cx = key // ny
        cy = key - cx * ny
        nc = 0
        for o in range(half, side * side):
            dx = o // side - reach
            ty = cy + o % side - reach
            if ty < 0 or ty >= ny:
                continue
            target = (cx + dx) * ny + ty
            k = seek[o]
            while k < ncol and ucol[k] < target:
                k += 1
            seek[o] = k
            if k < ncol and ucol[k] == target:
                lo[nc] = cstart[k]
                hi[nc] = cstart[k + 1]
                nc += 1
        for i in range(cstart[c], cstart[c + 1]):
            xi, yi, zi = xyz[i, 0], xyz[i, 1], xyz[i, 2]
            for t in range(nc):
                # layers ascend within a column and with i: the window only moves up
                if t == 0:
                    lo[0] = i + 1            # own column: the voxels after i
                while lo[t] < hi[t] and iz[lo[t]] < iz[i] - zreach:
                    lo[t] += 1
                for j in range(lo[t], hi[t]):
                    if iz[j] > iz[i] + zreach:
                        break
                    ex = xyz[j, 0] - xi
                    ey = xyz[j, 1] - yi
                    ez = xyz[j, 2] - zi
                    h2 = ex * ex + ey * ey
                    if h2 + (ez * squeeze) ** 2 > r2:
                        continue
                    expo = np.sqrt(h2) / sigma_h + abs(ez) / sigma_v
                    for g in range(ng):
                        f2 = 0.0
                        for q in range(groups[g], groups[g + 1]):
                            df = feat[j, q] - feat[i, q]
                            f2 += df * df
                        expo += np.sqrt(f2)
                    if ne == cap:
                        cap *= 2
                        grown = np.empty(cap, dtype=np.int64)
                        grown[:ne] = ea[:ne]
                        ea = grown
                        grown = np.empty(cap, dtype=np.int64)
                        grown[:ne] = eb[:ne]
                        eb = grown
                        grown_w = np.empty(cap, dtype=np.float64)
                        grown_w[:ne] = ew[:ne]
                        ew = grown_w
                    ea[ne] = i
                    eb[ne] = j
                    ew[ne] = np.exp(-expo)
                    ne += 1
    ea, eb, ew = ea[:ne], eb[:ne], ew[:ne]
    indptr = np.zeros(m + 1, dtype=np.int64)
    for e in range(ne):
        indptr[ea[e] + 1] += 1
        indptr[eb[e] + 1] += 1
    for i in range(m):
        indptr[i + 1] += indptr[i]
    fill = indptr[:-1].copy()
    indices = np.empty(2 * ne, dtype=np.int32)
    data = np.empty(2 * ne, dtype=np.float64)
    for e in range(ne):                  # partners before the row's voxel, ascending
        r = eb[e]
        indices[fill[r]] = ea[e]
        data[fill[r]] = ew[e]
        fill[r] += 1
    for e in range(ne):                  # then those after it, ascending
        r = ea[e]
        indices[fill[r]] = eb[e]
        data[fill[r]] = ew[e]
        fill[r] += 1
    return indptr, indices, data, ea, eb, ew


def _column_maxima(xy: np.ndarray, z: np.ndarray, cell_m: float) -> np.ndarray:
    """Indices of the highest point of every ``cell_m`` column (ties: the lowest index).

    A tree top is always such a point, so the local-maximum search only needs
    these (a canopy-surface thinning; cells narrower than the window keep the
    window maximum nearly exact).  Cells are whole multiples of ``cell_m`` in the
    local frame (anchored on a global grid by the pipeline), never relative to
    the points' extent, so any tiling gives the same columns."""
    if len(xy) == 0:
        return np.zeros(0, dtype=np.int64)
    ij = np.floor(xy / cell_m).astype(np.int64)
    ij -= ij.min(axis=0)
    ny = int(ij[:, 1].max()) + 1
    key = ij[:, 0] * ny + ij[:, 1]
    size = int(ij[:, 0].max() + 1) * ny
    if size <= 8 * len(key) + 1_000_000:      # a grid of cells is cheaper than two sorts
        return _cell_maxima(key, np.ascontiguousarray(z, dtype=np.float64), size)
    order = np.argsort(-z, kind="stable")
    _, first = np.unique(key[order], return_index=True)
    return np.sort(order[first])


@njit
def _cell_maxima(key, z, size):
    """Ascending indices of the highest point of each occupied cell 0..size-1 (ties: lowest index)."""
    best = np.full(size, -1, dtype=np.int64)
    for i in range(len(key)):
        b = best[key[i]]
        if b < 0 or z[i] > z[b]:
            best[key[i]] = i
    out = np.empty(len(key), dtype=np.int64)
    k = 0
    for c in range(size):
        if best[c] >= 0:
            out[k] = best[c]
            k += 1
    return np.sort(out[:k])


#: Half width (m) of the square neighbourhood of :func:`local_canopy_density`.
DENSITY_HALF_WIDTH_M = 5


def local_canopy_density(cloud: PointCloud, local: np.ndarray, crown: np.ndarray) -> np.ndarray:
    """Per point: canopy first returns per m² of canopy within the 1 m columns of the
    (2 x DENSITY_HALF_WIDTH_M + 1) m square around its own column (first returns of
    the crown points, all crown points without ``return_number``, over the occupied
    columns); 1 where there is no canopy.  Columns are whole metres of the local
    frame (anchored on a global grid by the pipeline), so the value depends on the
    neighbourhood only.  Sylva, not in Hu et al."""
    from scipy import ndimage

    n = len(local)
    out = np.ones(n)
    rn = cloud.attr("return_number")
    sel = crown if rn is None else crown & (np.asarray(rn) <= 1)
    if not sel.any():
        sel = crown
    if not sel.any():
        return out
    ij_all = np.floor(local[:, :2]).astype(np.int64)
    lo = ij_all[sel].min(axis=0) - DENSITY_HALF_WIDTH_M
    hi = ij_all[sel].max(axis=0) + DENSITY_HALF_WIDTH_M
    shape = tuple((hi - lo + 1).tolist())
    if shape[0] * shape[1] > 8 * n + 4_000_000:      # a sparse extent: the whole cloud's mean
        out[:] = canopy_density(cloud, local, crown)
        return out
    ij = ij_all[sel] - lo
    counts = np.zeros(shape)
    np.add.at(counts, (ij[:, 0], ij[:, 1]), 1.0)
    occupied = (counts > 0).astype(np.float64)
    size = 2 * DENSITY_HALF_WIDTH_M + 1
    # box sums as exact integers (uniform_filter of 0/1 and counts, times the box area)
    csum = np.rint(ndimage.uniform_filter(counts, size=size, mode="constant") * size * size)
    osum = np.rint(ndimage.uniform_filter(occupied, size=size, mode="constant") * size * size)
    dens = np.where(osum > 0, csum / np.maximum(osum, 1.0), 1.0)
    q = ij_all - lo
    inside = (q[:, 0] >= 0) & (q[:, 1] >= 0) & (q[:, 0] < shape[0]) & (q[:, 1] < shape[1])
    out[inside] = dens[q[inside, 0], q[inside, 1]]
    return np.maximum(out, 1e-3)


def canopy_density(cloud: PointCloud, local: np.ndarray, crown: np.ndarray) -> float:
    """Canopy first returns per m² of canopy: the crown points' first returns (all
    crown points when the cloud has no ``return_number``) over the number of
    occupied 1 m columns."""
    rn = cloud.attr("return_number")
    sel = crown if rn is None else crown & (np.asarray(rn) <= 1)
    if not sel.any():
        sel = crown
    xy = local[sel, :2]
    if len(xy) == 0:
        return 1.0
    ij = np.floor(xy - xy.min(axis=0)).astype(np.int64)
    ny = int(ij[:, 1].max()) + 1
    key = ij[:, 0] * ny + ij[:, 1]
    size = int(ij[:, 0].max() + 1) * ny
    if size <= 8 * len(key) + 1_000_000:      # an occupancy grid is cheaper than a sort
        occupied = np.zeros(size, dtype=bool)
        occupied[key] = True
        cells = int(occupied.sum())
    else:
        cells = len(np.unique(key))
    return len(xy) / cells


def _top_voxels(graph: VoxelGraph, tops, params: NormalizedCut):
    """The voxel of each tree top (nearest voxel mean, 3-D); tops without one are dropped.

    When several tops fall on one voxel, the first (highest, by TreeTops order) keeps it.
    """
    tree = cKDTree(graph.xyz)
    q = np.column_stack([tops.xy, tops.height])
    limit = max(params.radius_m, 2.0 * params.voxel_m)
    dist, vox = tree.query(q, distance_upper_bound=limit)
    ok = np.isfinite(dist)
    order = np.lexsort((np.arange(len(q)), -tops.height))
    order = order[ok[order]]
    vox_sorted = vox[order]
    _, first = np.unique(vox_sorted, return_index=True)
    keep = order[np.sort(first)]
    return (vox[keep].astype(np.int64), tops.tree_id[keep].astype(np.int64),
            tops.height[keep])


# --------------------------------------------------------------------------- cuts

def _lobpcg1(times, x: np.ndarray, y: np.ndarray, maxiter: int, tol: float = 1e-4) -> np.ndarray:
    """Smallest eigenvector of a symmetric matrix L orthogonal to unit vector ``y``.

    ``times(X)`` returns L X for an (n, k) array.  Knyazev's LOBPCG (2001) with
    block size one and no preconditioner (the normalised Laplacian has a unit
    diagonal, so Jacobi would change nothing): Rayleigh–Ritz on span{x,
    residual, previous step} per iteration.  A lean version of
    :func:`scipy.sparse.linalg.lobpcg`, whose per-call overhead dominates on
    the many small two-tree problems.
    """
    x = x - y * (y @ x)
    x /= np.linalg.norm(x)
    ax = times(x[:, None])[:, 0]
    lam = x @ ax
    p = None
    for _ in range(maxiter):
        r = ax - lam * x
        r -= y * (y @ r)
        if np.linalg.norm(r) < tol:
            break
        cols = [x, r] if p is None else [x, r, p]
        Q, R = np.linalg.qr(np.column_stack(cols))
        keep = np.abs(np.diag(R)) > 1e-10 * np.abs(R[0, 0])
        Q = Q[:, keep]
        Q -= np.outer(y, y @ Q)
        AQ = times(Q)
        G = Q.T @ AQ
        vals, vecs = np.linalg.eigh((G + G.T) / 2.0)
        c = vecs[:, 0]
        x_new = Q @ c
        p = Q[:, 1:] @ c[1:]
        norm = np.linalg.norm(x_new)
        x = x_new / norm
        ax = (AQ @ c) / norm
        lam = x @ ax
    return x


class _Pair(NamedTuple):
    """The union of two regions as a CSR graph of its own (rows in ``nodes`` order)."""

    indptr: np.ndarray
    indices: np.ndarray
    data: np.ndarray
    deg: np.ndarray          # D: the row sums of W


@njit
def _pair_subgraph(indptr, indices, data, nodes, local):
    """``W[nodes][:, nodes]`` (CSR arrays, W's entry order kept) and its row sums, for
    sorted ``nodes``; ``local`` maps a node to its place in ``nodes`` and is -1
    elsewhere (it is left as it was found).  Sylva, not in the paper: the
    bookkeeping of the two-tree sub-problems of Hu et al. §4.1."""
    m = len(nodes)
    for t in range(m):
        local[nodes[t]] = t
    count = 0
    for t in range(m):
        u = nodes[t]
        for e in range(indptr[u], indptr[u + 1]):
            if local[indices[e]] >= 0:
                count += 1
    sub_ptr = np.zeros(m + 1, dtype=np.int64)
    sub_idx = np.empty(count, dtype=np.int64)
    sub_dat = np.empty(count)
    deg = np.zeros(m)
    k = 0
    for t in range(m):
        u = nodes[t]
        s = 0.0
        for e in range(indptr[u], indptr[u + 1]):
            j = local[indices[e]]
            if j >= 0:
                sub_idx[k] = j
                sub_dat[k] = data[e]
                s += data[e]
                k += 1
        deg[t] = s
        sub_ptr[t + 1] = k
    for t in range(m):
        local[nodes[t]] = -1
    return sub_ptr, sub_idx, sub_dat, deg


@njit
def _normalised(indptr, indices, data, inv):
    """The stored values of D^-1/2 W D^-1/2: w_ij / sqrt(d_i) / sqrt(d_j) (``inv`` = 1/sqrt(d))."""
    out = np.empty(len(data))
    for i in range(len(indptr) - 1):
        for e in range(indptr[i], indptr[i + 1]):
            out[e] = data[e] * inv[i] * inv[indices[e]]
    return out


@njit
def _laplacian_times(indptr, indices, mdata, X):
    """(I − M) X for M in CSR with sorted column indices and no diagonal entries
    (the normalised Laplacian times a block of vectors).  Each row sums its
    terms in column order, the unit diagonal in its place, exactly as
    scipy's CSR product of the assembled matrix I − M does."""
    n, k = X.shape
    Y = np.zeros((n, k))
    for i in range(n):
        for c in range(k):
            s = 0.0
            diagonal = False
            for e in range(indptr[i], indptr[i + 1]):
                j = indices[e]
                if not diagonal and j > i:
                    s += X[i, c]
                    diagonal = True
                s += -mdata[e] * X[j, c]
            if not diagonal:
                s += X[i, c]
            Y[i, c] = s
    return Y


def _fiedler(pair: _Pair, start: np.ndarray) -> np.ndarray:
    """Second-smallest generalised eigenvector x of (D - W) x = λ D x (Hu et al. §4.1, after Shi & Malik).

    Computed as the second-smallest eigenvector u of the normalised Laplacian
    L = I - D^-1/2 W D^-1/2 (the same eigenproblem, x = D^-1/2 u; the smallest
    is D^1/2 1) by LOBPCG (:func:`_lobpcg1`, ``FIEDLER_ITERATIONS``) started
    from ``start``; dense LAPACK for tiny graphs.  L is never assembled: its
    products are :func:`_laplacian_times` of W's values scaled in place.
    """
    deg = pair.deg
    n = len(deg)
    sq = np.sqrt(deg)
    inv = 1.0 / sq
    mdata = _normalised(pair.indptr, pair.indices, pair.data, inv)
    if n > 60:
        u = _lobpcg1(lambda X: _laplacian_times(pair.indptr, pair.indices, mdata, np.ascontiguousarray(X)),
                     start * sq, sq / np.linalg.norm(sq), FIEDLER_ITERATIONS)
    else:
        M = np.zeros((n, n))
        M[np.repeat(np.arange(n), np.diff(pair.indptr)), pair.indices] = mdata
        _, vecs = scipy.linalg.eigh(M, subset_by_index=[n - 2, n - 2], check_finite=False)
        u = vecs[:, 0]
    return u / sq


@njit
def _split_search(indptr, indices, data, deg, x, a, b, total):
    """The kernel of :func:`_best_split`: (rank of every node, best t, its NCut; t = -1 when
    the Fiedler vector ties ``a`` and ``b``)."""
    n = len(x)
    xs = -x if x[a] > x[b] else x.copy()
    order = np.argsort(xs, kind="mergesort")
    rank = np.empty(n, dtype=np.int64)
    for t in range(n):
        rank[order[t]] = t
    # cut(t) with A = the first t nodes (t = 1..n-1): the edges with lo < t <= hi
    add = np.zeros(n + 1)
    sub = np.zeros(n + 1)
    for i in range(n):
        for e in range(indptr[i], indptr[i + 1]):
            j = indices[e]
            if i < j:
                r1, r2 = rank[i], rank[j]
                add[min(r1, r2) + 1] += data[e]
                sub[max(r1, r2) + 1] += data[e]
    t_lo, t_hi = rank[a] + 1, rank[b]
    if t_hi < t_lo:
        return rank, -1, np.inf
    cut = 0.0       # running sums in numpy's cumsum order
    assoc = 0.0
    best, best_ncut = -1, np.inf
    for t in range(n - 1):
        cut += add[t + 1] - sub[t + 1]
        assoc += deg[order[t]]
        if t_lo - 1 <= t < t_hi:
            ncut = cut / assoc + cut / max(total - assoc, 1e-300)
            if best < 0 or ncut < best_ncut:
                best, best_ncut = t, ncut
    return rank, best, best_ncut


def _best_split(pair: _Pair, x: np.ndarray, a: int, b: int):
    """Shi & Malik's threshold search on the sorted Fiedler vector: the split with
    the smallest NCut (Eq. 1) that puts node ``a`` in A and node ``b`` in B.

    Returns (boolean mask of A, NCut of that split)."""
    rank, best, ncut = _split_search(pair.indptr, pair.indices, pair.data, pair.deg, x, a, b,
                                     float(pair.deg.sum()))
    if best < 0:  # pragma: no cover - ties in x
        return rank <= rank[a], float("inf")
    return rank < best + 1, float(ncut)


def _geodesic_partition(graph: VoxelGraph, top_voxel: np.ndarray, climb: float) -> np.ndarray:
    """Index of the nearest top of every voxel along the graph (-1: unreachable).

    Paths start at the tops; a step costs the Eq. 2 dissimilarity -log w_ij
    plus ``climb`` times the height it gains, so a region runs down its own
    crown and stops at the crease where the neighbour's crown rises again."""
    W = graph.W
    return _nearest_source(W.indptr, W.indices, W.data, np.ascontiguousarray(graph.xyz[:, 2]),
                           float(climb), np.asarray(top_voxel, dtype=np.int64))


@njit
def _nearest_source(indptr, indices, w, z, climb, sources):
    """Multi-source Dijkstra over a CSR affinity graph: index into ``sources``
    of the nearest source of every node (-1: unreachable).

    The step i -> j costs -log w_ij + 1e-9 + ``climb`` x max(z_j - z_i, 0).

    An indexed binary heap with decrease-key (numba, O(n) memory); scipy's
    ``dijkstra(min_only=True)`` gives the same partition but its Fibonacci
    heap is twice as slow on graphs of millions of voxels.  The heap keeps
    each entry's distance beside its node (``key``), so sifting reads the
    heap's own contiguous memory instead of ``dist`` at random voxels (the
    same comparisons, so the same partition, but a tile of millions of
    voxels no longer waits on cache misses).  A node reached by two sources
    at exactly the same cost keeps the first; a voxel holding two sources
    keeps the later one."""
    n = len(indptr) - 1
    dist = np.full(n, np.inf)
    owner = np.full(n, -1, dtype=np.int64)
    heap = np.empty(n, dtype=np.int64)      # nodes, a binary heap on their distance
    key = np.empty(n)                       # key[i] = dist[heap[i]]
    pos = np.full(n, -1, dtype=np.int64)    # place in heap; -1 never queued, -2 settled
    size = 0
    for k in range(len(sources)):
        s = sources[k]
        owner[s] = k
        if pos[s] == -1:
            dist[s] = 0.0
            heap[size] = s
            key[size] = 0.0
            pos[s] = size
            size += 1
    while size:
        u = heap[0]
        pos[u] = -2
        size -= 1
        if size:                             # last node to the root, sift down
            x = heap[size]
            dx = key[size]
            i = 0
            while True:
                c = 2 * i + 1
                if c >= size:
                    break
                if c + 1 < size and key[c + 1] < key[c]:
                    c += 1
                if key[c] < dx:
                    heap[i] = heap[c]
                    key[i] = key[c]
                    pos[heap[i]] = i
                    i = c
                else:
                    break
            heap[i] = x
            key[i] = dx
            pos[x] = i
        du = dist[u]
        zu = z[u]
        o = owner[u]
        for e in range(indptr[u], indptr[u + 1]):
            v = indices[e]
            if pos[v] == -2:
                continue
            nd = du - np.log(max(w[e], 1e-300)) + 1e-9 + climb * max(z[v] - zu, 0.0)
            if nd < dist[v]:
                dist[v] = nd
                owner[v] = o
                i = pos[v]
                if i == -1:
                    i = size
                    size += 1
                while i > 0:                 # sift up
                    p = (i - 1) >> 1
                    if key[p] > nd:
                        heap[i] = heap[p]
                        key[i] = key[p]
                        pos[heap[i]] = i
                        i = p
                    else:
                        break
                heap[i] = v
                key[i] = nd
                pos[v] = i
    return owner


def _pair_ncut(graph: VoxelGraph, region: np.ndarray, pairs: np.ndarray, k: int) -> np.ndarray:
    """NCut (Eq. 1) of the start boundary of every pair of regions, in one pass.

    For regions p, q: cut = w(p, q); the association of p within the union is
    2 w(p, p) + w(p, q) (every internal edge counts from both ends)."""
    inner, key, wb, zb = _region_edges(graph.edges[:, 0], graph.edges[:, 1], graph.weights, region,
                                       np.ascontiguousarray(graph.xyz[:, 2]), k)
    ukey, inv = np.unique(key, return_inverse=True)
    cut_u = np.bincount(inv, weights=wb, minlength=len(ukey))
    pos = np.searchsorted(ukey, pairs[:, 0] * k + pairs[:, 1])
    cut = cut_u[pos]
    vol_p = 2.0 * inner[pairs[:, 0]] + cut
    vol_q = 2.0 * inner[pairs[:, 1]] + cut
    ncut = cut / np.maximum(vol_p, 1e-300) + cut / np.maximum(vol_q, 1e-300)
    # saddle: the highest boundary edge (the lower of its two voxel heights)
    return ncut, _group_max(inv, zb, len(ukey))[pos]


@njit
def _region_edges(a, b, w, region, z, k):
    """One pass over the edges (a, b, w) for :func:`_pair_ncut`: the weight inside each
    region (summed in edge order), and for the edges between two regions p < q the
    key p·k + q, the weight and the lower end's height (in edge order)."""
    inner = np.zeros(k)
    n = 0
    for e in range(len(a)):
        ra, rb = region[a[e]], region[b[e]]
        if ra >= 0 and rb >= 0:
            if ra == rb:
                inner[ra] += w[e]
            else:
                n += 1
    key = np.empty(n, dtype=np.int64)
    wb = np.empty(n)
    zb = np.empty(n)
    t = 0
    for e in range(len(a)):
        ra, rb = region[a[e]], region[b[e]]
        if ra >= 0 and rb >= 0 and ra != rb:
            key[t] = min(ra, rb) * k + max(ra, rb)
            wb[t] = w[e]
            zb[t] = min(z[a[e]], z[b[e]])
            t += 1
    return inner, key, wb, zb


@njit
def _group_max(group, values, n):
    """Per group 0..n-1 the largest of its ``values`` (-inf when empty); ``np.maximum.at`` without its overhead."""
    out = np.full(n, -np.inf)
    for e in range(len(group)):
        if values[e] > out[group[e]]:
            out[group[e]] = values[e]
    return out


def _find(parent: np.ndarray, i: int) -> int:
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


def _tops_of(xy, height, labels):
    """(ids, top xy, top height) of every label > 0: its highest point (ties: lowest x, then y,
    then the first point; never the point order alone, which depends on the tiling).  One pass
    (:func:`_label_maxima`), not a sort of every labelled point."""
    top = _label_maxima(np.ascontiguousarray(xy, dtype=np.float64),
                        np.ascontiguousarray(height, dtype=np.float64),
                        np.ascontiguousarray(labels, dtype=np.int64), int(labels.max(initial=0)) + 1)
    return labels[top], xy[top], height[top]


@njit
def _label_maxima(xy, h, labels, size):
    """Ascending by label: the index of the highest point of every label > 0 (ties: lowest x,
    then lowest y, then the lowest index), as a lexsort on (label, -h, x, y) picks it."""
    best = np.full(size, -1, dtype=np.int64)
    for i in range(len(labels)):
        lab = labels[i]
        if lab <= 0:
            continue
        b = best[lab]
        if b < 0 or h[i] > h[b] or (h[i] == h[b] and (xy[i, 0] < xy[b, 0] or (
                xy[i, 0] == xy[b, 0] and xy[i, 1] < xy[b, 1]))):
            best[lab] = i
    n = 0
    for lab in range(size):
        if best[lab] >= 0:
            n += 1
    out = np.empty(n, dtype=np.int64)
    k = 0
    for lab in range(size):
        if best[lab] >= 0:
            out[k] = best[lab]
            k += 1
    return out


def _reassign(xy, height, labels, bad, tid, txy, th, reach, fallback):
    """Labels of the points ``bad`` set to the tree (of tops tid/txy/th) within ``reach`` allometric
    crown radii whose top is nearest in those units and not lower than the point; ``fallback``
    (per bad point) where there is none."""
    out = labels.copy()
    if len(bad) == 0:
        return out
    if len(tid) == 0:
        out[bad] = fallback
        return out
    k = min(8, len(tid))
    dd, jj = cKDTree(txy).query(xy[bad], k=k)
    dd, jj = dd.reshape(len(bad), k), jj.reshape(len(bad), k)
    norm = dd / (reach * crown_radius_m(th[jj]))
    ok = (norm <= 1.0) & (th[jj] >= height[bad][:, None] - TOP_TOLERANCE_M)
    norm = np.where(ok, norm, np.inf)
    best = np.argmin(norm, axis=1)
    rows = np.arange(len(bad))
    out[bad] = np.where(np.isfinite(norm[rows, best]), tid[jj[rows, best]], fallback)
    return out


def _within_crown_reach(xy: np.ndarray, height: np.ndarray, labels: np.ndarray,
                        reach: float) -> np.ndarray:
    """Labels with every point farther (horizontally) from its tree's top than ``reach`` x the
    crown radius that top's height implies (:func:`crown_radius_m`) moved to the tree
    within reach whose top is nearest in those units and not lower than the point (a point
    no other top reaches keeps its tree: open-grown crowns are wider than the allometry).

    Dalponte & Coomes (2016) bound a crown by a maximum crown diameter; here the bound
    follows the tree's height (Popescu & Wynne 2004 crown width).  It removes the strays
    that graph paths carry across neighbouring crowns (Sylva, not in Hu et al.; measured on
    MixedConifer.laz against lidR's crowns, ``benchmarks/segmentation.py``)."""
    if not (labels > 0).any():
        return labels
    tid, txy, th = _tops_of(xy, height, labels)
    pos = np.zeros(int(tid.max()) + 1, dtype=np.int64)
    pos[tid] = np.arange(len(tid))
    sel = np.flatnonzero(labels > 0)
    p = pos[labels[sel]]
    far = np.hypot(xy[sel, 0] - txy[p, 0], xy[sel, 1] - txy[p, 1]) > reach * crown_radius_m(th[p])
    bad = sel[far]
    return _reassign(xy, height, labels, bad, tid, txy, th, reach, labels[bad])


def _merge_small(xy: np.ndarray, height: np.ndarray, labels: np.ndarray, min_points: np.ndarray,
                 reach: float) -> np.ndarray:
    """Trees of fewer than ``min_points[id]`` points merged into the tree within ``reach`` crown radii
    whose top is nearest (as :func:`_within_crown_reach`); with none in reach their points are
    no tree (0): a handful of points apart from every crown is not a tree.  Sylva, not in Hu et al."""
    if not (labels > 0).any():
        return labels
    size = np.bincount(labels, minlength=max(int(labels.max()) + 1, len(min_points)))
    need = np.zeros(len(size))
    need[:len(min_points)] = min_points
    small = (size < need) & (size > 0)
    small[0] = False
    if not small.any():
        return labels
    tid, txy, th = _tops_of(xy, height, labels)
    big = ~small[tid]
    bad = np.flatnonzero(small[labels])
    return _reassign(xy, height, labels, bad, tid[big], txy[big], th[big], reach, 0)


def crown_radius_m(height_m):
    """Expected crown radius (m) of a tree ``height_m`` metres high: half the crown width of
    Popescu & Wynne (2004), CW = 2.51503 + 0.00901 h² (pines and deciduous trees together;
    :meth:`sylva.core.tops.VariableWindow.combined`)."""
    h = np.asarray(height_m, dtype=np.float64)
    return 0.5 * (2.51503 + 0.00901 * h * h)


def _cut_graph(graph: VoxelGraph, top_voxel: np.ndarray, top_id: np.ndarray,
               top_height: np.ndarray, params: "NormalizedCut", progress: Progress,
               cancelled: CancelCheck) -> np.ndarray:
    """Tree id of every voxel: geodesic start, pairwise normalised cuts, merges, clean-up.

    1. Every voxel starts with its nearest top along the graph.
    2. For every pair of touching regions, the two-way normalised cut of their
       union (Fiedler vector + Shi–Malik threshold search, the top of each on
       its own side) proposes a new boundary; its NCut value (Eq. 1) says how
       separate the two parts are.
    3. Pairs whose start boundary costs less than ``SETTLED_NCUT`` are left
       as they are (no eigenproblem).
    4. Pairs whose best cut (Fiedler split or start boundary) costs more than
       ``always_merge_ncut``, or more than ``merge_ncut`` with a dip to the
       saddle below ``merge_dip`` x the lower top, are one tree with two local
       maxima: the lower top is merged into the higher one (which keeps its
       id); a lower top with several such neighbours joins only the one across
       the highest saddle.  The other
       proposals move voxels across the boundary (the lowest-NCut proposal
       wins when a voxel gets several).
    """
    region = _geodesic_partition(graph, top_voxel, params.climb)
    a, b = graph.edges[:, 0], graph.edges[:, 1]
    ra, rb = region[a], region[b]
    touch = (ra >= 0) & (rb >= 0) & (ra != rb)
    pairs = np.unique(np.sort(np.column_stack([ra[touch], rb[touch]]), axis=1), axis=0)
    k = len(top_voxel)
    parent = np.arange(k)
    best_ncut = np.full(graph.n, np.inf)
    proposal = region.copy()
    partner = np.full(k, -1, dtype=np.int64)    # the top each lower top merges into
    partner_dip = np.full(k, np.inf)
    if len(pairs):
        ncut_start, saddle = _pair_ncut(graph, region, pairs, k)
        order = np.argsort(region, kind="stable")
        starts = np.searchsorted(region[order], np.arange(-1, k + 1))
        W = graph.W
        local = np.full(graph.n, -1, dtype=np.int64)
        step = max(1, len(pairs) // 100)
        for i, (p, q) in enumerate(pairs):
            check(cancelled)
            if i % step == 0:
                report(progress, i / len(pairs), f"normalised cuts: {i}/{len(pairs)} tree pairs")
            ncut_now = ncut_start[i]
            hi, lo = (p, q) if (top_height[p], -p) >= (top_height[q], -q) else (q, p)
            low = top_height[lo]
            dip = (low - saddle[i]) / low
            gap = np.hypot(*(graph.xyz[top_voxel[p], :2] - graph.xyz[top_voxel[q], :2]))
            reach = crown_radius_m(top_height[hi])
            level = (top_height[hi] - low) / top_height[hi] < params.merge_plateau
            if ((dip < params.merge_prominence and gap < params.merge_reach * reach)
                    or (level and dip < 0.5 * params.merge_prominence and gap < PLATEAU_REACH * reach)):
                # a bump inside the crown the higher top's height implies (see step 4)
                if (dip, hi) < (partner_dip[lo], partner[lo]):
                    partner[lo], partner_dip[lo] = hi, dip
                continue
            if ncut_now < SETTLED_NCUT:
                continue   # the start boundary is already a near-perfect cut
            nodes = np.sort(np.concatenate([order[starts[p + 1]:starts[p + 2]],
                                            order[starts[q + 1]:starts[q + 2]]]))
            pair = _Pair(*_pair_subgraph(W.indptr, W.indices, W.data, nodes, local))
            if (pair.deg <= 0).any():
                continue
            ia = int(np.searchsorted(nodes, top_voxel[p]))
            ib = int(np.searchsorted(nodes, top_voxel[q]))
            start = np.where(region[nodes] == p, -1.0, 1.0)
            x = _fiedler(pair, start)
            side_a, ncut = _best_split(pair, x, ia, ib)
            best = min(ncut, ncut_now)   # the start boundary is a candidate cut too
            if best > params.always_merge_ncut or (best > params.merge_ncut
                                                   and dip < params.merge_dip):
                if (dip, hi) < (partner_dip[lo], partner[lo]):   # the highest saddle wins
                    partner[lo], partner_dip[lo] = hi, dip
                continue
            if not ncut < ncut_now:
                continue   # the start boundary is already the better cut (Eq. 1)
            new = np.where(side_a, p, q)
            moved = (new != region[nodes]) & (ncut < best_ncut[nodes])
            proposal[nodes[moved]] = new[moved]
            best_ncut[nodes[moved]] = ncut
    for lo in np.flatnonzero(partner >= 0):
        rp, rq = _find(parent, int(lo)), _find(parent, int(partner[lo]))
        if rp != rq:
            hi, low = (rp, rq) if (top_height[rp], -rp) >= (top_height[rq], -rq) else (rq, rp)
            parent[low] = hi
    roots = np.array([_find(parent, i) for i in range(k)], dtype=np.int64)
    vlabel = np.where(proposal >= 0, top_id[roots[np.maximum(proposal, 0)]], 0)
    alive = roots == np.arange(k)
    return _clean(graph, vlabel, top_voxel[alive], top_id[alive], top_height[alive],
                  0.0, params.attach_m)


@njit
def _pairs_within(xyz, query, r):
    """Every (query[i], j, distance) with point j within ``r`` of point query[i] (d² <= r²,
    d = sqrt((dx² + dy²) + dz²): the pairs and values of ``cKDTree.sparse_distance_matrix``),
    found on a uniform grid of cells of edge >= r (counted, then filled).  Sylva, not in
    the paper."""
    n = xyz.shape[0]
    lo = np.empty(3)
    hi = np.empty(3)
    for a in range(3):
        lo[a] = xyz[0, a]
        hi[a] = xyz[0, a]
    for i in range(n):
        for a in range(3):
            lo[a] = min(lo[a], xyz[i, a])
            hi[a] = max(hi[a], xyz[i, a])
    cell = max(r, 1e-9)
    while True:
        gx = int((hi[0] - lo[0]) / cell) + 1
        gy = int((hi[1] - lo[1]) / cell) + 1
        gz = int((hi[2] - lo[2]) / cell) + 1
        if gx * gy * gz <= 4 * n + 4096:
            break
        cell *= 1.5
    ncell = gx * gy * gz
    cid = np.empty(n, dtype=np.int64)
    for i in range(n):
        cx = min(int((xyz[i, 0] - lo[0]) / cell), gx - 1)
        cy = min(int((xyz[i, 1] - lo[1]) / cell), gy - 1)
        cz = min(int((xyz[i, 2] - lo[2]) / cell), gz - 1)
        cid[i] = (cx * gy + cy) * gz + cz
    start, member = bucket_by_cell(cid, ncell)
    r2 = r * r
    out_i = np.empty(0, dtype=np.int64)
    out_j = np.empty(0, dtype=np.int64)
    out_d = np.empty(0)
    for rnd in range(2):            # count, then fill
        k = 0
        for q in range(len(query)):
            p = query[q]
            px, py, pz = xyz[p, 0], xyz[p, 1], xyz[p, 2]
            c = cid[p]
            cx, cy, cz = c // (gy * gz), (c // gz) % gy, c % gz
            for ix in range(max(cx - 1, 0), min(cx + 2, gx)):
                for iy in range(max(cy - 1, 0), min(cy + 2, gy)):
                    for iz in range(max(cz - 1, 0), min(cz + 2, gz)):
                        g = (ix * gy + iy) * gz + iz
                        for t in range(start[g], start[g + 1]):
                            j = member[t]
                            dx = px - xyz[j, 0]
                            dy = py - xyz[j, 1]
                            dz = pz - xyz[j, 2]
                            d2 = (dx * dx + dy * dy) + dz * dz
                            if d2 <= r2:
                                if rnd == 1:
                                    out_i[k] = p
                                    out_j[k] = j
                                    out_d[k] = np.sqrt(d2)
                                k += 1
        if rnd == 0:
            out_i = np.empty(k, dtype=np.int64)
            out_j = np.empty(k, dtype=np.int64)
            out_d = np.empty(k)
    return out_i, out_j, out_d


@njit
def _joined_to_top(a, b, vlabel, top_voxel, top_id):
    """Per voxel: is it joined to its tree's top through voxels of that tree?

    The components of the edges (a, b) whose ends share a label > 0 (union-find);
    a component is good when it holds a top voxel whose label is that top's id
    (of several tops in one component, the last one listed decides, as numpy's
    fancy assignment does).  Sylva, not in the paper: the fragment test of
    :func:`_clean`."""
    m = len(vlabel)
    root = np.arange(m)
    for e in range(len(a)):
        u, v = a[e], b[e]
        if vlabel[u] > 0 and vlabel[u] == vlabel[v]:
            uf_union(root, u, v)
    for i in range(m):                  # flatten: root[i] is i's representative
        r = i
        while root[r] != r:
            r = root[r]
        root[i] = r
    good = np.zeros(m, dtype=np.bool_)
    for t in range(len(top_voxel)):
        good[root[top_voxel[t]]] = vlabel[top_voxel[t]] == top_id[t]
    out = np.empty(m, dtype=np.bool_)
    for i in range(m):
        out[i] = good[root[i]]
    return out


def _clean(graph: VoxelGraph, vlabel: np.ndarray, top_voxel: np.ndarray,
           top_id: np.ndarray, top_height: np.ndarray, tolerance_m: float,
           attach_m: float) -> np.ndarray:
    """Physical consistency of the labels, then fill the gaps.

    * A tree holds nothing higher than its top (+ ``tolerance_m``).
    * A tree's voxels not connected to its top through the tree itself are
      fragments; they are released.
    * Released voxels go to the neighbouring tree they are most strongly joined
      to (largest w_ij) among the trees whose top is high enough.
    * Voxels of top-less graph components (crown pieces a sparse scan left
      unconnected) join the nearest labelled voxel within ``attach_m`` (3-D)
      when that tree's top is high enough; farther ones (isolated noise) stay 0.
    """
    a, b = graph.edges[:, 0], graph.edges[:, 1]
    w = graph.weights
    z = graph.xyz[:, 2]
    size = int(max(top_id.max(initial=0), vlabel.max(initial=0))) + 1
    height_of = np.full(size, -np.inf)
    # a given top may lie a little below its voxel's mean (another source or DTM)
    height_of[top_id] = np.maximum(top_height, z[top_voxel])
    vlabel = np.where(z <= height_of[vlabel] + tolerance_m, vlabel, 0)
    vlabel = np.where(_joined_to_top(a, b, vlabel, top_voxel, top_id), vlabel, 0)
    # flood the unlabelled voxels from labelled neighbours, strongest edge first
    free_a = vlabel[a] == 0            # only edges into unlabelled voxels matter
    free_b = vlabel[b] == 0
    src = np.concatenate([a[free_a], b[free_b]])
    dst = np.concatenate([b[free_a], a[free_b]])
    ww = np.concatenate([w[free_a], w[free_b]])
    while len(src):
        cand = (vlabel[src] == 0) & (vlabel[dst] > 0)
        cand &= z[src] <= height_of[vlabel[dst]] + tolerance_m
        if not cand.any():
            break
        s, d, wc = src[cand], dst[cand], ww[cand]
        o = np.lexsort((-wc, s))
        s, d = s[o], d[o]
        first = np.ones(len(s), dtype=bool)
        first[1:] = s[1:] != s[:-1]
        vlabel[s[first]] = vlabel[d[first]]
        still = vlabel[src] == 0
        src, dst, ww = src[still], dst[still], ww[still]
    # crown pieces the graph left unconnected (sparse scans): nearest tree within attach_m
    free = np.flatnonzero(vlabel == 0)
    if not (len(free) and attach_m > 0 and (vlabel > 0).any()):
        return vlabel
    # every voxel within attach_m of a free one, found once (one tree of all voxels)
    fi, vj, dist = _pairs_within(graph.xyz, free, float(attach_m))
    order = np.lexsort((vj, dist, fi))          # per free voxel, nearest first
    fi, vj = fi[order], vj[order]
    for _ in range(ATTACH_ROUNDS):
        lab = vlabel[vj]
        ok = (vlabel[fi] == 0) & (lab > 0)
        ok[ok] = z[fi[ok]] <= height_of[lab[ok]] + tolerance_m
        if not ok.any():
            break
        f, l = fi[ok], lab[ok]
        first = np.ones(len(f), dtype=bool)
        first[1:] = f[1:] != f[:-1]
        vlabel[f[first]] = l[first]
    return vlabel
