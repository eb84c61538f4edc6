"""Reading a file, a folder or several paths as one stream in data-stamp order, damaged files included."""

from __future__ import annotations

import heapq
import logging
import os
import struct
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO

from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader, make_reader
from mcap.records import Metadata
from mcap.stream_reader import StreamReader
from mcap.writer import MCAP0_MAGIC

from lrfslam.errors import RecordingError
from lrfslam.runtime.recording.layout import (
    OLD_LAYOUT,
    RECEIVE,
    STAMP,
    TIMES,
    RecordedMessage,
    RecordingSource,
    segment_index,
)

if TYPE_CHECKING:
    from lrfslam.runtime.recording.recover import RecoverReport

log = logging.getLogger(__name__)

#: How long (receive time, ns) the reader holds a message back to let one received later with
#: an earlier data stamp overtake it: the transport's jitter between topics is far below it.
REORDER_WINDOW_NS = 5_000_000_000

#: What the mcap library raises on a file without a valid end (it has no single base).
_PARSE_ERRORS = (McapError, ValueError, EOFError, struct.error)


def recording_files(source: RecordingSource) -> list[Path]:
    """The MCAP files of ``source`` in recording order.

    A folder stands for its segments ``<name>_<n>.mcap`` by number (other files
    in it, such as a recovered copy ``<name>_<n>.recovered.mcap``, are not part of
    the recording); files are taken as given, in the order given.

    Raises
    ------
    RecordingError
        A path does not exist, a folder holds no segment, or a file does not
        start as an MCAP file does (complete or not): checked before anything is read or written.
    """
    items = [source] if isinstance(source, (str, os.PathLike)) else list(source)
    if not items:
        raise RecordingError("no recording given")
    files: list[Path] = []
    for item in map(Path, items):
        if item.is_dir():
            segments = sorted((p for p in item.glob("*.mcap") if segment_index(p) is not None),
                              key=lambda p: (segment_index(p), p.name))
            if not segments:
                raise RecordingError(f"{item} holds no recording segments (<name>_<n>.mcap)")
            files += segments
        elif item.exists():
            files.append(item)
        else:
            raise RecordingError(f"recording {item} does not exist")
    for path in files:
        with open(path, "rb") as f:
            head = f.read(len(MCAP0_MAGIC))
        if head != MCAP0_MAGIC:
            raise RecordingError(f"{path} is not an MCAP recording ({'empty' if not head else 'no MCAP magic'})")
    return files


def describe_source(source: RecordingSource) -> str:
    """A short name of ``source`` for logs and metadata: the path, or the paths joined by commas."""
    items = [source] if isinstance(source, (str, os.PathLike)) else list(source)
    return ",".join(Path(p).name for p in items)




INDEXED, UNINDEXED, TRUNCATED = "indexed", "unindexed", "truncated"


@dataclass
class SegmentReport:
    """What reading one file found: its state (indexed, unindexed, truncated), messages read, why."""

    path: Path
    state: str = INDEXED
    messages: int = 0
    reason: str = ""


@dataclass
class ReadReport:
    """What reading a recording found besides messages: each file's state.

    ``truncated`` is True once any file turned out unfinished (its writer was
    killed); ``reason`` says why for the first such file.
    """

    truncated: bool = False
    reason: str = ""
    segments: list[SegmentReport] = field(default_factory=list)


def read_recording(source: RecordingSource, topics: Iterable[str] | None = None,
                   report: ReadReport | None = None) -> Iterator[RecordedMessage]:
    """Yield the messages of ``topics`` (all if None) of every file of ``source``, in data-stamp order.

    ``source`` is a file, a recording folder or several of them
    (:func:`recording_files`); their files are merged by log time (ties in file
    order) into one stream. A file whose writer was killed has no summary: the
    messages of its complete chunks are read, sorted by log time, and its
    :class:`SegmentReport` says ``truncated``.

    The stream is then put in data-stamp order, as the pipeline takes time from the
    stamps: a message waits up to :data:`REORDER_WINDOW_NS` of log time for one with
    an earlier stamp (ties keep the log-time order). Where ``log_time`` is the data stamp
    (offline outputs, older recordings) that is the log-time order unchanged; in a live
    recording it undoes the transport's reordering between topics, so a replay does not
    depend on it. Either way the order is a function of the file alone.
    """
    topic_list = list(topics) if topics is not None else None
    files = recording_files(source)
    report = report if report is not None else ReadReport()
    streams = []
    for path in files:
        seg = SegmentReport(path)
        report.segments.append(seg)
        streams.append(_read_file(path, topic_list, seg, report))
    merged = streams[0] if len(streams) == 1 else heapq.merge(*streams, key=lambda m: m.log_time_ns)
    yield from in_stamp_order(merged)


