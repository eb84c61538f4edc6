"""The closure audit: every attempt the mapper reports, judged against relations made from the truth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lrfslam.algo.geometry import compose, relative, rotate_covariance
from lrfslam.algo.loop_closure import VERDICTS, ClosureAttempt, LoopClosingMapper
from lrfslam.evaluation import closure_audit
from lrfslam.evaluation.relations import load_relations
from lrfslam.sim.simulator import OdometryNoise, SimConfig, Simulator

RATE_HZ = 5.0


def relations_text(rows) -> str:
    """A Freiburg relations file: ``(t1 s, t2 s, delta (3,))`` rows."""
    return "".join(" ".join(repr(float(v)) for v in (t1, t2, d[0], d[1], 0, 0, 0, d[2])) + "\n" for t1, t2, d in rows)


@pytest.fixture(scope="module")
def hallway():
    """The simulator's hallway loop, once and a third, drifting odometry fed as the EKF pose: the
    mapper's closure attempts, the truth per scan and the stamps (s)."""
    cfg = SimConfig(speed_mps=1.0, rate_hz=RATE_HZ, seed=3,
                    odometry=OdometryNoise(trans_sigma_per_sqrt_m=0.02, rot_sigma_per_sqrt_rad=0.03, rot_sigma_per_sqrt_m=0.02))
    mapper = LoopClosingMapper()
    attempts: list[ClosureAttempt] = []
    mapper.observer = attempts.append
    truth, stamps = [], []
    for frame, _ in zip(Simulator(cfg), range(int(1.35 * 62 * RATE_HZ)), strict=False):
        angles, ranges = frame.scan.angles_rad, frame.scan.ranges_m
        ok = np.isfinite(ranges)
        pts = np.column_stack([ranges[ok] * np.cos(angles[ok]), ranges[ok] * np.sin(angles[ok])])
        mapper.add_scan(int(frame.t_s * 1e9), frame.odom_pose, pts)
        truth.append(frame.true_pose)
        stamps.append(int(frame.t_s * 1e9) / 1e9)
    return mapper, attempts, np.array(truth), np.array(stamps)


def test_the_mapper_reports_every_closure_it_accepted_and_dropped(hallway):
    mapper, attempts, _, _ = hallway
    stats = mapper.stats
    verdicts = [a.verdict for a in attempts]
    assert set(verdicts) <= set(VERDICTS) and stats.accepted >= 3
    for verdict in ("accepted", "low_score", "ambiguous", "refine_failed", "gated", "removed"):
        assert verdicts.count(verdict) == getattr(stats, verdict), verdict
    for a in attempts:
        assert a.old_stamp_ns < a.new_stamp_ns and a.pose.shape == (3,)
        assert (a.cov is not None) == (a.verdict in ("accepted", "gated"))


def test_each_attempt_is_judged_against_the_relation_that_covers_it(hallway):
    _, attempts, truth, stamps = hallway
    index = {round(s, 6): i for i, s in enumerate(stamps)}
    # A relation from one scan after each attempt's old keyframe to one scan before its new one
    # (every other one written the other way round), so the audit must bridge and turn it.
    rows = []
    for j, a in enumerate(attempts):
        o, n = index[round(a.old_stamp_ns / 1e9, 6)] + 1, index[round(a.new_stamp_ns / 1e9, 6)] - 1
        rows.append((stamps[o], stamps[n], relative(truth[o], truth[n])) if j % 2 == 0 else
                    (stamps[n], stamps[o], relative(truth[n], truth[o])))
    # The truth bridges the relation's scans to the keyframes': the error is exactly the pose's.
    judged = closure_audit.judge(attempts, load_relations(relations_text(rows)), stamps, truth, 1e-3)
    assert len(judged) == len(attempts) and all(j.covered for j in judged)
    for j in judged:
        a = j.attempt
        true_rel = relative(truth[index[round(a.old_stamp_ns / 1e9, 6)]], truth[index[round(a.new_stamp_ns / 1e9, 6)]])
        expected = relative(true_rel, a.pose)
        np.testing.assert_allclose(j.error, expected, atol=1e-9)
        assert j.right == (math.hypot(*expected[:2]) <= closure_audit.RIGHT_M
                           and abs(expected[2]) <= closure_audit.RIGHT_RAD)
        if a.cov is not None:   # the closure's covariance is in the old keyframe's axes, the error in the truth's
            cov = rotate_covariance(a.cov, -true_rel[2])
            assert j.chi2 == pytest.approx(expected @ np.linalg.solve(cov, expected))
    accepted = [j for j in judged if j.attempt.verdict == "accepted"]
    assert accepted and all(j.right for j in accepted)   # the hallway's closures are all right
    text = closure_audit.report(judged)
    assert f"of {len(accepted)} covered accepted closures" in text and "precision 1.000" in text


