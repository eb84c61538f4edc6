"""MCAP recordings: writing raw protobuf payloads with their embedded schemas, reading them back.

Every channel names its schema (with version) and embeds the protobuf
FileDescriptorSet, so any MCAP tool (Foxglove, ``mcap`` CLI, the ``mcap``
library) decodes the file without this package.

A recording is one MCAP file or, as the recorder writes it (rosbag2 style), a
folder of numbered segments ``<name>/<name>_0.mcap``, ``<name>_1.mcap``, … :
each recorder process opens the next free number with exclusive create, so a
restarted recorder never overwrites, and splits by size or duration. Every
reader here takes a file, a folder or several paths and yields one stream in
data-stamp order.

Times follow the MCAP specification: ``publish_time`` is the message's data stamp (its
``stamp_ns``) and ``log_time`` the time the recorder received it (its wall clock, ns since
the epoch). An offline writer (a replay, an import) has no receive time and puts the data
stamp in both. Every file written so says which in its metadata record ``lrfslam.times``
(:data:`TIMES`); a file without it is of the older layout, whose ``log_time`` held the data
stamp and ``publish_time`` the receive time, and reads as before. :class:`RecordedMessage`
gives both ways of a file the same meaning: ``stamp_ns`` and ``receive_ns``.

A file whose writer was killed has no summary; it is read from its complete
chunks and :func:`recover` rewrites it as an indexed file. A write error (a full
disk) cuts the file back to its last complete record and ends it there, so it
stays a valid (unindexed) MCAP file.
"""

from __future__ import annotations

import contextlib
import heapq
import logging
import os
import re
import struct
import tempfile
import time
from collections import Counter, deque
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO, Self

from mcap.data_stream import RecordBuilder
from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader, make_reader
from mcap.records import (
    Attachment,
    Channel,
    DataEnd,
    Footer,
    Header,
    Message,
    Metadata,
    Schema,
)
from mcap.stream_reader import StreamReader
from mcap.writer import MCAP0_MAGIC, CompressionType, Writer
from mcap_protobuf.schema import build_file_descriptor_set

from lrfslam import __name__ as _lib
from lrfslam.errors import RecordingError
from lrfslam.msgs.codec import CODECS, UPGRADES

log = logging.getLogger(__name__)

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

#: How long (receive time, ns) the reader holds a message back to let one received later with
#: an earlier data stamp overtake it: the transport's jitter between topics is far below it.
REORDER_WINDOW_NS = 5_000_000_000

#: What the mcap library raises on a file without a valid end (it has no single base).
_PARSE_ERRORS = (McapError, ValueError, EOFError, struct.error)


def _known_protos() -> dict[str, type]:
    protos = {name: codec.proto for name, codec in CODECS.items()}
    protos.update({old: proto for (old, _), (proto, _) in UPGRADES.items()})
    return protos


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


class _OutFile:
    """Unbuffered output that writes all or raises, and knows where its last complete write ended.

    The mcap writer hands over whole records per call, so the end of the last
    complete write is a record boundary: after a failed write the file can be
    cut back there and ended validly.
    """

    def __init__(self, path: Path, overwrite: bool) -> None:
        flags = os.O_WRONLY | os.O_CREAT | os.O_CLOEXEC | (os.O_TRUNC if overwrite else os.O_EXCL)
        self.fd = os.open(path, flags, 0o644)
        self.pos = 0
        #: Ends of the last complete writes (bytes), newest last.
        self.boundaries: deque[int] = deque([0], maxlen=16)
        #: Where the data section may be cut: after the header and metadata, and (once the
        #: summary is being written) not after the data section's end.
        self.floor = 0
        self.ceiling: int | None = None

    def write(self, data: bytes) -> int:
        view = memoryview(data)
        done = 0
        while done < len(view):
            n = os.write(self.fd, view[done:])
            if n <= 0:  # a regular file never does this, but a loop must not spin
                raise OSError(28, os.strerror(28))
            done += n
        self.pos += done
        self.boundaries.append(self.pos)
        return done

    def tell(self) -> int:
        return self.pos

    def flush(self) -> None:
        """Nothing to do: every write already reached the OS, which keeps it if the process dies."""

    def seal(self) -> bool:
        """After a failed write: cut back to a complete record and end the file there; True if it worked.

        Tries the newest boundary first and, where the disk has no room for the
        few bytes of the end, the older ones (each gives up one more write).
        """
        end = _minimal_end()
        for cut in reversed(self.boundaries):
            if self.ceiling is not None and cut > self.ceiling:
                continue  # inside a half-written summary: end the data section instead
            if cut < self.floor or not self.floor:
                break  # no header yet, or it would cut into the header: nothing valid to end
            try:
                os.ftruncate(self.fd, cut)
                if os.pwrite(self.fd, end, cut) == len(end):
                    self.pos = cut + len(end)
                    return True
            except OSError:
                pass
        with contextlib.suppress(OSError):
            os.ftruncate(self.fd, self.boundaries[-1])
        return False

    def close(self) -> None:
        os.close(self.fd)


