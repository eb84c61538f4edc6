"""``lrfslam play`` against live services, all real processes on a real router (TCP on loopback).

Fast: ``--loop`` numbering every topic on across loops under one producer, with the recorded
stamps and payloads, stopped by SIGINT; refusals (no live stage to wait for, a live sensor on the
same keys). Slow: the same stopped by SIGTERM; a stalled stage failing ``--rate max`` loudly; a
recording played ``--rate max`` through the stages as separate processes gives, in the recorder's
recording, the same outputs byte for byte as ``lrfslam pipeline --replay`` of the same input, with
no drop and no gap anywhere; ``lrfslam up --skip sensor`` fed by play.
"""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
from conftest import free_port

from lrfslam import services
from lrfslam.msgs import codec, counters, topics
from lrfslam.runtime.bus import parse_attachment
from lrfslam.runtime.recording import read_recording
from lrfslam.runtime.sequence import SequenceTracker
from lrfslam.tools.status import query_status

pytestmark = pytest.mark.integration

GOLDEN = Path(__file__).resolve().parents[1] / "data" / "golden"
SUMMARY = re.compile(r"^lrfslam play: (\d+) messages \((\d+) scans\) in [\d.]+ s: .*$")


def play(cluster, *args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "lrfslam.cli", "play", *args, "--robot", cluster.robot,
                             "--connect", cluster.endpoint], cwd=cluster.tmp, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def alive(cluster, session, *names: str) -> None:
    cluster.wait_for(session, lambda a, st: {s for _, s in a} >= set(names), 60, f"{', '.join(names)} alive")


@pytest.mark.parametrize("sig", [signal.SIGINT, pytest.param(signal.SIGTERM, marks=pytest.mark.slow)],
                         ids=["SIGINT", "SIGTERM"])
def test_loop_numbers_each_topic_on_across_loops_and_a_signal_stops_it(cluster, sig):
    source = GOLDEN / "sim_head.mcap"   # 80 frames of scan, odom and truth at 10 Hz
    recorded = defaultdict(list)
    for m in read_recording(source):
        recorded[m.topic].append(m)
    got = defaultdict(list)   # topic -> (seq, stamp, producer, payload)
    lock = threading.Lock()

    def on_sample(sample) -> None:
        att = parse_attachment(sample.attachment.to_bytes() if sample.attachment is not None else None)
        with lock:
            got[topics.relative(cluster.robot, str(sample.key_expr))].append(
                (att.seq, att.stamp_ns, att.producer, sample.payload.to_bytes()))

    session = cluster.session()
    with session:
        sub = session.declare_subscriber(topics.everything(cluster.robot), on_sample)
        time.sleep(0.5)
        proc = play(cluster, str(source), "--rate", "20", "--loop")
        deadline = time.monotonic() + 60
        while len(got["scan"]) < 2 * 80 + 10:   # into the third loop
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "too few scans played"
            time.sleep(0.05)
        proc.send_signal(sig)
        try:
            out, err = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            pytest.fail(f"play did not stop on {sig.name}; its stderr:\n{proc.communicate()[1]}")
        time.sleep(0.5)   # the last samples on their way
        sub.undeclare()
    assert proc.returncode == 128 + sig, err
    lines = out.splitlines()
    m = SUMMARY.match(lines[0]) if len(lines) == 1 else None
    assert m, out
    assert re.search(r"; (\d+) loops;", lines[0]) and lines[0].endswith(f"stopped by {sig.name}"), lines[0]
    assert int(m.group(1)) == sum(len(v) for v in got.values()) and int(m.group(2)) == len(got["scan"])
    producers = {p for samples in got.values() for _, _, p, _ in samples}
    assert len(producers) == 1 and len(next(iter(producers))) == 16
    tracker = SequenceTracker()   # what every consumer counts (docs/delivery.md)
    for topic in ("scan", "odom", "truth"):
        samples = got[topic]
        # Numbered by play, on and on: the consumers count no gap and no restart at a new loop.
        assert [s for s, _, _, _ in samples] == list(range(1, len(samples) + 1)), topic
        for seq, _, producer, _ in samples:
            tracker.observe(producer, topic, seq)
        # Each loop: the recorded stamps and payloads, in order.
        for i, (_, stamp, _, payload) in enumerate(samples):
            r = recorded[topic][i % len(recorded[topic])]
            assert (stamp, payload) == (r.stamp_ns, r.data), (topic, i)
    assert +tracker.counts == {}


