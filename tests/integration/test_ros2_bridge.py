"""``lrfslam ros2`` against a plain Zenoh session behaving as a ROS 2 node (rmw_zenoh, Jazzy), on a real router.

Out: the bridge runs beside ``lrfslam play`` of the golden pipeline recording; the "ROS node"
(its own liveliness token, subscribers on the exact Jazzy data keys) sees the bridge's node and
publisher tokens, receives LaserScan, Odometry, TFMessage, PoseWithCovarianceStamped and, after
the session puts the mapper's keyframes, OccupancyGrid with the 33-byte attachment, decodes them
with rosbags and finds the recorded values (the grid: lrfslam's grid of the keyframes' scans); a
late subscriber gets ``/tf_static`` and ``/map`` from the transient-local caches.

In: the "ROS node" publishes the golden Intel recording re-encoded as ROS 2 LaserScan and
Odometry (with its publisher tokens and attachments); ``lrfslam ros2 --subscribe`` puts them on
the robot's ``scan`` and ``odom``, where a subscriber finds the same stamps, ranges and poses.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
import zenoh
import zenoh.ext

from lrfslam.algo.geometry import wrap_angle
from lrfslam.algo.tiled_grid import TiledGrid
from lrfslam.msgs import codec, topics
from lrfslam.msgs import types as t
from lrfslam.msgs.grid_replica import GridReplica
from lrfslam.ros2 import convert, views, wire
from lrfslam.runtime.bus import attachment, parse_attachment, producer_id
from lrfslam.runtime.recording import read_recording
from lrfslam.tools import status

pytestmark = pytest.mark.integration

GOLDEN = Path(__file__).resolve().parents[1] / "data" / "golden"
NS = "/itest"


def bridge(cluster, *args: str) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-m", "lrfslam.cli", "ros2", "--robot", cluster.robot, "--connect",
                             cluster.endpoint, "--log-level", "WARNING", *args], cwd=cluster.tmp)
    cluster.procs["ros2"] = proc
    return proc


def ros_tokens(session: zenoh.Session) -> list[str]:
    return [str(r.ok.key_expr) for r in session.liveliness().get("@ros2_lv/**", timeout=2.0) if r.ok is not None]


def wait_tokens(session, proc, predicate, what: str) -> list[str]:
    deadline = time.monotonic() + 30
    while True:
        tokens = ros_tokens(session)
        if predicate(tokens):
            return tokens
        assert proc.poll() is None, f"lrfslam ros2 exited with {proc.returncode}"
        assert time.monotonic() < deadline, f"no {what} among {tokens}"
        time.sleep(0.2)


def recorded(name: str, path: Path) -> dict[int, object]:
    return {m.stamp_ns: topics.by_name(m.topic).codec.decode(m.data, m.schema) for m in read_recording(path, [name])}


def test_a_ros2_node_sees_the_pipeline(cluster):
    source = GOLDEN / "sim_head.pipeline.mcap"
    received = defaultdict(list)   # topic -> (attachment, decoded message)
    lock = threading.Lock()
    wanted = {views.SCAN: wire.LASER_SCAN, views.SCAN_FILTERED: wire.LASER_SCAN, views.ODOM: wire.ODOMETRY,
              views.TF: wire.TF_MESSAGE, views.POSE: wire.POSE_WITH_COVARIANCE_STAMPED, views.MAP: wire.OCCUPANCY_GRID}

    def receiver(topic: str, msgtype: str):
        def on_sample(sample: zenoh.Sample) -> None:
            att = sample.attachment.to_bytes() if sample.attachment is not None else None
            with lock:
                received[topic].append((att, sample.payload.to_bytes(), msgtype))
        return on_sample

    health = cluster.tmp / "ros2-health.json"
    proc = bridge(cluster, "--health-file", str(health))
    session = cluster.session()
    with session:
        zid = str(session.zid())
        me = session.liveliness().declare_token(wire.node_token(0, zid, 0, "", "rviz_stand_in"))
        subs = [session.declare_subscriber(wire.data_key(0, rt.qualified(NS), msgtype),
                                           receiver(rt.qualified(NS), msgtype)) for rt, msgtype in wanted.items()]
        tokens = wait_tokens(session, proc, lambda ts: sum("/MP/" in x for x in ts) == len(views.PUBLISHED),
                             "publisher tokens of the bridge")
        # Its node, in the namespace, and one publisher per topic with the Jazzy type and hash; ours too.
        assert any(x.endswith("/NN/%/%itest/lrfslam") and x.split("/")[1] == "0" for x in tokens)
        assert wire.node_token(0, zid, 0, "", "rviz_stand_in") in tokens
        published = {x.split("/")[9]: x for x in tokens if "/MP/" in x}
        assert set(published) == {wire.mangle(rt.qualified(NS)) for rt in views.PUBLISHED}
        for rt in views.PUBLISHED:
            parts = published[wire.mangle(rt.qualified(NS))].split("/")
            assert parts[6:9] == ["%", "%itest", "lrfslam"]
            assert parts[10:] == [wire.dds_type_name(rt.msgtype), wire.type_hash(rt.msgtype), rt.qos.keyexpr()]
        play = subprocess.run([sys.executable, "-m", "lrfslam.cli", "play", str(source), "--topics", "scan", "odom",
                               "scan/filtered", "slam/state", "slam/map", "--rate", "8", "--robot", cluster.robot,
                               "--connect", cluster.endpoint], cwd=cluster.tmp, capture_output=True, text=True, check=False,
                              timeout=120)
        assert play.returncode == 0, play.stderr
        assert status.main(["--check-file", str(health)]) == 0   # what its container's healthcheck runs
        # The mapper's live grid (this session stands in for it): every 10th scan laid at the EKF's pose.
        kf_stamps = sorted(recorded("scan", source))[::10]
        scan_at, state_at = recorded("scan", source), recorded("slam/state", source)
        tiled = TiledGrid()
        for s in kf_stamps:
            tiled.lay(s, state_at[s].pose, scan_at[s].grid_ranges(), scan_at[s].angle_min_rad,
                      scan_at[s].angle_increment_rad)
        tiles = tiled.tiles()
        grid_value = t.MapGrid(stamp_ns=kf_stamps[-1], seq=1, resolution_m=tiled.resolution_m,
                               tile_cells=tiled.tile_cells, tiles=tiles, cells=[tiled.trinary(x) for x in tiles],
                               whole=True, keyframes=len(kf_stamps))
        session.put(topics.key(cluster.robot, topics.MAP_GRID.name), topics.MAP_GRID.codec.encode(grid_value),
                    encoding=zenoh.Encoding(topics.MAP_GRID.codec.encoding),
                    attachment=attachment(1, grid_value.stamp_ns, producer_id(session)))
        deadline = time.monotonic() + 10
        while (len(received[views.POSE.qualified(NS)]) < 80 or not received[views.MAP.qualified(NS)]) \
                and time.monotonic() < deadline:
            time.sleep(0.1)
        # A subscriber joining now gets /tf_static and the map from the publishers' caches (transient local).
        late = defaultdict(list)
        late_subs = [zenoh.ext.declare_advanced_subscriber(
            session, wire.data_key(0, topic, msgtype), lambda s, topic=topic: late[topic].append(s.payload.to_bytes()),
            history=zenoh.ext.HistoryConfig(detect_late_publishers=True))
            for topic, msgtype in (("/tf_static", wire.TF_MESSAGE), (f"{NS}/map", wire.OCCUPANCY_GRID))]
        deadline = time.monotonic() + 10
        while len(late) < 2 and time.monotonic() < deadline:
            time.sleep(0.1)
        for sub in late_subs:
            sub.undeclare()
        for sub in subs:
            sub.undeclare()
        me.undeclare()
    assert cluster.stop("ros2") == 0

    scans, odoms = recorded("scan", source), recorded("odom", source)
    filtered, states = recorded("scan/filtered", source), recorded("slam/state", source)
    gids = {}
    for topic, samples in received.items():
        assert samples, topic
        seqs = []
        for att, payload, msgtype in samples:
            seq, stamp, gid = wire.parse_attachment(att)   # 33 bytes, or it raises
            msg = convert.deserialize(payload, msgtype)
            stamped = msg.transforms[0].header.stamp if msgtype == wire.TF_MESSAGE else msg.header.stamp
            assert stamp == convert.stamp_ns(stamped)      # the source timestamp: the data stamp
            seqs.append(seq)
            gids.setdefault(topic, set()).add(gid)
        assert seqs == list(range(1, len(seqs) + 1)), topic
    # Each publisher's GID is that of its token.
    for topic, found in gids.items():
        assert found == {wire.gid(published[wire.mangle(topic)])}
    decoded = {topic: [convert.deserialize(p, m) for _, p, m in samples] for topic, samples in received.items()}
    assert len(decoded["/itest/scan"]) == len(scans) == 80
    for msg in decoded["/itest/scan"]:
        scan = scans[convert.stamp_ns(msg.header.stamp)]
        assert msg.header.frame_id == "itest/laser" and msg.ranges.size == scan.ranges_m.size
        valid = scan.status == t.BEAM_VALID
        np.testing.assert_allclose(msg.ranges[valid], scan.ranges_m[valid], rtol=1e-6)
        assert np.isposinf(msg.ranges[scan.status == t.BEAM_NO_RETURN]).all()
        assert msg.angle_min == pytest.approx(scan.angle_min_rad, rel=1e-6)
        assert msg.angle_increment == pytest.approx(scan.angle_increment_rad, rel=1e-6)
    assert len(decoded["/itest/scan_filtered"]) == len(filtered)
    for msg in decoded["/itest/scan_filtered"]:
        f = filtered[convert.stamp_ns(msg.header.stamp)]
        np.testing.assert_allclose(msg.ranges[f.kept_mask], f.scan.ranges_m[f.kept_mask], rtol=1e-6)
    assert len(decoded["/itest/odom"]) == len(odoms)
    for msg in decoded["/itest/odom"]:
        odom = odoms[convert.stamp_ns(msg.header.stamp)]
        assert (msg.header.frame_id, msg.child_frame_id) == ("itest/odom", "itest/base_link")
        p = msg.pose.pose
        assert (p.position.x, p.position.y) == (odom.pose[0], odom.pose[1])
        assert wrap_angle(convert.yaw(p.orientation) - odom.pose[2]) == pytest.approx(0, abs=1e-12)
    assert len(decoded["/itest/pose"]) == len(states)
    for msg in decoded["/itest/pose"]:
        state = states[convert.stamp_ns(msg.header.stamp)]
        assert msg.header.frame_id == "itest/map"
        assert (msg.pose.pose.position.x, msg.pose.pose.position.y) == (state.pose[0], state.pose[1])
        assert msg.pose.covariance[0] == state.pose_cov[0, 0]
    frames = {(tr.header.frame_id, tr.child_frame_id) for m in decoded["/tf"] for tr in m.transforms}
    assert frames == {("itest/odom", "itest/base_link"), ("itest/map", "itest/odom")}
    # One odom -> base_link per odometry, one map -> odom per state but a first state that reached the
    # bridge before any odometry (the streams race at the start).
    assert len(odoms) + len(states) - 1 <= len(decoded["/tf"]) <= len(odoms) + len(states)
    (static,) = [convert.deserialize(p, wire.TF_MESSAGE) for p in late["/tf_static"][:1]]
    assert [(tr.header.frame_id, tr.child_frame_id) for tr in static.transforms] == [("itest/base_link", "itest/laser")]
    # The map: the mapper's tiles put together, every other cell unknown.
    (grid_msg,) = decoded["/itest/map"]
    assert [convert.deserialize(p, wire.OCCUPANCY_GRID).data.tolist() for p in late[f"{NS}/map"][:1]] == \
        [grid_msg.data.tolist()]
    replica = GridReplica()
    replica.apply(grid_value)
    grid = replica.image()
    assert (grid_msg.header.frame_id, convert.stamp_ns(grid_msg.header.stamp)) == ("itest/map", kf_stamps[-1])
    assert (grid_msg.info.height, grid_msg.info.width) == grid.cells.shape
    assert (grid_msg.info.origin.position.x, grid_msg.info.origin.position.y) == tuple(grid.origin_xy_m)
    assert grid_msg.info.resolution == pytest.approx(grid.resolution_m)
    assert grid_msg.data.tolist() == grid.cells.reshape(-1).tolist()
    assert {100, 0, -1} <= set(grid_msg.data.tolist())


def test_a_ros2_robots_scans_and_odometry_reach_the_pipeline(cluster):
    source = GOLDEN / "intel_150.mcap"
    scans, odoms = recorded("scan", source), recorded("odom", source)
    got = defaultdict(list)
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        att = parse_attachment(sample.attachment.to_bytes() if sample.attachment is not None else None)
        with lock:
            got[topics.relative(cluster.robot, str(sample.key_expr))].append(
                (att, sample.payload.to_bytes(), str(sample.encoding)))

    proc = bridge(cluster, "--subscribe")
    session = cluster.session()
    with session:
        zid = str(session.zid())
        sub = session.declare_subscriber(topics.everything(cluster.robot), on_sample)
        wait_tokens(session, proc, lambda ts: sum("/MS/" in x for x in ts) == 2, "subscription tokens of the bridge")
        node = session.liveliness().declare_token(wire.node_token(0, zid, 0, NS, "robot_driver"))
        publishers = {}
        for i, (name, msgtype) in enumerate((("scan", wire.LASER_SCAN), ("odom", wire.ODOMETRY)), start=1):
            token = wire.entity_token(0, zid, 0, i, wire.PUBLISHER, NS, "robot_driver", f"{NS}/{name}", msgtype,
                                      wire.SENSOR_QOS)
            publishers[name] = (session.liveliness().declare_token(token), wire.gid(token),
                                session.declare_publisher(wire.data_key(0, f"{NS}/{name}", msgtype)))
        deadline = time.monotonic() + 10
        while not all(p.matching_status.matching for _, _, p in publishers.values()):
            assert time.monotonic() < deadline, "the bridge's subscribers never matched"
            time.sleep(0.05)
        seq = defaultdict(int)
        for m in read_recording(source):   # in stamp order, as a robot's driver publishes them
            value = topics.by_name(m.topic).codec.decode(m.data, m.schema)
            msg = (convert.laser_scan(value, NS) if m.topic == "scan" else convert.odometry(value, NS))
            _, gid, pub = publishers[m.topic]
            seq[m.topic] += 1
            pub.put(convert.serialize(msg), attachment=wire.attachment(seq[m.topic], value.stamp_ns, gid))
            time.sleep(0.002)
        deadline = time.monotonic() + 15
        while (len(got["scan"]), len(got["odom"])) < (len(scans), len(odoms)):
            assert time.monotonic() < deadline, f"{len(got['scan'])} scans, {len(got['odom'])} odometry arrived"
            time.sleep(0.1)
        sub.undeclare()
        for token, _, pub in publishers.values():
            pub.undeclare()
            token.undeclare()
        node.undeclare()
    assert cluster.stop("ros2") == 0
    assert (len(got["scan"]), len(got["odom"])) == (len(scans), len(odoms)) == (150, 150)
    producers = {att.producer for samples in got.values() for att, _, _ in samples}
    assert len(producers) == 1 and len(next(iter(producers))) == 16
    for topic, want in (("scan", scans), ("odom", odoms)):
        samples = got[topic]
        assert [att.seq for att, _, _ in samples] == list(range(1, len(want) + 1)), topic   # numbered as a sensor's
        for att, payload, encoding in samples:
            value = topics.by_name(topic).codec.decode(payload, codec.parse_encoding(encoding))
            assert att.stamp_ns == value.stamp_ns and value.stamp_ns in want
            ref = want[value.stamp_ns]
            if topic == "scan":
                assert (value.ranges_m.size, value.frame_id, value.source) == (ref.ranges_m.size, "laser",
                                                                               f"ros2:{NS}/scan")
                np.testing.assert_allclose(value.angles_rad, ref.angles_rad, rtol=1e-6, atol=1e-7)
                valid = (ref.status == t.BEAM_VALID) & (ref.ranges_m <= ref.range_max_m)
                np.testing.assert_allclose(value.ranges_m[valid], ref.ranges_m[valid], rtol=1e-6)
                assert np.array_equal(value.status == t.BEAM_VALID, valid)
                assert value.range_max_m == pytest.approx(ref.range_max_m, rel=1e-6)
            else:
                np.testing.assert_allclose(value.pose[:2], ref.pose[:2], atol=1e-12)
                assert wrap_angle(value.pose[2] - ref.pose[2]) == pytest.approx(0, abs=1e-12)
                assert value.frame_id == "odom"