def _minimal_end() -> bytes:
    """DataEnd, a Footer with no summary and the closing magic: a valid end for any data section."""
    builder = RecordBuilder()
    DataEnd(0).write(builder)
    Footer(0, 0, 0).write(builder)
    return builder.end() + MCAP0_MAGIC


class RecordingWriter:
    """Chunked, zstd-compressed MCAP writer for raw payloads; a context manager.

    Parameters
    ----------
    path : path-like
        Output file; its folder is created.
    metadata : dict of str to dict of str
        Named metadata records (robot, config, provenance).
    chunk_size_bytes : int
        Chunk size; a chunk is also closed by :meth:`flush`.
    overwrite : bool
        False: refuse (``FileExistsError``) if ``path`` exists — the recorder's way.
    extra_schemas : mapping of str to bytes
        Protobuf FileDescriptorSets of schemas that are not lrfslam's, by full name (Foxglove's,
        lrfslam/viz/foxglove.py), embedded like lrfslam's when a channel names one.
    receive_times : bool
        What ``log_time`` holds: False, the data stamp as in ``publish_time`` (offline outputs,
        :data:`STAMP`); True, the receive time (a recorder, :data:`RECEIVE`). Written in the
        metadata record :data:`TIMES`.

    A write error (``OSError``, e.g. a full disk) ends the file at its last
    complete record (valid, unindexed), closes it and raises :class:`RecordingError`.
    """

    def __init__(self, path: str | Path, metadata: dict[str, dict[str, str]] | None = None,
                 chunk_size_bytes: int = 256 * 1024, overwrite: bool = True,
                 extra_schemas: Mapping[str, bytes] | None = None, receive_times: bool = False) -> None:
        self.path = Path(path)
        self.receive_times = receive_times
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = _OutFile(self.path, overwrite)
        self._closed = False
        self.messages_written = 0
        #: Messages certainly in the file (complete chunks), as of the last :meth:`flush`.
        self.messages_flushed = 0
        self._writer = Writer(self._file, chunk_size=chunk_size_bytes, compression=CompressionType.ZSTD)
        self._protos = _known_protos()
        self._extra_schemas = dict(extra_schemas or {})
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str], int] = {}
        with self._on_error("start"):
            self._writer.start(profile=PROFILE, library=f"{_lib}-python")
            self._writer.add_metadata(TIMES, {"log_time": RECEIVE if receive_times else STAMP, "publish_time": STAMP})
            for name, record in (metadata or {}).items():
                if name == TIMES:
                    continue  # a copy's source said what its own times were; this file's are above
                self._writer.add_metadata(name, {k: str(v) for k, v in record.items()})
        self._file.floor = self._file.pos

    @property
    def bytes_written(self) -> int:
        """Bytes in the file so far (complete chunks; the open chunk is still in memory)."""
        return self._file.pos

    @contextlib.contextmanager
    def _on_error(self, what: str) -> Iterator[None]:
        if self._closed:
            raise RecordingError(f"{self.path} is closed")
        try:
            yield
        except OSError as exc:
            self._closed = True
            sealed = self._file.seal()
            self._file.close()
            kept = ("it is ended validly after its last complete chunk" if sealed
                    else "it is cut after its last complete record and needs `lrfslam recover`")
            raise RecordingError(f"cannot {what} {self.path}: {exc.strerror or exc}; {kept}") from exc

    def _schema_id(self, schema: str) -> int:
        if schema not in self._schemas:
            proto = self._protos.get(schema)
            if proto is not None:
                fds = build_file_descriptor_set(proto).SerializeToString()
            elif schema in self._extra_schemas:
                fds = self._extra_schemas[schema]
            else:
                # Unknown (newer) schema: keep the bytes, schema-less, rather than lose data.
                self._schemas[schema] = 0
                return 0
            self._schemas[schema] = self._writer.register_schema(schema, "protobuf", fds)
        return self._schemas[schema]

    def write(self, topic: str, schema: str, data: bytes, stamp_ns: int,
              receive_ns: int = 0, sequence: int = 0) -> None:
        """Append one message with its data stamp and receive time (ns; negative ones are written as 0).

        ``publish_time`` gets ``stamp_ns``; ``log_time`` gets ``receive_ns`` in a file of
        ``receive_times`` (``stamp_ns`` where it is 0: nothing received it) and ``stamp_ns``
        in any other, which ignores ``receive_ns``.

        Raises
        ------
        RecordingError
            The file could not be written (it is ended validly and closed).
        """
        with self._on_error("write"):
            key = (topic, schema)
            if key not in self._channels:
                schema_id = self._schema_id(schema)
                self._channels[key] = self._writer.register_channel(
                    topic, "protobuf" if schema_id else "", schema_id, metadata={"schema": schema})
            stamp = max(0, int(stamp_ns))
            log_time = max(0, int(receive_ns)) if self.receive_times and receive_ns else stamp
            self._writer.add_message(self._channels[key], log_time=log_time, data=bytes(data), publish_time=stamp,
                                     sequence=int(sequence) & 0xFFFFFFFF)
            self.messages_written += 1

    def flush(self) -> None:
        """Close the open chunk and hand it to the OS, so a killed process loses at most what came after."""
        with self._on_error("write"):
            self._writer.flush()
            self.messages_flushed = self.messages_written

    def close(self) -> None:
        """Write the summary (index) and close; a failure leaves the file valid, unindexed."""
        if self._closed:
            return
        with self._on_error("finish"):
            self._writer.flush()
            self.messages_flushed = self.messages_written
            self._file.ceiling = self._file.pos
            self._writer.finish()
            self._closed = True
            self._file.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# ---- recording folders ------------------------------------------------------------------------