@pytest.mark.slow
def test_a_stalled_stage_fails_rate_max_loudly(cluster, monkeypatch):
    monkeypatch.setenv("LRFSLAM_BUS_DEBUG_SLOW", "denoise:4000")   # 4 s per scan
    cluster.start("denoise")
    session = cluster.session()
    with session:
        alive(cluster, session, "denoise")
    proc = play(cluster, str(GOLDEN / "sim_head.mcap"), "--rate", "max", "--window", "1", "--timeout", "1")
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 1, (out, err)
    # denoise answers its first scan, then sleeps over the second.
    m = re.search(r"the pipeline stalled: no scan/filtered for 1 s with 1 scans in flight \((\d+) of (\d+) "
                  r"answered\); denoise is alive but answered nothing$", err.strip())
    assert m and int(m.group(2)) == int(m.group(1)) + 1, err
    m = re.search(r"scan/filtered answered (\d+) of (\d+) scans", out)
    assert SUMMARY.match(out.strip()) and m and int(m.group(2)) == int(m.group(1)) + 1, out


def test_rate_max_needs_a_live_stage_and_nothing_plays_over_a_live_sensor(cluster):
    source = str(GOLDEN / "sim_head.mcap")
    proc = play(cluster, source, "--rate", "max")
    out, err = proc.communicate(timeout=60)
    assert (proc.returncode, out) == (2, "")
    assert err.strip().endswith("has none fed by scan, odom, truth (start them, e.g. lrfslam up --skip sensor, or "
                                "play with --rate X)") and err.strip().count("\n") == 0, err
    cluster.start("sensor", "source=sim")
    session = cluster.session()
    with session:
        alive(cluster, session, "sensor")
    proc = play(cluster, source, "--rate", "3")
    out, err = proc.communicate(timeout=60)
    assert (proc.returncode, out) == (2, "")
    assert "error: sensor is alive on this robot and publishes scan, odom, truth itself" in err


def stage_counters(session, cluster) -> dict[str, dict[str, int]]:
    return {s.service: s.counters for s in query_status(session, cluster.robot, 2.0)[1]}


def by_topic(source, names) -> dict[str, list]:
    out = defaultdict(list)
    for m in read_recording(source, names):
        out[m.topic].append(m)
    return out


@pytest.mark.parametrize(("name", "stages", "grouped"), [
    pytest.param("intel_150", ("denoise", "features", "slam"), False, marks=pytest.mark.slow),
    pytest.param("sim_head", ("denoise", "features", "slam", "mapper"), False, marks=pytest.mark.slow),
    pytest.param("sim_head", ("denoise", "features", "slam", "mapper"), True, id="sim_head-one-process")])
