"""Zenoh transport for one service: subscribers feeding a queue, publishers, status.

Subscriber callbacks only copy the payload into a bounded queue (Zenoh forbids
API calls or blocking inside callbacks); decoding happens in the service's main
thread. A full queue drops the sample and counts it (``drop.queue``), so a slow
stage never stalls Zenoh's receive thread and with it every other stream of the
session. Before queueing, the callback checks the sample's sequence number
against what its producer sent before (``runtime/sequence.py``): what went
missing between the producer and this process counts as ``gap.<topic>``.

A stage that falls behind (a slower computer, a burst, a long optimisation) skips to
the newest input rather than answering later and later: an input of the spec's
``skippable`` topics older than the spec's ``max_lag_s`` (its stamp against the wall clock:
only where stamps are on it, ``wall_clock_stamps``) while a newer sample of the last of them
(the *lead*: the slam's features, the mapper's slam states) already waits, is taken out
undecoded and counted as ``skip.<topic>``. The step bridges what it skipped as it
bridges a loss (the slam's next motion spans the skipped scans; the mapper's next state
carries the filter's pose across them). Only a live stream skips: one whose last lead input
arrived stamped within :data:`LIVE_WITHIN_S` of this machine's wall clock. A replay
(``lrfslam play``: recorded stamps; ``--speedup``: simulated ones) never does, so its outputs
stay those of the offline chain.

A consumer that need not answer at once (the recorder) is *batched*: its receive callbacks
queue without waking its main thread, which takes what waits when its ``get`` timeout ends,
or at once when a quarter of the queue is full. Waking a thread per message cost about as much
CPU as receiving it (docs/delivery.md); the recorder takes 7 messages per scan.

Publishers take their QoS from the topic's delivery policy (``msgs/topics.py``,
docs/delivery.md).
"""

from __future__ import annotations

import contextlib
import json
import logging
import re
import struct
import threading
import time
from collections import Counter, deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import zenoh

from lrfslam.errors import StartupError
from lrfslam.msgs import counters, topics
from lrfslam.msgs.codec import parse_encoding
from lrfslam.msgs.topics import Topic
from lrfslam.runtime import checkpoints
from lrfslam.runtime.decoding import LogOnce, decode_message
from lrfslam.runtime.sequence import SequenceTracker
from lrfslam.runtime.step import Message, Output

log = logging.getLogger(__name__)

# rmw_zenoh-style attachment: sequence number, data stamp and the publishing session's id, so
# raw consumers (the recorder) get them without decoding the payload, and every consumer can
# tell a lost message from a restarted producer.
_ATTACHMENT = struct.Struct("<QQ16s")
# Before the producer id was added (recordings and peers of older versions).
_ATTACHMENT_V0 = struct.Struct("<QQ")


@dataclass(frozen=True)
class BusConfig:
    """How to reach the Zenoh network. Defaults: a peer on loopback, multicast scouting off."""

    robot: str = "robot1"                               # namespace: every key is lrf/<robot>/...
    mode: str = "peer"                                  # peer | client | router
    connect: tuple[str, ...] = ("tcp/127.0.0.1:7447",)  # router/peers to dial (retried in the background)
    listen: tuple[str, ...] = ("tcp/127.0.0.1:0",)      # ignored in client mode
    zenoh_config: str = ""                              # optional Zenoh JSON5 file applied first
    queue_size: int = 512                               # received samples waiting for the step
    #: A stage that falls behind skips stale inputs to answer the newest (``skip.*``; each stage's
    #: ``ServiceSpec.max_lag_s`` says how stale); false: it queues them, up to ``queue_size``.
    skip_stale: bool = True
    health_period_s: float = 1.0                        # how often health/<service> is published
    #: For overload measurements only (docs/delivery.md): "<service>:<ms>" makes that service
    #: sleep <ms> after each input message. Every process of ``lrfslam up`` reads the same
    #: LRFSLAM_BUS_DEBUG_SLOW, so the service is named. Shows in the service's counters.
    debug_slow: str = ""
    join: bool = False                                  # start beside a live service of the same robot and name
    #: Also write each health status to this local file, for a container healthcheck
    #: (``lrfslam status --check-file``, lrfslam/runtime/health_file.py); "" for none.
    health_file: str = ""
    #: The data stamps are wall-clock times (the LMS200 driver's; the simulator's at speedup 1),
    #: so each stage reports the data's age at publishing, ``age.*`` (lrfslam/runtime/latency.py).
    #: ``lrfslam up --speedup`` other than 1 sets it false in every process it starts: simulated
    #: stamps run faster or slower than the wall clock and their age would mean nothing.
    wall_clock_stamps: bool = True
    #: Where a stage that keeps state (the slam, the mapper) saves it, ``<dir>/<service>.checkpoint.npz``,
    #: so a restarted one resumes (lrfslam/runtime/checkpoints.py); "" for none. ``lrfslam up`` sets
    #: the recording folder.
    checkpoint_dir: str = ""
    checkpoint_period_s: float = checkpoints.PERIOD_S   # data time between two saves

    def __post_init__(self) -> None:
        from lrfslam.errors import ConfigError
        topics.check_robot(self.robot)
        if self.mode not in ("peer", "client", "router"):
            raise ConfigError(f"bus.mode must be peer, client or router, got {self.mode!r}")
        if self.debug_slow:
            service, _, ms = self.debug_slow.partition(":")
            try:
                ok = bool(service) and float(ms) >= 0
            except ValueError:
                ok = False
            if not ok:
                raise ConfigError(f"bus.debug_slow must be <service>:<ms>, got {self.debug_slow!r}")
        if not self.checkpoint_period_s > 0:
            raise ConfigError(f"bus.checkpoint_period_s must be > 0, got {self.checkpoint_period_s}")

    def debug_delay_s(self, service: str) -> float:
        """How long ``service`` sleeps after each input (0: not slowed)."""
        name, _, ms = self.debug_slow.partition(":")
        return float(ms) / 1000.0 if self.debug_slow and name == service else 0.0