def segment_path(folder: str | Path, name: str, index: int) -> Path:
    """``<folder>/<name>_<index>.mcap``."""
    return Path(folder) / f"{name}_{index}.mcap"


def segment_index(path: Path) -> int | None:
    """The number of a segment file, None if the name is not ``<name>_<n>.mcap``."""
    m = SEGMENT.match(path.name)
    return int(m["index"]) if m else None


class SegmentedWriter:
    """One recorder process's part of a recording folder: segments ``<name>_<n>.mcap``, split by size or age.

    Each segment is opened with exclusive create at a number above every existing
    one, so a restarted recorder (or a second one) continues the folder and never
    overwrites a file.

    Parameters
    ----------
    folder : path-like
        The recording folder (created).
    name : str
        Stem of the segment files.
    metadata : dict of str to dict of str
        Metadata of every segment; each also gets ``lrfslam.segment`` (its number).
    chunk_size_bytes : int
        MCAP chunk size.
    max_bytes : int
        Start a new segment once the file has this many bytes (to within one
        chunk, as chunks are written whole); 0: no size limit.
    max_duration_s : float
        Start a new segment once this one is this old by ``clock``; 0: no limit.
    clock : callable
        Seconds (monotonic) for ``max_duration_s``.
    extra_schemas : mapping of str to bytes
        See :class:`RecordingWriter`.
    receive_times : bool
        See :class:`RecordingWriter` (the recorder: True).
    """

    def __init__(self, folder: str | Path, name: str, metadata: dict[str, dict[str, str]] | None = None,
                 chunk_size_bytes: int = 256 * 1024, max_bytes: int = 0, max_duration_s: float = 0.0,
                 clock: Callable[[], float] = time.monotonic, extra_schemas: Mapping[str, bytes] | None = None,
                 receive_times: bool = False) -> None:
        self.folder = Path(folder)
        self.name = name
        self._metadata = metadata or {}
        self._chunk = chunk_size_bytes
        self._max_bytes = max_bytes
        self._max_duration_s = max_duration_s
        self._clock = clock
        self._extra_schemas = dict(extra_schemas or {})
        self._receive_times = receive_times
        #: Segments this writer opened, in order.
        self.segments: list[Path] = []
        self.messages_written = 0
        self._finished_messages = 0   # in the segments closed so far
        self._writer: RecordingWriter | None = None
        self._opened_at = 0.0

    @property
    def messages_flushed(self) -> int:
        """Messages in complete chunks on disk: closed segments and the open one's last flush."""
        return self._finished_messages + (self._writer.messages_flushed if self._writer else 0)

    @property
    def current(self) -> RecordingWriter | None:
        """The open segment (None before the first message and after a failure or :meth:`close`)."""
        return self._writer

    def open_next(self) -> RecordingWriter:
        """Finish the open segment, if any, and open the next free number.

        Raises
        ------
        RecordingError
            The folder or the file cannot be created or started (nothing is left behind).
        """
        self.close()
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise RecordingError(f"cannot create {self.folder}: {exc.strerror or exc}") from exc
        taken = [int(m["index"]) for p in self.folder.iterdir()
                 if (m := SEGMENT.match(p.name)) and m["stem"] == self.name]
        index = max(taken, default=-1) + 1
        while True:
            path = segment_path(self.folder, self.name, index)
            meta = {k: dict(v) for k, v in self._metadata.items()}
            meta.setdefault("lrfslam", {})["segment"] = str(index)
            try:
                writer = RecordingWriter(path, meta, self._chunk, overwrite=False, extra_schemas=self._extra_schemas,
                                         receive_times=self._receive_times)
            except FileExistsError:
                index += 1  # another writer took it between the listing and the open
                continue
            except OSError as exc:
                raise RecordingError(f"cannot create {path}: {exc.strerror or exc}") from exc
            except RecordingError:
                with contextlib.suppress(OSError):
                    path.unlink()  # not even its header fit: an empty file helps no one
                raise
            break
        self._writer = writer
        self._opened_at = self._clock()
        self.segments.append(path)
        log.info("recording to %s", path)
        return writer

    def due(self) -> bool:
        """Whether the open segment is full (size) or old enough (duration) to start the next."""
        w = self._writer
        if w is None or w.messages_written == 0:
            return False
        return ((self._max_bytes > 0 and w.bytes_written >= self._max_bytes)
                or (self._max_duration_s > 0 and self._clock() - self._opened_at >= self._max_duration_s))

    def write(self, topic: str, schema: str, data: bytes, stamp_ns: int,
              receive_ns: int = 0, sequence: int = 0) -> None:
        """Append one message (see :meth:`RecordingWriter.write`), opening or splitting segments as needed.

        Raises
        ------
        RecordingError
            A write failed: that segment is ended validly and closed; the next
            call opens a new one.
        """
        if self._writer is None or self.due():
            self.open_next()
        try:
            self._writer.write(topic, schema, data, stamp_ns, receive_ns, sequence)
        except RecordingError:
            self._drop_failed()
            raise
        self.messages_written += 1

    def flush(self) -> None:
        """Flush the open segment (see :meth:`RecordingWriter.flush`); start the next one if it is due."""
        if self._writer is None:
            return
        try:
            self._writer.flush()
            if self.due():
                self.open_next()
        except RecordingError:
            self._drop_failed()
            raise

    def _drop_failed(self) -> None:
        """Forget a segment whose write failed (it has ended itself at its last complete chunk)."""
        if self._writer is not None:
            self._finished_messages += self._writer.messages_flushed
            self._writer = None

    def close(self) -> None:
        """Finish the open segment."""
        writer, self._writer = self._writer, None
        if writer is not None:
            try:
                writer.close()
            finally:
                self._finished_messages += writer.messages_flushed


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


