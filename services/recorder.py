"""recorder: everything under the robot's namespace into an MCAP file.

in:  lrf/<robot>/** (raw payloads, any schema)
out: recordings/<UTC time>_<robot>.mcap — zstd chunks, flushed every second, finished on SIGTERM

Payloads are stored as received, never re-encoded, with each channel's schema
(name with version, protobuf FileDescriptorSet) embedded. A write error such as a
full disk is counted and logged once; the recorder keeps running and the other
services never notice.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.runtime.decoding import LogOnce
from lrfslam.runtime.recording import RecordingWriter
from lrfslam.runtime.step import Message, RunContext, ServiceSpec, StepBase

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RecorderConfig:
    directory: str = "recordings"   # created if missing
    filename: str = ""              # default: <YYYYmmdd-HHMMSS>_<robot>.mcap (UTC)
    flush_period_s: float = 1.0     # a killed recorder loses at most this much
    chunk_size_kb: int = 256
    include_health: bool = True     # also record health/<service>


class RecorderStep(StepBase):
    def __init__(self, cfg: RecorderConfig, ctx: RunContext) -> None:
        super().__init__()
        self.cfg = cfg
        name = cfg.filename or time.strftime("%Y%m%d-%H%M%S", time.gmtime()) + f"_{ctx.robot}.mcap"
        self.path = Path(cfg.directory) / name
        self.writer = RecordingWriter(self.path, metadata={"lrfslam": {"robot": ctx.robot}},
                                      chunk_size_bytes=cfg.chunk_size_kb * 1024)
        self._next_flush = time.monotonic() + cfg.flush_period_s
        self._once = LogOnce(log)
        self._failing = False
        log.info("recording to %s", self.path)

    def on_message(self, msg: Message):
        if not self.cfg.include_health and topics.is_health(msg.name):
            return ()
        stamp = msg.stamp_ns or time.time_ns()
        try:
            self.writer.write(msg.name, msg.schema, msg.value, stamp, time.time_ns(), msg.seq)
        except OSError as exc:
            self._write_failed("write", exc)
            return ()
        self.counts["messages"] += 1
        self.counts[f"topic.{msg.name}"] += 1
        return ()

    def tick(self) -> None:
        now = time.monotonic()
        if now < self._next_flush:
            return
        self._next_flush = now + self.cfg.flush_period_s
        try:
            self.writer.flush()
            self._failing = False
        except OSError as exc:
            self._write_failed("flush", exc)

    def _write_failed(self, what: str, exc: OSError) -> None:
        self.counts[f"error.{what}"] += 1
        self._failing = True
        self._once.warning(what, str(exc.errno), "recording %s failed on %s: %s", what, self.path, exc)

    def health(self) -> tuple[int, str]:
        if self._failing:
            return t.HEALTH_ERROR, f"cannot write {self.path}"
        return t.HEALTH_OK, f"recording {self.path}"

    def close(self) -> None:
        try:
            self.writer.close()
            log.info("closed %s (%d messages)", self.path, self.writer.messages_written)
        except OSError as exc:
            self._write_failed("finish", exc)


SPEC = ServiceSpec(
    name="recorder",
    summary="Record every key of the robot to an MCAP file (zstd chunks, flushed every second).",
    config_type=RecorderConfig,
    inputs=(),
    outputs=(),
    build=lambda cfg, ctx: RecorderStep(cfg, ctx),
    raw_inputs=True,
)
