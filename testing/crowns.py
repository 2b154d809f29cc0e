"""Stands of crowns of every form: broadleaf crowns made of leaf clumps, mixed stands, suppressed trees.

:mod:`sylva.testing.synth` draws a broadleaf crown as one smooth ellipsoid and a
conifer as one cone.  Real broadleaf crowns are neither smooth nor single: the
foliage sits in clumps (shoots, branch systems) concentrated in the outer shell
of the crown, with gaps between branch systems, and an old or open-grown tree
often has several leaders, each carrying its own part of the crown.  This
module grows such crowns on top of ``synth``'s terrain, stem placement and
scan simulator (the same ray caster: every clump is one of its ellipsoids), so
a stand here has the same kind of truth (a tree per point, stem base, height,
crown radius) as ``synth``'s.

Forestry sources (the generator is written from them, not from the segmenter):

* **Crown envelope.** The crown is a solid of revolution around the stem
  whose radius at relative crown depth ``u`` (0 at the crown base, 1 at the
  top) is ``r(u) = R * (1 - |(u - u_w) / s|^p)^(1/p)``, ``s`` the distance from
  the widest point ``u_w`` to the top (above it) or the base (below): the
  exponent family of crown-envelope models (Biging & Wensel 1990, "Estimation
  of crown form for six conifer species of northern California", Can. J. For.
  Res. 20:1137-1142; Pretzsch 2009, *Forest Dynamics, Growth and Yield*,
  Springer, ch. 8: crown shape from conical via paraboloid and ellipsoid to
  cylinder as the exponent grows).  Forms: ``round`` (ellipsoid, ``u_w`` 0.5,
  ``p`` 2), ``flat`` (flat-topped / umbrella crowns of old broadleaves and
  open-grown trees: widest at ``u_w`` 0.75, ``p`` 4 above it), ``cylinder``
  (columnar crowns, ``p`` 6, a narrower radius).
* **Crown width and length.** Radius and crown ratio come from ``synth``'s
  allometry (crown radius linear in height by species group, Pretzsch 2009);
  columnar crowns are 0.6x as wide and 1.2x as long, flat crowns 1.15x as wide
  and 0.8x as long.
* **Leaders.** 1 leader (60 %), 2 (30 %) or 3 (10 %) for round and flat
  crowns: each leader carries a sub-crown of 0.55-0.7 of the radius, offset so
  that together they fill the crown, its top 0.88-1.0 of the tree's height
  (co-dominant stems of open-grown broadleaves; Pretzsch 2009).
* **Clumped foliage.** A crown is a set of leaf clumps (Cescatti 1997,
  "Modelling the radiative transfer in discontinuous canopies of asymmetric
  crowns", Ecol. Model. 101:263-274; clumping as in Nilson 1971): ellipsoids
  of radius 0.12 R (0.35-1.0 m, +/- 30 %), 80 % of them in the outer shell
  of the envelope (the foliage of broadleaves lies mostly in the outer
  metre or two of the crown: Horn 1971, *The Adaptive Geometry of Trees*,
  Princeton), 20 % inside, numbered to cover 0.8 of the envelope's lateral
  surface, so the surface is rough and has holes.  One or two *gaps* (branch
  systems missing: cones of 35 degrees half-width around a random direction)
  remove 90 % of the clumps in them.  A terminal clump stands at each leader's
  apex (apical dominance: the top of a leader is its terminal shoot).
* **Suppressed trees.** In a stand with ``suppressed`` > 0 that share of the
  dominant trees has a suppressed neighbour standing at 0.7-1.1 of its crown
  radius, 45-65 % of its height, with a round clumped crown partly under the
  dominant's (understorey trees of a two-storey stand).

* **Open-grown crowns.** A tree grown without neighbours (park, pasture,
  street, field edge) keeps its lower branches and spreads: at a given size
  its crown is much wider than a forest-grown tree's (Hasenauer 1997,
  "Dimensional relationships of open-grown trees in Austria", For. Ecol.
  Manage. 96:197-206, the open-grown crown widths behind the crown
  competition factor).  The suburban park of ``autzen_trim.laz`` has
  isolated round crowns of 4.6-7 m radius on trees 10-18 m high (about 2-3.5 x
  the forest allometry's radius at their height).  ``"parkland"`` crowns are
  the broadleaf crowns above with :data:`OPEN_GROWN_SCALE` x the radius.

Stands: ``"broadleaf"`` (all broadleaf clumped crowns, 40 % round, 30 %
flat, 30 % columnar), ``"mixed"`` (40 % conifers of ``synth``'s cones, 60 %
broadleaves as above, 15 % of the dominant trees with a suppressed
neighbour), each ``"open"``, ``"medium"`` or ``"dense"`` as ``synth``'s presets
(120 / 250 / 400 stems per ha, crowns overlapping 0 / 0.5 / 1);
``"parkland"`` (open-grown broadleaves, the same three structures with
:data:`OPEN_GROWN_SCALE`² fewer stems, so that the canopy covers as much
ground: 19 / 40 / 64 stems per ha, lone trees to touching groups);
``"tall"`` (the mixed stand with trees :data:`TALL_HEIGHT_M` high instead of
8-30 m: temperate rainforest conifers, tall eucalypts, old beech and oak
stands, whose heights the other stands never reach).
"""
from __future__ import annotations

