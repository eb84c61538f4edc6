"""Every service as a real process on loopback Zenoh: data flows through each stage into the recording.

Also: liveliness and status queryables, each stage's latency and the age of its outputs
(from the sensor stamp, wall clock: the simulator runs at speedup 1 so its stamps are wall
time), restart of a killed stage, wrong-version and malformed samples counted without
stopping the pipeline, clean SIGTERM exits, and a recording that the mcap library decodes
with the schemas embedded in it, at MCAP's times (log time received, publish time the stamp).
"""

from __future__ import annotations

import re
import signal
from collections import Counter

import pytest
import zenoh
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from lrfslam.msgs import codec, topics
from lrfslam.msgs import types as t
from lrfslam.tools.status import status_table

pytestmark = pytest.mark.integration

STAGES = ("recorder", "slam", "features", "denoise")


def out(statuses, service, topic):
    s = statuses.get(service)
    return s.counters.get(f"out.{topic}", 0) if s else 0


def test_pipeline_runs_end_to_end_over_zenoh(cluster, monkeypatch):
    for name in STAGES:
        cluster.start(name, *(("name=run",) if name == "recorder" else ()))
    session = cluster.session()
    with session:
        cluster.wait_for(session, lambda alive, st: {s for _, s in alive} >= set(STAGES), 30, "liveliness")
        cluster.start("sensor", "speedup=1", "seed=3", "source=sim")
        st = cluster.wait_for(session, lambda a, st: out(st, "slam", "slam/state") >= 40 and st, 60, "40 SLAM states")
        # Each stage's latency, receipt of an input to its outputs published: measured, ordered, in
        # the table; the sensor, which has no inputs, reports none.
        for name in ("denoise", "features", "slam"):
            c = st[name].counters
            assert 0 < c["latency.p50_us"] <= c["latency.p99_us"], (name, c)
            # The age of its outputs from the scan's stamp includes that latency (the same outputs in
            # both windows), is finite and plausible; no stamp came from the future.
            assert c["latency.p50_us"] <= c["age.p50_us"] <= c["age.p99_us"] < 60_000_000, (name, c)
            assert c["latency.p99_us"] <= c["age.p99_us"] and "age.ahead" not in c, (name, c)
            assert re.search(rf"\b{name}\b.*\b\d+\.\d/\d+\.\d\s+\d+\.\d/\d+\.\d\b",
                             status_table(set(), [st[name]])), name
        assert "latency.p50_us" not in st["sensor"].counters
        assert 0 <= st["sensor"].counters["age.p50_us"] <= st["sensor"].counters["age.p99_us"] < 60_000_000

        # Bad samples on the scan key: a future schema version and a corrupt payload.
        key = topics.key(cluster.robot, "scan")
        good = codec.LASER_SCAN.encode(t.LaserScan.from_ranges(1, 1, [1.0, 1.0, 1.0], 0.0, 0.1))
        session.put(key, good, encoding=zenoh.Encoding("application/protobuf;lrfslam.msgs.v9.LaserScan"))
        session.put(key, b"\xff\xfe garbage", encoding=zenoh.Encoding(topics.SCAN.codec.encoding))

        def bad_counted(alive, st):
            c = st["denoise"].counters if "denoise" in st else {}
            return c.get("error.schema", 0) >= 1 and c.get("error.decode", 0) >= 1
        cluster.wait_for(session, bad_counted, 15, "denoise to count the bad samples")

        # Kill a stage: its token goes, a restarted one takes over, data flows again.
        cluster.procs["features"].send_signal(signal.SIGKILL)
        cluster.procs.pop("features").wait(10)
        cluster.wait_for(session, lambda alive, st: ("itest", "features") not in alive, 15, "features token to vanish")
        # Restarted as `lrfslam up --speedup` other than 1 starts it: stamps not on the wall clock, no age.
        monkeypatch.setenv("LRFSLAM_BUS_WALL_CLOCK_STAMPS", "false")
        cluster.start("features")
        restarted = cluster.wait_for(session, lambda a, st: out(st, "features", "features") >= 10 and st, 60,
                                     "restarted features output")
        c = restarted["features"].counters
        assert "latency.p50_us" in c and not any(k.startswith("age.") for k in c), c
        assert re.search(r"\bfeatures\b.*\b\d+\.\d/\d+\.\d\s+–\s", status_table(set(), [restarted["features"]]))
        before = cluster.wait_for(session, lambda a, st: out(st, "slam", "slam/state"), 5, "slam counters")
        cluster.wait_for(session, lambda a, st: out(st, "slam", "slam/state") > before + 5, 30, "slam to continue")

    for name in ("sensor", "denoise", "features", "slam", "recorder"):
        assert cluster.stop(name) == 0, f"{name} did not exit cleanly on SIGTERM"

    path = cluster.tmp / "recordings" / "run" / "run_0.mcap"
    per_topic, schemas, undecodable = Counter(), {}, []
    factory = DecoderFactory()
    with open(path, "rb") as f:
        reader = make_reader(f)
        assert reader.get_summary() is not None  # finished cleanly: footer and summary written
        assert {m.name: dict(m.metadata) for m in reader.iter_metadata()}["lrfslam.times"] == {
            "log_time": "receive", "publish_time": "stamp"}
        for schema, channel, message in reader.iter_messages():
            # Received (recorder's wall clock) after stamped (the sensor's, the same clock here).
            assert message.log_time >= message.publish_time > 0, channel.topic
            # The recorder stores what it received, the two bad samples included.
            decoder = factory.decoder_for(channel.message_encoding, schema) if schema else None
            try:
                decoded = decoder(message.data) if decoder else None
            except Exception:  # noqa: BLE001 - the corrupt sample fails in protobuf's own way
                decoded = None
            if decoded is None:
                undecodable.append((channel.topic, channel.metadata.get("schema")))
                continue
            assert decoded.DESCRIPTOR.full_name == schema.name
            per_topic[channel.topic] += 1
            schemas[channel.topic] = schema.name
    assert sorted(undecodable) == [("scan", topics.SCAN.schema), ("scan", "lrfslam.msgs.v9.LaserScan")]
    for topic in ("scan", "odom", "truth", "scan/filtered", "features", "slam/state"):
        assert per_topic[topic] >= 40, (topic, per_topic)
        assert schemas[topic] == topics.by_name(topic).schema
    assert any(k.startswith("health/") for k in per_topic)
    # Every scan passed through every stage except while features was down.
    assert per_topic["scan/filtered"] >= per_topic["scan"] - 2
    assert per_topic["slam/state"] >= per_topic["features"] - 2
