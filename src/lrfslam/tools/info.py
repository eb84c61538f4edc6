"""``lrfslam info RECORDING``: topics, schemas, message counts, rates and duration of a recording.

RECORDING is a file, a recording folder (its segments ``<name>_<n>.mcap``) or
several files, read as one stream. Each file that was not finished (its writer
was killed) is named with the ``lrfslam recover`` command that makes it an
indexed file again.

Two clocks, never mixed: the *duration* is the span of the recorder's receive
times (MCAP log time; in a recording older than that convention, publish time: wall
time of the run; an offline output has none and gives its data stamps); *data time* is
the span of the data stamps (MCAP publish time, in older recordings log time), which
run faster than wall time under a simulator speedup. A topic's rate is its messages per second between its first and last
one: data topics' on the data stamps, health topics' (stamped with each
service's wall clock) and their Foxglove log on the receive clock.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections import defaultdict
from pathlib import Path

from lrfslam.errors import DecodeError, RecordingError
from lrfslam.msgs import topics
from lrfslam.runtime.recording import (
    TRUNCATED,
    UNINDEXED,
    ReadReport,
    RecordingSource,
    SegmentReport,
    read_metadata,
    read_recording,
    recording_files,
)

#: Metadata of an imported log that says what the laser is (see lrfslam.tools.importers).
SENSOR_KEYS = (("beams", "beams"), ("no_return_m", "no return (m)"), ("no_return_from", "  from"),
               ("laser_mount", "laser mount (x m, y m, theta rad)"))


def laser_lines(first_scan: tuple[bytes, str] | None, metadata: dict[str, dict[str, str]]) -> list[str]:
    """What the recording says of its laser: the first scan's layout and the importer's facts."""
    lines = []
    if first_scan is not None:
        try:
            scan = topics.SCAN.codec.decode(*first_scan)
        except DecodeError as exc:
            lines.append(f"laser:     first scan does not decode ({exc})")
        else:
            n = scan.ranges_m.size
            last = scan.angle_min_rad + (n - 1) * scan.angle_increment_rad
            lines.append(f"laser:     {n} beams, {math.degrees(scan.angle_increment_rad):.2f} deg apart, "
                         f"{math.degrees(scan.angle_min_rad):+.1f} to {math.degrees(last):+.1f} deg, "
                         f"range max {scan.range_max_m:.2f} m, source {scan.source or '-'}")
    facts = metadata.get("lrfslam", {})
    lines += [f"           {label}: {facts[key] or '-'}" for key, label in SENSOR_KEYS if key in facts]
    return lines


def recover_command(path: Path) -> str:
    """The command that rewrites ``path`` as an indexed file beside it (a name the folder reader skips)."""
    return f"lrfslam recover {path} -o {path.with_name(path.stem + '.recovered.mcap')}"


def state_note(seg: SegmentReport) -> str:
    """What a file's state asks of the user ("" for a finished, indexed file)."""
    if seg.state == TRUNCATED:
        return f"NOT FINISHED (its writer was killed?): {recover_command(seg.path)}"
    if seg.state == UNINDEXED:
        return f"not indexed (its writer stopped on a write error); an indexed copy: {recover_command(seg.path)}"
    return ""


def segment_lines(report: ReadReport, indent: str = "  ") -> list[str]:
    """One line per file read: name, size, messages, and what to do if it was not finished."""
    width = max(len(str(seg.path)) for seg in report.segments)
    return [f"{indent}{str(seg.path).ljust(width)}  {seg.path.stat().st_size / 1e6:8.2f} MB  {seg.messages:>7} msgs"
            + (f"  {note}" if (note := state_note(seg)) else "") for seg in report.segments]


def describe(source: RecordingSource) -> str:
    """Everything ``lrfslam info`` prints about the recording ``source`` (file, folder or files)."""
    files = recording_files(source)
    report = ReadReport()
    # per (topic, schema): count, first/last data stamp, first/last receive time (the stamp where none)
    stats: dict[tuple[str, str], list[int]] = defaultdict(lambda: [0, 2**63, 0, 2**63, 0])
    first_scan = None
    received_any = False
    for m in read_recording(files, report=report):
        if first_scan is None and m.topic == topics.SCAN.name:
            first_scan = (m.data, m.schema)
        s = stats[(m.topic, m.schema)]
        s[0] += 1
        received = m.receive_ns or m.stamp_ns
        received_any = received_any or m.receive_ns > 0
        s[1], s[2] = min(s[1], m.stamp_ns), max(s[2], m.stamp_ns)
        s[3], s[4] = min(s[3], received), max(s[4], received)
    size = sum(p.stat().st_size for p in files)
    if isinstance(source, (str, os.PathLike)) and Path(source).is_file():
        lines = [f"file:      {source} ({size / 1e6:.2f} MB)"]
        seg = report.segments[0]
        if note := state_note(seg):
            lines.append(f"WARNING:   {note}")
        if seg.state == TRUNCATED:
            lines.append(f"           ({seg.reason}; its complete chunks were read)")
    else:
        name = source if isinstance(source, (str, os.PathLike)) else ", ".join(map(str, source))
        lines = [f"recording: {name} ({len(files)} file{'s' * (len(files) > 1)}, {size / 1e6:.2f} MB)",
                 *segment_lines(report)]
    if not stats:
        return "\n".join([*lines, "no messages"])
    duration = span(stats.values(), 3)
    data = [s for (topic, _), s in stats.items() if not topics.on_wall_clock(topic)]
    data_time = span(data, 1) if data else 0.0
    ratio = f"; {data_time / duration:.2f} × the duration" if data and duration > 0 else ""
    clock = ("receive clock: first to last message received" if received_any
             else "an offline output, no receive times: first to last data stamp")
    lines += [f"duration:  {duration:.2f} s ({clock})",
              f"data time: {data_time:.2f} s (data stamps: first to last{ratio})" if data
              else "data time: no data topics",
              f"messages:  {sum(s[0] for s in stats.values())}"]
    lines += laser_lines(first_scan, read_metadata(files))
    lines.append("")
    width = max(len(t) for t, _ in stats)
    lines.append(f"{'topic'.ljust(width)}  {'count':>7}  {'rate_hz':>8}  {'clock':<7}  schema")
    for (topic, schema), s in sorted(stats.items()):
        clock, seconds = ("receive", span([s], 3)) if topics.on_wall_clock(topic) else ("data", span([s], 1))
        rate = (s[0] - 1) / seconds if seconds > 0 else 0.0
        lines.append(f"{topic.ljust(width)}  {s[0]:>7}  {rate:>8.2f}  {clock:<7}  {schema or '<none>'}")
    return "\n".join(lines)


def span(stats, first: int) -> float:
    """Seconds from the earliest of ``stats``' times at index ``first`` to the latest at ``first + 1``."""
    return (max(s[first + 1] for s in stats) - min(s[first] for s in stats)) / 1e9


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lrfslam info", description=__doc__.splitlines()[0])
    parser.add_argument("recording", nargs="+", type=Path, metavar="RECORDING",
                        help="an MCAP file, a recording folder, or several files (one stream)")
    args = parser.parse_args(argv)
    try:
        print(describe(args.recording[0] if len(args.recording) == 1 else args.recording))
    except RecordingError as exc:
        print(f"lrfslam info: error: {exc}", file=sys.stderr)
        return 2
    return 0
