"""``lrfslam up --save-map MAP/``: the run's map saved once the recorder has closed its file."""

from __future__ import annotations

import socket
import subprocess
import sys

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from lrfslam.algo.geometry import relative
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.runtime.recording import read_recording
from lrfslam.runtime.saved_map import load_map
from lrfslam.viz import foxglove as fx

pytestmark = [pytest.mark.integration, pytest.mark.slow]   # lrfslam up end to end: the slow step


def run_on_saved_map(tmp_path, mapping_robot: str, robot: str) -> tuple[list, dict]:
    """The ``map/pose`` messages of robot ``robot``'s run, and the truth of its scans in the saved map's
    frame: the mapping run's (``mapping_robot``) slam frame, whose origin is where that run started."""
    (mapping,) = (tmp_path / "recordings").glob(f"*_{mapping_robot}")
    first = next(read_recording(mapping, [topics.TRUTH.name]))
    map_origin = topics.TRUTH.codec.decode(first.data, first.schema).pose
    (recording,) = (tmp_path / "recordings").glob(f"*_{robot}")
    truth = {}
    for m in read_recording(recording, [topics.TRUTH.name]):
        v = topics.TRUTH.codec.decode(m.data, m.schema)
        truth[v.stamp_ns] = relative(map_origin, v.pose)
    poses = [topics.MAP_POSE.codec.decode(m.data, m.schema) for m in read_recording(recording, [topics.MAP_POSE.name])]
    return poses, truth


def up_twice(tmp_path, first: list[str], second: list[str]) -> subprocess.CompletedProcess:
    """``lrfslam up`` for 30 s at speedup 4 with ``first``'s arguments, then with ``second``'s (both must
    end with exit 0); the second run's result."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    base = [sys.executable, "-m", "lrfslam.cli", "up", "--speedup", "4", "--port", str(port), "--quiet",
            "--duration", "30"]   # (a later --duration wins)
    for args in (first, second):
        res = subprocess.run([*base, *args], cwd=tmp_path, capture_output=True, text=True, timeout=180, check=False)
        assert res.returncode == 0, res.stderr[-3000:]
    return res


def test_up_saves_the_runs_map(tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    res = subprocess.run([sys.executable, "-m", "lrfslam.cli", "up", "--duration", "6", "--speedup", "4", "--port",
                          str(port), "--robot", "r8", "--quiet", "--save-map", "saved"],
                         cwd=tmp_path, capture_output=True, text=True, timeout=120, check=False)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "map: saved to saved/" in res.stdout
    (recording,) = (tmp_path / "recordings").glob("*_r8")
    saved = load_map(tmp_path / "saved")
    last = [topics.MAP_KEYFRAMES.codec.decode(m.data, m.schema)
            for m in read_recording(recording, [topics.MAP_KEYFRAMES.name])][-1]
    assert saved.manifest["source"]["recording"] == recording.name and saved.stamp_ns.size >= 5
    np.testing.assert_array_equal(saved.stamp_ns, last.scan_stamp_ns)
    np.testing.assert_array_equal(saved.map_pose, last.map_pose)
    assert saved.points_xy_m.shape[0] > 100 * saved.stamp_ns.size and saved.landmark_ids.size > 0


def test_up_localizes_in_a_saved_map_from_elsewhere(tmp_path):
    """Map the hallway with ``up --save-map``, then ``up --map --localize`` from 20 m further along
    its loop with other noise: the recording's ``map/pose`` says localized after a few metres, and
    every localized pose lies where the simulator's truth says, in the saved map's frame (the
    mapping run's slam frame: its origin is where that run started)."""
    up_twice(tmp_path, ["--robot", "m1", "--save-map", "saved"],
             ["--robot", "l1", "--map", "saved", "--localize", "--set", "sensor.start_m=20", "--set", "sensor.seed=7"])
    poses, truth = run_on_saved_map(tmp_path, "m1", "l1")
    (recording,) = (tmp_path / "recordings").glob("*_l1")
    localized = [p for p in poses if p.localization == 1]
    assert len(poses) > 400 and len(localized) > len(poses) / 2, (len(poses), len(localized))
    errors = [np.hypot(*(p.pose[:2] - truth[p.stamp_ns][:2])) for p in localized if p.stamp_ns in truth]
    assert errors and max(errors) < 0.5 and np.median(errors) < 0.15, (np.median(errors), max(errors))
    assert all(p.pose_cov is not None for p in localized)
    # Foxglove's view, recorded beside: "not localized" at the start, then "localized" with an ellipse.
    said = []
    for segment in sorted(recording.glob("*.mcap")):
        with open(segment, "rb") as f:
            for _, channel, _, scene in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
                    topics=[fx.LOCALIZATION]):
                said.append((scene.entities[0].texts[0].text, len(scene.entities[0].spheres)))
    assert said[0] == ("not localized", 0) and ("localized", 1) in said, said[:5]


def test_up_maps_on_from_a_saved_map_and_saves_it_grown(tmp_path):
    """Map 20 m of the hallway's 62 m loop with ``up --save-map`` (10 s at 0.5 m/s, speedup 4), then
    ``up --map`` (no ``--localize``) from 5 m along with other noise for 60 m, and ``--save-map``
    again: the run is found on the map, then maps on it where the simulator's truth is (in the saved
    map's frame), the rest of the loop included; the map saved holds every saved keyframe and the
    new part's, and says what it was grown from."""
    res = up_twice(tmp_path, ["--robot", "m1", "--save-map", "day0", "--duration", "10"],
                   ["--robot", "m2", "--map", "day0", "--save-map", "day1", "--set", "sensor.start_m=5",
                    "--set", "sensor.seed=9"])
    assert "map: saved to day1/" in res.stdout
    poses, truth = run_on_saved_map(tmp_path, "m1", "m2")
    (mapping,) = (tmp_path / "recordings").glob("*_m1")
    states = [p.localization for p in poses]
    assert t.MAPPING in states, states[-5:]
    found = states.index(t.MAPPING)
    assert set(states[:found]) <= {t.NOT_LOCALIZED} and set(states[found:]) == {t.MAPPING}
    errors = [np.hypot(*(p.pose[:2] - truth[p.stamp_ns][:2])) for p in poses[found:] if p.stamp_ns in truth]
    assert len(errors) > 200 and max(errors) < 0.5 and np.median(errors) < 0.15, (np.median(errors), max(errors))
    day0, day1 = load_map(tmp_path / "day0"), load_map(tmp_path / "day1")
    assert set(day0.stamp_ns.tolist()) <= set(day1.stamp_ns.tolist())
    # The loop's other 42 m are new: keyframes added there, and the grid grown.
    assert 1.5 * day0.stamp_ns.size < day1.stamp_ns.size < 5 * day0.stamp_ns.size, (day0.stamp_ns.size,
                                                                                  day1.stamp_ns.size)
    assert np.count_nonzero(day1.grid_cells == 0) > 1.5 * np.count_nonzero(day0.grid_cells == 0)
    assert day1.manifest["based_on"][0]["recording"] == mapping.name
    assert day1.landmark_ids.size >= day0.landmark_ids.size
    info = subprocess.run([sys.executable, "-m", "lrfslam.cli", "map", "info", "day1"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=60, check=True).stdout
    assert f"based on:  {mapping.name}" in info