# ---- reading -----------------------------------------------------------------------------------


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
    yield from _by_stamp(merged)


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


def _by_stamp(messages: Iterable[RecordedMessage]) -> Iterator[RecordedMessage]:
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
        return {r.name: dict(r.metadata) for r in _records_until_damaged(f, emit_chunks=True)
                if isinstance(r, Metadata)}


# ---- recovery ----------------------------------------------------------------------------------


@dataclass
class RecoverReport:
    """What :func:`recover` kept: messages, channels, the byte where reading stopped and why."""

    messages: int = 0
    channels: int = 0
    read_bytes: int = 0
    total_bytes: int = 0
    reason: str = ""

    @property
    def complete(self) -> bool:
        """Whether the input was read to its end (nothing was lost)."""
        return not self.reason


def recover(in_path: str | Path, out_path: str | Path, chunk_size_bytes: int = 1024 * 1024) -> RecoverReport:
    """Rewrite the readable part of ``in_path`` as a finished, indexed MCAP file ``out_path``.

    Reads records in file order until the end or the first damaged record (a
    killed writer's last, incomplete chunk), and writes its header, schemas,
    channels, metadata, attachments and messages as recorded. ``out_path`` is
    written beside itself under a temporary name and only then linked into
    place, so it is never overwritten and never half-written.

    Raises
    ------
    RecordingError
        ``in_path`` is missing or not MCAP, or ``out_path`` exists or cannot be written.
    """
    in_path, out_path = Path(in_path), Path(out_path)
    if not in_path.is_file():
        raise RecordingError(f"{in_path} is not a file")
    if out_path.exists():
        raise RecordingError(f"{out_path} exists; give a new name (recover never overwrites)")
    out_path.parent.mkdir(parents=True, exist_ok=True)
    report = RecoverReport(total_bytes=in_path.stat().st_size)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{out_path.name}.", suffix=".partial", dir=out_path.parent)
    tmp = Path(tmp_name)
    try:
        with os.fdopen(fd, "wb") as out, open(in_path, "rb") as f:
            _copy_records(f, out, report, chunk_size_bytes)
        try:
            os.link(tmp, out_path)  # fails if out_path appeared meanwhile: never overwrite
        except FileExistsError:
            raise RecordingError(f"{out_path} exists; give a new name (recover never overwrites)") from None
    except OSError as exc:
        raise RecordingError(f"cannot write {out_path}: {exc.strerror or exc}") from exc
    finally:
        tmp.unlink(missing_ok=True)
    return report


