"""Finding loop closures: candidates, search windows, correlative search and verification.

:class:`ClosureSearch` looks for the newest keyframe in the maps of keyframes seen long before
(the package notes, :mod:`lrfslam.algo.loop_closure`: "Search window from the graph", "Where the
online estimate puts it", "Submaps", "Verification", "Cost") and returns the closures that passed
every check; the mapper adds them to its graph. It keeps what a search needs between keyframes:
the submaps' cache, a wide-window closure waiting for confirmation, the spacing of wide searches,
and the closures' NIS.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from lrfslam.algo.correlative_match import LikelihoodGrid, search
from lrfslam.algo.geometry import compose, from_frame, relative, thin_points
from lrfslam.algo.loop_closure.keyframes import Keyframe
from lrfslam.algo.loop_closure.params import (
    CACHED_SUBMAPS,
    CONFIRM_M,
    CONFIRM_RAD,
    CONFIRM_WITHIN_M,
    KEYFRAME_CELL_M,
    MAX_WINDOW_RAD,
    MIN_WINDOW_RAD,
    QUERY_CELL_M,
    SCAN_MATCH,
    SUBMAP_KEYFRAMES,
    WIDE_SEARCH_SPACING_M,
    WIDE_WINDOW_M,
    WINDOW_SIGMAS,
    LoopClosureParams,
)
from lrfslam.algo.pose_graph import PoseGraph
from lrfslam.algo.scan_match import ReferenceScan, match

#: A verified closure: ``(old keyframe, new keyframe, measurement (3,) — the new keyframe in the
#: old one's frame (m, m, rad), its covariance (3, 3), innovation (3,) against the graph's prediction)``.
Closure = tuple[int, int, np.ndarray, np.ndarray, np.ndarray]


@dataclass(frozen=True)
class ClosureStats:
    """Counts of :class:`LoopClosingMapper`'s closure attempts so far.

    Attributes
    ----------
    searched : int
        Correlative searches run.
    low_score, ambiguous, refine_failed, gated : int
        Candidates dropped at each verification step (see the module notes).
    unconfirmed : int
        Closures from a wide window that no second one confirmed.
    accepted : int
        Loop edges added to the graph.
    removed : int
        Of those, removed after optimisation (the graph disagreed).
    folded : int
        Revisit keyframes folded into the keyframes they revisited (``fold_revisits``).
    optimisations : int
        Graph optimisations run.
    ekf_jumps : int
        Odometry edges taken from matched scans because the local motion jumped.
    """

    searched: int = 0
    low_score: int = 0
    ambiguous: int = 0
    refine_failed: int = 0
    gated: int = 0
    unconfirmed: int = 0
    accepted: int = 0
    removed: int = 0
    folded: int = 0
    optimisations: int = 0
    ekf_jumps: int = 0


#: What became of a closure attempt (:class:`ClosureAttempt`): the verification step that dropped
#: it (as counted in :class:`ClosureStats`), ``accepted`` into the graph, or ``removed`` from it
#: after an optimisation (the graph disagreed).
VERDICTS = ("low_score", "ambiguous", "refine_failed", "gated", "unconfirmed", "accepted", "removed")


@dataclass(frozen=True)
class ClosureAttempt:
    """One loop closure the mapper tried, for an audit against ground truth (``lrfslam eval closures``).

    Attributes
    ----------
    old_stamp_ns, new_stamp_ns : int
        The stamps of the scans that made the old keyframe and the new one.
    pose : ndarray, shape (3,)
        What was measured: the new keyframe in the old one's frame (m, m, rad) — the refined
        match, or the correlative search's best pose where it stopped before refining.
    cov : ndarray, shape (3, 3), or None
        The measurement's covariance (m², rad²) where it was refined, else None.
    verdict : str
        One of :data:`VERDICTS`.
    """

    old_stamp_ns: int
    new_stamp_ns: int
    pose: np.ndarray
    cov: np.ndarray | None
    verdict: str


def window_covariance(graph: PoseGraph, k: int, n: int, drift_onset_rad: float) -> np.ndarray:
    """Covariance (3, 3) of node ``n`` relative to node ``k`` as the search and the gate take it:
    the graph's, grown by its own heading variance past ``drift_onset_rad`` (rad; 0: as is).

    Systematic drift: a random walk's standard deviation grows with the square root of the
    loop, a heading bias's error with the loop itself, so past the onset the graph's relative
    covariance grows by ``1 + σθ² / onset²``.
    """
    rel_cov = graph.relative_covariance(k, n)
    if drift_onset_rad > 0.0:
        rel_cov = rel_cov * (1.0 + rel_cov[2, 2] / drift_onset_rad**2)
    return rel_cov


class ClosureSearch:
    """The closure search's state between keyframes (mutable; see the module notes).

    Parameters
    ----------
    params : LoopClosureParams
    counts : dict
        The mapper's counters (:class:`ClosureStats`' names), incremented here for each check
        that drops a candidate.
    observe : callable
        ``observe(old keyframe, new keyframe, pose (3,), covariance (3, 3) or None, verdict)``
        for every closure verified or dropped.
    """

    def __init__(self, params: LoopClosureParams, counts: dict[str, int],
                 observe: Callable[[int, int, np.ndarray, np.ndarray | None, str], None]) -> None:
        self.params = params
        self.counts = counts
        self._observe = observe
        #: keyframe -> (last neighbour in it, grid, line reference), least recently used first
        self.submaps: OrderedDict[int, tuple[int, LikelihoodGrid, ReferenceScan]] = OrderedDict()
        self.tentative: Closure | None = None   # a closure from a wide window awaiting confirmation
        #: Keyframes made before this ordinal are a saved map's (:meth:`LoopClosingMapper.seeded`): a
        #: query is made of the run's own keyframes, a submap of one side's, never of both (the
        #: saved map's last keyframe and the run's first are neighbours in order, not in space).
        self.run_start = 0
        self.last_wide_search_m = -np.inf   # travel at the last wide search
        # Of the closures that passed verification: how many, and their NIS summed (a running
        # total: a long run's closures are not kept).
        self.closure_nis = (0, 0.0)

    def find(self, keyframes: list[Keyframe], graph: PoseGraph) -> list[Closure]:
        """The closures of the newest keyframe that passed every check (module notes, "Verification")."""
        p = self.params
        n = len(keyframes) - 1
        if p.max_candidates == 0:
            return []
        poses = graph.poses
        travel = np.array([kf.travel_m for kf in keyframes])
        # A candidate has points of its own (its scan may have been lost; its neighbours' may
        # have been trimmed), so its submap is never empty.
        # (A revisit is marked only with ``trim_revisits``.)
        older = (travel <= travel[n] - p.min_travel_m) & np.array([kf.points_xy_m.shape[0] > 0 and not kf.revisit
                                                                   for kf in keyframes])
        old = np.flatnonzero(older)
        if old.size == 0:
            return []
        reach = p.max_window_m + p.candidate_radius_m
        ordinal = [kf.ordinal for kf in keyframes]
        chosen: list[tuple[int, bool]] = []   # (keyframe, found by the online estimate)

        def choose(near: np.ndarray, dist: np.ndarray, online: bool) -> None:
            # Apart from every one chosen before, so their maps differ.
            taken = 0
            for i in np.argsort(dist, kind="stable").tolist():
                if dist[i] > reach or taken == p.max_candidates:
                    break
                k = int(near[i])
                if all(abs(ordinal[k] - ordinal[c]) > 2 * SUBMAP_KEYFRAMES for c, _ in chosen):
                    chosen.append((k, online))
                    taken += 1

        choose(old, np.hypot(poses[old, 0] - poses[n, 0], poses[old, 1] - poses[n, 1]), False)
        online_n = keyframes[n].online_pose
        if online_n is not None:
            near = old[[keyframes[k].online_pose is not None for k in old]]
            if near.size:
                xy = np.array([keyframes[k].online_pose[:2] for k in near])
                choose(near, np.hypot(xy[:, 0] - online_n[0], xy[:, 1] - online_n[1]), True)
        query = None
        found: list[Closure] = []
        for k, online in chosen:
            window = self._window(keyframes, graph, k, n, online)
            if window is None:
                continue
            wide = window[2] > WIDE_WINDOW_M
            if wide:
                if travel[n] - self.last_wide_search_m < WIDE_SEARCH_SPACING_M:
                    continue
                self.last_wide_search_m = travel[n]
            if query is None:
                query = self._query(keyframes, graph, n)
            if query.shape[0] == 0:
                return []   # the last keyframes came without their scans (lost): nothing to search with
            closure = self._try_closure(keyframes, graph, k, n, query, *window)
            if closure is None:
                continue
            if not wide:
                found.append(closure)
                continue
            # A closure from a wide window is the one kind a look-alike place can
            # fake (a twin corridor): it waits for a second one that agrees.
            earlier = self.tentative
            if earlier is not None and travel[n] - travel[earlier[1]] <= CONFIRM_WITHIN_M \
                    and self._agree(graph, earlier, closure):
                found += [earlier, closure]
                self.tentative = None
            else:
                if earlier is not None:
                    self.counts["unconfirmed"] += 1
                    self._observe(earlier[0], earlier[1], earlier[2], earlier[3], "unconfirmed")
                self.tentative = closure
        return found

    def same_side(self, a: int, b: int) -> bool:
        """Whether the keyframes made ``a``-th and ``b``-th (ordinals) are both the saved map's or both the run's."""
        return (a < self.run_start) == (b < self.run_start)

    def _agree(self, graph: PoseGraph, first: Closure, second: Closure) -> bool:
        """Do two closures put the second one's keyframe at the same place (``confirm_*``)?

        Each is ``(old keyframe, new keyframe, measurement, covariance, innovation)``;
        the first's placement is carried to the second's keyframe along the graph.
        """
        poses = graph.poses
        k1, n1, z1 = first[:3]
        k2, n2, z2 = second[:3]
        via_first = compose(compose(poses[k1], z1), relative(poses[n1], poses[n2]))
        via_second = compose(poses[k2], z2)
        diff = relative(via_first, via_second)
        return bool(np.hypot(diff[0], diff[1]) <= CONFIRM_M and abs(diff[2]) <= CONFIRM_RAD)

    def _window(self, keyframes: list[Keyframe], graph: PoseGraph, k: int, n: int, online: bool = False
                ) -> tuple[np.ndarray, np.ndarray, float, float, np.ndarray] | None:
        """Where to search ``n`` in ``k``'s frame, with the graph's prediction and its covariance.

        Returns ``(centre, covariance, half-width m, half-width rad, prediction)``: the centre is
        the graph's prediction, or with ``online`` the online estimator's relative pose. None when
        keyframe ``k`` lies farther from the centre than the window plus ``candidate_radius_m``:
        its map could not overlap the query.
        """
        p = self.params
        predicted = relative(graph.poses[k], graph.poses[n])
        rel_cov = window_covariance(graph, k, n, p.drift_onset_rad)
        sigma_xy = float(np.sqrt(max(np.linalg.eigvalsh(rel_cov[:2, :2])[-1], 0.0)))
        sigma_th = float(np.sqrt(max(rel_cov[2, 2], 0.0)))
        half_m = float(np.clip(WINDOW_SIGMAS * sigma_xy, p.min_window_m, p.max_window_m))
        half_rad = float(np.clip(WINDOW_SIGMAS * sigma_th, MIN_WINDOW_RAD, MAX_WINDOW_RAD))
        centre = relative(keyframes[k].online_pose, keyframes[n].online_pose) if online else predicted
        if np.hypot(centre[0], centre[1]) > half_m + p.candidate_radius_m:
            return None
        return centre, rel_cov, half_m, half_rad, predicted

    def _query(self, keyframes: list[Keyframe], graph: PoseGraph, n: int) -> np.ndarray:
        """The last ``query_keyframes`` keyframes' points in keyframe ``n``'s frame (graph poses), thinned."""
        first = max(0, n - self.params.query_keyframes + 1)
        poses = graph.poses
        parts = [from_frame(keyframes[i].points_xy_m, relative(poses[n], poses[i])) for i in range(first, n + 1)
                 if self.same_side(keyframes[i].ordinal, keyframes[n].ordinal)]
        return thin_points(np.vstack(parts), QUERY_CELL_M)

    def submap(self, keyframes: list[Keyframe], graph: PoseGraph, k: int,
                half_m: float) -> tuple[LikelihoodGrid, ReferenceScan]:
        """The likelihood grid and line reference of keyframe ``k``'s neighbourhood, in its frame.

        The neighbourhood covers the search window (``half_m``, m): at least ``SUBMAP_KEYFRAMES``
        keyframes each side, more where the window is wider than they reach. A map narrower than
        the window favours the placements that fall inside it: in a corridor of alike doors a
        twin a door period along, wholly inside the map, outscores the true place at its edge;
        with the window covered, twins inside it score alike and the ambiguity test sees them. A
        wider map takes only keyframes at least ``min_travel_m`` older than the newest (never the
        query's own). The usual neighbourhood is cached; a wider one (a wide window, searched at
        most once per ``WIDE_SEARCH_SPACING_M``) is not.
        """
        p = self.params
        span = max(SUBMAP_KEYFRAMES, math.ceil(half_m / p.keyframe_trans_m))
        if span == SUBMAP_KEYFRAMES:
            if k in self.submaps:
                self.submaps.move_to_end(k)
                return self.submaps[k][1:]
            self.cache_submap(keyframes, graph, k, min(keyframes[-1].ordinal, keyframes[k].ordinal + span))
            return self.submaps[k][1:]
        old_enough = keyframes[-1].travel_m - p.min_travel_m
        last = max((kf.ordinal for kf in keyframes if kf.ordinal <= keyframes[k].ordinal + span
                    and kf.travel_m <= old_enough), default=keyframes[k].ordinal)
        return self._build_submap(keyframes, graph, k, keyframes[k].ordinal - span, max(last, keyframes[k].ordinal))

    def cache_submap(self, keyframes: list[Keyframe], graph: PoseGraph, k: int, last: int) -> None:
        """Build keyframe ``k``'s submap from its neighbours up to the keyframe made ``last`` (an
        ordinal) and cache it.

        Neighbours are counted in keyframes made, so a retired one (a revisit, without points)
        still takes its place. The cache keeps ``last``: a submap built before all its later
        neighbours existed must be rebuilt the same way when a checkpoint is restored.
        """
        self.submaps[k] = (last, *self._build_submap(keyframes, graph, k, keyframes[k].ordinal - SUBMAP_KEYFRAMES,
                                                     last))
        if len(self.submaps) > CACHED_SUBMAPS:
            self.submaps.popitem(last=False)

    def _build_submap(self, keyframes: list[Keyframe], graph: PoseGraph, k: int, first: int,
                      last: int) -> tuple[LikelihoodGrid, ReferenceScan]:
        """The map of the keyframes made ``first`` to ``last`` (ordinals) in keyframe ``k``'s frame."""
        p = self.params
        poses = graph.poses
        ordinals = np.array([kf.ordinal for kf in keyframes], dtype=np.int64)
        start = int(np.searchsorted(ordinals, first))
        end = int(np.searchsorted(ordinals, last, side="right"))
        pts = np.vstack([from_frame(keyframes[i].points_xy_m, relative(poses[k], poses[i]))
                         for i in range(start, end) if self.same_side(keyframes[i].ordinal, keyframes[k].ordinal)])
        pts = thin_points(pts, KEYFRAME_CELL_M)
        return LikelihoodGrid(pts, p.correlative), ReferenceScan.build(pts)

    def _try_closure(self, keyframes: list[Keyframe], graph: PoseGraph, k: int, n: int, query: np.ndarray,
                     centre: np.ndarray, rel_cov: np.ndarray, half_m: float, half_rad: float,
                     predicted: np.ndarray) -> Closure | None:
        """Search keyframe ``n`` in ``k``'s submap around ``centre`` and verify what it finds.

        Returns ``(k, n, measurement (3,), covariance (3, 3), innovation (3,))`` of a closure
        that passed — the innovation against the graph's ``predicted`` pose — None if none did.
        """
        p = self.params
        count = self.counts
        grid, reference = self.submap(keyframes, graph, k, half_m)
        count["searched"] += 1
        found = search(grid, query, centre, half_m, half_rad, p.min_score)
        if found.score < p.min_score:
            count["low_score"] += 1
            self._observe(k, n, found.pose, None, "low_score")
            return None
        if found.second_score >= p.max_second_ratio * found.score:
            count["ambiguous"] += 1
            self._observe(k, n, found.pose, None, "ambiguous")
            return None
        refined = match(reference, query, found.pose, SCAN_MATCH)
        if not refined.ok:
            count["refine_failed"] += 1
            self._observe(k, n, found.pose, None, "refine_failed")
            return None
        cov = p.match_cov_scale * refined.cov
        # Gated against the graph's own prediction, wherever the search looked: the online
        # estimate only says where to look (in a building of look-alike corridors, a window round
        # it gated on it alone took neighbouring doors for the place). Chi-squared with 3 dof if
        # both covariances were right, so its mean is the closures' NIS (the consistency report).
        innovation = relative(predicted, refined.pose)
        chi2 = float(innovation @ np.linalg.solve(rel_cov + cov, innovation))
        if not chi2 <= p.gate_chi2:
            count["gated"] += 1
            self._observe(k, n, refined.pose, cov, "gated")
            return None
        count, total = self.closure_nis
        self.closure_nis = (count + 1, total + chi2)
        return k, n, refined.pose, cov, innovation
