"""The extended synthetic suite (sylva/testing/crowns.py): clumped broadleaf crowns, mixed stands."""
import numpy as np
import pytest

from sylva.testing import synth
from sylva.core.errors import InputError
from sylva.testing import crowns


def test_clumped_crowns_have_their_forms_and_truth():
    stand = crowns.suite_stand("mixed", "medium", seed=1, width_m=40.0)
    forms = crowns.crown_forms(stand)
    assert set(forms.values()) >= {"conifer", "round"} and len(forms) == len(stand.trees)
    for t in stand.trees:
        rows = slice(stand.part_ptr[t.tree_id - 1], stand.part_ptr[t.tree_id])
        kind = stand.parts["kind"][rows]
        if forms[t.tree_id] == "conifer":
            assert (kind == synth._CONE).sum() == 1
            continue
        clumps = kind == synth._ELLIPSOID
        assert clumps.sum() >= 6                        # a crown of many leaf clumps
        top = stand.parts["zt"][rows][clumps].max()
        assert top - t.ground_z == pytest.approx(t.height)   # truth height: the highest clump
        # clumps lie within the crown radius of the truth table
        d = np.hypot(stand.parts["cx"][rows][clumps] - t.x, stand.parts["cy"][rows][clumps] - t.y)
        assert (d + stand.parts["a"][rows][clumps] <= t.crown_radius_m + 1e-9).all()
    scan = synth.simulate_scan(stand, synth.ScanSpec(pulse_density=5.0, seed=1))
    tree_ids = np.unique(scan.truth_tree[scan.truth_tree > 0])
    assert len(tree_ids) > 0.9 * len(stand.trees)       # nearly every tree is seen from the air
    assert "suppressed" in forms.values() or len(stand.trees) < 10


def test_profiles_of_the_envelopes():
    u = np.linspace(0, 1, 11)
    assert crowns._profile(0.5, "round") == pytest.approx(1.0)
    assert crowns._profile(0.75, "flat") == pytest.approx(1.0)
    # flat-topped: still wide near the top; round: narrowing like an ellipse
    assert crowns._profile(0.95, "flat") > crowns._profile(0.95, "round")
    assert crowns._profile(0.9, "cylinder") > 0.9
    assert (crowns._profile(u, "round") >= 0).all() and crowns._profile(1.0, "round") == 0


def test_bad_kind_is_one_clear_error():
    with pytest.raises(InputError, match="kind"):
        crowns.suite_stand("palm", "open")
    with pytest.raises(InputError, match="structure"):
        crowns.suite_stand("broadleaf", "sparse")


def test_parkland_crowns_are_open_grown_and_cover_as_much_ground():
    """Open-grown broadleaves: OPEN_GROWN_SCALE x the forest crown radius, OPEN_GROWN_SCALE² fewer
    stems, so the canopy covers about as much ground as the broadleaf stand of the same structure."""
    def radius_share_and_cover(kind):
        stand = crowns.suite_stand(kind, "open", seed=1)
        r = np.array([t.crown_radius_m for t in stand.trees])
        h = np.array([t.height for t in stand.trees])
        return np.median(r / h), len(stand.trees), np.pi * (r ** 2).sum() / 1e4

    park, n_park, cover_park = radius_share_and_cover("parkland")
    forest, n_forest, cover_forest = radius_share_and_cover("broadleaf")
    assert park > 0.3 and park > 2.0 * forest
    assert n_park < n_forest / 4
    assert 0.6 < cover_park / cover_forest < 1.6
    assert set(crowns.crown_forms(crowns.suite_stand("parkland", "open", seed=1)).values()) <= set(crowns.FORMS)
    with pytest.raises(InputError, match="crown_scale"):
        synth.StandSpec(crown_scale=0.0)


def test_tall_stands_are_the_mixed_stand_grown_taller():
    """"tall": the mixed stand's trees at TALL_HEIGHT_M (30-60 m) instead of 8-30 m."""
    tall = crowns.suite_stand("tall", "open", seed=1)
    mixed = crowns.suite_stand("mixed", "open", seed=1)
    h_tall = np.array([t.height for t in tall.trees])
    h_mixed = np.array([t.height for t in mixed.trees])
    dominant = h_tall[[crowns.crown_forms(tall)[t.tree_id] != "suppressed" for t in tall.trees]]
    assert dominant.min() > 0.95 * crowns.TALL_HEIGHT_M[0] and dominant.max() < 1.05 * crowns.TALL_HEIGHT_M[1]
    assert np.median(h_tall) > 1.8 * np.median(h_mixed)
    assert set(crowns.crown_forms(tall).values()) >= {"conifer", "suppressed"}


def test_a_suite_stand_can_stand_on_a_slope():
    """slope_deg tilts the suite's ground (steepest descent eastwards, synth's default azimuth)
    under the same trees: 20 degrees drop tan(20 deg) x 30 m, give or take synth's gentle relief."""
    level = crowns.suite_stand("broadleaf", "open", seed=1, width_m=40.0)
    steep = crowns.suite_stand("broadleaf", "open", seed=1, width_m=40.0, slope_deg=20.0)
    x0, y0 = steep.spec.origin
    drop = float(steep.ground_z(x0 + 5.0, y0 + 20.0) - steep.ground_z(x0 + 35.0, y0 + 20.0))
    flat = float(level.ground_z(x0 + 5.0, y0 + 20.0) - level.ground_z(x0 + 35.0, y0 + 20.0))
    assert abs(drop - np.tan(np.radians(20.0)) * 30.0) < 1.0 and abs(flat) < 1.0
    assert np.allclose([t.height for t in steep.trees], [t.height for t in level.trees])
