"""The compiled guided-growth loop (core/reconstruct/colonize/growth.py, ``grow_kernel``) is exact.

Guo et al. 2018 §5.2 space colonisation was vectorised numpy with a per-iteration
``cKDTree`` until the loop moved into a numba kernel.  The kernel must give the
same skeleton bit for bit as that formulation, kept below verbatim as the
reference (:class:`NumpyGrowth`), on ~20 trees generated here (a synthetic
airborne stand, an airborne cone with no stem points, a multi-stem shrub, and
other parameter sets).  The trees are compared on this machine, not against
stored digests: LAPACK's 3x3 eigenvectors (the PCA weights of Eq. 8) round
differently on other CPUs, and any last-bit change alters a grown skeleton.
"""
from __future__ import annotations

import hashlib

import numpy as np
import pytest
from scipy.spatial import cKDTree

from sylva.core.progress import CancelCheck, Progress, check, report
from sylva.core.reconstruct.colonize import GuidedGrowth, influence_distance
from sylva.core.reconstruct.colonize import markers as col_markers
from sylva.core.reconstruct.colonize import method as col_method
from sylva.core.reconstruct.colonize.growth import _K_BUDS, _STALL_LIMIT, Nodes
from sylva.core.reconstruct.colonize.method import _DOWN, _UP, _unit
from sylva.core.reconstruct.model import TreePoints
from sylva.testing.synth import CROWN, STEM, ScanSpec, StandSpec, make_stand, simulate_scan


