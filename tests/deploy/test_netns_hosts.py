"""Several hosts without containers: Linux network namespaces as machines on one Ethernet segment.

Four namespaces stand for four computers, wired by veth pairs to a bridge on the router's:

=========  ===========  ========================================================
host       address      runs
=========  ===========  ========================================================
``rt``     SUBNET.1     ``lrfslam router --listen tcp/0.0.0.0:PORT --insecure`` (and the bridge)
``b``      SUBNET.2     robot r1's sensor and denoise; later r1's moved slam
``c``      SUBNET.3     robot r1's features, slam and recorder
``d``      SUBNET.4     robot r2, all five services (another robot on the same router)
(test)     SUBNET.254   the monitor: this process, through a veth into the bridge
=========  ===========  ========================================================

Every service is a client of ``tcp/SUBNET.1:PORT``, started with ``ip netns exec``. Each host
has its own working directory, as machines have their own disks; r1's slam keeps its
checkpoint in a folder both its hosts use (the shared storage deploy/README.md recommends).
While the pipeline runs, r1's slam is killed with SIGKILL on host c and, once its liveliness
token has gone, started on host b: r1's recording must show SLAM output continuing with the
restored filter, its recorder count one restart of ``slam/state`` and nothing else, and both
robots' recordings hold only their own robot's data, each slam's trajectory and landmarks
matching its own sensor's truth. Needs root (``ip netns``); skips without it, fails under CI.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import zenoh
from lrfslam.services.sensor import SensorConfig, SimSource

from lrfslam.msgs import codec, topics
from lrfslam.msgs.landmark_map import LandmarkMapReplica
from lrfslam.runtime.recording import read_recording
from lrfslam.sim import floor_plans
from lrfslam.tools.status import client_config, query_status

pytestmark = pytest.mark.slow

PORT = 7447
SPEEDUP = 3.0            # 30 scans per wall second
SCANS = 1200             # 40 s of wall time; the sensors stop after this frame
KILL_AFTER_STATES = 300  # r1's slam is killed once it has published this many states
WORLDS = {"r1": ("hallway_loop", 1), "r2": ("large_building_empty", 3)}   # robot -> (world, seed)
TIMEOUT_S = 120.0        # hang guard of every wait; nothing asserts on elapsed time
CHECKPOINT_EVERY = 50    # scans: bus.checkpoint_period_s (5 s of data time) at the simulator's 10 Hz


def unavailable(reason: str) -> None:
    """Skip on a developer's machine; under CI (``CI`` set, as .ci/run does) it fails."""
    if os.environ.get("CI"):
        pytest.fail(f"{reason}; CI must run this test")
    pytest.skip(reason)