def _records_until_damaged(f: BinaryIO, report: RecoverReport | None = None,
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


def _copy_records(f: BinaryIO, out: BinaryIO, report: RecoverReport, chunk_size_bytes: int) -> None:
    writer = Writer(out, chunk_size=chunk_size_bytes, compression=CompressionType.ZSTD)
    schemas: dict[int, int] = {0: 0}
    channels: dict[int, int] = {}
    started = False
    for record in _records_until_damaged(f, report):
        if isinstance(record, Header):
            writer.start(profile=record.profile, library=record.library)
            started = True
        elif not started:
            break
        elif isinstance(record, Schema) and record.id not in schemas:
            schemas[record.id] = writer.register_schema(record.name, record.encoding, record.data)
        elif isinstance(record, Channel) and record.id not in channels:
            channels[record.id] = writer.register_channel(record.topic, record.message_encoding,
                                                          schemas.get(record.schema_id, 0), record.metadata)
        elif isinstance(record, Message) and record.channel_id in channels:
            writer.add_message(channels[record.channel_id], record.log_time, record.data,
                               record.publish_time, record.sequence)
            report.messages += 1
        elif isinstance(record, Metadata):
            writer.add_metadata(record.name, record.metadata)
        elif isinstance(record, Attachment):
            writer.add_attachment(record.create_time, record.log_time, record.name, record.media_type, record.data)
        elif isinstance(record, DataEnd):
            report.read_bytes = report.total_bytes
            break  # the summary only repeats what came before
        report.read_bytes = f.tell()
    if not started:
        raise RecordingError(f"{f.name} is not an MCAP file ({report.reason or 'no header'})")
    report.channels = len(channels)
    writer.finish()
