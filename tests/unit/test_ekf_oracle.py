"""EkfSlam's sparse O(n)/O(n²) steps against dense reference computations.

The update is checked against filterpy's dense ``ExtendedKalmanFilter.update``
(Joseph form); prediction and augmentation against dense linearisations built
from finite-difference Jacobians, so the analytic Jacobians are checked too.
"""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import ExtendedKalmanFilter
from hypothesis import given, settings
from hypothesis import strategies as st

from lrfslam.algo.ekf_slam import (
    BACKWARD_SIGMA_SCALE,
    EkfParams,
    EkfSlam,
    ObsStatus,
    WallStatus,
)
from lrfslam.algo.geometry import compose, wrap_angle
from lrfslam.algo.wall_direction import wrap_quarter

TOL = 1e-9
PSI, LM0 = 3, 4  # state layout: [x, y, theta, psi, m1x, m1y, ...]


def random_filter(rng, n_lm, params=None, confirmed=True):
    """A filter holding a random state (building orientation set) and a random well-conditioned covariance."""
    n = LM0 + 2 * n_lm
    pose = np.array([rng.uniform(-2, 2), rng.uniform(-2, 2), rng.uniform(-np.pi, np.pi)])
    # Landmarks 1-5 m from the robot so ranges and bearings are well defined.
    ang = rng.uniform(-np.pi, np.pi, n_lm)
    rad = rng.uniform(1.0, 5.0, n_lm)
    lms = pose[:2] + np.column_stack((rad * np.cos(ang), rad * np.sin(ang)))
    a = rng.normal(size=(n, n)) * 0.1
    cov = a @ a.T / n + 0.01 * np.eye(n)
    psi = rng.uniform(-np.pi / 4, np.pi / 4)
    snap = {
        "format": 2,
        "state_mean": np.concatenate((pose, [psi], lms.ravel())),
        "state_cov": cov,
        "psi_set": True,
        "landmark_ids": np.arange(n_lm, dtype=np.int64) + 10,
        "landmark_kinds": np.zeros(n_lm, dtype=np.int8),
        "landmark_sightings": np.full(n_lm, 5),
        "landmark_confirmed": np.full(n_lm, confirmed),
        "landmark_born": np.zeros(n_lm, dtype=np.int64),
        "landmark_view_ref_rad": np.zeros(n_lm),
        "landmark_view_spread_rad": np.zeros(n_lm),
        "next_id": 10 + n_lm,
        "n_observe": 0,
    }
    return EkfSlam.restore(params or EkfParams(), snap)


def measure(x, i):
    """Dense range-bearing model of landmark index ``i``: returns h (2,1), H (2, n)."""
    dx, dy = x[LM0 + 2 * i] - x[0], x[LM0 + 1 + 2 * i] - x[1]
    q = dx * dx + dy * dy
    r = np.sqrt(q)
    h = np.array([[r], [wrap_angle(np.arctan2(dy, dx) - x[2])]])
    H = np.zeros((2, x.size))
    H[:, :3] = [[-dx / r, -dy / r, 0.0], [dy / q, -dx / q, -1.0]]
    H[:, LM0 + 2 * i: LM0 + 2 + 2 * i] = [[dx / r, dy / r], [-dy / q, dx / q]]
    return h, H


def filterpy_update(x, P, z, R, i):
    """One update through filterpy's dense EKF.

    ``z`` as a (2, 1) column and a wrapped bearing residual, as filterpy needs
    (docs/paper-reading.md, 'filterpy and a growing state').
    """
    ekf = ExtendedKalmanFilter(dim_x=x.size, dim_z=2)
    ekf.x = x.reshape(-1, 1).copy()
    ekf.P = P.copy()

    def residual(a, b):
        y = a - b
        y[1, 0] = wrap_angle(y[1, 0])
        return y

    ekf.update(
        z.reshape(2, 1),
        lambda xc, j: measure(xc.ravel(), j)[1],
        lambda xc, j: measure(xc.ravel(), j)[0],
        R=R, args=(i,), hx_args=(i,), residual=residual,
    )
    xo = ekf.x.ravel().copy()
    xo[2] = wrap_angle(xo[2])
    return xo, ekf.P


def num_jacobian(f, v, eps=1e-6):
    """Central-difference Jacobian of ``f`` at ``v``."""
    cols = []
    for k in range(v.size):
        d = np.zeros_like(v)
        d[k] = eps
        cols.append((f(v + d) - f(v - d)) / (2 * eps))
    return np.column_stack(cols)


