"""Synthetic forest stands and an airborne LiDAR scan simulator with ground truth.

Two steps, both deterministic (seeded :func:`numpy.random.default_rng` only):

1. :func:`make_stand` turns a :class:`StandSpec` into a :class:`Stand`: a
   terrain (plane of ``slope_deg`` plus a mild seeded undulation) and a list
   of :class:`TrueTree` (stem base, height, crown radius, crown base height,
   DBH, number of stems) of three crown shapes:

   * ``"conifer"``   one cone (apex at the tree top, base at the crown base);
   * ``"broadleaf"`` one ellipsoid between crown base and tree top;
   * ``"multistem"`` 2 to 4 leaning stems from one base, each carrying its own
     ellipsoidal sub-crown; together they fill ``crown_radius_m``.

   Every stem is a (possibly leaning) cylinder of radius ``dbh/2`` from the
   ground into the crown.

2. :func:`simulate_scan` casts one ray per laser pulse through that scene
   (fully vectorised) and records up to ``max_returns`` echoes per pulse, with
   per-point truth (tree id and kind: ground, stem, crown, noise).

:func:`write_scan` writes the result as a georeferenced LAZ (the truth as the
extra dimensions ``true_tree`` and ``true_kind``) plus a CSV table of the
trees; :func:`read_truth` reads that table back.  :func:`preset` gives the
"open", "medium" and "dense" stands the benchmarks use.

No paper of the project specification (``../shared/papers``) describes a
simulator; the relations used here come from the forestry and LiDAR
literature and are cited where they are used:

* height–diameter: Näslund (1936), ``h = 1.3 + d**2 / (a + b*d)**2`` (d in
  cm, h in m), inverted for d; see Mehtätalo, de-Miguel & Gregoire (2015),
  "Modeling height-diameter curves for prediction", Can. J. For. Res. 45,
  826–837, for its standing as the default h–d model;
* crown radius linear in height and crown ratio (crown length / height) by
  species group, the usual form of crown-width models (Pretzsch 2009,
  *Forest Dynamics, Growth and Yield*, Springer);
* stems placed by a Matérn type-II hard-core process (Matérn 1960; Illian et
  al. 2008, *Statistical Analysis and Modelling of Spatial Point Patterns*,
  Wiley) whose hard-core distance between two trees is
  ``(1 - 0.3*crown_overlap) * (r_i + r_j)``;
* pulses on a jittered grid, rays from an aircraft on the stand's centre
  line; candidate primitives per pulse found by projecting each primitive's
  box from the aircraft onto the pulse grid (see :func:`simulate_scan`);
* a laser beam of finite footprint (``footprint_diameter_m``), first echo at
  the first crown surface the footprint touches, further echoes inside the
  crown as a Poisson process along the beam (a turbid-medium crown: Ross
  1981, *The Radiation Regime and Architecture of Plant Stands*; as in the
  discrete-return simulations of Disney et al. 2010, Remote Sens. Environ.
  114, 1546–1560), a multi-target resolution of
  ``min_echo_separation_m`` between echoes.
"""
from __future__ import annotations

import csv
import io
import math
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, List, Optional, Sequence, Tuple

import numpy as np
from scipy.spatial import cKDTree

from ..core.cloud import PointCloud
from ..core.errors import CRSError, InputError
from ..core.io.las import write_las
from ..core.progress import check, report, scaled

__all__ = [
    "GROUND", "STEM", "CROWN", "NOISE", "KIND_NAMES", "SPECIES",
    "StandSpec", "TrueTree", "Stand", "make_stand",
    "ScanSpec", "Scan", "simulate_scan", "write_scan", "read_truth", "preset",
]

# Per-point truth kinds (``Scan.truth_kind`` and the LAS extra dimension ``true_kind``).
GROUND, STEM, CROWN, NOISE = 0, 1, 2, 3
KIND_NAMES = {GROUND: "ground", STEM: "stem", CROWN: "crown", NOISE: "noise"}

SPECIES = ("conifer", "broadleaf", "multistem")

# Allometry per species group.  Heights in m, DBH in cm (Näslund 1936, see the
# module docstring): h = 1.3 + d^2/(a + b d)^2  <=>  d = a s / (1 - b s), s = sqrt(h - 1.3).
# b = 0.125 puts the asymptote at 1.3 + 1/b^2 = 65 m, above any height allowed.
# Crown radius r = r0 + r1 * h (m); crown ratio (crown length / height) uniform in cr.
_ALLOMETRY = {
    "conifer": dict(naslund_a=2.5, naslund_b=0.125, r0=0.4, r1=0.08, cr=(0.45, 0.75)),
    "broadleaf": dict(naslund_a=2.9, naslund_b=0.125, r0=0.8, r1=0.13, cr=(0.35, 0.60)),
    "multistem": dict(naslund_a=2.7, naslund_b=0.125, r0=0.8, r1=0.15, cr=(0.50, 0.75)),
}
_MAX_HEIGHT_M = 60.0
_MIN_HEIGHT_M = 3.0

# Geometric primitives of a stand (Stand.parts["kind"]).
_CONE, _ELLIPSOID, _CYLINDER = 0, 1, 2

# How high up the crown the stem cylinder reaches, as a fraction of crown length.
_STEM_INTO_CROWN = {"conifer": 0.6, "broadleaf": 0.3, "multistem": 0.2}


# --------------------------------------------------------------------------- stand
@dataclass(frozen=True)
class StandSpec:
    """What stand to grow.  Lengths in metres, coordinates in units of ``crs``.

    ``stems_per_ha`` is a target: crowns shrink (competition) when the stand is
    too crowded for its hard-core distance, and if the packing still fails the
    stand has fewer trees; ``len(stand.trees)`` is the truth.
    ``crown_overlap`` 0 = open stand, crowns never touch; 1 = dense, crowns of
    neighbours overlap by up to 30 % of their radii.  ``slope_azimuth_deg`` is
    the direction of steepest descent, clockwise from grid north;
    ``undulation_m`` the amplitude of a smooth seeded relief on top of the slope.
    ``ground_z0`` is the terrain height at the centre of the stand.
    ``crown_scale`` multiplies every allometric crown radius (before the
    competition rule): 1 for forest-grown trees, more for open-grown ones.
    """

    width_m: float = 100.0
    depth_m: float = 100.0
    stems_per_ha: float = 300.0
    species: Tuple[str, ...] = SPECIES
    species_weights: Tuple[float, ...] = (0.5, 0.3, 0.2)
    height_m: Tuple[float, float] = (8.0, 35.0)
    crown_overlap: float = 0.5
    slope_deg: float = 0.0
    slope_azimuth_deg: float = 90.0
    undulation_m: float = 0.5
    origin: Tuple[float, float] = (500000.0, 5500000.0)
    crs: str = "EPSG:32632"
    ground_z0: float = 250.0
    seed: int = 0
    crown_scale: float = 1.0

    def __post_init__(self):
        if not (self.width_m > 0 and self.depth_m > 0):
            raise InputError(f"stand extent must be positive, got {self.width_m} x {self.depth_m} m")
        if not self.stems_per_ha > 0:
            raise InputError(f"stems_per_ha must be positive, got {self.stems_per_ha}")
        unknown = [s for s in self.species if s not in _ALLOMETRY]
        if unknown or not self.species:
            raise InputError(f"unknown species {unknown or '(none given)'}; choose from {SPECIES}")
        if len(self.species_weights) != len(self.species):
            raise InputError(
                f"species_weights has {len(self.species_weights)} values for "
                f"{len(self.species)} species {tuple(self.species)}")
        w = np.asarray(self.species_weights, dtype=float)
        if np.any(w < 0) or not w.sum() > 0:
            raise InputError(f"species_weights must be >= 0 and not all 0, got {self.species_weights}")
        lo, hi = self.height_m
        if not (_MIN_HEIGHT_M <= lo <= hi <= _MAX_HEIGHT_M):
            raise InputError(
                f"height_m must be a range within {_MIN_HEIGHT_M}..{_MAX_HEIGHT_M} m, got {self.height_m}")
        if not 0.0 <= self.crown_overlap <= 1.0:
            raise InputError(f"crown_overlap must be in 0..1, got {self.crown_overlap}")
        if not 0.0 <= self.slope_deg < 60.0:
            raise InputError(f"slope_deg must be in 0..60 degrees, got {self.slope_deg}")
        if self.undulation_m < 0:
            raise InputError(f"undulation_m must be >= 0, got {self.undulation_m}")
        if not 0.0 < self.crown_scale < float("inf"):
            raise InputError(f"crown_scale must be positive and finite, got {self.crown_scale}")
        _projected_crs(self.crs)


