"""deploy/compose.yaml brought up for real with podman + podman-compose.

Builds the image (deploy/podman-build.sh), starts the router, the six services and the
monitor as containers, asks the published router port from the host which services are alive
(as a remote monitor would), runs every container's healthcheck, reads the monitor's published
Foxglove WebSocket and dashboard from the host (bound to loopback, showing the live pipeline),
stops the sensor first and then the rest, and reads the recording back; once as shipped (the
certs service makes the certificates on the first start, every link is mutual TLS under the
router's access-control list, the host asks with the monitor certificate, which the monitor
container holds too, and intruders are refused: no certificate, another CA, a monitor
certificate that publishes), once with compose.group.yaml over it (denoise, features and slam in
one container, one process: still six services on the bus), and once with compose.insecure.yaml
over it. Needs podman,
podman-compose and a base image (deploy/setup-podman.sh prepares a Debian machine); skips
when podman is missing.
"""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import socket
import struct
import subprocess
import time
import urllib.request
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import websockets
import zenoh

from lrfslam import services
from lrfslam.msgs import codec, topics
from lrfslam.msgs.types import LaserScan
from lrfslam.runtime.bus import attachment
from lrfslam.runtime.recording import ReadReport, read_recording
from lrfslam.tools.certs import main as certs_main
from lrfslam.tools.status import check, client_config, query_status
from lrfslam.tools.status import main as status
from lrfslam.viz import foxglove as fx

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
COMPOSE = ROOT / "deploy" / "compose.yaml"
COMPOSE_INSECURE = ROOT / "deploy" / "compose.insecure.yaml"
COMPOSE_GROUP = ROOT / "deploy" / "compose.group.yaml"
RUN_S = 40.0            # wall time with all five up; at speedup 1 that is ~400 scans at 10 Hz
STARTUP_TIMEOUT_S = 90.0
CONTAINERS = ("zenohd", "monitor", *services.NAMES)
GROUPED = ("denoise", "features", "slam")   # compose.group.yaml's `stages` container
HEALTHCHECK_RETRIES = 3  # deploy/compose.yaml, x-healthcheck
ROBOT = "robot1"         # deploy/config.toml's [bus] robot
INTRUDER_STAMP_NS = 1    # no sensor stamps a scan 1 ns after 1970


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def podman_compose() -> list[str] | None:
    exe = shutil.which("podman-compose")
    return [exe] if exe else None


def unavailable(reason: str) -> None:
    """Skip on a developer's machine; under CI (``CI`` set, as .ci/run does) a missing engine fails."""
    if os.environ.get("CI"):
        pytest.fail(f"{reason}; CI must run this test")
    pytest.skip(reason)


@pytest.fixture(scope="module")
def engine():
    if shutil.which("podman") is None:
        unavailable("podman is not installed (Debian: sudo deploy/setup-podman.sh)")
    compose = podman_compose()
    if compose is None:
        unavailable("podman-compose is not installed (sudo deploy/setup-podman.sh, or pip install podman-compose)")
    return compose