@pytest.mark.parametrize("n_lm", [1, 2, 3, 4, 5, 6])
@pytest.mark.parametrize("seed", range(4))
def test_known_update_matches_filterpy(n_lm, seed):
    rng = np.random.default_rng(100 * n_lm + seed)
    f = random_filter(rng, n_lm)
    x, P = f.state_mean, f.state_cov
    i = int(rng.integers(n_lm))
    h, _ = measure(x, i)
    z = h.ravel() + rng.normal(scale=[0.05, 0.03])
    b = rng.normal(size=(2, 2)) * 0.05
    R = b @ b.T + np.diag([1e-4, 1e-4])
    x_ref, P_ref = filterpy_update(x, P, z, R, i)
    f.update_known(10 + i, z, R)
    np.testing.assert_allclose(f.state_mean, x_ref, atol=TOL, rtol=0)
    np.testing.assert_allclose(f.state_cov, P_ref, atol=TOL, rtol=0)


@pytest.mark.parametrize("seed", range(6))
def test_observe_of_confirmed_landmark_matches_filterpy(seed):
    """The whole observe() path: cartesian input → polar z and R → full update."""
    rng = np.random.default_rng(seed)
    params = EkfParams(corner_range_sigma_m=0.02, corner_bearing_sigma_rad=0.01)
    f = random_filter(rng, 3, params)
    x, P = f.state_mean, f.state_cov
    i = int(rng.integers(3))
    kind = int(rng.integers(2))
    h, _ = measure(x, i)
    z = h.ravel() + rng.normal(scale=[0.01, 0.005])
    point = z[0] * np.array([np.cos(z[1]), np.sin(z[1])])
    cov_xy = np.diag([4e-4, 1e-4])
    jac = np.array([[np.cos(z[1]), np.sin(z[1])], [-np.sin(z[1]) / z[0], np.cos(z[1]) / z[0]]])
    R = jac @ cov_xy @ jac.T + np.diag([0.02**2, 0.01**2])
    R *= BACKWARD_SIGMA_SCALE**2 if kind else 1.0
    x_ref, P_ref = filterpy_update(x, P, z, R, i)
    rep = f.observe(point[None], cov_xy[None], np.array([kind]))
    assert rep.status[0] == ObsStatus.MATCHED and rep.landmark_ids[0] == 10 + i
    assert rep.pose_corrected[0]
    np.testing.assert_allclose(f.state_mean, x_ref, atol=TOL, rtol=0)
    np.testing.assert_allclose(f.state_cov, P_ref, atol=TOL, rtol=0)


@pytest.mark.parametrize("seed", range(6))
def test_tentative_update_is_dense_joseph_with_landmark_only_gain(seed):
    rng = np.random.default_rng(50 + seed)
    params = EkfParams(corner_range_sigma_m=0.02, corner_bearing_sigma_rad=0.01, min_sightings_to_confirm=99)
    f = random_filter(rng, 4, params, confirmed=False)
    x, P = f.state_mean, f.state_cov
    i = int(rng.integers(4))
    h, H = measure(x, i)
    z = h.ravel() + rng.normal(scale=[0.01, 0.005])
    R = np.diag([0.02**2, 0.01**2])
    S = H @ P @ H.T + R
    K = np.zeros((x.size, 2))
    rows = slice(LM0 + 2 * i, LM0 + 2 + 2 * i)
    K[rows] = (P @ H.T @ np.linalg.inv(S))[rows]
    nu = z - h.ravel()
    nu[1] = wrap_angle(nu[1])
    IKH = np.eye(x.size) - K @ H
    P_ref = IKH @ P @ IKH.T + K @ R @ K.T
    rep = f.observe((z[0] * np.array([np.cos(z[1]), np.sin(z[1])]))[None])
    assert rep.status[0] == ObsStatus.MATCHED and not rep.pose_corrected[0]
    np.testing.assert_allclose(f.state_mean, x + K @ nu, atol=TOL, rtol=0)
    np.testing.assert_allclose(f.state_cov, P_ref, atol=TOL, rtol=0)
    # The pose block and every other landmark are untouched by a tentative.
    np.testing.assert_array_equal(f.state_cov[:3, :3], P[:3, :3])


