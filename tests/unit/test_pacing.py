"""``lrfslam play``'s pacing and flow control (src/lrfslam/runtime/pacing.py) against oracles.

RateSchedule: due times computed here from the stamps and the rate, in exact integer arithmetic.
CreditWindow: a simulated pipeline that answers the scans it is given in order and skips some;
the oracle frees every scan up to the last one answered. watched_stage: the real services'
topics, with the stages alive chosen by hand.
"""

from __future__ import annotations

from fractions import Fraction

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lrfslam.errors import ConfigError
from lrfslam.runtime.pacing import (
    CreditWindow,
    RateSchedule,
    StageTopics,
    watched_stage,
)
from lrfslam.tools.play import stage_topics

STAMPS = st.lists(st.integers(0, 10**12), min_size=1, max_size=60).map(sorted)
RATES = st.one_of(st.sampled_from([0.1, 0.5, 1.0, 2.0, 7.5, 100.0]), st.floats(0.01, 1000.0))


def test_ten_hz_at_twice_the_pace_is_one_every_50_ms():
    schedule = RateSchedule(2.0)
    stamps = [1_000_000_000_000 + i * 100_000_000 for i in range(5)]   # 10 Hz, from 1000 s
    assert [schedule.due_ns(s) for s in stamps] == [0, 50_000_000, 100_000_000, 150_000_000, 200_000_000]


@settings(max_examples=100, deadline=None)
@given(STAMPS, RATES)
def test_due_times_are_the_stamps_offsets_divided_by_the_rate(stamps, rate):
    schedule = RateSchedule(rate)
    due = [schedule.due_ns(s) for s in stamps]
    exact = [Fraction(s - stamps[0]) / Fraction(rate) for s in stamps]
    assert due[0] == 0
    assert all(abs(d - e) <= 1 for d, e in zip(due, exact, strict=True))
    assert due == sorted(due)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.integers(0, 10**12), min_size=1, max_size=60), RATES)
def test_what_was_played_is_never_waited_for_again(stamps, rate):
    """Stamps out of order: every due time is the latest so far of the in-order schedule."""
    schedule = RateSchedule(rate)
    due = [schedule.due_ns(s) for s in stamps]
    assert due == sorted(due)
    assert due[-1] == max(round((s - stamps[0]) / rate) for s in stamps)


@settings(max_examples=100, deadline=None)
@given(STAMPS, RATES, st.integers(2, 4))
def test_each_loop_continues_where_the_last_one_ended(stamps, rate, loops):
    one = RateSchedule(rate)
    single = [one.due_ns(s) for s in stamps]
    schedule = RateSchedule(rate)
    played = []
    for i in range(loops):
        if i:
            schedule.next_loop()
        played.append([schedule.due_ns(s) for s in stamps])
    for i, due in enumerate(played):
        assert due == [i * single[-1] + d for d in single]


@pytest.mark.parametrize("rate", [0.0, -1.0, float("nan"), float("inf")])
def test_a_rate_must_be_positive_and_finite(rate):
    with pytest.raises(ConfigError):
        RateSchedule(rate)


@st.composite
def pipeline_runs(draw, unique: bool):
    """Scan stamps (sorted; unique or with repeats), a window size, which scans the stage answers,
    and the order of the player's and the stage's moves."""
    n = draw(st.integers(1, 80))
    if unique:
        stamps = sorted(draw(st.lists(st.integers(0, 10**9), min_size=n, max_size=n, unique=True)))
    else:
        stamps = sorted(draw(st.lists(st.integers(0, 20), min_size=n, max_size=n)))
    answered = [draw(st.booleans()) or i == n - 1 for i in range(n)] if draw(st.booleans()) else [True] * n
    size = draw(st.integers(1, 12))
    moves = draw(st.lists(st.booleans(), min_size=4 * n, max_size=4 * n))
    return stamps, answered, size, moves


def simulate(stamps, answered, size, moves):
    """Player and stage take turns as ``moves`` say (True: the player sends if it may), then the stage
    works off the rest. Yields after each move: the window, scans sent, and the index of the last scan
    answered (-1: none yet). Ends when neither can move: everything answered, or a full window of
    scans the stage skipped (a stall, which play reports after its timeout)."""
    window = CreditWindow(size)
    sent = handled = 0        # scans sent; scans the stage has handled (answered or skipped)
    last_answered = -1
    turns = iter(moves)
    while True:
        may_send = sent < len(stamps) and not window.full
        may_handle = handled < sent
        if not (may_send or may_handle):
            return
        if may_send and (next(turns, True) or not may_handle):
            window.send(stamps[sent])
            sent += 1
        else:
            if answered[handled]:
                window.acknowledge(stamps[handled])
                last_answered = handled
            handled += 1
        yield window, sent, last_answered