import dataclasses
import math
from typing import Tuple

import numpy as np
from scipy.spatial import cKDTree

from . import synth
from ..core.errors import InputError

__all__ = ["KINDS", "STRUCTURES", "FORMS", "suite_stand", "suite_preset", "crown_forms"]

KINDS = ("broadleaf", "mixed", "parkland", "tall")
STRUCTURES = ("open", "medium", "dense")
FORMS = ("round", "flat", "cylinder")

_CONE, _ELLIPSOID, _CYLINDER = synth._CONE, synth._ELLIPSOID, synth._CYLINDER

#: (u_w, exponent above, exponent below, radius factor, crown length factor) per form.
_ENVELOPE = {
    "round": (0.5, 2.0, 2.0, 1.0, 1.0),
    "flat": (0.75, 4.0, 2.0, 1.15, 0.8),
    "cylinder": (0.5, 6.0, 6.0, 0.6, 1.2),
}
_FORM_WEIGHTS = (0.4, 0.3, 0.3)
_LEADERS = ((1, 0.6), (2, 0.3), (3, 0.1))
_SHELL_SHARE = 0.8
_COVERAGE = 0.8
_GAP_HALF_ANGLE = math.radians(35.0)

#: Crown radius of an open-grown broadleaf / a forest-grown one of the same height (2.5: a crown
#: 0.9 x as wide as the tree is high at 15 m, 0.8 x at 30 m, as autzen_trim.laz's park trees).
OPEN_GROWN_SCALE = 2.5

#: Heights (m) of the trees of the "tall" stands, and of the others.
TALL_HEIGHT_M = (30.0, 60.0)
HEIGHT_M = (8.0, 30.0)


def _profile(u: np.ndarray, form: str) -> np.ndarray:
    """Relative envelope radius r(u)/R at relative crown depth u (0 base, 1 top)."""
    uw, p_up, p_lo = _ENVELOPE[form][:3]
    u = np.clip(np.asarray(u, dtype=np.float64), 0.0, 1.0)
    up = u >= uw
    t = np.where(up, (u - uw) / (1.0 - uw), (uw - u) / uw)
    p = np.where(up, p_up, p_lo)
    return np.clip(1.0 - t ** p, 0.0, 1.0) ** (1.0 / p)


def _clumps(rng, cx, cy, base, top, radius, form):
    """Leaf clumps (cx, cy, zc, a, c) of one (sub-)crown envelope."""
    length = max(top - base, 0.5)
    a0 = float(np.clip(0.12 * radius, 0.35, 1.0))
    # lateral surface of the envelope ~ 2 pi R L mean(r(u)); clumps of area pi a^2 cover _COVERAGE of it
    uu = np.linspace(0.0, 1.0, 101)
    mean_r = float(_profile(uu, form).mean())
    n = max(6, int(round(_COVERAGE * 2.0 * math.pi * radius * length * mean_r / (math.pi * a0 * a0))))
    # heights weighted by the envelope's radius (area of the lateral surface at that depth)
    u = np.empty(0)
    while len(u) < n:
        cand = rng.random(2 * n)
        keep = rng.random(2 * n) < _profile(cand, form)
        u = np.concatenate([u, cand[keep]])
    u = u[:n]
    a = a0 * rng.uniform(0.7, 1.3, n)
    c = a * rng.uniform(0.6, 1.0, n)
    phi = rng.uniform(0.0, 2.0 * math.pi, n)
    r_env = radius * _profile(u, form)
    shell = rng.random(n) < _SHELL_SHARE
    rho = np.where(shell, np.maximum(r_env - a * rng.uniform(0.3, 1.0, n), 0.0),
                   r_env * rng.uniform(0.0, 0.6, n))
    # nothing pokes out of the envelope's upper surface: a clump's top stays below it
    uw, p_up = _ENVELOPE[form][0], _ENVELOPE[form][1]
    rel = np.clip(rho / max(radius, 1e-6), 0.0, 1.0)
    u_top = uw + (1.0 - uw) * (1.0 - rel ** p_up) ** (1.0 / p_up)
    zc = np.minimum(base + u * length, base + u_top * length - c)
    # gaps: one or two missing branch systems
    keep = rng.random(n) >= 0.0
    for _ in range(int(rng.integers(1, 3))):
        g_phi = rng.uniform(0.0, 2.0 * math.pi)
        g_u = rng.uniform(0.2, 0.9)
        dphi = np.abs((phi - g_phi + math.pi) % (2.0 * math.pi) - math.pi)
        du = np.abs(u - g_u) * length / max(radius, 0.5)
        inside = np.hypot(dphi, du) < _GAP_HALF_ANGLE * 1.5
        keep &= ~(inside & (rng.random(n) < 0.9))
    x = cx + rho * np.cos(phi)
    y = cy + rho * np.sin(phi)
    out = np.column_stack([x, y, zc, a, c])[keep]
    # the terminal clump of the leader
    at = a0 * 0.8
    ct = at * 0.8
    return np.vstack([out, [[cx, cy, top - ct, at, ct]]])


