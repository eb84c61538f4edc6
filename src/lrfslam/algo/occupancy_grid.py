"""Occupancy grid from laser scans placed along a trajectory: log-odds, beams traced cell by cell.

Every scan is placed at its pose; each beam then updates the cells it crosses:

* a return at range ``r`` (finite, ``0 < r``) marks the cells the beam crosses before
  ``min(r, free_range_m)`` free and, when ``r <= max_range_m``, the cell of its end point
  occupied. A return farther than ``max_range_m`` still clears the space in front of it,
  but is too far (too wide a footprint, too much angular error) to mark a wall;
* a beam with no return (``+inf``) marks nothing by default: on an LMS200 it also comes
  from black or mirroring surfaces close by. ``no_return_free_m > 0`` lets it clear that
  much space (Cartographer's ``missing_data_ray_length``);
* an invalid beam (NaN, or a range ``<= 0``) is skipped.

A cell gets at most one update per scan: a hit if any beam of the scan ends in it, else a
miss if any beam crosses it — so the many beams that cross the cells near the scanner
count once, and a wall cell that a grazing beam crosses on its way to a farther point of
the same wall stays a wall. A cell's log-odds is ``hit_log_odds`` times its hits plus
``miss_log_odds`` times its misses, clamped to ``[min_log_odds, max_log_odds]``: a function of
the scans and their poses alone, not of their order, so the live grid, which takes a scan out
and lays it again when an optimisation moves it (``lrfslam.algo.tiled_grid``), is the same grid.

The grid is sized to the data before any cell is written: the bounding box of the poses
and of every point a beam can update, plus one cell. Its memory is therefore
``4 bytes × cells`` and is refused above ``max_cells``.

Cell ``[row, col]`` covers ``x in [origin_x + col·res, origin_x + (col+1)·res)`` and
``y in [origin_y + row·res, origin_y + (row+1)·res)``: row 0 is the lowest ``y``, as in
ROS ``nav_msgs/OccupancyGrid`` (a map image, whose first row is the top, is this array
flipped upside down).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lrfslam.errors import ConfigError, InputError

#: ROS map_server's default thresholds on the occupancy probability.
OCCUPIED_THRESH = 0.65
FREE_THRESH = 0.196
#: Beam length (cells) past a grid line at which the cell entered is read.
_PAST = 1e-6
#: Values of :meth:`OccupancyGrid.trinary`, those of ``nav_msgs/OccupancyGrid``.
OCCUPIED, FREE, UNKNOWN = 100, 0, -1


@dataclass(frozen=True)
class GridParams:
    """How scans become a grid.

    Attributes
    ----------
    resolution_m : float
        Side of a square cell, metres.
    max_range_m : float
        Returns up to this range mark their end point occupied, metres.
    free_range_m : float
        Cap on the free space one beam marks, metres (from the scanner along the beam).
    no_return_free_m : float
        Free space a beam with no return marks, metres (0: none); capped by ``free_range_m``.
    hit_log_odds, miss_log_odds : float
        Log-odds added by a hit (> 0) and a miss (< 0); the defaults are P = 0.7 and P = 0.4.
    min_log_odds, max_log_odds : float
        Bounds of a cell's log-odds as read (how sure it reads; map_server's thresholds lie inside).
    max_cells : int
        Largest grid built; a larger one is refused (:class:`~lrfslam.errors.InputError`).
    batch_scans : int
        Scans traced together; their temporary arrays take about
        ``batch_scans × beams × 1.5 × free_range_m / resolution_m × 100`` bytes (8 scans of 181 beams,
        8 m at 5 cm: about 35 MB).
    """

    resolution_m: float = 0.05
    max_range_m: float = 8.0
    free_range_m: float = 8.0
    no_return_free_m: float = 0.0
    hit_log_odds: float = 0.85
    miss_log_odds: float = -0.4
    min_log_odds: float = -2.0
    max_log_odds: float = 3.5
    max_cells: int = 25_000_000
    batch_scans: int = 8

    def __post_init__(self) -> None:
        if not (np.isfinite(self.resolution_m) and self.resolution_m > 0):
            raise ConfigError(f"grid resolution_m must be > 0, got {self.resolution_m}")
        if not (self.max_range_m > 0 and self.free_range_m >= 0 and self.no_return_free_m >= 0):
            raise ConfigError("grid max_range_m must be > 0; free_range_m and no_return_free_m >= 0")
        if not (self.hit_log_odds > 0 > self.miss_log_odds and self.min_log_odds < 0 < self.max_log_odds):
            raise ConfigError("grid hit_log_odds > 0 > miss_log_odds and min_log_odds < 0 < max_log_odds required")
        if self.max_cells < 1 or self.batch_scans < 1:
            raise ConfigError("grid max_cells and batch_scans must be >= 1")


@dataclass(frozen=True, eq=False)
class OccupancyGrid:
    """A log-odds occupancy grid.

    Attributes
    ----------
    log_odds : ndarray of float32, shape (H, W)
        ``log(p / (1 - p))`` per cell; 0 where never observed. Row 0 is the lowest ``y``.
    resolution_m : float
        Side of a cell, metres.
    origin_xy_m : ndarray, shape (2,)
        World position of the lower-left corner of cell ``[0, 0]``, metres.
    """

    log_odds: np.ndarray
    resolution_m: float
    origin_xy_m: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        """(H rows along y, W columns along x)."""
        return self.log_odds.shape

    @property
    def extent_m(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) of the grid's outer edges, metres."""
        h, w = self.shape
        x0, y0 = self.origin_xy_m
        return float(x0), float(x0 + w * self.resolution_m), float(y0), float(y0 + h * self.resolution_m)

    def trinary(self, occupied_thresh: float = OCCUPIED_THRESH, free_thresh: float = FREE_THRESH) -> np.ndarray:
        """Cells as :data:`OCCUPIED` (p > occupied_thresh), :data:`FREE` (p < free_thresh) or :data:`UNKNOWN`.

        Returns
        -------
        ndarray of int8, shape (H, W)
        """
        # Compared as log-odds: no (H, W) float64 probability array for a large grid.
        out = np.full(self.shape, UNKNOWN, dtype=np.int8)
        out[self.log_odds > np.log(occupied_thresh / (1 - occupied_thresh))] = OCCUPIED
        out[self.log_odds < np.log(free_thresh / (1 - free_thresh))] = FREE
        return out

    def cell_centres_m(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """World xy of the centres of cells ``(rows[i], cols[i])``; shape (K, 2), metres."""
        rows, cols = np.asarray(rows), np.asarray(cols)
        return self.origin_xy_m + self.resolution_m * (np.column_stack((cols, rows)) + 0.5)

    def cell_of(self, xy_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rows, cols) of the cells holding points ``xy_m`` (K, 2) metres; may lie outside the grid."""
        idx = np.floor((np.asarray(xy_m, dtype=float).reshape(-1, 2) - self.origin_xy_m) / self.resolution_m)
        return idx[:, 1].astype(np.int64), idx[:, 0].astype(np.int64)


def _check(poses: np.ndarray, ranges: np.ndarray, angles: np.ndarray) -> tuple[np.ndarray, ...]:
    poses = np.asarray(poses, dtype=float).reshape(-1, 3)
    ranges = np.atleast_2d(np.asarray(ranges))   # float32 stays float32: half the memory for a whole log
    if not np.issubdtype(ranges.dtype, np.floating):
        ranges = ranges.astype(float)
    angles = np.asarray(angles, dtype=float)
    if ranges.shape[0] != poses.shape[0]:
        raise InputError(f"occupancy grid: {poses.shape[0]} poses but {ranges.shape[0]} scans")
    if angles.ndim == 1 and angles.shape[0] == ranges.shape[1]:
        angles = np.broadcast_to(angles, ranges.shape)
    if angles.shape != ranges.shape:
        raise InputError(f"occupancy grid: angles of shape {angles.shape} do not match ranges {ranges.shape}")
    if not (np.all(np.isfinite(poses)) and np.all(np.isfinite(angles))):
        raise InputError("occupancy grid: poses and beam angles must be finite")
    return poses, ranges, angles


def beam_lengths(ranges: np.ndarray, p: GridParams) -> tuple[np.ndarray, np.ndarray]:
    """Free length (m) and whether the end point is a hit, per beam; both shaped like ``ranges``."""
    with np.errstate(invalid="ignore"):
        returned = np.isfinite(ranges) & (ranges > 0)
        hit = returned & (ranges <= p.max_range_m)
        no_return = np.isposinf(ranges)
        free = np.where(returned, np.minimum(ranges, p.free_range_m), 0.0)
    free = np.where(no_return, min(p.no_return_free_m, p.free_range_m), free)
    return free, hit


def beam_points(poses: np.ndarray, dist: np.ndarray, angles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World x, y of the points ``dist`` metres along beams at ``angles`` of scans at ``poses`` (broadcast)."""
    bearing = poses[:, 2:3] + angles
    return poses[:, 0:1] + dist * np.cos(bearing), poses[:, 1:2] + dist * np.sin(bearing)


def _bounds_m(poses: np.ndarray, ranges: np.ndarray, angles: np.ndarray,
              params: GridParams) -> tuple[np.ndarray, np.ndarray]:
    """Lower-left and upper-right corners (m), shape (2,) each, of every pose and every point the
    scans update (checked arguments as :func:`grid_frame`'s; the resolution does not enter)."""
    lo, hi = poses[:, :2].min(axis=0), poses[:, :2].max(axis=0)
    # In batches, as the tracing: the whole log's beams at once would hold several (T, N) arrays.
    for start in range(0, poses.shape[0], params.batch_scans * 64):
        sl = slice(start, start + params.batch_scans * 64)
        rb = ranges[sl].astype(float)
        free, hit = beam_lengths(rb, params)
        x, y = beam_points(poses[sl], np.maximum(free, np.where(hit, rb, 0.0)), angles[sl])
        lo = np.minimum(lo, (x.min(), y.min()))
        hi = np.maximum(hi, (x.max(), y.max()))
    return lo, hi


def _cells(lo_m: np.ndarray, hi_m: np.ndarray, res: float) -> tuple[np.ndarray, int, int]:
    """Lower-left cell (2,) and the (H, W) cells of a grid over ``lo_m``–``hi_m`` at ``res``, a border included."""
    lo = np.floor(np.asarray(lo_m) / res) - 1
    w, h = (np.floor(np.asarray(hi_m) / res) + 2 - lo).astype(np.int64)
    return lo, int(h), int(w)


def fitting_resolution(lo_m, hi_m, params: GridParams) -> float:
    """The finest of ``params.resolution_m × 2^k`` (m; k = 0, 1, …) at which a grid over
    ``lo_m``–``hi_m`` (m, shape (2,) each) holds at most ``params.max_cells`` cells, border included."""
    res = params.resolution_m
    while True:
        _, h, w = _cells(lo_m, hi_m, res)
        if h * w <= params.max_cells:
            return float(res)
        res *= 2.0


def grid_frame(poses, ranges, angles, params: GridParams,
               fit: bool = False) -> tuple[np.ndarray, tuple[int, int], float]:
    """Origin, shape and resolution of the smallest grid holding every pose and every cell the scans update.

    Parameters
    ----------
    poses : array_like, shape (T, 3)
        Scanner pose of each scan ``(x_m, y_m, theta_rad)`` in the map frame.
    ranges : array_like, shape (T, N)
        Ranges in metres (``+inf`` no return, NaN invalid; pad shorter scans with NaN).
    angles : array_like, shape (N,) or (T, N)
        Bearing of each beam in the scanner frame, radians.
    params : GridParams
    fit : bool
        A grid larger than ``params.max_cells`` at ``params.resolution_m`` takes the finest
        doubling of it that fits (:func:`fitting_resolution`) instead of being refused.

    Returns
    -------
    origin_xy_m : ndarray, shape (2,)
        Lower-left corner, metres, a whole number of cells from the world origin.
    shape : (int, int)
        (H, W) cells.
    resolution_m : float
        Side of a cell (m): ``params.resolution_m`` unless ``fit`` coarsened it.

    Raises
    ------
    InputError
        No pose, non-finite poses or angles, or (without ``fit``) a grid larger than ``params.max_cells``.
    """
    poses, ranges, angles = _check(poses, ranges, angles)
    if poses.shape[0] == 0:
        raise InputError("occupancy grid: no scans")
    lo_m, hi_m = _bounds_m(poses, ranges, angles, params)
    res = fitting_resolution(lo_m, hi_m, params) if fit else params.resolution_m
    lo, h, w = _cells(lo_m, hi_m, res)
    if h * w > params.max_cells:
        raise InputError(f"occupancy grid of {h} x {w} cells at {res} m exceeds {params.max_cells} cells "
                         "(a coarser resolution, or a shorter max range)")
    return lo * res, (h, w), res


def build_grid(poses, ranges, angles, params: GridParams = GridParams(), fit: bool = False) -> OccupancyGrid:
    """The occupancy grid of scans ``ranges`` taken at ``poses``.

    Parameters
    ----------
    poses : array_like, shape (T, 3)
        Scanner pose of each scan ``(x_m, y_m, theta_rad)`` in the map frame.
    ranges : array_like, shape (T, N)
        Ranges in metres: ``+inf`` no return, NaN invalid (pad shorter scans with NaN).
    angles : array_like, shape (N,) or (T, N)
        Bearing of each beam in the scanner frame, radians.
    params : GridParams
    fit : bool
        As :func:`grid_frame`'s: a grid too large is built coarser rather than refused.

    Returns
    -------
    OccupancyGrid
        Sized by :func:`grid_frame`.

    Raises
    ------
    InputError
        As :func:`grid_frame`.
    """
    poses, ranges, angles = _check(poses, ranges, angles)
    origin, (h, w), res = grid_frame(poses, ranges, angles, params, fit)
    grid = np.zeros(h * w, dtype=np.float32)
    for start in range(0, poses.shape[0], params.batch_scans):
        sl = slice(start, start + params.batch_scans)
        free_cells, hit_cells = batch_cells(poses[sl], ranges[sl], angles[sl], params, origin, res, (h, w))
        np.add.at(grid, free_cells, np.float32(params.miss_log_odds))
        np.add.at(grid, hit_cells, np.float32(params.hit_log_odds))
    np.clip(grid, params.min_log_odds, params.max_log_odds, out=grid)
    return OccupancyGrid(grid.reshape(h, w), res, np.asarray(origin, dtype=float))


def batch_cells(poses: np.ndarray, ranges: np.ndarray, angles: np.ndarray, params: GridParams,
                origin_xy_m: np.ndarray, resolution_m: float,
                shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The cells a batch of B scans updates, each scan counting a cell once (the module's rules).

    Parameters
    ----------
    poses : ndarray, shape (B, 3)
        Scanner poses ``(x_m, y_m, theta_rad)`` (checked, finite).
    ranges : ndarray, shape (B, N)
        Ranges, metres (``+inf`` no return, NaN invalid).
    angles : ndarray, shape (B, N)
        Beam bearings in the scanner frame, radians.
    params : GridParams
    origin_xy_m : ndarray, shape (2,)
        Lower-left corner of the grid frame, metres; it must hold every cell the scans update.
    resolution_m : float
        Side of a cell, metres.
    shape : (int, int)
        (H, W) cells of the grid frame.

    Returns
    -------
    free_cells, hit_cells : ndarray of int64
        Flat indices ``row * W + col``, one entry per scan that frees (hits) the cell; a cell
        some beam of a scan ends in is that scan's hit and not its miss.
    """
    h, w = shape
    res = resolution_m
    n_cells = h * w
    rb = ranges.astype(float)
    free, hit = beam_lengths(rb, params)
    scan_of_beam = np.broadcast_to(np.arange(poses.shape[0])[:, None], rb.shape)

    hx, hy = beam_points(poses, np.where(hit, rb, 0.0), angles)
    hit_keys = _unique(scan_of_beam[hit] * n_cells + flat_index(hx[hit], hy[hit], origin_xy_m, res, h, w))

    use = free > 0
    bearing = (poses[:, 2:3] + angles)[use]
    u0 = np.broadcast_to((poses[:, 0:1] - origin_xy_m[0]) / res, rb.shape)[use]
    v0 = np.broadcast_to((poses[:, 1:2] - origin_xy_m[1]) / res, rb.shape)[use]
    beam, rows, cols = _crossed_cells(u0, v0, np.cos(bearing), np.sin(bearing), free[use] / res)
    cells = np.clip(rows, 0, h - 1) * w + np.clip(cols, 0, w - 1)
    free_keys = _unique(scan_of_beam[use][beam] * n_cells + cells)
    if hit_keys.size:
        at = np.minimum(np.searchsorted(hit_keys, free_keys), hit_keys.size - 1)
        free_keys = free_keys[hit_keys[at] != free_keys]
    return free_keys % n_cells, hit_keys % n_cells


def _crossed_cells(u0: np.ndarray, v0: np.ndarray, c: np.ndarray, s: np.ndarray,
                   length: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every cell that B beams cross before their end (a cell they cross for under 1e-6 cell, at a corner, may be left out).

    Parameters
    ----------
    u0, v0 : ndarray, shape (B,)
        Start of each beam in cell units from the grid origin (x, y).
    c, s : ndarray, shape (B,)
        Cosine and sine of its bearing.
    length : ndarray, shape (B,)
        Its length in cell units (> 0); a line crossed exactly at the end does not count.

    Returns
    -------
    beam, rows, cols : ndarray of int64, shape (K,)
        One entry per cell entered (the start cell, then one per grid line crossed), unsorted.
    """
    u1, v1 = u0 + length * c, v0 + length * s
    parts = [(np.arange(u0.size), np.floor(v0).astype(np.int64), np.floor(u0).astype(np.int64))]
    # Crossing line k of one axis enters cell k (moving up that axis) or k - 1 (moving down); the
    # lines crossed are those strictly between start and end, and the start's own line when moving down.
    for a0, a1, b0, da, db, along_x in ((u0, u1, v0, c, s, True), (v0, v1, u0, s, c, False)):
        up = da > 0
        first = np.where(up, np.floor(a0) + 1, np.floor(a1) + 1).astype(np.int64)
        last = np.where(up, np.ceil(a1) - 1, np.floor(a0)).astype(np.int64)
        n = np.maximum(last - first + 1, 0)
        beam = np.repeat(np.arange(u0.size), n)
        k = first[beam] + np.arange(beam.size) - np.repeat(np.cumsum(n) - n, n)
        # The other index just past the crossing: where the beam passes a cell corner, rounding
        # cannot then put the two crossings on different sides of it and skip the cell beyond.
        t = (k - a0[beam]) / da[beam] + _PAST
        other = np.floor(b0[beam] + db[beam] * t).astype(np.int64)
        entered = np.where(up[beam], k, k - 1)
        parts.append((beam, other, entered) if along_x else (beam, entered, other))
    return tuple(np.concatenate(x) for x in zip(*parts))


def _unique(a: np.ndarray) -> np.ndarray:
    """Sorted distinct values of an int array (by sorting: numpy's hashing unique is slower on these)."""
    a = np.sort(a)
    return a[np.concatenate(([True], a[1:] != a[:-1]))] if a.size else a


def flat_index(x: np.ndarray, y: np.ndarray, origin: np.ndarray, res: float, h: int, w: int) -> np.ndarray:
    """Flat cell index ``row * w + col`` of world points (the grid frame holds them; clipped for rounding)."""
    col = np.clip(np.floor((x - origin[0]) / res).astype(np.int64), 0, w - 1)
    row = np.clip(np.floor((y - origin[1]) / res).astype(np.int64), 0, h - 1)
    return row * w + col
