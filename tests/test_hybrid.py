"""Hu et al. 2017 §6.2 hybrid rule: core/reconstruct/hybrid.py."""
from __future__ import annotations

import numpy as np
import pytest

from sylva.core.errors import Cancelled, EmptyInputError, InputError
from sylva.core.reconstruct.colonize import GuidedGrowth
from sylva.core.reconstruct.hybrid import Hybrid
from sylva.core.reconstruct.model import Reconstruction, TreePoints, minimal_skeleton
from sylva.core.skeleton import Skeleton
from sylva.core.reconstruct.skeleton import GreedySkeleton
from sylva.testing.synth import CROWN, STEM, ScanSpec, StandSpec, make_stand, simulate_scan


class StubPrimary:
    """A primary method with a fixed outcome; counts its calls."""

    name = "stub"

    def __init__(self, visited=0.95, connected=True, flags=(), raises=None):
        self.visited, self.connected, self.flags, self.raises = visited, connected, list(flags), raises
        self.calls = 0

    def reconstruct(self, tree, progress=None, cancelled=None):
        self.calls += 1
        if self.raises is not None:
            raise self.raises
        if progress is not None:
            progress(1.0, "stub")
        skel = minimal_skeleton(tree.xyz, tree.ground_z)
        return Reconstruction(skel, self.name, self.visited, self.connected, {"stub": True},
                              list(self.flags), tree.tree_id)


class CountingFallback(GuidedGrowth):
    """The real guided growth, counting how often the hybrid calls it."""

    calls = 0

    def reconstruct(self, tree, progress=None, cancelled=None):
        type(self).calls += 1
        return super().reconstruct(tree, progress, cancelled)


def cone(seed=0, n=500):
    rng = np.random.default_rng(seed)
    z = 3.0 + 7.0 * (1.0 - np.sqrt(rng.random(n)))
    r = 2.0 * (10.0 - z) / 7.0
    a = rng.uniform(0, 2 * np.pi, n)
    return TreePoints(11, np.c_[r * np.cos(a), r * np.sin(a), z], 0.0)


@pytest.fixture(autouse=True)
def _reset_counter():
    CountingFallback.calls = 0


def test_keeps_primary_when_it_visits_enough():
    prim = StubPrimary(visited=0.9)
    rec = Hybrid(prim, CountingFallback()).reconstruct(cone())
    assert prim.calls == 1 and CountingFallback.calls == 0
    assert rec.method == "stub" and rec.visited_fraction == 0.9 and rec.stats["stub"]
    assert rec.stats["hybrid_used"] == "stub" and rec.stats["hybrid_reasons"] == []
    assert "fallback" not in rec.flags
    # exactly at the threshold is kept (Hu: exported when "greater than 85 %"; Sylva keeps >= 0.85)
    assert Hybrid(StubPrimary(visited=0.85), CountingFallback()).reconstruct(cone()).method == "stub"


def test_switches_when_visited_fraction_is_low():
    tree = cone()
    rec = Hybrid(StubPrimary(visited=0.6), CountingFallback(), min_visited=0.85).reconstruct(tree)
    assert CountingFallback.calls == 1
    assert rec.method == "guided_growth"
    assert "fallback" in rec.flags and "fallback:low_visited" in rec.flags
    assert rec.stats["primary_visited_fraction"] == 0.6 and rec.stats["primary_method"] == "stub"
    assert rec.stats["hybrid_used"] == "guided_growth" and rec.stats["hybrid_reasons"] == ["low_visited"]
    # the fallback result is the real guided growth: covers the points
    assert (rec.skeleton.distance(tree.xyz) < 0.5).mean() >= 0.9
    assert rec.visited_fraction >= 0.9 and rec.connected
    # a lower threshold keeps the same primary
    assert Hybrid(StubPrimary(visited=0.6), CountingFallback(), min_visited=0.5).reconstruct(tree).method == "stub"