@settings(max_examples=150, deadline=None)
@given(pipeline_runs(unique=True))
def test_every_scan_up_to_the_last_answered_one_is_freed(run):
    stamps, answered, size, moves = run
    for window, sent, last in simulate(stamps, answered, size, moves):
        assert window.in_flight <= size
        assert window.acknowledged == last + 1
        assert window.acknowledged + window.in_flight == window.sent == sent
        assert window.unmatched == 0
    if window.sent < len(stamps):   # stalled: every scan in flight is one the stage skipped
        assert window.full and not any(answered[window.acknowledged:window.sent])
    else:                           # the last scan is always answered
        assert window.in_flight == 0


@settings(max_examples=150, deadline=None)
@given(pipeline_runs(unique=False))
def test_with_repeated_stamps_a_scan_is_never_freed_before_its_answer(run):
    """An answer matches the oldest scan in flight with its stamp: never one played after the scan answered."""
    stamps, answered, size, moves = run
    for window, _, last in simulate(stamps, answered, size, moves):
        assert window.in_flight <= size
        assert window.acknowledged <= last + 1


def test_a_second_loop_matches_its_own_scans():
    window = CreditWindow(4)
    for s in (10, 20, 30, 10):        # the end of one loop, the start of the next
        window.send(s)
    assert window.acknowledge(10) == 1   # the first loop's scan, not the second's
    assert window.acknowledge(30) == 2
    assert window.oldest_ns() == 10 and window.in_flight == 1
    assert window.acknowledge(10) == 1 and window.in_flight == 0


def test_answers_for_nothing_in_flight_are_counted_not_applied():
    window = CreditWindow(2)
    window.send(5)
    assert window.acknowledge(4) == 0 and window.unmatched == 1 and window.in_flight == 1


def test_a_full_window_refuses_another_scan():
    window = CreditWindow(1)
    window.send(1)
    with pytest.raises(ConfigError):
        window.send(2)
    with pytest.raises(ConfigError):
        CreditWindow(0)


PIPELINE = stage_topics()


@pytest.mark.parametrize(("alive", "played", "expected"), [
    ({"denoise", "features", "slam", "mapper", "recorder"}, {"scan", "odom", "truth"}, "mapper"),
    ({"denoise", "features", "slam", "recorder"}, {"scan", "odom"}, "slam"),
    ({"denoise", "features"}, {"scan", "odom"}, "features"),
    # slam without its features (and the mapper behind it) cannot answer: the last fed stage does.
    ({"denoise", "slam", "mapper"}, {"scan", "odom"}, "denoise"),
    # slam waits for odometry it is not given.
    ({"denoise", "features", "slam"}, {"scan"}, "features"),
    ({"recorder"}, {"scan", "odom"}, None),
    ({"sensor", "recorder"}, {"scan", "odom"}, None),
    ({"denoise", "features", "slam"}, set(), None),
])
def test_the_watched_stage_is_the_deepest_fed_one_alive(alive, played, expected):
    stage = watched_stage(PIPELINE, played, alive)
    assert (stage.name if stage else None) == expected


@settings(max_examples=100, deadline=None)
@given(st.sets(st.sampled_from([s.name for s in PIPELINE])),
       st.sets(st.sampled_from(["scan", "odom", "truth", "scan/filtered", "features", "slam/state"])))
def test_the_watched_stage_is_alive_and_fed_and_none_deeper_is(alive, played):
    stage = watched_stage(PIPELINE, played, alive)

    def fed(upto: int) -> set[str]:
        reached = set(played)
        for s in PIPELINE[:upto]:
            if s.name in alive and s.inputs and s.outputs and reached >= set(s.inputs):
                reached |= set(s.outputs)
        return reached
    candidates = [i for i, s in enumerate(PIPELINE) if s.name in alive and s.inputs and s.outputs
                  and fed(i) >= set(s.inputs)]
    assert (stage is None) == (not candidates)
    if stage is not None:
        assert stage == PIPELINE[max(candidates)]


def test_stage_topics_are_plain_names():
    assert StageTopics("slam", ("odom", "scan", "features"), ("slam/state", "slam/map")) in PIPELINE