def _projected_crs(user_input):
    try:
        import pyproj

        crs = pyproj.CRS.from_user_input(user_input)
    except Exception as exc:  # pyproj raises CRSError, a subclass of its own tree
        raise CRSError(f"the stand CRS {user_input!r} is not a CRS pyproj knows: {exc}") from None
    if not crs.is_projected:
        raise CRSError(f"the stand CRS {user_input!r} is not a projected CRS (it must be metric, e.g. UTM)")
    unit = crs.axis_info[0].unit_name if crs.axis_info else ""
    if unit not in ("metre", "meter"):
        raise CRSError(f"the stand CRS {user_input!r} has axis unit {unit!r}; the simulator works in metres")
    return crs


@dataclass(frozen=True)
class TrueTree:
    """Ground truth of one tree.  ``x, y``: stem base in CRS units; ``ground_z``
    the terrain there; heights in metres above ``ground_z``.  For a multi-stem
    tree ``x, y`` is the common base of its stems and ``dbh_m`` the
    basal-area-equivalent diameter ``sqrt(sum d_i^2)`` (each of its
    ``n_stems`` stems has ``dbh_m / sqrt(n_stems)``)."""

    tree_id: int
    species: str
    x: float
    y: float
    ground_z: float
    height: float
    crown_radius_m: float
    crown_base_height_m: float
    dbh_m: float
    n_stems: int = 1

    @property
    def top_z(self) -> float:
        return self.ground_z + self.height


