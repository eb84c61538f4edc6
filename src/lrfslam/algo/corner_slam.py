"""EKF-SLAM driven scan by scan: move the filter, correct the heading, then the corner features.

One :meth:`CornerSlam.update` per scan, with what
:class:`~lrfslam.algo.stream_alignment.StreamAligner` lined up for it:

1. predict with the motion since the previous scan
   (:class:`~lrfslam.algo.motion_source.MotionSource`: scan-matched, else odometry);
2. if the scan has a dominant wall direction (and it is in use), correct the
   heading with it first: a corrected heading makes the features' association sharper;
3. observe the features (corners, and jump edges if in use) as landmarks.

What happens is counted in ``counts`` (the slam service's status counters).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np

from lrfslam.algo.checkpoint import Checkpoint
from lrfslam.algo.checkpoint import encode as encode_checkpoint
from lrfslam.algo.ekf_slam import EkfParams, EkfSlam, ObsStatus, UpdateReport
from lrfslam.algo.motion_source import MotionParams, MotionSource
from lrfslam.errors import ConfigError

#: 95 % quantile of the chi-squared distribution with 2 degrees of freedom.
CHI2_2DOF_95 = 5.991

FORWARD, BACKWARD = 0, 1   # the filter's feature kinds: right-angle corners, jump edges


@dataclass(frozen=True)
class LastUpdate:
    """The last update.

    Attributes
    ----------
    motion : ndarray, shape (3,), or None
        What moved the filter to this scan (scan-matched, else odometry):
        (dx m, dy m, dtheta rad) in the previous pose's frame; None if it did not move.
    motion_matched : bool
        ``motion`` was found by scan matching.
    xy_m : ndarray, shape (K, 2)
        The features given to the filter, robot frame (m).
    cov_m2 : ndarray, shape (K, 2, 2)
        Their covariances (m²).
    report : UpdateReport
        What the filter did with each of the K.
    """

    motion: np.ndarray | None
    motion_matched: bool
    xy_m: np.ndarray
    cov_m2: np.ndarray
    report: UpdateReport


class CornerSlam:
    """The filter and its motion source, updated once per scan.

    Parameters
    ----------
    ekf_params : EkfParams
    motion_params : MotionParams
    use_backward : bool
        Jump edges become (tentative, viewpoint-checked) landmarks too.
    use_wall_direction : bool
        Correct the heading with the walls' direction modulo 90° (not in the paper).
    counts : Counter, optional
        Where events are counted (a new one if not given).
    """

    def __init__(self, ekf_params: EkfParams, motion_params: MotionParams, use_backward: bool = True,
                 use_wall_direction: bool = True, counts: Counter | None = None) -> None:
        self.ekf = EkfSlam(ekf_params)
        self.motion = MotionSource(motion_params)
        self.use_backward = use_backward
        self.use_wall_direction = use_wall_direction
        self.counts: Counter[str] = Counter() if counts is None else counts
        self.scans = 0   # updates so far (the slam state's seq)
        self._last: LastUpdate | None = None

    @property
    def last_update(self) -> LastUpdate | None:
        """What the last update was given and decided (None before the first)."""
        return self._last

    def start_at(self, pose: np.ndarray) -> None:
        """Start at ``pose`` (3,) = (x m, y m, heading rad) instead of the origin; only before the first scan."""
        if self.scans:
            raise ConfigError("the start pose can only be set before the first scan")
        self.ekf = EkfSlam(self.ekf.params, pose0=pose)

    def update(self, odom_pose: np.ndarray | None, scan_xy_m: np.ndarray | None, xy_m: np.ndarray,
               cov_m2: np.ndarray, kinds: np.ndarray, wall: tuple[float, float] | None,
               follows_last: bool = True) -> UpdateReport:
        """Process one scan.

        Parameters
        ----------
        odom_pose : ndarray, shape (3,), or None
            Odometry pose at the scan; None without odometry.
        scan_xy_m : ndarray, shape (N, 2), or None
            The scan's points (robot frame, m) for scan matching; None if lost.
        xy_m : ndarray, shape (K, 2)
            Features, robot frame (m).
        cov_m2 : ndarray, shape (K, 2, 2)
        kinds : ndarray, shape (K,)
            :data:`FORWARD` or :data:`BACKWARD`.
        wall : (direction rad, sigma rad) or None
            The walls' direction modulo 90° in the robot frame, if the scan has one.
        follows_last : bool
            The scan is the one after the last scan updated (none lost between them).
        """
        motion = self.motion.next(odom_pose, scan_xy_m, self.ekf.odometry_cov, follows_last)
        self.counts.update(motion.events)
        if motion.increment is not None and motion.cov is None:
            self.ekf.predict(motion.increment)
        elif motion.increment is not None:
            self.ekf.predict_with_cov(motion.increment, motion.cov)
        if self.use_wall_direction and wall is not None:
            status = self.ekf.observe_wall_direction(*wall).status
            self.counts[f"wall_{status.name.lower()}"] += 1
        keep = slice(None) if self.use_backward else kinds == FORWARD
        xy, cov = xy_m[keep], cov_m2[keep]
        report = self.ekf.observe(xy, cov, np.asarray(kinds[keep], dtype=np.int8))
        self._last = LastUpdate(motion.increment, motion.matched, xy, cov, report)
        self.counts.update(scans=1, matched=report.n_matched, new=report.n_new,
                           ambiguous=report.n_ambiguous + report.n_rejected)
        # Consistency on data without ground truth: the NIS of matched observations averages 2
        # (chi-squared, 2 dof) and falls inside the 95 % bound 95 % of the time when the filter's
        # covariances are right. Counters are integers, so the sum is kept in thousandths.
        nis = report.nis[report.status == ObsStatus.MATCHED]
        self.counts.update(nis_matched_milli=int(np.round(1000.0 * nis.sum())),
                           nis_matched_within_95=int(np.count_nonzero(nis <= CHI2_2DOF_95)))
        self.scans += 1
        return report

    def checkpoint(self) -> dict:
        """The arrays of a checkpoint (:mod:`lrfslam.algo.checkpoint`)."""
        return encode_checkpoint(self.ekf, self.scans, self.motion.last_odom_pose)

    def resume(self, ck: Checkpoint) -> None:
        """Continue from a decoded checkpoint; the next scan's motion is odometry's."""
        self.ekf, self.scans = ck.ekf, ck.scans
        self.motion.resume(ck.last_odom_pose, started=ck.scans > 0)
