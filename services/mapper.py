"""mapper: loop closing behind the EKF — keyframes in a pose graph, closures found by correlative search.

in:  scan           LaserScan (the raw scan: the keyframes' points)
     slam/state     SlamState (the EKF's pose after each scan)
out: map/pose       MapPose (per slam state: the pose corrected by every closure so far)
     map/keyframes  MapKeyframes (after each optimisation and at the end: the graph's optimised
                    keyframes, and those retired from it since the last, once)

The EKF with corner landmarks stays the online estimator; this stage (``lrfslam.algo.loop_closure``)
closes the loops it cannot, from a large prior error. The EKF's pose of each scan tells the closure
search where else to look: after a long loop the EKF, having re-observed its landmarks, may know
where the robot is when the mapper's chain of motions has drifted beyond its search window. A slam state waits for its scan (or for a newer
scan: its own was lost), so the result does not depend on how the two streams interleave. The final
trajectory of a recording is every slam state placed by the last ``map/keyframes``
(``lrfslam.evaluation.map_trajectory``).

The step is :class:`Resumable`: where the runtime keeps checkpoints (``bus.checkpoint_dir``,
``lrfslam.runtime.checkpoints``) a restarted mapper continues its graph. The local trajectory is the chain of the
states' motions; where that chain breaks (a state number skipped: states lost, this stage or the slam
stage restarted) the filter's own pose change bridges the gap, taken as the motion across it: the
closures that follow correct what the filter got wrong meanwhile.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from lrfslam.algo import kernels
from lrfslam.algo.geometry import compose, polar_to_xy, relative
from lrfslam.algo.loop_closure import LoopClosingMapper, LoopClosureParams
from lrfslam.algo.stream_alignment import AlignmentParams, StreamAligner
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.runtime.step import Message, Output, RunContext, ServiceSpec, StepBase

log = logging.getLogger("lrfslam.mapper")

#: Slam states held for their scan at most, then placed without one (a lost scan must not hold
#: the map back: 2 s at the LMS200's 10 Hz).
MAX_WAITING_STATES = 20


@dataclass(frozen=True)
class MapperConfig:
    """The mapper stage's configuration; ``SETTINGS`` are the names an operator sets (docs/settings.md)."""

    loop_closure: LoopClosureParams = field(default_factory=LoopClosureParams)

    SETTINGS: ClassVar[tuple[str, ...]] = (
        *(f"loop_closure.{name}" for name in (
            "keyframe_trans_m", "keyframe_rot_rad", "max_range_m", "min_travel_m", "candidate_radius_m",
            "max_window_m", "min_score", "max_second_ratio", "gate_chi2", "match_cov_scale",
            "odom_trans_sigma_per_m", "odom_rot_sigma_per_m", "odom_rot_sigma_per_rad",
            "fold_revisits", "fold_after_keyframes", "correlative.cell_m")),
    )
    RETIRED: ClassVar[dict[str, str]] = {
        "checkpoint_path": "the runtime keeps every stage's checkpoint: bus.checkpoint_dir (<dir>/mapper.checkpoint.npz)",
        "checkpoint_every_keyframes": "the runtime saves every bus.checkpoint_period_s of data time",
        "max_waiting_states": f"fixed at {MAX_WAITING_STATES} (services/mapper.py MAX_WAITING_STATES)",
        "local_trajectory": "the local trajectory is always the chain of the slam's motions (slam_motion)",
        "loop_closure.drift_scale": "replaced by the drift model (loop_closure.odom_*); 1 did nothing",
        "loop_closure.interpolate": "always on: each scan is placed between its keyframes",
    }