def sh(*argv: str) -> None:
    proc = subprocess.run(argv, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise AssertionError(f"{' '.join(argv)} exited {proc.returncode}: {proc.stderr.strip()}")


class Hosts:
    """The namespaces, their links and the processes started in them; :meth:`close` removes all."""

    def __init__(self, tmp: Path) -> None:
        tag = os.getpid() % 100000
        self.tag = tag
        self.subnet = f"10.213.{tag % 250}"
        self.ns = {h: f"lrf{tag}{h}" for h in ("rt", "b", "c", "d")}
        self.monitor_if = f"lrf{tag}mon"
        self.tmp = tmp
        self.procs: list[tuple[str, subprocess.Popen]] = []
        self.logs: dict[str, Path] = {}
        self.router = f"tcp/{self.subnet}.1:{PORT}"
        self.made: list[str] = []

    def build(self) -> None:
        rt = self.ns["rt"]
        for ns in self.ns.values():
            sh("ip", "netns", "add", ns)
            self.made.append(ns)
            sh("ip", "-n", ns, "link", "set", "lo", "up")
        sh("ip", "-n", rt, "link", "add", "br0", "type", "bridge")
        sh("ip", "-n", rt, "addr", "add", f"{self.subnet}.1/24", "dev", "br0")
        sh("ip", "-n", rt, "link", "set", "br0", "up")
        for i, host in enumerate(("b", "c", "d"), start=2):
            # One cable per host: eth0 on the host, its other end a port of the bridge.
            sh("ip", "link", "add", "eth0", "netns", self.ns[host], "type", "veth", "peer", "name", f"p{host}",
               "netns", rt)
            sh("ip", "-n", self.ns[host], "addr", "add", f"{self.subnet}.{i}/24", "dev", "eth0")
            sh("ip", "-n", self.ns[host], "link", "set", "eth0", "up")
            sh("ip", "-n", rt, "link", "set", f"p{host}", "master", "br0", "up")
        # The monitoring host is this process: its cable ends in the root namespace.
        sh("ip", "link", "add", self.monitor_if, "type", "veth", "peer", "name", "pmon", "netns", rt)
        sh("ip", "-n", rt, "link", "set", "pmon", "master", "br0", "up")
        sh("ip", "addr", "add", f"{self.subnet}.254/24", "dev", self.monitor_if)
        sh("ip", "link", "set", self.monitor_if, "up")

    def workdir(self, host: str) -> Path:
        path = self.tmp / f"host-{host}"
        path.mkdir(exist_ok=True)
        return path

    def run(self, host: str, label: str, *args: str) -> subprocess.Popen:
        """``lrfslam ARGS`` on ``host`` (``ip netns exec`` execs it: the pid is the service's own)."""
        log = self.tmp / f"{label}.log"
        self.logs[label] = log
        with open(log, "ab") as out:
            proc = subprocess.Popen(["ip", "netns", "exec", self.ns[host], sys.executable, "-m", "lrfslam.cli", *args,
                                     "--log-level", "WARNING"], cwd=self.workdir(host), stdout=out, stderr=out)
        self.procs.append((label, proc))
        return proc

    def service(self, host: str, robot: str, name: str, *flags: str) -> subprocess.Popen:
        argv = [name, "--robot", robot, "--mode", "client", "--connect", self.router, *flags]
        return self.run(host, f"{robot}-{name}-{host}", *argv)

    def tail(self) -> str:
        return "\n".join(f"--- {label}\n{path.read_text(errors='replace')[-1500:]}" for label, path in self.logs.items())

    def close(self) -> None:
        for _, proc in self.procs:
            if proc.poll() is None:
                proc.kill()
            proc.wait()
        # Deleting a namespace deletes its interfaces, and with them their veth peers.
        for ns in self.made:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, check=False)
        subprocess.run(["ip", "link", "del", self.monitor_if], capture_output=True, check=False)


@pytest.fixture
def hosts(tmp_path):
    if shutil.which("ip") is None:
        unavailable("the ip command is missing (Debian package iproute2)")
    if os.geteuid() != 0:
        unavailable("network namespaces need root")
    h = Hosts(tmp_path)
    try:
        h.build()
    except AssertionError as exc:
        h.close()
        unavailable(f"cannot build network namespaces here: {exc}")
    yield h
    h.close()


def wait(session: zenoh.Session, robot: str, predicate, what: str, hosts: Hosts):
    """Poll ``robot``'s liveliness and statuses until ``predicate(alive services, statuses)`` is truthy."""
    deadline = time.monotonic() + TIMEOUT_S
    while time.monotonic() < deadline:
        alive, statuses = query_status(session, robot, 1.0)
        result = predicate({s for _, s in alive}, {s.service: s for s in statuses})
        if result:
            return result
        time.sleep(0.3)
    pytest.fail(f"timed out waiting for {what}\n{hosts.tail()}")


def true_pose_by_stamp(recording: Path) -> dict[int, np.ndarray]:
    return {(gt := codec.GROUND_TRUTH.decode(m.data)).stamp_ns: gt.pose
            for m in read_recording(recording, [topics.TRUTH.name])}


def to_world(anchor_est: np.ndarray, anchor_true: np.ndarray):
    """The rigid map from the filter's frame to the world's that takes ``anchor_est`` onto ``anchor_true``."""
    dth = anchor_true[2] - anchor_est[2]
    rot = np.array([[np.cos(dth), -np.sin(dth)], [np.sin(dth), np.cos(dth)]])

    def apply(xy: np.ndarray) -> np.ndarray:
        return (np.asarray(xy) - anchor_est[:2]) @ rot.T + anchor_true[:2]
    return apply


