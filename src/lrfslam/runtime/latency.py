"""Latency figures of a stage: percentiles over its last outputs, as status counters.

Two windows per stage (docs/monitoring.md):

- ``latency.*``: from receiving an input to publishing what it made of it. Measured in one
  process on its monotonic clock, from the moment the Zenoh callback queued the sample to the
  moment the step's outputs were published: the time the input waited in the stage's queue
  plus the time the step took. Summed along the chain it is the pipeline's latency but for
  the transport between processes.
- ``age.*``: from the data stamp of the sensor scan the outputs derive from (every message
  carries its scan's stamp) to the moment they were published, on the wall clock: the scan's
  end-to-end latency up to this stage, transport included. It means something only where the
  stamps are wall-clock times (``bus.wall_clock_stamps``, lrfslam/runtime/bus.py) and the
  sensor's host and this one keep their clocks together; an age below zero (a stamp ahead of
  this clock) counts as 0 and in ``age.ahead``.
"""

from __future__ import annotations

from collections import deque

import numpy as np

#: Latencies kept: the percentiles describe about the last this many outputs.
WINDOW = 1024


class LatencyWindow:
    """The last ``size`` latencies (µs) and their percentiles, as counters named ``<name>.*``."""

    def __init__(self, name: str = "latency", size: int = WINDOW) -> None:
        self.name = name
        self._us: deque[int] = deque(maxlen=size)
        self._ahead = 0

    def add(self, latency_ns: int) -> None:
        """One output's latency (ns); a negative one counts as 0 and in ``<name>.ahead``."""
        if latency_ns < 0:
            self._ahead += 1
        self._us.append(max(0, latency_ns) // 1000)

    def counters(self) -> dict[str, int]:
        """``<name>.p50_us`` and ``<name>.p99_us`` (µs) of the window, ``<name>.ahead`` once one was
        negative; empty before the first."""
        if not self._us:
            return {}
        p50, p99 = np.percentile(np.fromiter(self._us, dtype=np.int64), [50, 99])
        figures = {f"{self.name}.p50_us": round(float(p50)), f"{self.name}.p99_us": round(float(p99))}
        if self._ahead:
            figures[f"{self.name}.ahead"] = self._ahead
        return figures
