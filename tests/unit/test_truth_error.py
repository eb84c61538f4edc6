"""The one trajectory error: offline (``ate_rmse``, ``matched_ate_rmse``) and as a run goes
(``RunningTruthError``) give the same figure for the same estimate."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from lrfslam.algo.geometry import compose, relative
from lrfslam.evaluation.truth import (
    RunningTruthError,
    anchor,
    ate_rmse,
    matched_ate_rmse,
)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31))
def test_running_and_offline_errors_agree(seed):
    rng = np.random.default_rng(seed)
    n = 50
    stamps = 10**12 + np.arange(n) * 100_000_000
    truth = np.column_stack([np.cumsum(rng.normal(0.1, 0.02, n)), rng.normal(0, 0.5, n), rng.normal(0, 1, n)])
    frame = np.array([3.0, -1.0, 0.7])      # the estimate's own map frame
    est = np.array([compose(relative(frame, p), rng.normal(0, 0.02, 3)) for p in truth])
    running = RunningTruthError()
    for s, p in zip(stamps, truth, strict=True):
        running.add_truth(int(s), p)
    kept = sorted(rng.choice(n, size=n - 10, replace=False))
    for i in kept:
        assert running.add_estimate(int(stamps[i]), est[i])
    a = anchor(truth[kept[0]], est[kept[0]])
    in_truth_frame = np.array([compose(a, e) for e in est])
    assert np.isclose(running.ate_rmse_m, ate_rmse(truth[kept], in_truth_frame[kept]))
    assert np.isclose(running.ate_rmse_m, matched_ate_rmse(stamps[kept], in_truth_frame[kept], stamps, truth))
    assert running.matched == len(kept)


def test_an_estimate_without_its_truth_is_not_matched_and_no_common_stamp_is_none():
    running = RunningTruthError()
    running.add_truth(10, np.zeros(3))
    assert not running.add_estimate(11, np.zeros(3)) and running.matched == 0
    assert np.isnan(running.ate_rmse_m)
    assert matched_ate_rmse(np.array([1]), np.zeros((1, 3)), [2], np.zeros((1, 3))) is None