def base_config(mode: str, connect: Sequence[str], zenoh_config: str | None = None) -> zenoh.Config:
    """Every Zenoh session's configuration (services, router, tools): ``mode``, dialling ``connect``.

    ``zenoh_config`` (a JSON5 file: TLS, ACL, ...) is applied first and otherwise as it is.
    Without one, shared memory is off, as in rmw_zenoh's default: Zenoh 1.x otherwise gives
    every process that publishes a message over 3 KB a 16 MiB pool in /dev/shm, which every
    receiver on the host maps. Our messages are 0.1–10 KB, which loopback TCP carries as fast;
    the pools showed as one-time steps of 16–35 MB in router, slam and recorder an hour into a
    run (docs/delivery.md), and a container's /dev/shm is 64 MB by default. A config file that
    wants them sets ``transport/shared_memory/enabled``.
    """
    conf = zenoh.Config.from_file(zenoh_config) if zenoh_config else zenoh.Config()
    if not zenoh_config:
        conf.insert_json5("transport/shared_memory/enabled", "false")
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    # Multicast does not cross container networks and must not leave loopback in CI.
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


def zenoh_config(cfg: BusConfig) -> zenoh.Config:
    """The Zenoh session configuration for ``cfg``."""
    conf = base_config(cfg.mode, cfg.connect, cfg.zenoh_config)
    if cfg.mode != "client":
        conf.insert_json5("listen/endpoints", json.dumps(list(cfg.listen)))
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


@contextlib.contextmanager
def closing(session: zenoh.Session) -> Iterator[zenoh.Session]:
    """``with closing(session):`` closes ``session`` on exit, as ``with session:`` does, except
    that a close the network does not confirm in time (the router stopping at the same moment,
    as podman-compose's ``stop`` does; zenoh issues #2012 and #2675 show the same symptom) is one
    warning line, not an exception: by then everything was sent and every file closed, so the
    process still exits 0."""
    try:
        yield session
    finally:
        try:
            session.close()
        except zenoh.ZError as exc:
            log.warning("the bus did not confirm the session's close (%s); nothing was pending",
                        str(exc).split(" at /")[0])


class Attachment(NamedTuple):
    """What a sample carries beside its payload."""

    seq: int            # the producer's message number on this topic, from 1
    stamp_ns: int       # the data's stamp (ns)
    producer: bytes     # the publishing Zenoh session's id (16 bytes; b"" from older publishers)


NO_ATTACHMENT = Attachment(0, 0, b"")


def attachment(seq: int, stamp_ns: int, producer: bytes = b"") -> bytes:
    return _ATTACHMENT.pack(int(seq) & 0xFFFFFFFFFFFFFFFF, int(stamp_ns), producer)


def parse_attachment(data: bytes | None) -> Attachment:
    """The attachment's fields; :data:`NO_ATTACHMENT` when absent or malformed."""
    if data and len(data) == _ATTACHMENT.size:
        return Attachment(*_ATTACHMENT.unpack(data))
    if data and len(data) == _ATTACHMENT_V0.size:
        return Attachment(*_ATTACHMENT_V0.unpack(data), b"")
    return NO_ATTACHMENT


