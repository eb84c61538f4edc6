"""A real recorder process killed with SIGKILL, restarted, stopped with SIGTERM, and run out of disk.

The test publishes odometry with consecutive sequence numbers from 1 (20 Hz of data) on a
real router, so what a recording lost is the gap between what was published and what the
recovered files hold. Sequence 0 is the warm-up, repeated until the recorder has one (a
route is only set up once a publisher exists).
"""

from __future__ import annotations

import os
import resource
import signal
import subprocess
import threading
import time
from collections import Counter

import pytest
from mcap.reader import make_reader

from lrfslam.msgs import codec, topics
from lrfslam.msgs import types as t
from lrfslam.runtime.bus import ZenohBus
from lrfslam.runtime.recording import read_recording, recover
from lrfslam.tools import info
from lrfslam.tools.status import query_status

pytestmark = pytest.mark.integration

PERIOD_NS = 50_000_000   # 20 Hz of data


def publish(bus: ZenohBus, seqs, pause_s: float, sent: list[int] | None = None) -> None:
    for i in seqs:
        bus.put(topics.ODOM, odom(i), i * PERIOD_NS, i)
        if sent is not None:
            sent.append(i)
        time.sleep(pause_s)


def warm_up(cluster, session, bus: ZenohBus, topic: topics.Topic, payload: bytes) -> None:
    deadline = time.monotonic() + 30
    while not recorder_counter(cluster, session, f"step.topic.{topic.name}", 1, "the warm-up", 1.0):
        assert time.monotonic() < deadline, "the recorder never received the warm-up message"
        bus.put(topic, payload, 0, 0)


def recorder_counter(cluster, session, name: str, at_least: int, what: str, timeout_s: float = 30) -> int:
    """The recorder's counter ``name`` once it is ≥ ``at_least``; 0 if only ``timeout_s`` < 30 ran out."""
    def ready(alive, st):
        return "recorder" in st and st["recorder"].counters.get(name, 0) >= at_least and st["recorder"].counters[name]
    if timeout_s < 30:
        _, statuses = query_status(session, cluster.robot, timeout_s)
        return next((ready(None, {s.service: s}) or 0 for s in statuses if s.service == "recorder"), 0)
    return cluster.wait_for(session, ready, timeout_s, what)


def odom_seqs(source) -> list[int]:
    """The data's sequence numbers (the warm-up left out)."""
    return [m.sequence for m in read_recording(source, [topics.ODOM.name]) if m.sequence]


def odom(i: int) -> bytes:
    return codec.ODOMETRY.encode(t.Odometry(stamp_ns=i * PERIOD_NS, seq=i, pose=(0.1 * i, 0.0, 0.0)))