def count_messages(source: RecordingSource, report: ReadReport | None = None) -> Counter[str]:
    """Messages per topic in every file of ``source``, from each file's summary statistics.

    Nothing is decompressed where a file has its summary, so counting an hour's recording
    costs what its index does; a file without one (its writer was killed) is read through,
    as :func:`read_recording` reads it, and its :class:`SegmentReport` says so.
    """
    report = report if report is not None else ReadReport()
    counts: Counter[str] = Counter()
    for path in recording_files(source):
        seg = SegmentReport(path)
        report.segments.append(seg)
        with open(path, "rb") as f:
            try:
                summary = make_reader(f).get_summary()
            except _PARSE_ERRORS:
                summary = None
        if summary is not None and summary.statistics is not None:
            for channel_id, n in summary.statistics.channel_message_counts.items():
                counts[summary.channels[channel_id].topic] += n
                seg.messages += n
            continue
        for m in _read_file(path, None, seg, report):
            counts[m.topic] += 1
    return counts


def in_stamp_order(messages: Iterable[RecordedMessage]) -> Iterator[RecordedMessage]:
    """``messages`` (in log-time order) in stamp order within :data:`REORDER_WINDOW_NS` of log time."""
    held: list[tuple[int, int, RecordedMessage]] = []   # (stamp, arrival, message): a heap
    for arrival, m in enumerate(messages):
        heapq.heappush(held, (m.stamp_ns, arrival, m))
        while held and held[0][2].log_time_ns + REORDER_WINDOW_NS <= m.log_time_ns:
            yield heapq.heappop(held)[2]
    while held:
        yield heapq.heappop(held)[2]


def time_layout(path: str | Path) -> str:
    """What the times of the MCAP file ``path`` mean: :data:`RECEIVE`, :data:`STAMP` or :data:`OLD_LAYOUT`.

    From its :data:`TIMES` metadata record (read also from an unfinished file).
    """
    times = read_metadata(path).get(TIMES)
    if times is None:
        return OLD_LAYOUT
    return RECEIVE if times.get("log_time") == RECEIVE else STAMP


def _read_file(path: Path, topics: list[str] | None, seg: SegmentReport,
               report: ReadReport) -> Iterator[RecordedMessage]:
    layout = time_layout(path)
    f = open(path, "rb")  # noqa: SIM115 - closed below, also when the generator is abandoned
    try:
        try:
            reader = make_reader(f)
            indexed = reader.get_summary() is not None
        except _PARSE_ERRORS as exc:
            seg.state, seg.reason = TRUNCATED, f"{type(exc).__name__}: {exc}".rstrip(": ")
            report.truncated = True
            report.reason = report.reason or seg.reason
            log.warning("%s was not finished (%s); reading its complete chunks", path, seg.reason)
        else:
            if indexed:
                for schema, channel, message in reader.iter_messages(topics=topics, log_time_order=True):
                    seg.messages += 1
                    yield _recorded(schema, channel, message, layout)
                return
            seg.state = UNINDEXED
        f.seek(0)
        messages = []
        it = NonSeekingReader(f, validate_crcs=True).iter_messages(topics=topics, log_time_order=False)
        while True:
            try:
                schema, channel, message = next(it)
            except StopIteration:
                break
            except Exception as exc:  # noqa: BLE001 - any parse error (CRC, zstd, EOF) ends the readable part
                if seg.state != TRUNCATED:  # the footer was there, yet the data section is damaged
                    seg.state, report.truncated = TRUNCATED, True
                seg.reason = f"stopped at {type(exc).__name__}: {exc}".rstrip(": ")
                report.reason = report.reason or seg.reason
                break
            messages.append(_recorded(schema, channel, message, layout))
        # Stable: equal log times keep their file order, as the indexed reader does.
        messages.sort(key=lambda m: m.log_time_ns)
        seg.messages = len(messages)
        yield from messages
    finally:
        f.close()


def _recorded(schema, channel, message, layout: str) -> RecordedMessage:
    name = schema.name if schema is not None and schema.id else channel.metadata.get("schema", "")
    if layout == OLD_LAYOUT:
        stamp, received = message.log_time, message.publish_time
    else:
        stamp, received = message.publish_time, message.log_time if layout == RECEIVE else 0
    return RecordedMessage(channel.topic, name, bytes(message.data), message.log_time,
                           message.publish_time, message.sequence, stamp, received)


def read_metadata(source: RecordingSource) -> dict[str, dict[str, str]]:
    """The named metadata records of a recording (of its first file; also of an unfinished one)."""
    path = recording_files(source)[0]
    with open(path, "rb") as f:
        try:
            return {m.name: dict(m.metadata) for m in make_reader(f).iter_metadata()}
        except _PARSE_ERRORS:
            f.seek(0)
        # Metadata records sit outside chunks: no need to open those.
        return {r.name: dict(r.metadata) for r in records_until_damaged(f, emit_chunks=True)
                if isinstance(r, Metadata)}


def records_until_damaged(f: BinaryIO, report: RecoverReport | None = None,
                           emit_chunks: bool = False) -> Iterator[object]:
    """The records of ``f`` in file order up to its end or first damaged record (``report.reason`` says which)."""
    records = StreamReader(f, validate_crcs=True, emit_chunks=emit_chunks).records
    while True:
        try:
            record = next(records)
        except StopIteration:
            return
        except Exception as exc:  # noqa: BLE001 - any parse error (CRC, zstd, EOF) ends the readable part
            if report is not None:
                report.reason = f"{type(exc).__name__}: {exc}".rstrip(": ")
            return
        yield record
