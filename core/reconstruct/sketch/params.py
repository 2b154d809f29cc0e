"""The parameters of the sketch method: :class:`SketchTree` (the sketch paper's Table 1 where it gives them,
Sylva's values elsewhere), checked when the value is made."""
from __future__ import annotations

from dataclasses import dataclass

from ...errors import InputError


# --------------------------------------------------------------------------- parameters

@dataclass(frozen=True)
class SketchTree:
    """Parameters of the sketch method (paper defaults from Table 1 where it gives them).

    * ``sigma`` σ = 0.3: a sub-branch copies the first σ·k nodes of its parent (§6, Eq. 8);
    * ``cos_theta1`` = 0.5, ``cos_theta2`` = 0.9: range of cos θ, the angle between a
      sub-branch and its parent branch at the bud (Table 1; θ from 25.8° to 60°);
    * ``cos_phi1`` = −0.5, ``cos_phi2`` = 0.5: range of cos φ, the angle between two
      consecutive sub-branches of one branch (Table 1; φ from 60° to 120°);
    * ``levels`` l = 2: generations of small branches (Table 1);
    * ``buds_per_branch`` buds per branch η before crowding removal (not given by
      the paper: 8); they are spread evenly along η, and on the trunk only above
      the lowest main fork (the crown base);
    * ``crowd_radius_fraction`` and ``crowd_max``: a bud is removed when more than
      ``crowd_max`` small-branch nodes already lie within ``crowd_radius_fraction`` ×
      height of it (§6 "removing buds in crowded areas"; the paper gives no values:
      0.05 and 12);
    * ``step_fraction`` strokes are resampled every ``step_fraction`` × height
      (Sylva: 0.01), so depth retrieval pairs points of equal height (Eq. 5);
    * ``snap_fraction`` a stroke end within ``snap_fraction`` × drawing height of
      another stroke joins it (digitising rarely hits a line exactly; Sylva: 0.02);
    * ``grow`` False keeps the main branches only;
    * ``seed`` of the random generator (θ, φ, bud jitter): same inputs, same tree.
    """

    sigma: float = 0.3
    cos_theta1: float = 0.5
    cos_theta2: float = 0.9
    cos_phi1: float = -0.5
    cos_phi2: float = 0.5
    levels: int = 2
    buds_per_branch: int = 8
    crowd_radius_fraction: float = 0.05
    crowd_max: int = 12
    step_fraction: float = 0.01
    snap_fraction: float = 0.02
    grow: bool = True
    seed: int = 0

    name = "sketch"

    def __post_init__(self):
        if not 0 < self.sigma <= 1:
            raise InputError(f"SketchTree: sigma must be in (0, 1], got {self.sigma!r}")
        for a, b in (("cos_theta1", "cos_theta2"), ("cos_phi1", "cos_phi2")):
            lo, hi = getattr(self, a), getattr(self, b)
            if not (-1 <= lo <= 1 and -1 <= hi <= 1 and lo <= hi):
                raise InputError(f"SketchTree: {a} and {b} must be cosines with {a} <= {b}, got {lo!r}, {hi!r}")
        if int(self.levels) != self.levels or self.levels < 0:
            raise InputError(f"SketchTree: levels must be a whole number >= 0, got {self.levels!r}")
        if int(self.buds_per_branch) != self.buds_per_branch or self.buds_per_branch < 0:
            raise InputError(f"SketchTree: buds_per_branch must be a whole number >= 0, got {self.buds_per_branch!r}")
        if int(self.crowd_max) != self.crowd_max or self.crowd_max < 0:
            raise InputError(f"SketchTree: crowd_max must be a whole number >= 0, got {self.crowd_max!r}")
        for attr in ("crowd_radius_fraction", "step_fraction", "snap_fraction"):
            if not (getattr(self, attr) > 0 and getattr(self, attr) < 1):
                raise InputError(f"SketchTree: {attr} must be in (0, 1), got {getattr(self, attr)!r}")