def test_a_closure_the_relations_contradict_is_a_false_accept_and_one_they_do_not_cover_is_not_judged():
    stamps = np.arange(0.0, 20.0, 0.2)
    ekf = np.column_stack([stamps, np.zeros_like(stamps), np.zeros_like(stamps)])   # 1 m/s along x
    truth_rel = np.array([10.0, 0.0, 0.0])                                        # 10 s apart: 10 m
    rels = load_relations(relations_text([(1.0, 11.0, truth_rel)]))
    cov = np.diag([1e-4, 1e-4, 1e-6])

    def attempt(t_old, t_new, pose, verdict="accepted"):
        return ClosureAttempt(round(t_old * 1e9), round(t_new * 1e9), np.array(pose), cov, verdict)

    near = relative(ekf[6], ekf[51])   # keyframes at 1.2 s and 10.2 s: bridged 0.2 s and 0.8 s
    good = attempt(1.2, 10.2, compose(near, [0.01, 0.0, 0.0]))
    bad = attempt(1.2, 10.2, compose(near, [0.5, 0.0, 0.0]))
    missed = attempt(1.2, 10.2, near, "gated")
    far = attempt(5.0, 6.0, [1.0, 0.0, 0.0])
    judged = closure_audit.judge([good, bad, missed, far], rels, stamps, ekf, 1e-3)
    np.testing.assert_allclose(judged[0].error, [0.01, 0, 0], atol=1e-9)
    assert judged[0].chi2 == pytest.approx(1.0) and not judged[0].false_accept and judged[0].right
    assert judged[1].false_accept and not judged[1].right
    assert judged[2].right and not judged[2].false_accept
    assert not judged[3].covered and judged[3].error is None
    counts = closure_audit.summary_counts(judged)
    assert counts["false_accepts"] == 1 and counts["accepted.covered"] == 2 and counts["gated.right"] == 1
    text = closure_audit.report(judged)
    assert "false accepts" in text and ": 1 of 2 covered" in text
    assert "precision 0.500" in text and "recall 0.500" in text


def test_on_the_simulator_each_attempt_is_judged_by_the_true_poses_of_its_keyframes():
    stamps = np.arange(100, dtype=np.int64) * 100_000_000   # 10 Hz
    rng = np.random.default_rng(3)
    truth = np.cumsum(rng.normal(size=(100, 3)) * [0.1, 0.1, 0.05], axis=0)
    cov = np.diag([1e-4, 1e-4, 1e-6])
    true_rel = relative(truth[10], truth[80])

    def attempt(i, j, pose, verdict="accepted"):
        return ClosureAttempt(int(stamps[i]), int(stamps[j]), np.asarray(pose, dtype=float), cov, verdict)

    right = attempt(10, 80, compose(true_rel, [0.0, 0.01, 0.0]))
    wrong = attempt(10, 80, compose(true_rel, [6.0, 0.0, 0.0]))          # a door period off
    dropped = attempt(10, 80, compose(true_rel, [0.05, 0.0, 0.01]), "ambiguous")
    unknown = ClosureAttempt(int(stamps[10]) + 1, int(stamps[80]), true_rel, cov, "accepted")
    judged = closure_audit.judge_by_truth([right, wrong, dropped, unknown], stamps, truth)
    np.testing.assert_allclose(judged[0].error, [0.0, 0.01, 0.0], atol=1e-9)
    assert judged[0].right and judged[0].chi2 == pytest.approx(1.0)
    assert judged[1].false_accept and not judged[1].right
    assert judged[2].right and judged[2].attempt.verdict == "ambiguous"
    assert not judged[3].covered
    counts = closure_audit.summary_counts(judged)
    assert closure_audit.precision_recall(counts) == (0.5, 0.5)


