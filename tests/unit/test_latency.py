"""A stage's latency window: the percentiles of the last inputs' latencies, negative ones counted."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from lrfslam.runtime.latency import LatencyWindow


@given(st.lists(st.integers(-10**6, 10**12), min_size=1, max_size=300), st.integers(1, 100),
       st.sampled_from(["latency", "age"]))
def test_percentiles_are_those_of_the_last_window(latencies_ns, size, name):
    window = LatencyWindow(name, size)
    for ns in latencies_ns:
        window.add(ns)
    kept = np.array([max(0, ns) // 1000 for ns in latencies_ns[-size:]])
    expected = {f"{name}.p50_us": round(float(np.percentile(kept, 50))),
                f"{name}.p99_us": round(float(np.percentile(kept, 99)))}
    if ahead := sum(ns < 0 for ns in latencies_ns):   # all of them, not only the window's
        expected[f"{name}.ahead"] = ahead
    assert window.counters() == expected


def test_nothing_before_the_first_output():
    assert LatencyWindow().counters() == {}
