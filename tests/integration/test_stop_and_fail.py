"""Real processes, real signals: offline commands stopped by SIGTERM/SIGINT leave no output
behind, and ``lrfslam up`` stops at once when a stage fails to start."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.runtime.recording import RecordingWriter

pytestmark = pytest.mark.integration

N_SCANS = 20_000   # minutes of work for the pipeline: it is always stopped long before the end


def cli(*args: str, cwd: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "lrfslam.cli", *args], cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


@pytest.fixture(scope="module")
def long_recording(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("long") / "long.mcap"
    rng = np.random.default_rng(0)
    angles = np.linspace(-np.pi / 2, np.pi / 2, 181)
    with RecordingWriter(path) as w:
        for i in range(N_SCANS):
            stamp = 10**12 + i * 100_000_000
            # A corridor the robot drives along: features and scan matching both have work.
            ranges = np.minimum(1.5 / np.maximum(np.abs(np.sin(angles)), 1e-3), 6.0) + rng.normal(0, 0.01, 181)
            scan = t.LaserScan.from_ranges(stamp, i + 1, ranges, -np.pi / 2, np.pi / 180)
            odom = t.Odometry(stamp_ns=stamp, seq=i + 1, pose=(0.01 * i, 0.0, 0.0))
            for tp, v in ((topics.SCAN, scan), (topics.ODOM, odom)):
                w.write(tp.name, tp.schema, tp.codec.encode(v), stamp, stamp, i + 1)
    return path


@pytest.fixture(scope="module")
def long_log(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("log") / "long.clf"
    line = "FLASER 181 " + " ".join(["2.5"] * 181) + " 0 0 0 0 0 0 {s:.3f} host {s:.3f}\n"
    path.write_text("".join(line.format(s=1000 + 0.1 * i) for i in range(60_000)))
    return path


def wait_for_partial(folder: Path, proc: subprocess.Popen) -> None:
    """Until the command has opened its partial output (it is then mid-run)."""
    while not list(folder.glob(".*.partial*")):
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.05)


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=lambda s: signal.Signals(s).name)
def test_a_stopped_pipeline_removes_its_output(long_recording, tmp_path, signum):
    out = tmp_path / "run.mcap"
    out.write_bytes(b"the previous run")
    proc = cli("pipeline", "-q", "--log-level", "ERROR", "--replay", str(long_recording), "--out", str(out),
               cwd=tmp_path)
    wait_for_partial(tmp_path, proc)
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signum, err
    assert f"stopped by {signal.Signals(signum).name}" in err and "Traceback" not in err, err
    assert out.read_bytes() == b"the previous run"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.mcap"]


@pytest.mark.slow   # end to end, long: the slow step (.ci/run step 3)
def test_a_stopped_import_removes_its_output(long_log, tmp_path):
    proc = cli("import", "carmen", str(long_log), "-o", str(tmp_path / "log.mcap"), "-q", cwd=tmp_path)
    wait_for_partial(tmp_path, proc)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert list(tmp_path.iterdir()) == []


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_up_with_a_bad_setting_fails_before_starting_anything(tmp_path):
    proc = cli("up", "--set", "slam.nosuch=1", "--port", str(free_port()), cwd=tmp_path)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 2
    (line,) = [ln for ln in err.splitlines() if "error" in ln]
    assert line.startswith("lrfslam up: error: slam: unknown setting 'nosuch'"), err
    assert list(tmp_path.iterdir()) == []


def test_up_refuses_a_plain_endpoint_beyond_loopback_before_starting_anything(tmp_path):
    port, extra = free_port(), free_port()
    proc = cli("up", "--port", str(port), "--listen", f"tcp/0.0.0.0:{extra}", cwd=tmp_path)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 2
    assert err.splitlines() == [(f"lrfslam up: error: --listen tcp/0.0.0.0:{extra} is plain (no TLS) beyond loopback: "
                                "whoever reaches it can read and publish on the bus; listen on tls/ with a "
                                "--zenoh-config of the router's certificate (deploy/README.md, 'Access control'), "
                                "or pass --insecure on a closed network")], err
    # Nothing was started: no line from a router or a stage, no recording folder, no process left on a port.
    assert list(tmp_path.iterdir()) == []
    for p in (port, extra):
        with socket.socket() as s:
            s.bind(("0.0.0.0", p))


def test_up_stops_everything_when_a_stage_exits_while_starting(tmp_path):
    (tmp_path / "blocker").write_text("a file where the recordings folder should be")
    proc = cli("up", "--recordings", "blocker/rec", "--port", str(free_port()), "--duration", "60", cwd=tmp_path)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 2, err
    assert "lrfslam up: error: recorder exited with code 2 while starting" in err, err
    assert "Traceback" not in err and "lrfslam up: ran" not in err
