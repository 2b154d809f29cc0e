"""What a lossless write needs: :class:`LasTemplate`, a cloud's source header and raw point records.

Also laspy itself, imported lazily (:func:`load_laspy`: ``import sylva.core`` must not need laspy), and
the names of the records' integer coordinate fields (:data:`XYZ`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np


XYZ = ("X", "Y", "Z")


def load_laspy():
    import laspy  # imported lazily: `import sylva.core` must not need laspy

    return laspy


@dataclass(eq=False)
class LasTemplate:
    """What a lossless write needs: the source header and raw point records.

    ``header`` is the laspy :class:`~laspy.LasHeader` of the source file (never
    modified; :func:`write_las` works on a copy), ``array`` the raw structured
    numpy record array (integer X/Y/Z, packed bit fields, extra bytes) of the
    points the cloud holds, and ``crs`` the CRS parsed from the header (so a
    writer can tell whether the cloud's CRS was overridden).
    """

    header: Any
    array: np.ndarray
    crs: Any = None

    def subset(self, index) -> "LasTemplate":
        """The records of the selected points (boolean mask or index array)."""
        return LasTemplate(self.header, self.array[np.asarray(index)], self.crs)

    def __len__(self) -> int:
        return len(self.array)

    def record(self):
        """The records as a laspy ScaleAwarePointRecord (shares memory)."""
        laspy = load_laspy()
        h = self.header
        return laspy.ScaleAwarePointRecord(self.array, h.point_format, h.scales, h.offsets)