@pytest.mark.parametrize("seed", range(5))
def test_predict_matches_dense_linearisation(seed):
    rng = np.random.default_rng(seed)
    params = EkfParams(odom_trans_sigma_floor_m=0.01, odom_rot_sigma_floor_rad=0.02)
    f = random_filter(rng, 4, params)
    x, P = f.state_mean, f.state_cov
    u = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.2, 0.2), rng.uniform(-0.5, 0.5)])
    d = np.hypot(u[0], u[1])
    # Random-walk noise: wheel-scale error along the motion, the heading walk and the sideways
    # drift it integrates to (variance v d²/3, covariance v d/2 with the heading), isotropic floor.
    along, left = u[:2] / d, np.array([-u[1], u[0]]) / d
    v = params.odom_rot_sigma_per_sqrt_rad**2 * abs(u[2]) + params.odom_rot_sigma_per_sqrt_m**2 * d
    q_u = np.zeros((3, 3))
    q_u[:2, :2] = (params.odom_trans_sigma_per_sqrt_m**2 * d * np.outer(along, along) + v * d**2 / 3 * np.outer(left, left)
                   + 0.01**2 * np.eye(2))
    q_u[:2, 2] = q_u[2, :2] = v * d / 2 * left
    q_u[2, 2] = 0.02**2 + v

    def motion(v):  # full state and increment → new full state, heading unwrapped
        out = v[:-3].copy()
        out[:3] = compose(v[:3], v[-3:])
        out[2] = v[2] + v[-1]
        return out

    J = num_jacobian(motion, np.concatenate((x, u)))
    F, G = J[:, : x.size], J[:, x.size:]
    P_ref = F @ P @ F.T + G @ q_u @ G.T
    f.predict(u)
    np.testing.assert_allclose(f.state_cov, P_ref, atol=1e-8, rtol=0)
    np.testing.assert_allclose(f.pose, compose(x[:3], u), atol=1e-12)
    np.testing.assert_array_equal(f.state_mean[3:], x[3:])


@pytest.mark.parametrize("seed", range(5))
def test_augmentation_has_full_cross_covariance(seed):
    rng = np.random.default_rng(seed)
    params = EkfParams(corner_range_sigma_m=0.03, corner_bearing_sigma_rad=0.02)
    f = random_filter(rng, 3, params)
    x, P = f.state_mean, f.state_cov
    # A point far from every landmark (well beyond the new-landmark gate).
    far = x[LM0:].reshape(-1, 2).max(axis=0) + 20.0
    rb = np.array([np.hypot(*(far - x[:2])), wrap_angle(np.arctan2(*(far - x[:2])[::-1]) - x[2])])
    point = rb[0] * np.array([np.cos(rb[1]), np.sin(rb[1])])
    rep = f.observe(point[None])
    assert rep.status[0] == ObsStatus.NEW and rep.landmark_ids[0] == 13

    def augment(v):
        st, (r, b) = v[:-2], v[-2:]
        return np.concatenate((st, st[:2] + r * np.array([np.cos(st[2] + b), np.sin(st[2] + b)])))

    J = num_jacobian(augment, np.concatenate((x, rb)))
    big = np.zeros((x.size + 2, x.size + 2))
    big[: x.size, : x.size] = P
    big[x.size:, x.size:] = np.diag([0.03**2, 0.02**2])
    np.testing.assert_allclose(f.state_mean, augment(np.concatenate((x, rb))), atol=1e-9)
    np.testing.assert_allclose(f.state_cov, J @ big @ J.T, atol=1e-7, rtol=0)


def wall_model(x):
    """Dense wall-direction model: h (1, 1) = wrap_quarter(psi - theta), H (1, n)."""
    H = np.zeros((1, x.size))
    H[0, 2], H[0, PSI] = -1.0, 1.0
    return np.array([[wrap_quarter(x[PSI] - x[2])]]), H


