"""Optional dependencies fail with one line naming the extra, not a traceback."""

import subprocess
import sys

import numpy as np
import pytest

from lrfslam.errors import ConfigError, MissingExtraError
from lrfslam.extras import require
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.runtime.recording import RecordingWriter


@pytest.fixture
def slam_recording(tmp_path):
    path = tmp_path / "states.mcap"
    with RecordingWriter(path) as writer:
        for k in range(3):
            state = t.SlamState(stamp_ns=k * 100_000_000, seq=k + 1, scan_seq=k + 1, pose=(0.1 * k, 0.0, 0.0),
                                pose_cov=np.eye(3) * 1e-4)
            writer.write(topics.SLAM_STATE.name, topics.SLAM_STATE.schema,
                         topics.SLAM_STATE.codec.encode(state), state.stamp_ns)
    return path


def test_an_installed_module_is_returned():
    assert require("json", "none", "a test").dumps([1]) == "[1]"


def test_a_missing_module_names_the_extra():
    with pytest.raises(MissingExtraError, match=r"pip install 'lrfslam\[plot\]'") as info:
        require("lrfslam_no_such_module", "plot", "the map picture")
    assert isinstance(info.value, ConfigError)


def test_export_without_matplotlib_writes_json_and_says_which_extra(tmp_path, slam_recording):
    # Block matplotlib in a child interpreter, as on an install without the [plot] extra.
    code = ("import sys; sys.modules['matplotlib'] = None; from lrfslam.tools import export; "
            f"sys.exit(export.main([{str(slam_recording)!r}, '-o', {str(tmp_path / 'out')!r}]))")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    assert run.returncode == 2
    assert "lrfslam[plot]" in run.stderr and "Traceback" not in run.stderr
    assert (tmp_path / "out" / "map.json").exists() and not (tmp_path / "out" / "map.png").exists()
