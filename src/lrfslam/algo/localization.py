"""Localization on a saved map: a global search of the whole map until a fix is verified, then tracking.

The robot starts anywhere, with no initial pose. Its own filter (the EKF) gives a local trajectory
that drifts slowly but is right to centimetres over metres; the localizer finds the transform
``map_from_local`` that lays that trajectory on the saved map, and keeps it up to date.

* **Searching.** The scans of the last :data:`QUERY_TRAVEL_M` of travel, merged on the local
  trajectory into the robot's current frame, are searched for over the whole map, every
  :data:`SEARCH_SPACING_M` of travel once they span :data:`MIN_QUERY_TRAVEL_M`: branch and bound over every position and heading
  (:func:`lrfslam.algo.correlative_match.search`, the mapper's closure search, here with a window
  the size of the map), the robot's position only in the map's free space (within
  :data:`FREE_MARGIN_M` of a free cell): a robot stands there, not in a wall or beyond what the map
  saw, and most of a building-sized window is one or the other. A merged stretch tells look-alike places apart where one scan cannot: a
  room seen from its door looks like the next room, the corridor that led there does not.
* **Verifying.** A search's answer is a *candidate* when it scores at least :data:`MIN_SCORE`,
  point-to-line matching against the map's keyframes near it converges, and its beams do not pass
  through the map's walls there (:data:`MAX_SEE_THROUGH`: the walls a look-alike place has behind
  the ones matched disagree with what the scans saw through). Every other place the search found
  (a metre or 20° away) scoring :data:`MAX_SECOND_RATIO` of it is a rival unless the walls
  contradict it clearly more (:data:`SEE_THROUGH_MARGIN`). Before the returns are weighed, what
  the scanner did *not* see is: a place where the query's beams with no return (out through a
  window or an open door) would cross clearly more of the map's walls than at another
  (:data:`OPEN_BEAM_M`, :data:`OPEN_THROUGH_MARGIN`) is refuted, best or not: a building's mirror
  image matches every return and none of its windows. Twin corridors leave both places alike
  and both consistent, so the robot waits for more evidence. A rival stays one, checked at each
  search, until it scores below :data:`HOLD_RATIO` of the best or the walls refute it. A fix is
  *trusted* only when
  :data:`CONFIRM_CANDIDATES` successive candidates over :data:`CONFIRM_TRAVEL_M` of travel put the
  local trajectory in the same place (:data:`AGREE_M`, :data:`AGREE_RAD`), with no ambiguous search
  between them: one lucky search is not a fix. The places are compared where point-to-line
  matching puts them, by each point's distance to the walls (:meth:`LocalizationMap.fit`), not at
  the search's cells and angle steps.
* **Tracking.** Once trusted, ``map_from_local`` is a small filter's state: its uncertainty grows
  with the travel (the local trajectory drifts, :data:`DRIFT_M_PER_SQRT_M`), and each scan,
  matched point to line against the map's keyframes near the predicted pose, measures it; a
  match beyond :data:`TRACK_GATE_CHI2` of the estimate is refused (a person walking by drags a
  match along; the map's transform does not jump). A scan is *localized* when its match was
  taken, it lies on the map there (its points' mean likelihood at least :data:`ON_MAP_SCORE`),
  and its beams do not pass through clearly fewer of the map's walls a step ahead or behind
  (:data:`NEARBY_STEPS_M`; :meth:`Localizer._fits_better_nearby`, the rivals' test, scan by
  scan). The local trajectory can slip along a corridor that neither the returns nor the map tell
  apart (someone walking ahead holds the filter's scan matching), and matching from its
  prediction follows it there; the windows and doors the beams went out through then lie behind
  walls. A scan outside the mapped area, or where the building changed, is *not localized* —
  reported, not forced onto the map — and the transform carries the local trajectory on, its
  uncertainty growing. After :data:`LOST_TRAVEL_M` of travel without a localized scan the
  robot is searched for again, verified as before, but only as far from the dead-reckoned pose
  as it may have drifted: a robot back from an unmapped wing is where it left, and a mapped place
  elsewhere that looks like the wing is not a place to jump to.

The map is never changed. Everything is in metres and radians, poses ``(x_m, y_m, theta_rad)``.
"""

from __future__ import annotations

import enum
from collections import Counter
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from lrfslam.algo import correlative_match as cm
from lrfslam.algo.geometry import (
    compose,
    from_frame,
    inverse,
    relative,
    thin_points,
    wrap_angle,
)
from lrfslam.algo.scan_match import ReferenceScan, ScanMatchParams, match
from lrfslam.errors import InputError