def test_rate_max_through_live_stages_equals_the_offline_pipeline(cluster, name, stages, grouped):
    """As separate processes, or as one (``lrfslam group``: between stages in memory, each still on the bus)."""
    source = GOLDEN / f"{name}.mcap"
    cluster.start("recorder", "name=run")
    if grouped:
        cluster.start_group(stages)
    else:
        for stage in stages:
            cluster.start(stage)
    session = cluster.session()
    with session:
        alive(cluster, session, "recorder", *stages)
        proc = play(cluster, str(source), "--rate", "max")
        out, err = proc.communicate(timeout=600)
        assert proc.returncode == 0, (out, err)
        by_service = stage_counters(session, cluster)
        pids = {st.service: st.pid for st in query_status(session, cluster.robot, 2.0)[1]}
    scans = sum(1 for _ in read_recording(source, ["scan"]))
    watched = "map/pose" if "mapper" in stages else "slam/state"
    assert out.strip().endswith(f"{watched} answered {scans} of {scans} scans; live services dropped 0, gaps 0"), out
    for service in ("recorder", *stages):
        c = by_service[service]
        assert counters.total(c, "drop.", "gap.", "dup.", "restart.", "error.") == 0, (service, c)
    assert by_service["denoise"]["in.scan"] == scans and by_service["slam"]["out.slam/state"] == scans
    if grouped:
        assert len({pids[s] for s in stages}) == 1 and pids[stages[0]] != pids["recorder"], pids
    for service in ("group",) if grouped else stages:   # their last outputs reach the recorder before it stops
        assert cluster.stop(service) == 0, service
    assert cluster.stop("recorder") == 0

    reference = cluster.tmp / "reference.mcap"
    subprocess.run([sys.executable, "-m", "lrfslam.cli", "pipeline", "--replay", str(source), "--out", str(reference),
                    "-q", "--stages", ",".join(stages), "--log-level", "WARNING"], check=True, cwd=cluster.tmp)
    outputs = [tp.name for stage in stages for tp in services.spec(stage).outputs]
    live = by_topic(cluster.tmp / "recordings" / "run", ["scan", "odom", "truth", *outputs])
    offline = by_topic(reference, outputs)
    inputs = by_topic(source, ["scan", "odom", "truth"])
    # The played inputs: the recorded stamps and payloads, numbered by play from 1.
    for topic, recorded in inputs.items():
        assert [(m.stamp_ns, m.data) for m in live[topic]] == [(m.stamp_ns, m.data) for m in recorded], topic
        assert [m.sequence for m in live[topic]] == list(range(1, len(recorded) + 1)), topic
    for topic in outputs:
        assert offline[topic], topic
        assert [(m.stamp_ns, m.sequence) for m in live[topic]] == \
               [(m.stamp_ns, m.sequence) for m in offline[topic]], topic
        if topic == "slam/state":   # per scan: pose, covariance and landmarks, for a readable failure
            for a, b in zip(live[topic], offline[topic], strict=True):
                sa, sb = codec.SLAM_STATE.decode(a.data), codec.SLAM_STATE.decode(b.data)
                for field in ("pose", "pose_cov", "removed_landmark_ids"):
                    assert np.array_equal(getattr(sa, field), getattr(sb, field)), (sa.scan_seq, field)
                for field in ("ids", "xy_m", "cov_m2"):
                    assert np.array_equal(getattr(sa.landmarks, field), getattr(sb.landmarks, field)), \
                        (sa.scan_seq, field)
        assert [m.data for m in live[topic]] == [m.data for m in offline[topic]], topic


@pytest.mark.slow
def test_up_without_a_sensor_runs_on_a_recording_played_in(tmp_path):
    """``lrfslam up --skip sensor`` then ``lrfslam play --rate max``: up's summary holds every scan, nothing
    dropped or missed, and the SLAM against the truth that was played."""
    port = free_port()
    up = subprocess.Popen([sys.executable, "-m", "lrfslam.cli", "up", "--skip", "sensor", "--port", str(port),
                           "--robot", "played", "--quiet", "--recordings", str(tmp_path / "recordings")],
                          cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    endpoint = f"tcp/127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 90
        while True:
            assert up.poll() is None, up.communicate()
            assert time.monotonic() < deadline, "up's stages did not come up"
            check = subprocess.run([sys.executable, "-m", "lrfslam.cli", "status", "--connect", endpoint, "--robot",
                                    "played", "--check", *[a for s in ("denoise", "features", "slam", "mapper",
                                                                       "recorder") for a in ("-s", s)]],
                                   check=False, capture_output=True, text=True)
            if check.returncode == 0:
                break
            time.sleep(0.5)
        played = subprocess.run([sys.executable, "-m", "lrfslam.cli", "play", str(GOLDEN / "sim_head.mcap"),
                                 "--rate", "max", "--robot", "played", "--connect", endpoint],
                                check=False, capture_output=True, text=True, timeout=300)
        assert played.returncode == 0, played
        assert "map/pose answered 80 of 80 scans; live services dropped 0, gaps 0" in played.stdout
    finally:
        up.send_signal(signal.SIGTERM)
        out, err = up.communicate(timeout=120)
    assert up.returncode == 0, err
    rows = {line.split()[0]: line.split() for line in out.splitlines()
            if line.split() and line.split()[0] in ("denoise", "features", "slam", "mapper", "recorder")}
    assert set(rows) == {"denoise", "features", "slam", "mapper", "recorder"} and "sensor" not in out.split("SLAM:")[0]
    for name, row in rows.items():
        assert row[3:5] == ["0", "0"], (name, row)   # dropped, gaps
    # The slam's outputs: 80 states and its whole map at the first, at 5 s of data time and at the last.
    assert rows["denoise"][1] == "80" and rows["slam"][2] == "83"
    assert "SLAM: 80 scans" in out
    assert "scans in the recording 80 (no sensor: played in or published by another process)" in out