class MapperStep(StepBase):
    def __init__(self, cfg: MapperConfig, ctx: RunContext) -> None:
        super().__init__()
        self.cfg = cfg
        kernels.prepare()
        self.mapper = LoopClosingMapper(cfg.loop_closure, keep_scans=False)
        # A slam state waits for its scan as features do in the slam stage (no odometry here).
        self.align: StreamAligner[t.SlamState] = StreamAligner(AlignmentParams(
            wait_for_odometry=False, max_wait=MAX_WAITING_STATES, scans_optional=False))
        self.seq = 0
        self.keyframes_seq = 0
        self.optimisations = 0
        self._last_stamp = 0
        self._local: np.ndarray | None = None   # the last state's pose on the local trajectory
        self._last_slam_pose = np.zeros(3)
        self._last_state_seq = -1   # the last state's number; -1: none yet

    def on_message(self, msg: Message):
        v = msg.value
        if msg.topic is topics.SCAN:
            valid = (v.status == t.BEAM_VALID) & np.isfinite(v.ranges_m)
            self.align.add_scan(v.seq, v.stamp_ns, polar_to_xy(v.ranges_m[valid], v.angles_rad[valid]))
        elif msg.topic is topics.SLAM_STATE:
            self.align.add_features(v.stamp_ns, v.scan_seq, v)
        return [out for a in self.align.ready() for out in self._place(a.features, a.scan_xy_m)]

    def finish(self):
        outs = [out for a in self.align.ready(final=True) for out in self._place(a.features, a.scan_xy_m)]
        if self.mapper.keyframe_count:
            self.mapper.solve()   # every closure still pending
            outs.append(self._keyframes(self._last_stamp))
        return outs

    def _place(self, state: t.SlamState, points: np.ndarray | None) -> list[Output]:
        if points is None:
            self.counts["scan_missing"] += 1
            points = np.zeros((0, 2))
        local, reference = self._local_pose(state)
        pose = self.mapper.add_scan(state.stamp_ns, local, points, reference, online_pose=state.pose)
        self._last_stamp = state.stamp_ns
        stats = self.mapper.stats
        verified, nis_sum = self.mapper.closure_nis
        self.counts["closures_verified"] = verified
        self.counts["closure_nis_milli"] = round(1000.0 * nis_sum)
        self.counts["scans"] += 1
        self.seq += 1
        rejected = stats.ambiguous + stats.refine_failed + stats.gated + stats.removed
        outs = [Output(topics.MAP_POSE, t.MapPose(
            stamp_ns=state.stamp_ns, seq=self.seq, scan_seq=state.scan_seq, pose=pose,
            map_from_slam=compose(pose, relative(state.pose, np.zeros(3))), keyframes=self.mapper.keyframe_count,
            closures=stats.accepted - stats.removed, closures_rejected=rejected, local_pose=local))]
        if stats.optimisations != self.optimisations:
            self.optimisations = stats.optimisations
            outs.append(self._keyframes(state.stamp_ns))
        return outs

    def _local_pose(self, state: t.SlamState) -> tuple[np.ndarray, np.ndarray | None]:
        """The state's pose on the local trajectory (the chain of the motions that moved the filter), (3,), and the step the
        mapper checks it against for jumps (3,): the scan-matched motion; None if there is none."""
        matched = state.motion if state.motion is not None and state.motion_matched else None
        if self._local is None:
            local, reference = state.pose, matched   # (a chain starts where the filter does)
        elif state.motion is None:
            # A slam state recorded before they carried their motion: follow the filter's pose.
            self.counts["motion_missing"] += 1
            local, reference = compose(self._local, relative(self._last_slam_pose, state.pose)), None
        elif state.seq != self._last_state_seq + 1:
            # States missed (this stage or the slam stage restarted, or lost): the motion is from a
            # state this stage never saw. The filter's own pose change bridges the gap; it is
            # trusted as it stands, because the keyframes' scans cannot check a step metres long.
            self.counts["motion_bridged"] += 1
            bridge = relative(self._last_slam_pose, state.pose)
            local, reference = compose(self._local, bridge), bridge
        else:
            local, reference = compose(self._local, state.motion), matched
        self._local, self._last_slam_pose, self._last_state_seq = local, state.pose, state.seq
        return local, reference

    def _keyframes(self, stamp_ns: int) -> Output:
        stamps, local_poses = self.mapper.keyframe_stamped_local_poses()
        retired = self.mapper.take_retired()   # told once: a reader of the whole run keeps them
        self.keyframes_seq += 1
        self.counts["keyframe_updates"] += 1
        self.counts["keyframes_retired"] += len(retired)
        return Output(topics.MAP_KEYFRAMES, t.MapKeyframes(
            stamp_ns=stamp_ns, seq=self.keyframes_seq, scan_stamp_ns=stamps, local_pose=local_poses,
            map_pose=self.mapper.keyframe_poses(), local_edge=self.mapper.keyframe_local_edges(),
            retired_scan_stamp_ns=retired.stamp_ns, retired_local_pose=retired.local_pose,
            retired_local_edge=retired.local_edge, retired_anchor_stamp_ns=retired.anchor_stamp_ns,
            retired_offset=retired.offset))

    def snapshot(self) -> dict | None:
        """The pose graph with its keyframes' points, and where the streams stood; None before the first keyframe."""
        if not self.mapper.keyframe_count:
            return None
        arrays = self.mapper.snapshot()
        arrays.update(service_seq=self.seq, service_keyframes_seq=self.keyframes_seq,
                      service_last_stamp_ns=self._last_stamp, service_last_state_seq=self._last_state_seq,
                      service_local_pose=np.full(3, np.nan) if self._local is None else self._local,
                      service_last_slam_pose=self._last_slam_pose)
        return arrays

    def restore(self, arrays) -> str:
        mapper = LoopClosingMapper.restore(self.cfg.loop_closure, arrays)
        local = np.array(arrays["service_local_pose"], dtype=float).reshape(3)
        last_slam_pose = np.array(arrays["service_last_slam_pose"], dtype=float).reshape(3)
        counters = [int(arrays[k]) for k in ("service_seq", "service_keyframes_seq", "service_last_stamp_ns",
                                             "service_last_state_seq")]
        self.mapper = mapper
        self.seq, self.keyframes_seq, self._last_stamp, self._last_state_seq = counters
        self._local = None if np.any(np.isnan(local)) else local
        self._last_slam_pose = last_slam_pose
        self.optimisations = mapper.stats.optimisations
        return f"{mapper.keyframe_count} keyframes, {mapper.stats.accepted - mapper.stats.removed} closures"

    def health(self) -> tuple[int, str]:
        s = self.mapper.stats
        return t.HEALTH_OK, f"{self.mapper.keyframe_count} keyframes, {s.accepted - s.removed} closures"


SPEC = ServiceSpec(
    name="mapper",
    summary="Loop closing behind the EKF: keyframes in a pose graph, closures by correlative search; "
            "publishes the corrected pose per scan and the optimised keyframes.",
    config_type=MapperConfig,
    inputs=(topics.SCAN, topics.SLAM_STATE),
    outputs=(topics.MAP_POSE, topics.MAP_KEYFRAMES),
    latest=(topics.MAP_POSE, topics.MAP_KEYFRAMES),
    skippable=(topics.SCAN, topics.SLAM_STATE),
    # An optimisation holds the mapper up to a second now and then (docs/delivery.md); it catches up
    # within milliseconds after, so it skips only when behind for longer than that.
    max_lag_s=1.0,
    build=lambda cfg, ctx: MapperStep(cfg, ctx),
)