class NumpyGrowth(GuidedGrowth):
    """The reference: the vectorised numpy/cKDTree iterations the kernel replaced (verbatim)."""

    def _coverage(self, nodes: np.ndarray, xyz: np.ndarray) -> float:
        """Share of ``xyz`` within the kill distance of a node."""
        d, _ = cKDTree(nodes).query(xyz, distance_upper_bound=self.kill_distance_m * (1 + 1e-9))
        return float(np.isfinite(d).mean()) if len(xyz) else 0.0

    def _grow(self, nodes: Nodes, markers: np.ndarray, weight: np.ndarray, n_measured: int,
              height_m: float, progress: Progress, cancelled: CancelCheck):
        """Iterate space colonisation until no marker is left; returns (iterations, reason).

        ``markers[:n_measured]`` are the tree's points, the rest crown-filling
        markers; ``reason`` is "done", "stalled" or "max_iterations" (the
        last two only when measured points are left unreached) or
        "node_limit" (more than 20 nodes per marker: a safety net).
        """
        l = float(self.step_m)
        dk = float(self.kill_distance_m)
        cos_apical = np.cos(np.radians(min(self.perception_angle_deg / 2.0, 180.0)))
        half_lat = min(self.perception_angle_deg / 2.0 + self.branching_angle_deg, 180.0)
        cos_lateral = np.cos(np.radians(half_lat))
        psi = np.radians(self.branching_angle_deg)
        roll = np.radians(self.roll_angle_deg)
        alpha, beta = float(self.attraction_weight), float(self.tropism)
        di_max = float(self.influence_max_units) * l
        node_limit = 20 * len(markers) + 10_000      # a safety net, never reached in practice
        di_of_t = influence_distance(np.arange(int(self.max_iterations)), height_m, l, self.influence_h0,
                                     self.influence_rho0, self.influence_min_units,
                                     self.influence_max_units)

        active = np.ones(len(markers), dtype=bool)
        # Markers already within d_k of the seeds are taken.
        d, _ = cKDTree(nodes.pos[:nodes.m]).query(markers, distance_upper_bound=dk)
        active &= ~np.isfinite(d)
        stall = 0
        boost = 1.0
        it = 0
        reason = "done"
        total = len(markers)
        for it in range(1, int(self.max_iterations) + 1):
            if it % 16 == 0:
                check(cancelled)
                report(progress, 0.1 + 0.85 * (1.0 - active.sum() / max(total, 1)), "growing")
            am = np.flatnonzero(active)
            if len(am) == 0:
                break
            m = nodes.m
            if m > node_limit:
                reason = "node_limit"
                break
            buds = np.flatnonzero(nodes.bud_free[:m])
            if len(buds) == 0:
                reason = "stalled"
                break
            di0 = float(di_of_t[it - 1])
            rho_units = di0 / l
            di = min(di0 * boost, di_max)
            bud_tree = cKDTree(nodes.pos[buds])
            # Only markers with a bud within d_i can be perceived (the growth front).
            d1, _ = bud_tree.query(markers[am], distance_upper_bound=di)
            front = am[np.isfinite(d1)]
            has = np.zeros(0, dtype=bool)
            if len(front):
                kq = min(_K_BUDS, len(buds))
                mp = markers[front]
                _, j = bud_tree.query(mp, k=kq, distance_upper_bound=di)
                j = j.reshape(len(front), kq)
                valid = j < len(buds)
                b = buds[np.where(valid, j, 0)]                              # (a, kq) node ids
                vec = mp[:, None, :] - nodes.pos[b]
                norm = np.sqrt(np.einsum("akx,akx->ak", vec, vec))
                unit = vec / np.maximum(norm, 1e-12)[..., None]
                tip = (nodes.n_children[b] == 0) & ~nodes.seed[b]
                cos_min = np.where(tip, cos_apical, cos_lateral)
                ok = valid & (norm > 1e-9) & (np.einsum("akx,akx->ak", unit, nodes.heading[b]) > cos_min)
                has = ok.any(axis=1)
            if not has.any():
                # No bud perceives a marker.  The apical bud of the stem keeps growing
                # (L-system 1, rule 2, with no V_opt) while it is below the highest marker
                # left: it bridges an unscanned stretch of stem.  A stem is orthotropic, so
                # instead of the tropism its heading turns halfway to the vertical each unit
                # (z always rises, so this ends).
                seed_tips = np.flatnonzero(nodes.leader[:m] & (nodes.n_children[:m] == 0)
                                           & nodes.bud_free[:m])
                seed_tips = seed_tips[nodes.pos[seed_tips, 2] < markers[am, 2].max()]
                if len(seed_tips) and boost == 1.0:
                    v = _unit(nodes.heading[seed_tips] + _UP)
                    k = np.arange(1, max(1, int(rho_units)) + 1)
                    new_pos = (nodes.pos[seed_tips][:, None, :] + (l * k)[None, :, None]
                               * v[:, None, :]).reshape(-1, 3)
                    first_id = nodes.m
                    parent = np.arange(first_id - 1, first_id - 1 + len(new_pos))
                    parent[::len(k)] = seed_tips
                    nodes.add(new_pos, np.repeat(v, len(k), axis=0), parent, seed=True, added=True,
                              leader=True)
                    nodes.bud_free[seed_tips] = True
                    d, _ = cKDTree(new_pos).query(markers[am], distance_upper_bound=dk)
                    active[am[np.isfinite(d)]] = False
                    continue
                stall += 1
                if stall >= _STALL_LIMIT:
                    reason = "stalled"
                    break
                boost *= 1.5
                continue
            stall = 0
            boost = 1.0
            rows = np.flatnonzero(has)
            first = ok[rows].argmax(axis=1)
            bsel = b[rows, first]
            usel = unit[rows, first]
            wsel = weight[front[rows]]
            sums = np.zeros((m, 3))
            np.add.at(sums, bsel, wsel[:, None] * usel)
            wsum = np.bincount(bsel, weights=wsel, minlength=m)
            grow = np.flatnonzero(wsum > 0)
            v_opt = sums[grow] / wsum[grow, None]                            # Eq. 9, V_opt
            head = nodes.heading[grow]
            is_tip = nodes.n_children[grow] == 0
            # Lateral bud direction: ψ off the heading, towards the markers (φ if they give no azimuth).
            across = v_opt - (v_opt * head).sum(axis=1, keepdims=True) * head
            weak = np.linalg.norm(across, axis=1) < 1e-6
            if weak.any():
                ref = np.where(np.abs(head[weak, 2:3]) < 0.9, _UP, np.array([1.0, 0.0, 0.0]))
                e1 = _unit(np.cross(head[weak], ref))
                e2 = np.cross(head[weak], e1)
                ang = roll * (grow[weak] + nodes.n_children[grow[weak]])
                across[weak] = np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * e2
            lateral = np.cos(psi) * head + np.sin(psi) * _unit(across)
            default = np.where(is_tip[:, None], head, lateral)
            v = default + alpha * v_opt + beta * _DOWN                      # Eq. 9
            vn = np.linalg.norm(v, axis=1)
            v = np.where(vn[:, None] > 1e-9, v / np.maximum(vn, 1e-12)[:, None], default)
            # One growth unit (L-system 1, rule 2): a shoot of up to ρ_t internodes of length l
            # along V_A, no longer than the distance to the weighted centroid of the markers.
            csum = np.zeros((m, 3))
            np.add.at(csum, bsel, wsel[:, None] * markers[front[rows]])
            reach = np.linalg.norm(csum[grow] / wsum[grow, None] - nodes.pos[grow], axis=1)
            units = np.clip(np.rint(reach / l), 1, max(1, int(rho_units))).astype(np.int64)
            k = np.arange(int(units.sum())) - np.repeat(np.cumsum(units) - units, units) + 1
            owner = np.repeat(np.arange(len(grow)), units)
            new_pos = nodes.pos[grow][owner] + (l * k)[:, None] * v[owner]
            first_id = nodes.m
            parent = np.arange(first_id - 1, first_id - 1 + len(k))
            parent[k == 1] = grow
            nodes.add(new_pos, v[owner], parent, leader=(is_tip & nodes.leader[grow])[owner])
            # A node's buds are spent once it has its apical and one lateral child.
            nodes.bud_free[grow] = nodes.n_children[grow] < 2
            # Kill markers within d_k of the new nodes (only the front can be that close
            # when d_k + shoot length <= d_i).
            near = front if dk + l * units.max() <= di else am
            d, _ = cKDTree(new_pos).query(markers[near], distance_upper_bound=dk)
            active[near[np.isfinite(d)]] = False
            # Buds with no active marker within the largest influence distance never grow
            # again (except the stem's apical tip, which may still bridge a gap).
            if it % 8 == 0 and active.any():
                mm = nodes.m
                b_all = np.flatnonzero(nodes.bud_free[:mm] & ~(nodes.leader[:mm] & (nodes.n_children[:mm] == 0)))
                d, _ = cKDTree(markers[active]).query(nodes.pos[b_all], distance_upper_bound=di_max)
                nodes.bud_free[b_all[~np.isfinite(d)]] = False
        else:
            if active[:n_measured].any():
                reason = "max_iterations"
        if reason == "stalled" and not active[:n_measured].any():
            reason = "done"        # only crown-filling markers were left out of reach
        return it, reason


