"""``lrfslam status --watch`` against a running pipeline: router and services as processes."""

from __future__ import annotations

import re
import signal
import subprocess
import time

import pytest

pytestmark = pytest.mark.integration

STAGES = ("slam", "features", "denoise")
HEADER = "lrfslam status, every"


def test_watch_refreshes_the_table_until_ctrl_c(cluster):
    for name in STAGES:
        cluster.start(name)
    session = cluster.session()
    with session:
        cluster.wait_for(session, lambda alive, st: {s for _, s in alive} >= set(STAGES), 30, "liveliness")
        cluster.start("sensor", "speedup=4", "seed=3", "source=sim")
        cluster.wait_for(session, lambda a, st: st.get("slam") and st["slam"].counters.get(
            "out.slam/state", 0) >= 10, 60, "10 SLAM states")
    watcher = subprocess.Popen(cluster.cmd("status", "--watch", "--interval", "1", "--robot", cluster.robot,
                                           "--connect", cluster.endpoint),
                               stdout=subprocess.PIPE, stderr=(cluster.tmp / "watch.err").open("w"), text=True)
    try:
        out = ""
        deadline = time.monotonic() + 60
        while out.count(HEADER) < 2:    # the second header: the first table is complete
            assert time.monotonic() < deadline and watcher.poll() is None, out
            out += watcher.stdout.readline()
        watcher.send_signal(signal.SIGINT)
        rest = watcher.stdout.read()     # what readline buffered stays in the same reader
        watcher.wait(20)
    finally:
        if watcher.poll() is None:
            watcher.kill()
    out += rest
    err = (cluster.tmp / "watch.err").read_text()
    assert watcher.returncode == 0, err
    assert "Traceback" not in err
    tables = out.split(HEADER)[1:]
    assert len(tables) >= 2, out
    for table in tables[:2]:
        rows = {m.group(1): m for m in re.finditer(r"^itest\s+(\w+)\s+(yes|no)\s+(\w+)", table, re.MULTILINE)}
        assert set(rows) == {"sensor", *STAGES}, out
        assert all(m.group(2) == "yes" for m in rows.values()), table
        assert re.search(r"^slam itest: pose x -?[\d.]+ m, y -?[\d.]+ m, heading -?[\d.]+ deg; \d+ landmarks", table,
                         re.MULTILINE), table
    # From the second refresh on, the rates since the one before: the sensor publishes.
    sensor = re.search(r"^itest\s+sensor\s+yes\s+\w+\s+\d+\s+\d+\s+\d+\s+([\d.]+)\s+([\d.]+)", tables[1], re.MULTILINE)
    assert sensor and float(sensor.group(2)) > 0, tables[1]
    for name in ("sensor", *STAGES):
        assert cluster.stop(name) == 0
