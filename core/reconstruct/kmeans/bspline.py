"""The branch model: Yan et al. 2009 §4.

A cubic B-spline (Eq. 2) fitted to each branch's skeleton vertices, radii interpolated from the bounding
cylinders along it (§4.2) and the lofted tubes and cylinder list (:func:`model_branches`,
:class:`DenseModel`); the pruning of branches that stay inside their parent's tube and the start of a
branch where it leaves its parent (:func:`prune_branches`, ``_trim_in_parent``) are Sylva's, not in the paper.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import List, Optional, Tuple

import numpy as np

from ...errors import InputError
from ..model import Reconstruction
from .branches import BranchStructure
from .segmentation import Segmentation


# --------------------------------------------------------------------------- §4 model

@dataclass
class DenseModel:
    """Everything Yan's pipeline produces for one tree.

    ``reconstruction`` the :class:`Reconstruction` (skeleton of junctions and
    cluster centres with radii); ``segmentation`` / ``structure`` the §2 / §3
    results; ``curves`` per branch the sampled B-spline centre line (k, 3)
    and ``curve_radii`` (k,) metres; ``cylinders`` the cylinder table of
    :func:`sylva.core.qsm.cylinders_from_curves` (dict of arrays)."""

    reconstruction: Reconstruction
    segmentation: Optional[Segmentation]
    structure: Optional[BranchStructure]
    curves: List[np.ndarray]
    curve_radii: List[np.ndarray]
    branch_parent: np.ndarray
    branch_order: np.ndarray
    cylinders: dict
    #: centre lines and radii of the wood mesh when they differ from ``curves`` (levelset.LevelSetQSM)
    mesh_curves: Optional[List[np.ndarray]] = None
    mesh_radii: Optional[List[np.ndarray]] = None
    #: least chord tolerance (m) of the wood mesh's polygons at LOD 0 (levelset.LevelSetQSM.chord_spacing)
    mesh_chord_m: float = 0.0

    def mesh(self, sides: int = 10, cap: bool = True) -> Tuple[np.ndarray, np.ndarray]:
        """Lofted surface of all branches (Yan §4.2, ``n2 = 10`` sides, RMF frames) as (vertices, faces)."""
        from ...geometry import sweep_tube
        vs, fs, off = [], [], 0
        for pts, r in zip(self.curves, self.curve_radii):
            if len(pts) < 2:
                continue
            try:
                v, f = sweep_tube(pts, r, sides=sides, cap=cap)
            except InputError:
                continue
            vs.append(v)
            fs.append(f + off)
            off += len(v)
        if not vs:
            return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
        return np.vstack(vs), np.vstack(fs)


def _vertex_radii(seg: Segmentation, clusters: List[int], radius: str = "bounding") -> np.ndarray:
    """Radius per cluster of a branch: the bounding-cylinder radius of fixed clusters
    (§2.3, §4.2); loose (unfixed) clusters, which hold forks or noise, are
    filled by linear interpolation from the fixed ones along the branch, or,
    on a branch without any fixed cluster, get the mean distance of their
    points to their axis (less inflated by a fork than the enclosing circle).
    ``radius="fit"`` uses the least-squares circle of the projected points
    instead of the enclosing circle (unbiased by noise; not in the paper)."""
    r = seg.cylinders["radius" if radius == "bounding" else "fit_radius"][clusters].astype(float)
    ok = seg.fixed[clusters] & (r > 0)
    if ok.sum() == 0:
        return seg.cylinders["mean_rho"][clusters].astype(float)
    x = np.arange(len(r))
    return np.interp(x, x[ok], r[ok])


def tube_ratio(pts: np.ndarray, line: np.ndarray, rad: np.ndarray) -> np.ndarray:
    """Distance of each point to a polyline divided by the polyline's radius there."""
    if len(line) < 2:
        return np.linalg.norm(pts - line[0], axis=1) / max(float(rad[0]), 1e-6)
    a, b = line[:-1], line[1:]
    ab = b - a
    t = np.clip(((pts[:, None] - a[None]) * ab[None]).sum(2) / np.maximum((ab * ab).sum(1), 1e-18), 0, 1)
    d = np.linalg.norm(pts[:, None] - (a[None] + t[..., None] * ab[None]), axis=2)
    r = np.maximum(rad[:-1] + t * (rad[1:] - rad[:-1]), 1e-6)
    return (d / r).min(axis=1)


