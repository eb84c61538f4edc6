"""``lrfslam up`` with its recorder killed by SIGKILL mid-run: the restarted recorder adds a segment.

Before recordings were folders, the restarted recorder reopened the run's one file and
overwrote it (one run kept 836 of 1,079 scans, and the summary said nothing). Now the
killed recorder's segment stays as it was, the summary lists both segments and names
the command that recovers the first, and the folder reads as one stream.
"""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import time

import pytest
import zenoh

from lrfslam.msgs import topics
from lrfslam.runtime.recording import read_recording, recover
from lrfslam.tools.status import client_config, query_status

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def test_up_survives_a_killed_recorder_without_overwriting(tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    up = subprocess.Popen([sys.executable, "-m", "lrfslam.cli", "up", "--duration", "25", "--speedup", "2",
                           "--port", str(port), "--robot", "rk"], cwd=tmp_path, stdout=subprocess.PIPE, text=True)
    try:
        time.sleep(3)
        with zenoh.open(client_config([f"tcp/127.0.0.1:{port}"])) as session:
            deadline = time.monotonic() + 60
            pid, scans = 0, 0
            while time.monotonic() < deadline and scans < 100:   # the sensor has been running ~5 s
                _, statuses = query_status(session, "rk", 1.0)
                by = {s.service: s for s in statuses}
                pid = by["recorder"].pid if "recorder" in by else 0
                scans = by["recorder"].counters.get("step.topic.scan", 0) if "recorder" in by else 0
            assert pid and scans >= 100, "the recorder never got going"
        os.kill(pid, signal.SIGKILL)
        stdout, _ = up.communicate(timeout=120)
    finally:
        if up.poll() is None:
            up.kill()
            up.wait()
    assert up.returncode == 0, stdout
    (folder,) = (tmp_path / "recordings").glob("*_rk")
    first, second = folder / f"{folder.name}_0.mcap", folder / f"{folder.name}_1.mcap"
    assert sorted(folder.glob("*.mcap")) == [first, second]
    row = re.search(r"^recorder\s+\d+\s+\d+\s+\d+\s+\d+\s+\d+\s+\d+\s+(\d+)", stdout, re.MULTILINE)  # restarts
    assert row and row.group(1) == "1", stdout
    rel_first, rel_second = first.relative_to(tmp_path), second.relative_to(tmp_path)
    assert f"lrfslam recover {rel_first} -o" in stdout and f"{rel_second}" in stdout, stdout
    sent = int(re.search(r"^sensor\s+\d+\s+(\d+)", stdout, re.MULTILINE).group(1)) // 3   # scan + odom + truth
    per_file = [sum(1 for _ in read_recording(p, [topics.SCAN.name])) for p in (first, second)]
    recovered = recover(first, tmp_path / "first.mcap")
    assert recovered.messages > 0
    together = [m.sequence for m in read_recording(folder, [topics.SCAN.name])]
    assert len(together) == sum(per_file) and together == sorted(together)
    print(f"\nscans sent {sent}; kept {per_file[0]} before the kill + {per_file[1]} after the restart "
          f"= {sum(per_file)} ({sent - sum(per_file)} lost: the last unflushed second and the restart)")
