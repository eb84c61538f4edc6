"""The loop-closing mapper's parameters (:class:`LoopClosureParams`); the design they serve is
in the package notes (:mod:`lrfslam.algo.loop_closure`)."""

from __future__ import annotations

from dataclasses import dataclass, field

from lrfslam.algo.checks import require_finite
from lrfslam.algo.correlative_match import CorrelativeParams
from lrfslam.algo.scan_match import ScanMatchParams
from lrfslam.errors import ConfigError

#: The closures' refinement and the odometry edges' matches: the slam's scan tracker's defaults
#: (its ``max_point_range_m`` limits the matched points there).
SCAN_MATCH = ScanMatchParams()

#: A scan that moved this far since the previous one (m) starts a keyframe whatever the keyframe
#: spacing: faster than a robot drives, so the local trajectory jumped (an EKF correction); the jump
#: then falls between two keyframes, where the scan match replaces it, not inside a keyframe's scans.
MAX_SCAN_STEP_M = 0.2
#: A keyframe's points are thinned to one per square of this side (m).
KEYFRAME_CELL_M = 0.05
#: The map of a candidate is it and this many keyframes on each side of it.
SUBMAP_KEYFRAMES = 10
#: The query is thinned to one point per square of this side (m): the search's cost is linear in its points.
QUERY_CELL_M = 0.1
#: Floors of the odometry edges' position (m) and heading (rad) standard deviations.
ODOM_TRANS_SIGMA_M = 0.005
ODOM_ROT_SIGMA_RAD = 0.002
#: Search half-widths in standard deviations of the relative pose.
WINDOW_SIGMAS = 3.0
#: Bounds of the rotation half-width (rad).
MIN_WINDOW_RAD = 0.1
MAX_WINDOW_RAD = 0.5
#: A closure whose robust weight falls below this after optimisation is removed.
MIN_WEIGHT = 0.25
#: Submaps kept for re-use (the same old place is searched from consecutive keyframes).
CACHED_SUBMAPS = 8
#: A search whose translation half-width exceeds ``WIDE_WINDOW_M`` (m) is run at most once per
#: ``WIDE_SEARCH_SPACING_M`` of travel (m): its cost grows with the window's area, and while the robot
#: is lost in a place it saw long ago consecutive keyframes would search the same ground.
WIDE_WINDOW_M = 2.0
WIDE_SEARCH_SPACING_M = 2.0
#: A closure found in a wide window is added only once the next one found in a wide window, at most
#: ``CONFIRM_WITHIN_M`` of travel later (m), puts the robot within ``CONFIRM_M`` (m) and
#: ``CONFIRM_RAD`` (rad) of where it does.
CONFIRM_WITHIN_M = 10.0
CONFIRM_M = 0.5
CONFIRM_RAD = 0.05
#: A new closure whose own χ² at the current estimate exceeds ``OPTIMISE_CHI2`` is solved for at
#: once; smaller ones (the graph agrees already) wait until ``MAX_PENDING_CLOSURES`` have gathered
#: (or :meth:`LoopClosingMapper.trajectory` is asked for): each solve costs a sparse factorisation
#: of the whole graph.
OPTIMISE_CHI2 = 9.0
MAX_PENDING_CLOSURES = 10
#: A saved map's keyframes (:meth:`LoopClosingMapper.seeded`) are held at their saved poses, in the
#: first one's frame, to within this (m, rad): what a saved map, closed by its own run, is sure of
#: over the building; locally the drift model's odometry edges hold them to each other.
SAVED_EDGE_SIGMA_M = 0.05
SAVED_EDGE_SIGMA_RAD = 0.01
#: The new keyframe's scan is matched against this many last keyframes, merged.
ODOMETRY_KEYFRAMES = 3
#: An odometry edge is the local motion between the keyframes unless it differs from the keyframes'
#: scans matched (point-to-line, the local motion as the guess) by more than this (m, rad): then it
#: is the match.
EKF_JUMP_M = 0.05
EKF_JUMP_RAD = 0.02


