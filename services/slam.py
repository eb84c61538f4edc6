"""slam: EKF-SLAM with the corner features as landmarks.

in:  odom        Odometry  (motion between scans)
     scan        LaserScan (scan matching: the motion between scans from their overlap)
     features    Features  (robot frame, with covariances; the walls' direction mod 90° corrects the heading)
out: slam/state  SlamState (pose, 3x3 covariance, landmarks with stable ids and 2x2 covariances)

Features are processed once odometry up to their stamp and their own scan have
arrived, so the result does not depend on how the streams interleave (live, or
replayed from a recording in any tie order; the one exception: features that
arrive before the very first scan are not held for it, so that inputs without
scans still flow). Odometry is interpolated at the scan stamp.

With ``scan_matching`` on (default), the filter predicts with the motion found
by matching each scan against the last keyframes (``lrfslam.algo.scan_match``),
the odometry increment being the initial guess; where the match fails, or the
scan never arrives, it predicts with odometry as without. The raw ``scan`` is
matched, not ``scan/filtered``: the denoiser's 4 m cut leaves too little to
match in halls (on the Intel log, scan matching alone scores 2.77 m relation
error with points to 4 m and 1.46 m with the 8 m default: ``lrfslam eval
relations --scan-matching``, docs/slam.md). Without odometry at all, the guess is "no
motion" with the ``no_odometry_sigma_*`` uncertainty.
With ``checkpoint_path`` set, the filter is saved atomically every
``checkpoint_every_scans`` scans and on exit, and a restarted service resumes from it.
"""

from __future__ import annotations

import logging
import os
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lrfslam.algo.ekf_slam import EkfParams, EkfSlam, UpdateReport
from lrfslam.algo.geometry import polar_to_xy, relative, wrap_angle
from lrfslam.algo.scan_match import ScanMatchParams, ScanTracker
from lrfslam.errors import ConfigError, InputError
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.runtime.step import Message, Output, RunContext, ServiceSpec, StepBase

log = logging.getLogger(__name__)

# Features kinds on the wire (1 forward, 2 backward) -> the filter's (0, 1).
_KIND_FROM_SCHEMA = {t.FEATURE_FORWARD: 0, t.FEATURE_BACKWARD: 1}


@dataclass(frozen=True)
class SlamConfig:
    ekf: EkfParams = field(default_factory=EkfParams)
    use_backward_features: bool = True   # jump edges as (tentative, viewpoint-checked) landmarks
    use_wall_direction: bool = True      # heading from the walls' direction mod 90° (not in the paper)
    wait_for_odometry: bool = True       # false for a laser without odometry (e.g. a bare LMS200)
    max_odom_wait_scans: int = 20        # process features without newer odometry after this many pile up
    checkpoint_path: str = ""            # e.g. checkpoints/slam.npz; empty = no checkpoints
    checkpoint_every_scans: int = 50
    scan_matching: bool = True           # predict with the scan-matched motion (not in the paper)
    scan_match: ScanMatchParams = field(default_factory=ScanMatchParams)
    no_odometry_sigma_m: float = 0.2     # scan matching without odometry: guess "no motion" +- this per scan
    no_odometry_sigma_rad: float = 0.2


def interpolate_pose(stamps_ns: np.ndarray, poses: np.ndarray, stamp_ns: int) -> np.ndarray:
    """Odometry pose at ``stamp_ns``, linear between the bracketing samples (heading via the short way).

    ``stamps_ns`` (M,) ascending, ``poses`` (M, 3). Outside the range, the nearest sample.
    """
    i = int(np.searchsorted(stamps_ns, stamp_ns))
    if i < len(stamps_ns) and stamps_ns[i] == stamp_ns:
        return poses[i].copy()
    if i == 0:
        return poses[0].copy()
    if i == len(stamps_ns):
        return poses[-1].copy()
    a, b = poses[i - 1], poses[i]
    w = (stamp_ns - stamps_ns[i - 1]) / (stamps_ns[i] - stamps_ns[i - 1])
    out = a + w * (b - a)
    out[2] = wrap_angle(a[2] + w * wrap_angle(b[2] - a[2]))
    return out


@dataclass(frozen=True)
class LastUpdate:
    """What the filter's last feature update was given (robot frame) and what it decided.

    ``xy_m`` (K, 2) m, ``cov_m2`` (K, 2, 2) m², ``report`` the association of each of the K.
    """

    xy_m: np.ndarray
    cov_m2: np.ndarray
    report: UpdateReport


