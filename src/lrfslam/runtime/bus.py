"""Zenoh transport for one service: subscribers feeding a queue, publishers, status.

Subscriber callbacks only copy the payload into a bounded queue (Zenoh forbids
API calls or blocking inside callbacks); decoding happens in the service's main
thread. A full queue drops the sample and counts it, so a slow stage never
stalls Zenoh's receive thread and with it every other stream of the session.
"""

from __future__ import annotations

import json
import logging
import queue
import re
import struct
import threading
from collections import Counter
from dataclasses import dataclass

import zenoh

from lrfslam.errors import StartupError
from lrfslam.msgs import topics
from lrfslam.msgs.codec import parse_encoding
from lrfslam.msgs.topics import Topic
from lrfslam.runtime.decoding import LogOnce, decode_message
from lrfslam.runtime.step import Message, Output

log = logging.getLogger(__name__)

# rmw_zenoh-style attachment: sequence number and data stamp, so raw consumers
# (the recorder) get both without decoding the payload.
_ATTACHMENT = struct.Struct("<QQ")


@dataclass(frozen=True)
class BusConfig:
    """How to reach the Zenoh network. Defaults: a peer on loopback, multicast scouting off."""

    robot: str = "robot1"                               # namespace: every key is lrf/<robot>/...
    mode: str = "peer"                                  # peer | client | router
    connect: tuple[str, ...] = ("tcp/127.0.0.1:7447",)  # router/peers to dial (retried in the background)
    listen: tuple[str, ...] = ("tcp/127.0.0.1:0",)      # ignored in client mode
    zenoh_config: str = ""                              # optional Zenoh JSON5 file applied first
    queue_size: int = 512                               # received samples waiting for the step
    health_period_s: float = 1.0                        # how often health/<service> is published
    join: bool = False                                  # start beside a live service of the same robot and name

    def __post_init__(self) -> None:
        topics.check_robot(self.robot)
        if self.mode not in ("peer", "client", "router"):
            from lrfslam.errors import ConfigError
            raise ConfigError(f"bus.mode must be peer, client or router, got {self.mode!r}")


def zenoh_config(cfg: BusConfig) -> zenoh.Config:
    """The Zenoh session configuration for ``cfg``."""
    conf = zenoh.Config.from_file(cfg.zenoh_config) if cfg.zenoh_config else zenoh.Config()
    conf.insert_json5("mode", json.dumps(cfg.mode))
    conf.insert_json5("connect/endpoints", json.dumps(list(cfg.connect)))
    if cfg.mode != "client":
        conf.insert_json5("listen/endpoints", json.dumps(list(cfg.listen)))
    # Multicast does not cross container networks and must not leave loopback in CI.
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


def listen_error(exc: zenoh.ZError) -> str | None:
    """One line (no Zenoh source locations) if ``exc`` says a listener could not bind, else None.

    A port already in use is the common case (a second ``lrfslam up`` on the same
    port): say so, and how to choose another.
    """
    text = str(exc)
    endpoint = re.search(r"bound to (\S+?):? \[", text)
    reason = re.search(r"([A-Za-z][A-Za-z ]*?) \(os error \d+\)", text)
    if endpoint is None or reason is None:
        return None
    hint = (" (another router or lrfslam up has it: pass another --port or --listen, or join it with "
            "lrfslam up --connect)" if "in use" in reason.group(1) else "")
    return f"cannot listen on {endpoint.group(1)}: {reason.group(1)}{hint}"


def open_session(conf: zenoh.Config, stop: threading.Event, endpoints: tuple[str, ...]) -> zenoh.Session | None:
    """Open a Zenoh session, retrying while the router is not up yet; None if ``stop`` is set first.

    A client's ``open`` fails at once when its router is unreachable; services may
    start before their router (compose, restarts), so they wait for it instead.

    Raises
    ------
    StartupError
        A listen endpoint cannot be bound (waiting would not help).
    """
    delay = 0.2
    while True:
        try:
            return zenoh.open(conf)
        except zenoh.ZError as exc:
            if (message := listen_error(exc)) is not None:
                raise StartupError(message) from None
            if delay == 0.2:
                log.warning("cannot reach %s yet (%s); retrying", ", ".join(endpoints), str(exc).split(" at ")[0])
            if stop.wait(delay):
                return None
            delay = min(delay * 2, 2.0)