#: Travel whose scans make a global search's query (m): long enough to leave a look-alike room or
#: corridor behind, short enough for the filter's drift over it to stay within a cell.
QUERY_TRAVEL_M = 10.0
#: No search before the query spans this much travel (m): over the first metres a person in view
#: outweighs the walls, and a corridor's far end looks like many others.
MIN_QUERY_TRAVEL_M = 5.0
#: The query keeps a scan each time the robot moved this far (m) or turned this much (rad).
QUERY_SPACING_M = 0.25
QUERY_SPACING_RAD = 0.15
#: The query's points are thinned to one per square of this side (m), then to at most
#: :data:`MAX_QUERY_POINTS` (the search's cost is linear in them).
QUERY_CELL_M = 0.1
MAX_QUERY_POINTS = 300
#: Points of a scan farther than this are not used (m): the scan matcher's range.
MAX_RANGE_M = ScanMatchParams().max_point_range_m
#: The point-to-line matching of a candidate's query (its points reach back over the query's
#: travel) and of a tracked scan.
QUERY_MATCH = ScanMatchParams(max_point_range_m=QUERY_TRAVEL_M + MAX_RANGE_M)
TRACK_MATCH = ScanMatchParams(max_point_range_m=MAX_RANGE_M)
#: Candidates per level of a global search at most: its window is the whole map, where the pooled
#: bounds of the coarse levels are near 1 almost everywhere; a capped search is not exact, and an
#: ambiguity it did not see cannot be refused, so it is not used.
MAX_FRONTIER = 1_000_000
#: Greedy descents for a global search's first bound (``correlative_match.search``'s notes).
GREEDY_STARTS = 32
#: Travel between global searches while not localized (m).
SEARCH_SPACING_M = 1.0
#: A candidate's mean likelihood (0–1) at least this...
MIN_SCORE = 0.5
#: ...and its best separated rival's below this fraction of it.
MAX_SECOND_RATIO = 0.9
#: A place that once rivalled the best (:data:`MAX_SECOND_RATIO`) stays a rival while it scores at
#: least this fraction of the best: inside a stretch the building repeats, the map favours one copy
#: or the other by chance (a wall mapped thicker, a person), the right one no more often than the
#: wrong, so a rival is dismissed only when the walls beyond the stretch refute it.
HOLD_RATIO = 0.8
#: A candidate is refused when more than this share of its query's beams passes through an
#: occupied cell of the map (:meth:`Localizer.see_through`), followed up to SEE_THROUGH_CLEAR_M (m)
#: short of its return (the wall it ends on, blurred by a cell and the filter's drift).
MAX_SEE_THROUGH = 0.05
#: A rival scoring as well is dismissed when this much more of the query's beams (a share, 0–1)
#: passes through walls there than at the best pose: at ~20 beams a metre of travel, a hundred
#: beams more over the query is no chance.
SEE_THROUGH_MARGIN = 0.01
SEE_THROUGH_CLEAR_M = 0.4
#: A beam with no return crossed free space at least this far (m): an LMS200 returns from any wall
#: this close, dark or not (glass at a glancing angle aside, mapped as a wall where it once
#: returned: so places are only compared by these beams, never judged by them alone). At a
#: look-alike place such a beam may cross the map's walls where, at the true place, it left
#: through a window or an open door: what the scanner did *not* see tells a building's mirror
#: image from itself where every return matches both.
OPEN_BEAM_M = 4.0
#: A place whose beams with no return cross this much more of the map's walls (a share, 0–1) than
#: another's is refuted: at the true place a few cross where a wall was mapped thick or a door
#: closed (0.5–3 % in the simulator's building), at its mirror image most of them.
OPEN_THROUGH_MARGIN = 0.05
#: A tracked scan is not localized where it passes through clearly fewer walls this far ahead or
#: behind (m): a filter held back along a corridor shows there, before it is a metre off, and
#: where it is, a metre on it does not.
NEARBY_STEPS_M = (-1.0, -0.5, 0.5, 1.0)
#: Two candidates agree when their ``map_from_local`` differ by at most this (m, rad).
AGREE_M = 0.3
AGREE_RAD = 0.05
#: A fix is trusted when this many successive candidates agree over at least this travel (m); a
#: candidate that disagrees starts the count again. A building's symmetric halves, or two rooms
#: alike, agree with a wrong place for a few metres; the walls beyond part them.
CONFIRM_CANDIDATES = 3
CONFIRM_TRAVEL_M = 4.0
#: A tracked scan lies on the map when its points' mean likelihood is at least this (0–1).
ON_MAP_SCORE = 0.35
#: Travel without a scan on the map after which the fix is searched for again, around the
#: dead-reckoned pose, in a window of WINDOW_SIGMAS of its uncertainty (and this travel) (m).
LOST_TRAVEL_M = 3.0
WINDOW_SIGMAS = 3.0
#: The map's keyframes within this distance of the predicted pose make the reference for
#: tracking and verifying (m); it is rebuilt when the pose moved :data:`REFERENCE_MOVE_M` from
#: where it was built.
REFERENCE_RADIUS_M = 12.0
REFERENCE_MOVE_M = 2.0
#: The map's points are thinned to one per square of this side (m) for the reference.
REFERENCE_CELL_M = 0.05
#: The likelihood grid's cell (m) and the side (m) its coarsest level's blocks reach at least.
GRID_CELL_M = 0.1
TOP_BLOCK_M = 6.4
#: The floor of the prediction's error a tracking match starts from (m, rad): the local
#: trajectory's between scans, with room.
TRACK_GUESS_SIGMA_M = 0.05
TRACK_GUESS_SIGMA_RAD = 0.02
#: The local trajectory's drift against the map, a random walk (m and rad per √m travelled): the
#: transform's uncertainty grows so between matches, and off the map.
DRIFT_M_PER_SQRT_M = 0.02
DRIFT_RAD_PER_SQRT_M = 0.01
#: A tracking match's covariance is taken this many times the matcher's (which counts every point
#: as independent), plus the map's own error (m, rad).
TRACK_COV_SCALE = 4.0
MAP_SIGMA_M = 0.02
MAP_SIGMA_RAD = 0.005
#: A tracking match whose transform lies beyond this χ²₃ (99.9 %) of the estimate's is refused.
TRACK_GATE_CHI2 = 16.27
#: The heading window of a search around a lost fix, beyond its uncertainty's (rad).
LOST_WINDOW_RAD = 0.2


