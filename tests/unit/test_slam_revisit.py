"""The along-the-lap report: revisit detection and per-step error, sigma and NEES."""

from __future__ import annotations

import numpy as np
import pytest

from lrfslam.evaluation.slam_mc import RunResult
from lrfslam.evaluation.slam_revisit import along_lap, first_revisit


def _square_lap(n=400, side_m=10.0):
    s = np.linspace(0.0, 4.0 * side_m, n, endpoint=False)
    leg, t = np.divmod(s, side_m)
    corners = np.array([(0, 0), (side_m, 0), (side_m, side_m), (0, side_m)], dtype=float)
    dirs = np.array([(1, 0), (0, 1), (-1, 0), (0, -1)], dtype=float)
    xy = corners[leg.astype(int)] + t[:, None] * dirs[leg.astype(int)]
    xy = np.vstack((xy, xy[:60]))  # and on past the start
    return np.column_stack((xy, np.zeros(len(xy))))


def test_first_revisit_is_the_first_return_after_leaving():
    poses = _square_lap()
    k = first_revisit(poses)
    assert k is not None and 390 <= k <= 400
    assert first_revisit(poses[:300]) is None
    assert first_revisit(np.zeros((50, 3))) is None


def _result(true, est, sigma_m):
    covs = np.tile(np.diag([sigma_m**2, sigma_m**2, 1e-4]), (len(true), 1, 1))
    empty = np.zeros(0)
    return RunResult(true, est, true, covs, empty, empty, 0, empty, 0, 0, 0, 0, empty, empty)


def test_along_lap_reports_error_sigma_and_nees():
    true = _square_lap()
    est = true.copy()
    est[:, 0] += 0.3  # 0.3 m off everywhere, sigma 0.1 m: NEES 9
    rows = along_lap([_result(true, est, 0.1), _result(true, true, 0.1)], [10, 200])
    assert [r["step"] for r in rows] == [10, 200]
    assert rows[0]["err_m"] == pytest.approx(0.15) and rows[0]["err_max_m"] == pytest.approx(0.3)
    assert rows[1]["sigma_m"] == pytest.approx(0.1 * np.sqrt(2.0))
    assert rows[1]["nees"] == pytest.approx(4.5)
