"""EkfSlam.predict_with_cov: a motion increment with an explicit covariance (e.g. from scan matching)."""

from __future__ import annotations

import numpy as np
import pytest

from lrfslam.algo.ekf_slam import EkfParams, EkfSlam
from lrfslam.algo.geometry import compose
from lrfslam.errors import InputError


def filter_with_landmark(heading_rad: float) -> EkfSlam:
    f = EkfSlam(EkfParams(), pose0=(1.0, -2.0, heading_rad), pose0_cov=np.diag([0.01, 0.02, 0.003]))
    f.observe(np.array([[2.0, 0.5]]), np.tile(np.eye(2) * 1e-4, (1, 1, 1)), np.zeros(1, dtype=np.int8))
    return f


def test_predict_is_predict_with_cov_under_the_odometry_model():
    u = np.array([0.3, -0.05, 0.2])
    a, b = filter_with_landmark(0.7), filter_with_landmark(0.7)
    a.predict(u)
    b.predict_with_cov(u, b.odometry_cov(u))
    np.testing.assert_array_equal(a.state_mean, b.state_mean)
    np.testing.assert_array_equal(a.state_cov, b.state_cov)


def test_the_increment_covariance_is_rotated_into_the_world_and_added():
    heading = 0.9
    f = EkfSlam(EkfParams(), pose0=(0.0, 0.0, heading))
    u = np.array([0.5, 0.1, -0.3])
    q = np.array([[4e-4, 1e-4, 0.0], [1e-4, 1e-4, 2e-5], [0.0, 2e-5, 3e-5]])
    f.predict_with_cov(u, q)
    c, s = np.cos(heading), np.sin(heading)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(f.pose, compose((0.0, 0.0, heading), u))
    # Zero prior pose covariance: only the increment's covariance, in world axes.
    np.testing.assert_allclose(f.pose_cov, rot @ q @ rot.T, atol=1e-15)


def test_landmarks_keep_their_covariance_and_stay_correlated():
    f = filter_with_landmark(0.2)
    before = f.state_cov
    f.predict_with_cov([0.2, 0.0, 0.1], np.diag([1e-4, 1e-4, 1e-5]))
    after = f.state_cov
    np.testing.assert_array_equal(after[3:, 3:], before[3:, 3:])
    assert np.all(np.linalg.eigvalsh(after) > -1e-12)
    assert np.trace(after[:3, :3]) > np.trace(before[:3, :3])


@pytest.mark.parametrize("delta, cov", [([0.0, 0.0], np.eye(3)), ([0.0, 0.0, np.nan], np.eye(3)),
                                        ([0.0, 0.0, 0.0], np.eye(2)), ([0.0, 0.0, 0.0], np.full((3, 3), np.inf))])
def test_bad_shapes_and_values_are_rejected(delta, cov):
    with pytest.raises(InputError):
        EkfSlam(EkfParams()).predict_with_cov(delta, cov)
