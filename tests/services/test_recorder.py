"""The recorder stores raw payloads with their schemas, never overwrites, and survives a full disk."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from lrfslam.services.recorder import RecorderConfig, RecorderStep
from mcap.reader import make_reader

from lrfslam.msgs import codec, topics
from lrfslam.msgs import types as t
from lrfslam.runtime.recording import read_recording
from lrfslam.runtime.step import Message, RunContext


def raw(i: int) -> Message:
    ranges = np.random.default_rng(i).uniform(0.5, 8.0, 181)
    scan = t.LaserScan.from_ranges(1_000 + i, i, ranges, -np.pi / 2, np.radians(1))
    return Message(None, codec.LASER_SCAN.encode(scan), scan.stamp_ns, topics.SCAN.schema, "scan", i)


def test_records_payloads_as_received(tmp_path):
    step = RecorderStep(RecorderConfig(directory=str(tmp_path), name="r"), RunContext("r1"))
    for i in range(20):
        step.on_message(raw(i))
    step.close()
    got = list(read_recording(tmp_path / "r", ["scan"]))   # beside them: Foxglove's views (test_recorder_foxglove.py)
    assert [codec.LASER_SCAN.decode(m.data).seq for m in got] == list(range(20))
    assert {m.schema for m in got} == {topics.SCAN.schema}
    assert [p.name for p in (tmp_path / "r").iterdir()] == ["r_0.mcap"]


def test_each_start_adds_a_segment_and_never_overwrites(tmp_path):
    cfg = RecorderConfig(directory=str(tmp_path), name="r")
    first = RecorderStep(cfg, RunContext("r1"))
    for i in range(10):
        first.on_message(raw(i))
    first.tick()   # not due yet: nothing forced; the data is still written on close
    first.close()
    before = (tmp_path / "r" / "r_0.mcap").read_bytes()
    second = RecorderStep(cfg, RunContext("r1"))
    for i in range(10, 15):
        second.on_message(raw(i))
    second.close()
    assert (tmp_path / "r" / "r_0.mcap").read_bytes() == before
    assert [m.sequence for m in read_recording(tmp_path / "r", ["scan"])] == list(range(15))
    assert [m.sequence for m in read_recording(tmp_path / "r" / "r_1.mcap", ["scan"])] == list(range(10, 15))


FULL_DISK = """
import json, logging, resource, signal, sys
sys.path[:0] = {paths!r}
logging.basicConfig(level=logging.WARNING)
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)          # a write past the limit fails (EFBIG) like a full disk
resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, {limit}))
from test_recorder import raw
from lrfslam.runtime.step import RunContext
from lrfslam.services.recorder import RecorderConfig, RecorderStep
step = RecorderStep(RecorderConfig(directory={directory!r}, name="r", chunk_size_kb=2, flush_period_s=0.0,
                                   retry_period_s={retry}), RunContext("r1"))
health = []
for i in range(300):
    step.on_message(raw(i))
    step.tick()
    health.append(step.health()[0])
step.close()
print(json.dumps({{"counts": dict(step.counts), "health": health, "segments": [str(p) for p in step.writer.segments]}}))
"""


def run_full(tmp_path: Path, limit: int, retry: float) -> tuple[dict, str]:
    script = FULL_DISK.format(paths=[str(Path(__file__).parent)], limit=limit, directory=str(tmp_path), retry=retry)
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60, check=False,
                         env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"})
    assert res.returncode == 0, res.stderr
    return json.loads(res.stdout), res.stderr


def test_a_full_disk_is_one_error_a_valid_segment_and_not_fatal(tmp_path):
    out, stderr = run_full(tmp_path, limit=50_000, retry=1e9)
    c = out["counts"]
    assert stderr.count("recording stopped") == 1 and "File too large" in stderr, stderr
    assert c["error.write"] == 1 and c["messages"] + c["drop.unwritable"] == 300
    assert out["health"][0] == t.HEALTH_OK and out["health"][-1] == t.HEALTH_ERROR
    (segment,) = map(Path, out["segments"])
    with open(segment, "rb") as f:   # valid for the mcap library's default reader
        seqs = [m.sequence for _, _, m in make_reader(f).iter_messages(topics=["scan"])]
    # Everything up to the last complete chunk, in order; at most the chunk that failed is missing.
    assert seqs == list(range(len(seqs))) and c["messages"] - len(seqs) < 20


def test_after_a_write_error_it_retries_in_a_new_segment(tmp_path):
    out, stderr = run_full(tmp_path, limit=50_000, retry=0.0)
    # Each segment fills to the (per-file) limit, then the next one is opened; one error line for all.
    assert len(out["segments"]) >= 3 and stderr.count("recording stopped") == 1
    seqs = [m.sequence for m in read_recording(tmp_path / "r", ["scan"])]
    assert seqs == sorted(set(seqs)) and len(seqs) > 200
