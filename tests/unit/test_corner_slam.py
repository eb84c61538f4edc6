"""One filter update per scan (algo.corner_slam), against the EKF driven by hand."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from lrfslam.algo.checkpoint import decode
from lrfslam.algo.corner_slam import BACKWARD, FORWARD, CornerSlam
from lrfslam.algo.ekf_slam import EkfParams, EkfSlam, ObsStatus
from lrfslam.algo.geometry import relative
from lrfslam.algo.motion_source import MotionParams
from lrfslam.errors import ConfigError

PARAMS = EkfParams()
ODOMETRY_ONLY = MotionParams(scan_matching=False)
XY = np.array([[2.0, 1.0], [3.0, -1.0], [1.5, 2.5]])
COV = np.tile(np.eye(2) * 1e-4, (3, 1, 1))
KINDS = np.array([FORWARD, BACKWARD, FORWARD], dtype=np.int8)
ODOM = [np.array([0.1 * k, 0.01 * k, 0.02 * k]) for k in range(6)]
WALL = (0.05, 0.01)


def assert_same(a: EkfSlam, b: EkfSlam) -> None:
    np.testing.assert_array_equal(a.state_mean, b.state_mean)
    np.testing.assert_array_equal(a.state_cov, b.state_cov)


def test_each_update_is_predict_wall_then_features():
    counts: Counter = Counter()
    slam = CornerSlam(PARAMS, ODOMETRY_ONLY, counts=counts)
    oracle = EkfSlam(PARAMS)
    for k, pose in enumerate(ODOM):
        report = slam.update(pose, None, XY, COV, KINDS, WALL)
        if k:
            oracle.predict(relative(ODOM[k - 1], pose))
        oracle.observe_wall_direction(*WALL)
        expected = oracle.observe(XY, COV, KINDS)
        assert_same(slam.ekf, oracle)
        np.testing.assert_array_equal(report.landmark_ids, expected.landmark_ids)
    assert slam.scans == counts["scans"] == len(ODOM)
    # One wall measurement per scan (the fixed reading is gated once the heading has turned).
    assert counts["wall_initialised"] == 1
    assert sum(v for k, v in counts.items() if k.startswith("wall_")) == len(ODOM)
    assert slam.last_update.report is report
    np.testing.assert_array_equal(slam.last_update.xy_m, XY)


def test_options_leave_out_jump_edges_and_the_wall_direction():
    slam = CornerSlam(PARAMS, ODOMETRY_ONLY, use_backward=False, use_wall_direction=False)
    oracle = EkfSlam(PARAMS)
    slam.update(ODOM[0], None, XY, COV, KINDS, WALL)
    oracle.observe(XY[[0, 2]], COV[[0, 2]], KINDS[[0, 2]])
    assert_same(slam.ekf, oracle)
    np.testing.assert_array_equal(slam.last_update.xy_m, XY[[0, 2]])
    assert not any(k.startswith("wall_") for k in slam.counts)


def test_start_pose_only_before_the_first_scan():
    slam = CornerSlam(PARAMS, ODOMETRY_ONLY)
    slam.start_at(np.array([1.0, 2.0, 0.5]))
    slam.update(None, None, XY, COV, KINDS, None)
    oracle = EkfSlam(PARAMS, pose0=[1.0, 2.0, 0.5])
    oracle.observe(XY, COV, KINDS)
    assert_same(slam.ekf, oracle)
    assert slam.counts["no_odometry"] == 1
    with pytest.raises(ConfigError):
        slam.start_at(np.zeros(3))


def test_a_resumed_filter_goes_on_as_the_one_that_was_saved():
    first = CornerSlam(PARAMS, ODOMETRY_ONLY)
    for pose in ODOM[:3]:
        first.update(pose, None, XY, COV, KINDS, WALL)
    resumed = CornerSlam(PARAMS, ODOMETRY_ONLY)
    resumed.resume(decode(PARAMS, first.checkpoint()))
    assert resumed.scans == 3
    for pose in ODOM[3:]:
        for slam in (first, resumed):
            slam.update(pose, None, XY - 0.05, COV, KINDS, WALL)
    assert_same(resumed.ekf, first.ekf)


def test_matched_observations_leave_their_nis_in_the_counters():
    counts: Counter = Counter()
    slam = CornerSlam(PARAMS, ODOMETRY_ONLY, counts=counts)
    nis: list[float] = []
    for pose in ODOM:
        report = slam.update(pose, None, XY, COV, KINDS, None)
        nis += report.nis[report.status == ObsStatus.MATCHED].tolist()
    assert counts["matched"] == len(nis) > 0
    assert counts["nis_matched_milli"] == pytest.approx(1000.0 * sum(nis), abs=len(nis))
    assert counts["nis_matched_within_95"] == sum(v <= 5.991 for v in nis)
