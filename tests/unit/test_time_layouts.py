"""MCAP times: ``log_time`` the recorder's receive time, ``publish_time`` the data stamp; older files still read.

A file says which in its metadata record ``lrfslam.times``; one without it has the older
layout (``log_time`` the data stamp, ``publish_time`` the receive time), as the golden inputs
in tests/data/golden/ have. The oracle: the same messages in either layout, or with the
receive order shuffled by a transport, replay to the same bytes as the golden output.
"""

from __future__ import annotations

import random
import shutil
from pathlib import Path

from decoded_messages import SHORT_SLAM_RUN, assert_same_messages
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.writer import Writer
from mcap_protobuf.schema import build_file_descriptor_set

from lrfslam import cli
from lrfslam.msgs import topics
from lrfslam.msgs.codec import CODECS
from lrfslam.runtime.recording import (
    OLD_LAYOUT,
    PROFILE,
    RECEIVE,
    REORDER_WINDOW_NS,
    STAMP,
    TIMES,
    RecordedMessage,
    RecordingWriter,
    read_metadata,
    read_recording,
    reader,
    recover,
    time_layout,
)
from lrfslam.tools import info

GOLDEN = Path(__file__).resolve().parents[1] / "data" / "golden"
MS = 1_000_000
#: A transport's delay per topic (ns): odometry overtakes the scan of the same stamp and of the next ones.
DELAY = {"scan": 250 * MS, "odom": 2 * MS, "truth": 45 * MS}


def receive_times(messages: list[RecordedMessage], seed: int = 1) -> list[int]:
    """A live run's receive times of ``messages``: their stamp, a delay per topic and some jitter."""
    rng = random.Random(seed)
    return [m.stamp_ns + DELAY.get(m.topic, 5 * MS) + rng.randrange(10 * MS) for m in messages]


def write_live(path: Path, messages: list[RecordedMessage], received: list[int],
               metadata: dict[str, dict[str, str]]) -> None:
    """``messages`` as the recorder writes them now: ``log_time`` the receive time."""
    with RecordingWriter(path, metadata, receive_times=True) as w:
        for m, r in sorted(zip(messages, received, strict=True), key=lambda x: x[1]):
            w.write(m.topic, m.schema, m.data, m.stamp_ns, r, m.sequence)


def write_old_layout(path: Path, messages: list[RecordedMessage], received: list[int],
                     metadata: dict[str, dict[str, str]]) -> None:
    """``messages`` as the recorder wrote them before: ``log_time`` the stamp, no ``lrfslam.times``."""
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile=PROFILE, library="lrfslam-python")
        for name, record in metadata.items():
            w.add_metadata(name, record)
        channels: dict[str, int] = {}
        for m, r in zip(messages, received, strict=True):
            if m.topic not in channels:
                fds = build_file_descriptor_set(CODECS[m.schema].proto).SerializeToString()
                schema_id = w.register_schema(m.schema, "protobuf", fds)
                channels[m.topic] = w.register_channel(m.topic, "protobuf", schema_id, {"schema": m.schema})
            w.add_message(channels[m.topic], log_time=m.stamp_ns, data=m.data, publish_time=r, sequence=m.sequence)
        w.finish()


def golden_input() -> tuple[list[RecordedMessage], dict[str, dict[str, str]]]:
    metadata = read_metadata(GOLDEN / "sim_head.mcap")
    assert TIMES not in metadata and time_layout(GOLDEN / "sim_head.mcap") == OLD_LAYOUT
    return list(read_recording(GOLDEN / "sim_head.mcap")), metadata


