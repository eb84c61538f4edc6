"""Real processes on loopback Zenoh: a Python router and services started as OS processes."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh

from lrfslam.tools.status import client_config, query_status


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Cluster:
    """A router plus services, all separate processes, torn down at the end of the test."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.procs: dict[str, subprocess.Popen] = {}
        self.robot = "itest"

    def cmd(self, *args: str) -> list[str]:
        return [sys.executable, "-m", "lrfslam.cli", *args]

    def start_router(self) -> None:
        """Start the router and return once its port accepts connections: a client started
        before that (``lrfslam play``, which tries once) would find no router."""
        router = subprocess.Popen(self.cmd("router", "--listen", self.endpoint, "--log-level", "WARNING"))
        self.procs["router"] = router
        port = int(self.endpoint.rsplit(":", 1)[1])
        deadline = time.monotonic() + 30
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
                return
            except OSError:
                assert router.poll() is None, f"the router exited with {router.returncode}"
                assert time.monotonic() < deadline, f"the router never listened on {self.endpoint}"
                time.sleep(0.1)

    def start(self, name: str, *sets: str) -> subprocess.Popen:
        argv = self.cmd(name, "--robot", self.robot, "--mode", "client", "--connect", self.endpoint,
                        "--log-level", "WARNING")
        for s in sets:
            argv += ["--set", s]
        proc = subprocess.Popen(argv, cwd=self.tmp)
        self.procs[name] = proc
        return proc

    def start_group(self, stages) -> subprocess.Popen:
        """``stages`` in one process (``lrfslam group``), known as ``group``."""
        proc = subprocess.Popen(self.cmd("group", ",".join(stages), "--robot", self.robot, "--mode", "client",
                                         "--connect", self.endpoint, "--log-level", "WARNING"), cwd=self.tmp)
        self.procs["group"] = proc
        return proc

    def session(self) -> zenoh.Session:
        deadline = time.monotonic() + 15
        while True:
            try:
                return zenoh.open(client_config([self.endpoint]))
            except zenoh.ZError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)

    def wait_for(self, session, predicate, timeout_s: float, what: str):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            alive, statuses = query_status(session, self.robot, 1.0)
            result = predicate(alive, {s.service: s for s in statuses})
            if result:
                return result
            time.sleep(0.3)
        pytest.fail(f"timed out waiting for {what}")

    def stop(self, name: str, timeout_s: float = 15) -> int:
        proc = self.procs.pop(name)
        proc.terminate()
        return proc.wait(timeout_s)

    def close(self) -> None:
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.kill()
                proc.wait()


@pytest.fixture
def cluster(tmp_path):
    c = Cluster(tmp_path)
    c.start_router()
    yield c
    c.close()


@pytest.fixture
def router():
    """A Zenoh router session in this process, on a free loopback port: its endpoint."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(conf):
        yield endpoint
