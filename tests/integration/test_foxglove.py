"""Foxglove's views of a live pipeline: in its recording, and served by ``lrfslam monitor``.

Router, the five processing services, the recorder and the monitor run as real processes on
loopback Zenoh. A WebSocket client speaks Foxglove's protocol to the monitor (advertise →
subscribe → binary message frames) and decodes what it gets with the schemas the server
advertised; the recording is read back with the mcap library and decoded with the schemas
embedded in it. Both are compared with the pipeline's own messages in the recording.
"""

from __future__ import annotations

import asyncio
import base64
import json
import math
import struct
import subprocess
import time
from collections import defaultdict

import numpy as np
import pytest
import websockets
from conftest import Cluster, free_port
from mcap.reader import make_reader
from mcap.records import Schema
from mcap_protobuf.decoder import DecoderFactory

from lrfslam.algo.geometry import compose
from lrfslam.msgs import topics
from lrfslam.msgs.landmark_map import LandmarkMapReplica
from lrfslam.viz import foxglove as fx

pytestmark = pytest.mark.integration

STAGES = ("recorder", "mapper", "slam", "features", "denoise")
WANTED = (fx.SCAN, fx.TRAJECTORY_SLAM, fx.LANDMARKS, fx.FEATURES, fx.TF)


def ns(ts) -> int:
    return ts.seconds * 1_000_000_000 + ts.nanos


def xyt(translation, rotation) -> np.ndarray:
    return np.array([translation.x, translation.y, 2 * math.atan2(rotation.z, rotation.w)])


