"""python -m lrfslam.evaluation.ros2_roundtrip: a log as a ROS 2 robot's stream reaches the pipeline.

Oracle: the log read directly. Scans differ only by float32 rounding of returns (a ROS LaserScan's
ranges are float32), odometry by nothing beyond double rounding, and nothing else changes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lrfslam.algo.geometry import wrap_angle
from lrfslam.evaluation.ros2_roundtrip import main, through_ros2
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.runtime.recording import read_metadata, read_recording

GOLDEN = Path(__file__).resolve().parents[1] / "data" / "golden" / "intel_150.mcap"


def decoded(messages) -> list[tuple[str, object]]:
    return [(m.topic, topics.by_name(m.topic).codec.decode(m.data, m.schema)) for m in messages]


def test_a_log_through_ros2_keeps_its_scans_and_odometry_within_float32_rounding(tmp_path, capsys):
    out = tmp_path / "ros2.mcap"
    assert main([str(GOLDEN), "-o", str(out)]) == 0
    assert read_metadata(out)["lrfslam"] == read_metadata(GOLDEN)["lrfslam"]
    before, after = decoded(read_recording(GOLDEN)), decoded(read_recording(out))
    assert [topic for topic, _ in before] == [topic for topic, _ in after]
    assert {topic for topic, _ in before} == {"scan", "odom"}
    for (topic, ref), (_, got) in zip(before, after):
        assert got.stamp_ns == ref.stamp_ns
        if topic == "scan":
            valid = ref.status == t.BEAM_VALID
            assert np.array_equal(got.status == t.BEAM_VALID, valid)
            np.testing.assert_allclose(got.ranges_m[valid], ref.ranges_m[valid], rtol=2 ** -23)
            np.testing.assert_allclose(got.angles_rad, ref.angles_rad, rtol=1e-6, atol=1e-7)
        else:
            np.testing.assert_allclose(got.pose[:2], ref.pose[:2], atol=1e-12)
            assert wrap_angle(got.pose[2] - ref.pose[2]) == pytest.approx(0.0, abs=1e-12)
    # Never over an existing file.
    with pytest.raises(SystemExit):
        main([str(GOLDEN), "-o", str(out)])
    assert "not overwriting" in capsys.readouterr().err


def test_other_topics_pass_unchanged():
    """A pipeline's outputs beside the sensor's (features, states, health) are copied as they are."""
    messages = list(read_recording(GOLDEN.with_name("intel_150.pipeline.mcap")))
    others = [m for m in messages if m.topic not in ("scan", "odom")]
    assert others
    passed = [p for p in through_ros2(messages) if p[0] not in ("scan", "odom")]
    assert passed == [(m.topic, m.schema, m.data, m.stamp_ns, m.sequence) for m in others]
