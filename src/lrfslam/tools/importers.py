"""``lrfslam import carmen LOG -o FILE.mcap``: a CARMEN log as a recording in the project's schemas.

Each laser line (FLASER, RLASER, ROBOTLASERk) becomes one ``scan``
(:class:`~lrfslam.msgs.types.LaserScan`: "no return" as +inf with status
BEAM_NO_RETURN, ``source`` ``"carmen:<message>"``) and one ``odom``
(:class:`~lrfslam.msgs.types.Odometry`) holding the robot odometry pose logged
on that same line, at the same stamp. ``stamp_ns`` is the line's ipc timestamp
(exactly: the decimal as logged, in ns) and is also the MCAP log time; ``seq``
counts laser lines from 1 in file order. Messages are written in file order.

Why the odometry comes from the laser lines and not from the ODOM lines: the
slam service interpolates odometry at each scan's stamp and drops odometry whose
stamp does not increase. In the Intel log the laser stamps step backwards 631
times and the ODOM stamps 602 times, on different lines, so the two streams
disagree with each other by up to 0.9 s. The pose on a laser line is by
construction the robot pose at that scan, so a reader gets, for every scan stamp,
exactly its pose; ODOM lines are counted and left out.

Recordings are read back in log-time order, so a scan whose stamp runs backwards
is replayed at its stamp's place, with its own pose: the odometry stream stays
monotonic and consistent, but the motion between consecutive scans zigzags (on
Intel the file-order path of 508 m becomes 661 m in stamp order).
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from decimal import Decimal
from pathlib import Path

from tqdm import tqdm

from lrfslam.errors import LrfSlamError
from lrfslam.io.carmen import CarmenIssue, CarmenReader, LaserRecord, OdomRecord
from lrfslam.io.textfile import open_log
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.runtime.bus import BusConfig
from lrfslam.runtime.recording import RecordingWriter

IMPORTER = "lrfslam.tools.importers.carmen"

#: Malformed lines printed one by one before only their number is reported.
MAX_REPORTED_ISSUES = 20


@dataclass(frozen=True)
class CarmenImport:
    """What :func:`import_carmen` wrote and skipped.

    Attributes
    ----------
    scans, odom : int
        Messages written on ``scan`` and ``odom`` (one of each per laser line).
    skipped : dict of str to int
        Lines not turned into messages, by message name: the ODOM lines (see the
        module docstring), message types the parser ignores, ``"#"`` comments,
        ``""`` blank lines.
    issues : tuple of CarmenIssue
        Malformed lines (skipped), in file order.
    stamp_backsteps : int
        Laser lines whose stamp is earlier than the previous laser line's.
    """

    scans: int
    odom: int
    skipped: dict[str, int] = field(default_factory=dict)
    issues: tuple[CarmenIssue, ...] = ()
    stamp_backsteps: int = 0


def stamp_ns(stamp_s: float) -> int:
    """Nanoseconds of a logged stamp (s), exact for the decimal the log printed.

    ``round(stamp_s * 1e9)`` would be off by up to ~100 ns at Unix-epoch stamps
    (1e18 ns exceeds double precision); the shortest repr of the parsed float is
    the logged decimal, so scaling it as a Decimal is exact and converts back to
    the same float.
    """
    return int(Decimal(repr(float(stamp_s))).scaleb(9).to_integral_value())


def import_carmen(log_path: str | Path, out_path: str | Path, *, robot: str = BusConfig.robot,
                  no_return_min_m: float | None = None,
                  on_issue: Callable[[CarmenIssue], None] | None = None,
                  progress: bool = False) -> CarmenImport:
    """Convert the CARMEN log ``log_path`` (plain, .bz2 or .gz) into the recording ``out_path``.

    Parameters
    ----------
    log_path, out_path : path-like
        Input log and output MCAP file (overwritten).
    robot : str
        Robot namespace stored in the recording's metadata.
    no_return_min_m : float, optional
        Readings at or beyond this range (m) are "no return" (+inf); default as
        :class:`~lrfslam.io.carmen.CarmenReader` (80 m FLASER, the line's maximum
        range for ROBOTLASERk).
    on_issue : callable, optional
        Called with each malformed line as it is met (it is skipped either way).
    progress : bool
        Show a tqdm bar of lines read on stderr.

    Returns
    -------
    CarmenImport
        Counts of what was written and skipped.

    Raises
    ------
    ConfigError
        ``robot`` or ``no_return_min_m`` is invalid.
    OSError
        The log cannot be read or the recording written.
    """
    topics.check_robot(robot)
    log_path = Path(log_path)
    issues: list[CarmenIssue] = []
    odom_lines = scans = backsteps = 0
    previous_ns: int | None = None
    metadata = {"lrfslam": {"robot": robot, "importer": IMPORTER, "source_file": log_path.name,
                            "no_return_min_m": "" if no_return_min_m is None else repr(no_return_min_m)}}
    with open_log(log_path) as lines, RecordingWriter(out_path, metadata) as writer, \
            tqdm(desc=f"import {log_path.name}", unit=" lines", disable=not progress, file=sys.stderr) as bar:
        reader = CarmenReader(lines, no_return_min_m=no_return_min_m)
        for item in reader:
            bar.update(reader.lines_read - bar.n)
            if isinstance(item, OdomRecord):
                odom_lines += 1
                continue
            if isinstance(item, LaserRecord) and item.stamp_s < 0:
                # MCAP log times are unsigned; such a line cannot keep its stamp.
                item = CarmenIssue(item.line_no, item.source, f"negative timestamp {item.stamp_s}")
            if isinstance(item, CarmenIssue):
                issues.append(item)
                if on_issue is not None:
                    on_issue(item)
                continue
            scans += 1
            ns = stamp_ns(item.stamp_s)
            if previous_ns is not None and ns < previous_ns:
                backsteps += 1
            previous_ns = ns
            scan = t.LaserScan.from_ranges(ns, scans, item.ranges_m, item.angle_min_rad,
                                           item.angle_increment_rad, item.max_range_m,
                                           source=f"carmen:{item.source}")
            odom = t.Odometry(ns, scans, item.odom_pose)
            for topic, value in ((topics.SCAN, scan), (topics.ODOM, odom)):
                writer.write(topic.name, topic.schema, topic.codec.encode(value), ns, ns, scans)
        bar.update(reader.lines_read - bar.n)
        skipped = Counter(reader.skipped)
    if odom_lines:
        skipped["ODOM"] += odom_lines
    return CarmenImport(scans, scans, dict(skipped), tuple(issues), backsteps)


def _print_issue(count: list[int]) -> Callable[[CarmenIssue], None]:
    def report(issue: CarmenIssue) -> None:
        count[0] += 1
        if count[0] <= MAX_REPORTED_ISSUES:
            tqdm.write(f"line {issue.line_no}: malformed {issue.message_type or 'line'}: {issue.reason} (skipped)",
                       file=sys.stderr)
    return report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lrfslam import", description="Convert a log into a recording.")
    formats = parser.add_subparsers(dest="format", required=True, metavar="FORMAT")
    carmen = formats.add_parser("carmen", help="CARMEN log (.clf, plain, .bz2 or .gz)",
                                description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    carmen.add_argument("log", metavar="LOG", help="CARMEN log file")
    carmen.add_argument("-o", "--out", required=True, metavar="FILE.mcap", help="recording to write")
    carmen.add_argument("--robot", default=BusConfig.robot, help="robot namespace stored in the metadata")
    carmen.add_argument("--max-range-m", type=float, default=None, dest="max_range_m",
                        help="readings at or beyond this range (m) are 'no return' "
                             "(default 80 m for FLASER, the line's maximum range for ROBOTLASER)")
    carmen.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    shown = [0]
    try:
        result = import_carmen(args.log, args.out, robot=args.robot, no_return_min_m=args.max_range_m,
                               on_issue=_print_issue(shown),
                               progress=not args.quiet and sys.stderr.isatty())
    except (LrfSlamError, OSError) as exc:
        print(f"lrfslam import: {exc}", file=sys.stderr)
        return 2
    if shown[0] > MAX_REPORTED_ISSUES:
        print(f"... and {shown[0] - MAX_REPORTED_ISSUES} more malformed lines (skipped)", file=sys.stderr)
    skipped = ", ".join(f"{name or 'blank'} {n}" for name, n in sorted(result.skipped.items()))
    print(f"{args.log} -> {args.out}: {result.scans} scans, {result.odom} odom, "
          f"{sum(result.skipped.values())} lines skipped ({skipped or 'none'}), "
          f"{len(result.issues)} malformed, {result.stamp_backsteps} backward stamps")
    return 0
