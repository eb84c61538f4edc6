"""Landmark life cycle, backward-search policy, checkpoints and input validation."""

from __future__ import annotations

import io

import numpy as np
import pytest

from lrfslam.algo.ekf_slam import (
    BACKWARD,
    FORWARD,
    EkfParams,
    EkfSlam,
    ObsStatus,
    WallStatus,
)
from lrfslam.algo.geometry import compose, to_frame, wrap_angle
from lrfslam.errors import ConfigError, InputError

POSE_COV = np.diag([1e-3, 1e-3, 1e-4])


def see(f, world_xy, pose, kind=FORWARD):
    """Observe world points exactly from ``pose``."""
    pts = to_frame(np.atleast_2d(world_xy), pose)
    return f.observe(pts, None, np.full(len(pts), kind))


def test_forward_corner_confirms_on_second_sighting_and_only_then_corrects_pose():
    # Odometry noise large enough for the 5 cm shortfall below to stay inside the gate.
    f = EkfSlam(EkfParams(min_sightings_to_confirm=3, odom_trans_sigma_per_sqrt_m=0.05), pose0_cov=POSE_COV)
    rep = see(f, [3.0, 1.0], (0, 0, 0))
    assert rep.status[0] == ObsStatus.NEW and not f.landmarks().confirmed[0]
    f.predict([0.2, 0.0, 0.0])
    pose, cov = f.pose, f.pose_cov
    rep = see(f, [3.0, 1.0], (0.25, 0, 0))  # odometry was 5 cm short
    assert rep.status[0] == ObsStatus.MATCHED and not rep.pose_corrected[0]
    # A tentative refines itself only: pose mean and covariance are untouched.
    np.testing.assert_array_equal(f.pose, pose)
    np.testing.assert_array_equal(f.pose_cov, cov)
    rep = see(f, [3.0, 1.0], (0.25, 0, 0))
    assert rep.n_confirmed == 1 and rep.pose_corrected[0] and f.landmarks().confirmed[0]
    assert not np.array_equal(f.pose, pose)
    assert np.trace(f.pose_cov) < np.trace(cov)


def test_backward_feature_from_one_viewpoint_is_never_confirmed_and_expires():
    params = EkfParams(min_sightings_to_confirm=2, tentative_max_age_updates=5)
    f = EkfSlam(params, pose0_cov=POSE_COV)
    # Created by the first call, it has 5 further calls to get confirmed.
    reports = [see(f, [2.0, 0.5], (0, 0, 0), BACKWARD) for _ in range(6)]
    assert [r.status[0] for r in reports] == [ObsStatus.NEW] + [ObsStatus.MATCHED] * 5
    assert not any(r.pose_corrected[0] for r in reports)
    assert [r.n_dropped for r in reports] == [0] * 5 + [1] and f.n_landmarks == 0
    # The dropped id is not reused.
    assert see(f, [2.0, 0.5], (0, 0, 0)).landmark_ids[0] == 1


def test_backward_feature_confirms_after_a_change_of_viewpoint():
    params = EkfParams(min_sightings_to_confirm=2, backward_min_view_change_rad=0.2)
    f = EkfSlam(params, pose0_cov=POSE_COV)
    edge = np.array([3.0, 2.0])
    pose = np.zeros(3)
    see(f, edge, pose, BACKWARD)
    confirmed_at = None
    for step in range(1, 15):
        pose = compose(pose, [0.2, 0.0, 0.0])
        f.predict([0.2, 0.0, 0.0])
        rep = see(f, edge, pose, BACKWARD)
        if rep.n_confirmed:
            confirmed_at = step
            break
    # Viewing direction from the edge: atan2(-2, -3) at the start; 0.2 rad later
    # the robot has moved about 1 m along x.
    view = np.arctan2(pose[1] - edge[1], pose[0] - edge[0]) - np.arctan2(-2.0, -3.0)
    assert confirmed_at is not None and abs(view) >= 0.2
    prev_view = np.arctan2(-edge[1], pose[0] - 0.2 - edge[0]) - np.arctan2(-2.0, -3.0)
    assert abs(prev_view) < 0.2