def prune_branches(seg: Segmentation, st: BranchStructure, factor: float = 1.5,
                   radius: str = "bounding") -> BranchStructure:
    """Drop branches that stay inside the tube of an ancestor: patches of a thick stem.

    Not in Yan et al.: small clusters on the surface of a stem wider than
    they are become leaves of the shortest-path tree (§3.2) and so short
    "branches" (Alg. 3.1), sometimes routed through a neighbouring branch.
    A branch is kept when one of its vertices (cluster centres and tip
    junction) lies farther than ``factor`` radii from the centre line of
    every ancestor branch (parent, grandparent, ... trunk), or when it
    carries a kept branch.  Children are examined before parents.
    """
    nb = len(st.branches)
    if nb <= 1:
        return st
    keep = np.ones(nb, dtype=bool)
    has_kept_child = np.zeros(nb, dtype=bool)
    lines, lrad = [], []
    for bi, chain in enumerate(st.branches):
        own = chain if st.branch_parent[bi] < 0 else chain[1:]
        r_own = _vertex_radii(seg, own, radius)
        v = [st.junction[own[0]]] if st.branch_parent[bi] < 0 else [st.centre[chain[0]]]
        v += [st.centre[c] for c in own]
        lines.append(np.asarray(v))
        lrad.append(np.r_[r_own[0], r_own])
    for bi in range(nb - 1, 0, -1):
        if st.branch_parent[bi] < 0:
            continue
        if not has_kept_child[bi]:
            chain = st.branches[bi]
            pts = np.vstack([st.centre[chain[1:]], st.tip[chain[-1]][None]])
            pts = pts[np.all(np.isfinite(pts), axis=1)]
            outside = np.ones(len(pts), dtype=bool)
            a = int(st.branch_parent[bi])
            while a >= 0 and outside.any():
                outside &= tube_ratio(pts, lines[a], lrad[a]) > factor
                a = int(st.branch_parent[a])
            keep[bi] = bool(outside.any())
        if keep[bi]:
            has_kept_child[int(st.branch_parent[bi])] = True
    if keep.all():
        return st
    new_id = np.cumsum(keep) - 1
    branches = [st.branches[b] for b in range(nb) if keep[b]]
    bpar = np.array([new_id[st.branch_parent[b]] if st.branch_parent[b] >= 0 else -1
                     for b in range(nb) if keep[b]], dtype=np.int64)
    bord = st.branch_order[keep]
    return BranchStructure(st.parent, st.root, st.junction, st.tip, st.centre, branches, bpar, bord,
                           st.n_edges, st.bridged)


def _fit_bspline(pts: np.ndarray, samples: int) -> Tuple[np.ndarray, np.ndarray]:
    """Cubic B-spline through the branch vertices (Yan §4.1, Eq. 2); returns samples and their parameter.

    The curve interpolates the vertices (chord-length parameters).  §4.1
    approximates them with ``n`` control points on uniform knots, ``n`` left
    open; least-squares fits tried here (``m / 1.3`` and ``m / 2`` control
    points for ``m`` vertices) oscillated on the uneven vertex spacing of
    sparse branches, and the radius/axis refit (:func:`sylva.core.qsm.refit_radii`)
    corrects the zigzag of the interpolating curve instead.
    """
    from scipy.interpolate import splev, splprep
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    keep = np.r_[True, seg > 1e-6]
    pts = pts[keep]
    if len(pts) < 2:
        return pts, np.zeros(len(pts))
    u = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))]
    u = u / u[-1]
    kdeg = min(3, len(pts) - 1)
    uu = np.linspace(0, 1, max(2, samples))
    try:
        tck, _ = splprep(pts.T, u=u, k=kdeg, s=0.0)
        return np.stack(splev(uu, tck), axis=1), uu
    except Exception:  # scipy raises for degenerate inputs; fall back to the polyline
        return np.stack([np.interp(uu, u, pts[:, j]) for j in range(3)], axis=1), uu


