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
from lrfslam.runtime.recording import SegmentedWriter, read_recording

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


@pytest.mark.parametrize("as_files", [False, True], ids=["folder", "files"])
def test_a_split_recording_replays_as_the_single_file(as_files, tmp_path):
    """A golden recording cut into segments (a recording folder) reads, replays and exports as the file."""
    def split(golden: str, name: str) -> list[str]:
        writer = SegmentedWriter(tmp_path / name, name, chunk_size_bytes=2048, max_bytes=6000)
        for m in read_recording(GOLDEN / golden):
            writer.write(m.topic, m.schema, m.data, m.stamp_ns, m.receive_ns, m.sequence)
        writer.close()
        assert len(writer.segments) > 3
        return [str(p) for p in writer.segments] if as_files else [str(tmp_path / name)]

    source = split("sim_head.mcap", "run")
    argv = ["pipeline", "-q", "--stages", EKF_STAGES, "--replay", *source, "--out", str(tmp_path / "out.mcap")]
    assert cli.main(argv) == 0
    assert list(read_recording(tmp_path / "out.mcap")) == list(read_recording(GOLDEN / "sim_head.pipeline.mcap"))
    assert cli.main(["features", "--replay", *source, "--out", str(tmp_path / "f.mcap"), "--set", "mode=paper"]) == 0
    exported = split("sim_head.pipeline.mcap", "out")
    assert cli.main(["export", *exported, "-o", str(tmp_path / "a"), "--no-png"]) == 0
    assert cli.main(["export", str(GOLDEN / "sim_head.pipeline.mcap"), "-o", str(tmp_path / "b"), "--no-png"]) == 0
    assert (tmp_path / "a" / "map.json").read_text() == (tmp_path / "b" / "map.json").read_text()
