"""The mapper step: slam states placed with their scans, map/pose per state, map/keyframes that
reproduce the mapper's own final trajectory from a recording."""

from __future__ import annotations

import numpy as np
import pytest
from lrfslam.services import build_step

from lrfslam.algo.geometry import compose
from lrfslam.evaluation.map_trajectory import final_poses
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.runtime.step import Message, Output
from lrfslam.sim.simulator import OdometryNoise, SimConfig, Simulator

msg = Message.of


def drifting_loop(n: int):
    """(scan, slam state) per frame of the hallway loop, the 'slam' pose being drifting odometry."""
    cfg = SimConfig(speed_mps=1.0, rate_hz=5.0, seed=3,
                    odometry=OdometryNoise(trans_sigma_per_m=0.02, rot_sigma_per_rad=0.03, rot_sigma_per_m_rad=0.02))
    lidar = cfg.lidar
    out = []
    for frame, _ in zip(Simulator(cfg), range(n), strict=False):
        stamp, seq = round(frame.t_s * 1e9), frame.index + 1
        scan = t.LaserScan.from_ranges(stamp, seq, frame.scan.ranges_m, lidar.angle_min_rad,
                                       lidar.angle_increment_rad, lidar.max_range_m)
        state = t.SlamState(stamp, seq, seq, frame.odom_pose, np.eye(3) * 1e-4)
        out.append((scan, state, frame.true_pose))
    return out


@pytest.fixture(scope="module")
def mapped():
    frames = drifting_loop(620)   # two laps of the 62 m loop
    step = build_step("mapper")
    outs = []
    for scan, state, _ in frames:
        outs += step.on_message(msg(Output(topics.SCAN, scan)))
        outs += step.on_message(msg(Output(topics.SLAM_STATE, state)))
    outs += step.finish()
    return frames, step, outs


def test_every_state_gets_a_map_pose_and_the_closures_are_published(mapped):
    frames, step, outs = mapped
    poses = [o.value for o in outs if o.topic is topics.MAP_POSE]
    assert [p.scan_seq for p in poses] == [s.scan_seq for _, s, _ in frames]
    for p, (_, state, _) in zip(poses, frames, strict=True):
        np.testing.assert_allclose(compose(p.map_from_slam, state.pose), p.pose, atol=1e-9)
    assert poses[-1].closures >= 5 and step.counts.get("scan_missing", 0) == 0
    assert sum(o.topic is topics.MAP_KEYFRAMES for o in outs) >= 2   # after optimisations, and at the end
    nis = step.mapper.closure_nis
    assert step.counts["closures_verified"] == nis.size >= step.mapper.stats.accepted
    assert np.all(nis >= 0) and step.counts["closure_nis_milli"] == pytest.approx(1000 * nis.sum(), abs=nis.size)


def test_the_last_keyframes_reproduce_the_mappers_final_trajectory(mapped):
    frames, step, outs = mapped
    last = [o.value for o in outs if o.topic is topics.MAP_KEYFRAMES][-1]
    stamps = np.array([s.stamp_ns for _, s, _ in frames])
    from_recording = final_poses(stamps, np.array([s.pose for _, s, _ in frames]), last)
    own_stamps, own = step.mapper.trajectory()
    np.testing.assert_array_equal(own_stamps, stamps)
    np.testing.assert_allclose(from_recording, own, atol=1e-9)
    # And it is better than the drifting input, against the truth.
    truth = np.array([tp for _, _, tp in frames])
    drift = np.hypot(*(np.array([s.pose for _, s, _ in frames])[:, :2] - truth[:, :2]).T)
    final = np.hypot(*(own[:, :2] - truth[:, :2]).T)
    assert drift.max() > 1.0 and final.max() < 0.5 * drift.max()


def test_a_state_waits_for_its_scan_and_one_without_a_scan_is_placed_when_a_newer_scan_comes():
    frames = drifting_loop(6)
    step = build_step("mapper")
    (scan1, state1, _), (_, state2, _), (scan3, state3, _) = frames[:3]   # scan 2 is lost
    assert step.on_message(msg(Output(topics.SLAM_STATE, state1))) == []   # its scan is not there yet
    placed = step.on_message(msg(Output(topics.SCAN, scan1)))
    assert [o.value.scan_seq for o in placed if o.topic is topics.MAP_POSE] == [1]
    # scan 2 is lost: its state is placed once scan 3 shows it will not come.
    assert step.on_message(msg(Output(topics.SLAM_STATE, state2))) == []
    placed = step.on_message(msg(Output(topics.SCAN, scan3)))
    assert [o.value.scan_seq for o in placed if o.topic is topics.MAP_POSE] == [2]
    assert step.counts["scan_missing"] == 1
    placed = step.on_message(msg(Output(topics.SLAM_STATE, state3)))
    assert [o.value.scan_seq for o in placed if o.topic is topics.MAP_POSE] == [3]
