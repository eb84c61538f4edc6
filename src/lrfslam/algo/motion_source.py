"""The motion between consecutive scans that moves the filter: scan-matched, else odometry.

With scan matching on, the motion is the one found by matching each scan
against the last reference scans (:class:`~lrfslam.algo.scan_match.ScanTracker`),
the odometry increment being the initial guess; where the match fails, or the
scan never arrived, it is the odometry increment, as without scan matching.
Without odometry at all, the guess is "no motion" with the
``no_odometry_sigma_*`` uncertainty, and only a successful match moves the filter.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from lrfslam.algo.geometry import relative
from lrfslam.algo.scan_match import ScanMatchParams, ScanTracker


@dataclass(frozen=True)
class MotionParams:
    """Attributes
    ----------
    scan_matching : bool
        Predict with the scan-matched motion (not in the paper).
    tracker : ScanMatchParams
        The scan tracker's parameters.
    no_odometry_sigma_m, no_odometry_sigma_rad : float
        Scan matching without odometry: the guess "no motion" is good to this per scan (m, rad).
    """

    scan_matching: bool = True
    tracker: ScanMatchParams = field(default_factory=ScanMatchParams)
    no_odometry_sigma_m: float = 0.2
    no_odometry_sigma_rad: float = 0.2


@dataclass(frozen=True)
class Motion:
    """How to move the filter from the previous scan to this one.

    Attributes
    ----------
    increment : ndarray, shape (3,), or None
        (dx m, dy m, dtheta rad) in the previous pose's frame; None: no prediction.
    cov : ndarray, shape (3, 3), or None
        Its covariance; None: the filter's own odometry model applies.
    events : tuple of str
        What happened, as counter names: ``no_odometry``, ``scan_missing``,
        ``match_<status>``, ``scan_moved_points`` (some of the scan's points left out as moved).
    matched : bool
        The increment was found by scan matching (else it is odometry's, or None).
    """

    increment: np.ndarray | None
    cov: np.ndarray | None
    events: tuple[str, ...]
    matched: bool = False


class MotionSource:
    """Turns each scan's odometry pose and points into the :class:`Motion` since the previous scan."""

    def __init__(self, params: MotionParams) -> None:
        self.params = params
        self._tracker = ScanTracker(params.tracker) if params.scan_matching else None
        self._last_odom_pose: np.ndarray | None = None
        self._started = False   # a scan has been matched or skipped: the next one has a motion

    @property
    def last_odom_pose(self) -> np.ndarray | None:
        """The odometry pose (3,) of the previous scan, if any."""
        return self._last_odom_pose

    def resume(self, last_odom_pose: np.ndarray | None, started: bool) -> None:
        """Continue after a restart: the next scan's motion is odometry's (the tracker starts afresh)."""
        self._last_odom_pose = None if last_odom_pose is None else np.asarray(last_odom_pose, dtype=float)
        self._started = started

    def next(self, odom_pose: np.ndarray | None, scan_xy_m: np.ndarray | None,
             odometry_cov: Callable[[np.ndarray], np.ndarray], follows_last: bool = True) -> Motion:
        """The motion to this scan.

        Parameters
        ----------
        odom_pose : ndarray, shape (3,), or None
            Odometry pose at this scan; None if there is no odometry.
        scan_xy_m : ndarray, shape (N, 2), or None
            The scan's points, robot frame (m); None if the scan was lost.
        odometry_cov : callable
            The filter's odometry model: increment (3,) -> covariance (3, 3).
        follows_last : bool
            No scan was lost since the previous one (the tracker's previous motion is then a guess).
        """
        events = []
        increment = None
        if odom_pose is None:
            events.append("no_odometry")
        else:
            if self._last_odom_pose is not None:
                increment = relative(self._last_odom_pose, odom_pose)
            self._last_odom_pose = odom_pose
        if self._tracker is None:
            return Motion(increment, None, tuple(events))
        started, self._started = self._started, True
        if increment is not None:
            guess, guess_cov = increment, odometry_cov(increment)
        else:
            p = self.params
            guess = np.zeros(3)
            guess_cov = np.diag([p.no_odometry_sigma_m**2, p.no_odometry_sigma_m**2, p.no_odometry_sigma_rad**2])
        if scan_xy_m is None:
            events.append("scan_missing")
            # Keep the tracker's chain in step with the filter: this motion is odometry's.
            self._tracker.skip(guess)
            return Motion(increment if started else None, None, tuple(events))
        step = self._tracker.step(scan_xy_m, guess, guess_cov, follows_last)
        events.append(f"match_{step.match.status.name.lower()}")
        if step.moved_points:
            events.append("scan_moved_points")
        if started and (step.matched or increment is not None):
            return Motion(step.increment, step.cov, tuple(events), step.matched)
        return Motion(None, None, tuple(events))
