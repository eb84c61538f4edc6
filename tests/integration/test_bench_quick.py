"""``lrfslam bench --quick`` end to end: every section, real processes (``lrfslam up``, ``lrfslam play``).

A CARMEN log from tests/data stands in for ../shared/datasets. What is held is the table's
content, not its figures: every section gives its rows, with positive figures where it measured,
every process of the pipeline its peak memory, and the log is played without a drop. ~1.5 minutes.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from lrfslam.bench.command import PROCESSES

pytestmark = [pytest.mark.integration, pytest.mark.slow]

DATA = Path(__file__).resolve().parents[1] / "data"


def test_quick_bench_gives_every_section(tmp_path):
    logs = tmp_path / "datasets" / "intel"
    logs.mkdir(parents=True)
    shutil.copy(DATA / "intel_head.clf", logs / "intel_head.clf")
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-m", "lrfslam.cli", "bench", "--quick", "--json", "--datasets",
                           str(tmp_path / "datasets")], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=600, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(done.stdout)
    assert report["machine"]["cores"] >= 1 and report["machine"]["commit"]
    rows: dict[str, list[dict]] = {}
    for row in report["rows"]:
        rows.setdefault(row["section"], []).append(row)
    assert set(rows) == {"calibration", "stage cost", "EKF update", "encode/decode", "live 75 Hz", "max rate",
                         "logs, play --rate max", "slam/state per scan", "peak RSS"}
    # The played log's recording: its slam states at the start and the end, beside v1's whole-map state.
    states = rows["slam/state per scan"]
    assert [r["measure"].split(" states")[0] for r in states] == ["intel_head, first 10", "intel_head, last 10"]
    assert all(r["value"] > 0 and r["compared"].startswith("v1 whole-map state") for r in states), states
    for section in ("calibration", "stage cost", "EKF update", "encode/decode", "peak RSS"):
        assert all(r["value"] is not None and r["value"] > 0 for r in rows[section]), rows[section]
    ages = {r["measure"]: r["value"] for r in rows["live 75 Hz"] if "age" in r["measure"]}
    assert set(ages) == {f"scan → {k} age {p}" for k in ("slam/state", "map/pose") for p in ("p50", "p99")}
    assert all(v > 0 for v in ages.values()) and ages["scan → slam/state age p50"] <= ages["scan → slam/state age p99"]
    tried = [r for r in rows["max rate"] if r["measure"].endswith("for 8 s")]
    assert tried and tried[0]["measure"].startswith("75 scans/s")
    (played,) = rows["logs, play --rate max"]
    assert played["measure"] == "intel_head (10 scans): wall time" and played["value"] > 0
    assert "dropped 0, gaps 0" in played["note"]
    cpu = {r["measure"].removeprefix("CPU per scan: "): r["value"] for r in rows["live 75 Hz"] if "CPU" in r["measure"]}
    started = set(PROCESSES) - {"group"}   # a process per stage: no --group
    assert set(cpu) == {*started, "total"} and cpu["total"] == pytest.approx(sum(cpu.values()) - cpu["total"])
    assert {r["measure"] for r in rows["peak RSS"]} == started
    assert all(math.isfinite(r["value"]) for r in rows["peak RSS"])
