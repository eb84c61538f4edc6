"""Monte-Carlo consistency helpers and a short seeded run on the simulator."""

from __future__ import annotations

import numpy as np
import pytest

from lrfslam.evaluation.slam_mc import (
    McConfig,
    ate_rmse,
    nees_band,
    pose_nees,
    run_once,
    summarise,
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
