"""Invariants of EkfSlam over random scenarios (hypothesis)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from lrfslam.algo.ekf_slam import EkfParams, EkfSlam, ObsStatus
from lrfslam.algo.geometry import compose, to_frame
from lrfslam.algo.wall_direction import wrap_quarter

params_st = st.builds(
    EkfParams,
    association=st.sampled_from(["nn", "jcbb"]),
    min_sightings_to_confirm=st.integers(1, 3),
    tentative_max_age_updates=st.integers(1, 6),
    max_landmarks=st.integers(0, 8),
    backward_min_view_change_rad=st.floats(0.0, 0.5),
    corner_range_sigma_m=st.floats(0.005, 0.05),
    corner_bearing_sigma_rad=st.floats(0.002, 0.03),
)

scenario_st = st.fixed_dictionaries(
    {
        "seed": st.integers(0, 2**32 - 1),
        "n_world": st.integers(0, 8),
        "n_steps": st.integers(1, 15),
        "clutter": st.floats(0.0, 1.5),
        "turn_rad": st.floats(0.0, 4.0),  # large turns exercise the heading wrap
        "walls": st.booleans(),  # a wall direction after every scan
    }
)


def run_scenario(params, sc, check):
    """Drive a filter through a random world; ``check(filter, report)`` after every step."""
    rng = np.random.default_rng(sc["seed"])
    world = rng.uniform(-5, 5, size=(sc["n_world"], 2))
    f = EkfSlam(params, pose0=(0.0, 0.0, rng.uniform(-np.pi, np.pi)), pose0_cov=np.diag([1e-4, 1e-4, 1e-5]))
    truth = f.pose
    psi = rng.uniform(-np.pi, np.pi)  # the walls' direction in the world
    for _ in range(sc["n_steps"]):
        delta = np.array([rng.uniform(0, 0.4), rng.uniform(-0.05, 0.05), rng.uniform(-1, 1) * sc["turn_rad"]])
        truth = compose(truth, delta)
        f.predict(delta + rng.normal(scale=[0.01, 0.01, 0.005]))
        rel = to_frame(world, truth)
        rel = rel[np.hypot(rel[:, 0], rel[:, 1]) < 6.0]
        rel = rel + rng.normal(scale=0.01, size=rel.shape)
        pts = np.vstack((rel, rng.uniform(-4, 4, size=(rng.poisson(sc["clutter"]), 2))))
        kinds = rng.integers(0, 2, size=len(pts))
        rep = f.observe(pts, np.tile(np.eye(2) * 1e-4, (len(pts), 1, 1)), kinds)
        if sc["walls"]:
            f.observe_wall_direction(wrap_quarter(psi - truth[2]) + rng.normal(scale=0.01), 0.01)
        check(f, rep)
    return f


@settings(max_examples=40, deadline=None)
@given(params=params_st, sc=scenario_st)
def test_covariance_symmetric_psd_and_heading_wrapped(params, sc):
    def check(f, rep):
        P = f.state_cov
        scale = max(1.0, float(np.abs(P).max()))
        assert np.abs(P - P.T).max() <= 1e-12 * scale
        assert np.linalg.eigvalsh(P).min() >= -1e-9 * scale
        assert -np.pi <= f.pose[2] < np.pi
        assert np.all(np.isfinite(f.state_mean))
        assert f.n_landmarks <= params.max_landmarks
        assert rep.n_matched + rep.n_new + rep.n_ambiguous + rep.n_rejected == rep.status.size

    run_scenario(params, sc, check)


@settings(max_examples=40, deadline=None)
@given(params=params_st, sc=scenario_st)
def test_landmark_ids_are_stable_and_never_reused(params, sc):
    issued: set[int] = set()
    gone: set[int] = set()
    prev = np.zeros(0, dtype=np.int64)

    def check(f, rep):
        nonlocal prev
        ids = f.landmarks().ids
        assert ids.dtype == np.int64 and np.all(np.diff(ids) > 0)
        new = np.setdiff1d(ids, prev)
        # Every new id is larger than any id issued before and matches a NEW report.
        assert all(i > max(issued, default=-1) for i in new)
        np.testing.assert_array_equal(np.sort(rep.landmark_ids[rep.status == ObsStatus.NEW]), new)
        assert not gone & set(ids.tolist())
        matched = rep.landmark_ids[rep.status == ObsStatus.MATCHED]
        assert set(matched.tolist()) <= set(prev.tolist())
        gone.update(set(prev.tolist()) - set(ids.tolist()))
        issued.update(new.tolist())
        prev = ids

    run_scenario(params, sc, check)


@settings(max_examples=30, deadline=None)
@given(sc=scenario_st)
def test_zero_motion_with_zero_noise_floor_leaves_state_unchanged(sc):
    params = EkfParams(odom_trans_sigma_floor_m=0.0, odom_rot_sigma_floor_rad=0.0)
    f = run_scenario(params, {**sc, "n_steps": min(sc["n_steps"], 4)}, lambda f, r: None)
    x, P = f.state_mean, f.state_cov
    f.predict(np.zeros(3))
    np.testing.assert_array_equal(f.state_mean, x)
    np.testing.assert_array_equal(f.state_cov, P)
