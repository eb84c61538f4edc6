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

What the importer reads from the log rather than guess (a first pass,
:func:`~lrfslam.io.carmen.survey`), stored in the recording's ``lrfslam``
metadata, printed, and shown by ``lrfslam info``:

* the "no return" code: the largest reading, when it repeats on many beams
  (Intel writes 81.83 m, ACES 50.0 m); ``--max-range-m`` overrides it;
* the beam layout: beams per line and the angles CARMEN implies for them;
* the laser's mounting on the robot: from the laser and odometry poses each line
  holds (or the ``robot_frontlaser_offset`` parameter). The ranges are measured
  from the laser, so the odometry is written for the laser too (odometry pose ⊕
  mounting): the pipeline estimates the laser's path, the frame in which the
  scans are consistent. Intel, ACES and MIT CSAIL mount it at the robot's centre.

Recordings are read back in log-time order, so a scan whose stamp runs backwards
is replayed at its stamp's place, with its own pose: the odometry stream stays
monotonic and consistent, but the motion between consecutive scans zigzags (on
Intel the file-order path of 508 m becomes 661 m in stamp order).
"""

from __future__ import annotations

import argparse
import math
import sys
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from decimal import Decimal
from pathlib import Path

import numpy as np
from tqdm import tqdm

from lrfslam.algo.geometry import compose
from lrfslam.errors import ConfigError, InputError, LrfSlamError
from lrfslam.io.carmen import (
    CarmenIssue,
    CarmenReader,
    LaserRecord,
    LaserSurvey,
    OdomRecord,
    flaser_beam_geometry,
    survey,
)
from lrfslam.io.textfile import open_log
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.runtime.bus import BusConfig
from lrfslam.runtime.outputs import atomic_output
from lrfslam.runtime.recording import RecordingWriter

IMPORTER = "lrfslam.tools.importers.carmen"

#: Malformed lines printed one by one before only their number is reported.
MAX_REPORTED_ISSUES = 20
#: Names of skipped messages listed in the summary (a binary file has thousands).
MAX_SKIPPED_NAMES = 5
#: The most of a bad line's text echoed to the terminal.
ECHO_CHARS = 80


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
    sensor : dict of str to str
        What the log says of its laser, as stored in the metadata: ``beams``,
        ``no_return_m`` and where it came from, ``laser_mount``.
    """

    scans: int
    odom: int
    skipped: dict[str, int] = field(default_factory=dict)
    issues: tuple[CarmenIssue, ...] = ()
    stamp_backsteps: int = 0
    sensor: dict[str, str] = field(default_factory=dict)


def sensor_facts(found: LaserSurvey, no_return_min_m: float | None) -> dict[str, str]:
    """The laser facts of a surveyed log, as the recording's metadata keeps them (text)."""
    layouts = []
    for n, lines in sorted(found.beam_counts.items()):
        try:
            start, step = flaser_beam_geometry(n)
            layouts.append(f"{n} beams at {math.degrees(step):.2f} deg from {math.degrees(start):+.1f} deg "
                           f"({lines} lines)")
        except InputError:
            layouts.append(f"{n} beams ({lines} lines)")
    if no_return_min_m is not None:
        no_return, source = no_return_min_m, "--max-range-m"
    elif found.no_return_m is not None:
        share = 100.0 * found.no_return_count / max(found.readings, 1)
        code = found.no_return_code_m
        exact = found.no_return_count == found.top_counts[code]
        band = "exactly this value" if exact else f"at or above it, round the code {code} m"
        no_return, source = found.no_return_m, f"the log: {share:.2f} % of readings are {band}"
    else:
        no_return, source = None, "none written; CARMEN's 80 m rule (ROBOTLASER: the line's maximum range)"
    mount = found.mount
    return {"beams": "; ".join(layouts) or "none",
            "no_return_m": "" if no_return is None else repr(float(no_return)),
            "no_return_from": source,
            "laser_mount": f"{mount[0]:.4f} {mount[1]:.4f} {mount[2]:.5f}"}


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
                  progress: bool = False, range_noise_m: float = 0.0, seed: int = 0) -> CarmenImport:
    """Convert the CARMEN log ``log_path`` (plain, .bz2 or .gz) into the recording ``out_path``.

    Parameters
    ----------
    log_path, out_path : path-like
        Input log and output MCAP file (overwritten).
    robot : str
        Robot namespace stored in the recording's metadata.
    no_return_min_m : float, optional
        Readings at or beyond this range (m) are "no return" (+inf); default: the
        code the log writes (:attr:`~lrfslam.io.carmen.LaserSurvey.no_return_m`),
        else as :class:`~lrfslam.io.carmen.CarmenReader` (80 m FLASER, the line's
        maximum range for ROBOTLASERk).
    on_issue : callable, optional
        Called with each malformed line as it is met (it is skipped either way).
    progress : bool
        Show a tqdm bar of lines read on stderr.
    range_noise_m, seed : float, int
        Standard deviation (m) of Gaussian noise added to every return (not to no-return or zero
        readings), drawn from ``seed``: a perturbation that must not matter, for
        ``lrfslam eval relations --trials``. 0: the ranges as logged.

    Returns
    -------
    CarmenImport
        Counts of what was written and skipped.

    Raises
    ------
    ConfigError
        ``robot`` or ``no_return_min_m`` is invalid.
    InputError
        The log holds no valid laser line (nothing is written).
    OSError
        The log cannot be read or the recording written.

    ``out_path`` appears only once the import has finished
    (:func:`~lrfslam.runtime.outputs.atomic_output`).
    """
    topics.check_robot(robot)
    if not range_noise_m >= 0.0:
        raise ConfigError(f"range_noise_m must be >= 0, got {range_noise_m}")
    rng = np.random.default_rng(seed)
    log_path = Path(log_path)
    issues: list[CarmenIssue] = []
    odom_lines = scans = backsteps = 0
    previous_ns: int | None = None
    with open_log(log_path) as lines:
        found = survey(lines)
    facts = sensor_facts(found, no_return_min_m)
    no_return = float(facts["no_return_m"]) if facts["no_return_m"] else None
    mount = found.mount
    mounted = bool(np.any(mount != 0.0))   # else the logged poses pass through bit for bit
    metadata = {"lrfslam": {"robot": robot, "importer": IMPORTER, "source_file": log_path.name, **facts}}
    with open_log(log_path) as lines, atomic_output(out_path) as partial, RecordingWriter(partial, metadata) as writer, \
            tqdm(desc=f"import {log_path.name}", unit=" lines", disable=not progress, file=sys.stderr) as bar:
        reader = CarmenReader(lines, no_return_min_m=no_return)
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
            ranges = item.ranges_m
            if range_noise_m:
                returns = np.isfinite(ranges) & (ranges > 0)
                noisy = np.maximum(ranges + rng.normal(0.0, range_noise_m, ranges.shape), 0.0)
                ranges = np.where(returns, noisy, ranges)
            scan = t.LaserScan.from_ranges(ns, scans, ranges, item.angle_min_rad,
                                           item.angle_increment_rad, item.max_range_m,
                                           source=f"carmen:{item.source}")
            odom = t.Odometry(stamp_ns=ns, seq=scans, pose=compose(item.odom_pose, mount) if mounted else item.odom_pose)
            for topic, value in ((topics.SCAN, scan), (topics.ODOM, odom)):
                writer.write(topic.name, topic.schema, topic.codec.encode(value), ns, ns, scans)
        bar.update(reader.lines_read - bar.n)
        skipped = Counter(reader.skipped)
        if odom_lines:
            skipped["ODOM"] += odom_lines
        if not scans:
            raise InputError(f"{log_path} holds no valid laser line (FLASER, RLASER, ROBOTLASERk): "
                             f"{len(issues)} malformed, skipped {skipped_text(skipped)}")
    return CarmenImport(scans, scans, dict(skipped), tuple(issues), backsteps, facts)


