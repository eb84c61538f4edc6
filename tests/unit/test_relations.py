"""Tests for the Kümmerle et al. relation metric (lrfslam.evaluation.relations)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lrfslam.algo.geometry import compose, relative
from lrfslam.evaluation.relations import (
    RelationIssue,
    RelationsInputError,
    errors_by_span,
    load_relations,
    match_stamps,
    relation_errors,
)

DATA = Path(__file__).resolve().parents[1] / "data"


def relations_from(rows):
    """Relations from ``(t1, t2, x, y, yaw)`` rows."""
    lines = [" ".join(repr(float(v)) for v in (t1, t2, x, y, 0, 0, 0, yaw)) for t1, t2, x, y, yaw in rows]
    rel = load_relations(lines)
    assert not rel.issues
    return rel


# --- load_relations -------------------------------------------------------------------


def test_load_relations_fixture():
    rel = load_relations((DATA / "relations_small.relations").read_text())
    assert len(rel) == 3
    np.testing.assert_array_equal(rel.stamp1_s, [10.0, 11.0, 13.0])
    np.testing.assert_array_equal(rel.stamp2_s, [11.0, 12.5, 14.0])
    # columns x, y, yaw; z/roll/pitch (0.3 0.4 0.5 on line 7) are dropped
    np.testing.assert_array_equal(rel.delta, [[1.0, 0.0, 0.0], [0.5, -0.25, math.pi / 2], [0.1, 0.2, -3.0]])
    np.testing.assert_array_equal(rel.line_no, [2, 3, 7])
    assert [i.line_no for i in rel.issues] == [5, 6, 8]
    assert "got 7 tokens" in rel.issues[0].reason
    assert rel.issues[1] == RelationIssue(6, "not a number")
    assert rel.issues[2] == RelationIssue(8, "not finite")


def test_load_relations_empty():
    rel = load_relations([])
    assert len(rel) == 0 and rel.delta.shape == (0, 3)


# --- hand-computed errors -----------------------------------------------------------------


def test_perfect_estimate_gives_zero_error():
    stamps = np.array([10.0, 11.0, 12.5])
    poses = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.5, -0.25, math.pi / 2]])
    rel = relations_from([(10.0, 11.0, 1.0, 0.0, 0.0), (11.0, 12.5, 0.5, -0.25, math.pi / 2)])
    stats = relation_errors(stamps, poses, rel)
    assert (stats.n_relations, stats.n_used, stats.n_unmatched) == (2, 2, 0)
    assert stats.trans_abs_m.max == pytest.approx(0.0, abs=1e-12)
    assert stats.rot_abs_deg.max == pytest.approx(0.0, abs=1e-12)
    assert stats.max_match_gap_s == 0.0


def test_known_perturbation():
    # Truth: x0 = (0,0,0), x1 = (1,0,0), x2 = (1,0,pi/2) -> relations (1,0,0), (0,0,pi/2) + a rotated one.
    rel = relations_from(
        [(0.0, 1.0, 1.0, 0.0, 0.0), (1.0, 2.0, 0.0, 0.0, math.pi / 2), (0.0, 2.0, 1.0, 0.0, math.pi / 2)]
    )
    # Estimate: x1 shifted 0.3 m sideways; x2 turned 0.1 rad too far.
    poses = np.array([[0.0, 0.0, 0.0], [1.0, 0.3, 0.0], [1.0, 0.0, math.pi / 2 + 0.1]])
    stats = relation_errors(np.array([0.0, 1.0, 2.0]), poses, rel)
    # rel 0: delta = (1, .3, 0) -> e = (0, .3, 0)
    # rel 1: delta = relative((1,.3,0), (1,0,pi/2+.1)) = (0, -.3, pi/2+.1) -> |e_xy| = .3, e_t = .1
    # rel 2: delta = (1, 0, pi/2+.1) -> e = (0, 0, .1)
    np.testing.assert_allclose(stats.trans_err_m, [0.3, 0.3, 0.0], atol=1e-12)
    deg = math.degrees(0.1)
    np.testing.assert_allclose(stats.rot_err_deg, [0.0, deg, deg], atol=1e-12)
    assert stats.trans_abs_m.mean == pytest.approx(0.2)
    assert stats.trans_abs_m.std == pytest.approx(math.sqrt((0.01 + 0.01 + 0.04) / 3))
    assert stats.trans_abs_m.max == pytest.approx(0.3)
    assert stats.trans_sqr_m2.mean == pytest.approx(0.06)
    assert stats.rot_abs_deg.mean == pytest.approx(2 * deg / 3)
    assert stats.rot_sqr_deg2.mean == pytest.approx(2 * deg**2 / 3)


def test_error_is_measured_in_the_relation_frame():
    # delta* = (1, 0, pi/2); estimate (1, 0.5, pi/2): e = delta*^-1 + delta = (0.5, 0, 0).
    rel = relations_from([(0.0, 1.0, 1.0, 0.0, math.pi / 2)])
    stats = relation_errors(np.array([0.0, 1.0]), np.array([[0, 0, 0], [1.0, 0.5, math.pi / 2]]), rel)
    assert stats.trans_err_m[0] == pytest.approx(0.5)
    assert stats.trans_sqr_m2.mean == pytest.approx(0.25)
    assert stats.trans_abs_m.std == 0.0


def test_rotation_error_wraps():
    rel = relations_from([(0.0, 1.0, 0.0, 0.0, math.pi - 0.01)])
    poses = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -math.pi + 0.01]])
    stats = relation_errors(np.array([0.0, 1.0]), poses, rel)
    assert stats.rot_err_deg[0] == pytest.approx(math.degrees(0.02))


def test_unmatched_stamps_are_counted_and_excluded():
    rel = relations_from([(0.0, 1.05, 1.0, 0.0, 0.0), (0.0, 5.0, 9.0, 9.0, 0.0), (7.0, 1.0, 0.0, 0.0, 0.0)])
    poses = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    stamps = np.array([0.0, 1.0, 2.0])
    stats = relation_errors(stamps, poses, rel, max_stamp_gap_s=0.1)
    assert (stats.n_used, stats.n_unmatched) == (1, 2)
    np.testing.assert_array_equal(stats.matched, [True, False, False])
    assert np.isnan(stats.trans_err_m[1:]).all()
    assert stats.trans_abs_m.mean == pytest.approx(0.0, abs=1e-12)
    assert stats.max_match_gap_s == pytest.approx(0.05)
    tight = relation_errors(stamps, poses, rel, max_stamp_gap_s=0.049)
    assert tight.n_used == 0
    assert math.isnan(tight.trans_abs_m.mean) and math.isnan(tight.max_match_gap_s)


def test_match_stamps_unsorted_duplicates_and_ties():
    stamps = np.array([3.0, 1.0, 2.0, 1.0, 5.0])
    index, gap = match_stamps(stamps, np.array([1.0, 2.4, 4.0, 9.0, 1.2]), max_gap_s=1.0)
    # 1.0: first of the duplicates (index 1); 2.4 -> 2.0; 4.0: tie 3 vs 5 -> smaller; 9.0: none; 1.2 -> first 1.0
    np.testing.assert_array_equal(index, [1, 2, 0, -1, 1])
    np.testing.assert_allclose(gap, [0.0, 0.4, 1.0, np.inf, 0.2])
    assert match_stamps(np.array([]), np.array([1.0]), 1.0)[0].tolist() == [-1]


def test_bad_inputs_raise():
    rel = relations_from([(0.0, 1.0, 1.0, 0.0, 0.0)])
    with pytest.raises(RelationsInputError):
        relation_errors(np.zeros(2), np.zeros((3, 3)), rel)
    with pytest.raises(RelationsInputError):
        relation_errors(np.zeros(2), np.array([[0, 0, 0], [np.nan, 0, 0]]), rel)
    with pytest.raises(RelationsInputError):
        relation_errors(np.zeros(2), np.zeros((2, 3)), rel, max_stamp_gap_s=-1.0)


# --- properties ----------------------------------------------------------------------------

_pose = st.tuples(st.floats(-50, 50), st.floats(-50, 50), st.floats(-math.pi, math.pi))


@settings(max_examples=60, deadline=None)
@given(
    st.lists(_pose, min_size=2, max_size=12),
    st.lists(_pose, min_size=2, max_size=12),
    _pose,
    st.randoms(use_true_random=False),
)
def test_metric_ignores_the_world_frame_and_matches_abs_sqr(truth, noise, transform, rnd):
    """Relations from a truth; any estimate moved rigidly as a whole scores the same."""
    n = min(len(truth), len(noise))
    truth = np.array(truth[:n])
    estimate = truth + 0.01 * np.array(noise[:n])
    stamps = np.arange(n, dtype=float)
    pairs = [(rnd.randrange(n), rnd.randrange(n)) for _ in range(10)]
    rel = relations_from([(float(i), float(j), *relative(truth[i], truth[j])) for i, j in pairs])
    base = relation_errors(stamps, estimate, rel)
    moved = np.array([compose(transform, p) for p in estimate])
    # shuffled pose order must not matter either: matching is by stamp
    order = np.array(rnd.sample(range(n), n))
    other = relation_errors(stamps[order], moved[order], rel)
    np.testing.assert_allclose(other.trans_err_m, base.trans_err_m, atol=1e-7)
    np.testing.assert_allclose(other.rot_err_deg, base.rot_err_deg, atol=1e-6)
    # population std: mean(e^2) = mean(e)^2 + std(e)^2
    for abs_, sqr in ((base.trans_abs_m, base.trans_sqr_m2), (base.rot_abs_deg, base.rot_sqr_deg2)):
        assert sqr.mean == pytest.approx(abs_.mean**2 + abs_.std**2, rel=1e-9, abs=1e-12)
    perfect = relation_errors(stamps, truth, rel)
    assert perfect.trans_abs_m.max < 1e-9 and perfect.rot_abs_deg.max < 1e-7


def test_errors_are_split_by_the_time_each_relation_spans():
    # A straight 1 m/s path; the estimate drifts 1 cm per second, so a relation's error is 0.01 * span.
    stamps = np.arange(0.0, 61.0)
    truth = np.column_stack((stamps, np.zeros_like(stamps), np.zeros_like(stamps)))
    estimate = truth * [1.01, 0.0, 0.0]
    rel = relations_from([(0, 1, 1, 0, 0), (3, 4, 1, 0, 0), (10, 20, 10, 0, 0), (0, 40, 40, 0, 0),
                          (5, 65, 60, 0, 0)])   # the last one's second stamp is beyond the trajectory
    stats = relation_errors(stamps, estimate, rel, max_stamp_gap_s=0.6)
    by_span = errors_by_span(stats, rel)
    assert list(by_span) == ["< 2 s", "2-30 s", ">= 30 s"]
    (n_short, short), (n_mid, mid), (n_long, long_) = by_span.values()
    assert (n_short, n_mid, n_long) == (2, 1, 1)
    assert short.mean == pytest.approx(0.01)
    assert mid.mean == pytest.approx(0.10) and long_.mean == pytest.approx(0.40)