@pytest.mark.parametrize("n_lm", [0, 1, 4])
@pytest.mark.parametrize("seed", range(4))
def test_wall_direction_update_matches_filterpy(n_lm, seed):
    rng = np.random.default_rng(300 + 10 * n_lm + seed)
    f = random_filter(rng, n_lm, EkfParams(wall_model_sigma_rad=0.01))
    x, P = f.state_mean, f.state_cov
    # A measurement given by any representative modulo 90°, within the gate.
    h, _ = wall_model(x)
    z = float(h[0, 0]) + rng.normal(scale=0.02) + np.pi / 2 * rng.integers(-2, 3)
    sigma = 0.03
    ekf = ExtendedKalmanFilter(dim_x=x.size, dim_z=1)
    ekf.x, ekf.P = x.reshape(-1, 1).copy(), P.copy()
    ekf.update(np.array([[z]]), lambda xc: wall_model(xc.ravel())[1], lambda xc: wall_model(xc.ravel())[0],
               R=np.array([[sigma**2 + 0.01**2]]), residual=lambda a, b: wrap_quarter(a - b))
    x_ref = ekf.x.ravel()
    x_ref[2] = wrap_angle(x_ref[2])
    upd = f.observe_wall_direction(z, sigma)
    assert upd.status == WallStatus.APPLIED
    S = P[2, 2] + P[PSI, PSI] - 2 * P[2, PSI] + sigma**2 + 0.01**2
    assert upd.nis == pytest.approx(wrap_quarter(z - h[0, 0]) ** 2 / S, rel=1e-9)
    np.testing.assert_allclose(f.state_mean, x_ref, atol=TOL, rtol=0)
    np.testing.assert_allclose(f.state_cov, ekf.P, atol=TOL, rtol=0)


@pytest.mark.parametrize("seed", range(4))
def test_first_wall_direction_initialises_psi_with_theta_cross_covariances(seed):
    rng = np.random.default_rng(seed)
    params = EkfParams(wall_model_sigma_rad=0.004)
    f = EkfSlam(params, pose0=(0.3, -0.2, 2.0), pose0_cov=np.diag([0.01, 0.02, 0.003]))
    for _ in range(3):
        f.predict(rng.normal(scale=[0.3, 0.05, 0.2]))
        f.observe(rng.uniform(1.0, 3.0, size=(2, 2)))
    x, P = f.state_mean, f.state_cov
    assert f.building_orientation is None and not P[PSI].any() and x[PSI] == 0
    z, sigma = rng.uniform(-np.pi / 4, np.pi / 4), 0.01
    assert f.observe_wall_direction(z, sigma).status == WallStatus.INITIALISED

    def initialise(v):  # state with psi unset, and z -> state with psi = theta + z
        out = v[:-1].copy()
        out[PSI] = v[2] + v[-1]
        return out

    J = num_jacobian(initialise, np.concatenate((x, [z])))
    big = np.zeros((x.size + 1, x.size + 1))
    big[: x.size, : x.size] = P
    big[-1, -1] = sigma**2 + 0.004**2  # the model noise adds in quadrature
    np.testing.assert_allclose(f.state_cov, J @ big @ J.T, atol=1e-9, rtol=0)
    expected = initialise(np.concatenate((x, [z])))
    expected[PSI] = wrap_quarter(expected[PSI])
    np.testing.assert_allclose(f.state_mean, expected, atol=1e-12)
    assert f.building_orientation == pytest.approx((expected[PSI], P[2, 2] + sigma**2 + 0.004**2))


@settings(max_examples=50, deadline=None)
@given(st.floats(0.05, 20.0), st.integers(2, 40), st.floats(0.0, 0.05), st.floats(0.0, 0.05), st.floats(0.0, 0.05))
def test_predict_noise_does_not_depend_on_the_step_size(length_m, n, trans_per_m, rot_per_m, rot_per_rad):
    """Random-walk odometry noise along a straight line: one step and n steps over the same
    length agree, sideways drift included (what lets a resumed filter bridge many scans at once)."""
    params = EkfParams(odom_trans_sigma_per_sqrt_m=trans_per_m, odom_rot_sigma_per_sqrt_m=rot_per_m,
                       odom_rot_sigma_per_sqrt_rad=rot_per_rad, odom_trans_sigma_floor_m=0.0, odom_rot_sigma_floor_rad=0.0)
    one, many = EkfSlam(params), EkfSlam(params)
    one.predict([length_m, 0.0, 0.0])
    for _ in range(n):
        many.predict([length_m / n, 0.0, 0.0])
    np.testing.assert_allclose(many.pose_cov, one.pose_cov, rtol=1e-9, atol=1e-15)
    # The integral of a heading random walk of variance v per metre: sideways v L³/3.
    assert one.pose_cov[1, 1] == pytest.approx(rot_per_m**2 * length_m**3 / 3, rel=1e-9, abs=1e-18)
    assert one.pose_cov[0, 0] == pytest.approx(trans_per_m**2 * length_m, rel=1e-9, abs=1e-18)