def test_phantom_that_moves_with_the_robot_never_touches_the_pose():
    """An occlusion phantom fixed in the robot frame, seen while driving straight."""
    params = EkfParams(min_sightings_to_confirm=2, tentative_max_age_updates=100)
    f = EkfSlam(params, pose0_cov=POSE_COV)
    dead_reckoning = EkfSlam(params, pose0_cov=POSE_COV)
    for _ in range(12):
        f.predict([0.05, 0.0, 0.0])
        dead_reckoning.predict([0.05, 0.0, 0.0])
        f.observe(np.array([[2.5, 0.0]]), None, np.array([BACKWARD]))
    assert not f.landmarks().confirmed.any()
    np.testing.assert_array_equal(f.pose, dead_reckoning.pose)
    np.testing.assert_array_equal(f.pose_cov, dead_reckoning.pose_cov)


def test_forward_sighting_upgrades_a_backward_landmark():
    f = EkfSlam(EkfParams(min_sightings_to_confirm=2), pose0_cov=POSE_COV)
    see(f, [2.0, 1.0], (0, 0, 0), BACKWARD)
    rep = see(f, [2.0, 1.0], (0, 0, 0), FORWARD)
    table = f.landmarks()
    assert rep.n_confirmed == 1 and table.kinds[0] == FORWARD and table.confirmed[0]


def test_landmark_cap_and_too_close_features_are_rejected():
    f = EkfSlam(EkfParams(max_landmarks=2))
    rep = f.observe(np.array([[3.0, 0.0], [0.0, 3.0], [-3.0, 0.0], [0.04, 0.0]]))   # nearer than MIN_FEATURE_RANGE_M
    np.testing.assert_array_equal(
        rep.status, [ObsStatus.NEW, ObsStatus.NEW, ObsStatus.REJECTED, ObsStatus.REJECTED]
    )
    np.testing.assert_array_equal(rep.landmark_ids, [0, 1, -1, -1])
    assert f.n_landmarks == 2


def test_observation_between_the_gates_is_ambiguous_and_ignored():
    params = EkfParams(min_sightings_to_confirm=1, corner_range_sigma_m=0.015, corner_bearing_sigma_rad=0.001)
    f = EkfSlam(params)
    see(f, [3.0, 0.0], (0, 0, 0))
    s_rr = f.landmarks().cov[0, 0, 0] + 0.015**2
    x, P = f.state_mean, f.state_cov
    rep = f.observe(np.array([[3.0 + np.sqrt(15.0 * s_rr), 0.0]]))
    assert rep.status[0] == ObsStatus.AMBIGUOUS and rep.landmark_ids[0] == -1
    assert rep.nis[0] == pytest.approx(15.0, rel=1e-6)
    np.testing.assert_array_equal(f.state_mean, x)
    np.testing.assert_array_equal(f.state_cov, P)


@pytest.mark.parametrize("method", ["nn", "jcbb"])
def test_each_true_corner_keeps_its_id_over_a_loop(method):
    rng = np.random.default_rng(7)
    world = np.array([[3.0, 2.0], [3.0, -2.0], [-3.0, 2.0], [-3.0, -2.0], [0.0, 3.5], [0.0, -3.5]])
    params = EkfParams(association=method, corner_range_sigma_m=0.02, corner_bearing_sigma_rad=0.01)
    f = EkfSlam(params, pose0_cov=POSE_COV)
    truth, id_of = np.zeros(3), {}
    for _ in range(60):  # one circle of radius ~1.9 m
        delta = np.array([0.2, 0.0, 2 * np.pi / 60])
        truth = compose(truth, delta)
        f.predict(delta + rng.normal(scale=[0.01, 0.01, 0.005]))
        rel = to_frame(world, truth)
        vis = np.flatnonzero(np.hypot(rel[:, 0], rel[:, 1]) < 4.0)
        pts = rel[vis] + rng.normal(scale=0.01, size=(vis.size, 2))
        rep = f.observe(pts)
        for k, w in enumerate(vis):
            if rep.status[k] == ObsStatus.NEW:
                assert w not in id_of
                id_of[w] = rep.landmark_ids[k]
            elif rep.status[k] == ObsStatus.MATCHED:
                assert rep.landmark_ids[k] == id_of[w]
    assert len(id_of) == len(world) and f.landmarks().confirmed.all()
    np.testing.assert_allclose(f.landmarks().xy[np.argsort(list(id_of.values()))],
                               world[list(id_of.keys())][np.argsort(list(id_of.values()))], atol=0.15)


