"""The simulator as a whole: determinism, odometry start and drift, truth bookkeeping."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest

from lrfslam.algo.geometry import compose, from_frame, wrap_angle
from lrfslam.errors import ConfigError
from lrfslam.sim.lidar import LidarModel
from lrfslam.sim.odometry import OdometryNoise
from lrfslam.sim.simulator import SimConfig, Simulator


def _frames(config, n):
    return list(itertools.islice(Simulator(config), n))


def test_same_seed_gives_identical_frames():
    a, b = _frames(SimConfig(seed=7), 60), _frames(SimConfig(seed=7), 60)
    for fa, fb in zip(a, b):
        np.testing.assert_array_equal(fa.scan.ranges_m, fb.scan.ranges_m)
        np.testing.assert_array_equal(fa.scan.spurious, fb.scan.spurious)
        np.testing.assert_array_equal(fa.odom_pose, fb.odom_pose)
        np.testing.assert_array_equal(fa.visible_corner_ids, fb.visible_corner_ids)


def test_different_seeds_give_different_noise_on_the_same_path():
    a, b = _frames(SimConfig(seed=1), 20), _frames(SimConfig(seed=2), 20)
    np.testing.assert_array_equal(a[-1].true_pose, b[-1].true_pose)
    assert not np.array_equal(a[-1].scan.ranges_m, b[-1].scan.ranges_m)
    assert not np.array_equal(a[-1].odom_pose, b[-1].odom_pose)


def test_scan_model_does_not_change_the_odometry_stream():
    quiet = SimConfig(seed=3, lidar=LidarModel(range_sigma_m=0.0, mixed_pixel_prob=0.0, dropout_prob=0.5))
    a, b = _frames(SimConfig(seed=3), 30), _frames(quiet, 30)
    np.testing.assert_array_equal(a[-1].odom_pose, b[-1].odom_pose)


def test_time_index_and_start_pose():
    frames = _frames(SimConfig(rate_hz=10.0), 25)
    assert [f.index for f in frames] == list(range(25))
    np.testing.assert_allclose([f.t_s for f in frames], np.arange(25) / 10.0)
    np.testing.assert_array_equal(frames[0].odom_pose, frames[0].true_pose)
    np.testing.assert_array_equal(frames[0].odom_delta, 0.0)
    # 0.5 m/s along the first straight, heading east.
    np.testing.assert_allclose(frames[20].true_pose - frames[0].true_pose, [1.0, 0.0, 0.0], atol=1e-12)


def test_odometry_is_exact_without_noise_and_drifts_with_it():
    exact = _frames(SimConfig(odometry=OdometryNoise(0.0, 0.0, 0.0)), 400)
    err = np.array([f.odom_pose - f.true_pose for f in exact])
    np.testing.assert_allclose(err[:, :2], 0.0, atol=1e-9)
    np.testing.assert_allclose(wrap_angle(err[:, 2]), 0.0, atol=1e-9)

    noisy = _frames(SimConfig(seed=5), 400)
    drift = np.array([np.hypot(*(f.odom_pose[:2] - f.true_pose[:2])) for f in noisy])
    assert drift[-1] > 0.0 and drift[:50].max() < drift[350:].max()


def test_odom_delta_chains_into_odom_pose():
    frames = _frames(SimConfig(seed=9), 40)
    pose = frames[0].odom_pose
    for f in frames[1:]:
        pose = compose(pose, f.odom_delta)
    np.testing.assert_allclose(pose, frames[-1].odom_pose, atol=1e-12)


def test_visible_corners_robot_xy_maps_back_to_the_map():
    sim = Simulator(SimConfig())
    seen = 0
    for f in itertools.islice(sim, 0, 1200, 40):
        xy = sim.map_corners.xy_m[f.visible_corner_ids]
        np.testing.assert_allclose(from_frame(f.visible_corners_robot_xy, f.true_pose), xy, atol=1e-9)
        seen += len(xy)
    assert seen > 30
    assert len(sim.map_corners) == 96 and sim.world.name == "hallway_loop"


def test_unknown_world_is_a_config_error():
    with pytest.raises(ConfigError):
        Simulator(dataclasses.replace(SimConfig(), world_name="atlantis"))


def test_range_bias_is_drawn_once_per_run():
    lidar = LidarModel(range_sigma_m=0.0, quantum_m=0.0, mixed_pixel_prob=0.0, range_bias_sigma_m=0.02)
    frames = _frames(SimConfig(seed=11, lidar=lidar), 30)
    offsets = []
    for f in frames:
        finite = np.isfinite(f.scan.true_ranges_m) & np.isfinite(f.scan.ranges_m)
        offsets.append(f.scan.ranges_m[finite] - f.scan.true_ranges_m[finite])
    offsets = np.concatenate(offsets)
    assert offsets[0] != 0.0
    np.testing.assert_allclose(offsets, offsets[0], atol=1e-12)
    biases = [Simulator(SimConfig(seed=s, lidar=lidar)).range_bias_m for s in range(200)]
    assert np.std(biases) == pytest.approx(0.02, rel=0.2)
