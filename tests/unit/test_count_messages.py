"""Counting a recording's messages from its summaries agrees with reading every message, also for a
segment whose writer was killed (no summary: read through)."""

from __future__ import annotations

import shutil
from collections import Counter
from pathlib import Path

from lrfslam.runtime.recording import (
    INDEXED,
    ReadReport,
    RecordingWriter,
    count_messages,
    read_recording,
)

GOLDEN = Path(__file__).resolve().parents[1] / "data" / "golden"


def test_counts_from_the_summary_equal_a_full_read(tmp_path):
    folder = tmp_path / "run"
    folder.mkdir()
    shutil.copy(GOLDEN / "intel_150.pipeline.mcap", folder / "run_0.mcap")
    with RecordingWriter(tmp_path / "small_chunks.mcap", chunk_size_bytes=4096) as writer:
        for m in read_recording(GOLDEN / "sim_head.pipeline.mcap"):
            writer.write(m.topic, m.schema, m.data, m.stamp_ns, m.receive_ns, m.sequence)
    whole = (tmp_path / "small_chunks.mcap").read_bytes()
    # A second segment cut in the middle, as a killed writer leaves it: no summary, no footer.
    (folder / "run_1.mcap").write_bytes(whole[: len(whole) // 2])
    report = ReadReport()
    counted = count_messages(folder, report)
    assert counted == Counter(m.topic for m in read_recording(folder))
    assert counted["slam/state"] > 150 and counted["slam/map"] > 7   # both segments counted
    first, second = report.segments
    assert first.state == INDEXED and first.messages == sum(Counter(
        m.topic for m in read_recording(folder / "run_0.mcap")).values())
    assert second.state != INDEXED and 0 < second.messages < sum(Counter(
        m.topic for m in read_recording(GOLDEN / "sim_head.pipeline.mcap")).values())
