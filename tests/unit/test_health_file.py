"""The health file a service writes for its container healthcheck, and what the check makes of it."""

from __future__ import annotations

from dataclasses import replace

import pytest

from lrfslam.msgs import types as t
from lrfslam.runtime import health_file
from lrfslam.tools import status

NOW_NS = 1_700_000_000_000_000_000
GOOD = health_file.HealthRecord("slam", "robot1", t.HEALTH_OK, "ok", NOW_NS - 500_000_000, 1.0, True, 42)


def written(tmp_path, record):
    path = tmp_path / "health.json"
    health_file.write(path, record)
    return path


def test_a_fresh_connected_ok_record_is_healthy_and_round_trips(tmp_path):
    path = written(tmp_path, GOOD)
    assert health_file.problems(path, NOW_NS) == []
    assert list(tmp_path.iterdir()) == [path], "the temporary file stays behind"


@pytest.mark.parametrize("level", [t.HEALTH_WARN, t.HEALTH_STALE])
def test_warn_and_stale_pass_like_the_router_check(tmp_path, level):
    assert health_file.problems(written(tmp_path, replace(GOOD, level=level)), NOW_NS) == []


@pytest.mark.parametrize("change, reason", [
    ({"level": t.HEALTH_ERROR, "message": "cannot write to x"}, "ERROR cannot write to x"),
    ({"connected": False}, "no router or peer connected"),
    # Ten health periods without a rewrite: the main loop is stuck or the process gone.
    ({"wall_stamp_ns": NOW_NS - 10_500_000_000}, "written 10 s ago"),
    ({"wall_stamp_ns": NOW_NS - 2_100_000_000, "health_period_s": 0.2}, "written 2 s ago"),
])
def test_each_reason_is_reported(tmp_path, change, reason):
    found = health_file.problems(written(tmp_path, replace(GOOD, **change)), NOW_NS)
    assert len(found) == 1 and reason in found[0], found


@pytest.mark.parametrize("text", ["", "{", "[]", '{"service": "slam"}', '{"x": 1}'])
def test_a_missing_or_malformed_file_is_unhealthy_not_a_crash(tmp_path, text):
    path = tmp_path / "health.json"
    assert "no health file" in health_file.problems(path, NOW_NS)[0]
    path.write_text(text)
    assert "unreadable health file" in health_file.problems(path, NOW_NS)[0]


def test_status_check_file_exit_codes(tmp_path, capsys):
    path = tmp_path / "health.json"
    assert status.main(["--check-file", str(path)]) == 1
    assert "no health file" in capsys.readouterr().out
    health_file.write(path, replace(GOOD, wall_stamp_ns=status.time.time_ns()))
    assert status.main(["--check-file", str(path)]) == 0
    assert capsys.readouterr().out.startswith("ok: ")
