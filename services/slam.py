"""slam: EKF-SLAM with the corner features as landmarks.

in:  odom        Odometry  (motion between scans)
     scan        LaserScan (scan matching: the motion between scans from their overlap)
     features    Features  (robot frame, with covariances; the walls' direction mod 90° corrects the heading)
out: slam/state  SlamState (pose, 3x3 covariance, the landmarks that changed, the motion that moved the filter)
     slam/map    LandmarkMap (every landmark with its stable id and 2x2 covariance; every ``map_period_s``
                 of data time, at the first and the last state, and on request)

Features wait for their odometry and scan (``lrfslam.algo.stream_alignment``), so the result does not
depend on how the streams interleave; then ``lrfslam.algo.corner_slam`` moves the filter (scan-matched
motion, else odometry), corrects the heading and adds the features. A state carries only the landmarks
that moved (or whose spread changed) beyond ``LANDMARK_TOLERANCE_M`` since they were last sent, so its
size does not grow with the map (``lrfslam.msgs.landmark_map``). The filter is :class:`Resumable`: where
the runtime keeps checkpoints (``bus.checkpoint_dir``, ``lrfslam.runtime.checkpoints``) a restart resumes it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from lrfslam.algo import checkpoint, kernels
from lrfslam.algo.corner_slam import CornerSlam
from lrfslam.algo.ekf_slam import EkfParams
from lrfslam.algo.geometry import polar_to_xy
from lrfslam.algo.motion_source import MotionParams
from lrfslam.algo.scan_match import ScanMatchParams
from lrfslam.algo.stream_alignment import Aligned, AlignmentParams, StreamAligner
from lrfslam.msgs import landmark_map, topics
from lrfslam.msgs import types as t
from lrfslam.runtime.step import Message, Output, RunContext, ServiceSpec, StepBase

log = logging.getLogger(__name__)


#: A state carries a landmark that moved, or whose spread changed, more than this since it was
#: last sent (m): below the corners' own spread, so a subscriber's map is as good as the filter's.
LANDMARK_TOLERANCE_M = 0.005
#: Features go ahead without newer odometry once this many scans wait for it: a stalled odometry
#: stream must not hold the map back for long (2 s at the LMS200's 10 Hz).
MAX_ODOM_WAIT_SCANS = 20


#: Odometry noise settings renamed after their model (a random walk: σ·√distance, σ·√angle).
RENAMED_ODOMETRY = {"odom_trans_sigma_per_m": "odom_trans_sigma_per_sqrt_m",
                    "odom_rot_sigma_per_rad": "odom_rot_sigma_per_sqrt_rad",
                    "odom_rot_sigma_per_m": "odom_rot_sigma_per_sqrt_m"}


@dataclass(frozen=True)
class SlamConfig:
    """The slam stage's configuration; ``SETTINGS`` are the names an operator sets (docs/settings.md)."""

    ekf: EkfParams = field(default_factory=EkfParams)
    use_backward_features: bool = True   # jump edges as (tentative, viewpoint-checked) landmarks
    use_wall_direction: bool = True      # heading from the walls' direction mod 90° (not in the paper)
    wait_for_odometry: bool = True       # false for a laser without odometry (e.g. a bare LMS200)
    scan_matching: bool = True           # predict with the scan-matched motion (not in the paper)
    tracker: ScanMatchParams = field(default_factory=ScanMatchParams)   # the scan tracker's parameters
    no_odometry_sigma_m: float = 0.2     # scan matching without odometry: guess "no motion" +- this per scan
    no_odometry_sigma_rad: float = 0.2
    map_period_s: float = 5.0            # the whole map on slam/map at least this often (data time)

    SETTINGS: ClassVar[tuple[str, ...]] = (
        "scan_matching", "use_backward_features", "use_wall_direction", "wait_for_odometry",
        "no_odometry_sigma_m", "no_odometry_sigma_rad", "map_period_s",
        "ekf.odom_trans_sigma_per_sqrt_m", "ekf.odom_rot_sigma_per_sqrt_rad", "ekf.odom_rot_sigma_per_sqrt_m",
        "ekf.corner_range_sigma_m", "ekf.corner_bearing_sigma_rad", "ekf.association", "ekf.gate_assoc_chi2",
        "ekf.gate_new_chi2", "ekf.min_sightings_to_confirm", "ekf.max_landmarks",
        "tracker.max_point_range_m", "tracker.free_space_check",
    )
    RETIRED: ClassVar[dict[str, str]] = {
        "checkpoint_path": "the runtime keeps every stage's checkpoint: bus.checkpoint_dir (<dir>/slam.checkpoint.npz)",
        "checkpoint_every_scans": "the runtime saves every bus.checkpoint_period_s of data time",
        "landmark_tolerance_m": f"fixed at {LANDMARK_TOLERANCE_M} m (services/slam.py LANDMARK_TOLERANCE_M)",
        "max_odom_wait_scans": f"fixed at {MAX_ODOM_WAIT_SCANS} scans (services/slam.py MAX_ODOM_WAIT_SCANS)",
        **{f"scan_match.{name}": f"renamed slam.tracker.{name} (one name per idea: scan_matching turns the tracker on)"
           for name in ("max_point_range_m", "free_space_check")},
        **{f"scan_match.{name}": "the tracker's search of old reference scans was removed (it corrected the drift "
           "the landmarks correct, twice); it matches the last reference scans only"
           for name in ("map_radius_m", "map_max_keyframes", "max_keyframes")},
        **{f"scan_match.drift_{x}_sigma_per_m": "removed with the search of old reference scans, whose snaps it hid; "
           "the odometry noise is ekf.odom_*" for x in ("trans", "rot")},
        **{f"ekf.{old}": f"renamed ekf.{new}: a random walk, its sigma grows with the square root of the motion"
           for old, new in RENAMED_ODOMETRY.items()},
    }


