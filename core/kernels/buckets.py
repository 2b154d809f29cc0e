"""Items grouped by cell in one counting sort (compressed rows), for kernels that visit cells."""
from __future__ import annotations

import numpy as np

from ..jit import helper

__all__ = ["bucket_by_cell"]


@helper
def bucket_by_cell(cell, ncell):
    """``(start, order)``: the items of cell ``c`` (ids in [0, ncell)) are ``order[start[c]:start[c + 1]]``,
    in increasing index order (a stable counting sort: two passes over ``cell``, one over the cells)."""
    m = cell.shape[0]
    start = np.zeros(ncell + 1, dtype=np.int64)
    for i in range(m):
        start[cell[i] + 1] += 1
    for c in range(ncell):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    order = np.empty(m, dtype=np.int64)
    for i in range(m):
        order[fill[cell[i]]] = i
        fill[cell[i]] += 1
    return start, order