class SlamStep(StepBase):
    def __init__(self, cfg: SlamConfig, ctx: RunContext) -> None:
        super().__init__()
        self.cfg = cfg
        self.odom: deque[tuple[int, np.ndarray]] = deque()
        self.pending: deque[t.Features] = deque()
        # Scans waiting for their features, by scan seq: (stamp, points (N, 2) robot frame).
        self.scans: dict[int, tuple[int, np.ndarray]] = {}
        self.newest_scan_ns: int | None = None
        self.tracker = ScanTracker(cfg.scan_match) if cfg.scan_matching else None
        self.last_odom_pose: np.ndarray | None = None
        self.started = False  # a scan has been processed (the next one has a motion to predict)
        self.seq = 0
        self.ekf = EkfSlam(cfg.ekf)
        self._last_update: LastUpdate | None = None
        self.checkpoint = Path(cfg.checkpoint_path) if cfg.checkpoint_path and not ctx.replay else None
        if self.checkpoint is not None and self.checkpoint.exists():
            self._restore(self.checkpoint)

    def start_at(self, pose: np.ndarray) -> None:
        """Start the filter at ``pose`` (x m, y m, heading rad; shape (3,)) instead of the origin.

        Only before the first scan is processed.
        """
        if self.seq:
            raise ConfigError("the slam step's start pose can only be set before its first scan")
        self.ekf = EkfSlam(self.cfg.ekf, pose0=pose)

    @property
    def last_update(self) -> LastUpdate | None:
        """The last feature update (None before the first)."""
        return self._last_update

    # -- messages

    def on_message(self, msg: Message):
        if msg.topic is topics.ODOM or msg.name == topics.ODOM.name:
            od: t.Odometry = msg.value
            if not np.all(np.isfinite(od.pose)):
                raise InputError(f"odometry {od.seq} has a non-finite pose")
            if self.odom and od.stamp_ns <= self.odom[-1][0]:
                self.counts["odom_out_of_order"] += 1
                return ()
            self.odom.append((od.stamp_ns, od.pose.copy()))
        elif msg.topic is topics.SCAN or msg.name == topics.SCAN.name:
            if self.tracker is None:
                return ()
            scan: t.LaserScan = msg.value
            valid = (scan.status == t.BEAM_VALID) & np.isfinite(scan.ranges_m)
            self.scans[scan.seq] = (scan.stamp_ns, polar_to_xy(scan.ranges_m[valid], scan.angles_rad[valid]))
            # Bounded even if no features ever come: no more than the features that may wait.
            while len(self.scans) > 2 * self.cfg.max_odom_wait_scans + 2:
                del self.scans[min(self.scans, key=lambda q: (self.scans[q][0], q))]
            self.newest_scan_ns = scan.stamp_ns if self.newest_scan_ns is None \
                else max(self.newest_scan_ns, scan.stamp_ns)
        else:
            self.pending.append(msg.value)
        return list(self._drain(final=False))

    def finish(self):
        return list(self._drain(final=True))

    def _drain(self, final: bool):
        while self.pending:
            feats = self.pending[0]
            newest = self.odom[-1][0] if self.odom else None
            give_up = final or len(self.pending) > self.cfg.max_odom_wait_scans
            odom_ready = (newest is not None and newest >= feats.stamp_ns) or not self.cfg.wait_for_odometry
            # No scan yet: inputs without scans (features and odometry only) are not
            # held back. A scan newer than the features means theirs was lost (scans
            # arrive in stamp order).
            scan_ready = self.tracker is None or self.newest_scan_ns is None or feats.scan_seq in self.scans \
                or self.newest_scan_ns > feats.stamp_ns
            if not (give_up or (odom_ready and scan_ready)):
                return
            self.pending.popleft()
            yield self._process(feats)

    def _process(self, feats: t.Features) -> Output:
        self._predict(feats)
        if self.cfg.use_wall_direction and feats.has_wall_direction:
            # Before the features: a corrected heading makes their association sharper.
            wall = self.ekf.observe_wall_direction(feats.wall_direction_rad, feats.wall_direction_sigma_rad)
            self.counts[f"wall_{wall.status.name.lower()}"] += 1
        keep = np.ones(len(feats), dtype=bool) if self.cfg.use_backward_features \
            else feats.kind == t.FEATURE_FORWARD
        kinds = np.array([_KIND_FROM_SCHEMA.get(int(k), 0) for k in feats.kind[keep]], dtype=np.int8)
        xy, cov = feats.xy_m[keep], feats.cov_m2[keep]
        report = self.ekf.observe(xy, cov, kinds)
        self._last_update = LastUpdate(xy, cov, report)
        self.counts["scans"] += 1
        self.counts["matched"] += report.n_matched
        self.counts["new"] += report.n_new
        self.counts["ambiguous"] += report.n_ambiguous + report.n_rejected
        self.seq += 1
        if self.checkpoint is not None and self.seq % self.cfg.checkpoint_every_scans == 0:
            self._save(self.checkpoint)
        lm = self.ekf.landmarks()
        kinds_out = np.where(lm.kinds == 0, t.FEATURE_FORWARD, t.FEATURE_BACKWARD)
        return Output(topics.SLAM_STATE, t.SlamState(
            feats.stamp_ns, self.seq, feats.scan_seq, self.ekf.pose, self.ekf.pose_cov,
            lm.ids, lm.xy, lm.cov, kinds_out, lm.sightings, lm.confirmed,
            report.n_matched, report.n_new, report.n_ambiguous + report.n_rejected))

    def _predict(self, feats: t.Features) -> None:
        """Move the filter to the features' stamp: scan-matched motion, else odometry."""
        odom_increment = None
        if self.odom:
            stamps = np.fromiter((s for s, _ in self.odom), dtype=np.int64, count=len(self.odom))
            poses = np.array([p for _, p in self.odom])
            odom_pose = interpolate_pose(stamps, poses, feats.stamp_ns)
            # Keep one sample at or before this stamp for the next interpolation.
            while len(self.odom) > 1 and self.odom[1][0] <= feats.stamp_ns:
                self.odom.popleft()
            if self.last_odom_pose is not None:
                odom_increment = relative(self.last_odom_pose, odom_pose)
            self.last_odom_pose = odom_pose
        else:
            self.counts["no_odometry"] += 1
        if self.tracker is None:
            if odom_increment is not None:
                self.ekf.predict(odom_increment)
            return
        started, self.started = self.started, True
        entry = self.scans.pop(feats.scan_seq, None)
        # Scans older than these features will never be asked for.
        for seq in [q for q, (stamp, _) in self.scans.items() if stamp < feats.stamp_ns]:
            del self.scans[seq]
        if odom_increment is not None:
            guess, guess_cov = odom_increment, self.ekf.odometry_cov(odom_increment)
        else:
            guess = np.zeros(3)
            guess_cov = np.diag([self.cfg.no_odometry_sigma_m**2, self.cfg.no_odometry_sigma_m**2,
                                 self.cfg.no_odometry_sigma_rad**2])
        if entry is None:
            self.counts["scan_missing"] += 1
            # Keep the tracker's chain in step with the filter: this motion is odometry's.
            self.tracker.skip(guess)
            if started and odom_increment is not None:
                self.ekf.predict(odom_increment)
            return
        step = self.tracker.step(entry[1], guess, guess_cov)
        self.counts[f"match_{step.match.status.name.lower()}"] += 1
        if started and (step.matched or odom_increment is not None):
            self.ekf.predict_with_cov(step.increment, step.cov)

    # -- checkpoints

    def _save(self, path: Path) -> None:
        """Write the filter atomically: a crash mid-write leaves the previous checkpoint intact."""
        snap = self.ekf.snapshot()
        snap["service_seq"] = self.seq
        if self.last_odom_pose is not None:
            snap["last_odom_pose"] = self.last_odom_pose
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "wb") as f:
            np.savez(f, **snap)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        self.counts["checkpoints"] += 1

    def _restore(self, path: Path) -> None:
        try:
            with np.load(path) as data:
                snap = {k: data[k] for k in data.files}
            self.ekf = EkfSlam.restore(self.cfg.ekf, snap)
        except (OSError, ValueError, KeyError, InputError) as exc:
            log.warning("ignoring unreadable checkpoint %s: %s", path, exc)
            self.counts["checkpoint_unreadable"] += 1
            return
        self.seq = int(snap.get("service_seq", 0))
        # The next scan's motion is predicted (by odometry: the scan tracker starts afresh).
        self.started = self.seq > 0
        if "last_odom_pose" in snap:
            self.last_odom_pose = np.asarray(snap["last_odom_pose"], dtype=float)
        log.info("resumed from %s: scan %d, %d landmarks", path, self.seq, self.ekf.n_landmarks)
        self.counts["restored"] += 1

    def close(self) -> None:
        if self.checkpoint is not None and self.seq:
            self._save(self.checkpoint)


SPEC = ServiceSpec(
    name="slam",
    summary="EKF-SLAM over odometry, scan matching and corner features; publishes pose, covariance and landmarks.",
    config_type=SlamConfig,
    inputs=(topics.ODOM, topics.SCAN, topics.FEATURES),
    outputs=(topics.SLAM_STATE,),
    build=lambda cfg, ctx: SlamStep(cfg, ctx),
)
