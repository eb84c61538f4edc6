"""How ``lrfslam play`` paces a recording onto the bus, without a clock (src/lrfslam/tools/play.py).

Two ways of pacing, both plain bookkeeping here; the command reads the monotonic clock and waits.

:class:`RateSchedule` (``--rate X``)
    When each message is due, in ns after the first one, from the data stamps: a message
    stamped ``d`` ns after the first is due ``d / X`` ns after it. Never earlier than the
    message before it, and a new loop continues where the last one ended.

:class:`CreditWindow` (``--rate max``)
    Flow control by acknowledgement: at most ``size`` scans are *in flight* (played, not yet
    answered by the watched stage's output). Every stage copies its input's data stamp into its
    output (docs/architecture.md, "How a message travels"), so an output stamped like an
    in-flight scan acknowledges that scan and, cumulatively, every scan played before it (a
    stage that skipped one, e.g. a scan it could not use, does not hold the window). Matched in
    the order played, so the stamps of a second loop, which repeat the first's, match their
    own scans.

:func:`watched_stage` (``--wait-for``'s default)
    The last stage in pipeline order that is alive and fed: every one of its inputs is played
    or is an output of a fed stage. Its first output answers every scan that got that far.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Collection, Sequence
from dataclasses import dataclass

from lrfslam.errors import ConfigError


class RateSchedule:
    """Due times (ns after the first message) of messages played at ``rate`` times their recorded pace.

    Parameters
    ----------
    rate : float
        Data seconds per played second (> 0, finite): 1 plays as recorded, 2 twice as fast.
    """

    def __init__(self, rate: float) -> None:
        if not (math.isfinite(rate) and rate > 0):
            raise ConfigError(f"the rate must be a positive number or 'max', got {rate}")
        self.rate = float(rate)
        self._origin_ns: int | None = None   # data stamp of the loop's first message
        self._base_ns = 0                    # due time of the loop's first message
        self._last_ns = 0                    # due time of the message before

    def due_ns(self, stamp_ns: int) -> int:
        """When the message stamped ``stamp_ns`` (ns) is due: ns after the first message.

        A stamp earlier than the one before it is due at once after it: what was played is
        never waited for again.
        """
        if self._origin_ns is None:
            self._origin_ns = stamp_ns
        due = self._base_ns + round((stamp_ns - self._origin_ns) / self.rate)
        self._last_ns = max(due, self._last_ns)
        return self._last_ns

    def next_loop(self) -> None:
        """The recording starts over: its first message is due right after the last one played."""
        self._origin_ns = None
        self._base_ns = self._last_ns


class CreditWindow:
    """Scans in flight between the player and the watched stage, at most ``size``.

    Parameters
    ----------
    size : int
        Scans that may be in flight (≥ 1). Every stage's input queue holds at most this many
        scans (and what comes with them) from the player, so none overflows.

    Attributes
    ----------
    sent, acknowledged : int
        Scans played, and scans answered (directly or by a later scan's answer).
    unmatched : int
        Answers that matched no scan in flight (e.g. a stage still working on scans played
        before this window existed).
    """

    def __init__(self, size: int) -> None:
        if size < 1:
            raise ConfigError(f"the window must hold at least 1 scan, got {size}")
        self.size = int(size)
        self._in_flight: deque[int] = deque()
        self.sent = 0
        self.acknowledged = 0
        self.unmatched = 0

    @property
    def in_flight(self) -> int:
        return len(self._in_flight)

    @property
    def full(self) -> bool:
        """Whether the next scan must wait for an answer."""
        return len(self._in_flight) >= self.size

    def oldest_ns(self) -> int | None:
        """Data stamp (ns) of the oldest scan in flight; None when none is."""
        return self._in_flight[0] if self._in_flight else None

    def send(self, stamp_ns: int) -> None:
        """A scan stamped ``stamp_ns`` (ns) is played. Call before it is put on the bus, so its answer
        cannot come first.

        Raises
        ------
        ConfigError
            The window is full (the caller must wait for an answer first).
        """
        if self.full:
            raise ConfigError(f"the window of {self.size} scans is full")
        self._in_flight.append(int(stamp_ns))
        self.sent += 1

    def acknowledge(self, stamp_ns: int) -> int:
        """The watched stage answered the scan stamped ``stamp_ns`` (ns): how many scans that frees.

        The oldest in-flight scan with that stamp is answered, and every one played before it.
        """
        for i, stamp in enumerate(self._in_flight):
            if stamp == stamp_ns:
                for _ in range(i + 1):
                    self._in_flight.popleft()
                self.acknowledged += i + 1
                return i + 1
        self.unmatched += 1
        return 0


@dataclass(frozen=True)
class StageTopics:
    """A stage of the pipeline by the names of the topics it takes and gives (its first output per scan)."""

    name: str
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]


def watched_stage(stages: Sequence[StageTopics], played: Collection[str],
                  alive: Collection[str]) -> StageTopics | None:
    """The deepest stage of ``stages`` (pipeline order) that is in ``alive`` and fed; None if there is none.

    Fed: it has inputs and outputs, and each input is in ``played`` or is an output of a fed
    stage before it. A stage missing one input (a dead stage upstream, a topic not played)
    would hold its outputs or never give them, so it cannot answer for the scans.
    """
    reached = set(played)
    deepest = None
    for stage in stages:
        if stage.name in alive and stage.inputs and stage.outputs and reached.issuperset(stage.inputs):
            reached.update(stage.outputs)
            deepest = stage
    return deepest
