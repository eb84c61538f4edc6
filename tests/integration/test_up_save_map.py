"""``lrfslam up --save-map MAP/``: the run's map saved once the recorder has closed its file."""

from __future__ import annotations

import socket
import subprocess
import sys

import numpy as np
import pytest

from lrfslam.msgs import topics
from lrfslam.runtime.recording import read_recording
from lrfslam.runtime.saved_map import load_map

pytestmark = [pytest.mark.integration, pytest.mark.slow]   # lrfslam up end to end: the slow step


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
