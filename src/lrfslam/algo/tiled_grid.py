"""An occupancy grid kept in square tiles, from scans that can be taken out and laid again.

The live map (``map/grid``): each keyframe's scan is laid at its pose, traced as
:mod:`lrfslam.algo.occupancy_grid` traces a whole recording for ``lrfslam export`` (the same
cells, the same hit-or-miss rule per scan); when an optimisation moves a keyframe, its scan is
taken out where it was laid and laid again where it now is.

A cell keeps its numbers of hits and misses (integers, so taking a scan out is exact); its
log-odds ``hits · hit_log_odds + misses · miss_log_odds``, clamped to
``[min_log_odds, max_log_odds]``, is export's for the same scans at the same poses.

Tiles of ``tile_cells × tile_cells`` cells exist where scans reached: memory is 8 bytes a cell
of those tiles, so it grows with the area seen, not with the time. The resolution is
``params.resolution_m`` until the cells touched would span more than ``params.max_cells``
(their bounding box and a one-cell border, as export sizes its grid); then it doubles and every
scan is laid again: :func:`~lrfslam.algo.occupancy_grid.fitting_resolution`'s rule, applied as
the map grows.

Tile ``(row, col)`` holds cells ``[row·T, (row+1)·T) × [col·T, (col+1)·T)`` counted from the
world origin: cell ``(i, j)`` covers ``x in [j·res, (j+1)·res)``, ``y in [i·res, (i+1)·res)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lrfslam.algo import grid_kernel
from lrfslam.algo.occupancy_grid import (
    GridParams,
    OccupancyGrid,
    beam_lengths,
    beam_points,
    flat_index,
)
from lrfslam.errors import InputError

#: Default side of a tile, cells (64 × 64 cells: 3.2 m at 5 cm, 4 KB of trinary cells).
TILE_CELLS = 64


@dataclass(frozen=True, eq=False)
class LaidScan:
    """A scan as laid: its pose (3,), ranges (N,) float32 and beam layout."""

    pose: np.ndarray
    ranges: np.ndarray
    angle_min_rad: float
    angle_increment_rad: float


class TiledGrid:
    """Hit and miss counts in tiles, from scans laid under keys (a keyframe's stamp, say).

    Parameters
    ----------
    params : GridParams
        Tracing rules, the finest resolution, and ``max_cells`` (default: ``lrfslam export``'s).
    tile_cells : int
        Side of a tile, cells: a power of two.
    """

    def __init__(self, params: GridParams | None = None, tile_cells: int = TILE_CELLS) -> None:
        if tile_cells < 1 or tile_cells & (tile_cells - 1):
            raise InputError(f"tile_cells must be a power of two, got {tile_cells}")
        params = GridParams() if params is None else params
        self.params = params
        self.tile_cells = int(tile_cells)
        self._shift = self.tile_cells.bit_length() - 1
        self.resolution_m = float(params.resolution_m)
        #: Counts the resolution changed (each time every tile changes).
        self.resolution_changes = 0
        self._laid: dict[int, LaidScan] = {}
        self._scratch = grid_kernel.Scratch()
        self._changed: set[tuple[int, int]] = set()
        self._clear()
        #: How far from its pose a scan can update a cell, m.
        self.reach_m = max(params.max_range_m, params.free_range_m, params.no_return_free_m)

    # -- scans -------------------------------------------------------------------------------

    def __contains__(self, key: int) -> bool:
        return key in self._laid

    def __len__(self) -> int:
        """Scans laid."""
        return len(self._laid)

    def laid(self, key: int) -> LaidScan:
        """Scan ``key`` as laid (KeyError when it is not)."""
        return self._laid[key]

    def lay(self, key: int, pose, ranges, angle_min_rad: float, angle_increment_rad: float) -> None:
        """Lay one scan at ``pose``; a scan already laid under ``key`` is taken out first.

        Parameters
        ----------
        key : int
        pose : array_like, shape (3,)
            Scanner pose ``(x_m, y_m, theta_rad)`` in the map frame.
        ranges : array_like, shape (N,)
            Ranges, metres: ``+inf`` no return, NaN invalid.
        angle_min_rad, angle_increment_rad : float
            Bearing of the first beam and the step between beams, radians.
        """
        pose = np.asarray(pose, dtype=float).reshape(3)
        if not (np.all(np.isfinite(pose)) and np.isfinite(angle_min_rad) and np.isfinite(angle_increment_rad)):
            raise InputError("tiled grid: pose and beam angles must be finite")
        laid = LaidScan(pose.copy(), np.asarray(ranges, dtype=np.float32).reshape(-1),
                        float(angle_min_rad), float(angle_increment_rad))
        self.remove(key)
        self._laid[key] = laid
        self._apply(laid, 1)
        while self._too_large():
            self._coarsen()

    def move(self, key: int, pose) -> None:
        """Lay scan ``key`` again at ``pose`` (3,)."""
        laid = self._laid[key]
        self.lay(key, pose, laid.ranges, laid.angle_min_rad, laid.angle_increment_rad)

    def remove(self, key: int) -> None:
        """Take scan ``key`` out (nothing when it is not laid)."""
        laid = self._laid.pop(key, None)
        if laid is not None:
            self._apply(laid, -1)

    # -- tiles -------------------------------------------------------------------------------

    def tiles(self) -> list[tuple[int, int]]:
        """Every tile (row, col) that holds a cell ever touched at this resolution, sorted."""
        return sorted(self._slot)

    def take_changed(self) -> list[tuple[int, int]]:
        """The tiles whose counts changed since the last call, sorted; the set is then empty."""
        changed, self._changed = sorted(self._changed), set()
        return changed

    def counts(self, tile: tuple[int, int]) -> np.ndarray:
        """Hits (``[0]``) and misses (``[1]``) of tile ``tile``'s cells, (2, T, T) int32 (a copy; zeros for no tile)."""
        slot = self._slot.get(tile)
        return np.zeros((2, self.tile_cells, self.tile_cells), np.int32) if slot is None else self._pool[slot].copy()

    def log_odds(self, tile: tuple[int, int]) -> np.ndarray:
        """Clamped log-odds of tile ``tile``'s cells, (T, T) float32 (row 0 lowest y); 0 where unobserved."""
        slot = self._slot.get(tile)
        if slot is None:
            return np.zeros((self.tile_cells,) * 2, np.float32)
        p, counts = self.params, self._pool[slot]
        value = counts[0] * np.float32(p.hit_log_odds) + counts[1] * np.float32(p.miss_log_odds)
        return np.clip(value, p.min_log_odds, p.max_log_odds).astype(np.float32)

    def trinary(self, tile: tuple[int, int]) -> np.ndarray:
        """Tile ``tile``'s cells as OCCUPIED (100), FREE (0) or UNKNOWN (-1): (T, T) int8, map_server's thresholds."""
        return OccupancyGrid(self.log_odds(tile), self.resolution_m, np.zeros(2)).trinary()

    def state(self) -> dict[str, np.ndarray]:
        """What the scans alone do not give back, as named arrays: the resolution, the bounds of every
        cell touched (they never shrink) and the tiles changed since :meth:`take_changed`."""
        return {"resolution_m": np.float64(self.resolution_m), "resolution_changes": np.int64(self.resolution_changes),
                "bounds": self._bounds.copy(),
                "changed": np.array(sorted(self._changed), np.int64).reshape(-1, 2)}

    def set_state(self, state) -> None:
        """Take :meth:`state`'s values (before any scan is laid, then the tiles changed after them).

        Raises
        ------
        InputError
            The arrays are not such a state.
        """
        bounds = np.asarray(state["bounds"], np.int64)
        changed = np.asarray(state["changed"], np.int64)
        if bounds.shape != (4,) or changed.ndim != 2 or changed.shape[1] != 2 or not float(state["resolution_m"]) > 0:
            raise InputError("tiled grid state: bounds (4,), changed (n, 2) and a resolution > 0 expected")
        if self._laid:
            self._changed = {(int(r), int(c)) for r, c in changed}
            return
        self.resolution_m = float(state["resolution_m"])
        self.resolution_changes = int(state["resolution_changes"])
        self._bounds = bounds.copy()

    @property
    def nbytes(self) -> int:
        """Memory of the counts and the laid scans, bytes."""
        return self._pool.nbytes + sum(laid.ranges.nbytes + laid.pose.nbytes for laid in self._laid.values())

    # -- internals ---------------------------------------------------------------------------

    def _clear(self) -> None:
        t = self.tile_cells
        self._pool = np.zeros((16, 2, t, t), np.int32)   # tiles' counts, by slot; grown by doubling
        self._slot: dict[tuple[int, int], int] = {}      # tile -> its slot in the pool
        # Touched cells' (min row, max row, min col, max col).
        self._bounds = np.array([np.iinfo(np.int64).max, np.iinfo(np.int64).min] * 2, np.int64)

    def _apply(self, laid: LaidScan, sign: int) -> None:
        """Add (``sign`` 1) or take out (-1) the hits and misses of one laid scan."""
        res = self.resolution_m
        # A frame around the scan's reach, whole cells from the map origin, so the same scan laid
        # at the same pose always gives the same cells.
        lo_xy = np.floor((laid.pose[:2] - self.reach_m) / res).astype(np.int64) - 1   # (col, row)
        side = int(np.ceil(2 * self.reach_m / res)) + 3
        origin = lo_xy * res
        angles = laid.angle_min_rad + laid.angle_increment_rad * np.arange(laid.ranges.size)
        r = laid.ranges.astype(float)
        free_len, hit = beam_lengths(r, self.params)
        hx, hy = beam_points(laid.pose[None, :], np.where(hit, r, 0.0)[None, :], angles[None, :])
        hits = np.unique(flat_index(hx[0][hit], hy[0][hit], origin, res, side, side))
        use = free_len > 0
        bearing = laid.pose[2] + angles[use]
        u0 = np.full(bearing.size, (laid.pose[0] - origin[0]) / res)
        v0 = np.full(bearing.size, (laid.pose[1] - origin[1]) / res)
        lo_cell = lo_xy[::-1].copy()                                     # (row, col)
        tile0 = lo_cell >> self._shift
        span = ((lo_cell + side - 1) >> self._shift) - tile0 + 1
        slots = np.full(span, -1, np.int64)
        for i in range(span[0]):
            for j in range(span[1]):
                slots[i, j] = self._slot.get((int(tile0[0]) + i, int(tile0[1]) + j), -1)
        known = slots >= 0
        touched = np.zeros(span, bool)
        bounds = np.array([np.iinfo(np.int64).max, np.iinfo(np.int64).min] * 2, np.int64)
        next_slot = len(self._slot)
        while True:
            freed, next_slot = grid_kernel.lay_scan(
                side, lo_cell, self._shift, u0, v0, np.cos(bearing), np.sin(bearing), free_len[use] / res, hits,
                sign, slots, self._pool, next_slot, touched, bounds, self._scratch)
            if freed >= 0:
                break
            grown = np.zeros((2 * self._pool.shape[0],) + self._pool.shape[1:], np.int32)
            grown[:self._pool.shape[0]] = self._pool
            self._pool = grown
        for i, j in zip(*np.nonzero((slots >= 0) & ~known)):
            self._slot[(int(tile0[0]) + int(i), int(tile0[1]) + int(j))] = int(slots[i, j])
        for i, j in zip(*np.nonzero(touched)):
            self._changed.add((int(tile0[0]) + int(i), int(tile0[1]) + int(j)))
        if bounds[0] <= bounds[1]:
            self._bounds[0::2] = np.minimum(self._bounds[0::2], bounds[0::2] + lo_cell)
            self._bounds[1::2] = np.maximum(self._bounds[1::2], bounds[1::2] + lo_cell)

    def _too_large(self) -> bool:
        rmin, rmax, cmin, cmax = self._bounds.tolist()
        if rmin > rmax:
            return False
        # A one-cell border each side, as export sizes its grid.
        return (rmax - rmin + 3) * (cmax - cmin + 3) > self.params.max_cells

    def _coarsen(self) -> None:
        """Double the resolution and lay every scan again."""
        self._changed |= set(self._slot)
        self._clear()
        self.resolution_m *= 2.0
        self.resolution_changes += 1
        for laid in self._laid.values():
            self._apply(laid, 1)


def tiles_of(cells: np.ndarray, resolution_m: float, origin_xy_m, tile_cells: int = TILE_CELLS
             ) -> tuple[np.ndarray, np.ndarray]:
    """A whole trinary grid cut into the tiles ``map/grid`` carries.

    ``cells`` (H, W) int8 (100 / 0 / -1, row 0 the lowest y) with cell ``[0, 0]``'s corner at
    ``origin_xy_m`` (2,) m. Each cell goes to the tile cell holding its centre, so a grid whose origin
    is not on a whole cell moves by less than half a cell. Returns the tiles (n, 2) int64 (row, col)
    that hold a known cell and their cells (n, T, T) int8, unknown elsewhere.
    """
    cells = np.asarray(cells, dtype=np.int8)
    h, w = cells.shape
    side = int(tile_cells)
    r0, c0 = (int(np.floor(v / resolution_m + 0.5)) for v in (origin_xy_m[1], origin_xy_m[0]))
    tr0, tc0 = r0 // side, c0 // side
    top, left = r0 - tr0 * side, c0 - tc0 * side
    rows, cols = -(-(top + h) // side), -(-(left + w) // side)
    canvas = np.full((rows * side, cols * side), -1, np.int8)
    canvas[top:top + h, left:left + w] = cells
    blocks = canvas.reshape(rows, side, cols, side).swapaxes(1, 2)   # (rows, cols, T, T)
    keep = np.argwhere(np.any(blocks != -1, axis=(2, 3)))
    tiles = (keep + [tr0, tc0]).astype(np.int64).reshape(-1, 2)
    return tiles, blocks[keep[:, 0], keep[:, 1]].reshape(-1, side, side).copy()
