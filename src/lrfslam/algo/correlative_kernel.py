"""The branch-and-bound search's inner loops, compiled: the mean grid value under each candidate, and a level's children.

:func:`lrfslam.algo.correlative_match.search` scores whole levels of candidates at once; in
NumPy that is a gather of ``K × N`` cells (``K`` candidates, ``N`` points) with clipping and
a mean, allocating three ``K × N`` arrays per level. It was two thirds of the mapper's time
live. Here one loop does it without temporaries. The mean is summed in candidate order, not
NumPy's pairwise order, so scores equal the NumPy form's (kept in
``tests/unit/reference_correlative.py``) within round-off, not bit for bit. A candidate whose
points all lie on the grid (each rotation's extent says so: most of them) adds one precomputed
offset per point instead of clipping a row and a column (:class:`PointCells`), in the same order.

Compiled on first use and cached beside the module (numba's ``cache=True``), as the scan
matcher's kernels are.
"""

from __future__ import annotations

import numba
import numpy as np
from numba import njit, prange

# Numba's own scheduler for the parallel loop: its threads sleep between calls, where GNU OpenMP's
# (numba's first choice where libgomp is found) spin for a while after each, on a machine whose
# every core the other stages need.
numba.config.THREADING_LAYER = "workqueue"


@njit(cache=True)
def _score_one(flat, width, height, rows, cols, offsets, extent, cand, bound, full, out, k):
    """``out[k]``: candidate ``k``'s mean, or -1 once it cannot reach ``bound``."""
    n = rows.shape[1]
    need = bound * n * full   # a candidate whose sum cannot reach this is cut (grid values are <= full)
    a, di, dj = cand[k, 0], cand[k, 1], cand[k, 2]
    total = 0.0
    if (extent[a, 0] + dj >= 0 and extent[a, 1] + dj < height and extent[a, 2] + di >= 0
            and extent[a, 3] + di < width):
        # Every point on the grid (most candidates): one offset per point, nothing to clip.
        base = dj * width + di
        for i in range(n):
            total += flat[base + offsets[a, i]]
            if (i & 15) == 15 and total + full * (n - 1 - i) < need:
                out[k] = -1.0
                return
    else:
        for i in range(n):
            r = min(max(rows[a, i] + dj, 0), height - 1)
            q = min(max(cols[a, i] + di, 0), width - 1)
            total += flat[r * width + q]
            if (i & 15) == 15 and total + full * (n - 1 - i) < need:
                out[k] = -1.0
                return
    out[k] = total / (n * full)


@njit(cache=True)
def _scores(flat, width, height, rows, cols, offsets, extent, cand, bound, full):
    out = np.empty(cand.shape[0])
    for k in range(cand.shape[0]):
        _score_one(flat, width, height, rows, cols, offsets, extent, cand, bound, full, out, k)
    return out


@njit(cache=True, parallel=True)
def _scores_parallel(flat, width, height, rows, cols, offsets, extent, cand, bound, full):
    out = np.empty(cand.shape[0])
    for k in prange(cand.shape[0]):
        _score_one(flat, width, height, rows, cols, offsets, extent, cand, bound, full, out, k)
    return out


#: Candidates from which a call is spread over the CPU's cores (each candidate is still summed
#: in one thread, in point order: the same scores on any number of threads). Below it, waking
#: the threads would cost more than they save.
PARALLEL_FROM = 20_000


class PointCells:
    """The cells of N points under each of A rotations, with what the scoring needs of them, made once
    per search: each rotation's extent, and the points' offsets in the flattened grid.

    Parameters
    ----------
    rows, cols : array_like of int, shape (A, N)
        Cells of the N points rotated by each of A angles, with the window's centre translation.
    width : int
        Columns of the grid levels they are scored on (every pooled level has the grid's).
    """

    def __init__(self, rows, cols, width: int) -> None:
        self.rows = np.ascontiguousarray(rows, dtype=np.int64)
        self.cols = np.ascontiguousarray(cols, dtype=np.int64)
        if self.rows.shape != self.cols.shape or self.rows.ndim != 2:
            raise ValueError(f"rows and cols must be alike (A, N), got {self.rows.shape} and {self.cols.shape}")
        self.width = int(width)
        self.offsets = self.rows * self.width + self.cols   # (A, N): row * width + col
        if self.rows.shape[1]:
            self.extent = np.column_stack((self.rows.min(axis=1), self.rows.max(axis=1),
                                           self.cols.min(axis=1), self.cols.max(axis=1)))
        else:
            self.extent = np.zeros((self.rows.shape[0], 4), np.int64)