def printable(text: str, limit: int = ECHO_CHARS) -> str:
    """``text`` as one printable line of at most about ``limit`` characters (escaped, cut with '...')."""
    shown = text if text.isprintable() else repr(text)[1:-1]
    return shown if len(shown) <= limit else shown[:limit] + "..."


def skipped_text(skipped: dict[str, int]) -> str:
    """``"ODOM 12, PARAM 3, blank 1"``: the most frequent few names (printable, short), then how many more."""
    names = sorted(skipped.items(), key=lambda kv: (-kv[1], kv[0]))
    shown = ", ".join(f"{printable(name, 20) if name else 'blank'} {n}" for name, n in names[:MAX_SKIPPED_NAMES])
    if len(names) > MAX_SKIPPED_NAMES:
        rest = names[MAX_SKIPPED_NAMES:]
        shown += f" and {sum(n for _, n in rest)} lines of {len(rest)} other names"
    return f"{sum(skipped.values())} lines ({shown or 'none'})"


def _print_issue(count: list[int]) -> Callable[[CarmenIssue], None]:
    def report(issue: CarmenIssue) -> None:
        count[0] += 1
        if count[0] <= MAX_REPORTED_ISSUES:
            tqdm.write(f"line {issue.line_no}: malformed {printable(issue.message_type, 20) or 'line'}: "
                       f"{printable(issue.reason)} (skipped)", file=sys.stderr)
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
                        help="readings at or beyond this range (m) are 'no return' (default: the value the "
                             "log writes for it, found by a first pass; else 80 m for FLASER, the line's "
                             "maximum range for ROBOTLASER)")
    carmen.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    shown = [0]
    try:
        result = import_carmen(args.log, args.out, robot=args.robot, no_return_min_m=args.max_range_m,
                               on_issue=_print_issue(shown),
                               progress=not args.quiet and sys.stderr.isatty())
    except (LrfSlamError, OSError) as exc:
        print(f"lrfslam import: error: {exc}", file=sys.stderr)
        return 2
    finally:
        if shown[0] > MAX_REPORTED_ISSUES:
            print(f"... and {shown[0] - MAX_REPORTED_ISSUES} more malformed lines (skipped)", file=sys.stderr)
    print(f"{args.log} -> {args.out}: {result.scans} scans, {result.odom} odom, "
          f"skipped {skipped_text(result.skipped)}, "
          f"{len(result.issues)} malformed, {result.stamp_backsteps} backward stamps")
    sensor = result.sensor
    print(f"  laser: {sensor['beams']}; no return = {sensor['no_return_m'] or '-'} m "
          f"({sensor['no_return_from']}); mounted at {sensor['laser_mount']} (x m, y m, theta rad)")
    return 0