def run(argv: list[str], timeout: float, env: dict | None = None, check: bool = True) -> subprocess.CompletedProcess:
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=timeout, env=env, check=False)
    if check and proc.returncode != 0:
        raise AssertionError(f"{' '.join(argv)} exited {proc.returncode}\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return proc


class Deployment:
    """One compose project with its own name, router port and recordings folder."""

    def __init__(self, compose: list[str], tmp: Path, variant: str) -> None:
        """As shipped (TLS; its certs service makes the certificates in ``tmp``/tls), or with
        compose.group.yaml or compose.insecure.yaml over it (``variant``: shipped, group, insecure)."""
        self.project = f"lrfslam-test-{os.getpid()}"
        self.port = free_port()
        self.foxglove_port, self.dashboard_port = free_port(), free_port()
        self.recordings = tmp / "recordings"
        self.recordings.mkdir()
        # LRFSLAM_MONITOR_ADDRESS stays unset: the test sees the loopback binding users get.
        self.env = dict(os.environ, LRFSLAM_IMAGE="lrfslam:test", LRFSLAM_ROUTER_PORT=str(self.port),
                        LRFSLAM_RECORDINGS=str(self.recordings), LRFSLAM_FOXGLOVE_PORT=str(self.foxglove_port),
                        LRFSLAM_DASHBOARD_PORT=str(self.dashboard_port))
        self.env.pop("LRFSLAM_MONITOR_ADDRESS", None)
        self.compose = [*compose, "-p", self.project, "-f", str(COMPOSE)]
        self.certs = tmp / "tls"   # made by the certs service, not by the test
        self.env.update(LRFSLAM_TLS=str(self.certs), LRFSLAM_TLS_HOSTS="robot.test")
        self.monitor_config = tmp / "monitor-tls.json5"
        self.monitor_config.write_text((ROOT / "deploy" / "zenoh" / "monitor-tls.json5").read_text()
                                       .replace('"tls/', f'"{self.certs}/'))
        self.containers = CONTAINERS
        if variant == "group":
            self.compose += ["-f", str(COMPOSE_GROUP)]
            self.containers = (*(c for c in CONTAINERS if c not in GROUPED), "stages")
        if variant == "insecure":
            self.compose += ["-f", str(COMPOSE_INSECURE)]
            self.endpoint, self.zenoh_config = f"tcp/127.0.0.1:{self.port}", None
        else:
            self.endpoint, self.zenoh_config = f"tls/127.0.0.1:{self.port}", str(self.monitor_config)

    def __call__(self, *args: str, timeout: float = 120, check: bool = True) -> subprocess.CompletedProcess:
        return run([*self.compose, *args], timeout, self.env, check)

    def container(self, service: str) -> str:
        return f"{self.project}_{service}_1"

    def inspect(self, service: str, fmt: str) -> str:
        return run(["podman", "inspect", "--format", fmt, self.container(service)], 30).stdout.strip()

    def health_log(self, service: str) -> str:
        """What the container's last healthchecks printed (``podman healthcheck run`` only says
        'unhealthy')."""
        proc = run(["podman", "inspect", "--format", "{{json .State.Health.Log}}", self.container(service)], 30,
                   check=False)
        return f"--- {service} healthcheck output\n{proc.stdout}{proc.stderr}"

    def logs(self) -> str:
        out = []
        for service in ("certs", *self.containers):
            proc = run(["podman", "logs", "--timestamps", "--tail", "40", self.container(service)], 30,
                       check=False)
            out.append(f"--- {service}\n{proc.stdout}{proc.stderr}")
        return "\n".join(out)


def ask(dep: Deployment) -> tuple[set, list]:
    with zenoh.open(client_config([dep.endpoint], dep.zenoh_config)) as session:
        return query_status(session, "*", 3.0)


def http_get(url: str) -> tuple[str, bytes]:
    with urllib.request.urlopen(url, timeout=10) as reply:
        return reply.headers["Content-Type"], reply.read()


async def foxglove_scans(port: int, enough: int, timeout_s: float) -> tuple[str, set[str], int]:
    """As Foxglove connects: (subprotocol, the advertised topics, scan messages received after
    subscribing to the scan view)."""
    async with asyncio.timeout(timeout_s):
        async with websockets.connect(f"ws://127.0.0.1:{port}",
                                      subprotocols=["foxglove.websocket.v1", "foxglove.sdk.v1"]) as ws:
            topics, scans = {}, 0
            while scans < enough:
                frame = await ws.recv()
                if isinstance(frame, str):
                    op = json.loads(frame)
                    if op["op"] == "advertise":
                        new = {c["id"]: c["topic"] for c in op["channels"]}
                        topics.update(new)
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                            {"id": cid, "channelId": cid} for cid, topic in new.items() if topic == fx.SCAN]}))
                elif frame[0] == 0x01:   # message data: subscription id (= channel id here), log time, payload
                    (sub,) = struct.unpack_from("<I", frame, 1)
                    scans += topics[sub] == fx.SCAN
            return ws.subprotocol, set(topics.values()), scans