#: An occupied and a free cell of a saved map's grid (nav_msgs/OccupancyGrid's values).
OCCUPIED = 100
FREE = 0
#: A search places the robot only within this distance (m) of a free cell of the map: it stands in
#: the building's free space (where a person or a moved chair stood while mapping, too).
FREE_MARGIN_M = 0.5


class Status(enum.IntEnum):
    """Whether a scan was placed on the map (``MapPose.localization``'s values 1 and 2)."""

    LOCALIZED = 1
    NOT_LOCALIZED = 2


@dataclass(frozen=True, eq=False)
class Placement:
    """What :meth:`Localizer.add_scan` says of one scan.

    Attributes
    ----------
    status : Status
    pose : ndarray, shape (3,)
        The scan's pose in the map frame: matched on the map when localized; the local pose carried
        by the last fix when not (the local pose itself before any fix).
    cov : ndarray, shape (3, 3), or None
        Its covariance (m², m·rad, rad²); None before any fix.
    map_from_local : ndarray, shape (3,)
        ``pose = map_from_local ⊕ local pose``.
    score : float
        The scan's points' mean likelihood on the map at ``pose`` (0–1); 0 before any fix.
    """

    status: Status
    pose: np.ndarray
    cov: np.ndarray | None
    map_from_local: np.ndarray
    score: float


@dataclass(frozen=True, eq=False)
class Walls:
    """A saved map's occupancy grid: ``cells`` (H, W) int8, 100 occupied, 0 free, -1 unknown, row 0
    the lowest y, cell ``[0, 0]``'s corner at ``origin_xy_m`` (2,), ``resolution_m`` a side (m)."""

    cells: np.ndarray
    resolution_m: float
    origin_xy_m: np.ndarray

    def occupied_xy_m(self) -> np.ndarray:
        """Centres of the occupied cells (M, 2), m."""
        return self._centres(self.cells == OCCUPIED)

    def free_xy_m(self) -> np.ndarray:
        """Centres of the free cells (M, 2), m."""
        return self._centres(self.cells == FREE)

    def _centres(self, which: np.ndarray) -> np.ndarray:
        rows, cols = np.nonzero(which)
        return self.origin_xy_m + (np.column_stack((cols, rows)) + 0.5) * self.resolution_m

    def occupied_at(self, xy_m: np.ndarray) -> np.ndarray:
        """Whether each point (N, 2) lies in an occupied cell (N,) bool; outside the grid: no."""
        idx = np.floor((np.asarray(xy_m, float) - self.origin_xy_m) / self.resolution_m).astype(np.int64)
        h, w = self.cells.shape
        ok = (idx[:, 0] >= 0) & (idx[:, 0] < w) & (idx[:, 1] >= 0) & (idx[:, 1] < h)
        out = np.zeros(idx.shape[0], bool)
        out[ok] = self.cells[idx[ok, 1], idx[ok, 0]] == OCCUPIED
        return out