def _cone(rng, n=900, height=12.0, crown_base=4.0, radius=2.5, ground=100.0):
    z = crown_base + (height - crown_base) * (1.0 - np.sqrt(rng.random(n)))
    r = radius * (height - z) / (height - crown_base)
    a = rng.uniform(0, 2 * np.pi, n)
    xyz = np.c_[5.0 + r * np.cos(a), -3.0 + r * np.sin(a), ground + z]
    return xyz + rng.normal(0, 0.03, xyz.shape)


def _shrub(rng, k=3, spacing=1.6):
    pts = []
    for i in range(k):
        a = 2 * np.pi * i / k
        c = np.array([spacing * np.cos(a), spacing * np.sin(a)])
        z = rng.uniform(0.0, 1.0, 40)
        pts.append(np.c_[c[0] + rng.normal(0, 0.05, 40), c[1] + rng.normal(0, 0.05, 40), z])
        u = rng.normal(size=(300, 3))
        u /= np.linalg.norm(u, axis=1)[:, None]
        pts.append(np.array([c[0], c[1], 2.0]) + u * np.array([0.8, 0.8, 1.0]))
    return np.concatenate(pts)


def cases():
    """(name, GuidedGrowth keyword arguments, TreePoints); everything generated here, seeded."""
    spec = StandSpec(width_m=40, depth_m=40, stems_per_ha=150, crown_overlap=0.3,
                     species=("conifer", "broadleaf"), species_weights=(0.5, 0.5), seed=11)
    stand = make_stand(spec)
    scan = simulate_scan(stand, ScanSpec(pulse_density=8, seed=11))
    xyz = scan.cloud.xyz - np.array([spec.origin[0], spec.origin[1], 0.0])
    out = []
    for t in stand.trees:                   # edge-cut trees too: irregular, stalls, fill
        sel = (scan.truth_tree == t.tree_id) & np.isin(scan.truth_kind, (STEM, CROWN))
        if sel.sum() >= 30:
            out.append((f"stand_{t.tree_id}", {}, TreePoints(t.tree_id, xyz[sel], t.ground_z)))
    out = out[:14]
    cone = TreePoints(3, _cone(np.random.default_rng(4)), 100.0)
    shrub = TreePoints(5, _shrub(np.random.default_rng(5)), 0.0)
    # A stem of points exactly on the z axis: V_opt parallel to the heading, so the
    # lateral direction comes from the roll angle φ (the "no azimuth" branch).
    # (From z = 0.1: a point at z = 0 would give two coincident root nodes, and exactly
    # equidistant buds are the one case the kernel orders differently from cKDTree.)
    z = np.arange(0.1, 12.0, 0.2)
    stem = np.r_[np.c_[np.zeros_like(z), np.zeros_like(z), z],
                 np.random.default_rng(0).normal(size=(200, 3)) * [1.5, 1.5, 1.0] + [0.0, 0.0, 9.0]]
    out += [("cone", {}, cone),
            ("cone_never_fill", dict(crown_fill="never"), cone),
            ("cone_conifer", dict(species="conifer"), cone),
            ("shrub", {}, shrub),
            ("shrub_preset", dict(species="shrub"), shrub),
            ("shrub_single_root", dict(multi_root=False, crown_fill="always"), shrub),
            ("stem_on_axis", {}, TreePoints(6, stem, 0.0))]
    return out