def crown_forms(stand: synth.Stand) -> dict:
    """{tree_id: form} of a suite stand ("conifer", "round", "flat", "cylinder", "suppressed")."""
    return dict(getattr(stand, "forms", {}))


def _stem_row(ti, t: synth.TrueTree, tan_slope, stem_top, x_top=None, y_top=None, n_stems=1):
    r_stem = 0.5 * t.dbh_m / math.sqrt(n_stems)
    z_foot = t.ground_z - (r_stem + 0.3) * tan_slope - 0.2
    lx = ly = 0.0
    if x_top is not None:
        span = max(stem_top - z_foot, 1e-6)
        lx, ly = (x_top - t.x) / span, (y_top - t.y) / span
    return (ti, _CYLINDER, t.x, t.y, z_foot, stem_top, r_stem, 0.0, lx, ly)


def suite_stand(kind: str, structure: str, seed: int = 0, width_m: float = 100.0,
                slope_deg: float = 0.0) -> synth.Stand:
    """A stand of the extended suite: ``kind`` in :data:`KINDS`, ``structure`` in :data:`STRUCTURES`,
    on ground sloping ``slope_deg`` degrees (0: level, with synth's gentle relief)."""
    if kind not in KINDS:
        raise InputError(f"unknown suite stand kind {kind!r}; choose one of {', '.join(KINDS)}")
    if structure not in synth._PRESETS:
        raise InputError(f"unknown stand structure {structure!r}; choose one of {', '.join(STRUCTURES)}")
    stems, overlap = synth._PRESETS[structure]
    scale, heights = 1.0, HEIGHT_M
    if kind == "broadleaf":
        species, weights, suppressed = ("broadleaf",), (1.0,), 0.0
    elif kind == "parkland":
        species, weights, suppressed, scale = ("broadleaf",), (1.0,), 0.0, OPEN_GROWN_SCALE
        stems /= scale ** 2
    else:                                   # mixed, and tall: the mixed stand grown taller
        species, weights, suppressed = ("conifer", "broadleaf"), (0.4, 0.6), 0.15
        if kind == "tall":
            heights = TALL_HEIGHT_M
    spec = synth.StandSpec(width_m=width_m, depth_m=width_m, stems_per_ha=stems, species=species,
                           species_weights=weights, height_m=heights, crown_overlap=overlap, slope_deg=slope_deg,
                           seed=seed, crown_scale=scale)
    base = synth.make_stand(spec)
    rng = np.random.default_rng(10_000 + seed)
    tan_slope = math.tan(math.radians(spec.slope_deg))
    trees = list(base.trees)
    # suppressed neighbours of a share of the dominants, where their stems fit
    extra = []
    if suppressed > 0 and trees:
        stems_xy = np.array([[t.x, t.y] for t in trees])
        tree = cKDTree(stems_xy)
        x0, y0 = spec.origin
        for t in trees:
            if rng.random() >= suppressed:
                continue
            phi = rng.uniform(0.0, 2.0 * math.pi)
            d = t.crown_radius_m * rng.uniform(0.7, 1.1)
            x, y = t.x + d * math.cos(phi), t.y + d * math.sin(phi)
            if not (x0 + 1 < x < x0 + width_m - 1 and y0 + 1 < y < y0 + width_m - 1):
                continue
            if tree.query([x, y])[0] < 1.0:
                continue
            h = t.height * rng.uniform(0.45, 0.65)
            if h < 5.0:
                continue
            r = (0.8 + 0.13 * h) * 0.7
            extra.append(synth.TrueTree(
                tree_id=0, species="broadleaf", x=x, y=y, ground_z=float(base.ground_z(x, y)), height=h,
                crown_radius_m=r, crown_base_height_m=max(h * 0.5, 1.5),
                dbh_m=0.01 * float(synth._naslund_dbh_cm(np.array([h]), 2.9, 0.125)[0]), n_stems=1))
    forms = {}
    rows = []
    out_trees = []
    for ti, t in enumerate(trees + extra):
        tid = ti + 1
        H, R, cb = t.height, t.crown_radius_m, t.crown_base_height_m
        if t.species == "conifer":
            top, cbase = t.ground_z + H, t.ground_z + cb
            rows.append((ti, _CONE, t.x, t.y, cbase, top, R, 0.0, 0.0, 0.0))
            rows.append(_stem_row(ti, t, tan_slope, cbase + 0.6 * (H - cb)))
            out_trees.append(dataclasses.replace(t, tree_id=tid))
            forms[tid] = "conifer"
            continue
        is_sup = ti >= len(trees)
        form = "round" if is_sup else FORMS[int(rng.choice(3, p=_FORM_WEIGHTS))]
        forms[tid] = "suppressed" if is_sup else form
        uw, _, _, rf, lf = _ENVELOPE[form]
        R = R * rf
        length = min((H - cb) * lf, H - 1.5)
        cbase = t.ground_z + H - length
        top = t.ground_z + H
        n_lead = 1
        if form != "cylinder" and not is_sup:
            n_lead = int(rng.choice([k for k, _ in _LEADERS], p=[w for _, w in _LEADERS]))
        clumps = []
        if n_lead == 1:
            clumps.append(_clumps(rng, t.x, t.y, cbase, top, R, form))
            rows.append(_stem_row(ti, t, tan_slope, cbase + 0.3 * length))
        else:
            sub_r = R * rng.uniform(0.55, 0.7)
            offset = R - sub_r
            phi0 = rng.uniform(0.0, 2.0 * math.pi)
            for s in range(n_lead):
                phi = phi0 + 2.0 * math.pi * s / n_lead + rng.uniform(-0.3, 0.3)
                sx, sy = t.x + offset * math.cos(phi), t.y + offset * math.sin(phi)
                sub_top = top if s == 0 else t.ground_z + H * rng.uniform(0.88, 1.0)
                sub_top = max(sub_top, cbase + 0.5 * length)
                clumps.append(_clumps(rng, sx, sy, cbase, sub_top, sub_r, form))
                rows.append(_stem_row(ti, t, tan_slope, cbase + 0.2 * length, sx, sy, n_stems=n_lead))
        cl = np.vstack(clumps)
        for x, y, zc, a, c in cl:
            rows.append((ti, _ELLIPSOID, x, y, zc - c, zc + c, a, c, 0.0, 0.0))
        true_h = float((cl[:, 2] + cl[:, 4]).max() - t.ground_z)
        true_r = float((np.hypot(cl[:, 0] - t.x, cl[:, 1] - t.y) + cl[:, 3]).max())
        out_trees.append(dataclasses.replace(t, tree_id=tid, height=true_h, crown_radius_m=true_r,
                                             crown_base_height_m=H - length, n_stems=n_lead))
    names = ("tree", "kind", "cx", "cy", "zb", "zt", "a", "c", "lx", "ly")
    arr = np.array(rows, dtype=np.float64).reshape(-1, len(names))
    parts = {nm: arr[:, i].copy() for i, nm in enumerate(names)}
    parts["tree"] = parts["tree"].astype(np.int64)
    parts["kind"] = parts["kind"].astype(np.int64)
    counts = np.bincount(parts["tree"], minlength=len(out_trees))
    ptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    stand = synth.Stand(spec=spec, trees=out_trees, parts=parts, part_ptr=ptr, _terrain=base._terrain)
    stand.forms = forms
    return stand


def suite_preset(kind: str, structure: str, pulse_density: float, seed: int = 0,
                 width_m: float = 100.0, slope_deg: float = 0.0) -> Tuple[synth.Stand, synth.ScanSpec]:
    """(stand, scan spec) of the extended suite, scanned at ``pulse_density`` pulses/m2."""
    return (suite_stand(kind, structure, seed, width_m, slope_deg),
            synth.ScanSpec(pulse_density=pulse_density, seed=seed))