def test_every_file_says_what_its_times_are(tmp_path):
    messages, metadata = golden_input()
    received = receive_times(messages)
    write_live(tmp_path / "live.mcap", messages, received, metadata)
    write_old_layout(tmp_path / "old.mcap", messages, received, metadata)
    assert cli.main(["pipeline", "-q", "--stages", "denoise", "--replay", str(tmp_path / "live.mcap"),
                     "--out", str(tmp_path / "offline.mcap")]) == 0
    assert [time_layout(tmp_path / n) for n in ("live.mcap", "old.mcap", "offline.mcap")] == [RECEIVE, OLD_LAYOUT,
                                                                                              STAMP]
    assert read_metadata(tmp_path / "live.mcap")[TIMES] == {"log_time": "receive", "publish_time": "stamp"}
    assert read_metadata(tmp_path / "offline.mcap")[TIMES] == {"log_time": "stamp", "publish_time": "stamp"}

    # The mcap library sees MCAP's convention in the new file and the older one in the old.
    with open(tmp_path / "live.mcap", "rb") as f:
        raw = [(m.log_time, m.publish_time) for _, _, m in make_reader(f).iter_messages(log_time_order=True)]
    assert sorted(raw) == sorted(zip(received, (m.stamp_ns for m in messages), strict=True))
    # Both read as the same messages with the same stamps and receive times, in stamp order
    # (equal stamps in the order of the file: the receive order, or the older file's order).
    live, old = list(read_recording(tmp_path / "live.mcap")), list(read_recording(tmp_path / "old.mcap"))
    strip = sorted((m.topic, m.data, m.stamp_ns, m.receive_ns, m.sequence) for m in live)
    assert strip == sorted((m.topic, m.data, m.stamp_ns, m.receive_ns, m.sequence) for m in old)
    assert [m.stamp_ns for m in live] == sorted(m.stamp_ns for m in messages)
    assert all(m.receive_ns == m.log_time_ns and m.stamp_ns == m.publish_time_ns for m in live)
    assert all(m.receive_ns == 0 and m.stamp_ns == m.log_time_ns == m.publish_time_ns
               for m in read_recording(tmp_path / "offline.mcap"))
    # info tells the same clocks apart in both layouts.
    describe = [info.describe(tmp_path / n).splitlines()[1:] for n in ("live.mcap", "old.mcap")]
    assert describe[0] == describe[1] and "(receive clock" in describe[0][0]
    assert "an offline output, no receive times" in info.describe(tmp_path / "offline.mcap")


def test_a_live_recording_replays_as_the_older_one(tmp_path):
    """Receive order shuffled between topics, the replay still runs in stamp order: the golden results.

    The older layout gives the golden messages (within round-off: they were made on another
    CPU). The live one gives, on this machine, the same bytes on every topic in the same
    order; only messages of equal stamp on different topics (a scan and its odometry) keep
    their receive order in the output, where the older file had its own order.
    """
    messages, metadata = golden_input()
    received = receive_times(messages)
    order = [m.topic for m, _ in sorted(zip(messages, received, strict=True), key=lambda x: x[1])]
    assert order != [m.topic for m in messages]        # the transport did reorder them
    golden = GOLDEN / "sim_head.pipeline.mcap"

    def per_topic(path: Path) -> dict[str, list]:
        streams: dict[str, list] = {}
        for m in read_recording(path):
            streams.setdefault(m.topic, []).append((m.data, m.log_time_ns, m.publish_time_ns, m.sequence))
        return streams

    outs = {}
    for layout, write in (("live", write_live), ("old", write_old_layout)):
        (tmp_path / layout).mkdir()
        write(tmp_path / layout / "sim_head.mcap", messages, received, metadata)  # the name goes into metadata
        outs[layout] = out = tmp_path / layout / "sim_head.pipeline.mcap"
        assert cli.main(["pipeline", "--replay", str(tmp_path / layout / "sim_head.mcap"), "--out", str(out),
                         "-q", "--stages", "denoise,features,slam"]) == 0
    slam_run = {topics.SLAM_STATE.name: SHORT_SLAM_RUN, topics.SLAM_MAP.name: SHORT_SLAM_RUN}
    assert_same_messages(outs["old"], golden, slam_run)
    assert per_topic(outs["live"]) == per_topic(outs["old"])
    assert read_metadata(outs["live"]) == read_metadata(outs["old"])


