"""A live run against its truth (evaluation/live_truth.py, ``lrfslam up``'s summary): bounded however
long it runs, and the same errors as matching everything at the end."""

from __future__ import annotations

import time

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from lrfslam.services.sensor import SensorConfig, SimSource

from lrfslam.algo.geometry import compose, relative, wrap_angle
from lrfslam.evaluation.live_truth import LiveTruth, SeqRanges
from lrfslam.evaluation.truth import MAX_PENDING_TRUTH
from lrfslam.msgs import codec
from lrfslam.msgs import types as t


def state(stamp: int, seq: int, pose) -> bytes:
    return codec.SLAM_STATE.encode(t.SlamState(stamp_ns=stamp, seq=seq, scan_seq=seq, pose=np.asarray(pose, float),
                                               pose_cov=np.eye(3) * 1e-4,
                                               motion=np.zeros(3)))


def reference_errors(truth: dict[int, np.ndarray], states: list[tuple[int, np.ndarray]]) -> tuple[float, float]:
    """What up computed before: every pair at the end, anchored at SLAM's first matched pose."""
    pairs = [(est, truth[s]) for s, est in states if s in truth]
    anchor = compose(pairs[0][1], relative(pairs[0][0], np.zeros(3)))
    d = np.array([np.hypot(*(compose(anchor, e)[:2] - g[:2])) for e, g in pairs])
    return float(d[-1]), float(np.sqrt(np.mean(d ** 2)))


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31), st.floats(0.0, 0.5))
def test_running_errors_equal_matching_everything_at_the_end(seed, lost):
    rng = np.random.default_rng(seed)
    n = 200
    stamps = 10**15 + np.arange(n) * 13_333_333
    truth = {int(s): np.array([0.05 * i, np.sin(0.01 * i), wrap_angle(0.02 * i)]) for i, s in enumerate(stamps)}
    offset = np.array([1.0, -2.0, 0.3])   # SLAM's own map frame
    kept = [i for i in range(n) if rng.random() >= lost] or [0]
    states = [(int(stamps[i]), compose(relative(offset, truth[int(stamps[i])]), rng.normal(0, 0.01, 3)))
              for i in kept]
    obs = LiveTruth()
    for i, s in enumerate(stamps):
        obs.add_truth(i + 1, int(s), truth[int(s)])
    for s, pose in states:
        obs.add_state(state(s, 1, pose))
    final, rmse = reference_errors(truth, states)
    err = obs.pose_errors()
    assert err["scans"] == len(states)
    assert np.isclose(err["final_xy_m"], final) and np.isclose(err["ate_rmse_m"], rmse)


def test_truth_without_states_is_bounded():
    """A dead or stalled slam: truth keeps coming and nothing matches it."""
    obs = LiveTruth()
    for i in range(MAX_PENDING_TRUTH * 3):
        obs.add_truth(i + 1, 10**15 + i, np.zeros(3))
    assert len(obs.errors.pending) == MAX_PENDING_TRUTH
    assert len(obs.published.ranges) == 1 and len(obs.published) == MAX_PENDING_TRUTH * 3


def test_truth_is_released_as_states_come():
    obs = LiveTruth()
    for i in range(1000):
        obs.add_truth(i + 1, 10**15 + i, np.zeros(3))
        if i % 3 == 0:   # two of three states lost
            obs.add_state(state(10**15 + i, i + 1, np.zeros(3)))
        assert len(obs.errors.pending) <= 3


@given(st.lists(st.integers(0, 300), max_size=200))
def test_seq_ranges_hold_what_was_added(seqs):
    r = SeqRanges()
    for q in seqs:
        r.add(q)
    assert len(r) == len(set(seqs))
    assert [q for a, b in r.ranges for q in range(a, b + 1)] == sorted(set(seqs))
    assert all(b + 1 < a2 for (_, b), (a2, _) in zip(r.ranges, r.ranges[1:]))
    assert r.missing_from(set(seqs[::2])) == len(set(seqs) - set(seqs[::2]))


def test_epoch_from_any_truth_message():
    obs = LiveTruth()
    epoch, rate = 1_700_000_000_000_000_000, 10.0
    obs.add_truth(42, epoch + round(41 / rate * 1e9), np.zeros(3))   # the first one heard need not be seq 1
    assert obs.epoch_ns(rate) == epoch


def test_a_restarted_sensor_continues_where_the_robot_is_now():
    """Given its run's epoch, a sensor skips what it missed: the same frames as a sensor never stopped."""
    speedup, rate = 10.0, 10.0
    epoch = time.time_ns() - 3 * 10**9      # the run started 3 s of wall time ago: 300 frames
    restarted = SimSource(SensorConfig(seed=4, speedup=speedup, rate_hz=rate, epoch_ns=epoch))
    skipped = restarted.counts["skipped"]
    assert 300 <= skipped <= 330
    odom, truth, scan = (o.value for o in restarted.poll(1.0))
    never_stopped = SimSource(SensorConfig(seed=4, speedup=0, rate_hz=rate))
    for _ in range(skipped):
        next(never_stopped.frames)
    frame = next(never_stopped.frames)
    assert scan.seq == frame.index + 1 == skipped + 1
    assert scan.stamp_ns == epoch + round(frame.t_s * 1e9)
    np.testing.assert_array_equal(odom.pose, frame.odom_pose)
    np.testing.assert_array_equal(truth.pose, frame.true_pose)
    np.testing.assert_array_equal(scan.ranges_m, frame.scan.ranges_m)
