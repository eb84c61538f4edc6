"""Monte-Carlo consistency helpers and a short seeded run on the simulator."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from lrfslam.algo.geometry import wrap_angle
from lrfslam.evaluation.slam_mc import (
    PHANTOM,
    McConfig,
    ate_rmse,
    label_points,
    nees_band,
    pose_nees,
    run_once,
    summarise,
    truth_clusters,
)


def test_pose_nees_known_value_and_heading_wrap():
    covs = np.tile(np.diag([4.0, 1.0, 0.25]), (2, 1, 1))
    true = np.array([[2.0, 1.0, 0.5], [0.0, 0.0, -np.pi + 0.1]])
    est = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, np.pi - 0.1]])
    # Second row: the heading error is 0.2 rad across the ±π seam, not 2π − 0.2.
    np.testing.assert_allclose(pose_nees(true, est, covs), [3.0, 0.2**2 / 0.25])


def test_ate_rmse_known_value():
    true = np.zeros((4, 3))
    est = np.array([[3.0, 4.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    assert ate_rmse(true, est) == pytest.approx(np.sqrt(25.0 / 4))


@pytest.mark.parametrize("n_runs, band", [(30, (2.19, 3.94)), (50, (2.36, 3.72))])
def test_nees_band_matches_tabulated_values(n_runs, band):
    np.testing.assert_allclose(nees_band(n_runs, 3), band, atol=0.006)


def test_short_runs_are_seeded_and_consistent():
    cfg = McConfig(n_runs=2, n_steps=150)
    a, b = run_once(cfg, 0), run_once(cfg, 0)
    np.testing.assert_array_equal(a.est_poses, b.est_poses)
    s = summarise([a, run_once(cfg, 1)])
    assert s["wrong_associations"] == 0 and s["matched_observations"] > 100
    # A matched filter: NIS near its χ²₂ mean, NEES not far above χ²₃'s, and
    # landmarks within a few centimetres after 7.5 m of driving.
    assert 1.0 < s["mean_nis_matched"] < 3.0
    assert s["mean_nees_per_step"].mean() < 6.0
    assert s["landmark_rmse_m"] < 0.05


def test_label_points_and_jamb_clusters():
    truth = np.array([[0.0, 0.0], [0.0, 0.15], [5.0, 0.0]])
    labels = label_points(np.array([[0.02, 0.14], [5.1, 0.0], [2.0, 2.0]]), truth, 0.15)
    np.testing.assert_array_equal(labels, [1, 2, PHANTOM])
    # The two faces of a 0.15 m jamb are one feature; a far corner is its own.
    np.testing.assert_array_equal(truth_clusters(truth, 0.15), [0, 0, 2])


@pytest.mark.parametrize("sets, final_m, max_m, ate_m", [
    # Default: the slam step predicts with the scan-matched motion. Seed 0: ATE 1.7 cm,
    # at worst 3.0 cm, ends within 2.5 mm.
    ((), 0.01, 0.05, 0.03),
    # The paper's odometry-driven filter. Seed 0: ATE 4.3 cm, at worst 9.2 cm, ends
    # within 8 mm; the heading is held by the walls' direction (4 mrad at worst).
    (("slam.scan_matching=false",), 0.03, 0.15, 0.08),
])
def test_real_pipeline_closes_the_loop_without_wrong_pairings(sets, final_m, max_m, ate_m):
    # One lap (about 5 s) of simulated scans through the denoise, feature and
    # slam service steps, as `lrfslam up` runs them.
    r = run_once(McConfig(n_runs=1, features="extractor", stage_sets=sets), 0)
    s = summarise([r])
    assert s["wrong_confirmed"] == 0 and s["phantoms_confirmed"] == 0
    assert s["matched_observations"] > 1000 and s["landmarks_per_run"] >= 30
    err = np.hypot(*(r.true_poses[:, :2] - r.est_poses[:, :2]).T)
    odom_final = np.hypot(*(r.true_poses[-1, :2] - r.odom_poses[-1, :2]))
    # Seed 0 ends 1.4 m off by odometry alone (ATE 0.82 m).
    assert odom_final > 0.3 and err[-1] < final_m
    assert err.max() < max_m and s["ate_rmse_m"][0] < ate_m
    assert np.abs(wrap_angle(r.true_poses[:, 2] - r.est_poses[:, 2])).max() < 0.01
    assert s["mean_nees_per_step"].mean() < 4.0


def test_true_wall_direction_pins_the_heading_of_the_estimator():
    # True corners plus the true wall direction (1.3 mrad, what the extractor
    # measures): the heading error stays at a few mrad, a third of the corners-only run.
    base = McConfig(n_runs=1, n_steps=300)
    walls, corners = run_once(replace(base, truth_wall_sigma_rad=0.0013), 0), run_once(base, 0)
    heading = [np.abs(wrap_angle(r.true_poses[:, 2] - r.est_poses[:, 2])).max() for r in (walls, corners)]
    assert heading[0] < 0.006 and heading[1] > 2 * heading[0]
    assert ate_rmse(walls.true_poses, walls.est_poses) < 0.5 * ate_rmse(corners.true_poses, corners.est_poses)


@pytest.mark.slow   # end to end, long: the slow step (.ci/run step 3)
def test_with_the_mapper_its_closures_are_judged_by_the_truth():
    # A lap and a half of the hallway loop (59 m): the mapper closes the loop, and each closure
    # it tried is judged against the true poses of its keyframes.
    cfg = McConfig(n_runs=1, n_steps=1800, world_name="hallway_loop", features="extractor", mapper=True)
    result = run_once(cfg, 0)
    c = result.closures
    assert c["accepted"] > 0
    assert c["accepted.covered"] == c["accepted"]   # every stamp is a simulated frame's
    assert c["accepted.right"] == c["accepted"] and c["false_accepts"] <= c["accepted"] // 10
    s = summarise([result])
    assert s["closures"] == c
    assert result.map_final_poses.shape == result.true_poses.shape


@pytest.mark.slow
@pytest.mark.parametrize("run_index", [0, 1])
def test_the_mappers_closures_do_not_bend_the_large_building(run_index):
    # The large building with people and an uncalibrated robot (one lap, 261 m): every closure the
    # mapper accepted is right, and its final trajectory is no worse than the EKF under it. Run 1
    # once took a twin door a period along for the place (7.4 m against the EKF's 0.33 m), when a
    # candidate's map was narrower than the window searched in it.
    cfg = McConfig(n_runs=2, n_steps=5225, world_name="large_building", features="extractor", mapper=True)
    r = run_once(cfg, run_index)
    assert r.closures["accepted"] > 50
    assert r.closures["accepted.right"] == r.closures["accepted"]
    assert ate_rmse(r.true_poses, r.map_final_poses) <= ate_rmse(r.true_poses, r.est_poses) + 0.02