def producer_id(session: zenoh.Session) -> bytes:
    """The session's Zenoh id as 16 bytes: new for every process, so a restart is a new producer."""
    return bytes.fromhex(str(session.info.zid()).rjust(32, "0"))


def connected(session: zenoh.Session) -> bool:
    """Whether the session has at least one router or peer (what a health file reports)."""
    return any(True for _ in session.info.routers_zid()) or any(True for _ in session.info.peers_zid())


#: A lead input that arrives stamped within this of the wall clock (s, either way) is live: the
#: sensor's own time, a few milliseconds of transport and stages old. A recording's stamps are
#: minutes to years old, a simulation's at ``--speedup`` run ahead or behind.
LIVE_WITHIN_S = 2.0

_PRIORITY = {name: getattr(zenoh.Priority, name.upper()) for name in topics.PRIORITIES}


def publisher_qos(delivery: topics.Delivery) -> dict:
    """``declare_publisher`` keyword arguments for a topic's delivery policy."""
    return {
        "reliability": zenoh.Reliability.RELIABLE if delivery.reliable else zenoh.Reliability.BEST_EFFORT,
        "congestion_control": (zenoh.CongestionControl.BLOCK if delivery.congestion == "block"
                               else zenoh.CongestionControl.DROP),
        "priority": _PRIORITY[delivery.priority],
        "express": delivery.express,
    }


