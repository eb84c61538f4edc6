"""The motion that moves the filter between scans (algo.motion_source): scan-matched, else odometry."""

from __future__ import annotations

import numpy as np

from lrfslam.algo.ekf_slam import EkfParams, EkfSlam
from lrfslam.algo.geometry import compose, polar_to_xy, relative
from lrfslam.algo.motion_source import MotionParams, MotionSource
from lrfslam.sim.floor_plans import build_world
from lrfslam.sim.lidar import LidarModel, simulate_scan

EXACT = LidarModel(range_sigma_m=0.0, quantum_m=0.0, mixed_pixel_prob=0.0)
HALL = build_world("hallway_loop")
START = np.array([16.0, -0.5, 0.6])   # a corner of the loop: walls in two directions
ODOM_COV = EkfSlam(EkfParams()).odometry_cov


def scan_at(pose: np.ndarray) -> np.ndarray:
    scan = simulate_scan(HALL, pose, EXACT, np.random.default_rng(0))
    keep = np.isfinite(scan.ranges_m)
    return polar_to_xy(scan.ranges_m[keep], scan.angles_rad[keep])


def test_without_scan_matching_the_motion_is_the_odometry_increment():
    src = MotionSource(MotionParams(scan_matching=False))
    p0, p1 = np.array([1.0, 2.0, 0.3]), np.array([1.5, 2.1, 0.35])
    first = src.next(p0, None, ODOM_COV)
    assert first.increment is None and first.events == ()
    second = src.next(p1, None, ODOM_COV)
    np.testing.assert_array_equal(second.increment, relative(p0, p1))
    assert second.cov is None    # the filter's own odometry model
    assert src.next(None, None, ODOM_COV).events == ("no_odometry",)
    np.testing.assert_array_equal(src.last_odom_pose, p1)


def test_scan_matching_recovers_the_true_motion_from_poor_odometry():
    src = MotionSource(MotionParams())
    true_step = np.array([0.10, 0.02, 0.03])
    truth, odom = START, START.copy()
    first = src.next(odom, scan_at(truth), ODOM_COV)
    assert first.increment is None and first.events == ("match_no_reference",)
    for _ in range(3):
        truth = compose(truth, true_step)
        odom = compose(odom, true_step * [1.3, 0.0, 0.5])   # odometry off by 30 % and half the turn
        m = src.next(odom, scan_at(truth), ODOM_COV)
        assert m.events == ("match_ok",)
        np.testing.assert_allclose(m.increment, true_step, atol=2e-3)
        np.testing.assert_allclose(m.cov, m.cov.T)
        assert np.linalg.eigvalsh(m.cov).min() > -1e-15   # noiseless scans: nearly singular, never negative


def test_a_lost_scan_falls_back_to_odometry():
    src = MotionSource(MotionParams())
    p0, p1 = START, compose(START, [0.1, 0.0, 0.0])
    src.next(p0, scan_at(p0), ODOM_COV)
    m = src.next(p1, None, ODOM_COV)
    assert m.events == ("scan_missing",) and m.cov is None
    np.testing.assert_array_equal(m.increment, relative(p0, p1))


def test_without_odometry_only_a_match_moves_the_filter():
    src = MotionSource(MotionParams())
    assert src.next(None, scan_at(START), ODOM_COV).increment is None
    m = src.next(None, scan_at(compose(START, [0.05, 0.0, 0.0])), ODOM_COV)
    assert m.events == ("no_odometry", "match_ok")
    np.testing.assert_allclose(m.increment, [0.05, 0.0, 0.0], atol=2e-3)
    lost = src.next(None, None, ODOM_COV)
    assert lost.increment is None and lost.events == ("no_odometry", "scan_missing")


def test_resumed_the_next_motion_is_odometry_from_the_saved_pose():
    src = MotionSource(MotionParams(scan_matching=False))
    p0, p1 = np.array([1.0, 0.0, 0.0]), np.array([1.2, 0.0, 0.0])
    src.resume(p0, started=True)
    np.testing.assert_allclose(src.next(p1, None, ODOM_COV).increment, [0.2, 0.0, 0.0])
    matching = MotionSource(MotionParams())
    matching.resume(p0, started=True)
    # The tracker starts afresh: its first scan has nothing to match, so odometry moves the filter.
    m = matching.next(p1, scan_at(START), ODOM_COV)
    assert m.events == ("match_no_reference",)
    np.testing.assert_allclose(m.increment, [0.2, 0.0, 0.0])