@pytest.mark.slow   # end to end, long: the slow step (.ci/run step 3)
def test_a_killed_recorder_keeps_all_but_its_last_second_and_a_restart_adds_a_segment(cluster):
    folder = cluster.tmp / "recordings" / "run"
    cluster.start("recorder", "name=run", "flush_period_s=1.0")
    session = cluster.session()
    with session:
        bus = ZenohBus(session, cluster.robot, (), False, 10, Counter())
        cluster.wait_for(session, lambda alive, st: (cluster.robot, "recorder") in alive, 30, "the recorder")
        warm_up(cluster, session, bus, topics.ODOM, odom(0))
        # Data, then silence: the recorder's own timer puts it on disk without any new message.
        publish(bus, range(1, 40), 0.01)
        recorder_counter(cluster, session, "step.topic.odom", 40, "the first 40 received")
        received = recorder_counter(cluster, session, "step.messages", 40, "the count so far")
        recorder_counter(cluster, session, "step.flushed", received, "the first 40 flushed")
        # Data flowing when the kill comes: 20 Hz for 6 s, the kill after about 2 s.
        sent: list[int] = []
        streamer = threading.Thread(target=publish, args=(bus, range(40, 160), PERIOD_NS / 1e9, sent))
        streamer.start()
        while len(sent) < 40:
            time.sleep(0.05)
        flushed = recorder_counter(cluster, session, "step.flushed", received, "the status before the kill")
        cluster.procs["recorder"].send_signal(signal.SIGKILL)
        sent_at_kill = sent[-1]
        assert cluster.procs.pop("recorder").wait(10) == -signal.SIGKILL
        streamer.join()
        killed = folder / "run_0.mcap"
        left = killed.read_bytes()

        cluster.start("recorder", "name=run")
        cluster.wait_for(session, lambda alive, st: (cluster.robot, "recorder") in alive
                         and "recorder" in st and st["recorder"].uptime_s < 60, 30, "the restarted recorder")
        publish(bus, range(200, 220), 0.01)
        recorder_counter(cluster, session, "step.topic.odom", 20, "the restarted recorder to receive 20")
    assert cluster.stop("recorder") == 0

    # Nothing overwritten: the killed recorder's file is as it left it, the new one is next to it.
    assert killed.read_bytes() == left
    assert sorted(p.name for p in folder.iterdir()) == ["run_0.mcap", "run_1.mcap"]
    # The plain library refuses the killed file; recovered, it is indexed and holds a prefix.
    with open(killed, "rb") as f, pytest.raises(Exception):  # noqa: B017 - whatever the library raises
        make_reader(f).get_summary()
    assert "lrfslam recover" in info.describe(folder)
    recovered = cluster.tmp / "run_0.recovered.mcap"
    recover(killed, recovered)
    with open(recovered, "rb") as f:
        reader = make_reader(f)
        total = reader.get_summary().statistics.message_count   # all topics, the recorder's health too
        kept = [m.sequence for _, c, m in reader.iter_messages() if c.topic == topics.ODOM.name and m.sequence]
    assert kept == list(range(1, len(kept) + 1)), "the recovered messages are not a prefix of those sent"
    assert total >= flushed >= received
    lost_s = (sent_at_kill - kept[-1]) * PERIOD_NS / 1e9
    print(f"\nSIGKILL: kept {len(kept)} of the {sent_at_kill} messages sent before the kill; lost the last "
          f"{lost_s:.2f} s of data "
          f"(flush period 1 s; {flushed} messages of all topics reported flushed before the kill, {total} kept)")
    # SIGTERM loses nothing: the second segment is finished, indexed and complete.
    with open(folder / "run_1.mcap", "rb") as f:
        assert make_reader(f).get_summary().statistics.channel_message_counts  # indexed
    assert odom_seqs(folder / "run_1.mcap") == list(range(200, 220))
    assert odom_seqs(folder) == kept + list(range(200, 220))


def test_a_recorder_out_of_disk_says_so_once_and_leaves_a_valid_file(cluster):
    limit = 60_000

    def small_disk() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)   # EFBIG instead of death, like ENOSPC on a full disk
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    argv = cluster.cmd("recorder", "--robot", cluster.robot, "--mode", "client", "--connect", cluster.endpoint,
                       "--log-level", "WARNING", "--set", "name=full", "--set", "chunk_size_kb=4",
                       "--set", "flush_period_s=0.2", "--set", "retry_period_s=1000")
    # preexec_fn is safe enough here: the test process's other threads do not hold the import lock.
    proc = subprocess.Popen(argv, cwd=cluster.tmp, preexec_fn=small_disk, stderr=subprocess.PIPE,  # noqa: PLW1509
                            text=True, env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"})
    cluster.procs["recorder"] = proc
    session = cluster.session()
    with session:
        bus = ZenohBus(session, cluster.robot, (), False, 10, Counter())
        cluster.wait_for(session, lambda alive, st: (cluster.robot, "recorder") in alive, 30, "the recorder")
        ranges = [1.0 + 0.001 * k for k in range(361)]

        def scan(i: int) -> bytes:   # ~1 kB
            return codec.LASER_SCAN.encode(t.LaserScan.from_ranges(i * PERIOD_NS, i, [r + i for r in ranges], -1.5, 0.01))
        warm_up(cluster, session, bus, topics.SCAN, scan(0))
        for i in range(1, 400):   # well past the limit
            bus.put(topics.SCAN, scan(i), i * PERIOD_NS, i)
            time.sleep(0.002)
        status = cluster.wait_for(session, lambda a, st: "recorder" in st
                                  and st["recorder"].counters.get("step.drop.unwritable", 0) > 0 and st["recorder"],
                                  30, "the recorder to report the full disk")
        assert status.level == t.HEALTH_ERROR
    cluster.procs.pop("recorder")
    proc.terminate()
    _, stderr = proc.communicate(timeout=30)
    assert proc.returncode == 0, stderr
    assert stderr.count("recording stopped") == 1, stderr
    (segment,) = (cluster.tmp / "recordings" / "full").iterdir()
    assert segment.stat().st_size <= limit
    with open(segment, "rb") as f:   # valid for the default reader, up to the last complete chunk
        seqs = [m.sequence for _, c, m in make_reader(f).iter_messages() if c.topic == topics.SCAN.name and m.sequence]
    assert len(seqs) > 10 and seqs == list(range(1, len(seqs) + 1))