def _trim_in_parent(v: np.ndarray, rv: np.ndarray, pv: np.ndarray, prv: np.ndarray):
    """Cut the start of a branch that runs inside its parent's tube (not in Yan et al.).

    On a stem much thicker than the clusters, the shortest-path tree (§3.2)
    often reaches a side branch through a second chain of clusters on the
    other side of the bark, parallel to the trunk's own chain; Algorithm 3.1
    then makes that chain the start of the branch, and its cylinders lie
    inside the trunk (doubling its volume).  The branch is made to leave from
    the parent's centre line at its last vertex inside the parent's surface
    (ratio of distance to the parent's centre line over the parent's radius
    there <= 1): that vertex is replaced by its projection on the parent line
    and the vertices before it are dropped.  A branch entirely inside is kept.
    """
    ratio = tube_ratio(v, pv, prv)
    out = np.flatnonzero(ratio > 1.0)
    if len(out) == 0 or out[0] <= 1:
        return v, rv
    j = int(out[0]) - 1            # last vertex inside before the branch leaves the parent
    if len(pv) < 2:
        foot = pv[0]
    else:
        a, b = pv[:-1], pv[1:]
        ab = b - a
        t = np.clip(((v[j] - a) * ab).sum(1) / np.maximum((ab * ab).sum(1), 1e-18), 0, 1)
        cand = a + t[:, None] * ab
        foot = cand[int(np.argmin(np.linalg.norm(cand - v[j], axis=1)))]
    return np.vstack([foot[None], v[j + 1:]]), np.r_[rv[j + 1], rv[j + 1:]]


def model_branches(seg: Segmentation, st: BranchStructure, samples: int = 30, radius: str = "bounding",
                   trim: bool = True):
    """Yan §4: per branch the skeleton vertices (fork centre, junctions and centres, tip
    junction), a cubic B-spline through them sampled at ``samples`` points, radii
    interpolated linearly from the bounding cylinders.  With ``trim`` a branch's
    vertices inside its parent's tube are cut (:func:`_trim_in_parent`).  Returns
    (curves, radii, vertices, vertex_radii)."""
    curves, radii, verts, vrad = [], [], [], []
    own_r = []
    for bi, chain in enumerate(st.branches):
        own = chain if st.branch_parent[bi] < 0 else chain[1:]
        r_own = _vertex_radii(seg, own, radius)
        pb = int(st.branch_parent[bi])
        if pb >= 0:   # a branch is never thicker than its parent at the fork
            pch = st.branches[pb] if st.branch_parent[pb] < 0 else st.branches[pb][1:]
            j = pch.index(chain[0]) if chain[0] in pch else 0
            r_own = np.minimum(r_own, own_r[pb][min(j, len(own_r[pb]) - 1)])
        own_r.append(r_own)
        v, rv = [], []
        if st.branch_parent[bi] < 0:
            v.append(st.junction[own[0]])
            rv.append(r_own[0])
        else:
            v.append(st.centre[chain[0]])     # leaves from the fork cluster's centre
            rv.append(r_own[0])
        for j, c in enumerate(own):
            if j > 0 or st.branch_parent[bi] >= 0:
                v.append(st.junction[c])
                rv.append(r_own[j] if j == 0 else (r_own[j] + r_own[j - 1]) / 2)
            v.append(st.centre[c])
            rv.append(r_own[j])
        last = own[-1]
        if np.all(np.isfinite(st.tip[last])):
            v.append(st.tip[last])
            rv.append(r_own[-1])
        v = np.asarray(v)
        rv = np.asarray(rv)
        if pb >= 0 and trim and len(v) > 2:
            v, rv = _trim_in_parent(v, rv, verts[pb], vrad[pb])
        verts.append(v)
        vrad.append(rv)
        n_s = max(samples, 2) if len(v) > 2 else 2
        curve, uu = _fit_bspline(v, n_s)
        s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(v, axis=0), axis=1))]
        s = s / s[-1] if s[-1] > 0 else np.linspace(0, 1, len(v))
        curves.append(curve)
        radii.append(np.interp(uu, s, rv) if len(uu) == len(curve) else np.full(len(curve), rv.mean()))
    return curves, radii, verts, vrad
