"""Correlative scan-to-map matching by branch and bound over a large search window.

Finds the pose of a point set (a scan, or a few scans merged, in their robot
frame) in a map frame whose map is a likelihood grid, anywhere inside a window
of translations and rotations: the exhaustive search of Olson (2009) made fast
by branch and bound as in Hess et al. (2016), written here from those papers.

Symbols (inside this module only):

* ``G[r, c]`` the likelihood grid, ``exp(−d²/2σ²)`` of the distance ``d`` from
  cell (r, c) to the nearest map point (σ = ``hit_sigma_m``), in [0, 1];
  row = y, column = x, cell side ``cell_m``;
* ``P_h[r, c] = max G[r : r + 2^h, c : c + 2^h]``: the max-pooled grid of level
  ``h`` (``P_0 = G``), kept for ``h ≥ 1`` in steps of 1/255 rounded up (uint8: still a bound);
* a candidate ``(a, i, j)``: rotation index ``a``, x and y offsets in cells; the
  score of a leaf (level 0) is the mean of ``G`` over the rotated and shifted
  points; at level ``h`` the mean of ``P_h`` is an upper bound of every leaf
  ``(a, i..i+2^h−1, j..j+2^h−1)`` below it, so a branch whose bound is below the
  best leaf found cannot hold a better one and is cut (the search is exact).

Design choices
--------------
* **Rotations are enumerated, translations branched**, as Hess et al. do: the
  rotated points' cells are computed once per angle (``angle_step_rad``).
* **Breadth-first, by levels.** Python cannot afford a depth-first search one
  node at a time; a greedy descent from the best top-level candidates gives a
  good first leaf (lower bound) and then whole levels are scored (a compiled
  loop, ``correlative_kernel``) and pruned at once. ``max_frontier`` caps a level in a pathological (featureless)
  map; the search is then no longer exact and says so (``exact``).
* **Zero border.** The grid has a border of empty cells and indices are clipped
  into it, so a point pushed out of the map scores 0 at the leaves and the
  pooled bound stays an upper bound.
* **A good first bound.** A greedy descent from the best root gives the first bound. Over a
  window the size of a building one descent can end far below the best leaf, and a low bound cuts
  little at the coarse levels, where the pooled bounds are near 1 there: the best of descents from
  the ``greedy_starts`` best roots is then usually the best leaf or near it.
* **Where the pose may lie.** A caller that knows where the points' origin can be (a robot
  stands in free space: the localizer's global search) passes a :class:`PositionMask`; a block
  none of whose positions it admits is cut at every level, before it is scored. The search is
  exact over the admitted positions: over a building-sized window most blocks of a few metres
  hold no free cell, and their pooled bounds, near 1 beside any wall, would otherwise all be
  branched.
* **Second peak.** The best leaf more than ``peak_separation_m`` away (or a
  rotation step away by more than ``peak_separation_rad``) from the winner is
  reported too, so a caller can refuse an ambiguous match (a repeated corridor).
  It is searched with the same bound, so it too is exact (or capped). A caller interested in it
  only above a share of the best (``second_ratio``) gets both from one descent, to that share of
  the first bound: every leaf a second descent would have found is among its leaves.

References
----------
E. Olson, "Real-time correlative scan matching", ICRA 2009. W. Hess, D. Kohler,
H. Rapp, D. Andor, "Real-time loop closure in 2D LIDAR SLAM", ICRA 2016.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import distance_transform_edt, maximum_filter

from lrfslam.algo import correlative_kernel as kernel
from lrfslam.algo.checks import require_finite
from lrfslam.algo.geometry import from_frame
from lrfslam.errors import ConfigError, InputError

#: Standard deviation of the likelihood around each map point (m).
HIT_SIGMA_M = 0.1
#: Rotation step (rad). Hess et al. take the step that moves the farthest point by one cell; that
#: makes hundreds of angles for 20 m returns, and the far points are the least reliable anyway: this
#: step moves a point at ``cell_m / ANGLE_STEP_RAD`` by one cell, farther ones by a little more,
#: which the likelihood's blur and the refinement absorb.
ANGLE_STEP_RAD = 0.01
#: Candidates kept per level at most (then best first; see module notes).
MAX_FRONTIER = 20_000
#: A second peak must be this far from the best in translation (m) or rotation (rad).
PEAK_SEPARATION_M = 1.0
PEAK_SEPARATION_RAD = 0.35


@dataclass(frozen=True)
class CorrelativeParams:
    """Parameters of :class:`LikelihoodGrid` and :func:`search`.

    Attributes
    ----------
    cell_m : float
        Grid cell side (m): the resolution of the search.
    levels : int
        Pooled grids, level 0 (the grid) to ``levels − 1`` (blocks of
        ``2^(levels−1)`` cells).
    """

    cell_m: float = 0.1
    levels: int = 7

    def __post_init__(self) -> None:
        require_finite(self, ("cell_m",), positive=True, what="correlative matching ")
        if not 1 <= self.levels <= 12:
            raise ConfigError("correlative matching needs 1 <= levels <= 12")


def max_pooled(level0: np.ndarray, levels: int) -> list[np.ndarray]:
    """``P_0 = level0`` (H, W) and ``P_h[r, c] = max level0[r : r + 2^h, c : c + 2^h]`` for
    ``h < levels``, each (H, W), of ``level0``'s dtype (booleans: any)."""
    pooled = [level0]
    for h in range(1, levels):
        prev, half = pooled[-1], 1 << (h - 1)
        nxt = prev.copy()
        nxt[:-half, :] = np.maximum(nxt[:-half, :], prev[half:, :])
        nxt[:, :-half] = np.maximum(nxt[:, :-half], nxt[:, half:].copy())
        pooled.append(nxt)
    return pooled


