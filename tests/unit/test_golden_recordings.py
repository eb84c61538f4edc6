"""The offline commands give the same bytes as the golden recordings in tests/data/golden/.

Each command of tests/data/golden/README.md is run again, in process, on the committed
inputs (or on the committed output of an earlier command), and its output file must equal
the committed one byte for byte: replay is deterministic and the recordings were made
before the offline drivers became one chain.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from lrfslam import cli

GOLDEN = Path(__file__).resolve().parents[1] / "data" / "golden"
# The goldens predate the mapper stage; they pin the stages they were made with.
EKF_STAGES = "denoise,features,slam"

# (output, input, command before the --replay/--out arguments, extra arguments)
COMMANDS = [
    (f"{name}.{what}.mcap", f"{name}.{source}.mcap" if source else f"{name}.mcap", command, extra)
    for name in ("intel_150", "sim_head")
    for what, source, command, extra in (
        ("pipeline", "", ["pipeline"], ["-q", "--stages", EKF_STAGES]),
        ("denoise", "", ["denoise"], []),
        ("features", "denoise", ["features"], []),
        ("slam", "pipeline", ["slam"], []),
    )
] + [
    ("sim_head.paper_odometry.mcap", "sim_head.mcap", ["pipeline"],
     ["-q", "--stages", EKF_STAGES, "--set", "features.mode=paper", "--set", "denoise.mode=paper", "--set", "slam.scan_matching=false"]),
]


@pytest.mark.parametrize("out, source, command, extra", COMMANDS, ids=[c[0] for c in COMMANDS])
def test_replay_reproduces_the_golden_recording(out, source, command, extra, tmp_path, monkeypatch):
    for name in ("LRFSLAM_BUS_ROBOT", "LRFSLAM_LOG_LEVEL"):
        monkeypatch.delenv(name, raising=False)
    # The input's name goes into the output's metadata, so it keeps its name here.
    shutil.copy(GOLDEN / source, tmp_path / source)
    argv = [*command, "--replay", str(tmp_path / source), "--out", str(tmp_path / out), *extra]
    assert cli.main(argv) == 0
    assert (tmp_path / out).read_bytes() == (GOLDEN / out).read_bytes(), out
