"""The user's two paths: ``lrfslam up`` end to end, and one stage re-run on its recording."""

from __future__ import annotations

import re
import socket
import subprocess
import sys

import pytest

from lrfslam.msgs import codec
from lrfslam.runtime.recording import read_recording

pytestmark = [pytest.mark.integration, pytest.mark.slow]   # lrfslam up end to end: the slow step


def lrfslam(*args: str, cwd, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lrfslam.cli", *args], cwd=cwd, capture_output=True,
                          text=True, timeout=timeout, check=False)


@pytest.fixture(scope="module")
def up_run(tmp_path_factory):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    cwd = tmp_path_factory.mktemp("up")
    res = lrfslam("up", "--duration", "12", "--speedup", "4", "--port", str(port), "--robot", "r7", cwd=cwd)
    assert res.returncode == 0, res.stderr[-3000:]
    (recording,) = (cwd / "recordings").glob("*_r7")
    # One segment, and the checkpoints that up gives the slam and the mapper (a restarted one resumes from it).
    assert sorted(p.name for p in recording.iterdir()) == [f"{recording.name}_0.mcap", "mapper.checkpoint.npz",
                                                           "slam.checkpoint.npz"]
    return res.stdout, recording, cwd


def test_up_summarises_every_stage_and_the_pose_error(up_run):
    stdout, recording, _ = up_run
    rows = {m.group(1): (int(m.group(2)), int(m.group(3))) for m in
            re.finditer(r"^(sensor|denoise|features|slam|recorder)\s+(\d+)\s+(\d+)", stdout, re.MULTILINE)}
    assert set(rows) == {"sensor", "denoise", "features", "slam", "recorder"}, stdout
    scans = rows["sensor"][1] // 3            # scan + odom + truth per step
    assert scans >= 50
    assert rows["denoise"] == (scans, scans)
    # The slam stage's outputs: a state per scan, and the whole landmark map now and then.
    maps = sum(1 for _ in read_recording(recording, ["slam/map"]))
    assert rows["features"][0] == scans and rows["slam"][1] == scans + maps and maps >= 2
    err = re.search(r"final pose error ([\d.]+) cm", stdout)
    assert err and float(err.group(1)) < 50, stdout
    assert f"{recording.name}_0.mcap" in stdout     # the summary lists the segments


def test_up_prints_a_live_status_line_while_it_runs(up_run):
    stdout, _, _ = up_run
    live = re.findall(r"^\[\s*([\d.]+) s\] scans (\d+) \(([\d.]+)/s\)  landmarks (\d+) \(\d+ confirmed\)"
                      r"  pose error ([\d.]+) cm", stdout, re.MULTILINE)
    assert len(live) >= 2, stdout                    # every 5 s of a 12 s run
    assert int(live[-1][1]) > int(live[0][1]) > 0 and float(live[-1][2]) > 0 and int(live[-1][3]) > 0
    assert stdout.index(live[-1][0] + " s]") < stdout.index("lrfslam up: ran")   # before the summary


def test_up_loses_nothing_at_40_hz_and_says_so(up_run):
    stdout, recording, _ = up_run
    # stage, in, out, dropped (full input queue), gaps (sequence numbers never received)
    rows = re.findall(r"^(\w+)\s+\d+\s+\d+\s+(\d+)\s+(\d+)\s+\d+\s+\d+\s+\d+\s+\S+$", stdout, re.MULTILINE)
    assert {name for name, _, _ in rows} >= {"sensor", "denoise", "features", "slam", "mapper", "recorder"}, stdout
    assert all(dropped == gaps == "0" for _, dropped, gaps in rows), stdout
    recorded = sum(1 for _ in read_recording(recording, ["scan"]))
    assert f"scans published by the sensor {recorded} / scans in the recording {recorded} / lost 0" in stdout, stdout


def test_a_stage_replays_its_recording_deterministically(up_run):
    _, recording, cwd = up_run
    outs = []
    for name in ("a.mcap", "b.mcap"):
        res = lrfslam("slam", "--replay", str(recording), "--out", name, "--log-level", "WARNING", cwd=cwd)
        assert res.returncode == 0, res.stderr
        outs.append(cwd / name)
    assert outs[0].read_bytes() == outs[1].read_bytes()
    states = [codec.SLAM_STATE.decode(m.data) for m in read_recording(outs[0], ["slam/state"])]
    recorded = [m for m in read_recording(recording, ["features"])]
    assert len(states) == len(recorded) > 0
    assert [s.stamp_ns for s in states] == sorted(s.stamp_ns for s in states)


def test_a_source_cannot_be_replayed(up_run):
    _, recording, cwd = up_run
    res = lrfslam("sensor", "--replay", str(recording), cwd=cwd)
    assert res.returncode == 2 and "source" in res.stderr
