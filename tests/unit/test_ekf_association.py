"""Data association: NIS helper, gated NN, JCBB (brute-force oracle), corridor ambiguity."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import chi2

from lrfslam.algo import association
from lrfslam.algo.ekf_slam import EkfParams, EkfSlam, ObsStatus
from lrfslam.algo.geometry import to_frame


def filter_with_map(lms, pose_est, pose_sigmas, lm_sigma_m, params):
    """A filter whose map is ``lms`` (all confirmed), with a diagonal prior."""
    n = len(lms)
    cov = np.zeros((3 + 2 * n, 3 + 2 * n))
    cov[:3, :3] = np.diag(np.square(pose_sigmas))
    cov[3:, 3:] = np.eye(2 * n) * lm_sigma_m**2
    snap = {
        "format": 1,
        "state_mean": np.concatenate((pose_est, np.ravel(lms))),
        "state_cov": cov,
        "landmark_ids": np.arange(n, dtype=np.int64),
        "landmark_kinds": np.zeros(n, dtype=np.int8),
        "landmark_sightings": np.full(n, 3),
        "landmark_confirmed": np.ones(n, dtype=bool),
        "landmark_born": np.zeros(n, dtype=np.int64),
        "landmark_view_ref_rad": np.zeros(n),
        "landmark_view_spread_rad": np.zeros(n),
        "next_id": n,
        "n_observe": 0,
    }
    return EkfSlam.restore(params, snap)


def test_nis_2d_matches_linear_solve():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(7, 2, 2))
    covs = a @ a.transpose(0, 2, 1) + 0.1 * np.eye(2)
    nu = rng.normal(size=(7, 2))
    nis, log_det = association.nis_2d(nu, covs)
    ref = np.einsum("ki,ki->k", nu, np.linalg.solve(covs, nu[..., None])[..., 0])
    np.testing.assert_allclose(nis, ref, rtol=1e-12)
    np.testing.assert_allclose(log_det, np.log(np.linalg.det(covs)), rtol=1e-12)


def test_nearest_neighbour_gates_and_resolves_contested_landmark():
    nis = np.array([[1.0, 5.0], [0.5, 8.0], [20.0, 30.0]])
    pairing = association.nearest_neighbour(nis, np.zeros_like(nis), gate_assoc_chi2=9.21)
    # Landmark 0 goes to its closer observation 1; observation 0 does not fall back
    # to a second choice (it is left to the caller as ambiguous); 2 is out of gate.
    np.testing.assert_array_equal(pairing, [-1, 0, -1])


def test_nearest_neighbour_normalises_by_log_det():
    nis = np.array([[2.0, 1.0]])
    log_det = np.array([[0.0, 3.0]])  # landmark 1 is far more uncertain
    np.testing.assert_array_equal(association.nearest_neighbour(nis, log_det, 9.21), [0])


def brute_force(n_obs, cand_obs, cand_lm, innov, joint, confidence):
    """Best (pairs, D²) over every hypothesis, by enumeration.

    JCBB grows a hypothesis one observation at a time and gates every step, so a
    hypothesis counts only if each of its prefixes (in observation order) is
    jointly compatible too: with a χ² gate that widens with the pair count a set
    can pass while one of its subsets fails, and JCBB (Neira and Tardós) never
    reaches such a set.
    """

    def d2_of(chosen):
        idx = np.ravel([(2 * c, 2 * c + 1) for c in chosen])
        nu = innov[chosen].ravel()
        return float(nu @ np.linalg.solve(joint[np.ix_(idx, idx)], nu))

    best = (0, 0.0)
    options = [[None] + [c for c in range(cand_obs.size) if cand_obs[c] == k] for k in range(n_obs)]
    for hyp in itertools.product(*options):
        chosen = [c for c in hyp if c is not None]
        if not chosen or len({int(cand_lm[c]) for c in chosen}) < len(chosen):
            continue
        if all(d2_of(chosen[:j]) < chi2.ppf(confidence, 2 * j) for j in range(1, len(chosen) + 1)):
            d2 = d2_of(chosen)
            if len(chosen) > best[0] or (len(chosen) == best[0] and d2 < best[1]):
                best = (len(chosen), d2)
    return best


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n_obs=st.integers(1, 4), n_lm=st.integers(1, 4))
def test_jcbb_finds_the_brute_force_optimum(seed, n_obs, n_lm):
    rng = np.random.default_rng(seed)
    pairs = [(k, m) for k in range(n_obs) for m in range(n_lm) if rng.random() < 0.6]
    if not pairs:
        return
    cand_obs, cand_lm = np.array(pairs).T
    a = rng.normal(size=(2 * len(pairs), 2 * len(pairs)))
    joint = a @ a.T / len(pairs) + 0.3 * np.eye(2 * len(pairs))
    innov = rng.normal(scale=1.2, size=(len(pairs), 2))
    # The filter hands JCBB individually compatible candidates only.
    blocks = np.stack([joint[2 * k: 2 * k + 2, 2 * k: 2 * k + 2] for k in range(len(pairs))])
    nis, _ = association.nis_2d(innov, blocks)
    keep = nis < chi2.ppf(0.99, 2)
    if not keep.any():
        return
    pairs = [pr for pr, k in zip(pairs, keep, strict=True) if k]
    cand_obs, cand_lm, innov = cand_obs[keep], cand_lm[keep], innov[keep]
    joint = joint[np.ix_(np.repeat(keep, 2), np.repeat(keep, 2))]
    res = association.jcbb(n_obs, cand_obs, cand_lm, innov, joint, confidence=0.99)
    n_pairs, d2 = brute_force(n_obs, cand_obs, cand_lm, innov, joint, 0.99)
    assert np.count_nonzero(res.pairing >= 0) == n_pairs
    assert res.joint_nis == pytest.approx(d2, rel=1e-9, abs=1e-12)
    assert not res.exhausted
    # Each landmark at most once, and only along candidate pairs.
    paired = res.pairing[res.pairing >= 0]
    assert paired.size == np.unique(paired).size
    assert all((k, m) in pairs for k, m in enumerate(res.pairing) if m >= 0)


def test_jcbb_budget_is_reported():
    joint = np.eye(8)
    res = association.jcbb(4, np.arange(4), np.arange(4), np.zeros((4, 2)), joint, 0.99, max_nodes=2)
    assert res.exhausted and res.nodes <= 3


@pytest.mark.parametrize("method", ["nn", "jcbb"])
@pytest.mark.parametrize("seed", range(5))
def test_easy_scene_is_paired_correctly_by_both(method, seed):
    rng = np.random.default_rng(seed)
    gx, gy = np.meshgrid(np.arange(-4.0, 5.0, 2.0), np.arange(-4.0, 5.0, 2.0))
    lms = np.column_stack((gx.ravel(), gy.ravel())) + rng.normal(scale=0.2, size=(gx.size, 2))
    true_pose = np.array([0.3, -0.2, 0.4])
    est = true_pose + rng.normal(scale=[0.03, 0.03, 0.01])
    params = EkfParams(association=method, corner_range_sigma_m=0.02, corner_bearing_sigma_rad=0.01)
    f = filter_with_map(lms, est, [0.05, 0.05, 0.02], 0.02, params)
    seen = np.flatnonzero(np.hypot(*(lms - true_pose[:2]).T) < 4.0)
    rel = to_frame(lms[seen], true_pose)
    rng_b = np.column_stack((np.hypot(*rel.T), np.arctan2(rel[:, 1], rel[:, 0])))
    rng_b += rng.normal(scale=[0.02, 0.01], size=rng_b.shape)
    pts = rng_b[:, :1] * np.column_stack((np.cos(rng_b[:, 1]), np.sin(rng_b[:, 1])))
    rep = f.observe(pts)
    assert np.all(rep.status == ObsStatus.MATCHED)
    np.testing.assert_array_equal(rep.landmark_ids, seen)


@pytest.mark.parametrize(
    "method, unique, outcome",
    [("nn", False, "wrong"), ("nn", True, "discarded"), ("jcbb", False, "right"), ("jcbb", True, "right")],
)
def test_corridor_ambiguity_nn_fails_jcbb_resolves(method, unique, outcome):
    """Door frames every metre along a wall; odometry has put the robot 0.55 m ahead.

    Each observation is individually closest to the *next* frame, so plain NN
    shifts the whole set by one and drags the pose a metre forward; with the
    uniqueness rule NN discards the three frames that have two landmarks in gate.
    JCBB finds that pairing all four frames with their own landmarks is jointly
    compatible (one pose error explains the innovations) and prefers it because
    it pairs more; no single swap keeps that hypothesis compatible, so the
    uniqueness rule keeps it.
    """
    lms = np.column_stack((np.arange(3.0, 7.0), np.full(4, 1.5)))
    params = EkfParams(
        association=method, unique_match_required=unique, corner_range_sigma_m=0.01, corner_bearing_sigma_rad=0.005
    )
    f = filter_with_map(lms, [0.55, 0.0, 0.0], [0.6, 0.02, 0.005], 0.01, params)
    rep = f.observe(to_frame(lms, [0.0, 0.0, 0.0]))
    if outcome == "right":
        np.testing.assert_array_equal(rep.landmark_ids, np.arange(4))
        assert abs(f.pose[0]) < 0.05
    elif outcome == "wrong":
        np.testing.assert_array_equal(rep.landmark_ids[:3], [1, 2, 3])
        assert abs(f.pose[0] - 1.0) < 0.05
    else:  # only the last frame has a single landmark in its gate: the right one
        np.testing.assert_array_equal(rep.status[:3], [ObsStatus.AMBIGUOUS] * 3)
        assert rep.landmark_ids[3] == 3 and abs(f.pose[0]) < 0.1


def test_nearest_neighbour_can_require_a_unique_candidate():
    nis = np.array([[1.0, 5.0], [0.5, 30.0]])
    np.testing.assert_array_equal(association.nearest_neighbour(nis, np.zeros_like(nis), 9.21, True), [-1, 0])


def test_jcbb_unpairs_an_observation_that_could_swap_landmarks():
    # Observation 0 fits landmarks 0 and 1 about equally; observation 1 only fits 2.
    cand_obs, cand_lm = np.array([0, 0, 1]), np.array([0, 1, 2])
    innov = np.array([[0.5, 0.0], [-0.6, 0.0], [0.1, 0.1]])
    joint = np.eye(6)
    plain = association.jcbb(2, cand_obs, cand_lm, innov, joint, 0.99)
    strict = association.jcbb(2, cand_obs, cand_lm, innov, joint, 0.99, require_unique=True)
    np.testing.assert_array_equal(plain.pairing, [0, 2])
    np.testing.assert_array_equal(strict.pairing, [-1, 2])
    assert strict.joint_nis == pytest.approx(0.02)