def _straight_ekf():
    stamps = np.arange(0.0, 400.0, 0.1)
    return stamps, np.column_stack([0.5 * stamps, np.zeros_like(stamps), np.zeros_like(stamps)])   # 0.5 m/s along x


def test_the_reference_noise_is_the_short_relations_error_at_zero_span_and_its_growth_with_the_span():
    """Relations under 2 s whose own error has a known variance, and grows by a known one per second
    (the EKF's drift, here put in the relations): the fit finds both."""
    stamps, ekf = _straight_ekf()
    rng = np.random.default_rng(5)
    relation_var = np.array([1e-4, 4e-4, 1e-5])
    per_s_var = np.array([2e-4, 1e-4, 3e-6])
    rows = []
    for _ in range(6000):
        i = int(rng.integers(0, stamps.size - 25))
        j = i + int(rng.integers(1, 21))                       # 0.1–2 s on
        span = stamps[j] - stamps[i]
        noise = rng.normal(size=3) * np.sqrt(relation_var + span * per_s_var)
        rows.append((stamps[i], stamps[j], compose(relative(ekf[i], ekf[j]), noise)))
    rows.append((stamps[0], stamps[100], relative(ekf[0], ekf[100]) + [5.0, 0.0, 0.0]))   # 10 s: not used
    noise = closure_audit.reference_noise(load_relations(relations_text(rows)), stamps, ekf, 1e-3)
    np.testing.assert_allclose(noise.relation, relation_var, rtol=0.25)
    np.testing.assert_allclose(noise.per_s, per_s_var, rtol=0.25)


def test_a_closure_off_by_no_more_than_the_references_own_error_is_no_false_accept_beyond_it():
    stamps, ekf = _straight_ekf()
    rng = np.random.default_rng(7)
    # Short relations whose own error is 2 cm and 0.5 degrees (sigma), and one 10 s relation to judge by.
    sigma = np.array([0.02, 0.02, math.radians(0.5)])
    rows = [(stamps[i], stamps[i + 10], compose(relative(ekf[i], ekf[i + 10]), rng.normal(size=3) * sigma))
            for i in range(0, 3000, 3)]
    rows.append((stamps[10], stamps[110], relative(ekf[10], ekf[110])))
    rels = load_relations(relations_text(rows))
    cov = np.diag([0.005 ** 2, 0.005 ** 2, math.radians(0.1) ** 2])   # claims 5 mm and 0.1 degrees
    truth = relative(ekf[10], ekf[110])

    def attempt(off):
        return ClosureAttempt(round(stamps[10] * 1e9), round(stamps[110] * 1e9), compose(truth, off), cov, "accepted")

    within = attempt([0.0, 0.0, math.radians(0.6)])   # 6 of its own sigmas, one of the reference's
    beyond = attempt([0.0, 0.0, math.radians(3.0)])   # beyond both
    judged = closure_audit.judge([within, beyond], rels, stamps, ekf, 1e-3)
    assert judged[0].false_accept and not judged[0].false_accept_beyond_reference
    assert judged[1].false_accept and judged[1].false_accept_beyond_reference
    counts = closure_audit.summary_counts(judged)
    assert counts["false_accepts"] == 2 and counts["false_accepts_beyond_reference"] == 1
    assert "2 of 2 covered accepted closures; 1 beyond" in closure_audit.report(judged)