@dataclass(frozen=True, eq=False)
class _Peak:
    map_from_local: np.ndarray   # (3,)
    score: float                 # the query's mean likelihood there (0–1), LocalizationMap.fit
    see_through: float           # Localizer.see_through there: the returns'...
    open_through: float          # ...and the beams' with no return
    cov: np.ndarray              # (3, 3) the match's


@dataclass
class _QueryScan:
    local_pose: np.ndarray         # (3,)
    points_xy_m: np.ndarray        # (N, 2) robot frame, thinned
    open_bearings_rad: np.ndarray  # (K,) robot frame: the beams with no return


class LocalizationMap:
    """A saved map made ready to localize in (built once; the grids are read-only after).

    Parameters
    ----------
    keyframe_poses : array_like, shape (K, 3)
        The saved map's keyframes' poses in the map frame.
    keyframe_points : sequence of K arrays, shape (N_k, 2)
        Each keyframe's scan points in its own frame (m): the reference that tracking matches.
    walls : Walls
        The saved map's occupancy grid: the global search's map and the see-through test's walls.

    Attributes
    ----------
    grid : LikelihoodGrid
        The occupied cells' likelihood grid, pooled for the global search.
    """

    def __init__(self, keyframe_poses, keyframe_points, walls: Walls) -> None:
        poses = np.asarray(keyframe_poses, dtype=float).reshape(-1, 3)
        if poses.shape[0] == 0 or len(keyframe_points) != poses.shape[0]:
            raise InputError("a localizer needs a map with keyframes, one point set each")
        self.keyframe_xy_m = poses[:, :2].copy()
        self.keyframe_points = [thin_points(from_frame(np.asarray(p, float).reshape(-1, 2), pose), REFERENCE_CELL_M)
                                for p, pose in zip(keyframe_points, poses, strict=True)]
        self.walls = walls
        # The search's map is the grid's occupied cells: what stayed put while mapping (a person who
        # walked by was seen through later, and is free there), not every point ever returned.
        every = walls.occupied_xy_m()
        if every.shape[0] == 0:
            raise InputError("a localizer needs a map with occupied cells")
        extent = float(np.max(np.ptp(every, axis=0)))
        levels = int(min(12, max(1, np.ceil(np.log2(max(TOP_BLOCK_M, extent / 8.0) / GRID_CELL_M)) + 1)))
        self.grid = cm.LikelihoodGrid(every, cm.CorrelativeParams(cell_m=GRID_CELL_M, levels=levels))
        self._walls_tree = cKDTree(every)
        #: Where a search may place the robot: the map's free space (anywhere, in a grid with no free cell).
        free = walls.free_xy_m()
        self.free = cm.PositionMask(self.grid, free, FREE_MARGIN_M) if free.shape[0] else None
        lo, hi = every.min(axis=0), every.max(axis=0)
        self.centre = np.array([(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, 0.0])
        self.half_width_m = float(np.max(hi - lo)) / 2.0 + 1.0

    def fit(self, points_xy_m: np.ndarray, pose: np.ndarray) -> float:
        """Mean likelihood (0–1) of the points (N, 2, robot frame) at ``pose`` (3,), from each point's
        distance to the nearest occupied cell's centre: the search grid's likelihood without its
        cells. Peaks are compared by it: on cells of :data:`GRID_CELL_M` a wall lying on a cell's
        edge costs a place up to a fifth of its score, a wall mid-cell nothing, and a building's
        two alike halves have their walls on the grid differently (in the simulator's building the
        true place lost 0.7 against its mirror's 0.9 on the grid, and tied by this fit)."""
        d, _ = self._walls_tree.query(from_frame(points_xy_m, pose), distance_upper_bound=4.0 * cm.HIT_SIGMA_M)
        return float(np.mean(np.exp(-0.5 * (np.minimum(d, 4.0 * cm.HIT_SIGMA_M) / cm.HIT_SIGMA_M) ** 2)))

    def reference_near(self, pose: np.ndarray) -> ReferenceScan:
        """Point-to-line reference of the keyframes within :data:`REFERENCE_RADIUS_M` of ``pose`` (3,)."""
        near = np.flatnonzero(np.hypot(*(self.keyframe_xy_m - pose[:2]).T) <= REFERENCE_RADIUS_M)
        pts = np.vstack([self.keyframe_points[k] for k in near]) if near.size else np.zeros((0, 2))
        return ReferenceScan.build(thin_points(pts, REFERENCE_CELL_M))


class Localizer:
    """Finds and tracks the robot on a saved map (the module's docstring); one per run.

    Parameters
    ----------
    place : LocalizationMap
        The map, shared by any number of localizers.
    """

    def __init__(self, place: LocalizationMap) -> None:
        self.map = place
        self._query: list[_QueryScan] = []
        self._travel_m = 0.0                       # along the local trajectory, from the first scan
        self._last_local: np.ndarray | None = None
        self._next_search_m = 0.0
        self._agreeing: list[tuple[float, np.ndarray]] = []   # (travel m, map_from_local) of agreeing candidates
        self._rivals: list[np.ndarray] = []          # map_from_local of places that rivalled the best, not yet refuted
        self.map_from_local: np.ndarray | None = None   # the trusted fix
        self._last_on_map_m = 0.0
        self._cov = np.zeros((3, 3))                 # of map_from_local
        self._reference: tuple[np.ndarray, ReferenceScan] | None = None
        self._lost = False                         # off the map for LOST_TRAVEL_M since the last match
        #: Searches run (global, or around a lost fix), candidates found, fixes trusted, times the
        #: fix was lost (off the map).
        self.searches = self.candidates = self.fixes = self.lost = 0
        #: Searches that gave no candidate, by why: ``inexact`` (capped), ``low_score``,
        #: ``refine_failed``, ``ambiguous``, ``seen_through``.
        self.refused: Counter[str] = Counter()
        #: Tracking matches refused by the gate; tracked scans doubted (they fit the walls better a
        #: step on: not localized).
        self.gated = self.doubted = 0

    @property
    def localized(self) -> bool:
        """Whether a fix is trusted (the last scan may still have been off the map)."""
        return self.map_from_local is not None

    def add_scan(self, local_pose, points_xy_m, open_bearings_rad=()) -> Placement:
        """Take one scan: its pose on the local trajectory (3,), its points (N, 2) in the robot frame
        (m), and the bearings (K,) of its beams with no return (rad, robot frame)."""
        local = np.asarray(local_pose, dtype=float).reshape(3)
        pts = np.asarray(points_xy_m, dtype=float).reshape(-1, 2)
        pts = pts[np.all(np.isfinite(pts), axis=1) & (np.hypot(pts[:, 0], pts[:, 1]) <= MAX_RANGE_M)]
        step_m = 0.0 if self._last_local is None else float(np.hypot(*relative(self._last_local, local)[:2]))
        self._travel_m += step_m
        self._last_local = local
        open_rad = np.asarray(open_bearings_rad, dtype=float).reshape(-1)
        self._keep_for_query(local, pts, open_rad)
        if self.map_from_local is None:
            self._search(local, self.map.centre, self.map.half_width_m, np.pi)
        if self.map_from_local is None:
            return Placement(Status.NOT_LOCALIZED, local.copy(), None, np.zeros(3), 0.0)
        return self._track(local, pts, open_rad, step_m)

    # -- searching

    def _keep_for_query(self, local: np.ndarray, pts: np.ndarray, open_rad: np.ndarray) -> None:
        if self._query:
            d = relative(self._query[-1].local_pose, local)
            if np.hypot(d[0], d[1]) < QUERY_SPACING_M and abs(d[2]) < QUERY_SPACING_RAD:
                return
        self._query.append(_QueryScan(local, thin_points(pts, QUERY_CELL_M), open_rad))
        # Only the last QUERY_TRAVEL_M of travel: drop the oldest beyond it.
        while len(self._query) > 2 and self._path_m(self._query[1:]) > QUERY_TRAVEL_M:
            self._query.pop(0)

    @staticmethod
    def _path_m(scans: list[_QueryScan]) -> float:
        xy = np.array([q.local_pose[:2] for q in scans])
        return float(np.sum(np.hypot(*np.diff(xy, axis=0).T))) if len(scans) > 1 else 0.0

    def _query_points(self, local: np.ndarray) -> np.ndarray:
        """The query's points in the robot frame at ``local`` (M, 2): every kept scan merged, thinned."""
        return query_of(np.vstack([from_frame(q.points_xy_m, relative(local, q.local_pose)) for q in self._query]))

    def _search(self, local: np.ndarray, centre: np.ndarray, half_width_m: float, half_angle_rad: float) -> None:
        """Search the query in the window ``centre`` (3,) ± (``half_width_m``, ``half_angle_rad``) of
        the map (all of it before the first fix); a confirmed candidate becomes the fix."""
        if self._travel_m < self._next_search_m:
            return
        if self._path_m(self._query) < MIN_QUERY_TRAVEL_M:
            return
        self._next_search_m = self._travel_m + SEARCH_SPACING_M
        query = self._query_points(local)
        if query.shape[0] < 20:
            return
        self.searches += 1
        found = cm.search(self.map.grid, query, centre, half_width_m, half_angle_rad, MIN_SCORE, MAX_FRONTIER,
                          GREEDY_STARTS, MAX_SECOND_RATIO, where=self.map.free)
        if not found.exact:
            self.refused["inexact"] += 1
            return
        if found.score < MIN_SCORE:
            self.refused["low_score"] += 1
            return
        # The peaks are compared where point-to-line matching puts them: at the search's cells
        # and angle steps a place can lose more than its rival, which it may not deserve.
        best = self._refine(query, found.pose, local)
        if best is None:
            self.refused["refine_failed"] += 1
            return
        found_peaks = [best, *(self._refine(query, pose, local) for pose in found.rival_poses)]
        # Earlier rivals the search did not find again are checked where they were.
        earlier = [self._refine(query, compose(place, local), local) for place in self._rivals
                   if not any(p is not None and _agree(place, p.map_from_local) for p in found_peaks)]
        peaks = [p for p in found_peaks + earlier if p is not None]
        # What the scanner saw no wall through refutes a place before its returns are weighed: of the
        # places that score near the best, one whose beams with no return cross clearly more of
        # the map's walls than another's is not where the robot is, however well its returns fit.
        top = max(p.score for p in peaks)
        peaks = [p for p in peaks if p.score >= HOLD_RATIO * top]
        least = min(p.open_through for p in peaks)
        peaks = [p for p in peaks if p.open_through <= least + OPEN_THROUGH_MARGIN]
        best = max(peaks, key=lambda p: p.score)
        # A place as good, where the walls do not contradict it more, is a rival; one that was a
        # rival stays one down to HOLD_RATIO.
        held: list[np.ndarray] = []
        for peak in peaks:
            place = peak.map_from_local
            if _agree(place, best.map_from_local) or any(_agree(place, h) for h in held):
                continue
            ratio = HOLD_RATIO if any(_agree(place, r) for r in self._rivals) else MAX_SECOND_RATIO
            if peak.score >= ratio * best.score and self._rivals_with(peak, best):
                held.append(place)
        self._rivals = held
        if self._rivals:
            self._rivals.append(best.map_from_local)
            self.refused["ambiguous"] += 1
            self._agreeing.clear()   # wait, and count agreeing candidates from the next on
            return
        if best.see_through > MAX_SEE_THROUGH:
            self.refused["seen_through"] += 1
            return
        candidate, refined = best.map_from_local, best
        self.candidates += 1
        chain = self._agreeing
        if chain and not _agree(chain[-1][1], candidate):
            chain.clear()
        chain.append((self._travel_m, candidate))
        if len(chain) >= CONFIRM_CANDIDATES and self._travel_m - chain[0][0] >= CONFIRM_TRAVEL_M:
            self.fixes += 1
            self.map_from_local = candidate
            chain.clear()
            self._rivals.clear()
            self._last_on_map_m = self._travel_m
            inv = np.linalg.inv(_lever(compose(candidate, local), candidate))
            self._cov = inv @ (TRACK_COV_SCALE * refined.cov + np.diag([MAP_SIGMA_M ** 2] * 2 + [MAP_SIGMA_RAD ** 2])) @ inv.T

    @staticmethod
    def _rivals_with(rival: _Peak, best: _Peak) -> bool:
        """Whether ``rival`` stays a rival of ``best`` as far as the walls go: its beams do not pass
        through clearly more of them (:data:`SEE_THROUGH_MARGIN`) nor too many (:data:`MAX_SEE_THROUGH`)."""
        return rival.see_through <= min(MAX_SEE_THROUGH, best.see_through + SEE_THROUGH_MARGIN)

    def _refine(self, query: np.ndarray, pose: np.ndarray, local: np.ndarray) -> _Peak | None:
        """A search's peak ``pose`` (3,) matched point to line against the map near it; None if that fails."""
        res = match(self._reference_at(pose), query, pose, QUERY_MATCH)
        if not res.ok:
            return None
        map_from_local = compose(res.pose, inverse(local))
        returns, open_beams = self.see_through(map_from_local)
        return _Peak(map_from_local, self.map.fit(query, res.pose), returns, open_beams, res.cov)

    def see_through(self, map_from_local: np.ndarray) -> tuple[float, float]:
        """Shares (0–1) of the query's beams that pass through an occupied cell of the map when the
        query's scans are laid by ``map_from_local`` (3,): of the beams with a return, followed up to
        :data:`SEE_THROUGH_CLEAR_M` short of it, and of those with none, followed :data:`OPEN_BEAM_M`.
        At the true place a beam ends at the first wall on its way (a person or an opened door
        aside); at a look-alike place the walls behind the ones it matched disagree."""
        returns, open_beams = [], []
        for q in self._query:
            directions, reach, is_open = _beams(q.points_xy_m, q.open_bearings_rad)
            hit = self._crossing(directions, reach, compose(map_from_local, q.local_pose))
            if np.any(reach[~is_open] > 0.0):   # a scan of nothing but the last 0.4 m says nothing
                returns.append(hit[~is_open])
            open_beams.append(hit[is_open])
        return _share(returns, empty=1.0), _share(open_beams, empty=0.0)

    def _crossing(self, directions: np.ndarray, reach_m: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """Whether each beam (unit ``directions`` (N, 2), robot frame, from a sensor at ``pose`` (3,))
        meets an occupied cell of the map within its ``reach_m`` (N,), sampled a cell apart (N,) bool."""
        step = self.map.walls.resolution_m
        n = int(np.ceil(float(reach_m.max(initial=0.0)) / step))
        if n == 0:
            return np.zeros(directions.shape[0], bool)
        dist = step * np.arange(1, n + 1)
        inside = dist[None, :] <= reach_m[:, None]
        along = directions[:, None, :] * dist[None, :, None]
        hit = np.zeros(inside.shape, bool)
        hit[inside] = self.map.walls.occupied_at(from_frame(along[inside], pose))
        return np.any(hit, axis=1)

    # -- tracking

    def _reference_at(self, pose: np.ndarray) -> ReferenceScan:
        """The map's reference near ``pose``, kept while the pose stays within :data:`REFERENCE_MOVE_M` of where it was made."""
        if self._reference is None or np.hypot(*(self._reference[0] - pose[:2])) > REFERENCE_MOVE_M:
            self._reference = (pose[:2].copy(), self.map.reference_near(pose))
        return self._reference[1]

    def _track(self, local: np.ndarray, pts: np.ndarray, open_rad: np.ndarray, step_m: float) -> Placement:
        # The transform drifts as the filter's trajectory does: its uncertainty grows with the travel.
        self._cov += np.diag([DRIFT_M_PER_SQRT_M ** 2 * step_m] * 2 + [DRIFT_RAD_PER_SQRT_M ** 2 * step_m])
        predicted = compose(self.map_from_local, local)
        matched = False
        if pts.shape[0]:
            guess_cov = _lever(predicted, self.map_from_local) @ self._cov @ _lever(predicted, self.map_from_local).T
            guess_cov = guess_cov + np.diag([TRACK_GUESS_SIGMA_M ** 2] * 2 + [TRACK_GUESS_SIGMA_RAD ** 2])
            res = match(self._reference_at(predicted), pts, predicted, TRACK_MATCH, guess_cov)
            if res.ok:
                matched = self._update(compose(res.pose, inverse(local)), res.pose, res.cov)
        pose = compose(self.map_from_local, local)
        lever = _lever(pose, self.map_from_local)
        cov = lever @ self._cov @ lever.T
        score = self.map.grid.score(pts, pose) if pts.shape[0] else 0.0
        # The rivals' test, scan by scan: where the scan's beams pass through clearly fewer walls a
        # step on, the pose is not where the robot is (the filter's trajectory slipped, and matching
        # along a corridor neither the scan nor the map tell apart followed it). Such a scan is not
        # on the map, and LOST_TRAVEL_M of them search for the fix again.
        doubted = self._fits_better_nearby(pts, open_rad, pose)
        self.doubted += doubted
        if matched and score >= ON_MAP_SCORE and not doubted:
            self._lost, self._last_on_map_m = False, self._travel_m
            return Placement(Status.LOCALIZED, pose, cov, self.map_from_local.copy(), score)
        placement = Placement(Status.NOT_LOCALIZED, pose, cov, self.map_from_local.copy(), score)
        if self._travel_m - self._last_on_map_m > LOST_TRAVEL_M:
            # Off the map, or lost on it: search again around where the fix says the robot is,
            # as far as the dead reckoning may have drifted (a robot back from an unmapped wing is
            # where it left it; a copy of a mapped part elsewhere is not a place to jump to).
            if not self._lost:
                self._lost, self.lost, self._next_search_m = True, self.lost + 1, self._travel_m
            sigma_m = float(np.sqrt(max(cov[0, 0], cov[1, 1])))
            self._search(local, pose, min(WINDOW_SIGMAS * sigma_m + LOST_TRAVEL_M, self.map.half_width_m),
                         min(WINDOW_SIGMAS * float(np.sqrt(cov[2, 2])) + LOST_WINDOW_RAD, np.pi))
        return placement

    def _fits_better_nearby(self, pts: np.ndarray, open_rad: np.ndarray, pose: np.ndarray) -> bool:
        """Whether one scan passes through clearly fewer of the map's walls (:data:`OPEN_THROUGH_MARGIN`
        of its beams) ahead of or behind ``pose`` (3,) (:data:`NEARBY_STEPS_M`) than at it: its returns
        (``pts`` (N, 2), robot frame) followed as :meth:`see_through` follows a query's, and its
        beams with no return (``open_rad`` (K,), rad) :data:`OPEN_BEAM_M`. Relative, as rivals
        are judged: where glass or a door mapped shut lets beams through walls at the right pose,
        they pass through them a step on too."""
        directions, reach, _ = _beams(pts, open_rad)
        followed = reach > 0.0   # returns within SEE_THROUGH_CLEAR_M have no way to cross
        directions, reach = directions[followed], reach[followed]
        if not reach.size:
            return False

        def share(at: np.ndarray) -> float:
            return float(np.mean(self._crossing(directions, reach, at)))

        here = share(pose)
        return here > OPEN_THROUGH_MARGIN and any(
            share(compose(pose, np.array([step, 0.0, 0.0]))) < here - OPEN_THROUGH_MARGIN for step in NEARBY_STEPS_M)

    def _update(self, measured: np.ndarray, pose: np.ndarray, pose_cov: np.ndarray) -> bool:
        """Fuse a scan's ``map_from_local`` (3,), from its matched ``pose`` (3,) with ``pose_cov``, into
        the transform's estimate; False if it lies beyond :data:`TRACK_GATE_CHI2` (a person who
        dragged the match, a look-alike door)."""
        lever = _lever(pose, measured)
        inv = np.linalg.inv(lever)   # the pose's error, as the transform's
        r = inv @ (TRACK_COV_SCALE * pose_cov + np.diag([MAP_SIGMA_M ** 2] * 2 + [MAP_SIGMA_RAD ** 2])) @ inv.T
        innovation = measured - self.map_from_local
        innovation[2] = wrap_angle(innovation[2])
        s = self._cov + r
        if not float(innovation @ np.linalg.solve(s, innovation)) <= TRACK_GATE_CHI2:
            self.gated += 1
            return False
        gain = np.linalg.solve(s.T, self._cov.T).T   # P S⁻¹
        step = gain @ innovation
        self.map_from_local = self.map_from_local + step
        self.map_from_local[2] = wrap_angle(self.map_from_local[2])
        self._cov = (np.eye(3) - gain) @ self._cov
        self._cov = 0.5 * (self._cov + self._cov.T)
        return True


def _beams(points_xy_m: np.ndarray, open_bearings_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One scan's beams as the wall tests follow them: unit directions (N + K, 2), robot frame; how
    far each is followed (N + K,), m — a return up to :data:`SEE_THROUGH_CLEAR_M` short of it (≤ 0
    for one that close), a beam with no return :data:`OPEN_BEAM_M`; and which have no return (N + K,)."""
    r = np.hypot(points_xy_m[:, 0], points_xy_m[:, 1])
    directions = np.vstack((points_xy_m / np.maximum(r, 1e-9)[:, None],
                            np.column_stack((np.cos(open_bearings_rad), np.sin(open_bearings_rad)))))
    reach = np.concatenate((r - SEE_THROUGH_CLEAR_M, np.full(open_bearings_rad.size, OPEN_BEAM_M)))
    return directions, reach, np.arange(reach.size) >= r.size


def _share(hits: list[np.ndarray], empty: float) -> float:
    """The share of True in ``hits`` (arrays of bool), ``empty`` if there are none."""
    every = np.concatenate(hits) if hits else np.zeros(0, bool)
    return float(np.mean(every)) if every.size else empty


def query_of(merged_xy_m: np.ndarray) -> np.ndarray:
    """A global search's query from scans merged in the robot's frame (N, 2): thinned to one point
    per :data:`QUERY_CELL_M` square, then evenly to at most :data:`MAX_QUERY_POINTS` (M, 2), m."""
    pts = thin_points(merged_xy_m, QUERY_CELL_M)
    if pts.shape[0] > MAX_QUERY_POINTS:
        pts = pts[np.linspace(0, pts.shape[0] - 1, MAX_QUERY_POINTS).astype(int)]
    return pts


def _lever(pose: np.ndarray, transform: np.ndarray) -> np.ndarray:
    """Jacobian (3, 3) of ``pose = transform ⊕ local`` by ``transform`` at fixed ``local``: a turn
    of the transform moves the pose by its distance from the transform's origin."""
    return np.array([[1.0, 0.0, -(pose[1] - transform[1])], [0.0, 1.0, pose[0] - transform[0]], [0.0, 0.0, 1.0]])


def _agree(a: np.ndarray, b: np.ndarray) -> bool:
    d = relative(a, b)
    return bool(np.hypot(d[0], d[1]) <= AGREE_M and abs(d[2]) <= AGREE_RAD)