def test_export_foxglove_puts_views_at_receive_times_of_a_recording_and_stamps_of_an_output(tmp_path):
    messages, metadata = golden_input()
    received = receive_times(messages)
    write_old_layout(tmp_path / "old.mcap", messages, received, metadata)
    assert cli.main(["export", str(tmp_path / "old.mcap"), "--foxglove", str(tmp_path / "fox.mcap")]) == 0
    assert time_layout(tmp_path / "fox.mcap") == RECEIVE
    out = list(read_recording(tmp_path / "fox.mcap"))
    by_stamp = {(m.topic, m.stamp_ns): r for m, r in zip(messages, received, strict=True)}
    assert sorted((m.topic, m.stamp_ns, m.receive_ns) for m in out if not topics.is_foxglove(m.topic)) == \
        sorted((m.topic, m.stamp_ns, by_stamp[m.topic, m.stamp_ns]) for m in read_recording(tmp_path / "old.mcap"))
    scan_views = [m for m in out if m.topic == "/foxglove/scan"]
    assert [m.log_time_ns for m in scan_views] == [by_stamp["scan", m.stamp_ns] for m in scan_views]
    assert len(scan_views) == sum(m.topic == "scan" for m in messages)

    # An offline output has no receive times: its copy's timeline is data time.
    shutil.copy(GOLDEN / "sim_head.pipeline.mcap", tmp_path / "p.mcap")
    assert cli.main(["export", str(tmp_path / "p.mcap"), "--foxglove", str(tmp_path / "pfox.mcap")]) == 0
    assert time_layout(tmp_path / "pfox.mcap") == STAMP
    assert all(m.log_time_ns == m.publish_time_ns == m.stamp_ns for m in read_recording(tmp_path / "pfox.mcap"))


def test_an_unfinished_or_recovered_live_file_keeps_its_layout(tmp_path):
    messages, metadata = golden_input()
    received = receive_times(messages)
    w = RecordingWriter(tmp_path / "killed.mcap", metadata, chunk_size_bytes=4096, receive_times=True)
    for m, r in zip(messages, received, strict=True):
        w.write(m.topic, m.schema, m.data, m.stamp_ns, r, m.sequence)
    w.flush()   # never closed: no summary, as after a kill
    assert time_layout(tmp_path / "killed.mcap") == RECEIVE
    got = list(read_recording(tmp_path / "killed.mcap"))
    assert sorted((m.stamp_ns, m.receive_ns) for m in got) == sorted(zip((m.stamp_ns for m in messages), received,
                                                                         strict=True))
    recover(tmp_path / "killed.mcap", tmp_path / "recovered.mcap")
    assert time_layout(tmp_path / "recovered.mcap") == RECEIVE
    assert list(read_recording(tmp_path / "recovered.mcap")) == got


def _message(topic: str, stamp: int, received: int) -> RecordedMessage:
    return RecordedMessage(topic, "", b"", received, stamp, 0, stamp, received)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(["scan", "odom", "truth"]), st.integers(0, 10**10),
                          st.integers(0, REORDER_WINDOW_NS - 1)), max_size=60))
def test_receive_order_is_undone_within_the_window(draws):
    """Messages delayed by less than the window come out in stamp order, each once; ties in receive order."""
    messages = sorted((_message(topic, stamp, stamp + delay) for topic, stamp, delay in draws),
                      key=lambda m: m.log_time_ns)
    out = list(reader.in_stamp_order(messages))
    assert sorted(out, key=id) == sorted(messages, key=id)
    assert [m.stamp_ns for m in out] == sorted(m.stamp_ns for m in messages)
    # Where log time is the stamp (older and offline files), nothing moves.
    stamped = sorted((_message(topic, stamp, stamp) for topic, stamp, _ in draws), key=lambda m: m.log_time_ns)
    assert [id(m) for m in reader.in_stamp_order(stamped)] == [id(m) for m in stamped]
