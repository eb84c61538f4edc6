"""Point-to-line ICP (algo.scan_match): accuracy, failures, covariance consistency, the keyframe tracker."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lrfslam.algo import scan_match
from lrfslam.algo.geometry import compose, polar_to_xy, relative, wrap_angle
from lrfslam.algo.scan_match import (
    SECOND_GUESS_INLIER_MARGIN,
    MatchResult,
    MatchStatus,
    ReferenceScan,
    ScanMatchParams,
    ScanTracker,
    fits_better,
    match,
)
from lrfslam.errors import ConfigError, InputError
from lrfslam.sim.floor_plans import build_world, straight_wall
from lrfslam.sim.lidar import LidarModel, simulate_scan
from lrfslam.sim.simulator import SimConfig, Simulator

P = ScanMatchParams()
EXACT = LidarModel(range_sigma_m=0.0, quantum_m=0.0, mixed_pixel_prob=0.0)
HALL = build_world("hallway_loop")
# Near the south-east corner of the hallway loop, looking diagonally into it:
# walls in two directions, so every direction of motion is constrained.
CORNER_POSE = np.array([16.0, -0.5, 0.6])


def points(world, pose, lidar=EXACT, rng=None):
    scan = simulate_scan(world, pose, lidar, rng if rng is not None else np.random.default_rng(0))
    return polar_to_xy(scan.ranges_m, scan.angles_rad)


def test_a_known_rigid_motion_is_recovered_to_a_millimetre_and_a_tenth_of_a_degree():
    true = np.array([0.12, -0.03, 0.06])
    ref = ReferenceScan.build(points(HALL, CORNER_POSE))
    res = match(ref, points(HALL, compose(CORNER_POSE, true)), np.zeros(3), P)
    assert res.status is MatchStatus.OK and res.unconstrained == 0
    err = relative(true, res.pose)
    assert np.hypot(err[0], err[1]) < 1e-3 and abs(np.degrees(err[2])) < 0.1
    assert res.inlier_ratio > 0.7 and res.residual_rms_m < 2e-3


def test_with_lidar_noise_the_error_stays_within_the_reported_covariance():
    rng = np.random.default_rng(1)
    true = np.array([0.08, 0.02, -0.04])
    lidar = LidarModel()  # 1 cm noise, 1 cm quantum, mixed pixels
    ref = ReferenceScan.build(points(HALL, CORNER_POSE, lidar, rng))
    res = match(ref, points(HALL, compose(CORNER_POSE, true), lidar, rng), true + [0.05, -0.05, 0.03], P)
    assert res.ok
    err = res.pose - true
    err[2] = wrap_angle(err[2])
    assert np.hypot(err[0], err[1]) < 0.01 and abs(np.degrees(err[2])) < 0.3
    assert err @ np.linalg.solve(res.cov, err) < 16.3  # chi2_3 at 99.9 %


def test_too_few_points_and_a_scan_of_another_place_fall_back_to_the_guess():
    ref = ReferenceScan.build(points(HALL, CORNER_POSE))
    guess = np.array([0.1, 0.0, 0.0])
    few = match(ref, points(HALL, CORNER_POSE)[:10], guess, P)
    assert few.status is MatchStatus.TOO_FEW_POINTS and not few.ok
    np.testing.assert_array_equal(few.pose, guess)
    assert np.all(np.isnan(few.cov))
    elsewhere = match(ref, points(HALL, np.array([4.0, 11.0, 3.0])), guess, P)
    assert not elsewhere.ok
    np.testing.assert_array_equal(elsewhere.pose, guess)


def test_a_single_wall_leaves_the_motion_along_it_to_the_guess():
    wall = straight_wall(length_m=30.0, distance_m=1.5)  # across the view, 1.5 m ahead: x = 1.5
    true = np.array([0.03, 0.2, 0.02])
    guess = np.array([0.0, 0.27, 0.0])  # 7 cm too far along the wall, 3 cm and 1.1° off across it
    ref = ReferenceScan.build(points(wall, np.zeros(3)))
    cur = points(wall, true)
    alone = match(ref, cur, guess, P)
    assert alone.status is MatchStatus.DEGENERATE and alone.information_ratio < scan_match.MIN_INFORMATION_RATIO
    guess_cov = np.diag([0.05**2, 0.05**2, 0.02**2])
    res = match(ref, cur, guess, P, guess_cov)
    assert res.ok and res.unconstrained == 1
    # Across the wall and in heading the scan decides; along it the guess stays.
    assert abs(res.pose[0] - true[0]) < 2e-3 and abs(res.pose[2] - true[2]) < 1e-3
    assert abs(res.pose[1] - guess[1]) < 5e-3
    # The along-wall uncertainty is the guess's, the across-wall one the scan's.
    assert res.cov[1, 1] == pytest.approx(guess_cov[1, 1], rel=0.2)
    assert res.cov[0, 0] < 1e-2 * guess_cov[0, 0]


def test_monte_carlo_nees_of_matches_on_the_simulator_is_consistent():
    """Consecutive scans of a simulated lap (noise, quantum, mixed pixels): mean NEES near 3."""
    sim = Simulator(SimConfig(seed=3))
    frames = [next(sim) for _ in range(700)]
    rng = np.random.default_rng(5)
    nees = []
    for a, b in zip(frames[::7], frames[1::7]):
        true = relative(a.true_pose, b.true_pose)
        ref = ReferenceScan.build(points(sim.world, a.true_pose, sim.config.lidar, rng))
        res = match(ref, points(sim.world, b.true_pose, sim.config.lidar, rng), b.odom_delta, P)
        assert res.ok
        err = res.pose - true
        err[2] = wrap_angle(err[2])
        nees.append(err @ np.linalg.solve(res.cov, err))
    # 100 draws of chi2_3 have a mean of 3 +- 0.25; the Gauss-Newton covariance
    # alone (cov_scale 1) gives about 6 here.
    assert 2.0 < np.mean(nees) < 4.0, np.mean(nees)


@settings(max_examples=25, deadline=None)
@given(s_m=st.floats(0.0, 40.0), noisy=st.booleans(), seed=st.integers(0, 2**16))
def test_matching_a_scan_to_itself_gives_the_identity(s_m, noisy, seed):
    sim = Simulator(SimConfig(seed=0))
    pose = sim.trajectory.path.pose_at(s_m)
    pts = points(HALL, pose, LidarModel() if noisy else EXACT, np.random.default_rng(seed))
    res = match(ReferenceScan.build(pts), pts, np.zeros(3), P, np.diag([1e-2, 1e-2, 1e-2]))
    assert res.ok
    np.testing.assert_allclose(res.pose, np.zeros(3), atol=1e-9)


def test_the_tracker_beats_its_noisy_odometry_and_is_deterministic():
    cfg = SimConfig(seed=2)
    sim = Simulator(cfg)
    frames = [next(sim) for _ in range(300)]
    rng = np.random.default_rng(0)
    scans = [points(sim.world, f.true_pose, cfg.lidar, rng) for f in frames]
    # Odometry much worse than the simulator's: 10 % too long and a heading bias of 0.1° per scan.
    noisy = [np.array([f.odom_delta[0] * 1.1, f.odom_delta[1] * 1.1, f.odom_delta[2] + 0.002]) for f in frames]
    q = np.diag([1e-4, 1e-4, 1e-4])

    def run():
        tracker, pose, odo, out = ScanTracker(P), frames[0].true_pose, frames[0].true_pose, []
        for k, (pts, u) in enumerate(zip(scans, noisy)):
            step = tracker.step(pts, u if k else np.zeros(3), q)
            if k == 0:
                assert step.match.status is MatchStatus.NO_REFERENCE
            else:
                pose, odo = compose(pose, step.increment), compose(odo, u)
            out.append((pose, odo, step.matched))
        return out, tracker

    first, tracker = run()
    second, _ = run()
    assert all(np.array_equal(a[0], b[0]) for a, b in zip(first, second))
    err_sm = [np.hypot(*(p[:2] - f.true_pose[:2])) for (p, _, _), f in zip(first, frames)]
    err_odo = [np.hypot(*(o[:2] - f.true_pose[:2])) for (_, o, _), f in zip(first, frames)]
    assert sum(m for _, _, m in first) >= 290
    # Along a corridor the scans leave the motion to odometry, so its scale error still shows.
    assert max(err_sm) < 0.2 * max(err_odo) and max(err_sm) < 0.2, (max(err_sm), max(err_odo))
    # Only the recent reference scans are kept (memory of a long run); more were made: the oldest
    # kept is far from the start.
    assert len(tracker.reference_scans) == scan_match.REFERENCES_KEPT
    assert np.hypot(*tracker.reference_scans[0].pose[:2]) > 5 * scan_match.REFERENCE_TRANS_M


def test_the_tracker_falls_back_to_odometry_and_skip_moves_its_pose():
    tracker = ScanTracker(P)
    q = np.diag([1e-4, 1e-4, 1e-5])
    tracker.step(points(HALL, CORNER_POSE), np.zeros(3), q)
    tracker.skip([0.1, 0.0, 0.0])
    np.testing.assert_allclose(tracker.pose, [0.1, 0.0, 0.0])
    step = tracker.step(np.zeros((3, 2)), [0.05, 0.0, 0.01], q)
    assert not step.matched and step.match.status is MatchStatus.TOO_FEW_POINTS
    np.testing.assert_array_equal(step.increment, [0.05, 0.0, 0.01])
    np.testing.assert_array_equal(step.cov, q)


def test_bad_inputs_and_params_are_rejected():
    ref = ReferenceScan.build(points(HALL, CORNER_POSE))
    with pytest.raises(InputError):
        match(ref, points(HALL, CORNER_POSE), [0.0, np.nan, 0.0], P)
    with pytest.raises(InputError):
        match(ref, points(HALL, CORNER_POSE), np.zeros(3), P, np.eye(2))
    with pytest.raises(InputError):
        ScanTracker(P).step(np.zeros((0, 2)), np.zeros(3), np.eye(2))
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ConfigError):
            ScanMatchParams(max_point_range_m=bad)


def test_a_constrained_match_ignores_a_tight_guess_in_its_estimate_and_so_in_its_covariance():
    """The estimate does not use the guess where the scan decides; the covariance must not either."""
    rng = np.random.default_rng(3)
    lidar = LidarModel()
    ref = ReferenceScan.build(points(HALL, CORNER_POSE, lidar, rng))
    cur = points(HALL, compose(CORNER_POSE, [0.05, 0.0, 0.01]), lidar, rng)
    free = match(ref, cur, np.array([0.05, 0.0, 0.01]), P)
    tight = match(ref, cur, np.array([0.05, 0.0, 0.01]), P, np.diag([1e-8, 1e-8, 1e-10]))
    assert free.ok and tight.ok and tight.unconstrained == 0
    np.testing.assert_allclose(tight.pose, free.pose, atol=1e-12)
    np.testing.assert_allclose(tight.cov, free.cov, rtol=1e-9)


def _standing_tracker_covs(n: int) -> tuple[list[np.ndarray], list]:
    rng = np.random.default_rng(4)
    tracker = ScanTracker(P)
    q = np.diag([1e-4, 1e-4, 1e-5])
    covs, steps = [], []
    for k in range(n):
        step = tracker.step(points(HALL, CORNER_POSE, LidarModel(), rng), np.zeros(3), q)
        steps.append(step)
        if k:
            covs.append(step.cov)
    return covs, steps


def test_matches_against_one_reference_do_not_add_up_as_a_random_walk():
    """Standing still, every scan matches the same keyframe: the chain's error is one match's, not n."""
    covs, steps = _standing_tracker_covs(12)
    assert all(s.matched and s.match.unconstrained == 0 for s in steps[1:])
    one = steps[1].match.cov
    total = np.sum(covs, axis=0)
    # The handed-out covariances sum to about the largest single match's (a running
    # maximum), far below the 11 of a random walk.
    assert np.trace(total) <= 1.5 * max(np.trace(s.match.cov) for s in steps[1:])
    assert np.trace(total) >= 0.99 * np.trace(one)
    # Every increment's covariance is positive semi-definite.
    assert all(np.linalg.eigvalsh(c).min() >= -1e-18 for c in covs)


def _turns(world_name: str, lead_scans: int, starts: int = 8, follows_last: bool = True) -> list[float]:
    """Heading error (deg) of the tracker after each of a set of turns in place, odometry ``lead_scans``
    early (1: as MIT Killian's log, whose odometry runs about a scan ahead of its laser) or in step (0)."""
    world = build_world(world_name)
    sim = Simulator(SimConfig(world_name=world_name, seed=1))
    frames = [next(sim) for _ in range(3000)]
    rng = np.random.default_rng(0)
    errors = []
    for k in rng.choice(len(frames), starts, replace=False):
        for turn_deg in (15.0, 20.0, -15.0, -20.0):
            true = [np.zeros(3)] * 2 + [np.array([0.02, 0.0, np.radians(turn_deg)])] * 5 + [np.array([0.02, 0.0, 0.0])] * 3
            odom = true[lead_scans:] + true[-1:] * lead_scans
            tracker, pose, est = ScanTracker(P), frames[k].true_pose, frames[k].true_pose
            tracker.step(points(world, pose, LidarModel(), rng), np.zeros(3), np.eye(3) * 1e-4)
            for u, o in zip(true, odom):
                pose = compose(pose, u)
                step = tracker.step(points(world, pose, LidarModel(), rng), o,
                                    np.diag([1e-4, 1e-4, 4e-4 * abs(o[2]) + 1e-6]), follows_last)
                est = compose(est, step.increment)
            errors.append(abs(np.degrees(wrap_angle(est[2] - pose[2]))))
    return errors


def test_odometry_a_scan_early_in_a_turn_is_caught_by_the_second_guess(monkeypatch):
    """Matched from odometry a turn's worth off (it stopped turning a scan before the laser did), a
    scan can settle a turn short; the previous motion as a second guess catches most of those."""
    with_second = _turns("large_building_empty", lead_scans=1)
    monkeypatch.setattr(scan_match, "SECOND_GUESS_MIN_RAD", np.inf)
    without = _turns("large_building_empty", lead_scans=1)
    lost = lambda errors: sum(e > 1.0 for e in errors)
    assert lost(without) >= 3 and lost(with_second) <= lost(without) // 2, (lost(without), lost(with_second))


def test_odometry_in_step_with_the_laser_tracks_every_turn_either_way(monkeypatch):
    assert max(_turns("hallway_loop", lead_scans=0, starts=4)) < 1.0
    monkeypatch.setattr(scan_match, "SECOND_GUESS_MIN_RAD", np.inf)
    assert max(_turns("hallway_loop", lead_scans=0, starts=4)) < 1.0


@settings(max_examples=60, deadline=None)
@given(first_ok=st.booleans(), other_ok=st.booleans(), unconstrained=st.integers(0, 3),
       first_inliers=st.floats(0.0, 1.0), other_inliers=st.floats(0.0, 1.0))
def test_the_second_guess_wins_only_usable_fully_constrained_and_clearly_better(first_ok, other_ok, unconstrained,
                                                                                first_inliers, other_inliers):
    def result(ok: bool, inliers: float, free: int) -> MatchResult:
        status = MatchStatus.OK if ok else MatchStatus.NOT_CONVERGED
        return MatchResult(status, np.zeros(3), np.eye(3), inlier_ratio=inliers, unconstrained=free)
    first, other = result(first_ok, first_inliers, 0), result(other_ok, other_inliers, unconstrained)
    taken = fits_better(other, first)
    if not other_ok or unconstrained:
        assert not taken
    elif not first_ok:
        assert taken
    else:
        assert taken == (other_inliers >= first_inliers + SECOND_GUESS_INLIER_MARGIN)


def test_across_lost_scans_the_previous_motion_is_no_guess(monkeypatch):
    """After scans were lost (a restarted router) the previous motion is a step of another length:
    the tracker matches from odometry alone, as it did before the second guess existed."""
    across_a_gap = _turns("hallway_loop", lead_scans=1, starts=3, follows_last=False)
    monkeypatch.setattr(scan_match, "SECOND_GUESS_MIN_RAD", np.inf)
    assert across_a_gap == _turns("hallway_loop", lead_scans=1, starts=3)