class _Received(NamedTuple):
    """A sample as the receive callback queues it, its attachment read once."""

    key: str
    payload: bytes
    encoding: str
    seq: int
    stamp_ns: int           # the data stamp
    received_ns: int        # monotonic clock
    received_wall_ns: int   # wall clock


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
        Shared counters (``in.*``, ``out.*``, ``error.*``), written by the main thread. What the
        receive callbacks count (``drop.queue``, ``gap.*``, ``dup.*``, ``late.*``, ``restart.*``)
        and what :meth:`get` skips (``skip.*``) is kept apart: :meth:`receive_counts`.
    skippable : tuple of Topic
        Inputs that may be skipped when older than ``max_lag_s`` while a newer sample of the
        last of them waits (the module's docstring); empty or ``max_lag_s`` 0: none.
    max_lag_s : float
        Age (s) of an input's wall-clock stamp beyond which it may be skipped.
    batched : bool
        Wake the caller of :meth:`get` only when a quarter of the queue is full; otherwise inputs
        wait for its timeout (the module's docstring).
    """

    def __init__(self, session: zenoh.Session, robot: str, inputs: tuple[Topic, ...], raw: bool,
                 queue_size: int, counts: Counter, skippable: tuple[Topic, ...] = (), max_lag_s: float = 0.0,
                 batched: bool = False) -> None:
        self._session = session
        self._robot = robot
        self._raw = raw
        self._queue: deque[_Received] = deque()
        self._queue_size = queue_size
        self._wake_at = max(1, queue_size // 4) if batched else 1
        self._ready = threading.Condition(threading.Lock())
        self._skippable = {topics.key(robot, t.name) for t in skippable} if max_lag_s > 0 else set()
        self._lead = topics.key(robot, skippable[-1].name) if self._skippable else None
        self._max_lag_ns = int(max_lag_s * 1e9)
        self._lead_newest_ns: int | None = None
        self._lead_live = False   # the last lead input arrived stamped near the wall clock
        self._counts = counts
        self._once = LogOnce(log)
        self._publishers: dict[str, zenoh.Publisher] = {}
        #: This session's producer id, in every attachment it puts.
        self.producer = producer_id(session)
        self._tracker = SequenceTracker()
        self._dropped = 0
        self._left_at_stop = 0
        self._skipped: Counter[str] = Counter()
        #: When the Zenoh callback queued the input :meth:`get` returned last (monotonic ns).
        self.received_ns = 0
        self._prefix = topics.key(robot, "")
        self._by_key = {topics.key(robot, t.name): t for t in inputs}
        keys = [topics.everything(robot)] if raw else list(self._by_key)
        self._subscribers = [session.declare_subscriber(k, self._on_sample) for k in keys]

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        att = sample.attachment
        att_bytes = att.to_bytes() if att is not None else None
        seq, stamp_ns, producer = parse_attachment(att_bytes)
        now_ns = time.time_ns()
        item = _Received(key, sample.payload.to_bytes(), str(sample.encoding), seq, stamp_ns, time.monotonic_ns(),
                         now_ns)
        with self._ready:
            if att_bytes is not None:
                self._tracker.observe(producer, key.removeprefix(self._prefix), seq)
            if len(self._queue) >= self._queue_size:
                self._dropped += 1
                return
            self._queue.append(item)
            if key == self._lead:
                self._lead_newest_ns = stamp_ns   # the last to arrive: data time going back starts afresh
                self._lead_live = abs(now_ns - stamp_ns) <= LIVE_WITHIN_S * 1e9
            if len(self._queue) >= self._wake_at:
                self._ready.notify()

    def receive_counts(self) -> Counter:
        """``drop.queue`` (samples the full queue refused), ``drop.stop`` (received but still
        queued at :meth:`discard_pending`) and the tracker's nonzero ``gap.*``, ``dup.*``,
        ``late.*``, ``restart.*`` counters: a copy."""
        with self._ready:
            counts = Counter({k: v for k, v in self._tracker.counts.items() if v})
            counts.update({k: v for k, v in ((counters.DROP_QUEUE, self._dropped), (counters.DROP_STOP, self._left_at_stop)) if v})
            counts.update(self._skipped)
            return counts

    def stop_receiving(self) -> None:
        """Undeclare the subscribers: nothing more is queued; :meth:`get` returns what already was."""
        for sub in self._subscribers:
            sub.undeclare()
        self._subscribers = []

    def discard_pending(self) -> None:
        """Empty the queue, counting what was in it as ``drop.stop``.

        A stage stopped while behind has inputs it will never handle; they are counted, not
        silently thrown away with the process.
        """
        with self._ready:
            self._left_at_stop += len(self._queue)
            self._queue.clear()

    def pending(self) -> int:
        """Received samples waiting in the queue."""
        return len(self._queue)

    def _next(self, timeout_s: float) -> _Received | None:
        """The oldest waiting sample that is not stale (see the module's docstring), or None after ``timeout_s``."""
        with self._ready:
            while True:
                if not self._queue and not self._ready.wait_for(lambda: self._queue, timeout_s):
                    return None
                item = self._queue.popleft()
                if item.key not in self._skippable:
                    return item
                newer_waits = self._lead_newest_ns is not None and self._lead_newest_ns > item.stamp_ns
                if not (self._lead_live and newer_waits) or time.time_ns() - item.stamp_ns <= self._max_lag_ns:
                    return item
                self._skipped[f"{counters.SKIP}{item.key.removeprefix(self._prefix)}"] += 1

    def get(self, timeout_s: float) -> Message | None:
        """The next decodable input, or None after ``timeout_s`` without one."""
        item = self._next(timeout_s)
        if item is None:
            return None
        key, payload, encoding, seq, stamp_ns, self.received_ns, received_wall_ns = item
        schema = parse_encoding(encoding)
        if self._raw:
            name = topics.relative(self._robot, key)
            self._counts[counters.IN_RAW] += 1
            return Message(None, payload, stamp_ns, schema, name, seq, received_wall_ns)
        topic = self._by_key.get(key)
        if topic is None:
            return None
        self._counts[f"{counters.IN}{topic.name}"] += 1
        return decode_message(topic, payload, schema, self._counts, self._once, key)

    def publish(self, out: Output) -> bytes:
        """Encode and put ``out.value`` on its topic's key with schema and attachment; the payload put."""
        payload = out.topic.codec.encode(out.value)
        self.put(out.topic, payload, out.value.stamp_ns, out.value.seq)
        return payload

    def publisher(self, topic: Topic) -> zenoh.Publisher:
        """``topic``'s publisher, declared on first use with the topic's delivery policy."""
        pub = self._publishers.get(topic.name)
        if pub is None:
            pub = self._session.declare_publisher(topics.key(self._robot, topic.name),
                                                  encoding=zenoh.Encoding(topic.codec.encoding),
                                                  **publisher_qos(topic.delivery))
            self._publishers[topic.name] = pub
        return pub

    def put(self, topic: Topic, payload: bytes, stamp_ns: int, seq: int) -> None:
        """Put ``payload`` on ``topic``'s key; ``seq`` numbers the topic's messages 1, 2, 3, … (gaps are losses)."""
        self.publisher(topic).put(payload, attachment=attachment(seq, stamp_ns, self.producer))
        self._counts[f"{counters.OUT}{topic.name}"] += 1

    def close(self) -> None:
        for sub in self._subscribers:
            sub.undeclare()
        for pub in self._publishers.values():
            pub.undeclare()
