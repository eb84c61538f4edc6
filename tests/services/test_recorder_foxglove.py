"""The recorder writes Foxglove's views beside the raw payloads; a bad payload never costs the raw recording."""

from __future__ import annotations

import time
from collections import Counter

import numpy as np
from lrfslam.services.recorder import RecorderConfig, RecorderStep
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from lrfslam.msgs import codec, topics
from lrfslam.msgs import types as t
from lrfslam.runtime.recording import read_metadata, read_recording
from lrfslam.runtime.step import Message, RunContext
from lrfslam.tools import info


def raw(i: int, data: bytes | None = None, schema: str = topics.SCAN.schema) -> Message:
    scan = t.LaserScan.from_ranges(1_000_000 + i * 100_000_000, i, np.linspace(0.5, 8.0, 181), -np.pi / 2, np.radians(1))
    return Message(None, data if data is not None else codec.LASER_SCAN.encode(scan), scan.stamp_ns, schema, "scan", i)


def test_views_go_beside_the_payloads_at_their_times(tmp_path):
    """MCAP's times: log time the recorder's receive time (wall clock), publish time the data stamp."""
    started = time.time_ns()
    step = RecorderStep(RecorderConfig(directory=str(tmp_path), name="r"), RunContext("r1"))
    for i in range(5):
        step.on_message(raw(i))
    step.on_message(raw(5, b"\xff\xfe garbage"))                                  # a corrupt payload
    step.on_message(raw(6, codec.LASER_SCAN.encode(t.LaserScan.from_ranges(7, 7, [1.0], 0, 1)),
                        "lrfslam.msgs.v9.LaserScan"))                              # an unknown version
    status = t.ServiceStatus(service="slam", robot="r1", level=t.HEALTH_OK, message="ok", wall_stamp_ns=123,
                             uptime_s=1.0, counters={})
    step.on_message(Message(None, codec.SERVICE_STATUS.encode(status), 123, codec.SERVICE_STATUS.schema,
                            "health/slam", 1))
    step.close()
    ended = time.time_ns()
    assert step.counts["messages"] == 8 and step.counts["foxglove.undecodable"] == 2
    assert step.counts["foxglove.messages"] == 6 and step.health()[0] == t.HEALTH_OK

    (path,) = (tmp_path / "r").iterdir()
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        got = [(c.topic, s.name, c.message_encoding, m.publish_time, d, m.log_time)
               for s, c, m, d in reader.iter_decoded_messages(topics=["/foxglove/scan", "/foxglove/log"])]
    assert read_metadata(path)["lrfslam.times"] == {"log_time": "receive", "publish_time": "stamp"}
    scans = [g for g in got if g[0] == "/foxglove/scan"]
    assert [g[3] for g in scans] == [1_000_000 + i * 100_000_000 for i in range(5)]
    raw_scans = [m for m in read_recording(tmp_path / "r") if m.topic == "scan"][:5]
    assert [m.stamp_ns for m in raw_scans] == [1_000_000 + i * 100_000_000 for i in range(5)]
    # a view at the receive time of its source, which the recorder took from its wall clock
    assert [g[5] for g in scans] == [m.receive_ns for m in raw_scans] == [m.log_time_ns for m in raw_scans]
    assert all(started <= m.receive_ns <= ended for m in raw_scans)
    assert {(g[1], g[2]) for g in scans} == {("foxglove.LaserScan", "protobuf")}
    np.testing.assert_array_equal(scans[0][4].ranges, codec.LASER_SCAN.decode(raw(0).value).ranges_m)
    (log,) = [g for g in got if g[0] == "/foxglove/log"]
    assert (log[1], log[3], log[4].name, log[4].message) == ("foxglove.Log", 123, "slam", "ok")
    # every raw payload is there, the two that have no view included
    assert Counter(m.topic for m in read_recording(tmp_path / "r") if not topics.is_foxglove(m.topic)) == \
        {"scan": 7, "health/slam": 1}
    # info reads the views' log on the receive clock, like health
    (row,) = [line.split() for line in info.describe(tmp_path / "r").splitlines() if line.startswith("/foxglove/log")]
    assert row[3:] == ["receive", "foxglove.Log"]


def test_views_can_be_turned_off(tmp_path):
    step = RecorderStep(RecorderConfig(directory=str(tmp_path), name="r", foxglove=False), RunContext("r1"))
    for i in range(3):
        step.on_message(raw(i))
    step.close()
    assert [m.topic for m in read_recording(tmp_path / "r")] == ["scan"] * 3


def test_a_failing_view_is_counted_and_the_raw_recording_goes_on(tmp_path):
    step = RecorderStep(RecorderConfig(directory=str(tmp_path), name="r"), RunContext("r1"))

    def broken(*_args):
        raise ZeroDivisionError("a bug in a view")
    step.views.convert = broken
    for i in range(3):
        step.on_message(raw(i))
    step.close()
    assert step.counts["foxglove.failed"] == 3 and step.health()[0] == t.HEALTH_WARN
    assert [m.sequence for m in read_recording(tmp_path / "r")] == [0, 1, 2]