@dataclass(frozen=True)
class LoopClosureParams:
    """Parameters of :class:`LoopClosingMapper`.

    Attributes
    ----------
    keyframe_trans_m, keyframe_rot_rad : float
        A scan becomes a keyframe once the local trajectory has moved this far (m) or turned
        this much (rad) since the last keyframe (or jumped: :data:`MAX_SCAN_STEP_M`).
    max_range_m : float
        Points farther than this from the sensor are ignored (m); also drops a
        log's "no return" placeholder ranges (ACES writes 50 m).
    query_keyframes : int
        The query is the new keyframe and the ones before it, this many in all.
    min_travel_m : float
        A candidate must be at least this far back along the trajectory (m).
    candidate_radius_m : float
        ...and its graph position within the search window's half-width plus
        this distance of the predicted one (m): farther, its map would not
        overlap the query.
    max_candidates : int
        Candidates searched per keyframe at most, the nearest first, at least
        ``2 SUBMAP_KEYFRAMES + 1`` keyframes apart (so their maps differ).
    odom_trans_sigma_per_m : float
        The odometry edges' position standard deviation: :data:`ODOM_TRANS_SIGMA_M` plus this much per
        metre travelled (dimensionless)...
    odom_rot_sigma_per_m, odom_rot_sigma_per_rad : float
        ...and their heading's: :data:`ODOM_ROT_SIGMA_RAD` plus this much per metre travelled (rad/m)
        and per radian turned (dimensionless).
    drift_onset_rad : float
        The systematic drift model of the search window and the gate: the graph's relative
        covariance times ``1 + σθ² / drift_onset_rad²``, σθ its heading standard deviation (rad).
        Below the onset the drift is the edges' random walk; past it the error grows with
        the loop, not its square root. 0: no model (the covariance as the graph gives it).
    min_window_m, max_window_m : float
        Bounds of the translation half-width (m) of a search window :data:`WINDOW_SIGMAS` wide.
    min_score : float
        Mean likelihood (0–1) a closure must reach.
    max_second_ratio : float
        A separated second peak scoring this fraction of the best makes the match ambiguous.
    gate_chi2 : float
        Largest Mahalanobis χ² (3 dof) between the match and the graph's prediction.
    match_cov_scale : float
        Factor on the point-to-line matcher's covariance for a loop edge (it
        ignores that neighbouring beams' errors correlate, and the map's own error).
    correlative : CorrelativeParams
    trim_revisits : bool
        A keyframe that closed a loop (a revisit of a mapped place) is never a
        candidate, and its points are dropped once it is no longer one of the last
        ``max(query_keyframes, ODOMETRY_KEYFRAMES)``: a place's map is the visit that
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
        closures after it still place it; how late matters little (docs/slam.md).
    """

    keyframe_trans_m: float = 0.5
    keyframe_rot_rad: float = 0.35
    max_range_m: float = 20.0
    query_keyframes: int = 5
    min_travel_m: float = 10.0
    candidate_radius_m: float = 3.0
    max_candidates: int = 2
    odom_trans_sigma_per_m: float = 0.01
    odom_rot_sigma_per_m: float = 0.006
    odom_rot_sigma_per_rad: float = 0.03
    drift_onset_rad: float = 0.02
    min_window_m: float = 0.5
    max_window_m: float = 12.0
    min_score: float = 0.5
    max_second_ratio: float = 0.9
    gate_chi2: float = 16.0
    match_cov_scale: float = 16.0
    correlative: CorrelativeParams = field(default_factory=CorrelativeParams)
    trim_revisits: bool = True
    fold_revisits: bool = True
    fold_after_keyframes: int = 50

    def __post_init__(self) -> None:
        positive = ("max_range_m", "min_window_m", "max_window_m", "gate_chi2", "match_cov_scale", "candidate_radius_m")
        require_finite(self, positive, positive=True, what="loop closure ")
        non_negative = ("keyframe_trans_m", "keyframe_rot_rad", "min_travel_m", "odom_trans_sigma_per_m",
                        "odom_rot_sigma_per_m", "odom_rot_sigma_per_rad", "drift_onset_rad", "min_score", "max_second_ratio")
        require_finite(self, non_negative, positive=False, what="loop closure ")
        if self.min_window_m > self.max_window_m:
            raise ConfigError("loop closure min_window_m must not exceed max_window_m")
        if self.query_keyframes < 1 or self.max_candidates < 0:
            raise ConfigError("loop closure needs query_keyframes >= 1 and max_candidates >= 0")
        if self.fold_after_keyframes < 0:
            raise ConfigError("loop closure fold_after_keyframes must be >= 0")
        if self.fold_revisits and not self.trim_revisits:
            raise ConfigError("loop closure fold_revisits needs trim_revisits (only a revisit is folded)")
