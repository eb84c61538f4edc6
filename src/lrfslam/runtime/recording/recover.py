"""Rewriting a file whose writer was killed as an indexed MCAP file."""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from mcap.records import (
    Attachment,
    Channel,
    DataEnd,
    Header,
    Message,
    Metadata,
    Schema,
)
from mcap.writer import CompressionType, Writer

from lrfslam.errors import RecordingError
from lrfslam.runtime.recording.reader import records_until_damaged


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


def _copy_records(f: BinaryIO, out: BinaryIO, report: RecoverReport, chunk_size_bytes: int) -> None:
    writer = Writer(out, chunk_size=chunk_size_bytes, compression=CompressionType.ZSTD)
    schemas: dict[int, int] = {0: 0}
    channels: dict[int, int] = {}
    started = False
    for record in records_until_damaged(f, report):
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
