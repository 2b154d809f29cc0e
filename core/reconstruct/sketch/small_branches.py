"""Small branches by self-similarity: the sketch paper §6 (Eq. 8, Fig. 16, Table 1).

:func:`grow_small_branches` copies the first σ·k nodes of a parent branch at its buds, at angles θ to
the parent and φ to the previous sub-branch, removes crowded buds and cuts the nodes that leave the
crown silhouettes (an even-odd point-in-polygon test in numpy).
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

from ...progress import CancelCheck, check
from ..model import Skeleton
from .params import SketchTree
from .strokes import vertices_xy


# --------------------------------------------------------------------------- §6 small branches

def _rings(poly) -> np.ndarray:
    """All ring edges (e, 4) x0, y0, x1, y1 of a (multi)polygon."""
    import shapely

    edges = []
    for part in shapely.get_parts(poly):
        if part.geom_type != "Polygon":
            continue
        for ring in [part.exterior, *part.interiors]:
            c = vertices_xy(ring)
            edges.append(np.column_stack([c[:-1], c[1:]]))
    return np.vstack(edges) if edges else np.zeros((0, 4))


def _inside(poly, x: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Points (x, z) inside a (multi)polygon (or its ring edges from :func:`_rings`) by the
    even-odd rule, in numpy.

    Not ``shapely.contains_xy``: inside QGIS the system GEOS (3.11) is loaded first and that
    call (GEOS >= 3.12) crashes the process."""
    if poly is None:
        return np.ones(len(x), dtype=bool)
    e = poly if isinstance(poly, np.ndarray) else _rings(poly)
    x = np.asarray(x, dtype=np.float64)[:, None]
    z = np.asarray(z, dtype=np.float64)[:, None]
    x0, y0, x1, y1 = (e[:, i][None, :] for i in range(4))
    crosses = (y0 > z) != (y1 > z)
    with np.errstate(divide="ignore", invalid="ignore"):
        xc = x0 + (z - y0) * (x1 - x0) / (y1 - y0)
    return ((crosses & (x < xc)).sum(axis=1) % 2) == 1


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _perp_frame(t: np.ndarray):
    ref = np.array([0.0, 0.0, 1.0]) if abs(t[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = _cross(t, ref)
    e1 /= np.linalg.norm(e1)
    e2 = _cross(t, e1)
    return e1, e2


def _rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector a onto unit vector b (Rodrigues)."""
    v = _cross(a, b)
    c = float(a @ b)
    if c < -1 + 1e-9:
        e1, _ = _perp_frame(a)
        return 2.0 * np.outer(e1, e1) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def grow_small_branches(skeleton: Skeleton, method: SketchTree = SketchTree(), front_silhouette=None,
                        side_silhouette=None, crown_base_z: Optional[float] = None,
                        height_m: Optional[float] = None, cancelled: CancelCheck = None):
    """Self-similar small branches (§6, Eq. 8, Fig. 16, Table 1) added to ``skeleton``.

    Parents η are the chains of :func:`sylva.core.geometry.branches` (then, for
    ``levels`` = 2, the new sub-branches).  At each bud S_x (``buds_per_branch``
    evenly spread along η, above ``crown_base_z`` on the trunk, with a random
    shift), a sub-branch copies η's first σ·k nodes, rotated so its chord makes
    angle θ with η's tangent at S_x (cos θ drawn in [cos_theta1, cos_theta2])
    and angle φ with the previous sub-branch of η (cos φ in [cos_phi1, cos_phi2],
    up to 16 draws).  Buds with more than ``crowd_max`` small-branch nodes within
    ``crowd_radius_fraction`` × height are removed.  Nodes are projected on the
    x–z plane (``front_silhouette``, shapely polygon) and on the y–z plane
    (``side_silhouette``); a sub-branch is cut before its first node outside
    either (§6 pruning).  Returns (new Skeleton, level per node: 0 = input).
    """
    from scipy.spatial import cKDTree

    from ...geometry import branches

    rng = np.random.default_rng(method.seed)
    front_silhouette = None if front_silhouette is None else _rings(front_silhouette)
    side_silhouette = None if side_silhouette is None else _rings(side_silhouette)
    nodes = [np.asarray(skeleton.nodes, dtype=np.float64)]
    parent = [np.asarray(skeleton.parent, dtype=np.int64)]
    level = [np.zeros(len(skeleton), dtype=np.int64)]
    total = len(skeleton)
    if total < 2 or method.levels == 0 or method.buds_per_branch == 0:
        return skeleton, level[0]
    base = skeleton.nodes
    h = float(height_m) if height_m else float(np.ptp(base[:, 2]))
    crowd_r = method.crowd_radius_fraction * max(h, 1e-9)
    chains = [np.asarray(c) for c in branches(skeleton)]
    all_nodes = base.copy()
    small_pts = np.zeros((0, 3))
    lo_c, hi_c = sorted((method.cos_theta1, method.cos_theta2))
    for lev in range(1, method.levels + 1):
        check(cancelled)
        new_chains = []
        for ci, chain in enumerate(chains):
            k = len(chain)
            if k < 3:
                continue
            pts = all_nodes[chain]
            m = max(2, int(round(method.sigma * k)))
            piece = pts[:m] - pts[0]
            chord = piece[-1]
            if np.linalg.norm(chord) < 1e-9:
                continue
            chord = chord / np.linalg.norm(chord)
            # buds: evenly spaced with a random shift, not at the first or last node
            nb = method.buds_per_branch
            pos = (np.arange(nb) + rng.uniform(0.25, 0.75, nb)) / nb * (k - 1)
            xs = np.unique(np.clip(np.round(pos).astype(int), 1, k - 2))
            if lev == 1 and ci == 0 and crown_base_z is not None:
                xs = xs[pts[xs, 2] >= crown_base_z]
            prev_dir = None
            kd = cKDTree(small_pts) if len(small_pts) else None
            inside = (_inside(front_silhouette, pts[xs, 0], pts[xs, 2])
                      & _inside(side_silhouette, pts[xs, 1], pts[xs, 2]))
            for x in xs[inside]:
                s = pts[x]
                if kd is not None:
                    if len(kd.query_ball_point(s, crowd_r)) > method.crowd_max:
                        continue
                t = pts[min(x + 1, k - 1)] - pts[x - 1]
                t = t / max(np.linalg.norm(t), 1e-12)
                e1, e2 = _perp_frame(t)
                d = None
                for _ in range(16):
                    ct = rng.uniform(lo_c, hi_c)
                    st = math.sqrt(max(0.0, 1 - ct * ct))
                    psi = rng.uniform(0, 2 * math.pi)
                    cand = ct * t + st * (math.cos(psi) * e1 + math.sin(psi) * e2)
                    d = cand
                    if prev_dir is None:
                        break
                    cphi = float(cand @ prev_dir)
                    if method.cos_phi1 <= cphi <= method.cos_phi2:
                        break
                prev_dir = d
                new = s + piece[1:] @ _rotation(chord, d).T
                ok = _inside(front_silhouette, new[:, 0], new[:, 2]) & _inside(side_silhouette, new[:, 1], new[:, 2])
                bad = np.flatnonzero(~ok)
                keep = int(bad[0]) if len(bad) else len(new)
                if keep < 1:
                    continue
                new = new[:keep]
                first = total
                idx = np.arange(first, first + keep)
                par = np.r_[chain[x], idx[:-1]]
                nodes.append(new)
                parent.append(par)
                level.append(np.full(keep, lev, dtype=np.int64))
                total += keep
                all_nodes = np.vstack([all_nodes, new])
                small_pts = np.vstack([small_pts, new])
                if keep >= 2:
                    new_chains.append(np.r_[chain[x], idx])
        chains = new_chains
        if not chains:
            break
    sk = Skeleton(np.vstack(nodes), np.concatenate(parent),
                  is_added=np.r_[skeleton.is_added, np.zeros(total - len(skeleton), bool)])
    return sk, np.concatenate(level)