def drive(f, rng, steps):
    """Random drive past a few corners; returns the reports."""
    world = np.array([[2.0, 1.0], [4.0, -1.0], [5.0, 2.0], [1.0, -2.0]])
    reports = []
    for t in range(steps):
        delta = np.array([0.2, 0.0, 0.05])
        f.predict(delta)
        rel = to_frame(world, compose(np.zeros(3), delta * (t + 1))) + rng.normal(scale=0.01, size=(4, 2))
        reports.append(f.observe(rel, np.tile(np.eye(2) * 1e-4, (4, 1, 1)), np.array([0, 1, 0, 1])))
    return reports


def test_snapshot_round_trip_through_npz_resumes_identically():
    params = EkfParams(association="jcbb")
    f = EkfSlam(params, pose0_cov=POSE_COV)
    drive(f, np.random.default_rng(1), 6)
    buf = io.BytesIO()
    np.savez(buf, **f.snapshot())
    buf.seek(0)
    g = EkfSlam.restore(params, dict(np.load(buf)))
    for name, value in f.snapshot().items():
        np.testing.assert_array_equal(g.snapshot()[name], value)
    ra = drive(f, np.random.default_rng(2), 5)
    rb = drive(g, np.random.default_rng(2), 5)
    for a, b in zip(ra, rb, strict=True):
        np.testing.assert_array_equal(a.landmark_ids, b.landmark_ids)
        np.testing.assert_array_equal(a.nis, b.nis)
    np.testing.assert_array_equal(f.state_cov, g.state_cov)
    np.testing.assert_array_equal(f.landmarks().sightings, g.landmarks().sightings)


@pytest.mark.parametrize(
    "edit",
    [
        lambda s: s.pop("state_cov"),
        lambda s: s.update(format=99),
        lambda s: s.update(landmark_ids=s["landmark_ids"][:-1]),
        lambda s: s.update(state_cov=s["state_cov"][:-1]),
        lambda s: s.update(next_id=0),
    ],
)
def test_restore_rejects_broken_snapshots(edit):
    f = EkfSlam(EkfParams(), pose0_cov=POSE_COV)
    drive(f, np.random.default_rng(0), 3)
    snap = f.snapshot()
    edit(snap)
    with pytest.raises(InputError):
        EkfSlam.restore(EkfParams(), snap)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"association": "hungarian"},
        {"odom_trans_sigma_per_sqrt_m": -0.1},
        {"corner_range_sigma_m": 0.0},
        {"gate_new_chi2": 5.0},
        {"min_sightings_to_confirm": 0},
        {"corner_bearing_sigma_rad": float("nan")},
    ],
)
def test_bad_params_raise_config_error(kwargs):
    with pytest.raises(ConfigError):
        EkfParams(**kwargs)


def test_bad_inputs_raise_input_error():
    f = EkfSlam(EkfParams())
    with pytest.raises(InputError):
        f.predict([0.1, np.nan, 0.0])
    with pytest.raises(InputError):
        f.observe(np.ones((2, 2)), np.ones((3, 2, 2)))
    with pytest.raises(InputError):
        f.observe(np.ones((1, 2)), None, np.array([2]))
    with pytest.raises(InputError):
        f.observe(np.array([[np.inf, 0.0]]))
    with pytest.raises(InputError):
        f.update_known(5, [1.0, 0.0], np.eye(2))
    assert f.observe(np.zeros((0, 2))).status.size == 0


