"""Apexes of a lower crown layer: the tops of trees under the edge of a higher crown.

The tree-top search looks for maxima of the canopy surface, so a tree whose
apex is under a neighbour's crown has no top of its own: in the suite's dense
stands 21-24 % of the trees are such (``benchmarks/segmentation.py``, the loss
rows' "overtopped").  Hamraz, Contreras & Zhang (2017, "Vertical stratification
of forest canopy for segmentation of understory trees within small-footprint
airborne LiDAR point clouds", ISPRS J. Photogramm. Remote Sens. 130:385-392)
find such trees layer by layer: a lower layer begins below a gap in the
vertical profile of the points.  Here a crown point is the apex of a tree of
a lower layer when

* the :data:`LAYER_GAP_M` (2 m) above it are empty within :data:`LAYER_REACH_M`
  (1 m) horizontally while higher crown points lie within that reach: the gap
  between the upper layer and the lower one;
* a crown lies under it: at least :data:`LAYER_MASS` (5) x the scan's canopy
  density (first returns per m2 around it) points within
  :data:`LAYER_MASS_REACH_M` (1.5 m) horizontally and :data:`LAYER_MASS_DEPTH_M`
  (4 m) below;
* it is under the edge of a higher top's crown: :data:`LAYER_RING` (0.5-1.3)
  of that top's allometric crown radius away, in the middle storey of that
  tree's height (:data:`LAYER_HEIGHT`, 1/3 to 2/3), and no higher top is nearer
  than 0.5 crown radius (there it is a branch of that crown);
* the canopy there is closed (:data:`~.cut.CLOSED_COVER` around it, judged as
  around a top) and the scan holds at least :data:`LAYER_MIN_DENSITY` (8)
  canopy first returns per m2: in an open canopy, or a sparser scan, the band
  under any crown's edge is as empty as a gap.

One apex per :data:`LAYER_SPACING_M` (1.5 m): the highest (ties: lowest x,
then y, so any order of the points gives the same apexes).  Every test looks
at a fixed neighbourhood of the point, never at the tile.  Sylva, not in Hu
et al.

Measured (ncut F1 without -> with, seed 0, ``benchmarks/segmentation.py
--sizes 0``): dense broadleaf stands at 20 / 50 points/m2 0.792 / 0.797 ->
0.820 / 0.812, dense conifers 0.910 / 0.867 -> 0.917 / 0.876, dense mixed
0.810 / 0.775 -> 0.817 / 0.779, tall dense at 20 0.786 -> 0.788; no forest
stand loses more than 0.002 and none at 2 or 5 points/m2 changes; the
parkland stands lose 0.003-0.011 (the forest defaults) and, with the
"open-grown" preset, dense at 20 / 50 0.826 / 0.818 -> 0.835 / 0.803.
Held out (seed 1), dense at 20 points/m2: broadleaf 0.791 -> 0.803, mixed
0.790 -> 0.801, conifer 0.873 -> 0.882.  The shipped sample (0.985) and
MixedConifer.laz (4.7 points/m2) are unchanged.  Measured and not kept: the
middle storey up to 0.8 of the height and a crown of 3 x the density (the
dense parkland stands lost 0.03, mixed and tall dense at 50 points/m2 0.006);
without the density and closed-canopy conditions the open and medium stands
at 2 points/m2 lost 0.04-0.06 (broadleaf open 0.876 -> 0.812).  It costs
about 6 % of the segmentation's time (1 M points, ``farm-bench`` paired).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ...jit import njit
from ...noise import column_bounds, grid_buckets
from .cleanup import crown_radius_m
from .cut import CLOSED_COVER

#: The empty band above a lower layer's apex (m), and how far around it is looked for (m).
LAYER_GAP_M = 2.0
LAYER_REACH_M = 1.0

#: The crown under the apex: at least LAYER_MASS x the canopy density (per m2) points within
#: LAYER_MASS_REACH_M horizontally and LAYER_MASS_DEPTH_M below.
LAYER_MASS = 5.0
LAYER_MASS_REACH_M = 1.5
LAYER_MASS_DEPTH_M = 4.0

#: A lower layer's apex lies this far from a higher top (x its allometric crown radius) ...
LAYER_RING = (0.5, 1.3)
#: ... and is this share of its height: the middle storey of the IUFRO tree classification
#: (Leibundgut 1958: the upper storey reaches above 2/3 of the top height, the lower one stays
#: under 1/3).
LAYER_HEIGHT = (1.0 / 3.0, 2.0 / 3.0)

#: Canopy first returns per m2 below which an empty band says nothing.
LAYER_MIN_DENSITY = 8.0

#: One apex within this distance (m): the highest.
LAYER_SPACING_M = 1.5


def lower_layer_apexes(xy: np.ndarray, height: np.ndarray, density: np.ndarray, top_xy: np.ndarray,
                       top_height: np.ndarray, crown_scale: float, cover) -> np.ndarray:
    """Indices into (``xy``, ``height``), the crown points, of the apexes of a lower layer.

    ``density``: canopy first returns per m2 around each crown point; ``top_xy``, ``top_height``:
    the tops found on the canopy surface; ``cover(xy, height)``: the canopy cover around points
    of those heights (as around a top).  Ordered by height, then x, then y."""
    none = np.zeros(0, dtype=np.int64)
    dense = np.flatnonzero(density >= LAYER_MIN_DENSITY)
    if len(dense) == 0 or len(top_xy) == 0:
        return none
    lo, hi = column_bounds(xy)
    cell = LAYER_REACH_M
    nx, ny = (np.floor(np.maximum(hi - lo, 1e-6) / cell).astype(np.int64) + 1).tolist()
    order, starts, _ = grid_buckets(xy, float(lo[0]), float(lo[1]), cell, nx, ny)
    below = _under_gap(np.ascontiguousarray(xy[order]), np.ascontiguousarray(height[order]), starts,
                       np.ascontiguousarray(xy[dense]), np.ascontiguousarray(height[dense]),
                       float(lo[0]), float(lo[1]), cell, nx, ny, LAYER_REACH_M, LAYER_GAP_M,
                       LAYER_MASS_REACH_M, LAYER_MASS_DEPTH_M)
    cand = dense[below >= LAYER_MASS * density[dense]]
    if len(cand) == 0:
        return none
    # under the edge of a higher crown, and under no crown's centre
    radius = crown_radius_m(top_height, crown_scale)
    near = cKDTree(xy[cand]).sparse_distance_matrix(cKDTree(top_xy), LAYER_RING[1] * float(radius.max()),
                                                    output_type="ndarray")
    i, j, d = near["i"], near["j"], near["v"]
    higher = top_height[j] > height[cand[i]]
    i, j, d = i[higher], j[higher], d[higher]
    ratio = height[cand[i]] / top_height[j]
    ring = ((d >= LAYER_RING[0] * radius[j]) & (d <= LAYER_RING[1] * radius[j])
            & (ratio >= LAYER_HEIGHT[0]) & (ratio <= LAYER_HEIGHT[1]))
    centre = d < LAYER_RING[0] * radius[j]
    ok = (np.bincount(i[ring], minlength=len(cand)) > 0) & (np.bincount(i[centre], minlength=len(cand)) == 0)
    cand = cand[ok]
    if len(cand) == 0:
        return none
    cand = cand[cover(xy[cand], height[cand]) >= CLOSED_COVER]
    # one apex per LAYER_SPACING_M: the highest first
    cand = cand[np.lexsort((xy[cand, 1], xy[cand, 0], -height[cand]))]
    keep = np.ones(len(cand), dtype=bool)
    tree = cKDTree(xy[cand])
    for k in range(len(cand)):
        if keep[k]:
            for m in tree.query_ball_point(xy[cand[k]], LAYER_SPACING_M):
                if m > k:
                    keep[m] = False
    return cand[keep]


@njit
def _under_gap(pts, hs, starts, cxy, ch, x0, y0, cell, nx, ny, reach, gap, mass_reach, depth):
    """For each candidate (cxy, ch): the points of ``pts`` (bucketed by cell: ``starts``) within
    ``mass_reach`` horizontally and ``depth`` below it when none is within ``reach`` and ``gap``
    above it and some is within ``reach`` higher still; else -1.  The gap test stops at the first
    point in the gap, which is most candidates' fate; only the others count their mass."""
    out = np.full(len(ch), -1, dtype=np.int64)
    r2 = reach * reach
    m2 = mass_reach * mass_reach
    near = int(np.ceil(reach / cell))
    wide = int(np.ceil(mass_reach / cell))
    for k in range(len(ch)):
        px, py, own = cxy[k, 0], cxy[k, 1], ch[k]
        ix = int(np.floor((px - x0) / cell))
        iy = int(np.floor((py - y0) / cell))
        covered = False
        blocked = False
        for gx in range(max(ix - near, 0), min(ix + near, nx - 1) + 1):
            if blocked:
                break
            for gy in range(max(iy - near, 0), min(iy + near, ny - 1) + 1):
                if blocked:
                    break
                g = gx * ny + gy
                for j in range(starts[g], starts[g + 1]):
                    dz = hs[j] - own
                    if dz > 0.0:
                        dx = pts[j, 0] - px
                        dy = pts[j, 1] - py
                        if dx * dx + dy * dy <= r2:
                            if dz <= gap:
                                blocked = True
                                break
                            covered = True
        if blocked or not covered:
            continue
        mass = 0
        for gx in range(max(ix - wide, 0), min(ix + wide, nx - 1) + 1):
            for gy in range(max(iy - wide, 0), min(iy + wide, ny - 1) + 1):
                g = gx * ny + gy
                for j in range(starts[g], starts[g + 1]):
                    dz = hs[j] - own
                    if dz < 0.0 and dz >= -depth:
                        dx = pts[j, 0] - px
                        dy = pts[j, 1] - py
                        if dx * dx + dy * dy <= m2:
                            mass += 1
        out[k] = mass
    return out
