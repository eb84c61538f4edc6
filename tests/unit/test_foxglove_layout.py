"""The Foxglove layout shipped in deploy/foxglove/ shows the channels the recorder and the monitor make."""

from __future__ import annotations

import json
from pathlib import Path

from lrfslam.msgs import topics
from lrfslam.viz import foxglove as fx

LAYOUT = Path(__file__).resolve().parents[2] / "deploy" / "foxglove" / "lrfslam-layout.json"


def panels(tree) -> list[str]:
    """Panel ids in a layout tree (a panel id, or a split with ``first`` and ``second``)."""
    return [tree] if isinstance(tree, str) else panels(tree["first"]) + panels(tree["second"])


def test_every_panel_is_placed_and_every_placed_panel_configured():
    layout = json.loads(LAYOUT.read_text())
    assert sorted(panels(layout["layout"])) == sorted(layout["configById"])


def test_the_panels_name_only_channels_and_frames_that_exist():
    config = json.loads(LAYOUT.read_text())["configById"]
    (map_panel,) = (c for pid, c in config.items() if pid.startswith("3D!"))
    # Every view channel with something to draw in 3D is listed, and nothing else.
    assert set(map_panel["topics"]) == set(fx.CHANNELS) - {fx.TF, fx.LOG}
    frames = {fx.WORLD, fx.MAP, fx.SLAM, fx.ODOM, fx.BASE, fx.LASER}
    assert map_panel["followTf"] in frames
    assert all(layer.get("frameId", fx.MAP) in frames for layer in map_panel["layers"].values())
    assert {key.removeprefix("frame:") for key in map_panel["transforms"]} <= frames
    (log_panel,) = (c for pid, c in config.items() if pid.startswith("Log!"))
    assert log_panel["topicToRender"] == fx.LOG
    (raw,) = (c for pid, c in config.items() if pid.startswith("RawMessages!"))
    assert topics.is_health(json.loads(raw["topicPath"]))   # a recorded health channel, quoted
