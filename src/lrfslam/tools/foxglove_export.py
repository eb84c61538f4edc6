"""``lrfslam export RECORDING --foxglove OUT.mcap``: a copy of a recording that opens in Foxglove as a map.

Every message is copied as recorded (same channels, schemas, metadata, data stamps and
receive times), and Foxglove's views of them (lrfslam/viz/foxglove.py, docs/monitoring.md)
are added at the same times, so a recording made before the recorder wrote them opens in
Foxglove or Lichtblick as a map too. The copy follows MCAP's times (lrfslam/runtime/recording.py)
whatever the input's layout: a recording's receive times go to ``log_time`` (the timeline
Foxglove plays, as the recorder would have written the views live), an offline output's
data stamps to both fields (its timeline is data time). Views already in the input are made anew, not copied. A
message whose payload does not decode is copied without a view and counted.
"""

from __future__ import annotations

import sys
from collections import Counter
from pathlib import Path

from lrfslam.errors import InputError, RecordingError
from lrfslam.msgs import topics
from lrfslam.runtime.outputs import atomic_output
from lrfslam.runtime.recording import (
    STAMP,
    ReadReport,
    RecordingSource,
    RecordingWriter,
    describe_source,
    read_metadata,
    read_recording,
    recording_files,
    time_layout,
)
from lrfslam.viz.foxglove import FoxgloveViews, ViewConfig, schema_sets


def add_views(source: RecordingSource, out: str | Path, cfg: ViewConfig | None = None) -> Counter:
    """Write ``out``: the recording ``source`` (file, folder or files) with Foxglove's views added.

    Returns
    -------
    Counter
        ``copied`` messages, ``views`` added, ``replaced`` views of the input left out,
        ``undecodable`` messages copied without a view, ``truncated`` (1) if an input file was unfinished.

    Raises
    ------
    RecordingError
        ``source`` is no recording, or ``out`` is one of its files (checked before anything is written).
    """
    files = recording_files(source)
    out = Path(out)
    if out.exists() and any(out.resolve() == f.resolve() for f in files):
        raise RecordingError(f"{out} is the input; give the copy another name")
    metadata = read_metadata(source)
    metadata["lrfslam.foxglove"] = {"views_of": describe_source(source)}
    views = FoxgloveViews(cfg)
    counts: Counter = Counter()
    report = ReadReport()
    # An older recording's publish_time holds its receive times (an offline output's: the stamps again).
    received = time_layout(files[0]) != STAMP
    with atomic_output(out) as partial, RecordingWriter(partial, metadata, extra_schemas=schema_sets(),
                                                        receive_times=received) as writer:
        for rec in read_recording(source, report=report):
            if topics.is_foxglove(rec.topic):
                counts["replaced"] += 1
                continue
            writer.write(rec.topic, rec.schema, rec.data, rec.stamp_ns, rec.receive_ns, rec.sequence)
            counts["copied"] += 1
            try:
                made = views.from_payload(rec.topic, rec.schema, rec.data, rec.stamp_ns)
            except InputError:
                counts["undecodable"] += 1
                continue
            for view in made:
                writer.write(view.topic, view.schema, view.encode(), view.stamp_ns, rec.receive_ns)
                counts["views"] += 1
    if report.truncated:
        counts["truncated"] = 1
    return counts


def main(recording: list[Path], out: Path) -> int:
    """Run :func:`add_views` and say what it did; 0 when ``out`` was written."""
    source = recording[0] if len(recording) == 1 else recording
    counts = add_views(source, out)
    print(f"wrote {out}: {counts['copied']} messages copied, {counts['views']} Foxglove views added")
    notes = []
    if counts["replaced"]:
        notes.append(f"{counts['replaced']} views of the input made anew")
    if counts["undecodable"]:
        notes.append(f"{counts['undecodable']} undecodable messages copied without a view")
    if counts["truncated"]:
        notes.append("an input file was unfinished: its complete chunks were read")
    if notes:
        print(f"lrfslam export: {'; '.join(notes)}", file=sys.stderr)
    return 0