def test_wall_direction_pins_the_heading_against_odometry_drift():
    # Odometry under-reports every turn by 2 %: the heading error grows without bound
    # unless the walls (at psi = 0.2 rad mod 90° in the map) are observed.
    rng = np.random.default_rng(4)
    params = EkfParams(odom_rot_sigma_per_sqrt_rad=0.05)
    with_walls, without = EkfSlam(params), EkfSlam(params)
    truth = np.zeros(3)
    for _ in range(200):
        delta = np.array([0.1, 0.0, 0.1])
        truth = compose(truth, delta)
        for f in (with_walls, without):
            f.predict(delta * [1.0, 1.0, 0.98])
        upd = with_walls.observe_wall_direction(0.2 - truth[2] + rng.normal(scale=0.002) + np.pi / 2 * 3, 0.002)
        assert upd.status in (WallStatus.INITIALISED, WallStatus.APPLIED)
    err_without, err_with = (abs(wrap_angle(f.pose[2] - truth[2])) for f in (without, with_walls))
    assert err_without > 0.3
    assert err_with < 3 * np.sqrt(with_walls.pose_cov[2, 2]) and err_with < 0.01
    psi, var = with_walls.building_orientation
    assert abs(psi - 0.2) < 3 * np.sqrt(var) + 1e-9 and without.building_orientation is None


def test_wall_direction_outside_the_gate_or_ambiguous_is_discarded():
    f = EkfSlam(EkfParams(odom_rot_sigma_floor_rad=0.5), pose0_cov=POSE_COV)
    assert f.observe_wall_direction(0.1, 0.01).status == WallStatus.INITIALISED
    x, P = f.state_mean, f.state_cov
    off = f.observe_wall_direction(0.1 + np.radians(30), 0.01)  # 30° off, sigma 0.6°
    assert off.status == WallStatus.GATED and off.nis > 100
    np.testing.assert_array_equal(f.state_mean, x)
    np.testing.assert_array_equal(f.state_cov, P)
    # 0.5 rad of heading noise: a 99 % gate would span more than ±45°, so a wall a
    # quarter turn away would fit as well as the right one.
    f.predict([0.0, 0.0, 0.0])
    x, P = f.state_mean, f.state_cov
    assert f.observe_wall_direction(0.1, 0.01).status == WallStatus.AMBIGUOUS
    np.testing.assert_array_equal(f.state_mean, x)
    for bad in ((np.nan, 0.01), (0.1, 0.0), (0.1, np.inf)):
        with pytest.raises(InputError):
            f.observe_wall_direction(*bad)


def test_snapshot_keeps_the_building_orientation():
    f = EkfSlam(EkfParams(), pose0_cov=POSE_COV)
    drive(f, np.random.default_rng(1), 3)
    f.observe_wall_direction(-0.3, 0.005)
    g = EkfSlam.restore(EkfParams(), f.snapshot())
    assert g.building_orientation == f.building_orientation
    np.testing.assert_array_equal(g.state_cov, f.state_cov)
    assert g.observe_wall_direction(-0.29, 0.005) == f.observe_wall_direction(-0.29, 0.005)


def test_format_1_snapshot_is_migrated_with_psi_unset():
    f = EkfSlam(EkfParams(), pose0_cov=POSE_COV)
    drive(f, np.random.default_rng(1), 4)
    snap = f.snapshot()
    # The same filter as format 1 wrote it: no psi in the state, no psi_set.
    old = {**snap, "format": 1, "state_mean": np.delete(snap["state_mean"], 3),
           "state_cov": np.delete(np.delete(snap["state_cov"], 3, axis=0), 3, axis=1)}
    del old["psi_set"]
    g = EkfSlam.restore(EkfParams(), old)
    assert g.building_orientation is None
    for name, value in snap.items():
        np.testing.assert_array_equal(g.snapshot()[name], value)
    # An unset psi must be exactly uncorrelated; anything else is a corrupt snapshot.
    snap["state_cov"][3, 0] = snap["state_cov"][0, 3] = 1e-6
    with pytest.raises(InputError, match="unset building orientation"):
        EkfSlam.restore(EkfParams(), snap)
