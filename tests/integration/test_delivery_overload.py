"""A stage slowed to a third of its input rate under ``lrfslam up``: its losses are counted and shown,
the stages beside it lose nothing.

bus.debug_slow (LRFSLAM_BUS_DEBUG_SLOW=features:40) makes the features stage sleep 40 ms after
each filtered scan: 25 a second at most, while 75 arrive (``--speedup 7.5``). docs/delivery.md
has the measured figures (src/lrfslam/bench/delivery.py).
"""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
import time

import pytest
import zenoh

from lrfslam.runtime.recording import read_recording
from lrfslam.tools.status import client_config, query_status

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def test_an_overloaded_stage_counts_its_drops_and_the_others_keep_up(tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "LRFSLAM_BUS_DEBUG_SLOW": "features:40"}
    up = subprocess.Popen([sys.executable, "-m", "lrfslam.cli", "up", "--duration", "25", "--speedup", "7.5",
                           "--port", str(port), "--robot", "ov", "--skip", "mapper"],
                          cwd=tmp_path, env=env, stdout=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while True:   # up's router listens once up has started it
            try:
                session = zenoh.open(client_config([f"tcp/127.0.0.1:{port}"]))
                break
            except zenoh.ZError:
                assert time.monotonic() < deadline and up.poll() is None, "up's router never came up"
                time.sleep(0.5)
        dropped = 0
        with session:
            deadline = time.monotonic() + 60
            while not dropped and time.monotonic() < deadline:
                _, statuses = query_status(session, "ov", 1.0)
                dropped = next((s.counters.get("drop.queue", 0) for s in statuses if s.service == "features"), 0)
        assert dropped > 0, "lrfslam status never showed the features stage dropping"
        stdout, _ = up.communicate(timeout=180)
    finally:
        if up.poll() is None:
            up.kill()
            up.wait()
    assert up.returncode == 0, stdout
    rows = {m[0]: tuple(map(int, m[1:])) for m in
            re.findall(r"^(\w+)\s+(\d+)\s+(\d+)\s+(\d+)\s+(\d+)\s+\d+\s+\d+\s+\d+\s+\S+$", stdout, re.MULTILINE)}
    (folder,) = (tmp_path / "recordings").glob("*_ov")
    scans = sum(1 for _ in read_recording(folder, ["scan"]))
    assert f"scans published by the sensor {scans} / scans in the recording {scans} / lost 0" in stdout, stdout
    # stage: (in, out, dropped, gaps). The slow stage handled some scans and counted the rest: refused
    # by its full queue, or still queued when it was stopped.
    f_in, f_out, f_dropped, _ = rows["features"]
    assert f_dropped > 0 and f_in + f_dropped == scans and f_out == f_in, stdout
    # Beside it, nothing lost: denoise filtered every scan; nobody saw a gap.
    assert rows["denoise"][:3] == (scans, scans, 0), stdout
    assert rows["slam"][2] == rows["recorder"][2] == 0, stdout
    assert all(gaps == 0 for *_, gaps in rows.values()), stdout
