"""``lrfslam bench``: the EKF shape check, the table, the verdicts on live runs (src/lrfslam/bench/command.py).

No wall-clock limit is asserted: the check is fed synthetic times of a known shape, and the quick
sections are held to their structure (a row per measure, positive figures), not to their values.
"""

from __future__ import annotations

import json
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from filterpy.kalman import ExtendedKalmanFilter

from lrfslam import cli
from lrfslam.bench import command as bench
from lrfslam.bench import cost as bench_cost
from lrfslam.bench import live as bench_live
from lrfslam.io.textfile import carmen_logs, log_name
from lrfslam.msgs import topics
from lrfslam.runtime.pacing import CreditWindow
from lrfslam.runtime.recording import read_recording
from lrfslam.tools.importers import import_carmen
from lrfslam.tools.play import Summary, summary_line

DATA = Path(__file__).resolve().parents[1] / "data"


def shape(power: float, ratio: float, dense_power: float = 3.0) -> bench_cost.EkfShape:
    """Synthetic update times: ours ∝ n**power, the dense one ``ratio`` times ours at 400 landmarks and
    ∝ n**dense_power."""
    sizes = bench_cost.EKF_CHECK_SIZES
    ours = tuple(1e-9 * n**power for n in sizes)
    at = 1e-9 * 400**power * ratio
    return bench_cost.EkfShape(sizes, ours, tuple(at * (n / 400) ** dense_power for n in sizes))


def test_the_check_holds_a_quadratic_update_well_ahead_of_the_dense_one():
    s = shape(2.0, 50.0)
    assert s.slope_ours == pytest.approx(2.0) and s.slope_dense == pytest.approx(3.0)
    assert s.ratio_at(400) == pytest.approx(50.0)
    assert bench_cost.check_ekf(s) == []


@pytest.mark.parametrize(("power", "ratio", "broken"), [
    (3.0, 50.0, "slope 3.00"),      # cubic: the sparse update lost its shape
    (1.0, 50.0, "slope 1.00"),      # flat: not measuring the update at all
    (2.0, 5.0, "only 5.0x"),        # the right slope, but no longer ahead of the dense update
    (2.0, float("nan"), "only nanx"),   # the dense update was not timed at 400 landmarks
])
def test_the_check_fails_when_the_shape_breaks(power, ratio, broken):
    problems = bench_cost.check_ekf(shape(power, ratio))
    assert len(problems) == 1 and broken in problems[0]


