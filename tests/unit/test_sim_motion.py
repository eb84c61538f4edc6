"""Loop trajectory geometry and the odometry error model."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lrfslam.algo.geometry import relative, wrap_angle
from lrfslam.errors import ConfigError
from lrfslam.sim.floor_plans import hallway_loop, hallway_loop_path
from lrfslam.sim.odometry import OdometryNoise, integrate_odometry, noisy_increment
from lrfslam.sim.trajectory import LoopTrajectory, loop_path

SQUARE = np.array([(2.0, 0.0), (4.0, 0.0), (4.0, 4.0), (0.0, 4.0), (0.0, 0.0)])


def _hallway_trajectory(**kw):
    return LoopTrajectory(loop_path(hallway_loop_path(), 0.8), **kw)


def _point_segment_distance(points, seg):
    a, b = seg[None, :, :2], seg[None, :, 2:]
    p = points[:, None, :]
    ab = b - a
    u = np.clip(np.sum((p - a) * ab, axis=-1) / np.sum(ab * ab, axis=-1), 0.0, 1.0)
    return np.hypot(*(p - (a + u[..., None] * ab)).transpose(2, 0, 1))


def test_square_loop_length_is_lines_plus_quarter_circles():
    r = 0.5
    path = loop_path(SQUARE, r)
    assert path.total_length_m == pytest.approx(4 * (4.0 - 2 * r) + 2 * np.pi * r)
    np.testing.assert_allclose(path.pose_at(0.0), [2.0, 0.0, 0.0], atol=1e-12)


def test_path_is_continuous_and_tangent_everywhere():
    path = loop_path(SQUARE, 0.5)
    s = np.linspace(0.0, path.total_length_m, 4001)
    p = path.pose_at(s)
    step = np.diff(p[:, :2], axis=0)
    ds = s[1] - s[0]
    # Chord never exceeds arc length, and only just falls short of it on the arcs.
    chord = np.hypot(step[:, 0], step[:, 1])
    assert np.all(chord <= ds + 1e-12) and np.all(chord >= ds * (1 - 1e-4))
    travel_dir = np.arctan2(step[:, 1], step[:, 0])
    mid_heading = p[:-1, 2] + wrap_angle(p[1:, 2] - p[:-1, 2]) / 2
    # Exact on lines and arcs; a step straddling a line/arc joint is off by under ds * curvature.
    assert np.max(np.abs(wrap_angle(travel_dir - mid_heading))) < ds * 2.0
    np.testing.assert_allclose(path.pose_at(path.total_length_m), path.pose_at(0.0), atol=1e-12)


def test_turn_rate_is_bounded_and_steps_have_constant_length():
    traj = _hallway_trajectory(speed_mps=0.5, rate_hz=10.0)
    assert traj.max_turn_rate_rad_s == pytest.approx(0.5 / 0.8)
    poses = traj.pose(np.arange(1300))
    dtheta = np.abs(wrap_angle(np.diff(poses[:, 2])))
    assert dtheta.max() <= traj.max_turn_rate_rad_s / 10.0 + 1e-12
    assert dtheta.max() > 0.5 * traj.max_turn_rate_rad_s / 10.0  # it does turn
    step = np.hypot(*np.diff(poses[:, :2], axis=0).T)
    assert np.all(step <= 0.05 + 1e-12) and np.all(step > 0.049)


def test_trajectory_keeps_half_a_metre_from_every_wall():
    traj = _hallway_trajectory()
    n_lap = int(np.ceil(traj.path.total_length_m / 0.05))
    poses = traj.pose(np.arange(n_lap))
    clearance = _point_segment_distance(poses[:, :2], hallway_loop().segments_m).min(axis=1)
    assert clearance.min() >= 0.5


def test_laps_repeat_and_iteration_is_endless():
    traj = LoopTrajectory(loop_path(SQUARE, 0.5), speed_mps=1.0, rate_hz=1.0)
    lap = traj.path.total_length_m
    np.testing.assert_allclose(traj.path.pose_at(3.3 + 5 * lap), traj.path.pose_at(3.3), atol=1e-9)
    it = iter(traj)
    poses = [next(it) for _ in range(int(3 * lap) + 2)]
    np.testing.assert_allclose(poses[7], traj.pose(7))


@pytest.mark.parametrize(
    "waypoints, radius",
    [
        (SQUARE[:2], 0.5),  # too few
        (np.array([(0, 0), (0, 0), (1, 1)]), 0.5),  # coincident
        (np.array([(0, 0), (4, 0), (4, 4), (0, 4)]), 2.5),  # arcs do not fit
        (np.array([(0, 0), (4, 0), (0, 0.01)]), 0.1),  # reverses
        (SQUARE, 0.0),
    ],
)
def test_bad_paths_are_config_errors(waypoints, radius):
    with pytest.raises(ConfigError):
        loop_path(waypoints, radius)


def test_bad_speed_is_a_config_error():
    with pytest.raises(ConfigError):
        LoopTrajectory(loop_path(SQUARE, 0.5), speed_mps=0.0)


# --- odometry ------------------------------------------------------------------------


def test_zero_noise_odometry_reproduces_the_trajectory():
    traj = _hallway_trajectory()
    true = traj.pose(np.arange(600))
    rng = np.random.default_rng(0)
    zero = OdometryNoise(0.0, 0.0, 0.0)
    deltas = [noisy_increment(relative(a, b), zero, rng) for a, b in itertools.pairwise(true)]
    odom = integrate_odometry(true[0], deltas)
    np.testing.assert_allclose(odom[:, :2], true[:, :2], atol=1e-9)
    np.testing.assert_allclose(wrap_angle(odom[:, 2] - true[:, 2]), 0.0, atol=1e-9)


def _straight_run_errors(noise, n_runs, n_steps, step_m, seed):
    rng = np.random.default_rng(seed)
    finals = []
    for _ in range(n_runs):
        deltas = [noisy_increment((step_m, 0.0, 0.0), noise, rng) for _ in range(n_steps)]
        finals.append(integrate_odometry((0.0, 0.0, 0.0), deltas)[-1])
    finals = np.array(finals)
    return finals - (n_steps * step_m, 0.0, 0.0)


@pytest.mark.parametrize("n_steps", [4, 40])
def test_translation_drift_is_a_random_walk_independent_of_the_step_size(n_steps):
    noise = OdometryNoise(trans_sigma_per_sqrt_m=0.02, rot_sigma_per_sqrt_rad=0.0, rot_sigma_per_sqrt_m=0.0)
    err = _straight_run_errors(noise, n_runs=400, n_steps=n_steps, step_m=4.0 / n_steps, seed=n_steps)
    assert np.std(err[:, 0]) == pytest.approx(0.02 * np.sqrt(4.0), rel=0.15)
    np.testing.assert_allclose(err[:, 1:], 0.0, atol=1e-12)


def test_heading_drift_from_turning_in_place():
    noise = OdometryNoise(trans_sigma_per_sqrt_m=0.0, rot_sigma_per_sqrt_rad=0.02, rot_sigma_per_sqrt_m=0.0)
    rng = np.random.default_rng(4)
    step = 2 * np.pi / 36
    errs = [sum(noisy_increment((0.0, 0.0, step), noise, rng)[2] - step for _ in range(36)) for _ in range(400)]
    assert np.std(errs) == pytest.approx(0.02 * np.sqrt(2 * np.pi), rel=0.15)


def test_position_drift_grows_with_distance():
    err_short = _straight_run_errors(OdometryNoise(), n_runs=200, n_steps=20, step_m=0.25, seed=1)
    err_long = _straight_run_errors(OdometryNoise(), n_runs=200, n_steps=80, step_m=0.25, seed=2)
    rms_short = np.sqrt(np.mean(np.sum(err_short[:, :2] ** 2, axis=1)))
    rms_long = np.sqrt(np.mean(np.sum(err_long[:, :2] ** 2, axis=1)))
    # Heading noise makes the lateral error grow faster than sqrt(distance).
    assert rms_long > 2.0 * rms_short


@settings(max_examples=30, deadline=None)
@given(
    dx=st.floats(-0.5, 0.5),
    dy=st.floats(-0.5, 0.5),
    dtheta=st.floats(-0.5, 0.5),
    seed=st.integers(0, 2**32 - 1),
)
def test_increment_noise_keeps_direction_and_is_reproducible(dx, dy, dtheta, seed):
    a = noisy_increment((dx, dy, dtheta), OdometryNoise(), np.random.default_rng(seed))
    b = noisy_increment((dx, dy, dtheta), OdometryNoise(), np.random.default_rng(seed))
    np.testing.assert_array_equal(a, b)
    # Translation noise acts along the motion: the measured step is parallel to the true one.
    assert abs(a[0] * dy - a[1] * dx) <= 1e-12


def test_negative_sigma_is_a_config_error():
    with pytest.raises(ConfigError):
        OdometryNoise(trans_sigma_per_sqrt_m=-0.1)
