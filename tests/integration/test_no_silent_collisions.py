"""No silent collisions: a router that cannot listen, a second ``up`` on a taken port, a second
service of the same robot — each stops at once with one error line and exit 2, unless told to join.

Before, a second ``lrfslam up`` on the same port printed a zenoh traceback from its router, then
joined the first pipeline; both exited 0 with a recording of two robots mixed.
"""

from __future__ import annotations

import socket
import subprocess
import sys
import time

import pytest

from lrfslam.tools.status import query_status

pytestmark = pytest.mark.integration


def run(*args: str, cwd, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lrfslam.cli", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=timeout, check=False)


def one_error_line(stderr: str) -> str:
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    assert "Traceback" not in stderr and "ZError" not in stderr, stderr
    errors = [ln for ln in lines if "ERROR" in ln or "error:" in ln]
    assert errors, stderr
    return "\n".join(errors)


def test_a_router_that_cannot_listen_says_why_in_one_line(tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        res = run("router", "--listen", f"tcp/127.0.0.1:{port}", cwd=tmp_path)
    assert res.returncode == 2
    line = one_error_line(res.stderr)
    assert f"cannot listen on tcp/127.0.0.1:{port}: Address already in use" in line
    assert len(res.stderr.strip().splitlines()) == 1, res.stderr


def test_up_on_a_port_another_router_holds_stops_before_starting_anything(cluster):
    port = cluster.endpoint.rsplit(":", 1)[1]
    res = run("up", "--port", port, "--robot", cluster.robot, "--duration", "5", cwd=cluster.tmp)
    assert res.returncode == 2, res.stdout + res.stderr
    errors = one_error_line(res.stderr)
    assert "Address already in use" in errors                      # its router's own line
    assert "another router already listens on" in errors         # and up's
    assert not (cluster.tmp / "recordings").exists()               # nothing started, nothing written
    with cluster.session() as session:                               # and nothing joined the router's robot
        assert query_status(session, cluster.robot, 1.0)[0] == set()


def test_a_second_service_of_the_same_robot_refuses_unless_told_to_join(cluster):
    first = cluster.start("denoise")
    with cluster.session() as session:
        cluster.wait_for(session, lambda alive, _: (cluster.robot, "denoise") in alive, 30, "the first denoise")
        second = run("denoise", "--robot", cluster.robot, "--mode", "client", "--connect", cluster.endpoint,
                     cwd=cluster.tmp)
        assert second.returncode == 2
        line = one_error_line(second.stderr)
        assert f"denoise of robot '{cluster.robot}' is already running (pid {first.pid} on " in line
        assert "--join" in line
        assert first.poll() is None                                   # the first one never noticed

        joined = subprocess.Popen(cluster.cmd("denoise", "--robot", cluster.robot, "--mode", "client",
                                              "--connect", cluster.endpoint, "--join"), cwd=cluster.tmp)
        cluster.procs["joined"] = joined
        # Another robot's namespace is free: the same service starts beside them without --join.
        other = subprocess.Popen(cluster.cmd("denoise", "--robot", "other", "--mode", "client",
                                             "--connect", cluster.endpoint), cwd=cluster.tmp)
        cluster.procs["other"] = other
        wait_for_pids(session, cluster.robot, {first.pid, joined.pid}, joined)
        wait_for_pids(session, "other", {other.pid}, other)


def wait_for_pids(session, robot: str, pids: set[int], proc: subprocess.Popen) -> None:
    """Until every process in ``pids`` answers the status query of ``robot``."""
    deadline = time.monotonic() + 30
    while not {s.pid for s in query_status(session, robot, 1.0)[1]} >= pids:
        assert proc.poll() is None and time.monotonic() < deadline, "a service did not come up"
        time.sleep(0.2)


def test_up_refuses_a_robot_already_alive_on_the_router_it_connects_to(cluster):
    cluster.start("denoise")
    with cluster.session() as session:
        cluster.wait_for(session, lambda alive, _: (cluster.robot, "denoise") in alive, 30, "denoise")
    res = run("up", "--connect", cluster.endpoint, "--robot", cluster.robot, "--duration", "5", cwd=cluster.tmp)
    assert res.returncode == 2, res.stdout + res.stderr
    line = one_error_line(res.stderr)
    assert f"robot '{cluster.robot}' already has services running on {cluster.endpoint}: denoise (pid " in line
    assert not (cluster.tmp / "recordings").exists()
