"""``lrfslam info FILE.mcap``: topics, schemas, message counts, rates and duration of a recording."""

from __future__ import annotations

import argparse
import math
import sys
from collections import defaultdict
from pathlib import Path

from lrfslam.errors import DecodeError, RecordingError
from lrfslam.msgs import topics
from lrfslam.runtime.recording import ReadReport, read_metadata, read_recording

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


def describe(path: Path) -> str:
    report = ReadReport()
    stats: dict[tuple[str, str], list[int]] = defaultdict(lambda: [0, 2**63, 0])
    first_scan = None
    for m in read_recording(path, report=report):
        if first_scan is None and m.topic == topics.SCAN.name:
            first_scan = (m.data, m.schema)
        s = stats[(m.topic, m.schema)]
        s[0] += 1
        s[1] = min(s[1], m.log_time_ns)
        s[2] = max(s[2], m.log_time_ns)
    if not stats:
        return f"{path}: no messages" + (f" ({report.reason})" if report.truncated else "")
    start = min(s[1] for s in stats.values())
    end = max(s[2] for s in stats.values())
    duration = (end - start) / 1e9
    lines = [f"file:      {path} ({path.stat().st_size / 1e6:.2f} MB)",
             f"duration:  {duration:.2f} s", f"messages:  {sum(s[0] for s in stats.values())}"]
    if report.truncated:
        lines.append(f"WARNING:   not finished cleanly ({report.reason}); complete chunks were read")
    if not report.truncated:
        lines += laser_lines(first_scan, read_metadata(path))
    lines.append("")
    width = max(len(t) for t, _ in stats)
    lines.append(f"{'topic'.ljust(width)}  {'count':>7}  {'rate_hz':>8}  schema")
    for (topic, schema), (n, _, _) in sorted(stats.items()):
        rate = n / duration if duration > 0 else 0.0
        lines.append(f"{topic.ljust(width)}  {n:>7}  {rate:>8.2f}  {schema or '<none>'}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lrfslam info", description=__doc__)
    parser.add_argument("files", nargs="+", type=Path, metavar="FILE.mcap")
    args = parser.parse_args(argv)
    code = 0
    for path in args.files:
        try:
            print(describe(path))
        except RecordingError as exc:
            print(f"lrfslam info: error: {exc}", file=sys.stderr)
            code = 2
    return code
