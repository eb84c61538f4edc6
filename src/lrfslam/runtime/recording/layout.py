"""What a recording is: its files' naming, its time layout, a message as stored."""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

PROFILE = "lrfslam"

#: Anything a reader takes: one file, a recording folder, or several of them (read as one stream).
RecordingSource = str | os.PathLike | Sequence[str | os.PathLike]

#: Segment files of a recording folder: ``<name>_<n>.mcap``.
SEGMENT = re.compile(r"^(?P<stem>.+)_(?P<index>\d+)\.mcap$")

#: The metadata record that says what a file's times are: ``{"log_time": RECEIVE or STAMP, "publish_time": STAMP}``.
TIMES = "lrfslam.times"
#: ``log_time`` is the recorder's wall clock on receipt (a live recording).
RECEIVE = "receive"
#: The data stamp (``publish_time`` always; ``log_time`` too where no receive time exists: offline outputs).
STAMP = "stamp"
#: A file without :data:`TIMES`: ``log_time`` the data stamp, ``publish_time`` the receive time.
OLD_LAYOUT = "old"

@dataclass(frozen=True)
class RecordedMessage:
    """One message as stored: relative topic, schema name, payload, times in ns.

    ``log_time_ns`` and ``publish_time_ns`` are the file's fields as written; ``stamp_ns`` is
    the data stamp and ``receive_ns`` the recorder's receive time (0 where the file has
    none: an offline output), whichever field of the file's layout holds them.
    """

    topic: str
    schema: str
    data: bytes
    log_time_ns: int
    publish_time_ns: int
    sequence: int
    stamp_ns: int
    receive_ns: int



def segment_path(folder: str | Path, name: str, index: int) -> Path:
    """``<folder>/<name>_<index>.mcap``."""
    return Path(folder) / f"{name}_{index}.mcap"


def segment_index(path: Path) -> int | None:
    """The number of a segment file, None if the name is not ``<name>_<n>.mcap``."""
    m = SEGMENT.match(path.name)
    return int(m["index"]) if m else None