def digest(rec) -> str:
    s = rec.skeleton
    h = hashlib.sha256()
    for a in (s.nodes, s.parent, s.radius, s.is_added):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(repr((rec.flags, rec.stats["n_iterations"], rec.stats["n_nodes"], rec.stats["n_fill"],
                   rec.visited_fraction)).encode())
    return h.hexdigest()[:16]




@pytest.fixture(scope="module")
def pinned_cases():
    """Every case with the reference's digest, computed once."""
    return [(name, kw, tree, digest(NumpyGrowth(**kw).reconstruct(tree))) for name, kw, tree in cases()]


def test_kernel_equals_numpy_formulation(pinned_cases):
    assert len(pinned_cases) >= 18
    flags = {f for _, kw, tree, _ in pinned_cases for f in GuidedGrowth(**kw).reconstruct(tree).flags}
    assert {"crown_filled", "stalled", "multi_root"} <= flags          # the cases reach every path
    got = {name: digest(GuidedGrowth(**kw).reconstruct(tree)) for name, kw, tree, _ in pinned_cases}
    assert got == {name: ref for name, _, _, ref in pinned_cases}


def test_reallocation_and_roll_table_refill_change_nothing(pinned_cases, monkeypatch):
    """Tiny initial node arrays and roll tables: the kernel grows them (code 5 re-runs an iteration)."""
    codes = []
    kernel = col_method.grow_kernel

    def spy(*args):
        res = kernel(*args)
        codes.append(int(res[-1]))
        return res

    class SmallNodes(Nodes):
        def __init__(self, cap=256):
            super().__init__(4)

    tables = col_method.roll_tables

    def short_first(roll, size):           # the first table of every tree is too short
        cos, sin = tables(roll, size)
        return (cos[:1], sin[:1]) if size < 10 else (cos, sin)

    monkeypatch.setattr(col_method, "grow_kernel", spy)
    monkeypatch.setattr(col_method, "Nodes", SmallNodes)
    monkeypatch.setattr(col_method, "roll_tables", short_first)
    for name, kw, tree, ref in pinned_cases:
        codes.clear()
        assert digest(GuidedGrowth(**kw).reconstruct(tree)) == ref, name
        if name == "stem_on_axis":
            assert 5 in codes              # the roll-angle table refill was exercised