class LikelihoodGrid:
    """The likelihood grid of map points and its pooled levels (immutable after construction).

    Parameters
    ----------
    points_xy_m : array_like, shape (M, 2)
        Map points in the map frame (m); non-finite rows are ignored.
    params : CorrelativeParams
    margin_m : float
        Extra room around the points' bounding box (m): where the likelihood
        falls off; beyond it every cell is empty.
    """

    def __init__(self, points_xy_m, params: CorrelativeParams, margin_m: float = 0.5) -> None:
        pts = np.asarray(points_xy_m, dtype=float).reshape(-1, 2)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        if pts.shape[0] == 0:
            raise InputError("a likelihood grid needs at least one map point")
        self.params = params
        cell = params.cell_m
        # One empty border cell below, and enough above for the pooled windows.
        self.origin_xy_m = pts.min(axis=0) - margin_m - cell
        top = pts.max(axis=0) + margin_m + cell
        width, height = (np.ceil((top - self.origin_xy_m) / cell).astype(int) + 1).tolist()
        occupied = np.zeros((height, width), dtype=bool)
        col, row = np.floor((pts - self.origin_xy_m) / cell).astype(int).T
        occupied[row, col] = True
        dist_m = distance_transform_edt(~occupied) * cell
        grid = np.exp(-0.5 * (dist_m / HIT_SIGMA_M) ** 2)
        grid[0, :] = grid[-1, :] = grid[:, 0] = grid[:, -1] = 0.0
        # float32 halves the memory the search gathers from; scores are means of <= 1 numbers.
        grid = grid.astype(np.float32)
        pooled = max_pooled(grid, params.levels)
        # The pooled levels only bound: in 1/255 steps, rounded up (still bounds), they take a quarter
        # of the memory, and the search's gathers from them miss the cache less.
        # (A float32 times 255 is exact in float64.)
        self.pooled = [grid] + [np.ceil(level.astype(np.float64) * 255.0).astype(np.uint8) for level in pooled[1:]]

    @property
    def grid(self) -> np.ndarray:
        """The level-0 likelihood grid, shape (rows = y, cols = x)."""
        return self.pooled[0]

    def score(self, points_xy_m, pose) -> float:
        """Mean likelihood (0–1) of the points (N, 2, robot frame) placed at ``pose`` (3,) in the map frame."""
        pts = np.asarray(points_xy_m, dtype=float).reshape(-1, 2)
        moved = from_frame(pts, pose)
        col, row = self._cells(moved)
        return float(np.mean(self.grid[row, col])) if pts.size else 0.0

    def _cells(self, moved: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        idx = np.floor((moved - self.origin_xy_m) / self.params.cell_m).astype(np.int64)
        h, w = self.grid.shape
        return np.clip(idx[:, 0], 0, w - 1), np.clip(idx[:, 1], 0, h - 1)


class PositionMask:
    """Where a searched pose's translation may lie, on a :class:`LikelihoodGrid`'s cells, pooled by level.

    Parameters
    ----------
    grid : LikelihoodGrid
        The grid the search runs on (its cells, origin and levels).
    xy_m : array_like, shape (M, 2)
        Admitted positions (m, the map frame), e.g. the centres of a map's free cells.
    margin_m : float
        Every position within this distance (m, a square's half side) of one of them is admitted
        too: the cells of another grid, a robot's footprint.
    """

    def __init__(self, grid: LikelihoodGrid, xy_m, margin_m: float) -> None:
        pts = np.asarray(xy_m, dtype=float).reshape(-1, 2)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        cell = grid.params.cell_m
        h, w = grid.grid.shape
        mask = np.zeros((h, w), dtype=bool)
        col, row = np.floor((pts - grid.origin_xy_m) / cell).astype(np.int64).T
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        mask[row[inside], col[inside]] = True
        # One cell more than the margin: a searched position's cell is found by flooring, as here.
        reach = int(np.ceil(margin_m / cell)) + 1
        mask = maximum_filter(mask, size=2 * reach + 1, mode="constant", cval=False)
        self.origin_xy_m = grid.origin_xy_m
        self.cell_m = cell
        self.pooled = max_pooled(mask, grid.params.levels)   # of booleans: any admitted in the block

    def cell_of(self, centre_xy_m: np.ndarray) -> tuple[int, int]:
        """The mask's (column, row) of the cell holding ``centre_xy_m`` (2,), from which candidates' offsets count."""
        base = np.floor((np.asarray(centre_xy_m, dtype=float) - self.origin_xy_m) / self.cell_m).astype(np.int64)
        return int(base[0]), int(base[1])

    def admits(self, level: int, centre_xy_m: np.ndarray, cand: np.ndarray) -> np.ndarray:
        """Whether each candidate block (K, 3: angle index, x and y offsets in cells from
        ``centre_xy_m``; side ``2^level`` cells) holds an admitted position, (K,) bool."""
        base_col, base_row = self.cell_of(centre_xy_m)
        col, row = base_col + cand[:, 1], base_row + cand[:, 2]
        grid, size = self.pooled[level], 1 << level
        h, w = grid.shape
        # A block that starts below the grid but reaches into it: the pooled cell at the grid's edge
        # covers all of the block that lies on the grid (and more, which only admits more).
        inside = (col + size > 0) & (col < w) & (row + size > 0) & (row < h)
        out = np.zeros(cand.shape[0], dtype=bool)
        out[inside] = grid[np.maximum(row[inside], 0), np.maximum(col[inside], 0)]
        return out


@dataclass(frozen=True, eq=False)
class SearchResult:
    """What :func:`search` found.

    Attributes
    ----------
    pose : ndarray, shape (3,)
        Best ``(x_m, y_m, theta_rad)`` of the points in the map frame (to a cell and an angle step).
    score : float
        Its mean likelihood (0–1); 0 when nothing beat ``min_score``.
    second_score : float
        Best score of a pose separated from ``pose`` (see ``peak_separation_*``);
        0 when none reached ``min_score``.
    second_pose : ndarray, shape (3,)
        That pose (NaN when none).
    exact : bool
        False if a level was capped at ``max_frontier``.
    leaves : int
        Leaf candidates scored (a measure of the work).
    rival_poses : ndarray, shape (K, 3)
        With ``second_ratio``: the best pose of each place above it, separated from ``pose`` and
        from each other, best first (``second_pose`` the first): a building's copies of one
        stretch. Empty otherwise.
    """

    pose: np.ndarray
    score: float
    second_score: float
    second_pose: np.ndarray
    exact: bool
    leaves: int
    rival_poses: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


def search(grid: LikelihoodGrid, points_xy_m, centre, half_width_m: float, half_angle_rad: float,
           min_score: float, max_frontier: int = MAX_FRONTIER, greedy_starts: int = 1,
           second_ratio: float = 0.0, where: PositionMask | None = None) -> SearchResult:
    """Best pose of the points within ``centre ± (half_width_m, half_width_m, half_angle_rad)``.

    Parameters
    ----------
    grid : LikelihoodGrid
    points_xy_m : array_like, shape (N, 2)
        Points in their robot frame (m), thinned by the caller (the cost is linear in N).
    centre : array_like, shape (3,)
        Guess of their pose in the map frame.
    half_width_m, half_angle_rad : float
        Half sizes of the square translation window (m) and of the rotation window (rad).
    min_score : float
        Leaves scoring below are not of interest (an initial bound; 0–1).
    max_frontier : int
        Candidates kept per level at most (the module's notes).
    greedy_starts : int
        Greedy descents for the first bound, from as many of the best roots (the module's notes).
    second_ratio : float
        Only a second peak scoring at least this share of the best is of interest: it is searched
        for with that bound (far cheaper over a large window), and reported as none if below.
    where : PositionMask, optional
        Only translations it admits are searched, for the best and the second peak alike.

    Returns
    -------
    SearchResult
    """
    p = grid.params
    pts = np.asarray(points_xy_m, dtype=float).reshape(-1, 2)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    centre = np.asarray(centre, dtype=float)
    if pts.shape[0] == 0 or centre.shape != (3,) or not np.all(np.isfinite(centre)):
        raise InputError("search needs points and a finite (3,) centre")
    step = ANGLE_STEP_RAD
    n_ang = int(np.ceil(max(half_angle_rad, 0.0) / step))
    angles = centre[2] + step * np.arange(-n_ang, n_ang + 1)
    n_xy = int(np.ceil(max(half_width_m, 0.0) / p.cell_m))
    # Cells of the rotated points with the window's centre translation, per angle: (A, N).
    c, s = np.cos(angles)[:, None], np.sin(angles)[:, None]
    x = c * pts[:, 0] - s * pts[:, 1] + centre[0]
    y = s * pts[:, 0] + c * pts[:, 1] + centre[1]
    cols = np.floor((x - grid.origin_xy_m[0]) / p.cell_m).astype(np.int64)
    rows = np.floor((y - grid.origin_xy_m[1]) / p.cell_m).astype(np.int64)
    top = p.levels - 1
    cells = kernel.PointCells(rows, cols, grid.grid.shape[1])

    def scores(level: int, cand: np.ndarray, bound: float = -np.inf) -> np.ndarray:
        return kernel.scores(grid.pooled[level], cells, cand, bound)

    def children(level: int, cand: np.ndarray, keep) -> np.ndarray:
        """The four sub-blocks (level − 1) of each candidate that start inside the window and that
        ``keep(cand, side_cells)`` admits (the mask's part in the same compiled pass)."""
        half = 1 << (level - 1)
        mask = () if where is None else (where.pooled[level - 1], *where_cell)
        out = kernel.expand(cand, half, n_xy, *mask)
        return out if keep is everywhere else out[keep(out, half)]

    block = 1 << top
    starts = np.arange(-n_xy, n_xy + 1, block)
    aa, ii, jj = np.meshgrid(np.arange(angles.size), starts, starts, indexing="ij")
    roots = np.column_stack((aa.ravel(), ii.ravel(), jj.ravel()))
    root_scores = scores(top, roots)
    leaves = 0
    exact = True

    def descend(bound: float, keep) -> tuple[np.ndarray, np.ndarray, int, bool]:
        """All leaves scoring at least ``bound`` under blocks admitted by ``keep(cand, side_cells)``."""
        n_leaves, is_exact = 0, True
        admitted = keep(roots, block) & (root_scores >= bound)
        frontier, front_scores = roots[admitted], root_scores[admitted]
        for level in range(top, 0, -1):
            if frontier.shape[0] > max_frontier:
                best_first = np.argsort(-front_scores, kind="stable")[: max_frontier]
                frontier, is_exact = frontier[best_first], False
            frontier = children(level, frontier, keep)
            front_scores = scores(level - 1, frontier, bound)
            if level == 1:
                n_leaves += frontier.shape[0]
            frontier = frontier[front_scores >= bound]
            front_scores = front_scores[front_scores >= bound]
        return frontier, front_scores, n_leaves, is_exact

    def greedy(keep) -> float:
        """Best score of the leaves reached by always taking the best admitted child, from each of
        the ``greedy_starts`` best admitted roots."""
        admitted = np.flatnonzero(keep(roots, block))
        best = 0.0
        for start in admitted[np.argsort(-root_scores[admitted], kind="stable")[:greedy_starts]]:
            cand = roots[start][None, :]
            for level in range(top, 0, -1):
                cand = children(level, cand, keep)
                if cand.shape[0] == 0:
                    break
                cand = cand[np.argmax(scores(level - 1, cand))][None, :]
            else:
                best = max(best, float(scores(0, cand)[0]))
        return best

    def to_pose(cand: np.ndarray) -> np.ndarray:
        return np.array([centre[0] + cand[1] * p.cell_m, centre[1] + cand[2] * p.cell_m, angles[cand[0]]])

    where_cell = where.cell_of(centre[:2]) if where is not None else (0, 0)

    def everywhere(cand: np.ndarray, size: int) -> np.ndarray:
        if where is None:
            return np.ones(cand.shape[0], dtype=bool)
        return where.admits(size.bit_length() - 1, centre[:2], cand)

    first = greedy(everywhere)
    # With a second peak of interest only above second_ratio of the best, one descent to that share
    # of the first bound finds both: every leaf the second descent would, and the best.
    bound = max(min_score, second_ratio * first if second_ratio > 0 else first)
    found, found_scores, n, ok = descend(bound, everywhere)
    leaves += n
    exact &= ok
    if found_scores.size == 0 or found_scores.max() < max(min_score, first):
        nan = np.full(3, np.nan)
        return SearchResult(centre.copy(), 0.0, 0.0, nan, exact, leaves)
    # Ties go to the first in candidate order (angle, then x, then y): deterministic.
    best = found[int(np.argmax(found_scores))]
    best_score = float(found_scores.max())
    best_pose = to_pose(best)

    sep_cells = PEAK_SEPARATION_M / p.cell_m
    sep_angles = PEAK_SEPARATION_RAD / step
    full_turn = 2.0 * np.pi / step

    def apart(cand: np.ndarray, size: int, peak: np.ndarray) -> np.ndarray:
        """Blocks of side ``size`` cells holding a leaf separated from ``peak`` (its farthest corner is)."""
        dx = np.maximum(np.abs(cand[:, 1] - peak[1]), np.abs(cand[:, 1] + size - 1 - peak[1]))
        dy = np.maximum(np.abs(cand[:, 2] - peak[2]), np.abs(cand[:, 2] + size - 1 - peak[2]))
        # Angle steps apart, the short way round: a window of a whole turn holds a heading twice.
        turned = np.abs(cand[:, 0] - peak[0])
        turned = np.minimum(turned, np.abs(full_turn - turned))
        return (np.hypot(dx, dy) >= sep_cells) | (turned >= sep_angles)

    def separated(cand: np.ndarray, size: int) -> np.ndarray:
        return apart(cand, size, best) & everywhere(cand, size)

    # The second peak: the best leaf separated from the winner.
    if second_ratio > 0:
        second_bound = max(min_score, second_ratio * best_score)
        keep = separated(found, 1) & (found_scores >= second_bound)
        others, other_scores = found[keep], found_scores[keep]
    else:
        others, other_scores, n, ok = descend(max(min_score, greedy(separated)), separated)
        leaves += n
        exact &= ok
    if others.shape[0] == 0:
        return SearchResult(best_pose, best_score, 0.0, np.full(3, np.nan), exact, leaves)
    k = int(np.argmax(other_scores))
    second_pose = to_pose(others[k])
    rivals = []
    if second_ratio > 0:
        # Best first (ties in candidate order, as for the second), each place once.
        left = others[np.argsort(-other_scores, kind="stable")]
        while left.shape[0]:
            rivals.append(to_pose(left[0]))
            left = left[apart(left, 1, left[0])]
    return SearchResult(best_pose, best_score, float(other_scores[k]), second_pose, exact, leaves,
                        np.array(rivals).reshape(-1, 3))
