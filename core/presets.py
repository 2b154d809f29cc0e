"""Named sets of defaults for the frozen method dataclasses (species of GuidedGrowth, growth of NormalizedCut)."""
from __future__ import annotations

from dataclasses import fields


def apply_preset(method, values: dict) -> None:
    """Set each field of ``values`` on the frozen dataclass ``method`` (from its ``__post_init__``) where
    the field still has its default: a preset never overrides a value the caller gave."""
    defaults = {f.name: f.default for f in fields(method)}
    for key, value in values.items():
        if getattr(method, key) == defaults[key]:
            object.__setattr__(method, key, value)
