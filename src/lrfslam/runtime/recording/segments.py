"""A recording folder of numbered segments, split by size or age, never overwritten."""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable, Mapping
from pathlib import Path

from lrfslam.errors import RecordingError
from lrfslam.runtime.recording.layout import SEGMENT, segment_path
from lrfslam.runtime.recording.writer import RecordingWriter

log = logging.getLogger(__name__)


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

