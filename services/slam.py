"""slam: EKF-SLAM with the corner features as landmarks.

in:  odom        Odometry  (motion between scans)
     features    Features  (robot frame, with covariances; the walls' direction mod 90° corrects the heading)
out: slam/state  SlamState (pose, 3x3 covariance, landmarks with stable ids and 2x2 covariances)

Features are processed once odometry up to their stamp has arrived, so the
result does not depend on how the two streams interleave (live, or replayed
from a recording in any tie order). Odometry is interpolated at the scan stamp.
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

from lrfslam.algo.ekf_slam import EkfParams, EkfSlam
from lrfslam.algo.geometry import relative, wrap_angle
from lrfslam.errors import InputError
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.runtime.service import Message, Output, RunContext, ServiceSpec, StepBase

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


class SlamStep(StepBase):
    def __init__(self, cfg: SlamConfig, ctx: RunContext) -> None:
        super().__init__()
        self.cfg = cfg
        self.odom: deque[tuple[int, np.ndarray]] = deque()
        self.pending: deque[t.Features] = deque()
        self.last_odom_pose: np.ndarray | None = None
        self.seq = 0
        self.ekf = EkfSlam(cfg.ekf)
        self.checkpoint = Path(cfg.checkpoint_path) if cfg.checkpoint_path and not ctx.replay else None
        if self.checkpoint is not None and self.checkpoint.exists():
            self._restore(self.checkpoint)

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
        else:
            self.pending.append(msg.value)
        return list(self._drain(final=False))

    def finish(self):
        return list(self._drain(final=True))

    def _drain(self, final: bool):
        while self.pending:
            feats = self.pending[0]
            newest = self.odom[-1][0] if self.odom else None
            ready = (newest is not None and newest >= feats.stamp_ns) or final or not self.cfg.wait_for_odometry \
                or len(self.pending) > self.cfg.max_odom_wait_scans
            if not ready:
                return
            self.pending.popleft()
            yield self._process(feats)

    def _process(self, feats: t.Features) -> Output:
        if self.odom:
            stamps = np.fromiter((s for s, _ in self.odom), dtype=np.int64, count=len(self.odom))
            poses = np.array([p for _, p in self.odom])
            odom_pose = interpolate_pose(stamps, poses, feats.stamp_ns)
            # Keep one sample at or before this stamp for the next interpolation.
            while len(self.odom) > 1 and self.odom[1][0] <= feats.stamp_ns:
                self.odom.popleft()
            if self.last_odom_pose is not None:
                self.ekf.predict(relative(self.last_odom_pose, odom_pose))
            self.last_odom_pose = odom_pose
        else:
            self.counts["no_odometry"] += 1
        if self.cfg.use_wall_direction and feats.has_wall_direction:
            # Before the features: a corrected heading makes their association sharper.
            wall = self.ekf.observe_wall_direction(feats.wall_direction_rad, feats.wall_direction_sigma_rad)
            self.counts[f"wall_{wall.status.name.lower()}"] += 1
        keep = np.ones(len(feats), dtype=bool) if self.cfg.use_backward_features \
            else feats.kind == t.FEATURE_FORWARD
        kinds = np.array([_KIND_FROM_SCHEMA.get(int(k), 0) for k in feats.kind[keep]], dtype=np.int8)
        report = self.ekf.observe(feats.xy_m[keep], feats.cov_m2[keep], kinds)
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
        if "last_odom_pose" in snap:
            self.last_odom_pose = np.asarray(snap["last_odom_pose"], dtype=float)
        log.info("resumed from %s: scan %d, %d landmarks", path, self.seq, self.ekf.n_landmarks)
        self.counts["restored"] += 1

    def close(self) -> None:
        if self.checkpoint is not None and self.seq:
            self._save(self.checkpoint)


SPEC = ServiceSpec(
    name="slam",
    summary="EKF-SLAM over odometry and corner features; publishes pose, covariance and landmarks.",
    config_type=SlamConfig,
    inputs=(topics.ODOM, topics.FEATURES),
    outputs=(topics.SLAM_STATE,),
    build=lambda cfg, ctx: SlamStep(cfg, ctx),
)
