"""A short soak: ``lrfslam up`` for 12,000 scans of 75 Hz data, every process's memory sampled.

The run of benchmarks/soak.py, shortened: the whole pipeline (router, six services, ``up``
itself) must lose nothing (no drop, no gap, no restart, every published scan in the recording)
and no process's resident memory may grow by 10 % or more between 30 % and 100 % of the run
(expected to fail for now: see docs/operations.md, Soak).
The long run's figures and command are in docs/operations.md.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

pytestmark = [pytest.mark.integration, pytest.mark.slow]

SCANS = 12_000        # 160 s of 75 Hz data
RATE_HZ = 75.0
SPEEDUP = 1.5         # 112 scans per wall second: 107 s, below what the pipeline sustains (docs/operations.md)
FROM = 0.3            # memory compared from here (fraction of the producing span) to the end
MAX_GROWTH_PCT = 10.0


def load_soak():
    path = Path(__file__).resolve().parents[2] / "benchmarks" / "soak.py"
    spec = importlib.util.spec_from_file_location("soak", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules["soak"] = module   # dataclasses look their module up by name
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def short_soak(tmp_path_factory):
    soak = load_soak()
    result = soak.run_soak(SCANS, RATE_HZ, SPEEDUP, interval_s=2.0, workdir=tmp_path_factory.mktemp("soak"), seed=3)
    print(result.stdout)
    print(soak.table(result, FROM))
    return result


def test_short_soak_loses_nothing(short_soak):
    result = short_soak
    assert result.returncode == 0, result.stdout
    assert set(result.stages) == {"recorder", "mapper", "slam", "features", "denoise", "sensor"}, result.stdout
    assert result.problems(FROM, float("inf")) == []
    assert result.published == result.recorded == SCANS and result.lost == 0
    # Every process was sampled through the run: up, its router and the six services.
    assert set(result.rss_between(FROM)) == {"up", "router", *result.stages}
    assert all(len(s.samples) >= 10 for s in result.series.values())


@pytest.mark.xfail(strict=False, reason="router, mapper and recorder RSS step up by 20-35 MB once during the "
                   "run, not per scan; measured and open in docs/operations.md (Soak)")
def test_short_soak_memory_stays_bounded(short_soak):
    growth = {name: 100.0 * (last - first) / first for name, (first, last) in short_soak.rss_between(FROM).items()}
    assert max(growth.values()) < MAX_GROWTH_PCT, growth