def check_monitor(dep: Deployment) -> dict:
    """The monitor container from the host: both ports bound to loopback only, Foxglove's scans
    streaming, and the dashboard showing the whole pipeline alive and its map growing."""
    for container_port, host_port in ((8765, dep.foxglove_port), (8080, dep.dashboard_port)):
        bound = run(["podman", "port", dep.container("monitor"), f"{container_port}/tcp"], 30).stdout.split()
        assert bound == [f"127.0.0.1:{host_port}"], bound
    subprotocol, advertised, scans = asyncio.run(foxglove_scans(dep.foxglove_port, enough=10, timeout_s=30))
    assert subprotocol == "foxglove.sdk.v1"
    assert advertised == set(fx.CHANNELS), advertised
    assert scans >= 10
    url = f"http://127.0.0.1:{dep.dashboard_port}"
    content_type, page = http_get(f"{url}/")
    assert content_type.startswith("text/html") and b"<canvas" in page
    first = json.loads(http_get(f"{url}/state.json")[1])
    alive = {row["service"] for row in first["services"] if row["alive"]}
    assert alive == set(services.NAMES), first["services"]
    assert first["scans"] > 100 and first["states"] > 100 and first["landmarks"], \
        {k: first[k] for k in ("scans", "states")}
    time.sleep(2)
    later = json.loads(http_get(f"{url}/state.json")[1])
    assert later["scans"] > first["scans"] and later["states"] > first["states"], "the dashboard is not live"
    return later


def intrude(dep: Deployment, tmp: Path) -> None:
    """What the router must refuse or drop on the published port: a client with no certificate or
    plain TCP, one with a certificate of another CA (all refused), and one with the monitor's
    certificate that publishes scans on the robot's keys and on a key of its own (let in, its
    messages dropped). Oracle: the recording after the run (the test's end)."""
    no_cert = tmp / "no-cert.json5"
    no_cert.write_text(json.dumps({"transport": {"link": {"tls": {"root_ca_certificate": f"{dep.certs}/ca.pem"}}}}))
    rogue = tmp / "rogue"
    assert certs_main([str(rogue), "--host", "127.0.0.1"]) == 0
    rogue_config = tmp / "rogue.json5"
    rogue_config.write_text(dep.monitor_config.read_text().replace(f"{dep.certs}/monitor", f"{rogue}/monitor"))
    assert status(["-e", f"tcp/127.0.0.1:{dep.port}", "--check"]) == 2
    assert status(["--zenoh-config", str(no_cert), "-e", dep.endpoint, "--check"]) == 2
    assert status(["--zenoh-config", str(rogue_config), "-e", dep.endpoint, "--check"]) == 2
    with zenoh.open(client_config([dep.endpoint], dep.zenoh_config)) as session:
        scan = codec.LASER_SCAN.encode(LaserScan.from_ranges(stamp_ns=INTRUDER_STAMP_NS, seq=1, ranges_m=np.full(181, 1.0),
                                                           angle_min_rad=-np.pi / 2, angle_increment_rad=np.pi / 180))
        for _ in range(20):
            session.put(topics.key(ROBOT, topics.SCAN.name), scan, attachment=attachment(1, INTRUDER_STAMP_NS, b"\1" * 16))
            session.put(topics.key(ROBOT, "intruder"), b"x")
            time.sleep(0.05)


def check_nothing_intruded(messages: list) -> None:
    """The recording holds what the pipeline published and nothing else: no intruder topic, no scan
    stamped as the intruder's, and exactly the scans the sensor counted in its last health."""
    assert "intruder" not in {m.topic for m in messages}
    scans = [m for m in messages if m.topic == "scan"]
    assert INTRUDER_STAMP_NS not in {m.stamp_ns for m in scans}
    last_sensor = codec.SERVICE_STATUS.decode(next(m.data for m in reversed(messages) if m.topic == "health/sensor"))
    assert last_sensor.counters["out.scan"] == len(scans)


@pytest.mark.parametrize("variant", ["shipped", "group", "insecure"],
                         ids=["as-shipped-tls-acl", "group-override", "insecure-override"])