async def foxglove_client(port: int, enough: int, timeout_s: float) -> tuple[str, dict, dict]:
    """Connect as Foxglove does, subscribe to WANTED, and collect decoded messages per topic."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            ws = await websockets.connect(f"ws://127.0.0.1:{port}",
                                          subprotocols=["foxglove.websocket.v1", "foxglove.sdk.v1"])
            break
        except OSError:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.2)
    channels, received, factory = {}, defaultdict(list), DecoderFactory()
    async with ws:
        while time.monotonic() < deadline and not all(len(received[tp]) >= enough for tp in WANTED):
            frame = await asyncio.wait_for(ws.recv(), deadline - time.monotonic())
            if isinstance(frame, str):
                op = json.loads(frame)
                if op["op"] == "advertise":
                    new = {c["id"]: c for c in op["channels"]}
                    channels.update(new)
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                        {"id": cid, "channelId": cid} for cid, c in new.items() if c["topic"] in WANTED]}))
            elif frame[0] == 0x01:   # message data: subscription id, log time, payload
                sub, log_time = struct.unpack_from("<IQ", frame, 1)
                c = channels[sub]
                schema = Schema(id=sub, name=c["schemaName"], encoding=c["schemaEncoding"],
                                data=base64.b64decode(c["schema"]))
                received[c["topic"]].append((log_time, factory.decoder_for(c["encoding"], schema)(frame[13:])))
        return ws.subprotocol, channels, received


def status_out(cluster, session, service, topic):
    return cluster.wait_for(session, lambda a, st: st[service].counters.get(f"out.{topic}", 0)
                            if service in st else 0, 10, f"{service} counters")


@pytest.mark.slow   # end to end, long: the slow step (.ci/run step 3)
def test_the_live_pipeline_opens_in_foxglove_recorded_and_live(cluster):
    port = free_port()
    for name in STAGES:
        cluster.start(name, *(("name=run",) if name == "recorder" else ()))
    cluster.procs["monitor"] = subprocess.Popen(cluster.cmd(
        "monitor", "--connect", cluster.endpoint, "--robot", cluster.robot, "--port", str(port),
        "--log-level", "WARNING"), cwd=cluster.tmp)
    session = cluster.session()
    with session:
        cluster.wait_for(session, lambda alive, st: {s for _, s in alive} >= set(STAGES), 30, "liveliness")
        cluster.start("sensor", "speedup=4", "seed=3", "source=sim")
        subprotocol, channels, live = asyncio.run(foxglove_client(port, enough=15, timeout_s=60))
        cluster.wait_for(session, lambda a, st: st.get("slam") and st["slam"].counters.get(
            "out.slam/state", 0) >= 60, 60, "60 SLAM states")
    for name in ("sensor", *reversed(STAGES), "monitor"):
        assert cluster.stop(name) == 0, f"{name} did not exit cleanly on SIGTERM"

    # The protocol: every view channel advertised with its Foxglove schema, protobuf.
    assert subprotocol == "foxglove.sdk.v1"
    advertised = {c["topic"]: (c["schemaName"], c["encoding"], c["schemaEncoding"]) for c in channels.values()}
    assert advertised == {tp: (fx.SCHEMA_NAMES[cls], "protobuf", "protobuf") for tp, cls in fx.CHANNELS.items()}
    assert all(len(live[tp]) >= 15 for tp in WANTED), {tp: len(v) for tp, v in live.items()}

    # The recording, read back with the mcap library: its raw channels and its views.
    path = cluster.tmp / "recordings" / "run" / "run_0.mcap"
    raw, views, schemas, tf, receive_times = defaultdict(dict), defaultdict(dict), {}, [], defaultdict(dict)
    replica, map_at = LandmarkMapReplica(), {}   # the landmark map after each state, as the recorder's views saw it
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        # MCAP's times: publish time the data stamp, log time the recorder's receive time (the
        # simulated stamps run ahead of it here: speedup 4).
        for schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True):
            if topics.is_foxglove(channel.topic):
                schemas[channel.topic] = (schema.name, schema.encoding, channel.message_encoding)
                if channel.topic == fx.TF:    # odometry and EKF both send transforms at a scan's stamp
                    tf.append((message.publish_time, decoded))
                else:
                    # The loop-closed path is sent again at the stamp of the scan whose map/pose
                    # sent it when that scan's optimisation (map/keyframes) moves the past: the later wins.
                    assert message.publish_time not in views[channel.topic] or channel.topic == fx.TRAJECTORY_MAP
                    views[channel.topic][message.publish_time] = decoded
                    receive_times[channel.topic][message.publish_time] = message.log_time
            elif channel.topic in ("scan", "slam/state", "slam/map", "odom", "map/pose"):
                value = topics.by_name(channel.topic).codec.decode(message.data, schema.name)
                raw[channel.topic][message.publish_time] = value
                receive_times[channel.topic][message.publish_time] = message.log_time
                if channel.topic.startswith("slam/"):
                    replica.apply_message(value)
                    if channel.topic == "slam/state":
                        map_at[message.publish_time] = replica.landmarks
    # (Every view of a mapping run: the localization view is made only on a saved map.)
    assert schemas == {tp: (fx.SCHEMA_NAMES[cls], "protobuf", "protobuf") for tp, cls in fx.CHANNELS.items()
                       if tp != fx.LOCALIZATION}

    # Scans: one view per scan, at its stamp and its receive time, the same ranges (live too).
    assert set(views[fx.SCAN]) == set(raw["scan"]) and len(raw["scan"]) >= 60
    assert receive_times[fx.SCAN] == receive_times["scan"]
    for stamp, scan in raw["scan"].items():
        np.testing.assert_array_equal(views[fx.SCAN][stamp].ranges, scan.ranges_m)
        assert ns(views[fx.SCAN][stamp].timestamp) == stamp
    for stamp, msg in live[fx.SCAN]:
        np.testing.assert_array_equal(msg.ranges, raw["scan"][stamp].ranges_m)

    # Landmarks: ids and 95 % ellipses from the EKF's covariances (recorded and live).
    # The slam stage sends changes; the views draw the map they add up to (slam/map now and then).
    assert replica.complete and len(raw["slam/map"]) >= 2
    for stamp, msg in [*views[fx.LANDMARKS].items(), *live[fx.LANDMARKS]]:
        lms = map_at[stamp]
        ents = {e.id: e for e in msg.entities}
        assert set(ents) == {f"landmark/{i}" for i in lms.ids} | {"pose"}
        for i, lid in enumerate(lms.ids):
            ell = ents[f"landmark/{lid}"].spheres[1]
            vals = np.linalg.eigvalsh(lms.cov_m2[i])
            np.testing.assert_allclose(np.array([ell.size.y, ell.size.x]) ** 2 / 4 / 5.991, vals, rtol=1e-3)
    assert max(s.n_landmarks for s in raw["slam/state"].values()) >= 3

    # The EKF's trajectory ends at the state it was sent with; the transforms put the robot there.
    for stamp, msg in [*views[fx.TRAJECTORY_SLAM].items(), *live[fx.TRAJECTORY_SLAM]]:
        last = msg.poses[-1]
        np.testing.assert_allclose(xyt(last.position, last.orientation), raw["slam/state"][stamp].pose, atol=1e-9)
    odom_at, placed = {}, 0
    for stamp, msg in tf:
        trs = {(tr.parent_frame_id, tr.child_frame_id): xyt(tr.translation, tr.rotation) for tr in msg.transforms}
        assert all(ns(tr.timestamp) == stamp for tr in msg.transforms)
        if ("odom", "base_link") in trs:
            odom_at[stamp] = trs[("odom", "base_link")]
        if ("map", "odom") in trs:   # map→odom→base_link: the EKF's pose moved by the mapper's correction
            robot = compose(trs[("map", "odom")], odom_at[stamp])
            expected = compose(trs[("map", "slam")], raw["slam/state"][stamp].pose)
            np.testing.assert_allclose(robot[:2], expected[:2], atol=1e-6)
            placed += 1
    assert placed == len(raw["slam/state"])


def test_monitor_says_in_one_line_why_it_cannot_start(tmp_path):
    from lrfslam.tools.monitor import FoxgloveServer

    taken = FoxgloveServer("127.0.0.1", 0, "taken")
    try:
        for args, why in ((["--port", str(taken.port)], "cannot serve Foxglove on 127.0.0.1"),
                          (["--robot", "a/b"], "robot name 'a/b' must be one key chunk")):
            res = subprocess.run([*Cluster(tmp_path).cmd("monitor", *args)], capture_output=True, text=True,
                                 timeout=60, check=False)
            assert res.returncode == 2, res.stderr
            (line,) = [ln for ln in res.stderr.splitlines() if "ERROR" in ln]
            assert why in line and "Traceback" not in res.stderr
    finally:
        taken.close()