def test_pure_python_kernels_match(pinned_cases, monkeypatch):
    """Without numba (``SYLVA_NO_JIT``) the same code runs as Python: same skeleton."""
    for module, name in ((col_method, "grow_kernel"), (col_markers, "_inside_hull_kernel"),
                         (col_markers, "_pca_cov_kernel"), (col_markers, "near_any_kernel"),
                         (col_method, "near_any_kernel")):
        monkeypatch.setattr(module, name, getattr(module, name).py_func)
    name, kw, tree, ref = next(c for c in pinned_cases if c[0] == "shrub")
    assert digest(GuidedGrowth(**kw).reconstruct(tree)) == ref


def test_inside_hull_kernel_equals_einsum_test():
    """The early-exit hull test gives exactly the booleans of the einsum half-space test."""
    from scipy.spatial import ConvexHull
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(300, 3)) * [3.0, 2.0, 5.0] + [100.0, -50.0, 300.0]
    hull = ConvexHull(pts)
    q = rng.normal(size=(20000, 3)) * [4.0, 3.0, 7.0] + [100.0, -50.0, 300.0]
    eq = hull.equations
    ref = (np.einsum("ni,fi->nf", q, eq[:, :3]) + eq[:, 3] <= 1e-9).all(axis=1)
    got = col_markers._inside_hull(hull, q)
    assert 0.2 < ref.mean() < 0.9
    np.testing.assert_array_equal(got, ref)


def test_pca_covariance_kernel_equals_einsum():
    """Neighbourhood covariances of Eq. 8's PCA: identical to the numpy mean/einsum formulation."""
    rng = np.random.default_rng(3)
    xyz = rng.normal(size=(2000, 3)) * [2.0, 2.0, 6.0] + [500_000.0, 5_000_000.0, 300.0]
    _, idx = cKDTree(xyz).query(xyz, k=10)
    nb = xyz[idx]
    c = nb - nb.mean(axis=1, keepdims=True)
    ref = np.einsum("nki,nkj->nij", c, c) / 10
    np.testing.assert_array_equal(col_markers._pca_cov_kernel(xyz, idx.astype(np.int64)), ref)


@pytest.mark.parametrize("r", [0.15, 0.5, 3.0])
def test_near_any_kernel_equals_kdtree_bound(r):
    """"A centre closer than r" equals cKDTree's distance_upper_bound test, on a clustered cloud."""
    rng = np.random.default_rng(4)
    centres = np.r_[rng.normal(size=(500, 3)), rng.normal(size=(50, 3)) * 20.0] + [10.0, -4.0, 250.0]
    points = rng.normal(size=(5000, 3)) * 6.0 + [10.0, -4.0, 250.0]
    d, _ = cKDTree(centres).query(points, distance_upper_bound=r)
    got = col_markers.near_any_kernel(points, centres, r)
    assert got.any() and not got.all()
    np.testing.assert_array_equal(got, np.isfinite(d))
    assert not col_markers.near_any_kernel(points, centres[:0], r).any()