def test_compose_up_status_down_recording(engine, tmp_path, variant):
    t0 = time.monotonic()
    # The build is part of the test: the Dockerfile must install the repo on the base image.
    run([str(ROOT / "deploy" / "podman-build.sh")], 1200, dict(os.environ, LRFSLAM_IMAGE="lrfslam:test"))
    build_s = time.monotonic() - t0

    dep = Deployment(engine, tmp_path, variant)
    try:
        dep("up", "-d", "--no-build", timeout=180)
        # The certs service made every certificate before the router started, and said where.
        assert {p.name for p in dep.certs.iterdir()} >= {"ca.pem", "router.pem", "service.pem", "monitor.pem"}
        assert dep.inspect("certs", "{{.State.ExitCode}}") == "0"
        said = run(["podman", "logs", dep.container("certs")], 30).stdout.splitlines()
        # (podman-compose 1.6 may start it a second time, which keeps every file: "kept" last.)
        assert [ln for ln in said if ln.startswith("certificates made now in ") and "monitor.pem" in ln], said
        assert said[-1].startswith("certificates "), said

        # From the host through the published port, like `lrfslam status -e tcp/<robot>:7447`.
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        problems = ["not asked yet"]
        while time.monotonic() < deadline:
            try:
                alive, statuses = ask(dep)
                problems = check(alive, statuses, list(services.NAMES))
            except zenoh.ZError as exc:
                problems = [f"router unreachable: {exc}"]
            if not problems:
                break
            time.sleep(2)
        assert not problems, f"{problems}\n{dep.logs()}"
        up_s = time.monotonic() - t0 - build_s

        # Every healthcheck command, run by the engine inside its container. Here podman has no
        # systemd to schedule them, so this is also the only place they run at all. The engine
        # calls a container unhealthy after `retries` failures in a row, so that is the test too.
        for service in dep.containers:
            failures = []
            for _ in range(HEALTHCHECK_RETRIES):
                t_check = time.monotonic()
                proc = run(["podman", "healthcheck", "run", dep.container(service)], 120, check=False)
                if proc.returncode == 0:
                    break
                failures.append(f"{time.monotonic() - t_check:.1f} s: {proc.stdout}{proc.stderr}".strip())
            assert len(failures) < HEALTHCHECK_RETRIES, \
                f"{service} healthcheck: {failures}\n{dep.health_log(service)}\n{dep.logs()}"

        if variant != "insecure":
            intrude(dep, tmp_path)
        time.sleep(RUN_S)
        alive, statuses = ask(dep)
        assert not check(alive, statuses, list(services.NAMES)), dep.logs()
        by_name = {s.service: s.counters for s in statuses}
        assert set(by_name) == set(services.NAMES), sorted(by_name)
        assert by_name["sensor"].get("out.scan", 0) > 100, by_name["sensor"]
        assert by_name["slam"].get("out.slam/state", 0) > 100, by_name["slam"]
        try:
            dashboard = check_monitor(dep)
        except (AssertionError, OSError, TimeoutError) as exc:
            raise AssertionError(f"monitor: {exc!r}\n{dep.logs()}") from exc
        for service in dep.containers:
            assert dep.inspect(service, "{{.RestartCount}}") == "0", f"{service} restarted\n{dep.logs()}"
        if variant == "group":   # the three stages answer from one process
            assert len({(s.pid, s.host) for s in statuses if s.service in GROUPED}) == 1, statuses

        # Docker's stop order, which podman-compose does not keep by itself (deploy/README.md):
        # the sensor first so the pipeline drains, then the stages and the monitor, the recorder,
        # the router. Exit code 0 means each process got SIGTERM through tini and stopped through
        # its own handler, not a SIGKILL (137).
        dep("stop", "sensor", timeout=60)
        time.sleep(3)
        dep("stop", *(c for c in dep.containers if c not in ("zenohd", "recorder", "sensor")), timeout=60)
        dep("stop", timeout=120)
        codes = {s: dep.inspect(s, "{{.State.ExitCode}}") for s in dep.containers}
        assert set(codes.values()) == {"0"}, f"{codes}\n{dep.logs()}"
    finally:
        dep("down", timeout=180, check=False)
    total_s = time.monotonic() - t0

    # One recorder start, one recording folder holding one segment.
    files = sorted(dep.recordings.glob("*/*.mcap"))
    assert len(files) == 1 and files[0].name.endswith("_0.mcap"), files
    report = ReadReport()
    messages = list(read_recording(files[0], report=report))
    assert not report.truncated, f"the recorder did not finish its file: {report.reason}"
    per_topic = Counter(m.topic for m in messages)
    for topic in ("scan", "odom", "scan/filtered", "features", "slam/state", "map/pose"):
        assert per_topic[topic] > 100, per_topic
    assert {f"health/{s}" for s in services.NAMES} <= set(per_topic), per_topic
    check_nothing_intruded(messages)
    last = codec.SLAM_STATE.decode(next(m.data for m in reversed(messages) if m.topic == "slam/state"))
    assert last.n_landmarks > 0 and per_topic["slam/map"] >= 2, "SLAM built no map"
    print(f"\nbuild {build_s:.0f} s, up to all alive {up_s:.0f} s, total {total_s:.0f} s; "
          f"dashboard: {dashboard['scans']} scans, {dashboard['states']} states, "
          f"{len(dashboard['landmarks'])} landmarks; {files[0].name}: {dict(per_topic)}")
