"""``lrfslam recover IN.mcap -o OUT.mcap``: a finished, indexed copy of a recording whose writer was killed.

A recorder killed with SIGKILL (or a power cut) leaves its file without the
summary: every complete chunk is there, but the ``mcap`` library's default
reader refuses the file. This reads IN record by record up to its first damaged
one (the chunk being written when the writer died) and writes everything before
it — header, schemas, channels, metadata, messages — into OUT with a summary and
index. OUT must not exist (nothing is overwritten) and appears only once complete.
Exit status 0 when OUT was written (what was left out is printed), 2 when not.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from lrfslam.errors import RecordingError
from lrfslam.runtime.recording import recover


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lrfslam recover", description=__doc__.splitlines()[0])
    parser.add_argument("input", type=Path, metavar="IN.mcap", help="the damaged (or any) MCAP file")
    parser.add_argument("-o", "--out", type=Path, required=True, metavar="OUT.mcap", help="the file to write (new)")
    args = parser.parse_args(argv)
    try:
        report = recover(args.input, args.out)
    except RecordingError as exc:
        print(f"lrfslam recover: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {args.out}: {report.messages} messages on {report.channels} channels")
    if report.complete:
        print(f"{args.input} was read to its end; nothing was lost")
        return 0
    lost = report.total_bytes - report.read_bytes
    if lost:
        print(f"{args.input} ends in a damaged record at byte {report.read_bytes} ({report.reason}); "
              f"its last {lost} bytes (the chunk being written when its writer stopped) were left out")
    else:
        print(f"{args.input} had no end (its writer stopped after its last complete chunk); nothing was left out")
    return 0
