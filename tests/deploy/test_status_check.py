"""``lrfslam status --check``: the verdict container healthchecks rely on."""

from __future__ import annotations

from lrfslam.msgs import types as t
from lrfslam.tools.status import check, main


def status(service: str, level: int, message: str = "") -> t.ServiceStatus:
    return t.ServiceStatus(service=service, robot="robot1", level=level, message=message, wall_stamp_ns=0,
                           uptime_s=1.0, counters={}, config_json="{}", pid=1, host="host")


def test_alive_and_not_error_is_healthy_even_when_stale():
    alive = {("robot1", "slam"), ("robot1", "sensor")}
    statuses = [status("slam", t.HEALTH_STALE), status("sensor", t.HEALTH_WARN)]
    assert check(alive, statuses, ["slam", "sensor"]) == []


def test_missing_token_or_error_status_is_unhealthy():
    alive = {("robot1", "slam")}
    problems = check(alive, [status("slam", t.HEALTH_ERROR, "cannot write")], ["slam", "recorder"])
    assert problems == ["slam@robot1: ERROR cannot write", "recorder: no liveliness token"]


def test_a_service_without_a_status_reply_counts_as_alive():
    assert check({("robot1", "features")}, [], ["features"]) == []


def test_unreachable_router_fails_the_check(capsys):
    assert main(["--check", "-e", "tcp/127.0.0.1:1", "--timeout", "0.2"]) == 2
    assert "cannot reach tcp/127.0.0.1:1" in capsys.readouterr().err