def accuracy(recording: Path, world_name: str) -> tuple[float, float, float, int]:
    """Trajectory RMSE and final error (m) against the recording's truth, both anchored at the
    filter's first state; the fraction of confirmed landmarks within 0.3 m of a true corner or
    wall end of ``world_name``, and how many were confirmed."""
    truth = true_pose_by_stamp(recording)
    states, replica = [], LandmarkMapReplica()
    for m in read_recording(recording, [topics.SLAM_STATE.name, topics.SLAM_MAP.name]):
        value = topics.by_name(m.topic).codec.decode(m.data, m.schema)
        replica.apply_message(value)
        if m.topic == topics.SLAM_STATE.name:
            states.append(value)
    first = states[0]
    world = to_world(first.pose, truth[first.stamp_ns])
    errors = [np.hypot(*(world(s.pose[:2]) - truth[s.stamp_ns][:2])) for s in states]
    last = states[-1]
    lms = replica.landmarks
    assert replica.complete and len(lms) == last.n_landmarks
    landmarks = world(lms.xy_m[lms.confirmed])
    # Corners, and wall ends (jump edges: the slam's backward features).
    world_map = floor_plans.build_world(world_name)
    corners = np.vstack([world_map.corners().xy_m, world_map.free_endpoints()])
    near = np.min(np.linalg.norm(landmarks[:, None, :] - corners[None, :, :], axis=2), axis=1) < 0.3
    return float(np.sqrt(np.mean(np.square(errors)))), float(errors[-1]), float(near.mean()), len(landmarks)