def attachment(seq: int, stamp_ns: int) -> bytes:
    return _ATTACHMENT.pack(int(seq) & 0xFFFFFFFFFFFFFFFF, int(stamp_ns))


def parse_attachment(data: bytes | None) -> tuple[int, int]:
    """(seq, stamp_ns) from an attachment, (0, 0) when absent or malformed."""
    if not data or len(data) != _ATTACHMENT.size:
        return 0, 0
    return _ATTACHMENT.unpack(data)


class ZenohBus:
    """Inputs and outputs of one service over an open Zenoh session.

    Parameters
    ----------
    session : zenoh.Session
    robot : str
    inputs : tuple of Topic
        Topics to subscribe to and decode.
    raw : bool
        Subscribe to everything under the robot instead, and deliver payloads undecoded.
    queue_size : int
    counts : Counter
        Shared counters (``in.*``, ``out.*``, ``drop.queue``, ``error.*``).
    """

    def __init__(self, session: zenoh.Session, robot: str, inputs: tuple[Topic, ...], raw: bool,
                 queue_size: int, counts: Counter) -> None:
        self._session = session
        self._robot = robot
        self._raw = raw
        self._queue: queue.Queue = queue.Queue(maxsize=queue_size)
        self._counts = counts
        self._once = LogOnce(log)
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._by_key = {topics.key(robot, t.name): t for t in inputs}
        keys = [topics.everything(robot)] if raw else list(self._by_key)
        self._subscribers = [session.declare_subscriber(k, self._on_sample) for k in keys]

    def _on_sample(self, sample: zenoh.Sample) -> None:
        att = sample.attachment
        item = (str(sample.key_expr), sample.payload.to_bytes(), str(sample.encoding),
                att.to_bytes() if att is not None else None)
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            self._counts["drop.queue"] += 1

    def get(self, timeout_s: float) -> Message | None:
        """The next decodable input, or None after ``timeout_s`` without one."""
        try:
            key, payload, encoding, att = self._queue.get(timeout=timeout_s)
        except queue.Empty:
            return None
        seq, stamp_ns = parse_attachment(att)
        schema = parse_encoding(encoding)
        if self._raw:
            name = topics.relative(self._robot, key)
            self._counts["in.raw"] += 1
            return Message(None, payload, stamp_ns, schema, name, seq)
        topic = self._by_key.get(key)
        if topic is None:
            return None
        self._counts[f"in.{topic.name}"] += 1
        return decode_message(topic, payload, schema, self._counts, self._once, key)

    def publish(self, out: Output) -> None:
        """Encode and put ``out.value`` on its topic's key with schema and attachment."""
        self.put(out.topic, out.topic.codec.encode(out.value), out.value.stamp_ns, out.value.seq)

    def put(self, topic: Topic, payload: bytes, stamp_ns: int, seq: int) -> None:
        pub = self._publishers.get(topic.name)
        if pub is None:
            pub = self._session.declare_publisher(
                topics.key(self._robot, topic.name),
                encoding=zenoh.Encoding(topic.codec.encoding),
                congestion_control=(zenoh.CongestionControl.DROP if topic.droppable
                                    else zenoh.CongestionControl.BLOCK),
            )
            self._publishers[topic.name] = pub
        pub.put(payload, attachment=attachment(seq, stamp_ns))
        self._counts[f"out.{topic.name}"] += 1

    def close(self) -> None:
        for sub in self._subscribers:
            sub.undeclare()
        for pub in self._publishers.values():
            pub.undeclare()
