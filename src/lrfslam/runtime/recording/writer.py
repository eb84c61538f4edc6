"""One MCAP file written with raw payloads, their schemas embedded; a write error ends it validly."""

from __future__ import annotations

import contextlib
import os
from collections import deque
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Self

from mcap.data_stream import RecordBuilder
from mcap.records import DataEnd, Footer
from mcap.writer import MCAP0_MAGIC, CompressionType, Writer
from mcap_protobuf.schema import build_file_descriptor_set

from lrfslam import __name__ as _lib
from lrfslam.errors import RecordingError
from lrfslam.msgs.codec import CODECS, UPGRADES
from lrfslam.runtime.recording.layout import PROFILE, RECEIVE, STAMP, TIMES


def _known_protos() -> dict[str, type]:
    protos = {name: codec.proto for name, codec in CODECS.items()}
    protos.update({old: proto for (old, _), (proto, _) in UPGRADES.items()})
    return protos


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