def test_pipeline_across_hosts_with_a_moved_slam_and_a_second_robot(hosts):
    h = hosts
    shared = h.tmp / "shared"        # storage both of r1's slam hosts mount (NFS, say)
    shared.mkdir()
    h.run("rt", "router", "router", "--listen", f"tcp/0.0.0.0:{PORT}", "--insecure")

    def sensor_sets(robot: str) -> list[str]:
        world, seed = WORLDS[robot]
        return [a for s in (f"world={world}", f"seed={seed}", f"speedup={SPEEDUP}", f"max_scans={SCANS}")
                for a in ("--set", s)]

    checkpoint = ["--checkpoint-dir", str(shared)]
    # Consumers first, the sensors last (as `lrfslam up` and compose order them).
    procs = {
        "r1-recorder": h.service("c", "r1", "recorder"),
        "r2-recorder": h.service("d", "r2", "recorder"),
        "r1-slam": h.service("c", "r1", "slam", *checkpoint),
        "r2-slam": h.service("d", "r2", "slam"),
        "r1-features": h.service("c", "r1", "features"),
        "r2-features": h.service("d", "r2", "features"),
        "r1-denoise": h.service("b", "r1", "denoise"),
        "r2-denoise": h.service("d", "r2", "denoise"),
    }
    stages = {"recorder", "slam", "features", "denoise"}
    deadline = time.monotonic() + TIMEOUT_S
    while True:
        try:
            session = zenoh.open(client_config([h.router]))
            break
        except zenoh.ZError:
            assert time.monotonic() < deadline, f"the router never answered\n{h.tail()}"
            time.sleep(0.5)
    with session:
        for robot in ("r1", "r2"):
            wait(session, robot, lambda alive, _: stages <= alive, f"{robot}'s stages", h)
        procs["r1-sensor"] = h.service("b", "r1", "sensor", *sensor_sets("r1"))
        procs["r2-sensor"] = h.service("d", "r2", "sensor", *sensor_sets("r2"))

        st = wait(session, "r1", lambda _, st: "slam" in st and "sensor" in st
                  and st["slam"].counters.get("out.slam/state", 0) >= KILL_AFTER_STATES and st, "r1's slam states", h)
        killed_at = st["sensor"].last_data_stamp_ns
        old_pid = st["slam"].pid
        procs["r1-slam"].send_signal(signal.SIGKILL)
        procs["r1-slam"].wait()
        # The move: its token must be gone before the new one may start (runtime/runner.py,
        # wait_until_free); a killed process's socket closes with it, so the router drops it at once.
        wait(session, "r1", lambda alive, _: "slam" not in alive, "the killed slam's token to go", h)
        gone_at = time.monotonic()
        procs["r1-slam-b"] = h.service("b", "r1", "slam", *checkpoint)
        wait(session, "r1", lambda alive, _: "slam" in alive, "the moved slam", h)
        move_s = time.monotonic() - gone_at

        for robot in ("r1", "r2"):
            # Done when the sensor has sent its last frame and the slam has handled it.
            wait(session, robot, lambda _, st: "sensor" in st and "slam" in st
                 and st["sensor"].counters.get("out.scan", 0) >= SCANS
                 and st["slam"].last_data_stamp_ns == st["sensor"].last_data_stamp_ns, f"{robot}'s last scan", h)
    for name in ("sensor", "denoise", "features", "slam-b", "slam", "recorder"):
        for robot in ("r1", "r2"):
            proc = procs.get(f"{robot}-{name}")
            if proc is not None and proc.poll() is None:
                proc.terminate()
                assert proc.wait(30) == 0, f"{robot}-{name} did not stop cleanly\n{h.tail()}"

    (rec1,) = (h.workdir("c") / "recordings").glob("*_r1")
    (rec2,) = (h.workdir("d") / "recordings").glob("*_r2")

    # -- the move: SLAM output continues, from the restored filter, in another process
    states = [codec.SLAM_STATE.decode(m.data) for m in read_recording(rec1, [topics.SLAM_STATE.name])]
    stamps = [s.stamp_ns for s in states]
    assert stamps == sorted(set(stamps))
    after = [s for s in states if s.stamp_ns > killed_at]
    assert len(after) > SCANS - KILL_AFTER_STATES - 200, len(after)
    seqs = [s.seq for s in states]
    # The restart is where the scans jump: the frames sent while no slam ran (seconds of them).
    # The state's own count cannot mark it: a kill just after a checkpoint resumes it seamlessly.
    scan_seqs = np.array([s.scan_seq for s in states])
    restart = int(np.argmax(np.diff(scan_seqs))) + 1
    assert scan_seqs[restart] - scan_seqs[restart - 1] > 5, scan_seqs[restart - 2:restart + 2]
    assert all(seqs[i] == seqs[i - 1] + 1 for i in range(1, len(seqs)) if i != restart), seqs
    # Resumed from the checkpoint (at most CHECKPOINT_EVERY scans old), not from 1.
    assert seqs[restart - 1] - CHECKPOINT_EVERY <= seqs[restart] <= seqs[restart - 1] + 1, seqs[restart - 2:restart + 2]
    slam_health = [codec.SERVICE_STATUS.decode(m.data) for m in read_recording(rec1, ["health/slam"])]
    pids = list(dict.fromkeys(s.pid for s in slam_health))
    assert len(pids) == 2 and pids[0] == old_pid, pids
    assert slam_health[-1].counters.get("step.restored") == 1
    rec_health = [codec.SERVICE_STATUS.decode(m.data) for m in read_recording(rec1, ["health/recorder"])]
    restarts = {k: v for k, v in rec_health[-1].counters.items() if k.startswith("restart.")}
    # The slam process published all its outputs anew: the state, the whole map and its health.
    assert restarts == {"restart.slam/state": 1, "restart.slam/map": 1, "restart.health/slam": 1}, restarts

    # -- no crosstalk: each recording holds its own robot's streams, each once, and nothing else
    for robot, rec in (("r1", rec1), ("r2", rec2)):
        world, seed = WORLDS[robot]
        sim = SimSource(SensorConfig(world=world, seed=seed, speedup=0))
        odom = [next(sim.frames).odom_pose for _ in range(SCANS)]
        recorded = [(m.sequence, codec.ODOMETRY.decode(m.data).pose) for m in read_recording(rec, [topics.ODOM.name])]
        assert [q for q, _ in recorded] == list(range(1, SCANS + 1))
        for q, pose in recorded:
            np.testing.assert_array_equal(pose, odom[q - 1])
        assert {codec.GROUND_TRUTH.decode(m.data).world for m in read_recording(rec, [topics.TRUTH.name])} == {world}
        services = {m.topic.removeprefix("health/") for m in read_recording(rec) if m.topic.startswith("health/")}
        assert services == {"sensor", "denoise", "features", "slam", "recorder"}, services
        for m in read_recording(rec, ["health/sensor", "health/slam"]):
            assert codec.SERVICE_STATUS.decode(m.data).robot == robot
        if robot == "r2":
            counters = [codec.SERVICE_STATUS.decode(m.data) for m in read_recording(rec, ["health/recorder"])][-1]
            assert not [k for k in counters.counters if k.startswith(("restart.", "dup.", "gap."))], counters.counters

    figures = {}
    for robot, rec in (("r1", rec1), ("r2", rec2)):
        rmse, final, near, confirmed = accuracy(rec, WORLDS[robot][0])
        figures[robot] = (rmse, final, near, confirmed)
        # Each map is of its own robot's world (the two worlds differ), its trajectory its own truth's.
        assert confirmed >= 10 and near >= 0.9, (robot, near, confirmed)
        assert rmse < 0.25 and final < 0.25, (robot, rmse, final)
        # The landmark check tells the worlds apart: the other robot's world does not fit.
        other = WORLDS["r2" if robot == "r1" else "r1"][0]
        assert accuracy(rec, other)[2] < 0.5, (robot, other)
    print(f"\nslam moved c -> b: token gone to new slam alive {move_s:.2f} s; {len(after)} states after the kill")
    for robot, (rmse, final, near, confirmed) in figures.items():
        print(f"{robot}: RMSE {rmse * 100:.1f} cm, final {final * 100:.1f} cm, "
              f"{confirmed} confirmed landmarks, {near:.0%} within 0.3 m of a true corner")