def test_check_mode_exits_1_with_one_line_when_the_shape_breaks(monkeypatch, capsys):
    monkeypatch.setattr(bench_cost, "ekf_shape", lambda *a, **k: shape(3.0, 50.0))
    assert cli.main(["bench", "--check", "ekf"]) == 1
    out, err = capsys.readouterr()
    assert "| EKF update | log-log slope against landmarks | 3 |" in out
    assert len(err.strip().splitlines()) == 1 and "check ekf failed: EKF update log-log slope 3.00" in err
    monkeypatch.setattr(bench_cost, "ekf_shape", lambda *a, **k: shape(2.0, 50.0))
    assert cli.main(["bench", "--check", "ekf", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["problems"] == []


@pytest.mark.parametrize("argv", [["--only", "stages,nosuch"], ["--check", "speed"], ["--rates", "75,-1"],
                                  ["--rates", "fast"], ["--duration", "0"]])
def test_bad_options_are_one_line_and_exit_2(argv, capsys):
    assert cli.main(["bench", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("lrfslam bench: error:")


def test_loglog_slope_recovers_a_power_law_and_skips_what_was_not_timed():
    n = np.array([50, 200, 500, 1000])
    assert bench_cost.loglog_slope(n, 3e-7 * n**2.4) == pytest.approx(2.4)
    assert bench_cost.loglog_slope(n, [np.nan, 1.0, np.nan, 4.0]) == pytest.approx(np.log(4) / np.log(5))
    assert np.isnan(bench_cost.loglog_slope(n, [np.nan, 1.0, np.nan, np.nan]))


def test_the_table_is_one_markdown_table_under_a_header_naming_machine_and_commit():
    info = bench.machine()
    rows = [*bench_cost.ekf_rows(shape(2.0, 50.0)),
            bench_cost.Row("logs", "none", float("nan"), "")]
    text = bench.table(info, rows)
    header, blank, *lines = text.splitlines()
    assert info["commit"] in header and f"{info['cores']} cores" in header and "numpy" in header and blank == ""
    assert all(line.count("|") == 8 for line in lines) and len(lines) == 2 + len(rows)
    assert "| 50.0× |" in text and "| logs | none | – |" in text
    assert bench.fmt(1234.5) == "1,234" and bench.fmt(0.01234) == "0.0123" and bench.fmt(float("nan")) == "–"


def test_quick_sections_give_a_positive_figure_for_every_measure():
    settings = replace(bench.Settings.quick(), scans=20)
    rows = bench.run(["stages", "ekf", "codecs"], settings, Path("."), lambda _: None)
    by_section: dict[str, list[str]] = {}
    for r in rows:
        by_section.setdefault(r.section, []).append(r.measure)
        assert np.isfinite(r.value) and r.value > 0, r
    assert len(by_section["stage cost"]) == 4   # the kernels' compile time only outside --quick
    assert len(by_section["calibration"]) == 2
    ekf = [r for r in rows if r.section == "EKF update" and r.ratio is not None]
    assert [int(r.measure.split()[0]) for r in ekf] == list(bench_cost.EKF_TABLE_SIZES)
    assert all(r.ratio > 0 for r in ekf)
    codecs = by_section["encode/decode"]
    for tp in (topics.SCAN, topics.ODOM, topics.SCAN_FILTERED, topics.FEATURES, topics.SLAM_STATE):
        assert tp.name in codecs
    for n in bench_cost.STATE_MAP_SIZES:   # the slam stage's whole map, at every map size
        assert f"{topics.SLAM_MAP.name}, {n}-landmark map" in codecs


def test_state_rows_hold_the_start_and_the_end_of_a_recorded_run():
    golden = Path(__file__).resolve().parents[1] / "data" / "golden" / "intel_150.pipeline.mcap"
    first, last = bench_cost.state_rows("intel_150", golden, 50, 1)
    assert first.measure == "intel_150, first 50 states (2 landmarks)" and first.value > 0
    assert last.measure.startswith("intel_150, last 50 states") and last.ratio > 0
    # The v1 state it compares with is the one the slam stage published before (same filter, the
    # whole map): its mean size is that of the v1 golden's last 50 states.
    v1 = [len(m.data) for m in read_recording(golden.with_name("intel_150.slam_v1.mcap"), [topics.SLAM_STATE.name])]
    sizes = [float(x.replace(",", "")) for x in re.findall(r"([\d,]+) B", last.note)]
    assert len(sizes) == 2 and sizes[1] == pytest.approx(np.mean(v1[-50:]), abs=0.5)


def test_a_queue_grows_when_its_end_stands_well_above_its_start():
    assert not bench_live.queue_growing([0, 3, 1, 2, 5, 1, 0, 2, 4, 1, 2, 3])
    assert bench_live.queue_growing(list(range(0, 60, 2)))
    assert not bench_live.queue_growing([0, 200, 300])   # too few samples for a verdict


def run_at(rate: float, dropped: int = 0, pending: list[int] | None = None) -> bench_live.LiveRun:
    stages = {"slam": bench_live.StageRow("slam", 10, 10, dropped, 0, 0, 0, 0, "0")}
    return bench_live.LiveRun(rate, 60.0, 0, stages, 100, 100, 0, {"slam": pending or [1] * 8},
                              {"slam": (8000, 14000)})


def test_the_highest_rate_held_is_the_last_that_held():
    runs = [run_at(75), run_at(150), run_at(225, pending=list(range(0, 80, 10)))]
    rows = bench.rate_rows(runs)
    assert [r.value for r in rows[:3]] == [14.0] * 3
    assert "largest queue.pending 70 (slam)" in rows[2].note and "queue growing in slam" in rows[2].note
    assert rows[-1].value == 150
    assert np.isnan(bench.rate_rows([run_at(75, dropped=3)])[-1].value)


def test_the_rate_search_climbs_to_the_first_failure_then_halves_the_interval_once():
    limit = 190.0   # a pipeline that holds up to this rate
    asked: list[float] = []

    def at(rate: float) -> bench_live.LiveRun:
        asked.append(rate)
        return run_at(rate, dropped=int(rate > limit))
    runs = bench.search_rates((75.0, 150.0, 225.0, 300.0), 1, at)
    assert asked == [75.0, 150.0, 225.0, 190.0]
    assert bench.rate_rows(runs)[-1].value == 190.0
    assert [r.measure.split()[0] for r in bench.rate_rows(runs)[:-1]] == ["75", "150", "190", "225"]
    asked.clear()
    assert [r.rate_hz for r in bench.search_rates((75.0, 150.0), 1, at)] == [75.0, 150.0] == asked


def test_the_play_figures_are_read_from_plays_own_summary_line():
    window = CreditWindow(8)
    line = summary_line(Summary(messages=31, scans=10, seconds=2.5, data_s=20.0), topics.MAP_POSE, window,
                        {"slam": (1, 2), "mapper": (0, 3)}, None)
    run = bench_live.parse_play_line("intel", 0, line)
    assert (run.scans, run.seconds, run.scans_per_s, run.pace, run.dropped, run.gaps) == (10, 2.5, 4.0, 8.0, 1, 5)


def test_the_head_of_a_log_holds_its_first_scans(tmp_path):
    head = bench.head_of_log(DATA / "intel_head.clf", 3, tmp_path / "head.clf")
    assert import_carmen(head, tmp_path / "head.mcap").scans == 3
    assert [log_name(p) for p in carmen_logs(DATA)] == ["carmen_mixed", "intel_head"]
    assert re.fullmatch(r"\w+", log_name(Path("x/intel.clf.bz2")))


def test_the_dense_update_timed_against_ours_is_the_same_update():
    """The ratio compares like with like: filterpy's update with the bench's dense model moves the
    bench's random filter exactly as ``update_known`` does."""
    rng = np.random.default_rng(1)
    f = bench_cost.random_filter(6, rng)
    k = f.state_mean.size - 12 + 2 * 4   # landmark 4's x
    R = np.diag([0.015**2, 0.005**2])
    x = f.state_mean
    dx, dy = x[k] - x[0], x[k + 1] - x[1]
    bearing = (np.arctan2(dy, dx) - x[2] + np.pi) % (2 * np.pi) - np.pi
    z = np.array([np.hypot(dx, dy), bearing]) + [0.05, 0.01]
    dense = ExtendedKalmanFilter(dim_x=f.state_mean.size, dim_z=2)
    dense.x, dense.P = f.state_mean.reshape(-1, 1).copy(), f.state_cov.copy()
    bench_cost.dense_update(dense, z, R, k)
    f.update_known(4, z, R)
    np.testing.assert_allclose(dense.x.ravel(), f.state_mean, atol=1e-12)
    np.testing.assert_allclose(dense.P, f.state_cov, atol=1e-12)
