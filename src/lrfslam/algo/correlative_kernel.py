"""The branch-and-bound search's inner loop, compiled: the mean grid value under each candidate.

:func:`lrfslam.algo.correlative_match.search` scores whole levels of candidates at once; in
NumPy that is a gather of ``K × N`` cells (``K`` candidates, ``N`` points) with clipping and
a mean, allocating three ``K × N`` arrays per level. It was two thirds of the mapper's time
live. Here one loop does it without temporaries. The mean is summed in candidate order, not
NumPy's pairwise order, so scores equal the NumPy form's (kept in
``tests/unit/reference_correlative.py``) within round-off, not bit for bit.

Compiled on first use and cached beside the module (numba's ``cache=True``), as the scan
matcher's kernels are.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _scores(flat, width, height, rows, cols, cand, bound):
    k_count, n = cand.shape[0], rows.shape[1]
    out = np.empty(k_count)
    need = bound * n   # a candidate whose sum cannot reach this is cut (grid values are <= 1)
    for k in range(k_count):
        a, di, dj = cand[k, 0], cand[k, 1], cand[k, 2]
        total = 0.0
        cut = False
        for i in range(n):
            r = min(max(rows[a, i] + dj, 0), height - 1)
            q = min(max(cols[a, i] + di, 0), width - 1)
            total += flat[r * width + q]
            if (i & 15) == 15 and total + (n - 1 - i) < need:
                cut = True
                break
        out[k] = -1.0 if cut else total / n
    return out


def scores(grid_level: np.ndarray, rows: np.ndarray, cols: np.ndarray, cand: np.ndarray,
           bound: float = -np.inf) -> np.ndarray:
    """Mean of ``grid_level`` over each candidate's shifted points.

    Parameters
    ----------
    grid_level : ndarray, shape (H, W)
        A (pooled) likelihood grid, row = y.
    rows, cols : ndarray of int64, shape (A, N)
        Cells of the N points rotated by each of A angles, with the window's centre translation.
    cand : ndarray of int64, shape (K, 3)
        Candidates ``(angle index, x offset, y offset)`` in cells.

    bound : float
        Candidates that cannot reach this mean (the grid's values are at most 1) are scored -1
        as soon as that is certain: the search cuts them anyway, and most are cut after a
        fraction of their points. The others' scores are summed as without it.

    Returns
    -------
    ndarray, shape (K,)
        Mean grid value (float64) under each candidate's points, indices clipped into the grid;
        -1 for a candidate cut by ``bound``.
    """
    height, width = grid_level.shape
    return _scores(grid_level.ravel(), width, height, rows, cols, np.ascontiguousarray(cand, dtype=np.int64),
                   float(bound))


def warm_up() -> None:
    """Compile the kernel now (or load it from numba's cache), on a tiny grid."""
    idx = np.zeros((1, 2), np.int64)
    scores(np.zeros((2, 2), np.float32), idx, idx, np.zeros((1, 3), np.int64))