def test_a_monitor_on_another_host_serves_the_live_pipeline(hosts):
    """The robot (router on rt, pipeline on c) watched from host b: ``lrfslam monitor`` there
    connects to the robot's router across the bridge, and its dashboard, read from a third
    host (this process), shows the pipeline live: every service alive, scans and SLAM states
    rising, the pose and landmarks on the map."""
    h = hosts
    h.run("rt", "router", "router", "--listen", f"tcp/0.0.0.0:{PORT}", "--insecure")
    for name in ("recorder", "slam", "features", "denoise"):
        h.service("c", "r1", name)
    http_port = 8080
    # --insecure: the namespaces' bridge is a closed network (tests/services/test_monitor_token.py
    # covers the token a monitor beyond loopback otherwise asks for).
    h.run("b", "monitor", "monitor", "--connect", h.router, "--robot", "r1", "--dashboard",
          "--host", "0.0.0.0", "--http-port", str(http_port), "--port", "8765", "--insecure")
    url = f"http://{h.subnet}.2:{http_port}/state.json"

    def snapshot() -> dict | None:
        try:
            with urllib.request.urlopen(url, timeout=5) as reply:
                return json.loads(reply.read())
        except OSError:
            return None

    def wait_for(predicate, what: str) -> dict:
        deadline = time.monotonic() + TIMEOUT_S
        while time.monotonic() < deadline:
            snap = snapshot()
            if snap is not None and predicate(snap):
                return snap
            time.sleep(0.5)
        pytest.fail(f"timed out waiting for {what}: {snapshot()}\n{h.tail()}")

    stages = {"recorder", "slam", "features", "denoise"}
    wait_for(lambda s: stages <= {r["service"] for r in s["services"] if r["alive"]}, "the stages on the dashboard")
    h.service("b", "r1", "sensor", "--set", f"speedup={SPEEDUP}", "--set", f"max_scans={SCANS}")
    first = wait_for(lambda s: s["scans"] >= 30 and s["pose"] is not None, "live scans")
    later = wait_for(lambda s: s["states"] >= first["states"] + 60 and len(s["landmarks"]) > 0, "more states")
    rows = {r["service"]: r for r in later["services"]}
    assert set(rows) == stages | {"sensor"} and all(r["alive"] for r in rows.values()), rows
    assert later["scans"] > first["scans"] and len(later["trajectory"]) >= 2
