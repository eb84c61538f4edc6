"""MCAP recordings: writing raw protobuf payloads with their embedded schemas, reading them back.

Every channel names its schema (with version) and embeds the protobuf
FileDescriptorSet, so any MCAP tool (Foxglove, ``mcap`` CLI, the ``mcap``
library) decodes the file without this package.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Self

from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader, make_reader
from mcap.writer import MCAP0_MAGIC, CompressionType, Writer
from mcap_protobuf.schema import build_file_descriptor_set

from lrfslam import __name__ as _lib
from lrfslam.errors import RecordingError
from lrfslam.msgs.codec import CODECS, UPGRADES

log = logging.getLogger(__name__)

PROFILE = "lrfslam"


def _known_protos() -> dict[str, type]:
    protos = {name: codec.proto for name, codec in CODECS.items()}
    protos.update({old: proto for (old, _), (proto, _) in UPGRADES.items()})
    return protos


@dataclass(frozen=True)
class RecordedMessage:
    """One message as stored: relative topic, schema name, payload, times in ns."""

    topic: str
    schema: str
    data: bytes
    log_time_ns: int
    publish_time_ns: int
    sequence: int


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
    """

    def __init__(self, path: str | Path, metadata: dict[str, dict[str, str]] | None = None,
                 chunk_size_bytes: int = 256 * 1024) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file: BinaryIO = open(self.path, "wb")  # noqa: SIM115 - owned by the writer, closed by close()
        self._writer = Writer(self._file, chunk_size=chunk_size_bytes, compression=CompressionType.ZSTD)
        self._writer.start(profile=PROFILE, library=f"{_lib}-python")
        for name, record in (metadata or {}).items():
            self._writer.add_metadata(name, {k: str(v) for k, v in record.items()})
        self._protos = _known_protos()
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str], int] = {}
        self.messages_written = 0
        self._closed = False

    def _schema_id(self, schema: str) -> int:
        if schema not in self._schemas:
            proto = self._protos.get(schema)
            if proto is None:
                # Unknown (newer) schema: keep the bytes, schema-less, rather than lose data.
                self._schemas[schema] = 0
            else:
                fds = build_file_descriptor_set(proto).SerializeToString()
                self._schemas[schema] = self._writer.register_schema(schema, "protobuf", fds)
        return self._schemas[schema]

    def write(self, topic: str, schema: str, data: bytes, log_time_ns: int,
              publish_time_ns: int | None = None, sequence: int = 0) -> None:
        """Append one message; ``log_time_ns`` must be ≥ 0."""
        key = (topic, schema)
        if key not in self._channels:
            schema_id = self._schema_id(schema)
            self._channels[key] = self._writer.register_channel(
                topic, "protobuf" if schema_id else "", schema_id, metadata={"schema": schema})
        self._writer.add_message(self._channels[key], log_time=max(0, int(log_time_ns)), data=bytes(data),
                                 publish_time=max(0, int(publish_time_ns if publish_time_ns is not None
                                                         else log_time_ns)),
                                 sequence=int(sequence) & 0xFFFFFFFF)
        self.messages_written += 1

    def flush(self) -> None:
        """Close the open chunk and push it to the OS, so a crash loses at most what came after."""
        self._writer.flush()
        self._file.flush()

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            try:
                self._writer.finish()
            finally:
                self._file.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass
class ReadReport:
    """What reading a recording found besides messages."""

    truncated: bool = False
    reason: str = ""


def check_recording(path: str | Path) -> Path:
    """``path``, if it is a file that starts as an MCAP file does (complete or not).

    Raises
    ------
    RecordingError
        It does not exist, is a folder, or holds something else.
    """
    path = Path(path)
    if not path.exists():
        raise RecordingError(f"recording {path} does not exist")
    if not path.is_file():
        raise RecordingError(f"recording {path} is not a file")
    with open(path, "rb") as f:
        head = f.read(len(MCAP0_MAGIC))
    if head != MCAP0_MAGIC:
        raise RecordingError(f"{path} is not an MCAP recording ({'empty' if not head else 'no MCAP magic'})")
    return path


def read_recording(path: str | Path, topics: Iterable[str] | None = None,
                   report: ReadReport | None = None) -> Iterator[RecordedMessage]:
    """Yield the messages of ``topics`` (all if None) in log-time order.

    A file whose writer was killed has no footer: the indexed reader refuses it,
    so the messages of its complete chunks are read sequentially instead (in file
    order, which is log-time order for our recorder), and ``report.truncated`` is set.
    A path that is no MCAP file at all raises :class:`RecordingError` (see
    :func:`check_recording`) when the first message is asked for.
    """
    topic_set = set(topics) if topics is not None else None
    path = check_recording(path)
    report = report if report is not None else ReadReport()
    f = open(path, "rb")  # noqa: SIM115 - the generator's finally closes it, also when abandoned
    try:
        reader = make_reader(f)
        if reader.get_summary() is None:
            raise McapError("no summary section")
    except (McapError, ValueError, EOFError, struct.error) as exc:
        f.close()
        report.truncated, report.reason = True, f"{type(exc).__name__}: {exc}"
        log.warning("%s has no valid summary (%s); reading its complete chunks in file order",
                    path, report.reason)
    else:
        with f:
            for schema, channel, message in reader.iter_messages(topics=topic_set and list(topic_set),
                                                                 log_time_order=True):
                yield _recorded(schema, channel, message)
        return
    with open(path, "rb") as f:
        reader = NonSeekingReader(f, validate_crcs=True)
        it = reader.iter_messages(topics=topic_set and list(topic_set), log_time_order=False)
        while True:
            try:
                schema, channel, message = next(it)
            except StopIteration:
                return
            except Exception as exc:  # noqa: BLE001 - any parse error ends a truncated file
                report.reason = f"stopped at {type(exc).__name__}: {exc}"
                return
            yield _recorded(schema, channel, message)


def _recorded(schema, channel, message) -> RecordedMessage:
    name = schema.name if schema is not None and schema.id else channel.metadata.get("schema", "")
    return RecordedMessage(channel.topic, name, bytes(message.data), message.log_time,
                           message.publish_time, message.sequence)


def read_metadata(path: str | Path) -> dict[str, dict[str, str]]:
    """The named metadata records of a finished recording."""
    with open(check_recording(path), "rb") as f:
        return {m.name: dict(m.metadata) for m in make_reader(f).iter_metadata()}
