"""``lrfslam play``'s choices before anything goes on the bus: what is played, what is refused, what is
waited for, the summary; and bad input: one line, exit 2, nothing played.

The command against live services is tested in tests/integration/test_play.py.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from lrfslam import cli
from lrfslam.errors import ConfigError
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.runtime.pacing import CreditWindow
from lrfslam.tools import play

GOLDEN = str(Path(__file__).resolve().parents[2] / "tests" / "data" / "golden" / "sim_head.mcap")


def test_by_default_the_sensors_topics_are_played():
    assert play.played_topics(None) == (topics.SCAN, topics.ODOM, topics.TRUTH)


def test_topics_may_be_given_with_spaces_or_commas_once_each():
    assert play.played_topics(["scan,odom", "scan"]) == (topics.SCAN, topics.ODOM)


@pytest.mark.parametrize(("name", "why"), [("health/slam", "wall-clock status"), ("/foxglove/scan", "Foxglove"),
                                           ("scans", "unknown topic")])
def test_what_is_not_a_data_topic_is_refused(name, why):
    with pytest.raises(ConfigError, match=why):
        play.played_topics([name])


def test_a_topic_a_live_service_publishes_is_refused():
    with pytest.raises(ConfigError, match="sensor is alive.*scan, odom"):
        play.check_collisions((topics.SCAN, topics.ODOM), {"sensor", "denoise"})
    with pytest.raises(ConfigError, match="denoise is alive.*scan/filtered"):
        play.check_collisions((topics.SCAN, topics.SCAN_FILTERED), {"denoise", "recorder"})
    play.check_collisions((topics.SCAN, topics.ODOM), {"denoise", "features", "slam", "mapper", "recorder", "x"})


def test_the_watched_topic_is_the_deepest_live_stages_or_the_one_asked_for():
    played = play.played_topics(None)
    assert play.choose_watched(None, played, {"denoise", "features", "slam", "recorder"}) is topics.SLAM_STATE
    assert play.choose_watched(None, played, {"denoise", "recorder"}) is topics.SCAN_FILTERED
    assert play.choose_watched(None, played, {"recorder"}) is None
    assert play.choose_watched("features", played, {"denoise", "features", "slam"}) is topics.FEATURES
    with pytest.raises(ConfigError, match="slam is not alive"):
        play.choose_watched("slam/state", played, {"denoise", "features"})
    with pytest.raises(ConfigError, match="must be one of scan/filtered, features, slam/state, map/pose"):
        play.choose_watched("map/keyframes", played, {"mapper"})


def status(service: str, pid: int, **counters: int) -> t.ServiceStatus:
    return t.ServiceStatus(service=service, robot="r", level=t.HEALTH_OK, message="ok", wall_stamp_ns=0, uptime_s=1.0,
                           counters=dict(counters), last_data_stamp_ns=0, config_json="{}", schemas=(), pid=pid,
                           host="h")


def test_losses_are_the_counters_growth_of_the_same_process():
    before = [status("denoise", 1, **{"drop.queue": 2, "gap.scan": 1}), status("slam", 2, **{"gap.features": 5})]
    after = [status("denoise", 1, **{"drop.queue": 2, "gap.scan": 4, "drop.stop": 1}),
             status("slam", 3, **{"gap.features": 1}),   # restarted: its counters start again
             status("recorder", 4)]
    assert play.losses(before, after) == {"denoise": (1, 3), "slam": (0, 1), "recorder": (0, 0)}


def test_the_summary_is_one_line_with_the_figures():
    window = CreditWindow(4)
    window.send(1)
    window.acknowledge(1)
    line = play.summary_line(play.Summary(messages=300, scans=150, seconds=2.0, data_s=29.0, loops=2),
                             topics.SLAM_STATE, window, {"denoise": (0, 0), "recorder": (2, 1)}, "SIGINT")
    assert "\n" not in line
    assert line == ("lrfslam play: 300 messages (150 scans) in 2.00 s: 150.0 messages/s, 75.0 scans/s, 14.50 x the "
                    "recorded pace; 2 loops; slam/state answered 1 of 1 scans; live services dropped 2, gaps 1 "
                    "(recorder 2/1); stopped by SIGINT")


@pytest.mark.parametrize(("argv", "message"), [
    (["missing.mcap"], "recording missing.mcap does not exist"),
    (["not.mcap"], "not.mcap is not an MCAP recording"),
    ([GOLDEN, "--topics", "health/slam"], "cannot play 'health/slam'"),
    ([GOLDEN, "--window", "0"], "--window must be at least 1"),
    ([GOLDEN, "--connect", "tcp/127.0.0.1:1"], "cannot reach tcp/127.0.0.1:1"),
])
def test_bad_input_is_one_line_and_exit_2(argv, message, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "not.mcap").write_text("hello")
    assert cli.main(["play", *argv]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err.strip().count("\n") == 0 and err.startswith(f"lrfslam play: error: {message}"), err


@pytest.mark.parametrize("rate", ["0", "-2", "fast", "nan"])
def test_a_rate_is_a_positive_number_or_max(rate, capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["play", GOLDEN, "--rate", rate])
    assert exc.value.code == 2
    assert "--rate: must be a positive number or 'max'" in capsys.readouterr().err
    assert play.parse_rate("max") is None and play.parse_rate("2.5") == 2.5
