"""Loop closing behind the EKF: keyframes in a pose graph, closures found by correlative search.

:class:`LoopClosingMapper` is fed every scan with its pose on a *local trajectory* and the
scan's points. It keeps a pose graph (:mod:`lrfslam.algo.pose_graph`) of keyframes
joined by the local trajectory's relative motion, looks for each new keyframe in the maps
of keyframes seen long before, adds what it finds as robust loop edges and
optimises. Per scan it returns the corrected (online) pose; at any time it
gives the optimised trajectory of every scan fed (:meth:`LoopClosingMapper.trajectory`).

Design choices
--------------
* **The local trajectory** is what the mapper service feeds: the chain of the
  motions that moved the EKF (its scan-matched motion, else odometry;
  ``services/mapper.py``), not the EKF's poses: those also hold its landmark
  corrections, as jumps (2.3 m at once on ACES), and a jump is not motion. Older
  recordings' states carry no motion and give the poses. So the new keyframe's
  scan is matched against the last few keyframes with the local motion as the
  guess (standing still if that fails: a jump beyond the matcher's reach), and
  where the two differ by more than ``ekf_jump_*`` the match is the edge. An
  edge made only of scan-matched motions is not checked: it has no jump, and
  the keyframes' match, no better than the slam stage's, would only add noise
  (ACES 0.042 → 0.041 m; short spans 0.040 → 0.039 m). Odometry's motions
  (the paper's filter, a failed match) are checked like jumps.
  The edge covariance grows with the distance and the angle travelled
  (``odom_*``): a model of the drift the local trajectory does not see, not the EKF's
  covariance, which is absolute and shrinks whenever it re-observes a
  landmark (on ACES it claims 3° where the heading is 20° off).
* **Two uncertainties.** The edges' covariance is the local one (0.2° and 1 cm
  per half metre), so loop closures do not bend what the local trajectory got right; but
  the drift over a long loop is systematic (20° of heading round ACES's loops),
  far beyond what a random walk of local errors predicts: a random walk's standard
  deviation grows with the square root of the loop, a heading bias's error with the loop.
  The search window and the gate therefore use the graph's relative covariance grown by
  its own heading variance, ``× (1 + σθ² / drift_onset_rad²)``: unchanged over a short
  loop or right after a closure, growing with the square of the loop past the onset;
  the optimisation does not. It replaced a constant factor (window and gate on 9 × the
  covariance), which was three times too wide for short loops and
  still overconfident for long ones (docs/slam.md, "The mapper").
  (Loose edges, 2.5 cm and 0.9° per half metre, with no model: Intel 0.028 m relation
  error against 0.022 m, ACES 0.051 m either way.)
* **Search window from the graph.** A candidate is an old keyframe (at least
  ``min_travel_m`` back along the trajectory) near the predicted pose. The
  covariance of the new keyframe relative to it (:meth:`PoseGraph.relative_covariance`)
  sets the window, ``window_sigmas`` standard deviations, clamped: after a long
  loop without a closure the window is metres wide, right after one it is small.
  The search is only worth it if the candidate's map can overlap the query
  anywhere in the window (``candidate_radius_m``).
* **Where the online estimate puts it.** The EKF closes loops of its own when it
  re-observes old landmarks; the local trajectory, a chain of motions, never does,
  so after a long loop (MIT Killian's, 2 km) the graph may hold the robot tens of
  metres from where it is, beyond any window. Each scan therefore also brings the
  online estimator's pose (``add_scan(online_pose=...)``, the slam stage's). After
  the candidates near the new keyframe in the graph, up to ``max_candidates`` more
  are taken near it in the online estimate (apart from those: other places), and
  searched around the online relative pose, with the window and every check of the
  others: the gate stays against the graph's own prediction, drift model included.
  The online poses only say where to look; a closure is still the scans' match.
* **Submaps.** The candidate and its ``submap_keyframes`` neighbours on each
  side, placed by their graph poses in the candidate's frame, make the map
  (likelihood grid, :mod:`lrfslam.algo.correlative_match`); the new keyframe
  and its ``query_keyframes − 1`` predecessors, placed by their graph poses
  (the odometry edges), make the query: more wall than one scan, so less ambiguity.
* **Verification**, in order: the best score must reach ``min_score``; the best
  pose separated from it (another corridor, a turned copy) must score below
  ``max_second_ratio`` of it; the point-to-line matcher
  (:func:`lrfslam.algo.scan_match.match`) started there must converge and
  constrain all three directions (a corridor seen end-on cannot say where along
  it the robot is), and gives the covariance; the match must agree with the
  graph's prediction within ``gate_chi2`` (Mahalanobis, the drift-scaled relative and the
  match covariances summed). Accepted closures are Cauchy-robust edges; after
  each optimisation, a closure whose weight fell below ``min_weight`` (the rest
  of the graph disagrees) is removed and the graph optimised again. A closure
  found in a wide window (after a long excursion) waits for the next wide one
  to agree with it (``confirm_*``): in two identical corridors the best peak
  in a wide window can be the twin's, but the twin's peaks of consecutive
  keyframes do not agree with each other (``tests/unit/test_loop_closure.py``).

* **Cost.** A search's cost grows with its window's area, so wide searches
  are spaced (``wide_search_spacing_m``); a closure the graph already agrees
  with is not solved for at once (``optimise_chi2``, ``max_pending_closures``).

Everything is deterministic: same calls, same results.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from lrfslam.algo.checks import require_finite
from lrfslam.algo.correlative_match import CorrelativeParams, LikelihoodGrid, search
from lrfslam.algo.geometry import (
    anchored_poses,
    compose,
    compose_with_covariance,
    from_frame,
    inverse_with_covariance,
    relative,
    thin_points,
)
from lrfslam.algo.pose_graph import PoseGraph, PoseGraphParams
from lrfslam.algo.scan_match import ReferenceScan, ScanMatchParams, match
from lrfslam.errors import ConfigError, InputError

#: Version of :meth:`LoopClosingMapper.snapshot`'s arrays.
SNAPSHOT_FORMAT = 1


@dataclass(frozen=True)
class LoopClosureParams:
    """Parameters of :class:`LoopClosingMapper`.

    Attributes
    ----------
    keyframe_trans_m, keyframe_rot_rad : float
        A scan becomes a keyframe once the local trajectory has moved this far (m) or turned
        this much (rad) since the last keyframe...
    max_scan_step_m : float
        ...or moved this far since the previous scan (m): faster than the robot
        drives, so the local trajectory jumped (an EKF correction); the jump then falls between two keyframes,
        where the scan match replaces it, and not inside a keyframe's scans.
    max_range_m : float
        Points farther than this from the sensor are ignored (m); also drops a
        log's "no return" placeholder ranges (ACES writes 50 m).
    keyframe_cell_m : float
        A keyframe's points are thinned to one per square of this side (m).
    submap_keyframes : int
        The map of a candidate is it and this many keyframes on each side of it.
    query_keyframes : int
        The query is the new keyframe and the ones before it, this many in all.
    query_cell_m : float
        The query is thinned to one point per square of this side (m): the
        search's cost is linear in its points.
    min_travel_m : float
        A candidate must be at least this far back along the trajectory (m).
    candidate_radius_m : float
        ...and its graph position within the search window's half-width plus
        this distance of the predicted one (m): farther, its map would not
        overlap the query.
    max_candidates : int
        Candidates searched per keyframe at most, the nearest first, at least
        ``2 submap_keyframes + 1`` keyframes apart (so their maps differ).
    odom_trans_sigma_m : float
        Floor of the odometry edges' position standard deviation (m)...
    odom_trans_sigma_per_m : float
        ...plus this much per metre travelled (dimensionless)...
    odom_rot_sigma_rad : float
        ...and heading standard deviation floor (rad)...
    odom_rot_sigma_per_m, odom_rot_sigma_per_rad : float
        ...plus this much per metre travelled (rad/m) and per radian turned (dimensionless).
    window_sigmas : float
        Search half-widths in standard deviations of the relative pose.
    drift_onset_rad : float
        The systematic drift model of the search window and the gate: the graph's relative
        covariance times ``1 + σθ² / drift_onset_rad²``, σθ its heading standard deviation (rad).
        Below the onset the drift is the edges' random walk; past it the error grows with
        the loop, not its square root. 0: no model (the covariance as the graph gives it).
    min_window_m, max_window_m : float
        Bounds of the translation half-width (m).
    min_window_rad, max_window_rad : float
        Bounds of the rotation half-width (rad).
    min_score : float
        Mean likelihood (0–1) a closure must reach.
    max_second_ratio : float
        A separated second peak scoring this fraction of the best makes the match ambiguous.
    gate_chi2 : float
        Largest Mahalanobis χ² (3 dof) between the match and the graph's prediction.
    match_cov_scale : float
        Factor on the point-to-line matcher's covariance for a loop edge (it
        ignores that neighbouring beams' errors correlate, and the map's own error).
    min_weight : float
        A closure whose robust weight falls below this after optimisation is removed.
    correlative : CorrelativeParams
    scan_match : ScanMatchParams
        Of the closures' refinement and the odometry edges' matches (its
        ``max_point_range_m`` limits the matched points there).
    graph : PoseGraphParams
    cached_submaps : int
        Submaps kept for re-use (the same old place is searched from consecutive keyframes).
    wide_window_m, wide_search_spacing_m : float
        A search whose translation half-width exceeds ``wide_window_m`` (m) is
        run at most once per ``wide_search_spacing_m`` of travel (m): its cost
        grows with the window's area, and while the robot is lost in a place it
        saw long ago consecutive keyframes would search the same ground.
    confirm_within_m, confirm_m, confirm_rad : float
        A closure found in a wide window is added only once the next one found
        in a wide window, at most ``confirm_within_m`` of travel later (m), puts
        the robot within ``confirm_m`` (m) and ``confirm_rad`` (rad) of where it does.
    optimise_chi2 : float
        A new closure whose own χ² at the current estimate exceeds this is
        solved for at once; smaller ones (the graph agrees already) wait...
    max_pending_closures : int
        ...until this many have gathered (or :meth:`LoopClosingMapper.trajectory`
        is asked for): each solve costs a sparse factorisation of the whole graph.
    odometry_keyframes : int
        The new keyframe's scan is matched against this many last keyframes, merged.
    ekf_jump_m, ekf_jump_rad : float
        An odometry edge is the local motion between the keyframes unless it
        differs from the keyframes' scans matched (point-to-line, the local
        motion as the guess) by more than this (m, rad): then it is the match.
        0 always takes the match, a large value (1e9) always the local motion.
    trim_revisits : bool
        A keyframe that closed a loop (a revisit of a mapped place) is never a
        candidate, and its points are dropped once it is no longer one of the last
        ``max(query_keyframes, odometry_keyframes)``: a place's map is the visit that
        first mapped it, and a robot driving the same rounds adds a node and its edges
        per keyframe (~0.3 KB), not a scan's points (~2.4 KB).
    fold_revisits : bool
        Once an optimisation has kept its closure and it is no longer one of the recent keyframes,
        a revisit keyframe is folded into the keyframe it closed the loop to: its other edges are
        carried there (composed with the closure, whose uncertainty they take on) and merged with
        the edges already between the same keyframes, and it stays only as a leaf on its closure,
        placed by it. A leaf's pose is then its closure's old keyframe's composed with the
        closure, whatever the optimisations after: it is taken out of the graph (*retired*,
        :meth:`LoopClosingMapper.take_retired`). A robot driving the same rounds then keeps a graph
        the size of the place, instead of adding a lap of nodes tied to the first lap's by their
        closures, whose fill grows with the square of the laps (docs/operations.md, "Soak").
        Needs ``trim_revisits``.
    fold_after_keyframes : int
        A revisit is folded once this many keyframes came after it: the optimisations of the
        closures after it still place it (Intel's relations over 30 s, m: 0.027 folding
        after 5, 0.025 after 50, 0.032 after 100, 0.025 after 200, 0.024 unfolded: closures decided
        differently, no trend; docs/slam.md).
    """

    keyframe_trans_m: float = 0.5
    keyframe_rot_rad: float = 0.35
    max_scan_step_m: float = 0.2
    max_range_m: float = 20.0
    keyframe_cell_m: float = 0.05
    submap_keyframes: int = 10
    query_keyframes: int = 5
    query_cell_m: float = 0.1
    min_travel_m: float = 10.0
    candidate_radius_m: float = 3.0
    max_candidates: int = 2
    odom_trans_sigma_m: float = 0.005
    odom_trans_sigma_per_m: float = 0.01
    odom_rot_sigma_rad: float = 0.002
    odom_rot_sigma_per_m: float = 0.006
    odom_rot_sigma_per_rad: float = 0.03
    window_sigmas: float = 3.0
    drift_onset_rad: float = 0.02
    min_window_m: float = 0.5
    max_window_m: float = 12.0
    min_window_rad: float = 0.1
    max_window_rad: float = 0.5
    min_score: float = 0.5
    max_second_ratio: float = 0.9
    gate_chi2: float = 16.0
    match_cov_scale: float = 16.0
    min_weight: float = 0.25
    correlative: CorrelativeParams = field(default_factory=CorrelativeParams)
    scan_match: ScanMatchParams = field(default_factory=ScanMatchParams)
    graph: PoseGraphParams = field(default_factory=PoseGraphParams)
    cached_submaps: int = 8
    wide_window_m: float = 2.0
    wide_search_spacing_m: float = 2.0
    confirm_within_m: float = 10.0
    confirm_m: float = 0.5
    confirm_rad: float = 0.05
    optimise_chi2: float = 9.0
    max_pending_closures: int = 10
    odometry_keyframes: int = 3
    ekf_jump_m: float = 0.05
    ekf_jump_rad: float = 0.02
    trim_revisits: bool = True
    fold_revisits: bool = True
    fold_after_keyframes: int = 50

    def __post_init__(self) -> None:
        positive = ("max_range_m", "keyframe_cell_m", "query_cell_m", "odom_trans_sigma_m", "odom_rot_sigma_rad",
                    "window_sigmas", "min_window_m", "max_window_m", "min_window_rad", "max_window_rad",
                    "gate_chi2", "match_cov_scale", "candidate_radius_m")
        require_finite(self, positive, positive=True, what="loop closure ")
        non_negative = ("keyframe_trans_m", "max_scan_step_m", "keyframe_rot_rad", "min_travel_m", "odom_trans_sigma_per_m",
                        "odom_rot_sigma_per_m", "odom_rot_sigma_per_rad", "drift_onset_rad", "min_score", "max_second_ratio",
                        "min_weight", "optimise_chi2", "ekf_jump_m", "ekf_jump_rad", "wide_window_m",
                        "wide_search_spacing_m", "confirm_within_m", "confirm_m", "confirm_rad")
        require_finite(self, non_negative, positive=False, what="loop closure ")
        if self.min_window_m > self.max_window_m or self.min_window_rad > self.max_window_rad:
            raise ConfigError("loop closure window minima must not exceed the maxima")
        if self.submap_keyframes < 0 or self.query_keyframes < 1 or self.max_candidates < 0 \
                or self.cached_submaps < 1 or self.max_pending_closures < 1 or self.odometry_keyframes < 1:
            raise ConfigError("loop closure needs submap_keyframes >= 0, query_keyframes >= 1, "
                              "max_candidates >= 0 cached_submaps >= 1, max_pending_closures >= 1 and odometry_keyframes >= 1")
        if self.fold_after_keyframes < 0:
            raise ConfigError("loop closure fold_after_keyframes must be >= 0")
        if self.fold_revisits and not self.trim_revisits:
            raise ConfigError("loop closure fold_revisits needs trim_revisits (only a revisit is folded)")


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


#: The points of a keyframe that has none (trimmed), one array for all of them (read-only).
_NO_POINTS = np.zeros((0, 2))
_NO_POINTS.flags.writeable = False


# Slots: a long run keeps thousands of these (~0.2 KB each without a __dict__).
@dataclass(frozen=True, eq=False, slots=True)
class _Keyframe:
    local_pose: np.ndarray  # (3,) its pose on the local trajectory
    points_xy_m: np.ndarray  # (N, 2) its scan, robot frame, thinned
    travel_m: float  # local trajectory length from the first keyframe (m)
    local_edge: bool  # the odometry edge into it is the local motion (no jump)
    scan_index: int  # the scan that made it, in the order fed
    stamp_ns: int  # that scan's stamp
    ordinal: int  # keyframes made before it (its graph node, until keyframes are retired)
    revisit: bool = False  # it closed a loop into an older part of the map
    online_pose: np.ndarray | None = None  # (3,) the online estimator's pose of it, in its own frame


@dataclass(frozen=True, eq=False)
class RetiredKeyframes:
    """R keyframes folded into older ones and taken out of the graph (``fold_revisits``).

    Each one's pose is, ever after, its anchor's (the old keyframe its closure came from)
    composed with ``offset``: place it from the anchor's latest pose.

    Attributes
    ----------
    stamp_ns : ndarray of int, shape (R,)
        The scans that made them, ascending.
    local_pose : ndarray, shape (R, 3)
        Their poses on the local trajectory.
    local_edge : ndarray of bool, shape (R,)
        Whether the odometry edge into each was the local motion (as ``keyframe_local_edges``).
    anchor_stamp_ns : ndarray of int, shape (R,)
        The stamp of each one's anchor keyframe (older than it).
    offset : ndarray, shape (R, 3)
        Its pose in the anchor's frame ``(dx_m, dy_m, dtheta_rad)``.
    """

    stamp_ns: np.ndarray
    local_pose: np.ndarray
    local_edge: np.ndarray
    anchor_stamp_ns: np.ndarray
    offset: np.ndarray

    def __len__(self) -> int:
        return int(self.stamp_ns.size)


@dataclass(frozen=True, eq=False, slots=True)
class _Retired:
    """One retired keyframe, as the mapper remembers it until it is taken (and, keeping scans, always)."""

    ordinal: int
    stamp_ns: int
    local_pose: np.ndarray  # (3,)
    local_edge: bool
    scan_index: int
    anchor_ordinal: int
    anchor_stamp_ns: int
    offset: np.ndarray  # (3,) its pose in the anchor's frame


class LoopClosingMapper:
    """The loop-closing back end (mutable state; see the module notes).

    Parameters
    ----------
    params : LoopClosureParams
    keep_scans : bool
        Keep every scan's place (its keyframe and local pose relative to it, ~60 B a
        scan) for :meth:`trajectory`. A long-running service does not: its published
        local poses and keyframes give the same trajectory
        (``lrfslam.evaluation.map_trajectory.final_poses``).

    Attributes
    ----------
    observer : callable or None
        Called with a :class:`ClosureAttempt` for every closure verified or dropped (an audit;
        None, the default: nothing is kept).
    """

    def __init__(self, params: LoopClosureParams | None = None, keep_scans: bool = True) -> None:
        self.params = params or LoopClosureParams()
        self.graph = PoseGraph(self.params.graph)
        self._keyframes: list[_Keyframe] = []   # the graph's, node i the i-th
        self._made = 0   # keyframes made, retired ones included
        self._retired: list[_Retired] = []   # retired since the last take_retired()
        self._retired_kept: list[_Retired] = []   # every one retired (keep_scans: the trajectory places them)
        self._keep_scans = keep_scans
        self._scans_fed = 0
        self._scan_kf: list[int] = []  # per scan fed (keep_scans): its keyframe's ordinal
        self._scan_rel: list[np.ndarray] = []  # per scan: local pose relative to that keyframe's
        self._stamps: list[int] = []
        self._loop_edges: list[int] = []  # graph edge ids of the closures in the graph
        # Of the closures that passed verification: how many, and their NIS summed (a running
        # total: a long run's closures are not kept).
        self._closure_nis = (0, 0.0)
        # keyframe -> (last neighbour in it, grid, line reference), least recently used first
        self._submaps: OrderedDict[int, tuple[int, LikelihoodGrid, ReferenceScan]] = OrderedDict()
        self._counts = dict.fromkeys(ClosureStats.__dataclass_fields__, 0)
        self._last_local_pose = np.zeros(3)  # the previous scan's local pose
        # The reference steps since the last keyframe composed (3,); None once one was missing.
        self._reference: np.ndarray | None = np.zeros(3)
        self._pending = 0  # closures added since the last optimisation
        self._last_wide_search_m = -np.inf  # travel at the last wide search
        self._tentative = None  # a closure from a wide window awaiting confirmation
        self._pending_strong = False  # one of them disagrees strongly with the estimate they were added to
        self._fold_queue: list[int] = []  # revisit keyframes not folded yet, oldest first
        self.observer: Callable[[ClosureAttempt], None] | None = None

    @property
    def stats(self) -> ClosureStats:
        return ClosureStats(**self._counts)

    @property
    def keyframe_count(self) -> int:
        """Keyframes made so far, retired ones included."""
        return self._made

    @property
    def graph_keyframes(self) -> int:
        """Keyframes in the graph (made, less the retired)."""
        return len(self._keyframes)

    def add_scan(self, stamp_ns: int, local_pose, points_xy_m, reference_step=None, online_pose=None) -> np.ndarray:
        """Take one scan; returns its corrected pose (3,), as known now.

        Parameters
        ----------
        stamp_ns : int
            The scan's stamp (ns): the keyframes' and :meth:`trajectory`'s.
        local_pose : array_like, shape (3,)
            The scan's pose on the local trajectory, ``(x_m, y_m, theta_rad)``.
        points_xy_m : array_like, shape (N, 2)
            The scan's points in the robot frame (m); non-finite rows are ignored.
        reference_step : array_like, shape (3,), optional
            The motion from the previous scan to this one found by scan matching
            (dx m, dy m, dtheta rad), if it was: an odometry edge whose every step
            has one is checked against their chain (``ekf_jump_*``), the others
            against the keyframes' scans matched.
        online_pose : array_like, shape (3,), optional
            The online estimator's pose of this scan (the EKF's, in its own map frame): the
            closure search also looks where it puts the robot (module notes).
        """
        pose = np.asarray(local_pose, dtype=float)
        if pose.shape != (3,) or not np.all(np.isfinite(pose)):
            raise InputError("local_pose must be (3,) and finite")
        p = self.params
        stamp_ns = int(stamp_ns)
        online = None if online_pose is None else np.asarray(online_pose, dtype=float)
        if online is not None and (online.shape != (3,) or not np.all(np.isfinite(online))):
            raise InputError("online_pose must be (3,) and finite")
        if not self._keyframes:
            self._add_keyframe(pose, points_xy_m, None, stamp_ns, online)
        else:
            if self._reference is not None and reference_step is not None:
                self._reference = compose(self._reference, np.asarray(reference_step, dtype=float))
            else:
                self._reference = None
            last = self._keyframes[-1]
            moved = relative(last.local_pose, pose)
            jumped = np.hypot(*(pose[:2] - self._last_local_pose[:2])) > p.max_scan_step_m
            if jumped or np.hypot(moved[0], moved[1]) >= p.keyframe_trans_m or abs(moved[2]) >= p.keyframe_rot_rad:
                self._add_keyframe(pose, points_xy_m, moved, stamp_ns, online)
                self._reference = np.zeros(3)
                self._close_loops()
        self._last_local_pose = pose
        k = len(self._keyframes) - 1
        rel = relative(self._keyframes[k].local_pose, pose)
        self._scans_fed += 1
        if self._keep_scans:
            self._scan_kf.append(self._keyframes[k].ordinal)
            self._scan_rel.append(rel)
            self._stamps.append(stamp_ns)
        return compose(self.graph.poses[k], rel)

    def solve(self) -> None:
        """Optimise the graph for every closure not solved for yet (the keyframe poses are then final)."""
        if self._pending:
            self._optimise()

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """Stamps (ns, (T,)) and poses ((T, 3)) of every scan fed, from the graph with every closure solved for.

        Raises
        ------
        ConfigError
            The mapper was made with ``keep_scans=False``.
        """
        if not self._keep_scans:
            raise ConfigError("this mapper keeps no per-scan history (keep_scans=False)")
        self.solve()
        live, gone = self._keyframes, self._retired_kept
        ordinals = np.array([k.ordinal for k in live] + [r.ordinal for r in gone], dtype=np.int64)
        order = np.argsort(ordinals)   # (every ordinal below self._made is one of the two)
        live_ordinals = ordinals[: len(live)]
        kf_poses = np.vstack((self.graph.poses, anchored_poses(
            live_ordinals, self.graph.poses, ordinals[len(live):],
            np.array([r.anchor_ordinal for r in gone], dtype=np.int64),
            np.array([r.offset for r in gone], dtype=float).reshape(-1, 3))))[order]
        kf_local = np.vstack((self.keyframe_local_poses(),
                              np.array([r.local_pose for r in gone], dtype=float).reshape(-1, 3)))[order]
        kf_scan = np.concatenate((self.keyframe_scans(), np.array([r.scan_index for r in gone], dtype=np.int64)))
        kf_edge = np.concatenate((self.keyframe_local_edges(), np.array([r.local_edge for r in gone], dtype=bool)))
        poses = place_scans(np.array(self._scan_kf, dtype=np.int64), np.array(self._scan_rel, dtype=float),
                            kf_poses, kf_local, kf_scan[order], kf_edge[order])
        return np.array(self._stamps, dtype=np.int64), poses

    @property
    def closure_nis(self) -> tuple[int, float]:
        """How many closures passed verification, and their NIS (3 dof, against the graph's
        prediction) summed: the mean is the consistency report's figure."""
        return self._closure_nis

    def keyframe_poses(self) -> np.ndarray:
        """The graph's K keyframes' poses as they stand (optimised at the last optimisation), (K, 3).

        Every keyframe accessor gives the keyframes in the graph, oldest first; the retired
        ones are given once, by :meth:`take_retired`.
        """
        return self.graph.poses.copy()

    def keyframe_local_poses(self) -> np.ndarray:
        """Each keyframe's pose on the local trajectory, (K, 3)."""
        return np.array([k.local_pose for k in self._keyframes], dtype=float).reshape(-1, 3)

    def keyframe_local_edges(self) -> np.ndarray:
        """Whether the odometry edge into each keyframe is the local motion (no jump), (K,) bool."""
        return np.array([k.local_edge for k in self._keyframes], dtype=bool)

    def keyframe_scans(self) -> np.ndarray:
        """Index (in the order fed) of the scan that made each keyframe, (K,)."""
        return np.array([k.scan_index for k in self._keyframes], dtype=np.int64)

    def keyframe_stamped_local_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """Stamps (ns, (K,)) of the scans that made the keyframes, and their local poses (K, 3)."""
        return np.array([k.stamp_ns for k in self._keyframes], dtype=np.int64), self.keyframe_local_poses()

    def take_retired(self) -> RetiredKeyframes:
        """The keyframes retired from the graph since the last call (each given once), oldest first."""
        gone, self._retired = self._retired, []
        return RetiredKeyframes(np.array([r.stamp_ns for r in gone], dtype=np.int64),
                                np.array([r.local_pose for r in gone], dtype=float).reshape(-1, 3),
                                np.array([r.local_edge for r in gone], dtype=bool),
                                np.array([r.anchor_stamp_ns for r in gone], dtype=np.int64),
                                np.array([r.offset for r in gone], dtype=float).reshape(-1, 3))

    def closures(self) -> list[tuple[int, int, np.ndarray]]:
        """The closures in the graph: (old keyframe, new keyframe, pose of the new in the old's frame (3,))."""
        return [(self.graph.edge_nodes(e)[0], self.graph.edge_nodes(e)[1], self.graph.edge_measurement(e))
                for e in self._loop_edges]

    # -- checkpoint -----------------------------------------------------------------------------

    def snapshot(self) -> dict[str, np.ndarray]:
        """Everything needed to continue exactly where this mapper stands, as named arrays (copies).

        The graph's arrays (:meth:`PoseGraph.snapshot`); the keyframes' (``keyframe_*``, their
        points concatenated with ``keyframe_point_counts``); the per-scan history if kept; the
        closure search's state. Feeding the restored mapper the same scans gives the same results.
        """
        kfs = self._keyframes
        tentative = self._tentative
        return {
            "mapper_format": np.int64(SNAPSHOT_FORMAT),
            **self.graph.snapshot(),
            "keyframe_local_pose": self.keyframe_local_poses(),
            "keyframe_points": np.vstack([k.points_xy_m for k in kfs]) if kfs else np.zeros((0, 2)),
            "keyframe_point_counts": np.array([k.points_xy_m.shape[0] for k in kfs], dtype=np.int64),
            "keyframe_travel_m": np.array([k.travel_m for k in kfs], dtype=float),
            "keyframe_local_edge": self.keyframe_local_edges(),
            "keyframe_scan_index": self.keyframe_scans(),
            "keyframe_stamp_ns": np.array([k.stamp_ns for k in kfs], dtype=np.int64),
            "keyframe_revisit": np.array([k.revisit for k in kfs], dtype=bool),
            "keyframe_ordinal": np.array([k.ordinal for k in kfs], dtype=np.int64),
            # NaN rows: keyframes made without an online pose.
            "keyframe_online_pose": np.array([np.full(3, np.nan) if k.online_pose is None else k.online_pose
                                              for k in kfs], dtype=float).reshape(-1, 3),
            "keyframes_made": np.int64(self._made),
            **_retired_arrays("retired", self._retired),
            **_retired_arrays("retired_kept", self._retired_kept),
            "fold_queue": np.array(self._fold_queue, dtype=np.int64),
            "scans_fed": np.int64(self._scans_fed),
            "keep_scans": np.bool_(self._keep_scans),
            "scan_keyframe": np.array(self._scan_kf, dtype=np.int64),
            "scan_relative_pose": np.array(self._scan_rel, dtype=float).reshape(-1, 3),
            "scan_stamp_ns": np.array(self._stamps, dtype=np.int64),
            "loop_edges": np.array(self._loop_edges, dtype=np.int64),
            "closure_nis_total": np.array([float(self._closure_nis[0]), self._closure_nis[1]]),
            "stats": np.array([self._counts[name] for name in ClosureStats.__dataclass_fields__], dtype=np.int64),
            "last_local_pose": self._last_local_pose.copy(),
            "reference_step": np.full(3, np.nan) if self._reference is None else self._reference.copy(),
            "pending_closures": np.int64(self._pending),
            "pending_strong": np.bool_(self._pending_strong),
            "last_wide_search_m": np.float64(self._last_wide_search_m),
            # keyframe pairs (2,), measurement (3,), covariance (9,), innovation (3,); empty if none
            "tentative_closure": np.zeros(0) if tentative is None else np.concatenate(
                (np.array(tentative[:2], dtype=float), tentative[2], np.ravel(tentative[3]), tentative[4])),
            "cached_submaps": np.array([(k, entry[0]) for k, entry in self._submaps.items()],
                                       dtype=np.int64).reshape(-1, 2),
        }

    @classmethod
    def restore(cls, params: LoopClosureParams | None, arrays) -> LoopClosingMapper:
        """The mapper :meth:`snapshot` gave ``arrays`` of (e.g. loaded from an ``.npz``).

        Raises
        ------
        InputError
            If the arrays are not a snapshot of this format or disagree with each other.
        """
        try:
            fmt = int(arrays["mapper_format"])
            if fmt != SNAPSHOT_FORMAT:
                raise InputError(f"mapper snapshot format {fmt} is not {SNAPSHOT_FORMAT}")
            mapper = cls(params, keep_scans=bool(arrays["keep_scans"]))
            mapper.graph = PoseGraph.restore(mapper.params.graph, arrays)
            counts = np.array(arrays["keyframe_point_counts"], dtype=np.int64)
            points = np.array(arrays["keyframe_points"], dtype=float).reshape(-1, 2)
            local = np.array(arrays["keyframe_local_pose"], dtype=float).reshape(-1, 3)
            travel = np.array(arrays["keyframe_travel_m"], dtype=float)
            edge = np.array(arrays["keyframe_local_edge"], dtype=bool)
            scan_index = np.array(arrays["keyframe_scan_index"], dtype=np.int64)
            stamps = np.array(arrays["keyframe_stamp_ns"], dtype=np.int64)
            revisit = np.array(arrays["keyframe_revisit"], dtype=bool)
            k = len(mapper.graph)
            # A snapshot from before keyframes were retired has every keyframe made in its graph.
            ordinal = np.array(arrays["keyframe_ordinal"], dtype=np.int64) if "keyframe_ordinal" in arrays \
                else np.arange(k, dtype=np.int64)
            mapper._made = int(arrays["keyframes_made"]) if "keyframes_made" in arrays else k
            # A snapshot from before the online poses has none.
            online = np.array(arrays["keyframe_online_pose"], dtype=float).reshape(-1, 3) \
                if "keyframe_online_pose" in arrays else np.full((k, 3), np.nan)
            mapper._retired = _retired_from("retired", arrays)
            mapper._retired_kept = _retired_from("retired_kept", arrays)
            # A snapshot from before revisits were folded has none queued.
            queue = np.array(arrays["fold_queue"], dtype=np.int64) if "fold_queue" in arrays \
                else np.zeros(0, dtype=np.int64)
            if not (counts.shape == travel.shape == edge.shape == scan_index.shape == stamps.shape == revisit.shape
                    == ordinal.shape == (k,) and np.all((queue >= 0) & (queue < k))
                    and np.all(np.diff(ordinal) > 0) and (k == 0 or 0 <= ordinal[0] and ordinal[-1] < mapper._made)
                    and local.shape == online.shape == (k, 3) and np.all(counts >= 0)
                    and counts.sum() == points.shape[0]):
                raise InputError("mapper snapshot: keyframe arrays disagree with the graph")
            for i, pts in enumerate(np.split(points, np.cumsum(counts)[:-1]) if k else []):
                mapper._keyframes.append(_Keyframe(local[i], pts, float(travel[i]), bool(edge[i]),
                                                   int(scan_index[i]), int(stamps[i]), int(ordinal[i]),
                                                   bool(revisit[i]),
                                                   None if np.isnan(online[i]).any() else online[i]))
            mapper._fold_queue = queue.tolist()
            mapper._scans_fed = int(arrays["scans_fed"])
            if mapper._keep_scans:
                mapper._scan_kf = np.array(arrays["scan_keyframe"], dtype=np.int64).tolist()
                mapper._scan_rel = list(np.array(arrays["scan_relative_pose"], dtype=float).reshape(-1, 3))
                mapper._stamps = np.array(arrays["scan_stamp_ns"], dtype=np.int64).tolist()
            mapper._loop_edges = np.array(arrays["loop_edges"], dtype=np.int64).tolist()
            if "closure_nis_total" in arrays:
                count, total = np.array(arrays["closure_nis_total"], dtype=float).reshape(2)
                mapper._closure_nis = (int(count), float(total))
            else:   # a snapshot from before the running total holds every closure's
                nis = np.array(arrays["closure_nis"], dtype=float)
                mapper._closure_nis = (nis.size, float(nis.sum()))
            stats = np.array(arrays["stats"], dtype=np.int64)
            if stats.shape != (len(ClosureStats.__dataclass_fields__),):
                raise InputError("mapper snapshot: wrong number of statistics")
            mapper._counts = dict(zip(ClosureStats.__dataclass_fields__, stats.tolist(), strict=True))
            mapper._last_local_pose = np.array(arrays["last_local_pose"], dtype=float).reshape(3)
            reference = np.array(arrays["reference_step"], dtype=float).reshape(3)
            mapper._reference = None if np.any(np.isnan(reference)) else reference
            mapper._pending = int(arrays["pending_closures"])
            mapper._pending_strong = bool(arrays["pending_strong"])
            mapper._last_wide_search_m = float(arrays["last_wide_search_m"])
            tentative = np.array(arrays["tentative_closure"], dtype=float)
            if tentative.size:
                mapper._tentative = (int(tentative[0]), int(tentative[1]), tentative[2:5],
                                     tentative[5:14].reshape(3, 3), tentative[14:17])
            for kf, last in np.array(arrays["cached_submaps"], dtype=np.int64).reshape(-1, 2).tolist():
                mapper._cache_submap(kf, last)
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise InputError(f"mapper snapshot: {exc!r}") from None
        edges, keyframes = len(arrays["graph_edge_alive"]), len(mapper._keyframes)
        if any(not 0 <= e < edges for e in mapper._loop_edges) or (
                mapper._tentative is not None and not all(0 <= n < keyframes for n in mapper._tentative[:2])):
            raise InputError("mapper snapshot: a closure names an edge or a keyframe that is not there")
        return mapper

    # -- keyframes and odometry edges -----------------------------------------------------------

    def _add_keyframe(self, local_pose: np.ndarray, points_xy_m, moved: np.ndarray | None, stamp_ns: int,
                      online_pose: np.ndarray | None) -> None:
        p = self.params
        pts = np.asarray(points_xy_m, dtype=float).reshape(-1, 2)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        pts = pts[np.hypot(pts[:, 0], pts[:, 1]) < p.max_range_m]
        pts = thin_points(pts, p.keyframe_cell_m)
        self._made += 1
        if moved is None:
            self.graph.add_node(local_pose)
            self._keyframes.append(_Keyframe(local_pose.copy(), pts, 0.0, True, self._scans_fed, stamp_ns,
                                             self._made - 1, online_pose=online_pose))
            return
        prev = len(self._keyframes) - 1
        dist = float(np.hypot(moved[0], moved[1]))
        cov = self._odometry_cov(dist, abs(moved[2]))
        if self._reference is None:
            step = self._checked_motion(prev, pts, moved, cov)
        else:
            step = self._step_or_jump(moved, self._reference)
        node = self.graph.add_node(compose(self.graph.poses[prev], step))
        self.graph.add_edge(prev, node, step, np.linalg.inv(cov))
        self._keyframes.append(_Keyframe(local_pose.copy(), pts, self._keyframes[-1].travel_m + dist,
                                         step is moved, self._scans_fed, stamp_ns, self._made - 1,
                                         online_pose=online_pose))
        self._trim(len(self._keyframes) - 1 - self._recent_keyframes)

    @property
    def _recent_keyframes(self) -> int:
        """The last this many keyframes keep their points whatever they are (the query and the edge checks use them)."""
        return max(self.params.query_keyframes, self.params.odometry_keyframes)

    def _mark_revisit(self, k: int) -> None:
        """Keyframe ``k`` closed a loop: with ``trim_revisits``, no candidate, and no points once not recent."""
        if self.params.trim_revisits and not self._keyframes[k].revisit:
            self._keyframes[k] = replace(self._keyframes[k], revisit=True)
            self._trim(k)
            if self.params.fold_revisits:
                self._fold_queue.append(k)

    def _trim(self, k: int) -> None:
        """Drop keyframe ``k``'s points if it is a revisit and no longer one of the recent keyframes."""
        if 0 <= k < len(self._keyframes) - self._recent_keyframes and self._keyframes[k].revisit \
                and self._keyframes[k].points_xy_m.shape[0]:
            self._keyframes[k] = replace(self._keyframes[k], points_xy_m=_NO_POINTS)

    def _step_or_jump(self, moved: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """``moved`` (3,), or ``reference`` (3,) where the two differ by more than ``ekf_jump_*``."""
        jump = relative(moved, reference)
        if np.hypot(jump[0], jump[1]) > self.params.ekf_jump_m or abs(jump[2]) > self.params.ekf_jump_rad:
            self._counts["ekf_jumps"] += 1
            return reference
        return moved

    def _checked_motion(self, prev: int, pts: np.ndarray, moved: np.ndarray, cov: np.ndarray) -> np.ndarray:
        """``moved`` (3,), the local motion from keyframe ``prev`` to the new one, or the scans' match where it jumped."""
        p = self.params
        # The EKF's poses hold its landmark corrections as jumps (2.3 m at once
        # on ACES), which are not motion. The keyframes' scans, matched with
        # the local motion as the guess, say what the motion was:
        # where the two disagree by more than ``ekf_jump_*`` the match is taken.
        recent = self._recent_map(prev)
        found = match(recent, pts, moved, p.scan_match, cov)
        if not found.ok:
            # A jump beyond the matcher's reach (its largest correction): the keyframes
            # are at most ``keyframe_*`` apart, so standing still is a guess within it.
            found = match(recent, pts, np.zeros(3), p.scan_match, cov)
        return self._step_or_jump(moved, found.pose) if found.ok else moved

    def _recent_map(self, last: int) -> ReferenceScan:
        """The ``odometry_keyframes`` keyframes up to ``last`` merged in ``last``'s frame by their graph poses."""
        p = self.params
        poses = self.graph.poses
        first = max(0, last - p.odometry_keyframes + 1)
        pts = np.vstack([from_frame(self._keyframes[i].points_xy_m, relative(poses[last], poses[i]))
                         for i in range(first, last + 1)])
        return ReferenceScan.build(thin_points(pts, p.keyframe_cell_m), p.scan_match)

    def _odometry_cov(self, dist_m: float, turn_rad: float) -> np.ndarray:
        """Covariance (3, 3) of an odometry edge over ``dist_m`` metres and ``turn_rad`` radians."""
        p = self.params
        var_xy = p.odom_trans_sigma_m**2 + (p.odom_trans_sigma_per_m * dist_m) ** 2
        var_th = p.odom_rot_sigma_rad**2 + (p.odom_rot_sigma_per_m * dist_m) ** 2 \
            + (p.odom_rot_sigma_per_rad * turn_rad) ** 2
        return np.diag([var_xy, var_xy, var_th])

    # -- closures -------------------------------------------------------------------------------

    def _close_loops(self) -> None:
        p = self.params
        n = len(self._keyframes) - 1
        if p.max_candidates == 0:
            return
        poses = self.graph.poses
        travel = np.array([kf.travel_m for kf in self._keyframes])
        # A candidate has points of its own (its scan may have been lost; its neighbours' may
        # have been trimmed), so its submap is never empty.
        # (A revisit is marked only with ``trim_revisits``.)
        older = (travel <= travel[n] - p.min_travel_m) & np.array([kf.points_xy_m.shape[0] > 0 and not kf.revisit
                                                                   for kf in self._keyframes])
        old = np.flatnonzero(older)
        if old.size == 0:
            return
        reach = p.max_window_m + p.candidate_radius_m
        ordinal = [kf.ordinal for kf in self._keyframes]
        chosen: list[tuple[int, bool]] = []   # (keyframe, found by the online estimate)

        def choose(near: np.ndarray, dist: np.ndarray, online: bool) -> None:
            # Apart from every one chosen before, so their maps differ.
            taken = 0
            for i in np.argsort(dist, kind="stable").tolist():
                if dist[i] > reach or taken == p.max_candidates:
                    break
                k = int(near[i])
                if all(abs(ordinal[k] - ordinal[c]) > 2 * p.submap_keyframes for c, _ in chosen):
                    chosen.append((k, online))
                    taken += 1

        choose(old, np.hypot(poses[old, 0] - poses[n, 0], poses[old, 1] - poses[n, 1]), False)
        online_n = self._keyframes[n].online_pose
        if online_n is not None:
            near = old[[self._keyframes[k].online_pose is not None for k in old]]
            if near.size:
                xy = np.array([self._keyframes[k].online_pose[:2] for k in near])
                choose(near, np.hypot(xy[:, 0] - online_n[0], xy[:, 1] - online_n[1]), True)
        query = None
        found: list[tuple[int, int, np.ndarray, np.ndarray, np.ndarray]] = []
        for k, online in chosen:
            window = self._window(k, n, online)
            if window is None:
                continue
            wide = window[2] > p.wide_window_m
            if wide:
                if travel[n] - self._last_wide_search_m < p.wide_search_spacing_m:
                    continue
                self._last_wide_search_m = travel[n]
            if query is None:
                query = self._query(n)
            if query.shape[0] == 0:
                return   # the last keyframes came without their scans (lost): nothing to search with
            closure = self._try_closure(k, n, query, *window)
            if closure is None:
                continue
            if not wide:
                found.append(closure)
                continue
            # A closure from a wide window is the one kind a look-alike place can
            # fake (a twin corridor): it waits for a second one that agrees.
            earlier = self._tentative
            if earlier is not None and travel[n] - travel[earlier[1]] <= p.confirm_within_m \
                    and self._agree(earlier, closure):
                found += [earlier, closure]
                self._tentative = None
            else:
                if earlier is not None:
                    self._counts["unconfirmed"] += 1
                    self._observe(earlier[0], earlier[1], earlier[2], earlier[3], "unconfirmed")
                self._tentative = closure
        urgent = False
        for k, n_, z, cov, innovation in found:
            self._mark_revisit(n_)
            info = np.linalg.inv(cov)
            self._loop_edges.append(self.graph.add_edge(k, n_, z, info, robust=True))
            self._counts["accepted"] += 1
            self._observe(k, n_, z, cov, "accepted")
            edge_chi2 = float(innovation @ info @ innovation)
            self._pending += 1
            urgent |= edge_chi2 > p.optimise_chi2
            self._pending_strong |= edge_chi2 > p.graph.cauchy_scale**2
        if urgent or self._pending >= p.max_pending_closures:
            self._optimise()

    def _observe(self, k: int, n: int, pose: np.ndarray, cov: np.ndarray | None, verdict: str) -> None:
        """Tell the :attr:`observer` what became of a closure between keyframes ``k`` and ``n``."""
        if self.observer is not None:
            self.observer(ClosureAttempt(self._keyframes[k].stamp_ns, self._keyframes[n].stamp_ns,
                                         np.array(pose, float), None if cov is None else np.array(cov, float), verdict))

    def _agree(self, first, second) -> bool:
        """Do two closures put the second one's keyframe at the same place (``confirm_*``)?

        Each is ``(old keyframe, new keyframe, measurement, covariance, innovation)``;
        the first's placement is carried to the second's keyframe along the graph.
        """
        p = self.params
        poses = self.graph.poses
        k1, n1, z1 = first[:3]
        k2, n2, z2 = second[:3]
        via_first = compose(compose(poses[k1], z1), relative(poses[n1], poses[n2]))
        via_second = compose(poses[k2], z2)
        diff = relative(via_first, via_second)
        return bool(np.hypot(diff[0], diff[1]) <= p.confirm_m and abs(diff[2]) <= p.confirm_rad)

    def _window(self, k: int, n: int, online: bool = False
                ) -> tuple[np.ndarray, np.ndarray, float, float, np.ndarray] | None:
        """Where to search ``n`` in ``k``'s frame, with the graph's prediction and its covariance.

        Returns ``(centre, covariance, half-width m, half-width rad, prediction)``: the centre is
        the graph's prediction, or with ``online`` the online estimator's relative pose. None when
        keyframe ``k`` lies farther from the centre than the window plus ``candidate_radius_m``:
        its map could not overlap the query.
        """
        p = self.params
        predicted = relative(self.graph.poses[k], self.graph.poses[n])
        rel_cov = self.graph.relative_covariance(k, n)
        if p.drift_onset_rad > 0.0:
            # Systematic drift: a random walk's standard deviation grows with the square root of
            # the loop, a heading bias's error with the loop itself, so past the onset the
            # graph's relative covariance grows with its own heading variance.
            rel_cov = rel_cov * (1.0 + rel_cov[2, 2] / p.drift_onset_rad**2)
        sigma_xy = float(np.sqrt(max(np.linalg.eigvalsh(rel_cov[:2, :2])[-1], 0.0)))
        sigma_th = float(np.sqrt(max(rel_cov[2, 2], 0.0)))
        half_m = float(np.clip(p.window_sigmas * sigma_xy, p.min_window_m, p.max_window_m))
        half_rad = float(np.clip(p.window_sigmas * sigma_th, p.min_window_rad, p.max_window_rad))
        centre = relative(self._keyframes[k].online_pose, self._keyframes[n].online_pose) if online else predicted
        if np.hypot(centre[0], centre[1]) > half_m + p.candidate_radius_m:
            return None
        return centre, rel_cov, half_m, half_rad, predicted

    def _query(self, n: int) -> np.ndarray:
        """The last ``query_keyframes`` keyframes' points in keyframe ``n``'s frame (graph poses), thinned."""
        first = max(0, n - self.params.query_keyframes + 1)
        poses = self.graph.poses
        parts = [from_frame(self._keyframes[i].points_xy_m, relative(poses[n], poses[i])) for i in range(first, n + 1)]
        return thin_points(np.vstack(parts), self.params.query_cell_m)

    def _submap(self, k: int) -> tuple[LikelihoodGrid, ReferenceScan]:
        """The likelihood grid and line reference of keyframe ``k``'s neighbourhood, in its frame (cached)."""
        if k in self._submaps:
            self._submaps.move_to_end(k)
            return self._submaps[k][1:]
        self._cache_submap(k, min(self._keyframes[-1].ordinal, self._keyframes[k].ordinal + self.params.submap_keyframes))
        return self._submaps[k][1:]

    def _cache_submap(self, k: int, last: int) -> None:
        """Build keyframe ``k``'s submap from its neighbours up to the keyframe made ``last`` (an
        ordinal) and cache it.

        Neighbours are counted in keyframes made, so a retired one (a revisit, without points)
        still takes its place. The cache keeps ``last``: a submap built before all its later
        neighbours existed must be rebuilt the same way when a checkpoint is restored.
        """
        p = self.params
        poses = self.graph.poses
        ordinals = np.array([kf.ordinal for kf in self._keyframes], dtype=np.int64)
        first = int(np.searchsorted(ordinals, ordinals[k] - p.submap_keyframes))
        end = int(np.searchsorted(ordinals, last, side="right"))
        pts = np.vstack([from_frame(self._keyframes[i].points_xy_m, relative(poses[k], poses[i]))
                         for i in range(first, end)])
        pts = thin_points(pts, p.keyframe_cell_m)
        self._submaps[k] = (last, LikelihoodGrid(pts, p.correlative), ReferenceScan.build(pts, p.scan_match))
        if len(self._submaps) > p.cached_submaps:
            self._submaps.popitem(last=False)

    def _try_closure(self, k: int, n: int, query: np.ndarray, centre: np.ndarray, rel_cov: np.ndarray,
                     half_m: float, half_rad: float, predicted: np.ndarray):
        """Search keyframe ``n`` in ``k``'s submap around ``centre`` and verify what it finds.

        Returns ``(k, n, measurement (3,), covariance (3, 3), innovation (3,))`` of a closure
        that passed — the innovation against the graph's ``predicted`` pose — None if none did.
        """
        p = self.params
        count = self._counts
        grid, reference = self._submap(k)
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
        refined = match(reference, query, found.pose, p.scan_match)
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
        count, total = self._closure_nis
        self._closure_nis = (count + 1, total + chi2)
        return k, n, refined.pose, cov, innovation

    def _optimise(self) -> None:
        """Optimise; drop closures the graph disagrees with (the worst first) and optimise again."""
        p = self.params
        # Every closure passed the gate against the graph. One that disagrees
        # strongly with the estimate would start with a tiny robust weight: solve
        # with all of them first, then let the kernel find the ones the others disagree with.
        if self._pending_strong:
            self.graph.optimize(robust=False)
        self._pending, self._pending_strong = 0, False
        while True:
            self.graph.optimize()
            self._counts["optimisations"] += 1
            self._submaps.clear()  # neighbours moved: the submaps are rebuilt from the new poses
            if not self._loop_edges:
                break
            weights = self.graph.loop_weights()[self._loop_edges]
            worst = int(np.argmin(weights))
            if weights[worst] >= p.min_weight:
                break
            edge = self._loop_edges.pop(worst)
            if self.observer is not None:
                i, j = self.graph.edge_nodes(edge)
                self._observe(i, j, self.graph.edge_measurement(edge), None, "removed")
            self.graph.remove_edge(edge)
            self._counts["removed"] += 1
        self._fold_settled()

    # -- folding revisits -----------------------------------------------------------------------

    def _fold_settled(self) -> None:
        """Fold every queued revisit keyframe that is no longer recent (``fold_revisits``).

        Run right after an optimisation: every closure in the graph has been through one and
        kept its weight, and the poses are the optimum the folded edges are linearised at.
        """
        last = len(self._keyframes) - max(self._recent_keyframes, self.params.fold_after_keyframes)
        if not self._fold_queue or self._fold_queue[0] >= last:
            return
        weights = self.graph.loop_weights()
        loops = {e: self.graph.edge_nodes(e) for e in self._loop_edges}
        folded = []
        while self._fold_queue and self._fold_queue[0] < last:
            n = self._fold_queue.pop(0)
            into = [e for e, (_, j) in loops.items() if j == n]
            if into:   # (its closure may have been removed: then it stays a node like any other)
                anchor = max(into, key=lambda e: weights[e])
                self._fold(n, anchor, weights)
                folded.append((n, anchor))
        if folded:
            self._retire(folded)

    def _retire(self, leaves: list[tuple[int, int]]) -> None:
        """Take the folded keyframes ``(node, its closure's edge)`` out of the graph, remembering
        each one's place on its anchor (:class:`RetiredKeyframes`), and renumber what refers to
        the graph. A leaf sits exactly on its closure at every optimum, so this changes no pose."""
        graph, kfs = self.graph, self._keyframes
        for n, edge in leaves:
            k = graph.edge_nodes(edge)[0]
            kf = kfs[n]
            retired = _Retired(kf.ordinal, kf.stamp_ns, kf.local_pose, kf.local_edge, kf.scan_index,
                               kfs[k].ordinal, kfs[k].stamp_ns, graph.edge_measurement(edge))
            self._retired.append(retired)
            if self._keep_scans:
                self._retired_kept.append(retired)
        node_map, edge_map = graph.remove_nodes([n for n, _ in leaves])
        self._keyframes = [kf for i, kf in enumerate(kfs) if node_map[i] >= 0]
        self._loop_edges = [int(edge_map[e]) for e in self._loop_edges if edge_map[e] >= 0]
        self._fold_queue = [int(node_map[n]) for n in self._fold_queue]
        if self._tentative is not None:
            k, n, *rest = self._tentative
            kept = node_map[k] >= 0 and node_map[n] >= 0
            self._tentative = (int(node_map[k]), int(node_map[n]), *rest) if kept else None
        self._submaps.clear()

    def _fold(self, n: int, anchor_edge: int, weights: np.ndarray) -> None:
        """Fold keyframe ``n`` into the keyframe its closure ``anchor_edge`` comes from.

        ``n = k ⊕ z_L``: every other edge of ``n`` is re-expressed as an edge of ``k`` through
        ``z_L``, its covariance grown by the closure's (``Σ_L / w``, its information as the
        optimisation weighed it), and merged with an edge already between the same keyframes.
        ``n`` keeps only its closure, so a leaf: its pose follows ``k``'s.
        """
        graph = self.graph
        k = graph.edge_nodes(anchor_edge)[0]
        # Where the optimisation put n, not where the closure alone did: the optimum weighed the
        # closure against the odometry chain, and the folded edges are to keep that optimum.
        z_l = relative(graph.poses[k], graph.poses[n])
        info_l = graph.edge_information(anchor_edge)
        graph.set_edge(anchor_edge, k, n, z_l, info_l, robust=True)
        cov_l = np.linalg.inv(info_l) / max(float(weights[anchor_edge]), 1e-9)
        z_l_inv, cov_l_inv = inverse_with_covariance(z_l, cov_l)
        for e in graph.edges_of(n).tolist():
            if e == anchor_edge:
                continue
            i, j = graph.edge_nodes(e)
            cov = np.linalg.inv(graph.edge_information(e)) / max(float(weights[e]), 1e-9)
            if j == n:   # i -> n becomes i -> k
                a, b = i, k
                z, cov = compose_with_covariance(graph.edge_measurement(e), cov, z_l_inv, cov_l_inv)
            else:        # n -> j becomes k -> j
                a, b = k, j
                z, cov = compose_with_covariance(z_l, cov_l, graph.edge_measurement(e), cov)
            if e in self._loop_edges:   # a second closure of n: now a plain edge between old keyframes
                self._loop_edges.remove(e)
            parallel = graph.find_edge(a, b) if a != b else None
            if a == b or parallel is not None:
                graph.remove_edge(e)
            if parallel is not None:
                self._merge(parallel, a, b, z, cov)
            elif a != b:
                graph.set_edge(e, a, b, z, np.linalg.inv(cov))
        self._counts["folded"] += 1

    def _merge(self, edge: int, a: int, b: int, z: np.ndarray, cov: np.ndarray) -> None:
        """Fuse the measurement ``z`` (3,) of ``b`` in ``a``'s frame, covariance ``cov`` (3, 3), into ``edge``.

        Information adds; the measurement moves from the edge's towards ``z`` by the new
        information's share, in the edge's own frame (the two differ by a correction, not a turn).
        """
        graph = self.graph
        i, _ = graph.edge_nodes(edge)
        if i != a:   # the edge runs b -> a
            z, cov = inverse_with_covariance(z, cov)
        old_z, old_info = graph.edge_measurement(edge), graph.edge_information(edge)
        info = np.linalg.inv(cov)
        fused_info = old_info + info
        step = np.linalg.solve(fused_info, info @ relative(old_z, z))
        graph.set_edge(edge, *graph.edge_nodes(edge), compose(old_z, step), fused_info)


def _retired_arrays(prefix: str, retired: list[_Retired]) -> dict[str, np.ndarray]:
    """Retired keyframes as a snapshot's named arrays (``<prefix>_*``, R rows each)."""
    return {
        f"{prefix}_ordinal": np.array([r.ordinal for r in retired], dtype=np.int64),
        f"{prefix}_stamp_ns": np.array([r.stamp_ns for r in retired], dtype=np.int64),
        f"{prefix}_local_pose": np.array([r.local_pose for r in retired], dtype=float).reshape(-1, 3),
        f"{prefix}_local_edge": np.array([r.local_edge for r in retired], dtype=bool),
        f"{prefix}_scan_index": np.array([r.scan_index for r in retired], dtype=np.int64),
        f"{prefix}_anchor_ordinal": np.array([r.anchor_ordinal for r in retired], dtype=np.int64),
        f"{prefix}_anchor_stamp_ns": np.array([r.anchor_stamp_ns for r in retired], dtype=np.int64),
        f"{prefix}_offset": np.array([r.offset for r in retired], dtype=float).reshape(-1, 3),
    }


def _retired_from(prefix: str, arrays) -> list[_Retired]:
    """The retired keyframes :func:`_retired_arrays` wrote (none in a snapshot from before them)."""
    if f"{prefix}_ordinal" not in arrays:
        return []
    cols = [np.array(arrays[f"{prefix}_{name}"]) for name in
            ("ordinal", "stamp_ns", "local_pose", "local_edge", "scan_index", "anchor_ordinal", "anchor_stamp_ns",
             "offset")]
    r = cols[0].shape[0]
    if any(c.shape[0] != r for c in cols) or cols[2].shape != (r, 3) or cols[7].shape != (r, 3) \
            or not (np.all(np.isfinite(cols[2])) and np.all(np.isfinite(cols[7]))):
        raise InputError(f"mapper snapshot: {prefix} arrays of inconsistent shapes or not finite")
    return [_Retired(int(o), int(st), lp.astype(float), bool(le), int(si), int(ao), int(ast), off.astype(float))
            for o, st, lp, le, si, ao, ast, off in zip(*cols, strict=True)]


def place_scans(scan_kf: np.ndarray, scan_rel: np.ndarray, kf_poses: np.ndarray, kf_local_poses: np.ndarray,
                kf_first_scan: np.ndarray, kf_local_edge: np.ndarray) -> np.ndarray:
    """Every scan placed by the (optimised) keyframes: the one way the mapper and a recording's reader do it.

    Parameters
    ----------
    scan_kf : ndarray of int, shape (T,)
        Keyframe of each scan (the newest one made at or before it), ascending.
    scan_rel : ndarray, shape (T, 3)
        Each scan's local pose relative to its keyframe's.
    kf_poses, kf_local_poses : ndarray, shape (K, 3)
        The keyframes' optimised poses and their local poses.
    kf_first_scan : ndarray of int, shape (K,)
        Index of the scan that made each keyframe.
    kf_local_edge : ndarray of bool, shape (K,)
        Whether the odometry edge into each keyframe is the local motion.

    Returns
    -------
    ndarray, shape (T, 3)
    """
    kf = np.asarray(scan_kf, dtype=np.int64)
    rel = np.asarray(scan_rel, dtype=float).reshape(-1, 3)
    poses = _compose_rows(kf_poses[kf], rel)
    if kf.size == 0:
        return poses
    # A scan between two keyframes is placed from both, weighted by where it lies between
    # them, so the trajectory does not step at the next keyframe by what the optimisation
    # changed in between (from the earlier one alone: Intel 0.021 m against 0.020, ACES 0.044 m either way). Not across a jump: the local motion from the scan to the
    # next keyframe would hold it.
    nxt = np.minimum(kf + 1, len(kf_poses) - 1)
    blend = (nxt > kf) & np.asarray(kf_local_edge, dtype=bool)[nxt]
    if blend.any():
        idx = np.flatnonzero(blend)
        local_scan = _compose_rows(kf_local_poses[kf[idx]], rel[idx])
        from_next = _compose_rows(kf_poses[nxt[idx]], _relative_rows(kf_local_poses[nxt[idx]], local_scan))
        first = np.asarray(kf_first_scan, dtype=np.int64)
        w = (idx - first[kf[idx]]) / (first[nxt[idx]] - first[kf[idx]]).astype(float)
        poses[idx] = _compose_rows(poses[idx], _relative_rows(poses[idx], from_next) * w[:, None])
    return poses


def _compose_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise ``a ⊕ b`` of poses (T, 3)."""
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    return np.column_stack((a[:, 0] + c * b[:, 0] - s * b[:, 1], a[:, 1] + s * b[:, 0] + c * b[:, 1],
                            np.angle(np.exp(1j * (a[:, 2] + b[:, 2])))))


def _relative_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise ``a ⊖ b`` (``b`` in ``a``'s frame) of poses (T, 3)."""
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    return np.column_stack((c * dx + s * dy, -s * dx + c * dy, np.angle(np.exp(1j * (b[:, 2] - a[:, 2])))))
