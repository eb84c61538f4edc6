"""Systematic odometry error: calibration scale errors, curve, slip, and the drift they give."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lrfslam.algo.geometry import compose, relative
from lrfslam.errors import ConfigError
from lrfslam.sim.floor_plans import waypoints
from lrfslam.sim.odometry import (
    CALIBRATED,
    REALISTIC,
    OdometryNoise,
    SystematicOdometryError,
    biased_increment,
    integrate_odometry,
    noisy_increment,
)
from lrfslam.sim.simulator import SimConfig, Simulator
from lrfslam.sim.trajectory import LoopTrajectory, loop_path

EXACT = OdometryNoise(0.0, 0.0, 0.0)


def _straight_steps(length_m, step_m=0.05):
    return np.tile([step_m, 0.0, 0.0], (round(length_m / step_m), 1))


def _measure(increments, error, seed=0):
    rng = np.random.default_rng(seed)
    return np.array([biased_increment(d, error, rng) for d in increments])


def test_calibrated_leaves_every_increment_exact():
    rng = np.random.default_rng(0)
    for delta in ([0.05, 0.0, 0.0], [0.04, 0.01, 0.06], [0.0, 0.0, -0.1], [0.0, 0.0, 0.0]):
        np.testing.assert_array_equal(biased_increment(delta, CALIBRATED, rng), delta)


@settings(max_examples=30, deadline=None)
@given(k=st.floats(-0.1, 0.1))
def test_a_wheel_radius_error_of_k_gives_k_distance_error_on_a_straight_line(k):
    steps = _straight_steps(10.0)
    end = integrate_odometry([0.0, 0.0, 0.0], _measure(steps, SystematicOdometryError(distance_scale=k)))[-1]
    np.testing.assert_allclose(end, [10.0 * (1.0 + k), 0.0, 0.0], atol=1e-9)


@settings(max_examples=30, deadline=None)
@given(k=st.floats(-0.1, 0.1), turn=st.floats(-np.pi, np.pi))
def test_a_wheelbase_error_of_k_gives_k_rotation_error(k, turn):
    steps = np.tile([0.0, 0.0, turn / 50.0], (50, 1))
    measured = _measure(steps, SystematicOdometryError(rotation_scale=k))
    assert measured[:, 2].sum() == pytest.approx(turn * (1.0 + k), abs=1e-12)
    np.testing.assert_array_equal(measured[:, :2], 0.0)


def test_unequal_wheels_report_a_straight_line_as_an_arc():
    c = 0.002
    end = integrate_odometry([0.0, 0.0, 0.0], _measure(_straight_steps(20.0), SystematicOdometryError(
        heading_drift_rad_per_m=c)))[-1]
    assert end[2] == pytest.approx(20.0 * c)
    # An arc of curvature c and length 20 m: it bends left by about c * 20^2 / 2.
    assert end[1] == pytest.approx(c * 20.0**2 / 2.0, rel=0.01)


def test_slip_comes_in_bursts_at_the_given_rate_and_always_over_reports_distance():
    error = SystematicOdometryError(slip_rate_per_m=0.1, slip_trans_sigma_m=0.2, slip_rot_sigma_rad=0.05)
    steps = _straight_steps(2000.0)
    measured = _measure(steps, error, seed=4)
    extra = measured[:, 0] - steps[:, 0]
    slipped = (extra > 1e-12) | (measured[:, 2] != 0.0)
    # Poisson: 200 expected events in 2000 m; ±4 sigma.
    assert 200 - 4 * np.sqrt(200) < slipped.sum() < 200 + 4 * np.sqrt(200)
    assert np.all(extra >= -1e-15)
    assert np.mean(extra[slipped]) == pytest.approx(0.2 * np.sqrt(2.0 / np.pi), rel=0.2)
    assert np.std(measured[slipped, 2]) == pytest.approx(0.05, rel=0.2)


def test_every_call_draws_the_same_from_the_stream():
    a, b = np.random.default_rng(9), np.random.default_rng(9)
    biased_increment([0.05, 0.0, 0.0], CALIBRATED, a)
    biased_increment([0.05, 0.0, 0.0], REALISTIC, b)
    assert a.random() == b.random()


def test_bad_parameters_are_rejected():
    with pytest.raises(ConfigError):
        SystematicOdometryError(slip_rate_per_m=-1.0)
    with pytest.raises(ConfigError):
        SystematicOdometryError(distance_scale=-1.0)


def test_hallway_odometry_is_what_it_was_before_systematic_errors():
    # Oracle: the odometry stream as the simulator drew it before (random walks on the
    # second spawned generator, nothing else), so figures from older commits still hold.
    sim = Simulator(SimConfig(seed=11))
    frames = list(itertools.islice(sim, 300))
    _, odom_rng = np.random.default_rng(11).spawn(2)
    pose = frames[0].true_pose
    for prev, f in itertools.pairwise(frames):
        pose = compose(pose, noisy_increment(relative(prev.true_pose, f.true_pose), OdometryNoise(), odom_rng))
        np.testing.assert_array_equal(f.odom_pose, pose)


def _lap_drift(error, noise, seed):
    """Odometry position error (m) along one lap of large_building, sampled every step."""
    traj = LoopTrajectory(loop_path(waypoints("large_building"), 0.8))
    true = traj.pose(np.arange(int(traj.path.total_length_m / 0.05)))
    slip_rng, odom_rng = np.random.default_rng(seed).spawn(2)
    deltas = [noisy_increment(biased_increment(relative(a, b), error, slip_rng), noise, odom_rng)
              for a, b in itertools.pairwise(true)]
    odom = integrate_odometry(true[0], deltas)
    return np.hypot(*(odom[:, :2] - true[:, :2]).T)


def test_realistic_robot_drifts_metres_before_the_first_revisit_of_the_large_building():
    revisit = int(156.0 / 0.05)  # the outer loop
    # Calibration errors alone, no random walk: deterministic apart from slip.
    alone = np.array([_lap_drift(REALISTIC, EXACT, seed)[revisit] for seed in range(5)])
    assert np.all(alone > 3.0)
    with_walks = np.array([_lap_drift(REALISTIC, OdometryNoise(), seed)[revisit] for seed in range(5)])
    assert np.median(with_walks) > 3.0
    calibrated = np.array([_lap_drift(CALIBRATED, OdometryNoise(), seed)[revisit] for seed in range(5)])
    assert np.median(with_walks) > 2.0 * np.median(calibrated)


def test_large_building_takes_its_realistic_preset_unless_the_config_says_otherwise():
    assert Simulator(SimConfig(world_name="large_building")).odometry_error == REALISTIC
    assert Simulator(SimConfig(world_name="hallway_loop")).odometry_error == CALIBRATED
    chosen = SystematicOdometryError(distance_scale=0.05)
    assert Simulator(SimConfig(world_name="hallway_loop", odometry_error=chosen)).odometry_error == chosen
    exact = Simulator(SimConfig(world_name="large_building", odometry=EXACT, odometry_error=CALIBRATED))
    f = list(itertools.islice(exact, 200))[-1]
    np.testing.assert_allclose(f.odom_pose, f.true_pose, atol=1e-9)
