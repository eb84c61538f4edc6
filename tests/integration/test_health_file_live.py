"""A live service's --health-file (and the monitor's), read by `lrfslam status --check-file` as a container
healthcheck would."""

from __future__ import annotations

import json
import os
import subprocess
import time

import pytest

from lrfslam.tools import status


def check_until(path, want: int, says: str, timeout_s: float, capsys) -> None:
    """Run the check until it exits ``want`` saying ``says``; fail with its last line after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        code = status.main(["--check-file", str(path)])
        out = capsys.readouterr().out
        if (code, says in out) == (want, True):
            return
        assert time.monotonic() < deadline, f"exit {code}: {out}"
        time.sleep(0.2)


# The monitor is no service (no --mode; its WebSocket server on any free port) but writes the same file.
COMMANDS = {
    "denoise": ["denoise", "--mode", "client"],
    "monitor": ["monitor", "--port", "0"],
}


@pytest.mark.parametrize("name", ["denoise", pytest.param("monitor", marks=pytest.mark.slow)])
def test_healthy_while_connected_then_not_once_the_router_is_gone(cluster, tmp_path, capsys, name):
    path = tmp_path / "health.json"
    cluster.procs[name] = subprocess.Popen(
        cluster.cmd(*COMMANDS[name], "--robot", cluster.robot, "--connect", cluster.endpoint,
                    "--log-level", "WARNING", "--health-file", str(path)), cwd=tmp_path,
        env={**os.environ, "LRFSLAM_BUS_HEALTH_PERIOD_S": "0.2"})   # the service's file is stale after 2 s
    check_until(path, 0, "ok: ", 30, capsys)
    assert json.loads(path.read_text())["service"] == name
    # The router goes; the service keeps running and retrying, and says it is cut off.
    cluster.stop("router")
    check_until(path, 1, "no router or peer connected", 30, capsys)
    # The process goes: within ten health periods its file is too old.
    cluster.procs[name].kill()
    cluster.procs[name].wait()
    check_until(path, 1, "main loop stuck or process gone", 15, capsys)
