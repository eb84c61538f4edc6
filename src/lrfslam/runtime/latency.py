"""A stage's latency: from receiving an input to publishing what it made of it.

Measured in one process on its monotonic clock, from the moment the Zenoh callback queued
the sample to the moment the step's outputs were published: the time the input waited in
the stage's queue plus the time the step took. Summed along the chain it is the pipeline's
latency but for the transport between processes (docs/monitoring.md).
"""

from __future__ import annotations

from collections import deque

import numpy as np

#: Latencies kept: the percentiles describe about the last this many outputs.
WINDOW = 1024


class LatencyWindow:
    """The last ``size`` latencies (µs) and their percentiles."""

    def __init__(self, size: int = WINDOW) -> None:
        self._us: deque[int] = deque(maxlen=size)

    def add(self, latency_ns: int) -> None:
        """One input's latency (ns; negative values, impossible on one monotonic clock, count as 0)."""
        self._us.append(max(0, latency_ns) // 1000)

    def counters(self) -> dict[str, int]:
        """``latency.p50_us`` and ``latency.p99_us`` (µs) of the window; empty before the first."""
        if not self._us:
            return {}
        p50, p99 = np.percentile(np.fromiter(self._us, dtype=np.int64), [50, 99])
        return {"latency.p50_us": round(float(p50)), "latency.p99_us": round(float(p99))}
