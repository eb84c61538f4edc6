"""The cells one scan frees, compiled: the live grid traces every scan the mapper places.

:func:`lrfslam.algo.occupancy_grid.batch_cells` traces a batch of scans with NumPy: every cell
each beam enters as an array, then a sort to count a cell once per scan. For one scan of 181
beams of up to 8 m at 5 cm that is ~30 000 entries and about a millisecond. Here one loop
walks each beam with the same arithmetic (the start cell, then the cell entered at each grid
line crossed, read just past the line) and marks the cells of this scan in a scratch array, so
each is listed once without a sort. The cells equal the NumPy form's, which stays the oracle
(``tests/unit/test_grid_kernel.py``).

Compiled on first use and cached beside the module (numba's ``cache=True``), as the scan
matcher's kernels are.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: As :data:`lrfslam.algo.occupancy_grid._PAST`: how far past a grid line the cell entered is read, cells.
_PAST = 1e-6


@njit(cache=True)
def _visit(row, col, mark, side, rows, cols, n):
    """List cell (row, col) of the frame in ``rows``/``cols`` unless this scan marked it already."""
    f = row * side + col
    if mark[f] == 0:
        mark[f] = 1
        rows[n], cols[n] = row, col
        n += 1
    return n


@njit(cache=True)
def _trace(side, u0, v0, c, s, length, hit_rows, hit_cols, mark, rows, cols):
    """The frame cells (row, col) the beams cross and no return of the scan ends in, each once; returns their number."""
    for i in range(hit_rows.shape[0]):
        mark[hit_rows[i] * side + hit_cols[i]] = 2
    n = 0
    last = side - 1
    for b in range(u0.shape[0]):
        a_u, a_v, cb, sb, length_b = u0[b], v0[b], c[b], s[b], length[b]
        n = _visit(min(max(math.floor(a_v), 0), last), min(max(math.floor(a_u), 0), last), mark, side, rows, cols, n)
        u1, v1 = a_u + length_b * cb, a_v + length_b * sb
        for axis in range(2):
            if axis == 0:
                a0, a1, b0, da, db = a_u, u1, a_v, cb, sb
            else:
                a0, a1, b0, da, db = a_v, v1, a_u, sb, cb
            up = da > 0
            if up:
                first, final = math.floor(a0) + 1, math.ceil(a1) - 1
            else:
                first, final = math.floor(a1) + 1, math.floor(a0)
            for k in range(first, final + 1):
                other = min(max(math.floor(b0 + db * ((k - a0) / da + _PAST)), 0), last)
                entered = min(max(k if up else k - 1, 0), last)
                if axis == 0:
                    n = _visit(other, entered, mark, side, rows, cols, n)
                else:
                    n = _visit(entered, other, mark, side, rows, cols, n)
    for i in range(n):
        mark[rows[i] * side + cols[i]] = 0
    for i in range(hit_rows.shape[0]):
        mark[hit_rows[i] * side + hit_cols[i]] = 0
    return n


@njit(cache=True)
def _lay(side, shift, off_r, off_c, u0, v0, c, s, length, hit_rows, hit_cols, sign, mark, rows, cols, slots, pool,
         next_slot, touched, bounds):
    n_free = _trace(side, u0, v0, c, s, length, hit_rows, hit_cols, mark, rows, cols)
    mask = (1 << shift) - 1
    # Tiles are numbered from the frame's first; off_r, off_c put the frame's cells on the tile grid.
    for which in range(2):
        r_list, c_list = (hit_rows, hit_cols) if which == 0 else (rows, cols)
        n = hit_rows.shape[0] if which == 0 else n_free
        for i in range(n):
            touched[(r_list[i] + off_r) >> shift, (c_list[i] + off_c) >> shift] = True
    # Every tile the scan touches gets a slot of the pool before any count changes, so a pool too
    # small is found first (the caller grows it and calls again).
    need = next_slot
    for i in range(touched.shape[0]):
        for j in range(touched.shape[1]):
            if touched[i, j] and slots[i, j] < 0:
                if need >= pool.shape[0]:
                    return -1, need
                slots[i, j] = need
                need += 1
    for which in range(2):
        r_list, c_list = (hit_rows, hit_cols) if which == 0 else (rows, cols)
        n = hit_rows.shape[0] if which == 0 else n_free
        for i in range(n):
            r, q = r_list[i] + off_r, c_list[i] + off_c
            pool[slots[r >> shift, q >> shift], which, r & mask, q & mask] += sign
        if sign > 0 and n:
            for i in range(n):
                bounds[0] = min(bounds[0], r_list[i])
                bounds[1] = max(bounds[1], r_list[i])
                bounds[2] = min(bounds[2], c_list[i])
                bounds[3] = max(bounds[3], c_list[i])
    return n_free, need


class Scratch:
    """Work arrays of :func:`lay_scan`, kept between calls: fresh ones cost more than the tracing (page faults)."""

    def __init__(self) -> None:
        self.mark = np.zeros(0, np.uint8)   # zero between calls
        self.rows = np.zeros(0, np.int64)
        self.cols = np.zeros(0, np.int64)

    def ensure(self, side: int, cells: int) -> None:
        """Room for a ``side × side`` frame and ``cells`` listed cells."""
        if self.mark.size < side * side:
            self.mark = np.zeros(side * side, np.uint8)
        if self.rows.size < cells:
            self.rows, self.cols = np.empty(2 * cells, np.int64), np.empty(2 * cells, np.int64)


def lay_scan(side: int, lo_cell: np.ndarray, shift: int, u0: np.ndarray, v0: np.ndarray, c: np.ndarray,
             s: np.ndarray, length: np.ndarray, hits: np.ndarray, sign: int, slots: np.ndarray, pool: np.ndarray,
             next_slot: int, touched: np.ndarray, bounds: np.ndarray, scratch: Scratch) -> tuple[int, int]:
    """Add ``sign`` (1 or -1) to the hit count of every cell of ``hits`` and to the miss count of every
    other cell one scan's beams cross (each cell once), in tiles of a pool.

    Parameters
    ----------
    side : int
        The scan's frame is ``side × side`` cells, its lower-left cell ``lo_cell`` (row, col) from the
        map origin; indices are clipped into the frame.
    shift : int
        Tiles are ``2**shift`` cells a side; tile (row, col) holds the cells from (row, col) · 2**shift.
    u0, v0, c, s, length : ndarray, shape (B,)
        Each beam's start in cell units from the frame's lower-left corner (x, y), the cosine and
        sine of its bearing, and its free length in cell units (> 0).
    hits : ndarray of int64, shape (H,)
        Distinct flat frame indices ``row * side + col`` of the cells the scan's returns end in.
    slots : ndarray of int64, shape (R, C)
        The pool slot of each tile the frame overlaps, from the tile of ``lo_cell`` on; -1 where
        the tile has none yet. A tile the scan touches gets the next free slot (written here).
    pool : ndarray of int32, shape (capacity, 2, 2**shift, 2**shift)
        Hit (``[:, 0]``) and miss (``[:, 1]``) counts; slots from ``next_slot`` on are free (zero).
    touched : ndarray of bool, shape (R, C)
        Set where a tile's counts changed.
    bounds : ndarray of int64, shape (4,)
        (min row, max row, min col, max col) of the cells counted, in the frame's cells (from
        ``lo_cell``); widened here when ``sign`` > 0.
    scratch : Scratch
        Work arrays (one per caller; not shared between threads).

    Returns
    -------
    (free, next_slot) : (int, int)
        Cells freed and the next free slot. ``free`` -1: the pool is full and nothing was counted;
        grow it and call again with the same ``slots`` (some now filled) and this ``next_slot``.
    """
    scratch.ensure(side, int(u0.size * (2 * (np.ceil(length.max()) + 2) + 1)) if u0.size else 0)
    hits = np.asarray(hits, dtype=np.int64)
    tile = 1 << shift
    off = np.asarray(lo_cell, np.int64) - (np.asarray(lo_cell, np.int64) >> shift) * tile   # in [0, tile)
    free, need = _lay(side, shift, int(off[0]), int(off[1]), u0, v0, c, s, length, hits // side, hits % side, sign,
                      scratch.mark, scratch.rows, scratch.cols, slots, pool, next_slot, touched, bounds)
    return int(free), int(need)


def warm_up() -> None:
    """Compile the kernel now (or load it from numba's cache), on one short beam."""
    one = np.ones(1)
    bounds = np.array([np.iinfo(np.int64).max, np.iinfo(np.int64).min] * 2, np.int64)
    lay_scan(4, np.zeros(2, np.int64), 2, one, one, one, 0 * one, one, np.zeros(0, np.int64), 1,
             np.full((1, 1), -1, np.int64), np.zeros((1, 2, 4, 4), np.int32), 0, np.zeros((1, 1), bool), bounds, Scratch())
