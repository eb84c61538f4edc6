"""recorder: everything under the robot's namespace into a recording folder of MCAP segments.

in:  lrf/<robot>/** (raw payloads, any schema)
out: recordings/<name>/<name>_<n>.mcap, name <UTC YYYYmmdd-HHMMSS>_<robot> by default — zstd
     chunks, flushed every second, finished on SIGTERM

Payloads are stored as received, never re-encoded, with each channel's schema
(name with version, protobuf FileDescriptorSet) embedded, at MCAP's times: ``log_time`` the
recorder's wall clock when the message arrived, ``publish_time`` its data stamp
(lrfslam/runtime/recording.py). Beside them (``foxglove = true``,
the default) go Foxglove's views of them, ``/foxglove/...`` channels of Foxglove's
well-known schemas at the same times (lrfslam/viz/foxglove.py), so the recording
opens in Foxglove or Lichtblick as a map. A payload the views cannot decode is counted
(``foxglove.undecodable``) and recorded all the same: the views never stop the raw recording. Each start of the
recorder opens the next free segment number of its folder (never an existing
file), so a recorder restarted after a crash continues the recording; a segment
is also closed and the next one opened by size or age (rosbag2's split).

A recorder that cannot open its first segment fails to start. Later, a write
error such as a full disk ends the segment validly at its last complete
chunk and is logged once; the recorder keeps running (the other services never
notice), counts what it cannot record, and tries a new segment every
``retry_period_s``.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

from lrfslam.errors import ConfigError, InputError, RecordingError
from lrfslam.msgs import counters, topics
from lrfslam.msgs import types as t
from lrfslam.runtime.decoding import LogOnce
from lrfslam.runtime.recording import SegmentedWriter
from lrfslam.runtime.step import Message, RunContext, ServiceSpec, StepBase
from lrfslam.viz.foxglove import FoxgloveViews, schema_sets

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RecorderConfig:
    directory: str = "recordings"   # parent of the recording folder; created if missing
    name: str = ""                  # recording folder and segment stem; default <YYYYmmdd-HHMMSS>_<robot> (UTC)
    flush_period_s: float = 1.0     # a killed recorder loses at most this much
    # MCAP's own default. The flush closes a chunk every second anyway; a smaller limit only adds
    # chunks, and MCAP's writer keeps an index entry (~1.5 KB) per chunk until the segment closes.
    chunk_size_kb: int = 1024
    # Start the next segment past this size (MB); 0: no limit. It bounds the chunk index above in
    # memory (docs/operations.md, "Soak").
    max_segment_mb: float = 512.0
    max_segment_s: float = 0.0      # start the next segment at this age (s); 0: no limit
    retry_period_s: float = 10.0    # after a write error (full disk), try a new segment this often
    include_health: bool = True     # also record health/<service>
    foxglove: bool = True           # also write Foxglove's views (/foxglove/... channels; docs/monitoring.md)

    def __post_init__(self) -> None:
        if min(self.flush_period_s, self.max_segment_mb, self.max_segment_s, self.retry_period_s) < 0:
            raise ConfigError("recorder periods and segment limits must be ≥ 0")


class RecorderStep(StepBase):
    def __init__(self, cfg: RecorderConfig, ctx: RunContext) -> None:
        super().__init__()
        self.cfg = cfg
        name = cfg.name or time.strftime("%Y%m%d-%H%M%S", time.gmtime()) + f"_{ctx.robot}"
        self.views = FoxgloveViews() if cfg.foxglove else None
        self.writer = SegmentedWriter(f"{cfg.directory}/{name}", name,
                                      metadata={"lrfslam": {"robot": ctx.robot, "recording": name}},
                                      chunk_size_bytes=cfg.chunk_size_kb * 1024,
                                      max_bytes=int(cfg.max_segment_mb * 1e6), max_duration_s=cfg.max_segment_s,
                                      extra_schemas=schema_sets() if self.views else None, receive_times=True)
        self.folder = self.writer.folder
        self._next_flush = time.monotonic() + cfg.flush_period_s
        self._once = LogOnce(log)
        self._blocked_until: float | None = None   # set while writes fail
        # Where the first segment cannot even be opened (a folder it may not create), the
        # recorder fails to start, so `up` stops at once instead of running without a recording.
        self.writer.open_next()

    def _open(self) -> None:
        try:
            self.writer.open_next()
            self._blocked_until = None
        except RecordingError as exc:
            self._failed("open", exc)

    def on_message(self, msg: Message):
        if not self.cfg.include_health and topics.is_health(msg.name):
            return ()
        if self._blocked_until is not None:
            self.counts[counters.DROP_UNWRITABLE] += 1
            return ()
        received = msg.received_wall_ns or time.time_ns()
        stamp = msg.stamp_ns or received   # unstamped (an older or foreign publisher): when it arrived
        try:
            self.writer.write(msg.name, msg.schema, msg.value, stamp, received, msg.seq)
        except RecordingError as exc:
            self._failed("write", exc)
            self.counts[counters.DROP_UNWRITABLE] += 1
            return ()
        self.counts["messages"] += 1
        self.counts[f"topic.{msg.name}"] += 1
        if self.views is not None:
            self._write_views(msg, stamp, received)
        return ()

    def _write_views(self, msg: Message, stamp: int, received: int) -> None:
        try:
            views = self.views.from_payload(msg.name, msg.schema, msg.value, stamp)
        except InputError as exc:
            self.counts["foxglove.undecodable"] += 1
            self._once.warning("foxglove", f"{msg.name}:{msg.schema}", "no Foxglove view of a message on %s: %s "
                               "(it is recorded as received)", msg.name, exc)
            return
        except Exception:  # a bug in a view must not cost the raw recording
            self.counts["foxglove.failed"] += 1
            if self.counts["foxglove.failed"] == 1:
                log.exception("a Foxglove view of a message on %s failed (it is recorded as received; "
                              "further failures are only counted)", msg.name)
            return
        for view in views:
            try:
                self.writer.write(view.topic, view.schema, view.encode(), view.stamp_ns, received)
            except RecordingError as exc:
                self._failed("write", exc)
                return
            self.counts["foxglove.messages"] += 1

    def tick(self) -> None:
        now = time.monotonic()
        if self._blocked_until is not None:
            if now >= self._blocked_until:
                self._open()
            return
        if now < self._next_flush:
            return
        self._next_flush = now + self.cfg.flush_period_s
        try:
            self.writer.flush()
        except RecordingError as exc:
            self._failed("write", exc)
            return
        self.counts["flushed"] = self.writer.messages_flushed

    def _failed(self, what: str, exc: RecordingError) -> None:
        self.counts[f"{counters.ERROR}{what}"] += 1
        self._blocked_until = time.monotonic() + self.cfg.retry_period_s
        cause = exc.__cause__
        self._once.warning(what, str(getattr(cause, "errno", "")), "recording stopped: %s; retrying in a "
                           "new segment every %.0f s", exc, self.cfg.retry_period_s)

    def health(self) -> tuple[int, str]:
        if self._blocked_until is not None:
            return t.HEALTH_ERROR, f"cannot write to {self.folder}"
        current = self.writer.current
        where = f"recording {current.path if current else self.folder}"
        if self.counts["foxglove.failed"]:
            return t.HEALTH_WARN, f"{where}; {self.counts['foxglove.failed']} Foxglove views failed"
        return t.HEALTH_OK, where

    def close(self) -> None:
        current = self.writer.current
        try:
            self.writer.close()
        except RecordingError as exc:
            self._failed("finish", exc)
            return
        if current is not None:
            log.info("closed %s (%d messages in %d segment(s) of %s)", current.path, self.writer.messages_written,
                     len(self.writer.segments), self.folder)


SPEC = ServiceSpec(
    name="recorder",
    summary="Record every key of the robot to a folder of MCAP segments (zstd chunks, flushed every second).",
    config_type=RecorderConfig,
    inputs=(),
    outputs=(),
    build=lambda cfg, ctx: RecorderStep(cfg, ctx),
    raw_inputs=True,
    batched=True,
)
