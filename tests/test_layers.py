"""Apexes of a lower crown layer (core/segment/ncut/layers.py)."""
import numpy as np
import pytest

from sylva.core.segment.ncut.cleanup import crown_radius_m
from sylva.core.segment.ncut.layers import LAYER_GAP_M, LAYER_MIN_DENSITY, lower_layer_apexes

TOP_H = 20.0


def _scene(apex_h=10.0, upper_h=18.0, ring=0.8, seed=0):
    """A higher top at the origin; a lower tree's apex ``ring`` crown radii east of it at ``apex_h``,
    under a layer of the higher crown at ``upper_h``, its own crown a cone below the apex."""
    rng = np.random.default_rng(seed)
    ax = ring * float(crown_radius_m(TOP_H))
    # the higher crown's layer over the lower apex: 25 points/m2 on a 3 m square
    upper = np.column_stack([rng.uniform(ax - 1.5, ax + 1.5, 225), rng.uniform(-1.5, 1.5, 225),
                             np.full(225, upper_h) + rng.uniform(-0.2, 0.2, 225)])
    # the lower crown: a cone 4 m deep under the apex
    depth = rng.uniform(0.1, 4.0, 300)
    phi = rng.uniform(0, 2 * np.pi, 300)
    rad = 0.4 * depth
    lower = np.column_stack([ax + rad * np.cos(phi), rad * np.sin(phi), apex_h - depth])
    pts = np.vstack([[[ax, 0.0, apex_h]], upper, lower])
    return pts[:, :2].copy(), pts[:, 2].copy()


def _apexes(xy, h, density=10.0, cover=1.0, top_xy=((0.0, 0.0),)):
    return lower_layer_apexes(xy, h, np.full(len(h), density), np.asarray(top_xy, dtype=float),
                              np.array([TOP_H] * len(top_xy)), 1.0,
                              lambda p, z: np.full(len(p), cover))


def test_the_apex_under_a_gap_is_found():
    xy, h = _scene()
    assert _apexes(xy, h).tolist() == [0]


def test_same_apex_whatever_the_order_of_the_points():
    xy, h = _scene()
    order = np.random.default_rng(5).permutation(len(h))
    found = _apexes(xy[order], h[order])
    assert len(found) == 1 and order[found[0]] == 0


@pytest.mark.parametrize("case", ["no gap", "sparse scan", "open canopy", "crown centre", "no higher top",
                                  "same layer", "no crown below"])
def test_no_apex(case):
    kw = {}
    if case == "no gap":           # the higher crown's points come down into the 2 m above the apex
        xy, h = _scene(upper_h=10.0 + 0.5 * LAYER_GAP_M)
    elif case == "crown centre":   # nearer to the higher top than half its crown radius: its own branch
        xy, h = _scene(ring=0.3)
    elif case == "same layer":     # 90 % of the higher top's height: a neighbour in its layer
        xy, h = _scene(apex_h=0.9 * TOP_H, upper_h=0.9 * TOP_H + 3.0)
    elif case == "no crown below":  # a lone point under the higher crown: a twig, not a tree
        xy, h = _scene()
        xy, h = xy[:226], h[:226]
    else:
        xy, h = _scene()
        kw = {"sparse scan": {"density": 0.5 * LAYER_MIN_DENSITY}, "open canopy": {"cover": 0.5},
              "no higher top": {"top_xy": ((50.0, 50.0),)}}[case]
    assert 0 not in _apexes(xy, h, **kw).tolist()
