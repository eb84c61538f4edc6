"""deploy/zenoh/router-tls-acl.json5: mutual TLS plus an access-control list, with real processes.

The committed JSON5 files and make-certs.sh are used as shipped (only the certificate folder is
moved into a temporary directory). A real router and a real denoise service run as processes on
loopback; the test's own sessions hold the service certificate (the pipeline's side) or the
monitor certificate (a remote monitor). Oracles: what a service-certificate subscriber and the
denoise service receive, and which queryable a query reaches.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import zenoh

from lrfslam.msgs import codec, topics
from lrfslam.msgs import types as t
from lrfslam.runtime.bus import (
    BusConfig,
    Message,
    ZenohBus,
    attachment,
    parse_attachment,
)
from lrfslam.tools.certs import main as certs_main
from lrfslam.tools.certs import robot_acl
from lrfslam.tools.monitor import Monitor
from lrfslam.tools.status import client_config
from lrfslam.tools.status import main as status

pytestmark = pytest.mark.integration

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"
ROBOT = "robot1"


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def acl(tmp_path, make_certs):
    """Config files for the router and every kind of client, and the router's TLS endpoint."""
    certs, rogue = tmp_path / "tls", tmp_path / "rogue"
    make_certs(certs)
    make_certs(rogue)   # another CA, with certificates of the same common names
    confs = {}
    for name, text in (("router", (DEPLOY / "zenoh" / "router-tls-acl.json5").read_text()),
                       ("service", (DEPLOY / "zenoh" / "service-tls.json5").read_text())):
        confs[name] = text.replace("/etc/lrfslam/tls/", f"{certs}/")
    confs["monitor"] = (DEPLOY / "zenoh" / "monitor-tls.json5").read_text().replace('"tls/', f'"{certs}/')
    confs["rogue"] = confs["monitor"].replace(f"{certs}/monitor", f"{rogue}/monitor")
    # Trusts the robot's CA but presents no certificate.
    confs["no-cert"] = json.dumps({"transport": {"link": {"tls": {"root_ca_certificate": f"{certs}/ca.pem"}}}})
    # A certificate from the right CA whose common name no policy names: default deny.
    confs["stranger"] = confs["monitor"].replace(f"{certs}/monitor", f"{certs}/router")
    for role in ("ros2-desk", "ros2-robot"):
        confs[role] = confs["monitor"].replace(f"{certs}/monitor", f"{certs}/{role}")
    paths = {}
    for name, text in confs.items():
        paths[name] = tmp_path / f"{name}.json5"
        paths[name].write_text(text)
    return paths, f"tls/127.0.0.1:{free_port()}"


@pytest.fixture
def pipeline(acl):
    """The ACL router and a denoise service holding the service certificate, as processes."""
    paths, endpoint = acl
    cli = [sys.executable, "-m", "lrfslam.cli"]
    procs = [subprocess.Popen([*cli, "router", "--zenoh-config", str(paths["router"]), "--log-level", "WARNING",
                               "--listen", endpoint])]
    try:
        procs.append(subprocess.Popen([*cli, "denoise", "--robot", ROBOT, "--zenoh-config", str(paths["service"]),
                                       "--mode", "client", "--connect", endpoint, "--log-level", "WARNING"]))
        deadline = time.monotonic() + 30
        while status(["--zenoh-config", str(paths["service"]), "-e", endpoint, "--robot", ROBOT,
                      "--check", "-s", "denoise"]) != 0:
            assert time.monotonic() < deadline, "denoise never answered over TLS with the service certificate"
            time.sleep(0.5)
        yield paths, endpoint
    finally:
        for proc in procs[::-1]:
            proc.terminate()
        for proc in procs[::-1]:
            proc.wait(10)


def scan(seq: int) -> bytes:
    n = 181
    return codec.LASER_SCAN.encode(t.LaserScan(stamp_ns=seq * 100_000_000, seq=seq,
                                               ranges_m=np.full(n, 2.0 + 0.01 * seq),
                                               status=np.zeros(n, np.uint8), angle_min_rad=-np.pi / 2,
                                               angle_increment_rad=np.pi / (n - 1)))


