"""``lrfslam info`` keeps its clocks apart: a 9 s run at a 2.5× simulator speedup is a 9 s run.

The recording is laid out as the recorder writes one under ``lrfslam up --speedup 2.5``: data
stamped with simulated time (2.5 s per wall second, from the sensor's start), health stamped
with each service's wall clock, every message's log time the recorder's receive time. Mixing
the two in one span made info report a 22 s duration and a 0.26 Hz health rate for this run.
"""

from __future__ import annotations

import re

import numpy as np

from lrfslam.msgs import codec, topics
from lrfslam.msgs import types as t
from lrfslam.runtime.recording import RecordingWriter
from lrfslam.tools import info

T0 = 1_700_000_000_000_000_000   # wall time at the recorder's start (ns)
S = 1_000_000_000
SPEEDUP = 2.5
RUN_S = 9


def rate(text: str, topic: str) -> tuple[float, str]:
    m = re.search(rf"^{re.escape(topic)}\s+\d+\s+([\d.]+)\s+(\w+)", text, re.MULTILINE)
    return float(m[1]), m[2]


def test_duration_is_the_run_and_each_rate_is_on_its_own_clock(tmp_path):
    path = tmp_path / "run.mcap"
    sensor_start = T0 + S // 2
    scans = int((RUN_S - 1) * 10 * SPEEDUP)      # 10 Hz of simulated time, stopped before the rest
    with RecordingWriter(path, receive_times=True) as w:
        for i in range(RUN_S + 1):               # health once a wall second, from the start
            for service in ("denoise", "slam"):
                st = t.ServiceStatus(service=service, robot="r", level=t.HEALTH_OK, message="ok",
                                     wall_stamp_ns=T0 + i * S, uptime_s=float(i), counters={"health": i + 1})
                w.write(topics.health(service).name, topics.health(service).schema,
                        codec.SERVICE_STATUS.encode(st), st.wall_stamp_ns, st.wall_stamp_ns + 1_000_000, i + 1)
        for k in range(scans):
            data_ns = sensor_start + k * S // 10
            received = sensor_start + round(k * S / 10 / SPEEDUP) + 2_000_000
            scan = t.LaserScan.from_ranges(data_ns, k + 1, np.full(181, 2.0), -np.pi / 2, np.pi / 180)
            w.write(topics.SCAN.name, topics.SCAN.schema, codec.LASER_SCAN.encode(scan), data_ns, received, k + 1)
    text = info.describe(path)
    duration = float(re.search(r"^duration:\s+([\d.]+) s \(receive clock", text, re.MULTILINE)[1])
    data_time = float(re.search(r"^data time:\s+([\d.]+) s \(data stamps", text, re.MULTILINE)[1])
    assert abs(duration - RUN_S) < 0.01, text    # not the 20 s of simulated time
    assert abs(data_time - (scans - 1) / 10) < 1e-6, text
    scan_hz, scan_clock = rate(text, "scan")
    health_hz, health_clock = rate(text, "health/slam")
    assert (scan_clock, health_clock) == ("data", "receive")
    assert abs(scan_hz - 10.0) < 0.01 and abs(health_hz - 1.0) < 0.01, text
