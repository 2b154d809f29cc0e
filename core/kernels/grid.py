"""Square grid cells of 2-D positions, for kernels that keep one point a cell (Sylva, not in the papers)."""
from __future__ import annotations

import numpy as np

from ..jit import helper

__all__ = ["grid_cells"]


@helper
def grid_cells(xy, cell, max_cells):
    """``(ix, iy, x0, y0, nx, ny)``: the column and row of every position (``floor(x / cell)``, from the
    first two columns of ``xy``) and the bounding block of cells, ``nx`` by ``ny`` from (x0, y0).

    ``nx == 0`` (and empty ix, iy) when there is no position, a coordinate is not finite or beyond ``max_cells`` cells from 0,
    or the block would hold more than ``max_cells`` cells: the caller then takes its sorting route."""
    n = xy.shape[0]
    ix = np.empty(n, dtype=np.int64)
    iy = np.empty(n, dtype=np.int64)
    x0, y0, x1, y1 = 0, 0, 0, 0
    for i in range(n):
        fx = np.floor(xy[i, 0] / cell)
        fy = np.floor(xy[i, 1] / cell)
        if not (abs(fx) < max_cells and abs(fy) < max_cells):
            return ix[:0], iy[:0], 0, 0, 0, 0
        ix[i], iy[i] = int(fx), int(fy)
        if i == 0:
            x0, y0, x1, y1 = ix[i], iy[i], ix[i], iy[i]
        x0, y0 = min(x0, ix[i]), min(y0, iy[i])
        x1, y1 = max(x1, ix[i]), max(y1, iy[i])
    nx, ny = x1 - x0 + 1, y1 - y0 + 1
    if n == 0 or nx * ny > max_cells:
        return ix[:0], iy[:0], 0, 0, 0, 0
    return ix, iy, x0, y0, nx, ny