class SlamStep(StepBase):
    def __init__(self, cfg: SlamConfig, ctx: RunContext) -> None:
        super().__init__()
        self.cfg = cfg
        kernels.prepare()
        self.align = StreamAligner(AlignmentParams(cfg.wait_for_odometry, cfg.scan_matching, MAX_ODOM_WAIT_SCANS))
        motion = MotionParams(cfg.scan_matching, cfg.tracker, cfg.no_odometry_sigma_m, cfg.no_odometry_sigma_rad)
        self.slam = CornerSlam(cfg.ekf, motion, cfg.use_backward_features, cfg.use_wall_direction, self.counts)
        self.current = t.Landmarks()         # the filter's map after the last update
        self.sent = t.Landmarks()            # the map as the subscribers hold it (sorted by id)
        self.last_state: t.SlamState | None = None
        self.maps = 0                        # slam/map messages published (their sequence numbers)
        self.map_sent_ns: int | None = None  # the stamp of the last one
        self._last_scan_seq: int | None = None   # the scan of the last update

    def on_message(self, msg: Message):
        v = msg.value
        if msg.topic is topics.ODOM:
            if not self.align.add_odometry(v.stamp_ns, v.pose):
                self.counts["odom_out_of_order"] += 1
        elif msg.topic is topics.SCAN and self.cfg.scan_matching:
            valid = (v.status == t.BEAM_VALID) & np.isfinite(v.ranges_m)
            self.align.add_scan(v.seq, v.stamp_ns, polar_to_xy(v.ranges_m[valid], v.angles_rad[valid]))
        elif msg.topic is topics.FEATURES:
            self.align.add_features(v.stamp_ns, v.scan_seq, v)
        return [out for a in self.align.ready() for out in self._process(a)]

    def finish(self):
        outs = [out for a in self.align.ready(final=True) for out in self._process(a)]
        if self.last_state is not None and self.map_sent_ns != self.last_state.stamp_ns:
            outs.append(self._whole_map())
        return outs

    def latest(self, topic):
        if topic is topics.SLAM_MAP and self.last_state is not None:
            # The map every subscriber holds now (not the filter's exact one: the states that
            # follow carry their changes against it).
            return t.LandmarkMap(stamp_ns=self.last_state.stamp_ns, seq=self.maps, state_seq=self.last_state.seq,
                                 landmarks=self.sent, tolerance_m=LANDMARK_TOLERANCE_M)
        return None

    def _process(self, a: Aligned[t.Features]) -> list[Output]:
        f = a.features
        wall = (f.wall_direction_rad, f.wall_direction_sigma_rad) if f.has_wall_direction else None
        # Wire kinds (1 forward, 2 backward; 0 unknown, treated as forward) -> the filter's (0, 1).
        # Scans lost between two (a restarted router, a skipped input) make one motion of several steps.
        follows_last = self._last_scan_seq is None or f.scan_seq == self._last_scan_seq + 1
        self._last_scan_seq = f.scan_seq
        report = self.slam.update(a.odom_pose, a.scan_xy_m, f.xy_m, f.cov_m2,
                                  (f.kind == t.FEATURE_BACKWARD).astype(np.int8), wall, follows_last)
        ekf, lm = self.slam.ekf, self.slam.ekf.landmarks()
        self.current = t.Landmarks(ids=lm.ids, xy_m=lm.xy, cov_m2=lm.cov,
                                   kind=np.where(lm.kinds == 0, t.FEATURE_FORWARD, t.FEATURE_BACKWARD),
                                   sightings=lm.sightings, confirmed=lm.confirmed)
        changed, removed = landmark_map.changes(self.sent, self.current, LANDMARK_TOLERANCE_M)
        self.sent = landmark_map.apply(self.sent, changed, removed)
        self.last_state = t.SlamState(stamp_ns=f.stamp_ns, seq=self.slam.scans, scan_seq=f.scan_seq, pose=ekf.pose,
                                      pose_cov=ekf.pose_cov, landmarks=changed, removed_landmark_ids=removed,
                                      landmarks_complete=False, n_landmarks=len(self.current),
                                      n_confirmed=int(np.count_nonzero(lm.confirmed)), associated=report.n_matched,
                                      added=report.n_new, rejected=report.n_ambiguous + report.n_rejected,
                                      motion=self._motion(), motion_matched=self.slam.last_update.motion_matched)
        outs = [Output(topics.SLAM_STATE, self.last_state)]
        since = None if self.map_sent_ns is None else f.stamp_ns - self.map_sent_ns
        # A first state (of the run, or after a restart) is followed by the whole map, so late
        # and restarted subscribers have one; data time going back (another run) restarts the period.
        if since is None or not 0 <= since < self.cfg.map_period_s * 1e9:
            outs.append(self._whole_map())
        return outs

    def _whole_map(self) -> Output:
        """The filter's map as it stands, on slam/map; the subscribers then hold it exactly."""
        self.sent = landmark_map.by_id(self.current)
        self.maps += 1
        self.map_sent_ns = self.last_state.stamp_ns
        return Output(topics.SLAM_MAP, t.LandmarkMap(stamp_ns=self.last_state.stamp_ns, seq=self.maps,
                                                     state_seq=self.last_state.seq, landmarks=self.sent,
                                                     tolerance_m=LANDMARK_TOLERANCE_M))

    def _motion(self) -> np.ndarray:
        """What moved the filter to this scan, (3,); zero where nothing did (absent only in older recordings)."""
        motion = self.slam.last_update.motion
        return np.zeros(3) if motion is None else motion

    def snapshot(self) -> dict | None:
        """The filter and where the stream stood (:mod:`lrfslam.algo.checkpoint`); None before the first scan."""
        return self.slam.checkpoint() if self.slam.scans else None

    def restore(self, arrays) -> str:
        self.slam.resume(checkpoint.decode(self.cfg.ekf, arrays))
        return f"scan {self.slam.scans}, {self.slam.ekf.n_landmarks} landmarks"

SPEC = ServiceSpec(
    name="slam",
    summary="EKF-SLAM over odometry, scan matching and corner features; publishes pose, covariance and landmarks.",
    config_type=SlamConfig,
    inputs=(topics.ODOM, topics.SCAN, topics.FEATURES),
    outputs=(topics.SLAM_STATE, topics.SLAM_MAP),
    latest=(topics.SLAM_STATE, topics.SLAM_MAP),
    skippable=(topics.SCAN, topics.FEATURES),
    build=lambda cfg, ctx: SlamStep(cfg, ctx),
)
