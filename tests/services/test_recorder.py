"""The recorder stores raw payloads with their schemas, and survives a full disk."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest
from lrfslam.services.recorder import RecorderConfig, RecorderStep

from lrfslam.msgs import codec, topics
from lrfslam.msgs import types as t
from lrfslam.runtime.recording import read_recording
from lrfslam.runtime.step import Message, RunContext


def raw(i: int) -> Message:
    scan = t.LaserScan.from_ranges(1_000 + i, i, np.ones(181), -np.pi / 2, np.radians(1))
    return Message(None, codec.LASER_SCAN.encode(scan), scan.stamp_ns, topics.SCAN.schema, "scan", i)


def test_records_payloads_as_received(tmp_path):
    step = RecorderStep(RecorderConfig(directory=str(tmp_path), filename="r.mcap"), RunContext("r1"))
    for i in range(20):
        step.on_message(raw(i))
    step.close()
    got = list(read_recording(tmp_path / "r.mcap"))
    assert [codec.LASER_SCAN.decode(m.data).seq for m in got] == list(range(20))
    assert {m.schema for m in got} == {topics.SCAN.schema}


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full (Linux)")
def test_a_full_disk_is_counted_and_reported_not_fatal():
    # /dev/full accepts the open and fails every write with ENOSPC, like a full disk.
    step = RecorderStep(RecorderConfig(directory="/dev", filename="full", flush_period_s=0.0), RunContext("r1"))
    for i in range(50):
        step.on_message(raw(i))
        time.sleep(0.001)
        step.tick()
    level, message = step.health()
    assert level == t.HEALTH_ERROR and "/dev/full" in message
    assert step.counts["error.flush"] >= 1
    step.close()   # must not raise either