def scores(grid_level: np.ndarray, cells: PointCells, cand: np.ndarray, bound: float = -np.inf) -> np.ndarray:
    """Mean of ``grid_level`` over each candidate's shifted points.

    Parameters
    ----------
    grid_level : ndarray, shape (H, W)
        A (pooled) likelihood grid, row = y: float32 in [0, 1], or uint8 in 0–255 standing for
        the value / 255 (a pooled level's bounds, a quarter of the memory to gather from).
    cells : PointCells
        The points' cells per rotation.
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
    if width != cells.width:
        raise ValueError(f"cells made for a grid {cells.width} wide, scored on one {width} wide")
    full = 255.0 if grid_level.dtype == np.uint8 else 1.0
    kernel = _scores_parallel if cand.shape[0] >= PARALLEL_FROM else _scores
    return kernel(grid_level.ravel(), width, height, cells.rows, cells.cols, cells.offsets, cells.extent,
                  np.ascontiguousarray(cand, dtype=np.int64), float(bound), full)


@njit(cache=True)
def _expand(cand, half, n_xy, admitted, base_col, base_row, size):
    """The four sub-blocks of each candidate that start inside the window and, where ``admitted`` has
    cells, hold an admitted position: the numbers of :func:`expand`, in one pass."""
    h, w = admitted.shape
    out = np.empty((4 * cand.shape[0], 3), np.int64)
    m = 0
    for k in range(cand.shape[0]):
        for c in range(4):
            i = cand[k, 1] + (half if c & 1 else 0)
            j = cand[k, 2] + (half if c & 2 else 0)
            if i > n_xy or j > n_xy:
                continue
            if h > 0:
                col, row = base_col + i, base_row + j
                if not (col + size > 0 and col < w and row + size > 0 and row < h):
                    continue
                if not admitted[max(row, 0), max(col, 0)]:
                    continue
            out[m, 0], out[m, 1], out[m, 2] = cand[k, 0], i, j
            m += 1
    return out[:m]


def expand(cand: np.ndarray, half: int, n_xy: int, admitted: np.ndarray | None = None, base_col: int = 0,
           base_row: int = 0) -> np.ndarray:
    """Children of the candidates ``cand`` (K, 3) of a branch-and-bound level, in order: each one's four
    sub-blocks offset by ``half`` cells in x and y, those starting beyond ``n_xy`` dropped, and where
    ``admitted`` (H, W) bool, a pooled position mask of the children's level indexed from cell
    ``(base_col, base_row)``, is given, those holding no admitted position (a block reaching into the
    mask from below its edge is judged by the edge's cell). (M, 3) int64."""
    mask = np.zeros((0, 0), np.bool_) if admitted is None else admitted
    return _expand(np.ascontiguousarray(cand, dtype=np.int64), int(half), int(n_xy), mask, int(base_col),
                   int(base_row), int(half))


def warm_up() -> None:
    """Compile the kernel now (or load it from numba's cache), on a tiny grid."""
    cells = PointCells(np.zeros((1, 2), np.int64), np.zeros((1, 2), np.int64), 2)
    cand = np.zeros((1, 3), np.int64)
    expand(cand, 1, 4)
    expand(cand, 1, 4, np.ones((2, 2), np.bool_))
    for dtype in (np.float32, np.uint8):
        for kernel in (_scores, _scores_parallel):
            kernel(np.zeros(4, dtype), 2, 2, cells.rows, cells.cols, cells.offsets, cells.extent, cand, 0.0, 1.0)
