"""``lrfslam pipeline``: several stages in one process, offline (lrfslam.tools.pipeline)."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from lrfslam.services import stage

from lrfslam import services
from lrfslam.errors import ConfigError
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.runtime import config as config_mod
from lrfslam.runtime.recording import RecordingWriter, read_metadata, read_recording
from lrfslam.runtime.runner import replay
from lrfslam.sim import SimConfig, Simulator
from lrfslam.tools import pipeline
from lrfslam.tools.pipeline import build_stages, run_pipeline, stage_names

T0_NS = 1_000_000_000_000
N_SCANS = 60
ROBOT = "testbot"


def write(writer: RecordingWriter, topic, value) -> None:
    writer.write(topic.name, topic.schema, topic.codec.encode(value), value.stamp_ns, value.stamp_ns, value.seq)


@pytest.fixture(scope="module")
def sim_recording(tmp_path_factory) -> Path:
    """60 simulated scans with odometry and truth, as the sensor service would record them."""
    path = tmp_path_factory.mktemp("sim") / "sim.mcap"
    sim = Simulator(SimConfig(seed=3))
    lidar = sim.config.lidar
    with RecordingWriter(path) as writer:
        for frame, _ in zip(sim, range(N_SCANS)):
            stamp, seq = T0_NS + round(frame.t_s * 1e9), frame.index + 1
            write(writer, topics.ODOM, t.Odometry(stamp_ns=stamp, seq=seq, pose=frame.odom_pose))
            write(writer, topics.TRUTH, t.GroundTruth(stamp_ns=stamp, seq=seq, pose=frame.true_pose, corner_ids=[],
                                                      corners_xy_m=np.zeros((0, 2))))
            write(writer, topics.SCAN, t.LaserScan.from_ranges(stamp, seq, frame.scan.ranges_m, lidar.angle_min_rad,
                                                              lidar.angle_increment_rad, lidar.max_range_m))
    return path


def default_stages(names=pipeline.DEFAULT_STAGES):
    return build_stages(names, [], {}, {})


def payloads(path: Path, topic: str) -> list[bytes]:
    return [r.data for r in read_recording(path, [topic])]


def test_outputs_per_stage_and_passthrough(sim_recording, tmp_path):
    out = tmp_path / "out.mcap"
    counts = run_pipeline(default_stages(), ROBOT, sim_recording, out)
    by_topic = Counter(r.topic for r in read_recording(out))
    per_scan = ("scan", "odom", "truth", "scan/filtered", "features", "slam/state", "map/pose")
    # map/keyframes: after each graph optimisation and once at the end; slam/map: the whole landmark
    # map at the first state, every 5 s of data time (6 s here) and at the last; map/grid: at most
    # once a second of data time (6 s here) and at the end.
    assert by_topic == {**{name: N_SCANS for name in per_scan}, "map/keyframes": by_topic["map/keyframes"],
                        "slam/map": 3, "map/grid": by_topic["map/grid"]}
    assert by_topic["map/keyframes"] >= 1 and 1 <= by_topic["map/grid"] <= 7
    assert counts["input"] == {"read": 3 * N_SCANS, "copied": 3 * N_SCANS}
    assert counts["denoise"]["in.scan"] == counts["denoise"]["out.scan/filtered"] == N_SCANS
    assert counts["features"]["out.features"] == counts["slam"]["in.features"] == N_SCANS
    assert counts["slam"]["in.odom"] == counts["slam"]["out.slam/state"] == N_SCANS
    # A run that finds nothing would pass the counts above; the sim hallway has corners and edges.
    assert counts["features"]["step.forward"] + counts["features"]["step.backward"] > 0
    meta = read_metadata(out)["lrfslam"]
    assert meta["robot"] == ROBOT and meta["stages"] == "denoise,features,slam,mapper" and meta["replay_of"] == "sim.mcap"
    assert '"mode": "default"' in meta["config.features"]


def test_deterministic(sim_recording, tmp_path):
    run_pipeline(default_stages(), ROBOT, sim_recording, tmp_path / "a.mcap")
    run_pipeline(default_stages(), ROBOT, sim_recording, tmp_path / "b.mcap")
    assert (tmp_path / "a.mcap").read_bytes() == (tmp_path / "b.mcap").read_bytes()


def test_same_outputs_as_the_services_replayed_one_by_one(sim_recording, tmp_path):
    run_pipeline(default_stages(), ROBOT, sim_recording, tmp_path / "all.mcap")

    def cfg(name):
        return stage(name).config

    replay(services.spec("denoise"), cfg("denoise"), ROBOT, sim_recording, tmp_path / "d.mcap")
    replay(services.spec("features"), cfg("features"), ROBOT, tmp_path / "d.mcap", tmp_path / "f.mcap")
    slam_inputs = [tp.name for tp in services.spec("slam").inputs]  # odom, scan (scan matching), features
    with RecordingWriter(tmp_path / "odom_features.mcap") as writer:
        for path in (sim_recording, tmp_path / "f.mcap"):
            for r in read_recording(path, slam_inputs):
                writer.write(r.topic, r.schema, r.data, r.stamp_ns, r.receive_ns, r.sequence)
    replay(services.spec("slam"), cfg("slam"), ROBOT, tmp_path / "odom_features.mcap", tmp_path / "s.mcap")

    for topic, path in (("scan/filtered", "d.mcap"), ("features", "f.mcap"), ("slam/state", "s.mcap")):
        assert payloads(tmp_path / "all.mcap", topic) == payloads(tmp_path / path, topic), topic


def test_stage_outputs_replace_the_inputs_copies(sim_recording, tmp_path):
    first = tmp_path / "first.mcap"
    run_pipeline(default_stages(), ROBOT, sim_recording, first)
    again = tmp_path / "again.mcap"
    counts = run_pipeline(default_stages(("features", "slam")), ROBOT, first, again)
    assert counts["input"]["dropped"] == 2 * N_SCANS + 3   # the old features, slam/state and slam/map
    assert Counter(r.topic for r in read_recording(again))["features"] == N_SCANS
    assert payloads(again, "slam/state") == payloads(first, "slam/state")


def test_bad_input_is_counted_and_skipped(tmp_path):
    path = tmp_path / "bad.mcap"
    with RecordingWriter(path) as writer:
        for seq, n_beams in enumerate((181, 1, 181), start=1):
            write(writer, topics.SCAN, t.LaserScan.from_ranges(T0_NS + seq, seq, np.full(n_beams, 2.0),
                                                              -np.pi / 2, np.pi / 180))
    counts = run_pipeline(default_stages(("denoise", "features")), ROBOT, path, None)
    assert counts["denoise"]["error.input"] == 1
    assert counts["denoise"]["out.scan/filtered"] == counts["features"]["out.features"] == 2


def test_stage_names_and_sets():
    assert stage_names("slam, denoise") == ("denoise", "slam")
    for bad in ("sensor", "recorder", "denoise,nope", "", "slam,slam"):
        with pytest.raises(ConfigError):
            stage_names(bad)
    assert config_mod.by_service(["features.mode=paper", "slam.ekf.gate_assoc_chi2=4"], ("features", "slam")) == {
        "features": ["mode=paper"], "slam": ["ekf.gate_assoc_chi2=4"]}
    with pytest.raises(ConfigError):
        config_mod.by_service(["mode=paper"], ("features",))
    with pytest.raises(ConfigError):
        config_mod.by_service(["slam.ekf.gate_assoc_chi2=4"], ("features",))


def test_cli_layers_stage_settings(sim_recording, tmp_path, monkeypatch):
    monkeypatch.setenv("LRFSLAM_BUS_ROBOT", "fromenv")
    out = tmp_path / "cli.mcap"
    assert pipeline.main(["--replay", str(sim_recording), "--out", str(out), "--stages", "denoise,features",
                          "--set", "features.mode=paper", "-q"]) == 0
    meta = read_metadata(out)["lrfslam"]
    assert meta["robot"] == "fromenv" and meta["stages"] == "denoise,features"
    assert '"mode": "paper"' in meta["config.features"] and '"mode": "default"' in meta["config.denoise"]
    assert "slam/state" not in {r.topic for r in read_recording(out)}
    assert pipeline.main(["--replay", str(sim_recording), "--stages", "sensor"]) == 2
    assert pipeline.main(["--replay", str(sim_recording), "--set", "features.mode=nonsense"]) == 2
