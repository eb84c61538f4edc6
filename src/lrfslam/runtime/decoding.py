"""Turning received payloads into messages, the same way live, on replay and offline.

A payload that does not decode with the schema it names, names an unknown
version, or is larger than :data:`MAX_PAYLOAD_BYTES` is counted as
``error.decode`` / ``error.schema`` / ``error.oversize``, logged once per topic
and kind, and skipped: one bad sample never stops a stage.
"""

from __future__ import annotations

import logging
from collections import Counter
from typing import Any

from lrfslam.errors import DecodeError, SchemaVersionError
from lrfslam.msgs import counters
from lrfslam.msgs.topics import Topic
from lrfslam.runtime.step import Message

#: Payloads larger than this are refused unparsed. The largest real message, ``map/keyframes``
#: with 20 000 keyframes, is about 1 MB; a scan of the LMS200 about 3 kB.
MAX_PAYLOAD_BYTES = 64 * 1024 * 1024


class LogOnce:
    """Log each distinct (kind, detail) once; later occurrences are only counted."""

    def __init__(self, logger: logging.Logger) -> None:
        self._log = logger
        self._seen: set[tuple[str, str]] = set()

    def warning(self, kind: str, detail: str, msg: str, *args: Any) -> None:
        if (kind, detail) not in self._seen:
            self._seen.add((kind, detail))
            self._log.warning(msg + " (further ones are only counted)", *args)


def decode_message(topic: Topic, payload: bytes, schema: str, counts: Counter, once: LogOnce,
                   where: str) -> Message | None:
    """The decoded message, or None (counted and logged once) if ``payload`` is bad.

    Parameters
    ----------
    topic : Topic
        The topic the payload arrived on; its codec decodes it.
    schema : str
        Schema name the payload claims; ``""`` (none given) counts as a schema error.
    where : str
        Key or file the payload came from, for the log line.
    """
    try:
        if not schema:
            raise DecodeError("", "the sample names no schema")
        if len(payload) > MAX_PAYLOAD_BYTES:
            raise DecodeError(schema, f"{len(payload)} bytes, more than the {MAX_PAYLOAD_BYTES} accepted")
        value = topic.codec.decode(payload, schema)
    except DecodeError as exc:
        if isinstance(exc, SchemaVersionError) or not schema:
            kind = counters.ERROR_SCHEMA
        else:
            kind = counters.ERROR_OVERSIZE if len(payload) > MAX_PAYLOAD_BYTES else counters.ERROR_DECODE
        counts[kind] += 1
        once.warning(kind, f"{topic.name}:{exc.schema}", "skipping a message on %s: %s", where, exc)
        return None
    return Message(topic, value, value.stamp_ns, schema, topic.name, value.seq)
