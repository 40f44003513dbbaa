"""Kernel of the tree labeller's cell shortcuts (:class:`vlsforest.extract.TreeLabeller`).

Kept apart from :mod:`vlsforest.extract` so that commands that never label by distance do not
import numba.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: bits of a cell's code: within 3 cells of the tree's points / holds one of them
NEAR, INNER = 1, 2


@njit(cache=True)
def near_points(xyz, near, eligible, lo, hi, cell, codes, has_codes, tid, n_near, in_inner, inner_tree, out):
    """Mark the points of ``near`` (indices into ``xyz``) that lie near one tree.

    A point counts when it is eligible and inside the box [``lo``, ``hi``]; it is near when its
    cell's code has :data:`NEAR` (or always, without ``codes``), and then it is counted in
    ``n_near``, written to ``out`` and, when its cell has :data:`INNER`, flagged in ``in_inner``
    with ``tid`` in ``inner_tree``. The cell of a point is ``floor((x − lo) / cell)`` per axis,
    clipped to the grid, in float64 as numpy computes it. Returns the number written to ``out``.
    """
    k = 0
    nx, ny, nz = codes.shape
    for j in range(near.shape[0]):
        i = near[j]
        if not eligible[i]:
            continue
        x, y, z = xyz[i, 0], xyz[i, 1], xyz[i, 2]
        if not (x >= lo[0] and x <= hi[0] and y >= lo[1] and y <= hi[1] and z >= lo[2] and z <= hi[2]):
            continue
        c = NEAR
        if has_codes:
            a = min(max(np.int64(np.floor((x - lo[0]) / cell)), 0), nx - 1)
            b = min(max(np.int64(np.floor((y - lo[1]) / cell)), 0), ny - 1)
            e = min(max(np.int64(np.floor((z - lo[2]) / cell)), 0), nz - 1)
            c = codes[a, b, e]
        if c & NEAR:
            n_near[i] += 1
            out[k] = i
            k += 1
            if c & INNER:
                in_inner[i] = True
                inner_tree[i] = tid
    return k
