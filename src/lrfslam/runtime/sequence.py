"""Counting lost, repeated and late messages from the sequence numbers producers attach.

Every publisher numbers its messages per topic 1, 2, 3, … (each stage's outputs carry their
own counter, the sensor's the scan number; see ``docs/delivery.md``) and attaches that number
with an id of its process (``runtime/bus.py``). A consumer feeds what it receives to a
:class:`SequenceTracker`, which keeps, per (producer, topic), the highest number seen and the
numbers skipped on the way:

``gap.<topic>``
    messages skipped: published (a higher number arrived) but not received. A skipped number
    that turns up later is taken back off (and counted as ``late.<topic>``).
``dup.<topic>``
    a number received again.
``late.<topic>``
    a number received after a higher one (reordered, not lost).
``restart.<topic>``
    a new origin: a producer id not seen before on a topic that already had one (a restarted
    or second process); for a producer without an id (``b""``, older publishers), its numbers
    falling back to the origin (≤ 1) after higher ones. The new run starts counting afresh;
    nothing before it is a gap.

A consumer that joins a running stream starts at the first number it gets: the messages
before it were never due to it. No clock is read; the tracker is plain bookkeeping, so the
same sequence of calls always gives the same counts.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

from lrfslam.msgs import counters

#: Skipped numbers remembered per stream, so one arriving late can be taken back off the gaps.
#: Older ones stay counted as lost.
MISSING_WINDOW = 1024

# Outcomes of one observation (what :meth:`SequenceTracker.observe` returns).
FIRST = "first"
NEXT = "next"
GAP = "gap"
LATE = "late"
DUP = "dup"
RESTART = "restart"


@dataclass
class _Stream:
    low: int
    high: int
    missing: dict[int, None] = field(default_factory=dict)   # insertion-ordered set, oldest first


class SequenceTracker:
    """Per (producer, topic) bookkeeping of sequence numbers; see the module docstring.

    Parameters
    ----------
    window : int
        How many skipped numbers per stream are remembered to recognise late arrivals.

    Attributes
    ----------
    counts : Counter
        ``gap.<topic>``, ``dup.<topic>``, ``late.<topic>``, ``restart.<topic>`` (counts of messages).
    """

    def __init__(self, window: int = MISSING_WINDOW) -> None:
        self.window = window
        self.counts: Counter[str] = Counter()
        self._streams: dict[tuple[bytes, str], _Stream] = {}
        self._producers: dict[str, set[bytes]] = {}

    def observe(self, producer: bytes, topic: str, seq: int) -> str:
        """Account for message ``seq`` of ``producer`` on ``topic``; which of the outcomes it was.

        Parameters
        ----------
        producer : bytes
            Id of the publishing process (``b""`` when the producer gave none: then only a fall
            back to the origin tells a restart).
        topic : str
            Relative key.
        seq : int
            The message's sequence number.
        """
        stream = self._streams.get((producer, topic))
        if stream is None:
            known = self._producers.setdefault(topic, set())
            known.add(producer)
            self._streams[(producer, topic)] = _Stream(seq, seq)
            if len(known) > 1:
                self.counts[f"{counters.RESTART}{topic}"] += 1
                return RESTART
            return FIRST
        if seq == stream.high + 1:
            stream.high = seq
            return NEXT
        if seq > stream.high:
            self._skip(stream, topic, stream.high + 1, seq)
            stream.high = seq
            return GAP
        if seq in stream.missing:
            del stream.missing[seq]
            self.counts[f"{counters.GAP}{topic}"] -= 1
            self.counts[f"late.{topic}"] += 1
            return LATE
        if not producer and seq <= 1 < stream.high:
            # The origin again after higher numbers: without an id, the one sign of a new run.
            self._streams[(producer, topic)] = _Stream(seq, seq)
            self.counts[f"{counters.RESTART}{topic}"] += 1
            return RESTART
        if seq < stream.low:
            # Sent before the first one this consumer got, arriving after it: the stream starts
            # earlier than it seemed, and the numbers between are now skipped ones.
            self._skip(stream, topic, seq + 1, stream.low)
            stream.low = seq
            self.counts[f"late.{topic}"] += 1
            return LATE
        self.counts[f"{counters.DUP}{topic}"] += 1
        return DUP

    def _skip(self, stream: _Stream, topic: str, first: int, end: int) -> None:
        """Numbers ``first`` … ``end - 1`` were skipped."""
        if end <= first:
            return
        self.counts[f"{counters.GAP}{topic}"] += end - first
        for s in range(max(first, end - self.window), end):
            stream.missing[s] = None
        while len(stream.missing) > self.window:
            del stream.missing[next(iter(stream.missing))]