@pytest.mark.parametrize("prim, reason", [
    (StubPrimary(visited=0.99, connected=False), "disconnected"),
    (StubPrimary(visited=0.99, flags=["needs_fallback"]), "needs_fallback"),
    (StubPrimary(visited=0.99, flags=["too_few_points"]), "too_few_points"),
    (StubPrimary(raises=InputError("tree 11: broken")), "primary_error"),
])
def test_switches_on_failure(prim, reason):
    rec = Hybrid(prim, CountingFallback()).reconstruct(cone())
    assert rec.method == "guided_growth" and CountingFallback.calls == 1
    assert f"fallback:{reason}" in rec.flags and reason in rec.stats["hybrid_reasons"]
    if reason == "primary_error":
        assert "broken" in rec.stats["primary_error"]


def test_cancel_and_empty_are_not_swallowed():
    with pytest.raises(Cancelled):
        Hybrid(StubPrimary(raises=Cancelled()), CountingFallback()).reconstruct(cone())
    with pytest.raises(Cancelled):
        Hybrid(StubPrimary(visited=0.1), CountingFallback()).reconstruct(cone(), cancelled=lambda: True)
    with pytest.raises(EmptyInputError):
        Hybrid().reconstruct(TreePoints(3, np.zeros((0, 3)), 0.0))
    assert CountingFallback.calls == 0


def test_progress_is_monotone_and_ends_at_one():
    seen = []
    Hybrid(StubPrimary(visited=0.1), CountingFallback()).reconstruct(cone(), progress=lambda f, m: seen.append(f))
    assert seen[-1] == 1.0 and all(b >= a - 1e-12 for a, b in zip(seen, seen[1:]))


def test_validation_and_defaults():
    h = Hybrid()
    assert isinstance(h.primary, GreedySkeleton) and isinstance(h.fallback, GuidedGrowth)
    assert h.min_visited == 0.85
    with pytest.raises(InputError, match="min_visited"):
        Hybrid(min_visited=1.5)
    with pytest.raises(InputError, match="primary"):
        Hybrid(primary=object())


def test_real_greedy_skeleton_on_synthetic_stand():
    """The real primary: the hybrid switches exactly for the trees the greedy skeleton fails."""
    spec = StandSpec(width_m=50, depth_m=50, stems_per_ha=120, crown_overlap=0.0, seed=3)
    stand = make_stand(spec)
    scan = simulate_scan(stand, ScanSpec(pulse_density=10, seed=3))
    x0, y0 = spec.origin
    xyz = scan.cloud.xyz - np.array([x0, y0, 0.0])
    greedy, hybrid = GreedySkeleton(), Hybrid()
    # A crippled greedy skeleton (tiny graph radius, one neighbour) must fail and switch.
    crippled = GreedySkeleton(radius_m=0.3, k=1)
    n_trees = forced = 0
    for t in stand.trees[:12]:
        sel = (scan.truth_tree == t.tree_id) & np.isin(scan.truth_kind, (STEM, CROWN))
        if sel.sum() < 30:
            continue
        n_trees += 1
        tree = TreePoints(t.tree_id, xyz[sel], t.ground_z)
        g = greedy.reconstruct(tree)
        rec = hybrid.reconstruct(tree)
        fails = g.visited_fraction < 0.85 or not g.connected or "needs_fallback" in g.flags
        if fails:
            assert rec.method == "guided_growth"
            assert rec.stats["primary_visited_fraction"] == pytest.approx(g.visited_fraction)
            assert (rec.skeleton.distance(tree.xyz) < 0.5).mean() >= 0.9
        else:
            assert rec.method == g.method and "fallback" not in rec.flags
            np.testing.assert_array_equal(rec.skeleton.nodes, g.skeleton.nodes)
        assert isinstance(rec.skeleton, Skeleton) and rec.skeleton.parent[0] == -1
        c = crippled.reconstruct(tree)
        if c.visited_fraction < 0.85 or not c.connected:
            forced += 1
            r2 = Hybrid(primary=crippled).reconstruct(tree)
            assert r2.method == "guided_growth"
            assert r2.stats["primary_visited_fraction"] == pytest.approx(c.visited_fraction)
    assert n_trees >= 8 and forced >= n_trees // 2
