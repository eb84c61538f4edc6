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

The package: :mod:`.layout` (names, time layouts, a message as stored), :mod:`.writer` (one
file), :mod:`.segments` (a recording folder), :mod:`.reader` (one stream from any of them) and
:mod:`.recover`; everything a caller needs is imported here.
"""


from lrfslam.runtime.recording.layout import (
    OLD_LAYOUT,
    PROFILE,
    RECEIVE,
    STAMP,
    TIMES,
    RecordedMessage,
    RecordingSource,
)
from lrfslam.runtime.recording.reader import (
    INDEXED,
    REORDER_WINDOW_NS,
    TRUNCATED,
    UNINDEXED,
    ReadReport,
    SegmentReport,
    count_messages,
    describe_source,
    read_metadata,
    read_recording,
    recording_files,
    time_layout,
)
from lrfslam.runtime.recording.recover import RecoverReport, recover
from lrfslam.runtime.recording.segments import SegmentedWriter
from lrfslam.runtime.recording.writer import RecordingWriter

__all__ = [
    "INDEXED", "OLD_LAYOUT", "PROFILE", "RECEIVE", "REORDER_WINDOW_NS", "STAMP", "TIMES", "TRUNCATED", "UNINDEXED",
    "ReadReport", "RecordedMessage", "RecordingSource", "RecordingWriter", "RecoverReport", "SegmentReport",
    "SegmentedWriter", "count_messages", "describe_source", "read_metadata", "read_recording", "recording_files",
    "recover", "time_layout",
]
