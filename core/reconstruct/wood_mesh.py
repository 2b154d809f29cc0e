"""The wood mesh of a dense model fitted to a scan (:class:`sylva.core.reconstruct.levelset.LevelSetQSM`):
its centre lines (:func:`fitted_mesh_lines`: the stem's fitted tubes and the fine branches beside them),
tubes no point is nearest to left out (:func:`prune_redundant`), centre lines simplified
(:func:`simplify_lines`), the tubes swept with the fewest sides their chord tolerance allows
(:func:`tube_mesh`).
All Sylva, not in the papers (see the levelset module docstring); ``benchmarks/dense.py`` measures it.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["fitted_mesh_lines", "prune_redundant", "simplify_lines", "ROUND_RADIUS_M", "ROUND_SIDES",
           "polygon_sides", "mean_radius_factor", "tube_mesh"]


def _line_samples(curves, radii, step_m: float = 0.01):
    """Points every ``step_m`` along centre lines and the radius there (linear between vertices)."""
    pts, rad = [], []
    for c, r in zip(curves, radii):
        seg = np.linalg.norm(np.diff(c, axis=0), axis=1)
        s = np.r_[0.0, np.cumsum(seg)]
        t = np.arange(0.0, s[-1] + 1e-9, step_m)
        pts.append(np.stack([np.interp(t, s, c[:, j]) for j in range(3)], 1))
        rad.append(np.interp(t, s, r))
    return np.vstack(pts), np.concatenate(rad)


def fitted_mesh_lines(structure, nodes: dict, fine_branches, fine: dict, xyz: np.ndarray, thick_m: float,
                      cover_m: float, cover_share: float):
    """Centre lines of the wood mesh (Sylva, measured by benchmarks/dense.py): one tube per run of the
    structure's cross-sections that got a circle fit and are at least ``thick_m`` thick (a stem section
    fitted from its points, radius from its circle), and the fine level's branches of which more than
    ``cover_share`` of the points lie farther than ``cover_m`` from those tubes' surface.  A thick stem
    no longer falls apart into the fine level's parallel thin tubes (one per arc of its bark) where its
    circles are fitted; elsewhere (twigs, stems seen on too short an arc for a circle) the fine level's
    tubes follow the points.  Fully scanned synthetic trees: surface -> points 3.4 / 4.1 cm -> 1.3 / 1.5 cm,
    points -> surface 0.82 / 0.88 -> 0.67 / 0.84 cm, a quarter to a third of the vertices.  The lines are
    then simplified (6 mm + 0.4 radius off the chord, radius within 0.4 of the neighbours': TLS tree7 about
    5 % fewer vertices for 0.01 cm of points -> surface) and the tubes no point needs left out
    (:func:`prune_redundant`)."""
    sc, sr, _, _, _, schains = structure
    fc, fr, _, _, _, fchains = fine_branches
    good = nodes["fitted"] & (nodes["radius"] >= thick_m)
    curves, radii = [], []
    for c, r, ch in zip(sc, sr, schains):
        idx = np.flatnonzero(good[ch])
        if len(idx) < 2:
            continue
        for run in np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1):
            if len(run) >= 2:                       # curve vertex k + 1 is the chain's node k
                curves.append(c[run + 1])
                radii.append(r[run + 1])
    lab = fine["label"]
    ok = lab >= 0
    m = len(fine["centre"])
    if curves:
        pts, rad = _line_samples(curves, radii)
        d, j = cKDTree(pts).query(xyz, k=min(8, len(pts)))
        d, j = d.reshape(len(xyz), -1), j.reshape(len(xyz), -1)
        far_pt = np.abs(d - rad[j]).min(axis=1) > cover_m
        far = np.bincount(lab[ok], weights=far_pt[ok].astype(float), minlength=m) / np.maximum(
            np.bincount(lab[ok], minlength=m), 1)
        lens = np.array([len(ch) for ch in fchains], dtype=np.int64)
        sums = np.bincount(np.repeat(np.arange(len(fchains)), lens), minlength=len(fchains),
                           weights=far[np.concatenate(fchains)] if len(fchains) else None)
        keep = np.flatnonzero(sums > cover_share * lens).tolist()      # the chain's mean share above cover_share
    else:
        keep = range(len(fc))
    curves += [fc[k] for k in keep]
    radii += [fr[k] for k in keep]
    curves, radii = simplify_lines(curves, radii, tolerance_m=0.006, rel=0.4, passes=8)
    return prune_redundant(curves, radii, xyz)


def prune_redundant(curves, radii, xyz: np.ndarray, cost_m: float = 0.0, step_m: float = 0.02, k: int = 16):
    """Leave out the tubes the points do not need (Sylva, measured by benchmarks/dense.py): every point is
    served by the tube whose surface is nearest (distance to the centre line sampled every ``step_m``,
    less the radius there), and a tube goes when serving its points by their next-nearest tube instead
    moves them by at most ``cost_m`` in all (a tube nested in a thicker one, a second tube along the
    same branch, a tube no point is nearest to).  Cheapest first; a tube that takes over the points of
    a dropped one is kept.  The default ``cost_m`` 0 drops only the tubes that serve no point (TLS trees
    1 / 7 / 13: about 190 / 110 / 100 of 2,000 / 1,500 / 1,900 tubes, points -> surface unchanged).
    Samples every 2 cm rather than 1 cm: the same points -> surface within 0.005 cm, vertices within
    1.1 %, a quarter less time for the whole tree on tree13.  Returns the kept (curves, radii)."""
    nt = len(curves)
    if nt < 2 or not len(xyz):
        return curves, radii
    # samples every ``step_m`` along every segment (and its end), all tubes at once
    lens = np.array([len(c) for c in curves])
    cp, cr = np.concatenate(curves), np.concatenate(radii)
    lid = np.repeat(np.arange(nt), lens)
    seg = np.flatnonzero(lid[:-1] == lid[1:])
    ns = np.maximum(1, np.ceil(np.linalg.norm(cp[seg + 1] - cp[seg], axis=1) / step_m).astype(np.int64))
    si = np.repeat(seg, ns)
    f = (np.arange(len(si)) - np.repeat(np.cumsum(ns) - ns, ns)) / np.repeat(ns, ns)
    ends = np.r_[seg[1:][lid[seg[1:]] != lid[seg[:-1]]], seg[-1:]] if len(seg) else seg
    pts = np.vstack([cp[si] + f[:, None] * (cp[si + 1] - cp[si]), cp[ends + 1]])
    rad = np.r_[cr[si] + f * (cr[si + 1] - cr[si]), cr[ends + 1]]
    tid = np.r_[lid[si], lid[ends + 1]]
    # candidates: the nearest centre-line samples, and those of the thick tubes (whose axes lie farther
    # from their own points than a twig's)
    kk = min(k, len(pts))
    d, j = cKDTree(pts).query(xyz, k=kk, workers=-1)
    d, j = d.reshape(len(xyz), -1), j.reshape(len(xyz), -1)
    thick = np.flatnonzero(rad >= 0.03)
    if len(thick):
        k2 = min(4, len(thick))
        d2, j2 = cKDTree(pts[thick]).query(xyz, k=k2, workers=-1)
        d = np.hstack([d, d2.reshape(len(xyz), -1)])
        j = np.hstack([j, thick[j2.reshape(len(xyz), -1)]])
    sd = np.abs(d - rad[j])
    t = tid[j]
    o = np.argsort(sd, axis=1)
    sd, t = np.take_along_axis(sd, o, 1), np.take_along_axis(t, o, 1)
    best, d1 = t[:, 0], sd[:, 0]
    other = t != best[:, None]
    has = other.any(axis=1)
    col = np.argmax(other, axis=1)
    rows = np.arange(len(xyz))
    second = np.where(has, t[rows, col], -1)
    d2 = np.where(has, sd[rows, col], np.inf)
    cost = np.bincount(best, weights=np.minimum(d2 - d1, 1e3), minlength=nt)
    keep = np.ones(nt, dtype=bool)
    protected = np.zeros(nt, dtype=bool)
    order = np.argsort(cost, kind="stable")
    served = np.argsort(best, kind="stable")                # the points of tube b: served[start[b]:start[b + 1]]
    start = np.r_[0, np.cumsum(np.bincount(best, minlength=nt))]
    for b in order[cost[order] <= cost_m]:
        if protected[b]:
            continue
        sec = second[served[start[b]:start[b + 1]]]
        if (sec < 0).any() or (~keep[sec]).any():
            continue
        keep[b] = False
        protected[sec] = True
    idx = np.flatnonzero(keep)
    return [curves[i] for i in idx], [radii[i] for i in idx]


def simplify_lines(curves, radii, tolerance_m: float = 0.003, rel: float = 0.25, passes: int = 4):
    """Drop interior centre-line points that lie within ``tolerance_m`` + ``rel`` × radius of the chord of
    their neighbours and whose radius is within ``rel`` of their neighbours' mean (every other candidate
    per pass; Sylva: a lighter mesh with the same surface to a few millimetres)."""
    out_c, out_r = [], []
    pts = np.concatenate(curves) if curves else np.zeros((0, 3))
    rad = np.concatenate(radii) if radii else np.zeros(0)
    off = np.r_[0, np.cumsum([len(c) for c in curves])]
    keep = np.ones(len(pts), dtype=bool)
    for _ in range(passes):
        idx = np.flatnonzero(keep)
        lid = np.searchsorted(off, idx, side="right") - 1
        inner = np.r_[False, (lid[1:-1] == lid[:-2]) & (lid[1:-1] == lid[2:]), False] if len(idx) > 2 \
            else np.zeros(len(idx), bool)
        i = np.flatnonzero(inner)
        if not len(i):
            break
        a, p, b = pts[idx[i - 1]], pts[idx[i]], pts[idx[i + 1]]
        ab = b - a
        t = np.clip(((p - a) * ab).sum(1) / np.maximum((ab * ab).sum(1), 1e-18), 0, 1)
        dev = np.linalg.norm(a + t[:, None] * ab - p, axis=1)
        rm = (rad[idx[i - 1]] + rad[idx[i + 1]]) / 2
        cand = (dev <= tolerance_m + rel * rad[idx[i]]) & (np.abs(rad[idx[i]] - rm) <= rel * np.maximum(rad[idx[i]], 1e-3))
        ci = i[cand]
        if not len(ci):
            break
        take = np.r_[True, np.diff(ci) > 1]        # no two neighbours in one pass
        keep[idx[ci[take]]] = False
    for k in range(len(curves)):
        m = keep[off[k]:off[k + 1]]
        out_c.append(curves[k][m])
        out_r.append(radii[k][m])
    return out_c, out_r


#: With a chord tolerance, a tube at least this thick (m) keeps at least ROUND_SIDES sides however coarse
#: the tolerance (LOD 0 on a sparse scan, :attr:`LevelSetQSM.chord_spacing`): stems and limbs stay round
#: to the eye (Sylva; TLS trees 1 / 7 / 13 at LOD 0: 14,041 / 12,116 / 11,993 -> 14,123 / 12,116 / 13,320
#: vertices, points -> surface 0.85 / 0.61 / 2.08 -> 0.85 / 0.61 / 2.10 cm; tree13's stems were
#: triangles and squares).
ROUND_RADIUS_M = 0.10
ROUND_SIDES = 6


def polygon_sides(radius_m, tolerance_m: float, most: int) -> np.ndarray:
    """Fewest sides (3 to ``most``) of a regular polygon of circumradius ``radius_m`` whose chord error
    ``r (1 - cos(pi / n))`` is at most ``tolerance_m``."""
    r = np.maximum(np.asarray(radius_m, dtype=np.float64), 1e-9)
    c = np.clip(1.0 - tolerance_m / r, -1.0, 1.0)
    n = np.ceil(np.pi / np.maximum(np.arccos(c), 1e-9) - 1e-9)
    return np.clip(n, 3, max(3, int(most))).astype(np.int64)


def mean_radius_factor(sides) -> np.ndarray:
    """Mean distance from the centre to the boundary of a regular ``sides``-gon of circumradius 1: a polygon
    of circumradius ``r / factor`` is on average as far from its axis as the circle of radius ``r``."""
    h = np.pi / np.asarray(sides, dtype=np.float64)
    return np.cos(h) / h * np.log(1.0 / np.cos(h) + np.tan(h))


def tube_mesh(curves, radii, sides: int = 10, twig_sides: int = 6, twig_radius_m: float = 0.03,
              thin_sides: int = 3, thin_radius_m: float = 0.008, tolerance_m=None, match: bool = False,
              pointed_m: float = 0.0):
    """(vertices, faces) of all branch tubes (RMF frames, each end closed by a fan of its own ring, no
    centre vertex).  Sides per tube: with ``tolerance_m``, the fewest (3 to ``sides``) whose chord error at
    the tube's largest radius is at most ``tolerance_m`` (:func:`polygon_sides`), at least
    :data:`ROUND_SIDES` from :data:`ROUND_RADIUS_M` up; otherwise ``sides`` for
    branches whose largest radius reaches ``twig_radius_m``, ``twig_sides`` for thinner ones,
    ``thin_sides`` under ``thin_radius_m``.  ``match``: the polygon's circumradius is scaled so that its
    mean distance to the axis is the fitted radius (:func:`mean_radius_factor`: the polygon's surface is
    on average where the circle's is, not inside it).  Tubes thinner than ``pointed_m`` (largest radius) start at a
    point, their centre line's first point, not a ring (a twig's base, inside its parent: a cone to the
    twig's second ring).  Sylva: the polygon is finer where it is seen."""
    from ..geometry import dedupe, tube_batch

    vs, fs, nv = [], [], 0
    rmax = np.array([float(np.max(r)) if len(r) else 0.0 for r in radii])
    if tolerance_m is not None:
        per = polygon_sides(rmax, float(tolerance_m), sides)
        per = np.where(rmax >= ROUND_RADIUS_M, np.maximum(per, min(ROUND_SIDES, sides)), per)
        groups = [(np.flatnonzero((per == s) & (rmax >= pointed_m)), int(s)) for s in np.unique(per)]
        groups += [(np.flatnonzero((per == s) & (rmax < pointed_m)), -int(s)) for s in np.unique(per)]
    else:
        groups = [(np.flatnonzero((lo <= rmax) & (rmax < hi) & (rmax >= pointed_m)), s) for lo, hi, s in
                  ((twig_radius_m, np.inf, sides), (thin_radius_m, twig_radius_m, twig_sides),
                   (-1.0, thin_radius_m, thin_sides))]
        groups += [(np.flatnonzero((lo <= rmax) & (rmax < hi) & (rmax < pointed_m)), -s) for lo, hi, s in
                   ((twig_radius_m, np.inf, sides), (thin_radius_m, twig_radius_m, twig_sides),
                    (-1.0, thin_radius_m, thin_sides))]
    for sel, s in groups:
        sel = [k for k in sel if len(curves[k]) >= 2]
        if not sel:
            continue
        pointed = s < 0                      # (a negative side count marks the pointed group)
        s = max(3, abs(int(s)))
        pts = np.concatenate([curves[k] for k in sel])
        rad = np.concatenate([radii[k] for k in sel])
        if match:
            rad = rad / float(mean_radius_factor(s))
        off = np.r_[0, np.cumsum([len(curves[k]) for k in sel])]
        pts, rad, off, _ = dedupe(pts, rad, off)
        if len(pts) == 0:
            continue
        v, f, _ = tube_batch(pts, rad, off, s, False)
        n = len(pts)
        lines = np.flatnonzero(np.diff(off) >= 2)
        if len(lines):
            # the ends: a fan from each end ring's first corner (the ring is a planar convex polygon)
            j = np.arange(1, s - 1)[:, None]
            first, last = off[lines][None], (off[lines + 1] - 1)[None]
            caps = [np.stack([np.broadcast_to(last, (s - 2, len(lines))), j * n + last,
                              (j + 1) * n + last], -1).reshape(-1, 3)]
            if not pointed:
                caps.append(np.stack([np.broadcast_to(first, (s - 2, len(lines))), (j + 1) * n + first,
                                      j * n + first], -1).reshape(-1, 3))
            f = np.concatenate([f] + caps)
        if pointed and len(lines):
            # every corner of the first ring becomes its centre: the side quads there turn into triangles
            start = off[lines]
            v[start] = pts[start]
            remap = np.arange(len(v))
            remap[(np.arange(1, s)[:, None] * n + start[None]).ravel()] = np.tile(start, s - 1)
            f = remap[f]
            f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
            used = np.zeros(len(v), dtype=bool)
            used[f.ravel()] = True
            new = np.cumsum(used) - 1
            v, f = v[used], new[f]
        vs.append(v)
        fs.append(f + nv)
        nv += len(v)
    if not vs:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    return np.vstack(vs), np.vstack(fs)
