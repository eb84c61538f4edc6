"""MCAP recordings read back with the mcap library, with embedded schemas, even after a crash."""

from __future__ import annotations

import shutil

import numpy as np
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from lrfslam.msgs import codec, topics
from lrfslam.msgs import types as t
from lrfslam.runtime.recording import (
    ReadReport,
    RecordingWriter,
    read_metadata,
    read_recording,
)


def _scan(i: int) -> t.LaserScan:
    return t.LaserScan.from_ranges(1_000 + i, i, np.full(181, 1.0 + i), -np.pi / 2, np.radians(1))


def test_round_trip_with_embedded_schema(tmp_path):
    path = tmp_path / "r.mcap"
    with RecordingWriter(path, metadata={"lrfslam": {"robot": "r1"}}) as w:
        for i in range(5):
            w.write("scan", topics.SCAN.schema, codec.LASER_SCAN.encode(_scan(i)), 1_000 + i, sequence=i)
        w.write("odom", topics.ODOM.schema, codec.ODOMETRY.encode(t.Odometry(999, 1, (1, 2, 3))), 999)
    got = list(read_recording(path))
    assert [m.topic for m in got] == ["odom", "scan", "scan", "scan", "scan", "scan"]  # log-time order
    assert codec.LASER_SCAN.decode(got[-1].data).ranges_m[0] == 5.0
    assert read_metadata(path)["lrfslam"]["robot"] == "r1"
    # Any MCAP tool can decode it from the file alone: the protobuf descriptors are embedded.
    with open(path, "rb") as f:
        decoded = list(make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages())
    assert decoded[1][0].name == "lrfslam.msgs.v1.LaserScan"
    assert list(decoded[4][3].ranges_m)[:1] == [4.0]


def test_unknown_schema_is_kept_schemaless(tmp_path):
    path = tmp_path / "r.mcap"
    with RecordingWriter(path) as w:
        w.write("future", "lrfslam.msgs.v7.Thing", b"\x01\x02", 5)
    (m,) = read_recording(path)
    assert (m.topic, m.schema, m.data) == ("future", "lrfslam.msgs.v7.Thing", b"\x01\x02")


def test_killed_writer_loses_at_most_the_unflushed_tail(tmp_path):
    path = tmp_path / "r.mcap"
    w = RecordingWriter(path)
    for i in range(10):
        w.write("scan", topics.SCAN.schema, codec.LASER_SCAN.encode(_scan(i)), 1_000 + i)
    w.flush()
    for i in range(10, 13):
        w.write("scan", topics.SCAN.schema, codec.LASER_SCAN.encode(_scan(i)), 1_000 + i)
    crashed = tmp_path / "crashed.mcap"
    shutil.copy(path, crashed)  # the file as a SIGKILL would leave it: no footer, no summary
    w.close()
    report = ReadReport()
    got = list(read_recording(crashed, report=report))
    assert report.truncated
    assert [codec.LASER_SCAN.decode(m.data).seq for m in got] == list(range(10))
