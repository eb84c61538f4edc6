"""The sequence tracker against an oracle: what was published, what was delivered, in which order.

Deliveries are generated from what producers published (numbers 1..n per run): some lost,
some delivered twice, reordered by a bounded shift, runs of one topic interleaved. The
oracle counts from the delivered list alone: for each producer run, the numbers between the
first and the highest delivered that never came are gaps, repeats are duplicates, a number
arriving after a higher one for the first time is late; every producer after the first is a
restart.
"""

from __future__ import annotations

from collections import Counter

from hypothesis import given, settings
from hypothesis import strategies as st

from lrfslam.runtime.sequence import (
    DUP,
    FIRST,
    GAP,
    LATE,
    NEXT,
    RESTART,
    SequenceTracker,
)


@st.composite
def one_run(draw, max_n: int = 60) -> list[int]:
    """What a consumer receives of one producer run: lost, duplicated, reordered by ≤ 4 places."""
    n = draw(st.integers(1, max_n))
    kept = [s for s in range(1, n + 1) if not draw(st.booleans()) or s == 1] if draw(st.booleans()) \
        else list(range(1, n + 1))
    delivered = []
    for s in kept:
        delivered += [s] * draw(st.sampled_from([1, 1, 1, 2]))
    keys = [i + draw(st.integers(0, 4)) for i in range(len(delivered))]
    delivered = [s for _, s in sorted(zip(keys, delivered, strict=True), key=lambda p: p[0])]
    # The consumer's first sample of a run is where it joined the stream: put the lowest first.
    lowest = delivered.index(min(delivered))
    return [delivered[lowest], *delivered[:lowest], *delivered[lowest + 1:]]


def oracle(delivered: list[int]) -> Counter:
    got = set(delivered)
    counts = Counter(gap=len(set(range(min(got), max(got) + 1)) - got), dup=len(delivered) - len(got))
    seen: set[int] = set()
    for s in delivered:
        counts["late"] += bool(seen and s < max(seen) and s not in seen)
        seen.add(s)
    return counts


def interleave(draw, runs: list[list[tuple[bytes, int]]]) -> list[tuple[bytes, int]]:
    """Merge the runs in a random order that keeps each run's own order."""
    queues = [list(r) for r in runs if r]
    merged = []
    while queues:
        q = queues[draw(st.integers(0, len(queues) - 1))]
        merged.append(q.pop(0))
        if not q:
            queues.remove(q)
    return merged


def tracked(samples: list[tuple[bytes, int]], topic: str = "scan") -> Counter:
    tracker = SequenceTracker()
    for producer, seq in samples:
        tracker.observe(producer, topic, seq)
    return Counter({k.split(".")[0]: v for k, v in tracker.counts.items() if v})


@settings(max_examples=300, deadline=None)
@given(st.data())
def test_one_producer_gaps_dups_and_late_arrivals_match_the_oracle(data):
    run = data.draw(one_run())
    assert tracked([(b"p1", s) for s in run]) == +oracle(run)


@settings(max_examples=300, deadline=None)
@given(st.data(), st.integers(2, 4))
def test_interleaved_producers_and_restarts_are_told_apart(data, n_producers):
    """Concurrent producers, or one restarted several times (a new id each run): never a false gap."""
    runs = [data.draw(one_run(30)) for _ in range(n_producers)]
    concurrent = data.draw(st.booleans())
    tagged = [[(bytes([i + 1]) * 16, s) for s in run] for i, run in enumerate(runs)]
    samples = interleave(data.draw, tagged) if concurrent else [x for r in tagged for x in r]
    expected = sum((oracle(r) for r in runs), Counter())
    expected["restart"] = n_producers - 1
    assert tracked(samples) == +expected


@given(st.lists(st.tuples(st.sampled_from(["scan", "odom", "health/x"]), st.integers(1, 5)), max_size=40))
def test_topics_are_counted_apart(steps):
    """The same producer on several topics: one topic's numbers never make a gap in another's."""
    tracker = SequenceTracker()
    next_seq = Counter()
    for topic, skip in steps:
        next_seq[topic] += skip
        tracker.observe(b"p", topic, next_seq[topic])
    for topic in next_seq:
        first = next(skip for tp, skip in steps if tp == topic)
        assert tracker.counts[f"gap.{topic}"] == next_seq[topic] - first - sum(1 for tp, _ in steps if tp == topic) + 1


def test_outcomes_of_each_case():
    tracker = SequenceTracker()
    assert [tracker.observe(b"a", "scan", s) for s in (5, 6, 9, 8, 8, 3)] == [FIRST, NEXT, GAP, LATE, DUP, LATE]
    # 7 still missing; 4 skipped once 3 turned up before the first one seen.
    assert tracker.counts == Counter({"gap.scan": 2, "late.scan": 2, "dup.scan": 1})
    assert tracker.observe(b"b", "scan", 1) == RESTART
    assert tracker.counts["restart.scan"] == 1 and tracker.counts["gap.scan"] == 2


def test_without_a_producer_id_a_fall_back_to_the_origin_is_a_restart():
    tracker = SequenceTracker()
    outcomes = [tracker.observe(b"", "odom", s) for s in (1, 2, 3, 1, 2, 0)]
    assert outcomes == [FIRST, NEXT, NEXT, RESTART, NEXT, RESTART]
    assert tracker.counts == Counter({"restart.odom": 2})
    # With an id, the same numbers are a duplicate: its restart would come with a new id.
    with_id = SequenceTracker()
    assert [with_id.observe(b"x", "odom", s) for s in (1, 2, 3, 1)][-1] == DUP


def test_a_long_gap_is_counted_in_full_and_only_recent_numbers_are_remembered():
    tracker = SequenceTracker(window=10)
    tracker.observe(b"a", "scan", 1)
    tracker.observe(b"a", "scan", 1002)
    assert tracker.counts["gap.scan"] == 1000
    assert tracker.observe(b"a", "scan", 1000) == LATE      # within the window: taken back
    assert tracker.observe(b"a", "scan", 500) == DUP        # beyond it: stays lost, the sample is a repeat
    assert tracker.counts["gap.scan"] == 999