class Received:
    """Every sample on ``lrf/<robot>/**`` that a session gets: (relative key, stamp in ns, payload)."""

    def __init__(self, session: zenoh.Session) -> None:
        self.samples: list[tuple[str, int | None, bytes]] = []
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber(topics.everything(ROBOT), self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        att = sample.attachment
        _, stamp_ns, _ = parse_attachment(att.to_bytes() if att is not None else None)
        with self._lock:
            self.samples.append((topics.relative(ROBOT, str(sample.key_expr)), stamp_ns, sample.payload.to_bytes()))

    def on(self, name: str) -> list[tuple[int | None, bytes]]:
        with self._lock:
            return [(stamp_ns, payload) for key, stamp_ns, payload in self.samples if key == name]


class Names:
    """A monitor sink: the relative key of every message the `lrfslam monitor` feed hands it."""

    def __init__(self) -> None:
        self.names: list[str] = []

    def on_message(self, msg: Message) -> None:
        self.names.append(msg.name)

    def on_alive(self, service: str, alive: bool) -> None:
        pass

    def close(self) -> None:
        pass


def wait_until(predicate, what: str, timeout_s: float = 15.0):
    deadline = time.monotonic() + timeout_s
    while not (value := predicate()):
        assert time.monotonic() < deadline, what
        time.sleep(0.05)
    return value


def open_session(conf: Path, endpoint: str) -> zenoh.Session:
    return zenoh.open(client_config([endpoint], str(conf)))


def test_clients_without_the_robots_credentials_are_refused(pipeline):
    paths, endpoint = pipeline
    plain_tcp = endpoint.replace("tls/", "tcp/")
    assert status(["-e", plain_tcp, "--check"]) == 2                                   # no TLS at all
    assert status(["--zenoh-config", str(paths["no-cert"]), "-e", endpoint, "--check"]) == 2
    assert status(["--zenoh-config", str(paths["rogue"]), "-e", endpoint, "--check"]) == 2
    # Let in by the CA, but no policy names its common name: it sees no service at all.
    assert status(["--zenoh-config", str(paths["stranger"]), "-e", endpoint, "--check"]) == 0
    assert status(["--zenoh-config", str(paths["stranger"]), "-e", endpoint, "--robot", ROBOT,
                   "--check", "-s", "denoise"]) == 1
    # The monitor's certificate passes the same check.
    assert status(["--zenoh-config", str(paths["monitor"]), "-e", endpoint, "--robot", ROBOT,
                   "--check", "-s", "denoise"]) == 0


def test_a_monitor_reads_but_cannot_publish_or_answer(pipeline, capsys):
    paths, endpoint = pipeline
    # The `lrfslam monitor` feed (its Foxglove server left out) with the monitor certificate.
    feed, stop = Names(), threading.Event()
    monitor = Monitor(BusConfig(robot=ROBOT, mode="client", connect=(endpoint,), zenoh_config=str(paths["monitor"])),
                      [feed])
    feed_thread = threading.Thread(target=monitor.run, args=(stop,))
    feed_thread.start()
    try:
        wait_until(lambda: "health/denoise" in feed.names, "the monitor feed never got denoise's health")
        monitor_sees_the_pipeline_but_cannot_write(paths, endpoint)
        wait_until(lambda: "scan/filtered" in feed.names, "the monitor feed never got the pipeline's output")
    finally:
        stop.set()
        feed_thread.join(10)
    assert feed.names.count("scan") == 1 and feed.names.count("scan/filtered") == 1

    # The monitor's certificate runs `lrfslam status` and sees the pipeline's counters.
    capsys.readouterr()
    assert status(["--zenoh-config", str(paths["monitor"]), "-e", endpoint, "--robot", ROBOT, "--json"]) == 0
    (denoise,) = json.loads(capsys.readouterr().out)
    assert denoise["service"] == "denoise"
    assert denoise["counters"]["in.scan"] == 1


def monitor_sees_the_pipeline_but_cannot_write(paths: dict[str, Path], endpoint: str) -> None:
    with open_session(paths["service"], endpoint) as svc, open_session(paths["monitor"], endpoint) as mon:
        seen_by_service, seen_by_monitor = Received(svc), Received(mon)
        monitor_queries: list[str] = []
        mon_q = mon.declare_queryable(topics.status(ROBOT, topics.ANY),
                                      lambda q: monitor_queries.append(str(q.key_expr)))
        mon.liveliness().declare_token(topics.alive(ROBOT, "slam"))   # pretends to be a service
        mon_bus = ZenohBus(mon, ROBOT, (), False, 16, Counter())
        svc_bus = ZenohBus(svc, ROBOT, (), False, 16, Counter())
        wait_until(lambda: svc_bus.publisher(topics.SCAN).matching_status.matching, "denoise never subscribed")

        # The monitor's scans, through a declared publisher and a bare put: both dropped.
        mon_bus.put(topics.SCAN, scan(1), 100_000_000, 1)
        mon.put(topics.key(ROBOT, topics.SCAN.name), scan(2), attachment=attachment(2, 200_000_000, b"\0" * 16))
        # The service's scan goes through the pipeline, and the monitor gets the result.
        svc_bus.put(topics.SCAN, scan(3), 300_000_000, 3)
        wait_until(lambda: seen_by_service.on(topics.SCAN_FILTERED.name), "denoise never published")
        wait_until(lambda: seen_by_monitor.on(topics.SCAN_FILTERED.name), "the monitor never got the pipeline's data")
        time.sleep(1.0)   # the monitor's scans went out first: give them time to arrive if they could
        # Stamps tell the scans apart (denoise numbers its outputs itself).
        assert [stamp for stamp, _ in seen_by_service.on(topics.SCAN.name)] == [300_000_000]
        assert [stamp for stamp, _ in seen_by_service.on(topics.SCAN_FILTERED.name)] == [300_000_000]
        assert seen_by_monitor.on(topics.SCAN_FILTERED.name) == seen_by_service.on(topics.SCAN_FILTERED.name)
        # (The monitor's own scans reach its own subscriber inside its session, not through the router.)
        assert [stamp for stamp, _ in seen_by_monitor.on(topics.SCAN.name)] == [100_000_000, 200_000_000, 300_000_000]

        # Status queries reach denoise and never the monitor's queryable; its token is not seen.
        replies = [r for key in (topics.status(ROBOT, "denoise"), topics.status(ROBOT, "slam"))
                   for r in svc.get(key, timeout=2.0)]
        assert [str(r.ok.key_expr) for r in replies if r.ok is not None] == [topics.status(ROBOT, "denoise")]
        assert monitor_queries == []
        alive = [str(r.ok.key_expr) for r in svc.liveliness().get(topics.alive(ROBOT, topics.ANY), timeout=2.0)]
        assert alive == [topics.alive(ROBOT, "denoise")]

        # A queryable held by a service certificate is asked (so the check above could fail), by
        # another monitor too; the first monitor's still is not (a session's own queries would
        # reach it inside the session, hence the second one).
        svc_queries: list[str] = []
        svc_q = svc.declare_queryable(topics.status(ROBOT, "slam"), lambda q: svc_queries.append(str(q.key_expr)))
        with open_session(paths["monitor"], endpoint) as other_monitor:
            list(other_monitor.get(topics.status(ROBOT, "slam"), timeout=2.0))
        assert svc_queries == [topics.status(ROBOT, "slam")] and monitor_queries == []
        for entity in (svc_q, mon_q):
            entity.undeclare()
        svc_bus.close()
        mon_bus.close()


def test_a_late_monitor_catches_up_through_the_acl(pipeline):
    """What `lrfslam monitor` asks as it starts (the compose monitor with the monitor certificate):
    every service's status and the newest of the outputs kept for late joiners (``topics.latest``),
    answered by service-certificate queryables. Both are queries the list lets a monitor make."""
    paths, endpoint = pipeline
    state = t.SlamState(stamp_ns=900_000_000, seq=9, scan_seq=9, pose=np.array([1.0, 2.0, 0.5]),
                        pose_cov=np.eye(3) * 0.01)
    payload = codec.SLAM_STATE.encode(state)
    key = topics.latest(ROBOT, topics.SLAM_STATE.name)
    asked: list[str] = []

    def answer(query: zenoh.Query) -> None:
        asked.append(str(query.key_expr))
        query.reply(key, payload, attachment=attachment(9, state.stamp_ns, b"\0" * 16),
                    encoding=zenoh.Encoding(codec.SLAM_STATE.encoding))

    with open_session(paths["service"], endpoint) as svc:
        queryable = svc.declare_queryable(key, answer)
        feed, stop = Names(), threading.Event()
        monitor = Monitor(BusConfig(robot=ROBOT, mode="client", connect=(endpoint,),
                                    zenoh_config=str(paths["monitor"])), [feed])
        feed_thread = threading.Thread(target=monitor.run, args=(stop,))
        feed_thread.start()
        try:
            wait_until(lambda: "slam/state" in feed.names, "the monitor never got the latest SLAM state")
        finally:
            stop.set()
            feed_thread.join(10)
        queryable.undeclare()
    # Nothing publishes slam/state here: it came by the query, as did denoise's status.
    assert asked == [topics.latest(ROBOT, "**")]
    assert feed.names.count("slam/state") == 1
    assert monitor.counts["catch_up"] == 2 and not monitor.counts["catch_up.undecodable"], monitor.counts


def delivered(sender: Path, receiver: Path, endpoint: str, key: str) -> bool:
    """Whether a put on ``key`` by a session holding ``sender``'s certificate reaches a subscriber
    holding ``receiver``'s, through the router (a second put after a pause, so a subscription
    still propagating cannot explain a miss)."""
    got = threading.Event()
    with open_session(receiver, endpoint) as rx, open_session(sender, endpoint) as tx:
        sub = rx.declare_subscriber(key, lambda _sample: got.set())
        time.sleep(0.5)
        for _ in range(2):
            tx.put(key, b"x")
            if got.wait(1.0):
                break
        sub.undeclare()
    return got.is_set()


#: rmw_zenoh's data key of /robot1/scan (sensor_msgs/msg/LaserScan) in domain 0, and a graph token.
ROS_SCAN = "0/robot1/scan/sensor_msgs::msg::dds_::LaserScan_/RIHS01_0123"
ROS_TOKEN = "@ros2_lv/0/aaaa/0/11/MP/%/%/robot1/%robot1%scan/sensor_msgs::msg::dds_::LaserScan_/RIHS01_0123/::,7:,:,:,,"


def test_ros2_roles_a_desk_reads_and_a_robot_feeds_the_ros2_keys_only(pipeline):
    paths, endpoint = pipeline
    service, desk, robot = paths["service"], paths["ros2-desk"], paths["ros2-robot"]
    lrf_scan = topics.key(ROBOT, topics.SCAN.name)
    # The bridge (service certificate) publishes ROS 2 topics a desk and a robot receive.
    assert delivered(service, desk, endpoint, ROS_SCAN)
    assert delivered(service, robot, endpoint, ROS_SCAN)
    # A ROS 2 robot's /scan reaches the bridge; a desk publishes nothing, on ROS 2 keys or ours.
    assert delivered(robot, service, endpoint, ROS_SCAN)
    assert not delivered(desk, service, endpoint, ROS_SCAN)
    assert not delivered(desk, service, endpoint, lrf_scan)
    # Neither ROS 2 role touches lrfslam's own keys, either way.
    assert delivered(service, service, endpoint, lrf_scan)   # (the control: the key does carry data)
    assert not delivered(robot, service, endpoint, lrf_scan)
    assert not delivered(service, desk, endpoint, lrf_scan)
    assert not delivered(service, robot, endpoint, lrf_scan)
    # The graph: a desk lists the bridge's token and is listed in turn, as ros2 topic list needs.
    with open_session(service, endpoint) as svc, open_session(desk, endpoint) as dsk:
        token = svc.liveliness().declare_token(ROS_TOKEN)
        desk_token = dsk.liveliness().declare_token(ROS_TOKEN.replace("/aaaa/", "/bbbb/"))
        time.sleep(0.5)
        seen_by_desk = {str(r.ok.key_expr) for r in dsk.liveliness().get("@ros2_lv/0/**", timeout=2.0) if r.ok}
        seen_by_service = {str(r.ok.key_expr) for r in svc.liveliness().get("@ros2_lv/0/**", timeout=2.0) if r.ok}
        assert ROS_TOKEN in seen_by_desk
        assert ROS_TOKEN.replace("/aaaa/", "/bbbb/") in seen_by_service
        # and sees no lrfslam service's token
        assert not [r for r in dsk.liveliness().get(topics.alive(ROBOT, topics.ANY), timeout=2.0) if r.ok]
        token.undeclare()
        desk_token.undeclare()


def test_a_robots_own_certificate_publishes_on_its_keys_only(acl, tmp_path):
    """``lrfslam certs --robot robot1`` and the lines it prints, added to the shipped list: that
    certificate publishes under lrf/robot1/** and nowhere else; the shared service one everywhere."""
    paths, endpoint = acl
    certs_dir = tmp_path / "tls"
    assert certs_main([str(certs_dir), "--if-absent", "--robot", ROBOT]) == 0
    router_text = paths["router"].read_text()
    for section, entries in robot_acl(ROBOT).items():
        head = f"\n    {section}: ["   # the access_control list itself, not a policy's
        assert router_text.count(head) == 1, section
        router_text = router_text.replace(head, head + "".join(json.dumps(e) + "," for e in entries))
    paths["router"].write_text(router_text)
    own = tmp_path / "service-robot1.json5"
    own.write_text(paths["service"].read_text().replace(f"{certs_dir}/service", f"{certs_dir}/service-{ROBOT}"))
    router = subprocess.Popen([sys.executable, "-m", "lrfslam.cli", "router", "--zenoh-config", str(paths["router"]),
                               "--log-level", "WARNING", "--listen", endpoint])
    try:
        wait_until(lambda: status(["--zenoh-config", str(paths["service"]), "-e", endpoint, "--check"]) == 0,
                   "the router with the robot's lines never answered", 30)
        other = topics.key("robot2", topics.SCAN.name)
        assert delivered(own, paths["service"], endpoint, topics.key(ROBOT, topics.SCAN.name))
        assert delivered(paths["service"], own, endpoint, topics.key(ROBOT, topics.SCAN.name))
        assert not delivered(own, paths["service"], endpoint, other)
        assert delivered(paths["service"], paths["service"], endpoint, other)   # the control
        assert not delivered(own, paths["service"], endpoint, ROS_SCAN)
    finally:
        router.terminate()
        router.wait(10)
