"""The sensor service drives an LMS200 through pyserial: the emulator on a real pseudo-terminal.

Each published scan must be exactly one that the emulator sent (its --dump-ranges
log), never a telegram it corrupted, and the faults must show in the status.
"""

from __future__ import annotations

import subprocess
import sys
import time

import numpy as np
import pytest

from lrfslam.msgs import codec, topics

pytestmark = pytest.mark.integration


def read_dump(path):
    """scan number -> (faults, ranges) from the emulator's dump."""
    sent = {}
    for line in path.read_text().splitlines():
        number, faults, *values = line.split()
        sent[int(number)] = (faults, np.array([float(v) for v in values]))
    return sent


@pytest.mark.parametrize("faults", [(), pytest.param(("--fault-bitflip-pct", "2", "--fault-garbage", "10",
                                         "--fault-truncate", "3"), marks=pytest.mark.slow)], ids=["clean", "faulty"])
def test_published_scans_are_the_emulators(cluster, tmp_path, faults):
    dump, link = tmp_path / "sent.txt", tmp_path / "lms0"
    emu = subprocess.Popen([sys.executable, "-m", "lrfslam.cli", "emulate-lms200", "--seed", "4",
                            "--dump-ranges", str(dump), "--link", str(link), *faults],
                           stdout=subprocess.PIPE, text=True)
    cluster.procs["emulator"] = emu
    assert emu.stdout.readline().startswith("/dev/")   # it prints its device path first
    received = []
    with cluster.session() as session:
        sub = session.declare_subscriber(topics.key(cluster.robot, "scan"),
                                         lambda s: received.append((s.payload.to_bytes(), str(s.encoding))))
        cluster.start("sensor", f"device={link}", "baud=38400")
        deadline = time.monotonic() + 60
        while len(received) < 40 and time.monotonic() < deadline:
            time.sleep(0.2)
        st = cluster.wait_for(session, lambda a, st: st.get("sensor"), 10, "sensor status")
        sub.undeclare()
    assert len(received) >= 40
    sent = read_dump(dump)
    by_ranges = {}
    for number, (fault, ranges) in sent.items():
        by_ranges.setdefault(np.round(ranges, 3).tobytes(), []).append((number, fault))
    for payload, encoding in received:
        scan = codec.LASER_SCAN.decode(payload, codec.parse_encoding(encoding))
        assert scan.ranges_m.size == 181 and scan.source == "lms200"
        np.testing.assert_allclose(scan.angles_rad[[0, 90, 180]], [-np.pi / 2, 0, np.pi / 2], atol=1e-6)
        matches = by_ranges.get(np.round(scan.ranges_m, 3).tobytes())
        assert matches, "a published scan the emulator never sent"
        assert all(f in ("none", "garbage") for _, f in matches), matches
    counters = st.counters
    if faults:
        bad = sum(v for k, v in counters.items() if k.startswith("step.lms200.") and
                  any(w in k for w in ("crc", "truncat", "garbage", "resync", "bad")))
        assert bad > 0, counters
    assert counters.get("step.scans", 0) >= 40
