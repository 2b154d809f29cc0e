"""PointCloud: the one data model every core function shares.

A cloud is ``xyz`` (float64, shape (n, 3), in the units of its CRS, exactly
as the file stores them), a dict of named per-point attribute arrays (LAS
dimension names: ``intensity``, ``return_number``, ``number_of_returns``,
``classification``, ``red``/``green``/``blue``, extra bytes such as
``treeID``), the CRS (a :class:`pyproj.CRS` or None) and the units of its
horizontal and vertical axes.

Computation happens in a local metric frame (ARCHITECTURE.md, conventions):
:meth:`PointCloud.local_xyz` gives metres, z-up, relative to an origin at the
tile's lower-left corner; :meth:`PointCloud.from_local` goes back. Files keep
the source CRS and units.

A cloud read from LAS/LAZ also carries ``template``: the laspy header and raw
point records, so that writing it back keeps every source dimension and VLR
(see :mod:`sylva.core.io.las`).  :meth:`subset` keeps that template in step.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Optional

import numpy as np

# Linear units Sylva recognises, as metres per unit.
METRE = 1.0
INTERNATIONAL_FOOT = 0.3048
US_SURVEY_FOOT = 1200.0 / 3937.0

UNIT_NAMES = {
    METRE: "metre",
    INTERNATIONAL_FOOT: "international foot",
    US_SURVEY_FOOT: "US survey foot",
}


@dataclass(frozen=True)
class Units:
    """Metres per unit of the horizontal and the vertical axes."""

    horizontal_m: float = METRE
    vertical_m: float = METRE

    @property
    def horizontal_name(self) -> str:
        return unit_name(self.horizontal_m)

    @property
    def vertical_name(self) -> str:
        return unit_name(self.vertical_m)

    @property
    def is_metric(self) -> bool:
        return self.horizontal_m == METRE and self.vertical_m == METRE

    def describe(self) -> str:
        if self.horizontal_m == self.vertical_m:
            return self.horizontal_name
        return f"{self.horizontal_name} (horizontal), {self.vertical_name} (vertical)"


METRES = Units()


def unit_name(metres_per_unit: float) -> str:
    for factor, name in UNIT_NAMES.items():
        if abs(factor - metres_per_unit) < 1e-9:
            return name
    return f"{metres_per_unit:g} m"


@dataclass(eq=False)
class PointCloud:
    xyz: np.ndarray
    attrs: dict = field(default_factory=dict)
    crs: Any = None  # pyproj.CRS or None
    units: Units = METRES
    source: Optional[str] = None
    template: Any = None  # io-specific record that makes a lossless write possible

    def __post_init__(self):
        self.xyz = np.asarray(self.xyz, dtype=np.float64).reshape(-1, 3)
        n = len(self.xyz)
        for name, values in self.attrs.items():
            if len(values) != n:
                raise ValueError(f"attribute {name!r} has {len(values)} values for {n} points")

    def __len__(self) -> int:
        return len(self.xyz)

    @property
    def name(self) -> str:
        """How messages refer to this cloud: its file name, or 'the point cloud'."""
        return str(self.source) if self.source else "the point cloud"

    @property
    def origin(self) -> np.ndarray:
        """Lower-left corner (min x, min y, 0) in CRS units: the local frame's origin."""
        if len(self) == 0:
            return np.zeros(3)
        return np.array([self.xyz[:, 0].min(), self.xyz[:, 1].min(), 0.0])

    def bounds(self) -> tuple:
        """(xmin, ymin, zmin, xmax, ymax, zmax) in CRS units."""
        return (*self.xyz.min(axis=0), *self.xyz.max(axis=0))

    def local_xyz(self, origin: Optional[np.ndarray] = None) -> np.ndarray:
        """Coordinates in metres relative to ``origin`` (default :attr:`origin`), z up."""
        origin = self.origin if origin is None else np.asarray(origin, dtype=np.float64)
        scale = np.array([self.units.horizontal_m] * 2 + [self.units.vertical_m])
        return (self.xyz - origin) * scale

    def from_local(self, local: np.ndarray, origin: Optional[np.ndarray] = None) -> np.ndarray:
        """Inverse of :meth:`local_xyz`: local metres back to CRS units."""
        origin = self.origin if origin is None else np.asarray(origin, dtype=np.float64)
        scale = np.array([self.units.horizontal_m] * 2 + [self.units.vertical_m])
        return np.asarray(local, dtype=np.float64) / scale + origin

    def attr(self, name: str, default=None) -> Optional[np.ndarray]:
        return self.attrs.get(name, default)

    def with_attrs(self, **arrays) -> "PointCloud":
        """A copy with attributes added or replaced (arrays of length n)."""
        attrs = dict(self.attrs)
        attrs.update({k: np.asarray(v) for k, v in arrays.items()})
        return replace(self, attrs=attrs)

    def subset(self, index) -> "PointCloud":
        """The points selected by a boolean mask or an index array."""
        index = np.asarray(index)
        template = self.template.subset(index) if self.template is not None else None
        return replace(
            self,
            xyz=self.xyz[index],
            attrs={k: v[index] for k, v in self.attrs.items()},
            template=template,
        )


#: Local frames are anchored on multiples of this many metres (a common multiple of
#: 0.7 m ncut voxels, 0.5 m CHM cells, 5 m noise voxels, 0.2 m thinning voxels, 1 m cells).
ANCHOR_GRID_M = 70.0


@dataclass(eq=False)
class AnchoredCloud(PointCloud):
    """A :class:`PointCloud` whose local frame starts at ``anchor`` (CRS units), not at its minimum.

    (Sylva, not in the paper.) An anchor on multiples of :data:`ANCHOR_GRID_M` puts voxels and grid
    cells at the same places whatever the tiling, which keeps tree IDs and labels tiling-invariant.
    ``dataclasses.replace`` (used by ``subset``/``with_attrs``) keeps the anchor.
    """

    anchor: Any = None

    @property
    def origin(self) -> np.ndarray:  # noqa: D102
        if self.anchor is None:
            return super().origin
        return np.asarray(self.anchor, dtype=np.float64)