@dataclass(eq=False)
class Stand:
    """A synthetic stand: its spec, trees, terrain and the geometric primitives
    (cones, ellipsoids, leaning cylinders) the scan simulator intersects.

    ``parts`` is a dict of arrays, one row per primitive, rows of one tree
    contiguous; ``part_ptr[i]:part_ptr[i+1]`` are the rows of ``trees[i]``.
    """

    spec: StandSpec
    trees: List[TrueTree]
    parts: dict
    part_ptr: np.ndarray
    _terrain: tuple = field(repr=False)

    @property
    def crs(self):
        return _projected_crs(self.spec.crs)

    @property
    def extent(self) -> Tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) in CRS units."""
        x0, y0 = self.spec.origin
        return (x0, y0, x0 + self.spec.width_m, y0 + self.spec.depth_m)

    def ground_z(self, x, y) -> np.ndarray:
        """Terrain height at ``x, y`` (CRS units, arrays broadcast), vectorised."""
        return _terrain_eval(self._terrain, x, y)

    def tree_arrays(self) -> dict:
        """The trees as a dict of arrays (the truth table's columns)."""
        return _tree_columns(self.trees)

    def inside(self, tree_id, kind, xyz, tolerance_m: float = 0.0) -> np.ndarray:
        """Per point: does the point lie in the envelope of its labelled tree?

        ``tree_id`` (1-based, per point), ``kind`` (:data:`STEM` or :data:`CROWN`
        per point), ``xyz`` (n, 3).  Crown points are tested against the
        crown primitives of their tree, stem points against its stems, with
        every primitive grown by ``tolerance_m`` (horizontally and vertically).
        Points of other kinds, or with tree id 0, give False.
        """
        tree_id = np.asarray(tree_id, dtype=np.int64).ravel()
        kind = np.asarray(kind).ravel()
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        n = len(xyz)
        result = np.zeros(n, dtype=bool)
        ok = (tree_id >= 1) & (tree_id <= len(self.trees)) & ((kind == STEM) | (kind == CROWN))
        if not ok.any():
            return result
        pts = np.flatnonzero(ok)
        pt, part = _expand(pts, tree_id[pts] - 1, self.part_ptr)
        pk = self.parts["kind"][part]
        want_stem = kind[pt] == STEM
        match = (pk == _CYLINDER) == want_stem
        pt, part, pk = pt[match], part[match], pk[match]
        p = {k: v[part] for k, v in self.parts.items()}
        x, y, z = xyz[pt, 0], xyz[pt, 1], xyz[pt, 2]
        tol = float(tolerance_m)
        zin = (z >= p["zb"] - tol) & (z <= p["zt"] + tol)
        # cone
        rho = np.hypot(x - p["cx"], y - p["cy"])
        k = p["a"] / np.maximum(p["zt"] - p["zb"], 1e-9)
        in_cone = zin & (rho <= k * np.clip(p["zt"] - z, 0.0, None) + tol)
        # ellipsoid
        cz = 0.5 * (p["zb"] + p["zt"])
        in_ell = (rho / (p["a"] + tol)) ** 2 + ((z - cz) / (p["c"] + tol)) ** 2 <= 1.0
        # leaning cylinder
        h = z - p["zb"]
        rho_c = np.hypot(x - p["cx"] - p["lx"] * h, y - p["cy"] - p["ly"] * h)
        in_cyl = zin & (rho_c <= p["a"] + tol)
        inside = np.where(pk == _CONE, in_cone, np.where(pk == _ELLIPSOID, in_ell, in_cyl))
        result[pt[inside]] = True
        return result


def _expand(items: np.ndarray, groups: np.ndarray, ptr: np.ndarray):
    """For each (item, group) pair, one row per member of the group's CSR range."""
    start = ptr[groups]
    counts = ptr[groups + 1] - start
    total = int(counts.sum())
    rep = np.repeat(np.arange(len(items)), counts)
    offs = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
    return items[rep], start[rep] + offs


def _tree_columns(trees: Sequence[TrueTree]) -> dict:
    return dict(
        tree_id=np.array([t.tree_id for t in trees], dtype=np.int32),
        species=np.array([t.species for t in trees], dtype=object),
        x=np.array([t.x for t in trees], dtype=np.float64),
        y=np.array([t.y for t in trees], dtype=np.float64),
        ground_z=np.array([t.ground_z for t in trees], dtype=np.float64),
        height=np.array([t.height for t in trees], dtype=np.float64),
        crown_radius=np.array([t.crown_radius_m for t in trees], dtype=np.float64),
        crown_base_height=np.array([t.crown_base_height_m for t in trees], dtype=np.float64),
        dbh=np.array([t.dbh_m for t in trees], dtype=np.float64),
        n_stems=np.array([t.n_stems for t in trees], dtype=np.int32),
    )


def _make_terrain(spec: StandSpec, rng: np.random.Generator) -> tuple:
    cx = spec.origin[0] + 0.5 * spec.width_m
    cy = spec.origin[1] + 0.5 * spec.depth_m
    g = math.tan(math.radians(spec.slope_deg))
    az = math.radians(spec.slope_azimuth_deg)
    # Descent along (sin az, cos az): gradient points the other way.
    gx, gy = -g * math.sin(az), -g * math.cos(az)
    waves = []
    if spec.undulation_m > 0:
        for share in (0.6, 0.4):
            wavelength = rng.uniform(60.0, 150.0)
            theta = rng.uniform(0.0, 2 * math.pi)
            kk = 2 * math.pi / wavelength
            waves.append((share * spec.undulation_m, kk * math.cos(theta), kk * math.sin(theta),
                          rng.uniform(0.0, 2 * math.pi)))
    return (cx, cy, float(spec.ground_z0), gx, gy, tuple(waves))


def _naslund_dbh_cm(height_m: np.ndarray, a: np.ndarray, b: float) -> np.ndarray:
    """DBH (cm) from height (m) by inverting Näslund's (1936) h–d curve."""
    s = np.sqrt(np.maximum(height_m - 1.3, 0.01))
    return a * s / (1.0 - b * s)


def make_stand(spec: StandSpec = StandSpec()) -> Stand:
    """Grow the stand ``spec`` describes (deterministic for a given ``spec.seed``).

    Heights: Beta(1.6, 1.6) over ``height_m``.  Crown radius ``r0 + r1*h`` and
    crown ratio per species with seeded variation (lognormal, sigma 0.12; the
    crown ratio uniform in its species range); DBH from Näslund's (1936)
    height–diameter relation ``h = 1.3 + d^2/(a + b d)^2`` inverted, with a
    lognormal sigma 0.10.  If the requested density cannot be packed with the
    crown_overlap hard core (expected random-sequential coverage 0.40), all
    crowns shrink by one factor (competition).  Stems are then placed by a
    Matérn type-II hard-core process, largest crowns first.
    """
    if not isinstance(spec, StandSpec):
        hint = " (preset() returns (StandSpec, ScanSpec): unpack it)" if isinstance(spec, tuple) else ""
        raise InputError(f"make_stand expects a StandSpec, got {type(spec).__name__}{hint}")
    rng = np.random.default_rng(spec.seed)
    terrain = _make_terrain(spec, rng)
    area = spec.width_m * spec.depth_m
    n = max(1, int(round(spec.stems_per_ha * area / 10_000.0)))

    weights = np.asarray(spec.species_weights, dtype=float)
    sp_idx = rng.choice(len(spec.species), size=n, p=weights / weights.sum())
    species = np.array(spec.species, dtype=object)[sp_idx]
    lo, hi = spec.height_m
    height = lo + (hi - lo) * rng.beta(1.6, 1.6, size=n)
    al = [_ALLOMETRY[s] for s in species]
    r0 = np.array([a["r0"] for a in al])
    r1 = np.array([a["r1"] for a in al])
    cr_lo = np.array([a["cr"][0] for a in al])
    cr_hi = np.array([a["cr"][1] for a in al])
    na = np.array([a["naslund_a"] for a in al])
    nb = _ALLOMETRY["conifer"]["naslund_b"]
    radius = (r0 + r1 * height) * spec.crown_scale * rng.lognormal(0.0, 0.12, size=n)
    crown_ratio = rng.uniform(cr_lo, cr_hi)
    cbh = np.maximum(height * (1.0 - crown_ratio), 1.5)
    dbh_m = 0.01 * _naslund_dbh_cm(height, na, nb) * rng.lognormal(0.0, 0.10, size=n)
    multi = species == "multistem"
    n_stems = np.where(multi, rng.integers(2, 5, size=n), 1)

    # Competition: shrink crowns if the hard-core disks cannot cover the target density.
    core = 1.0 - 0.3 * spec.crown_overlap
    r_fit = math.sqrt(0.40 * area / (n * math.pi)) / core
    mean_r = float(radius.mean())
    if mean_r > r_fit:
        radius *= r_fit / mean_r
    radius = np.maximum(radius, 0.5)

    xy, placed = _place_stems(rng, radius, core, spec)
    order = np.flatnonzero(placed)
    # Stable, readable ids: sort the placed trees south-to-north, west-to-east.
    order = order[np.lexsort((xy[order, 0], xy[order, 1]))]
    gz = _terrain_eval(terrain, xy[order, 0], xy[order, 1])

    trees = []
    for new_id, (i, z) in enumerate(zip(order, gz), start=1):
        trees.append(TrueTree(
            tree_id=new_id, species=str(species[i]),
            x=float(xy[i, 0]), y=float(xy[i, 1]), ground_z=float(z),
            height=float(height[i]), crown_radius_m=float(radius[i]),
            crown_base_height_m=float(cbh[i]), dbh_m=float(dbh_m[i]), n_stems=int(n_stems[i]),
        ))
    parts, ptr = _build_parts(trees, spec, rng)
    return Stand(spec=spec, trees=trees, parts=parts, part_ptr=ptr, _terrain=terrain)


def _terrain_eval(terrain, x, y):
    """Plane through (cx, cy, z0) with gradient (gx, gy) plus sine waves."""
    cx, cy, z0, gx, gy, waves = terrain
    dx = np.asarray(x, dtype=np.float64) - cx
    dy = np.asarray(y, dtype=np.float64) - cy
    z = z0 + gx * dx + gy * dy
    for amp, kx, ky, phase in waves:
        z = z + amp * np.sin(kx * dx + ky * dy + phase)
    return z


def _place_stems(rng, radius: np.ndarray, core: float, spec: StandSpec):
    """Matérn type-II hard-core placement in rounds, largest crowns first.

    In each round every unplaced tree proposes a uniform position; a proposal
    survives if it keeps the hard-core distance ``core*(r_i + r_j)`` to every
    placed tree and to every proposal of higher priority (larger crown).
    """
    n = len(radius)
    prio = np.argsort(-radius, kind="stable")  # prio[k] = tree index of rank k
    rank = np.empty(n, dtype=np.int64)
    rank[prio] = np.arange(n)
    margin = 0.5
    x0, y0 = spec.origin
    lo = np.array([x0 + margin, y0 + margin])
    span = np.array([max(spec.width_m - 2 * margin, 1e-3), max(spec.depth_m - 2 * margin, 1e-3)])
    xy = np.zeros((n, 2))
    placed = np.zeros(n, dtype=bool)
    rmax = float(radius.max())
    for _ in range(100):
        todo = np.flatnonzero(~placed)
        if len(todo) == 0:
            break
        prop = lo + span * rng.random((len(todo), 2))
        ok = np.ones(len(todo), dtype=bool)
        done = np.flatnonzero(placed)
        if len(done):
            pairs = cKDTree(prop).sparse_distance_matrix(
                cKDTree(xy[done]), core * (rmax + rmax), output_type="ndarray")
            if len(pairs):
                need = core * (radius[todo[pairs["i"]]] + radius[done[pairs["j"]]])
                bad = pairs["i"][pairs["v"] < need]
                ok[bad] = False
        cand = np.flatnonzero(ok)
        if len(cand) > 1:
            tree = cKDTree(prop[cand])
            pairs = tree.query_pairs(core * 2 * rmax, output_type="ndarray")
            if len(pairs):
                a, b = cand[pairs[:, 0]], cand[pairs[:, 1]]
                d = np.hypot(*(prop[a] - prop[b]).T)
                clash = d < core * (radius[todo[a]] + radius[todo[b]])
                a, b = a[clash], b[clash]
                loser = np.where(rank[todo[a]] > rank[todo[b]], a, b)
                ok[loser] = False
        xy[todo[ok]] = prop[ok]
        placed[todo[ok]] = True
    return xy, placed


def _build_parts(trees: Sequence[TrueTree], spec: StandSpec, rng) -> Tuple[dict, np.ndarray]:
    """Primitives per tree (loop over trees: a few thousand at most, not a hot path)."""
    rows = []
    tan_slope = math.tan(math.radians(spec.slope_deg))
    for ti, t in enumerate(trees):
        zg, H, R, cb = t.ground_z, t.height, t.crown_radius_m, t.crown_base_height_m
        top, base = zg + H, zg + cb
        length = H - cb
        into = _STEM_INTO_CROWN[t.species]
        r_stem = 0.5 * t.dbh_m / math.sqrt(t.n_stems)
        z_foot = zg - (r_stem + 0.3) * tan_slope - 0.2
        stem_top = base + into * length
        if t.species == "conifer":
            rows.append((ti, _CONE, t.x, t.y, base, top, R, 0.0, 0.0, 0.0))
            rows.append((ti, _CYLINDER, t.x, t.y, z_foot, stem_top, r_stem, 0.0, 0.0, 0.0))
        elif t.species == "broadleaf":
            rows.append((ti, _ELLIPSOID, t.x, t.y, base, top, R, 0.5 * length, 0.0, 0.0))
            rows.append((ti, _CYLINDER, t.x, t.y, z_foot, stem_top, r_stem, 0.0, 0.0, 0.0))
        else:
            k = t.n_stems
            a_sub = 0.6 * R
            offset = R - a_sub
            phi0 = rng.uniform(0.0, 2 * math.pi)
            for s in range(k):
                phi = phi0 + 2 * math.pi * s / k + rng.uniform(-0.3, 0.3)
                ux, uy = math.cos(phi), math.sin(phi)
                sub_top = top if s == 0 else zg + H * rng.uniform(0.85, 1.0)
                sub_top = max(sub_top, base + 0.5 * length)
                rows.append((ti, _ELLIPSOID, t.x + offset * ux, t.y + offset * uy,
                             base, sub_top, a_sub, 0.5 * (sub_top - base), 0.0, 0.0))
                # Stem leans from the common base to under its sub-crown centre.
                lean = offset / max(stem_top - z_foot, 1e-6)
                rows.append((ti, _CYLINDER, t.x, t.y, z_foot, stem_top, r_stem, 0.0,
                             lean * ux, lean * uy))
    names = ("tree", "kind", "cx", "cy", "zb", "zt", "a", "c", "lx", "ly")
    arr = np.array(rows, dtype=np.float64).reshape(-1, len(names))
    parts = {nm: arr[:, i].copy() for i, nm in enumerate(names)}
    parts["tree"] = parts["tree"].astype(np.int64)
    parts["kind"] = parts["kind"].astype(np.int64)
    counts = np.bincount(parts["tree"], minlength=len(trees))
    ptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    return parts, ptr


# --------------------------------------------------------------------------- scan
@dataclass(frozen=True)
class ScanSpec:
    """How to scan.  ``pulse_density`` is in pulses (= first returns) per m2
    of ground; with multiple returns the total point density is higher, and
    first returns in the canopy, closer to the aircraft, are denser by about
    canopy height / flying height (a few per cent).

    Crown interaction (a turbid medium seen by a beam of ``footprint_diameter_m``):
    on entering a crown the pulse gives an echo unless it passes a gap
    (probability ``crown_gap_fraction``); inside, echoes occur at
    ``crown_echo_rate_per_m`` per metre of path; each crown echo stops the pulse
    with ``crown_stop_probability`` and each stem hit with
    ``stem_stop_probability``; a pulse that survives echoes off the ground.
    Echoes closer than ``min_echo_separation_m`` to the previous one merge
    into it; at most ``max_returns`` per pulse are recorded.  Where crowns
    overlap, each contributes its own echoes, labelled with its own tree.
    ``range_noise_m`` is the ranging noise (1 sigma, along the beam).

    Classification: ground returns class 2 when ``classify_ground`` (else
    everything class 1); vegetation class 1; noise class 1 as in most
    delivered tiles, or 7 (low noise) / 18 (high noise) when ``classify_noise``.
    ``noise_fraction`` adds that share (of the pulses) of isolated outliers,
    half high above the canopy, half below ground.
    The aircraft flies north along the stand's centre line at the height that
    makes the stand's width (plus the lean of the rays over the canopy) one
    swath of +/- ``scan_angle_max_deg``; ``flying_speed_m_s`` only sets the
    GPS times.
    """

    pulse_density: float = 10.0
    max_returns: int = 4
    crown_gap_fraction: float = 0.15
    crown_echo_rate_per_m: float = 0.35
    crown_stop_probability: float = 0.3
    stem_stop_probability: float = 0.6
    footprint_diameter_m: float = 0.3
    min_echo_separation_m: float = 1.0
    range_noise_m: float = 0.02
    noise_fraction: float = 0.001
    rgb: bool = False
    intensity: bool = True
    classify_ground: bool = True
    classify_noise: bool = False
    scan_angle_max_deg: float = 15.0
    flying_speed_m_s: float = 60.0
    seed: int = 0

    def __post_init__(self):
        if not 0.01 <= self.pulse_density <= 1000.0:
            raise InputError(f"pulse_density must be in 0.01..1000 pulses/m2, got {self.pulse_density}")
        if not 1 <= int(self.max_returns) <= 15:
            raise InputError(f"max_returns must be 1..15 (LAS 1.4), got {self.max_returns}")
        for name in ("crown_gap_fraction", "crown_stop_probability", "stem_stop_probability",
                     "noise_fraction"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise InputError(f"{name} must be in 0..1, got {v}")
        for name in ("crown_echo_rate_per_m", "footprint_diameter_m", "min_echo_separation_m",
                     "range_noise_m"):
            if getattr(self, name) < 0:
                raise InputError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not 0.0 <= self.scan_angle_max_deg <= 40.0:
            raise InputError(f"scan_angle_max_deg must be in 0..40, got {self.scan_angle_max_deg}")
        if not self.flying_speed_m_s > 0:
            raise InputError(f"flying_speed_m_s must be positive, got {self.flying_speed_m_s}")


@dataclass(eq=False)
class Scan:
    """A simulated scan: the cloud and its per-point truth.

    ``cloud``: xyz in CRS units (the stand's CRS) and the attributes
    ``return_number``, ``number_of_returns``, ``classification`` (uint8),
    ``gps_time`` (float64, GPS week seconds), ``scan_angle`` (int16, LAS 1.4
    units of 0.006 degree), ``intensity`` (uint16, when asked) and
    ``red``/``green``/``blue`` (uint16, when asked).
    ``truth_tree`` int32 (tree id, 0 = none), ``truth_kind`` uint8
    (:data:`GROUND`, :data:`STEM`, :data:`CROWN`, :data:`NOISE`).
    ``n_pulses``: pulses with at least one point in the stand.
    Points are in acquisition (GPS time, then return number) order.
    """

    cloud: PointCloud
    truth_tree: np.ndarray
    truth_kind: np.ndarray
    stand: Stand
    spec: ScanSpec
    n_pulses: int = 0


_CHUNK_PULSES = 100_000
_GPS_T0 = 302_400.0  # GPS week seconds (Thursday 00:00), valid for either LAS time encoding

# Reflectance (relative, 1064 nm) by kind; crowns by species.
_REFLECTANCE = {"ground": 0.30, "stem": 0.25, "conifer": 0.40, "broadleaf": 0.55, "multistem": 0.50}
_RGB = {
    "ground": (0.42, 0.35, 0.24), "stem": (0.32, 0.24, 0.16),
    "conifer": (0.15, 0.27, 0.13), "broadleaf": (0.30, 0.47, 0.19), "multistem": (0.36, 0.50, 0.22),
}


def simulate_scan(stand: Stand, scan: ScanSpec = ScanSpec(),
                  progress: Optional[Callable[[float, str], None]] = None,
                  cancelled: Optional[Callable[[], bool]] = None) -> Scan:
    """Scan ``stand`` with an airborne LiDAR as ``scan`` describes.

    Geometry: the aircraft flies north along the stand's centre line; pulse
    targets form a jittered grid (one pulse per cell of 1/``pulse_density``
    m2, uniform inside it) on the plane ``ground_z0``, over the stand widened
    across track by the lean of the rays, and each pulse is the ray from the
    aircraft through its target (off nadir by up to ``scan_angle_max_deg``).
    Points are then clipped to the stand's extent by their own x, y, as a
    tile is cut from a flight strip, so the canopy at the tile's edges is
    covered too.

    Candidate search: every primitive (cone, ellipsoid, leaning cylinder,
    grown by the footprint radius) is projected from the aircraft onto the
    target plane; the pulses of the grid cells under that box are its
    candidates, enumerated by index arithmetic on the pulse grid (exact and
    cheaper than a radius query around stems, which must allow for the
    largest crown and the largest ray lean).  Intersections are analytic
    (quadratics); the terrain is hit by a fixed-point iteration of the ray
    against :meth:`Stand.ground_z`.  Echo events (crown surface, crown
    interior, stem, ground) are sorted per pulse; those after the first
    stopping event, closer than ``min_echo_separation_m`` to the previous
    echo, or beyond ``max_returns`` are dropped.  Everything is vectorised
    over pulses, in chunks of about 100 000 pulses (progress and
    cancellation are checked per chunk).
    """
    if not isinstance(stand, Stand):
        raise InputError(f"simulate_scan expects a Stand from make_stand, got {type(stand).__name__}")
    if not isinstance(scan, ScanSpec):
        raise InputError(f"simulate_scan expects a ScanSpec, got {type(scan).__name__}")
    spec = stand.spec
    rng = np.random.default_rng([scan.seed, 0x5EED])
    report(progress, 0.0, "placing laser pulses")
    check(cancelled)

    trees = stand.trees
    parts = stand.parts
    x0, y0 = spec.origin
    hmax = max((t.height for t in trees), default=0.0)
    rf = 0.5 * scan.footprint_diameter_m
    tan_max = math.tan(math.radians(scan.scan_angle_max_deg))
    # Rays lean across track: widen the pulse grid by buffer_x on both sides so
    # that points over the whole extent, from ground to tree top, are sampled.
    # The terrain range over the widened grid bounds the lean (a contraction
    # while tan(angle) * tan(slope) < 1, so a few rounds settle it).
    buffer_x = 1.0
    for _ in range(8):
        g_lo, g_hi = _terrain_bounds(stand, x0 - buffer_x, x0 + spec.width_m + buffer_x,
                                     y0, y0 + spec.depth_m)
        buffer_x = (hmax + max(g_hi - spec.ground_z0, spec.ground_z0 - g_lo)) * tan_max + 1.0
    g_lo, g_hi = _terrain_bounds(stand, x0 - buffer_x, x0 + spec.width_m + buffer_x,
                                 y0, y0 + spec.depth_m)
    gx0 = x0 - buffer_x
    grid_w = spec.width_m + 2 * buffer_x
    xc = x0 + 0.5 * spec.width_m
    # (scan_angle_max_deg 0: nadir-only rays, from an aircraft "infinitely" high)
    fly_h = 0.5 * grid_w / tan_max if tan_max > 1e-9 else 1e9
    z_sensor = spec.ground_z0 + fly_h
    if z_sensor < g_hi + hmax + 20.0:
        raise InputError(
            f"scan_angle_max_deg {scan.scan_angle_max_deg} is too wide for this stand: the "
            "aircraft would fly through the canopy; use a smaller angle or a wider stand")

    root = math.sqrt(scan.pulse_density)
    nx = max(1, int(round(grid_w * root)))
    ny = max(1, int(round(spec.depth_m * root)))
    cw, ch = grid_w / nx, spec.depth_m / ny
    grid = dict(x0=gx0, y0=y0, cw=cw, ch=ch, nx=nx, ny=ny, xc=xc, z0=spec.ground_z0,
                fly_h=fly_h, z_start=g_hi + hmax + 5.0)
    row_time = ch / scan.flying_speed_m_s

    # Every primitive's box in target space (grown by the footprint radius).
    boxes = _part_boxes(parts, grid, rf) if trees else None

    rows_per_chunk = max(1, _CHUNK_PULSES // nx)
    n_chunks = max(1, -(-ny // rows_per_chunk))
    sub = scaled(progress, 0.0, 0.9)
    chunks = []
    for c in range(n_chunks):
        check(cancelled)
        j0, j1 = c * rows_per_chunk, min(ny, (c + 1) * rows_per_chunk)
        report(sub, c / n_chunks, f"casting pulses {j0 * nx:,} of {nx * ny:,}")
        crng = np.random.default_rng([scan.seed, 0x5EED, c + 1])
        chunks.append(_cast_chunk(stand, scan, crng, grid, j0, j1, boxes, rf))
    report(progress, 0.9, "assembling returns")
    check(cancelled)

    def cat(key):
        return np.concatenate([ch_[key] for ch_ in chunks])

    pulse, xyz, kind, tree = cat("pulse"), cat("xyz"), cat("kind"), cat("tree")
    rn, nr, share = cat("rn"), cat("nr"), cat("share")
    # Clip to the stand by the points' own x, y (as a tile is cut from a strip).
    inside = ((xyz[:, 0] >= x0) & (xyz[:, 0] < x0 + spec.width_m)
              & (xyz[:, 1] >= y0) & (xyz[:, 1] < y0 + spec.depth_m))
    pulse, xyz, kind, tree, rn, nr, share = (
        a[inside] for a in (pulse, xyz, kind, tree, rn, nr, share))
    n_pulses = int(len(np.unique(pulse)))
    # Time: rows one after the other, a zig-zag sweep across each row.
    jj, ii = np.divmod(pulse, nx)
    gps = _GPS_T0 + (jj + (ii + 0.5) / nx) * row_time
    tx = gx0 + (np.where(jj % 2 == 1, nx - 1 - ii, ii) + 0.5) * cw  # cell centre, for the angle
    angle = np.degrees(np.arctan2(tx - xc, fly_h)).astype(np.float32)

    # Noise: isolated single-return outliers, half high above the canopy, half below ground.
    n_noise = int(rng.binomial(n_pulses, scan.noise_fraction)) if scan.noise_fraction > 0 else 0
    noise_high = np.zeros(len(xyz), dtype=bool)
    if n_noise:
        nx_ = x0 + spec.width_m * rng.random(n_noise)
        ny_ = y0 + spec.depth_m * rng.random(n_noise)
        high = rng.random(n_noise) < 0.5
        gz = stand.ground_z(nx_, ny_)
        nz = np.where(high, gz + hmax + rng.uniform(5.0, 100.0, n_noise),
                      gz - rng.uniform(1.0, 20.0, n_noise))
        xyz = np.concatenate([xyz, np.stack([nx_, ny_, nz], axis=1)])
        kind = np.concatenate([kind, np.full(n_noise, NOISE, dtype=np.uint8)])
        tree = np.concatenate([tree, np.zeros(n_noise, dtype=np.int32)])
        rn = np.concatenate([rn, np.ones(n_noise, dtype=np.uint8)])
        nr = np.concatenate([nr, np.ones(n_noise, dtype=np.uint8)])
        share = np.concatenate([share, rng.uniform(0.05, 0.5, n_noise)])
        gps = np.concatenate([gps, _GPS_T0 + ny * row_time * rng.random(n_noise)])
        angle = np.concatenate([angle, np.degrees(np.arctan2(nx_ - xc, fly_h)).astype(np.float32)])
        noise_high = np.concatenate([noise_high, high])

    order = np.lexsort((rn, gps))
    xyz, kind, tree, rn, nr = xyz[order], kind[order], tree[order], rn[order], nr[order]
    share, gps, angle, noise_high = share[order], gps[order], angle[order], noise_high[order]

    n = len(xyz)
    classification = np.ones(n, dtype=np.uint8)
    if scan.classify_ground:
        classification[kind == GROUND] = 2
    if scan.classify_noise:
        classification[(kind == NOISE) & ~noise_high] = 7
        classification[(kind == NOISE) & noise_high] = 18
    attrs = dict(
        return_number=rn, number_of_returns=nr, classification=classification,
        gps_time=gps,
        # LAS 1.4 (point formats 6+) stores the scan angle as int16 in 0.006 degree units.
        scan_angle=np.rint(angle / 0.006).astype(np.int16),
    )
    species_of = np.array(["none"] + [t.species for t in trees], dtype=object)
    if scan.intensity:
        refl = np.full(n, _REFLECTANCE["ground"])
        refl[kind == STEM] = _REFLECTANCE["stem"]
        for sp in SPECIES:
            refl[(kind == CROWN) & (species_of[tree] == sp)] = _REFLECTANCE[sp]
        value = 40_000.0 * refl * share * rng.lognormal(0.0, 0.15, n)
        attrs["intensity"] = np.clip(np.rint(value), 1, 65535).astype(np.uint16)
    if scan.rgb:
        attrs.update(_colours(stand, rng, xyz, kind, tree, species_of))

    cloud = PointCloud(xyz=xyz, attrs=attrs, crs=stand.crs, source=f"synthetic stand (seed {spec.seed})")
    report(progress, 1.0, f"{n:,} points from {n_pulses:,} pulses")
    return Scan(cloud=cloud, truth_tree=tree.astype(np.int32), truth_kind=kind.astype(np.uint8),
                stand=stand, spec=scan, n_pulses=n_pulses)


def _terrain_bounds(stand: Stand, xmin, xmax, ymin, ymax) -> Tuple[float, float]:
    """Lowest and highest terrain over a rectangle (+/- 1 m): the plane's
    corners plus or minus the undulation amplitude."""
    _, _, _, _, _, waves = stand._terrain
    amp = sum(abs(w[0]) for w in waves)
    cx, cy = np.meshgrid([xmin, xmax], [ymin, ymax])
    plane = _terrain_eval(stand._terrain[:5] + ((),), cx, cy)
    return float(plane.min()) - amp - 1.0, float(plane.max()) + amp + 1.0


def _part_boxes(parts: dict, grid: dict, rf: float) -> dict:
    """Each primitive's bounding box projected from the aircraft onto the target
    plane, as ranges of pulse-grid cells (i0..i1, j0..j1 inclusive)."""
    h = parts["zt"] - parts["zb"]
    ex = parts["a"] + rf + 0.01
    lean_x, lean_y = parts["lx"] * h, parts["ly"] * h
    xmin = parts["cx"] + np.minimum(lean_x, 0.0) - ex
    xmax = parts["cx"] + np.maximum(lean_x, 0.0) + ex
    ymin = parts["cy"] + np.minimum(lean_y, 0.0) - ex
    ymax = parts["cy"] + np.maximum(lean_y, 0.0) + ex
    xc, z0, fh = grid["xc"], grid["z0"], grid["fly_h"]
    # Target x of a point (x, z): xc + (x - xc) * fh / (z0 + fh - z); monotone in x and z.
    txs = [xc + (x - xc) * fh / (z0 + fh - z)
           for x in (xmin, xmax) for z in (parts["zb"], parts["zt"])]
    tmin = np.minimum.reduce(txs)
    tmax = np.maximum.reduce(txs)
    i0 = np.floor((tmin - grid["x0"]) / grid["cw"]).astype(np.int64)
    i1 = np.floor((tmax - grid["x0"]) / grid["cw"]).astype(np.int64)
    j0 = np.floor((ymin - grid["y0"]) / grid["ch"]).astype(np.int64)
    j1 = np.floor((ymax - grid["y0"]) / grid["ch"]).astype(np.int64)
    return dict(i0=np.clip(i0, 0, grid["nx"] - 1), i1=np.clip(i1, 0, grid["nx"] - 1),
                j0=np.clip(j0, 0, grid["ny"] - 1), j1=np.clip(j1, 0, grid["ny"] - 1))


def _ray_ground(stand: Stand, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Range along each ray to the terrain: fixed-point iteration on
    t = (o_z - ground(o + t d)) / -d_z, a contraction while
    tan(scan angle) * tan(slope) < 1."""
    t = (o[:, 2] - stand.ground_z(o[:, 0], o[:, 1])) / -d[:, 2]
    for _ in range(30):
        x = o[:, 0] + t * d[:, 0]
        y = o[:, 1] + t * d[:, 1]
        t_new = (o[:, 2] - stand.ground_z(x, y)) / -d[:, 2]
        done = np.abs(t_new - t).max() < 1e-6 if len(t) else True
        t = t_new
        if done:
            break
    return t


def _cast_chunk(stand, scan, rng, grid, j0, j1, boxes, rf):
    """Pulses of grid rows j0..j1-1: their echoes, sorted by pulse then range."""
    nx = grid["nx"]
    first = j0 * nx
    m = (j1 - j0) * nx
    idx = np.arange(first, first + m, dtype=np.int64)  # pulse index = j * nx + i (acquisition order)
    jj, ii = np.divmod(idx, nx)
    col = np.where(jj % 2 == 1, nx - 1 - ii, ii)       # zig-zag: grid column of the pulse
    u = rng.random((m, 2))
    tx = grid["x0"] + (col + u[:, 0]) * grid["cw"]
    ty = grid["y0"] + (jj + u[:, 1]) * grid["ch"]
    fh = grid["fly_h"]
    dxy = tx - grid["xc"]
    norm = np.sqrt(dxy * dxy + fh * fh)
    d = np.stack([dxy / norm, np.zeros(m), -fh / norm], axis=1)
    # Ray start on the plane z_start (above every tree).
    t_ref = (grid["z_start"] - grid["z0"]) / fh * norm
    o = np.stack([tx - d[:, 0] * t_ref, ty, np.full(m, grid["z_start"])], axis=1)
    t_ground = _ray_ground(stand, o, d)

    ev_p, ev_t, ev_kind, ev_tree, ev_stop = [], [], [], [], []
    if boxes is not None:
        # Pairs (pulse, part) from the parts' boxes on the grid, rows clipped to the chunk.
        pj0 = np.maximum(boxes["j0"], j0)
        pj1 = np.minimum(boxes["j1"], j1 - 1)
        live = np.flatnonzero(pj1 >= pj0)
        ni = boxes["i1"][live] - boxes["i0"][live] + 1
        nj = pj1[live] - pj0[live] + 1
        cnt = ni * nj
        part = np.repeat(live, cnt)
        k = np.arange(int(cnt.sum()), dtype=np.int64) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        nir = np.repeat(ni, cnt)
        cj = pj0[part] + k // nir
        ci = boxes["i0"][part] + k % nir
        pi = cj * nx + np.where(cj % 2 == 1, nx - 1 - ci, ci) - first
        t_in, t_out = _intersect(stand.parts, part, o[pi], d[pi], rf)
        t_out = np.minimum(t_out, t_ground[pi])
        hit = t_in < t_out
        pi, part, t_in, t_out = pi[hit], part[hit], t_in[hit], t_out[hit]
        pk = stand.parts["kind"][part]
        ptree = (stand.parts["tree"][part] + 1).astype(np.int32)

        crown = pk != _CYLINDER
        # Crown surface echo, unless the pulse slips through a gap.
        skin = crown & (rng.random(len(pi)) >= scan.crown_gap_fraction)
        ev_p.append(pi[skin]); ev_t.append(t_in[skin])
        ev_kind.append(np.full(int(skin.sum()), CROWN, np.uint8)); ev_tree.append(ptree[skin])
        ev_stop.append(rng.random(int(skin.sum())) < scan.crown_stop_probability)
        # Crown interior echoes: Poisson along the path, denser near the surface.
        ci_ = np.flatnonzero(crown)
        length = t_out[ci_] - t_in[ci_]
        kk = rng.poisson(scan.crown_echo_rate_per_m * length)
        rep = np.repeat(ci_, kk)
        pos = t_in[rep] + (t_out[rep] - t_in[rep]) * rng.random(len(rep)) ** 1.5
        ev_p.append(pi[rep]); ev_t.append(pos)
        ev_kind.append(np.full(len(rep), CROWN, np.uint8)); ev_tree.append(ptree[rep])
        ev_stop.append(rng.random(len(rep)) < scan.crown_stop_probability)
        # Stem hits.
        st = ~crown
        ev_p.append(pi[st]); ev_t.append(t_in[st])
        ev_kind.append(np.full(int(st.sum()), STEM, np.uint8)); ev_tree.append(ptree[st])
        ev_stop.append(rng.random(int(st.sum())) < scan.stem_stop_probability)
    # Ground: always there, always stops the pulse.
    ev_p.append(np.arange(m)); ev_t.append(t_ground)
    ev_kind.append(np.full(m, GROUND, np.uint8)); ev_tree.append(np.zeros(m, np.int32))
    ev_stop.append(np.ones(m, dtype=bool))

    p = np.concatenate(ev_p)
    t = np.concatenate(ev_t)
    kind = np.concatenate(ev_kind)
    tree = np.concatenate(ev_tree)
    stop = np.concatenate(ev_stop)
    # Sort by (pulse, range) through one float key (much faster than lexsort).
    span = 2.0 ** math.ceil(math.log2(float(t.max()) + 2.0)) if len(t) else 1.0
    order = np.argsort(p * span + t)
    p, t, kind, tree, stop = p[order], t[order], kind[order], tree[order], stop[order]

    def group_start(pp):
        counts = np.bincount(pp, minlength=m)
        return (np.cumsum(counts) - counts)[pp]

    # Nothing after the first stopping event of a pulse.
    start = group_start(p)
    cs = np.cumsum(stop)
    stops_before = cs - stop - (cs[start] - stop[start])
    keep = stops_before == 0
    p, t, kind, tree = p[keep], t[keep], kind[keep], tree[keep]
    # Multi-target resolution: an echo too close to the previous one merges into it.
    keep = np.ones(len(p), dtype=bool)
    keep[1:] = (p[1:] != p[:-1]) | (t[1:] - t[:-1] >= scan.min_echo_separation_m)
    p, t, kind, tree = p[keep], t[keep], kind[keep], tree[keep]
    # Return numbers and the max_returns cap.
    rank = np.arange(len(p)) - group_start(p)
    keep = rank < scan.max_returns
    p, t, kind, tree, rank = p[keep], t[keep], kind[keep], tree[keep], rank[keep]
    nr = np.bincount(p, minlength=m)[p]

    # Energy shares for the intensity: a random split among a pulse's echoes.
    w = rng.uniform(0.3, 1.0, len(p))
    share = w / np.bincount(p, weights=w, minlength=m)[p]

    if scan.range_noise_m > 0:
        t = t + rng.normal(0.0, scan.range_noise_m, len(t))
    xyz = o[p] + t[:, None] * d[p]
    return dict(pulse=p + first, xyz=xyz, kind=kind, tree=tree,
                rn=(rank + 1).astype(np.uint8), nr=nr.astype(np.uint8), share=share)


def _colours(stand, rng, xyz, kind, tree, species_of) -> dict:
    n = len(xyz)
    base = np.empty((n, 3))
    base[:] = _RGB["ground"]
    # Ground: patches of litter and grass.
    patch = 0.5 + 0.5 * np.sin(xyz[:, 0] * 0.21) * np.sin(xyz[:, 1] * 0.17)
    g = kind == GROUND
    grass = np.array([0.33, 0.42, 0.20])
    base[g] = (1 - patch[g, None]) * np.array(_RGB["ground"]) + patch[g, None] * grass
    base[kind == STEM] = _RGB["stem"]
    crown = kind == CROWN
    tree_tint = rng.uniform(0.8, 1.2, len(stand.trees) + 1)
    for sp in SPECIES:
        m = crown & (species_of[tree] == sp)
        base[m] = _RGB[sp]
    if crown.any():
        gz = np.array([0.0] + [t.ground_z for t in stand.trees])
        hh = np.array([1.0] + [t.height for t in stand.trees])
        rel = np.clip((xyz[crown, 2] - gz[tree[crown]]) / hh[tree[crown]], 0.0, 1.0)
        base[crown] *= (tree_tint[tree[crown]] * (0.6 + 0.5 * rel))[:, None]
    noise = kind == NOISE
    base[noise] = rng.uniform(0.2, 0.9, (int(noise.sum()), 1))
    rgb = np.clip(base + rng.normal(0.0, 0.03, (n, 3)), 0.0, 1.0)
    v = np.rint(rgb * 65535).astype(np.uint16)
    return dict(red=v[:, 0], green=v[:, 1], blue=v[:, 2])


def _intersect(parts: dict, part: np.ndarray, o: np.ndarray, d: np.ndarray, rf: float):
    """Entry and exit range of each ray (o, d) through primitive ``part``,
    every primitive grown horizontally by ``rf``.  Misses give t_in >= t_out."""
    n = len(part)
    t_in = np.full(n, np.inf)
    t_out = np.full(n, -np.inf)
    kind = parts["kind"][part]
    dz = d[:, 2]  # < 0 everywhere

    for kk, fn in ((_CONE, _hit_cone), (_ELLIPSOID, _hit_ellipsoid), (_CYLINDER, _hit_cylinder)):
        sel = np.flatnonzero(kind == kk)
        if len(sel) == 0:
            continue
        p = {key: parts[key][part[sel]] for key in ("cx", "cy", "zb", "zt", "a", "c", "lx", "ly")}
        a, b = fn(p, o[sel], d[sel], rf)
        # Slab zb..zt (ellipsoids lie inside theirs anyway).
        t_top = (o[sel, 2] - p["zt"]) / -dz[sel]
        t_bot = (o[sel, 2] - p["zb"]) / -dz[sel]
        t_in[sel] = np.maximum(a, t_top)
        t_out[sel] = np.minimum(b, t_bot)
    return t_in, t_out


def _roots(A, B, C):
    """Roots of A t^2 + 2 B t + C (NaN where none), ordered lo <= hi."""
    disc = B * B - A * C
    with np.errstate(invalid="ignore", divide="ignore"):
        s = np.sqrt(disc)
        r1 = (-B - s) / A
        r2 = (-B + s) / A
    return np.fmin(r1, r2), np.fmax(r1, r2), disc


def _hit_ellipsoid(p, o, d, rf):
    a = p["a"] + rf
    c = np.maximum(p["c"], 1e-6)
    s = a / c
    qx, qy = o[:, 0] - p["cx"], o[:, 1] - p["cy"]
    qz = (o[:, 2] - 0.5 * (p["zb"] + p["zt"])) * s
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2] * s
    A = dx * dx + dy * dy + dz * dz
    B = qx * dx + qy * dy + qz * dz
    C = qx * qx + qy * qy + qz * qz - a * a
    lo, hi, disc = _roots(A, B, C)
    miss = ~(disc > 0)
    return np.where(miss, np.inf, lo), np.where(miss, -np.inf, hi)


def _hit_cone(p, o, d, rf):
    # Grown cone: rho <= k (za - z) with its apex raised to za = zt + rf/k, cut at zt.
    k = p["a"] / np.maximum(p["zt"] - p["zb"], 1e-6)
    za = p["zt"] + rf / np.maximum(k, 1e-6)
    qx, qy, qz = o[:, 0] - p["cx"], o[:, 1] - p["cy"], o[:, 2] - za
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    k2 = k * k
    A = k2 * dz * dz - (dx * dx + dy * dy)
    B = k2 * qz * dz - (qx * dx + qy * dy)
    C = k2 * qz * qz - (qx * qx + qy * qy)
    A = np.where(np.abs(A) < 1e-12, -1e-12, A)
    lo, hi, disc = _roots(A, B, C)
    has = disc > 0
    steep = A > 0  # the ray is steeper than the cone: f >= 0 outside the roots
    # Lower nappe (downwards along the ray, dz < 0): [hi, +inf) when steep, [lo, hi] otherwise.
    t_in = np.where(steep, np.where(has, hi, -np.inf), np.where(has, lo, np.inf))
    t_out = np.where(steep, np.inf, np.where(has, hi, -np.inf))
    return t_in, t_out


def _hit_cylinder(p, o, d, rf):
    r = p["a"] + rf
    # Horizontal offset from the (leaning) axis is linear in t.
    wx = o[:, 0] - (p["cx"] + p["lx"] * (o[:, 2] - p["zb"]))
    wy = o[:, 1] - (p["cy"] + p["ly"] * (o[:, 2] - p["zb"]))
    ex = d[:, 0] - p["lx"] * d[:, 2]
    ey = d[:, 1] - p["ly"] * d[:, 2]
    A = ex * ex + ey * ey
    B = wx * ex + wy * ey
    C = wx * wx + wy * wy - r * r
    parallel = A < 1e-14
    A = np.where(parallel, 1.0, A)
    lo, hi, disc = _roots(A, B, C)
    has = disc > 0
    inside = C <= 0
    t_in = np.where(parallel, np.where(inside, -np.inf, np.inf), np.where(has, lo, np.inf))
    t_out = np.where(parallel, np.where(inside, np.inf, -np.inf), np.where(has, hi, -np.inf))
    return t_in, t_out


# --------------------------------------------------------------------------- files
_TRUTH_COLUMNS = ("tree_id", "species", "x", "y", "ground_z", "height", "crown_radius",
                  "crown_base_height", "dbh", "n_stems")


def write_scan(scan: Scan, folder, name: str) -> Tuple[Path, Path]:
    """Write ``<folder>/<name>.laz`` (the cloud, its CRS, and the truth as extra
    dimensions ``true_tree`` int32 and ``true_kind`` uint8) and
    ``<folder>/<name>_trees.csv`` (one row per tree, columns
    tree_id, species, x, y, ground_z, height, crown_radius, crown_base_height,
    dbh, n_stems; lengths in metres, x/y in CRS units).  Both are written to a
    temporary name and moved into place.  Returns the two paths."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"output folder {folder} does not exist")
    if not name or any(ch in name for ch in "/\\"):
        raise InputError(f"output name {name!r} must be a plain file name")
    laz_path = folder / f"{name}.laz"
    csv_path = folder / f"{name}_trees.csv"
    extra = {"true_tree": scan.truth_tree.astype(np.int32), "true_kind": scan.truth_kind.astype(np.uint8)}
    write_las(laz_path, scan.cloud, extra)
    _fix_creation_date(laz_path)
    _write_truth_csv(csv_path, scan.stand.trees)
    return laz_path, csv_path


# A synthetic file's bytes depend only on its specs: a fixed creation date
# (LAS header, all versions: uint16 day of year at byte 90, uint16 year at 92).
_CREATION_DAY, _CREATION_YEAR = 1, 2024


def _fix_creation_date(path: Path) -> None:
    with open(path, "r+b") as fh:
        if fh.read(4) != b"LASF":
            raise InputError(f"{path}: not a LAS file after writing")
        fh.seek(90)
        fh.write(struct.pack("<HH", _CREATION_DAY, _CREATION_YEAR))


def _write_truth_csv(path: Path, trees: Sequence[TrueTree]) -> None:
    buf = io.StringIO(newline="")
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(_TRUTH_COLUMNS)
    for t in trees:
        w.writerow([t.tree_id, t.species, f"{t.x:.3f}", f"{t.y:.3f}", f"{t.ground_z:.3f}",
                    f"{t.height:.3f}", f"{t.crown_radius_m:.3f}", f"{t.crown_base_height_m:.3f}",
                    f"{t.dbh_m:.4f}", t.n_stems])
    tmp = path.with_name(path.name + ".part")
    with open(tmp, "w", newline="", encoding="utf-8") as fh:
        fh.write(buf.getvalue())
    os.replace(tmp, path)


def read_truth(path) -> List[TrueTree]:
    """Read a truth table written by :func:`write_scan` back into TrueTree objects."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"truth table {path} does not exist")
    with open(path, newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        missing = [c for c in _TRUTH_COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise InputError(f"truth table {path} lacks the column(s) {', '.join(missing)}")
        trees = []
        for line, row in enumerate(reader, start=2):
            try:
                trees.append(TrueTree(
                    tree_id=int(row["tree_id"]), species=row["species"],
                    x=float(row["x"]), y=float(row["y"]), ground_z=float(row["ground_z"]),
                    height=float(row["height"]), crown_radius_m=float(row["crown_radius"]),
                    crown_base_height_m=float(row["crown_base_height"]), dbh_m=float(row["dbh"]),
                    n_stems=int(row["n_stems"])))
            except (TypeError, ValueError) as exc:
                raise InputError(f"truth table {path}, line {line}: {exc}") from None
    return trees


# --------------------------------------------------------------------------- presets
_PRESETS = {
    # name: (stems_per_ha, crown_overlap)
    "open": (120.0, 0.0),
    "medium": (250.0, 0.5),
    "dense": (400.0, 1.0),
}


def preset(name: str, pulse_density: float = 10.0, seed: int = 0) -> Tuple[StandSpec, ScanSpec]:
    """(StandSpec, ScanSpec) of a 100 m x 100 m mixed stand: "open" (120 stems/ha,
    crowns never touch), "medium" (250/ha, crown_overlap 0.5) or "dense"
    (400/ha, crowns overlap up to 30 % of their radii), scanned at
    ``pulse_density`` pulses/m2.  The segmentation benchmark uses
    open/dense x 5/20/50."""
    if name not in _PRESETS:
        raise InputError(f"unknown preset {name!r}; choose one of {', '.join(_PRESETS)}")
    stems, overlap = _PRESETS[name]
    return (StandSpec(stems_per_ha=stems, crown_overlap=overlap, seed=seed),
            ScanSpec(pulse_density=pulse_density, seed=seed))
