"""mapper: loop closing behind the EKF — keyframes in a pose graph, closures found by correlative search.

in:  scan           LaserScan (the raw scan: the keyframes' points)
     slam/state     SlamState (the EKF's pose after each scan)
out: map/pose       MapPose (per slam state: the pose corrected by every closure so far)
     map/keyframes  MapKeyframes (after each optimisation and at the end: the optimised keyframes)

The EKF with corner landmarks stays the online estimator; this stage (``lrfslam.algo.loop_closure``)
closes the loops it cannot, from a large prior error. A slam state waits for its scan (or for a newer
scan: its own was lost), so the result does not depend on how the two streams interleave. The final
trajectory of a recording is every slam state placed by the last ``map/keyframes``
(``lrfslam.evaluation.map_trajectory``).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from lrfslam.algo.geometry import compose, polar_to_xy, relative
from lrfslam.algo.loop_closure import LoopClosingMapper, LoopClosureParams
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.runtime.step import Message, Output, RunContext, ServiceSpec, StepBase


@dataclass(frozen=True)
class MapperConfig:
    loop_closure: LoopClosureParams = field(default_factory=LoopClosureParams)
    max_waiting_states: int = 20   # slam states held for their scan at most (then placed without one)


class MapperStep(StepBase):
    def __init__(self, cfg: MapperConfig, ctx: RunContext) -> None:
        super().__init__()
        self.cfg = cfg
        self.mapper = LoopClosingMapper(cfg.loop_closure)
        self.scans: dict[int, tuple[int, np.ndarray]] = {}   # seq -> (stamp, points (N, 2) robot frame)
        self.newest_scan_ns = -1
        self.waiting: deque[t.SlamState] = deque()
        self.seq = 0
        self.keyframes_seq = 0
        self.optimisations = 0
        self._last_stamp = -1   # stamp of the last placed state (none yet)

    def on_message(self, msg: Message):
        v = msg.value
        if msg.topic is topics.SCAN:
            valid = (v.status == t.BEAM_VALID) & np.isfinite(v.ranges_m)
            self.scans[v.seq] = (v.stamp_ns, polar_to_xy(v.ranges_m[valid], v.angles_rad[valid]))
            self.newest_scan_ns = max(self.newest_scan_ns, v.stamp_ns)
        elif msg.topic is topics.SLAM_STATE:
            self.waiting.append(v)
        return self._ready(final=False)

    def finish(self):
        outs = self._ready(final=True)
        if self.mapper.keyframe_count:
            self.mapper.trajectory()   # solves for every closure still pending
            outs.append(self._keyframes(self.waiting[-1].stamp_ns if self.waiting else self._last_stamp))
        return outs

    def _ready(self, final: bool) -> list[Output]:
        outs: list[Output] = []
        while self.waiting:
            state = self.waiting[0]
            have_scan = state.scan_seq in self.scans or self.newest_scan_ns > state.stamp_ns
            if not (have_scan or final or len(self.waiting) > self.cfg.max_waiting_states):
                break
            self.waiting.popleft()
            outs += self._place(state)
        # Scans no newer than the last placed state are never asked for again; and however many
        # scans come without states, no more are kept than states may wait.
        for seq in [q for q, (stamp, _) in self.scans.items() if stamp <= self._last_stamp]:
            del self.scans[seq]
        while len(self.scans) > 2 * self.cfg.max_waiting_states + 2:
            del self.scans[min(self.scans, key=lambda q: (self.scans[q][0], q))]
        return outs

    def _place(self, state: t.SlamState) -> list[Output]:
        entry = self.scans.pop(state.scan_seq, None)
        if entry is None:
            self.counts["scan_missing"] += 1
        points = entry[1] if entry is not None else np.zeros((0, 2))
        pose = self.mapper.add_scan(state.stamp_ns, state.pose, state.pose_cov, points)
        self._last_stamp = state.stamp_ns
        stats = self.mapper.stats
        nis = self.mapper.closure_nis[self.counts["closures_verified"]:]
        self.counts.update(closures_verified=nis.size, closure_nis_milli=int(np.round(1000.0 * nis.sum())))
        self.counts["scans"] += 1
        self.seq += 1
        outs = [Output(topics.MAP_POSE, t.MapPose(
            state.stamp_ns, self.seq, state.scan_seq, pose, compose(pose, relative(state.pose, np.zeros(3))),
            self.mapper.keyframe_count, stats.accepted - stats.removed,
            stats.ambiguous + stats.refine_failed + stats.gated + stats.removed))]
        if stats.optimisations != self.optimisations:
            self.optimisations = stats.optimisations
            outs.append(self._keyframes(state.stamp_ns))
        return outs

    def _keyframes(self, stamp_ns: int) -> Output:
        stamps, slam_poses = self.mapper.keyframe_slam_poses()
        self.keyframes_seq += 1
        self.counts["keyframe_updates"] += 1
        return Output(topics.MAP_KEYFRAMES, t.MapKeyframes(stamp_ns, self.keyframes_seq, stamps, slam_poses,
                                                           self.mapper.keyframe_poses(),
                                                           self.mapper.keyframe_ekf_edges()))

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
    build=lambda cfg, ctx: MapperStep(cfg, ctx),
)
