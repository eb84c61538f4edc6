"""``lrfslam play RECORDING [--rate X | --rate max] [--topics T ...] [--loop]``: a recording onto the live bus.

What ``ros2 bag play`` does for ROS 2: the recorded messages go out on Zenoh under their own keys
(``lrf/<robot>/<topic>``), with their recorded data stamps and payloads as recorded, so the live
services (``lrfslam up --skip sensor``, or ``lrfslam denoise --connect ...`` and the others one by
one) process them as if the sensor were running. RECORDING is an MCAP file, a recording folder
(its segments in order) or several files, read as one stream in data-stamp order.

What is played (``--topics``, default the sensor's outputs that the recording holds: ``scan``,
``odom``, ``truth``): the recorded inputs of the pipeline, not what its stages made of them, which
the live stages publish themselves under the same keys. A topic a live service of the robot
publishes is refused (both would be on one key), and so are ``health/*`` (the recorded services'
wall-clock status) and the ``/foxglove/...`` views.

Pacing:

``--rate X``
    X times the recorded pace, by the data stamps (src/lrfslam/runtime/pacing.py,
    ``RateSchedule``), waited for on the monotonic clock.
``--rate max``
    As fast as the slowest live stage goes, without a drop: at most ``--window`` scans are in
    flight, played and not yet answered on ``--wait-for`` (by default the first output of the
    deepest live stage fed by the played topics: ``map/pose``, ``slam/state``, ``features`` or
    ``scan/filtered``); each answer, matched by the scan's data stamp, frees its scan and every
    scan before it (``CreditWindow``). Every stage therefore has at most ``--window`` scans queued,
    far below its queue (``bus.queue_size``). No answer for ``--timeout`` seconds with scans in
    flight fails the command (exit 1), saying whether the stage is still alive.

Sequence numbers: play numbers each topic's messages itself, 1, 2, 3, ... over all loops, under
its own producer id (docs/delivery.md): a consumer that saw another producer on the key before
(the sensor, an earlier play) counts one ``restart.<topic>``, and then a gap is a message lost
between play and it, never a hole in the recording. ``--loop`` plays the recording again and
again (until Ctrl-C) with its recorded stamps, as ``ros2 bag play --loop`` does: the stages see
the data time go back at each new loop.

At the end (after waiting up to ``--timeout`` for the watched stage to answer the last scan),
one line on stdout: messages and scans played, seconds (monotonic clock, first message to the last
answer), their rates and the pace against the recording; how many scans the watched stage
answered; what the live services dropped and missed meanwhile (their status counters before and
after). Exit codes: 0 done; 1 the pipeline stalled, or with ``--rate max`` a live service dropped
or missed messages; 2 bad input or usage (one line); 130/143 stopped by SIGINT/SIGTERM.
"""

from __future__ import annotations

import argparse
import faulthandler
import logging
import queue
import signal
import threading
import time
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import zenoh

from lrfslam import services
from lrfslam.errors import ConfigError, DecodeError, LrfSlamError, StartupError
from lrfslam.msgs import codec, counters, topics
from lrfslam.msgs import types as t
from lrfslam.msgs.topics import Topic
from lrfslam.runtime.bus import BusConfig, ZenohBus, closing, parse_attachment
from lrfslam.runtime.decoding import LogOnce
from lrfslam.runtime.pacing import (
    CreditWindow,
    RateSchedule,
    StageTopics,
    watched_stage,
)
from lrfslam.runtime.recording import (
    RecordingSource,
    read_metadata,
    read_recording,
    recording_files,
)
from lrfslam.runtime.runner import (
    BACKLOG,
    STOP_STACKS_AFTER_S,
    live_services,
    setup_logging,
)
from lrfslam.tools.status import client_config, query_status

log = logging.getLogger("lrfslam.play")

DEFAULT_WINDOW = 8
DEFAULT_TIMEOUT_S = 10.0
#: How long play waits for the live services' subscriptions to reach its publishers, s.
MATCH_WAIT_S = 2.0
#: Seconds between progress lines.
PROGRESS_PERIOD_S = 10.0
#: With --rate max, no scan goes out while a live service has more inputs than this queued (a quarter
#: of ``bus.queue_size``: what arrives while its status is on the way still fits).
BACKLOG_HIGH = BusConfig.queue_size // 4
#: How often the live services' backlogs are asked for, s.
BACKLOG_POLL_S = 0.05


def sensor_topics() -> tuple[Topic, ...]:
    """The raw inputs of the pipeline: what the sensor publishes."""
    return services.spec("sensor").outputs


def stage_topics() -> list[StageTopics]:
    """The services in pipeline order, by the names of their input and output topics."""
    return [StageTopics(name, tuple(tp.name for tp in spec.inputs), tuple(tp.name for tp in spec.outputs))
            for name in services.NAMES for spec in (services.spec(name),)]


def answer_topics() -> dict[str, str]:
    """Topics that answer for each scan, by name: each processing stage's first output -> the stage."""
    return {s.outputs[0]: s.name for s in stage_topics() if s.inputs and s.outputs}


def parse_rate(text: str) -> float | None:
    """``--rate``: a positive number, or ``max`` (None)."""
    if text.strip().lower() == "max":
        return None
    try:
        rate = float(text)
        RateSchedule(rate)
    except (ValueError, ConfigError):
        raise argparse.ArgumentTypeError(f"must be a positive number or 'max', got {text!r}") from None
    return rate


def played_topics(names: Sequence[str] | None) -> tuple[Topic, ...]:
    """The topics ``--topics`` names (comma- or space-separated), or the sensor's by default.

    Raises
    ------
    ConfigError
        A name is not a data topic (``health/*``, ``/foxglove/...`` and unknown names are refused).
    """
    if not names:
        return sensor_topics()
    wanted = [n.strip() for item in names for n in item.split(",") if n.strip()]
    known = {tp.name: tp for tp in topics.DATA_TOPICS}
    for name in wanted:
        if name not in known:
            why = ("health is each service's own wall-clock status" if topics.is_health(name)
                   else "Foxglove's views are made from the data topics" if topics.is_foxglove(name)
                   else "unknown topic")
            raise ConfigError(f"cannot play {name!r} ({why}); data topics: {', '.join(known)}")
    return tuple(known[n] for n in dict.fromkeys(wanted))


def check_collisions(played: Iterable[Topic], alive: Iterable[str]) -> None:
    """Refuse to play a topic a live service of the robot publishes itself.

    Raises
    ------
    ConfigError
        Naming the service and the topics.
    """
    names = {tp.name for tp in played}
    for service in sorted(alive):
        if service not in services.NAMES:
            continue
        clash = [tp.name for tp in services.spec(service).outputs if tp.name in names]
        if clash:
            hint = ("stop it (lrfslam up --skip sensor runs the pipeline without one)" if service == "sensor"
                    else "leave them out with --topics")
            raise ConfigError(f"{service} is alive on this robot and publishes {', '.join(clash)} itself; both on "
                              f"one key would mix: {hint}, or play to another --robot")


def choose_watched(wait_for: str | None, played: Iterable[Topic], alive: Iterable[str]) -> Topic | None:
    """The topic whose messages answer for the played scans: ``wait_for``, or the deepest live stage's.

    Raises
    ------
    ConfigError
        ``wait_for`` is no stage's per-scan output, or its stage is not alive.
    """
    answers = answer_topics()
    alive = set(alive)
    if wait_for is not None:
        if wait_for not in answers:
            raise ConfigError(f"--wait-for {wait_for!r}: must be one of {', '.join(answers)} (a stage's output "
                              "per scan)")
        if answers[wait_for] not in alive:
            raise ConfigError(f"--wait-for {wait_for}: {answers[wait_for]} is not alive on this robot")
        return topics.by_name(wait_for)
    stage = watched_stage(stage_topics(), {tp.name for tp in played}, alive)
    return None if stage is None else topics.by_name(stage.outputs[0])


def losses(before: Sequence[t.ServiceStatus], after: Sequence[t.ServiceStatus]) -> dict[str, tuple[int, int]]:
    """Per service: (dropped, gaps) counted between the two snapshots of its status (``drop.*``, ``gap.*``).

    A service whose process changed (or that was not there before) counts from zero.
    """
    first = {(s.service, s.pid, s.host): s.counters for s in before}
    out = {}
    for s in after:
        c0 = first.get((s.service, s.pid, s.host), {})
        out[s.service] = (counters.total(s.counters, counters.DROP) - counters.total(c0, counters.DROP),
                          counters.total(s.counters, counters.GAP) - counters.total(c0, counters.GAP))
    return out


class BacklogWatch:
    """The live services' input backlogs (their status counter ``queue.pending``), asked for every
    :data:`BACKLOG_POLL_S` s in a thread: the backpressure of services that answer no scan (the recorder)."""

    def __init__(self, session: zenoh.Session, robot: str) -> None:
        self._session, self._robot = session, robot
        self._lock = threading.Lock()
        self._pending: dict[str, int] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="backlog", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            pending = {}
            for reply in self._session.get(topics.status(self._robot, topics.ANY), timeout=1.0,
                                           target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE):
                if reply.ok is None:
                    continue
                try:
                    st = codec.SERVICE_STATUS.decode(reply.ok.payload.to_bytes())
                except DecodeError:
                    continue
                pending[st.service] = int(st.counters.get(BACKLOG, 0))
            with self._lock:
                self._pending = pending
            self._stop.wait(BACKLOG_POLL_S)

    def highest(self) -> tuple[str, int]:
        """The service with the most inputs queued, and how many (``("", 0)`` before the first answer)."""
        with self._lock:
            return max(self._pending.items(), key=lambda kv: kv[1], default=("", 0))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)


class Stalled(LrfSlamError):
    """The watched stage answered no scan for the timeout while scans were in flight."""


@dataclass
class Summary:
    """What a play did: messages and scans played, seconds (monotonic), data seconds played, loops begun."""

    messages: int = 0
    scans: int = 0
    seconds: float = 0.0
    data_s: float = 0.0
    loops: int = 1


class Player:
    """Plays ``source``'s ``played`` topics onto ``session`` for ``robot``.

    Parameters
    ----------
    rate : float or None
        ``--rate X``; None for ``--rate max`` (needs ``watched``).
    watched : Topic or None
        The output whose messages answer for the scans; None: nothing waited for.
    window : int
        ``--rate max``: scans in flight at most.
    timeout_s : float
        No answer this long with scans in flight: :class:`Stalled` (``--rate max``), a warning at the end (``--rate X``).
    """

    def __init__(self, session: zenoh.Session, robot: str, source: RecordingSource, played: Sequence[Topic],
                 rate: float | None, watched: Topic | None, window: int, timeout_s: float, loop: bool,
                 stop: threading.Event) -> None:
        self.session, self.robot, self.source = session, robot, source
        self.played = {tp.name: tp for tp in played}
        self.rate, self.watched, self.timeout_s, self.loop, self.stop = rate, watched, timeout_s, loop, stop
        self.counts: Counter = Counter()
        self.bus = ZenohBus(session, robot, (), False, 1, self.counts)
        self.window = CreditWindow(window if rate is None else 2**62)
        self.schedule = RateSchedule(rate) if rate is not None else None
        self.summary = Summary()
        self._seq: Counter = Counter()
        self._once = LogOnce(log)
        # Not a SimpleQueue: on CPython 3.11 its get(timeout) waits forever when a signal handler
        # outlasts the timeout, and Ctrl-C lands here while the main thread waits for answers.
        self._answers: queue.Queue[int] = queue.Queue()
        self._progress_ns = 0
        self._sub = (session.declare_subscriber(topics.key(robot, watched.name), self._on_answer)
                     if watched is not None else None)
        self.backlog = BacklogWatch(session, robot) if rate is None else None

    def _on_answer(self, sample: zenoh.Sample) -> None:
        # Zenoh's thread: only hand the stamp over.
        att = sample.attachment
        stamp = parse_attachment(att.to_bytes() if att is not None else None).stamp_ns
        if stamp:
            self._answers.put(stamp)

    def wait_for_subscribers(self, alive: Iterable[str]) -> None:
        """Declare the publishers, and give the subscriptions of the live services that take a played
        topic up to :data:`MATCH_WAIT_S` to reach them, so that the first messages find their consumers."""
        pubs = {name: self.bus.publisher(tp) for name, tp in self.played.items()}
        specs = [services.spec(n) for n in alive if n in services.NAMES]
        taken = {name for name in pubs if any(sp.raw_inputs or name in {tp.name for tp in sp.inputs} for sp in specs)}
        deadline = time.monotonic() + MATCH_WAIT_S
        while not self.stop.is_set() and time.monotonic() < deadline:
            if all(pubs[name].matching_status.matching for name in taken):
                return
            time.sleep(0.01)
        for name in sorted(taken):
            if not pubs[name].matching_status.matching:
                log.warning("no subscriber of %s has reached play yet", topics.key(self.robot, name))

    def _take_answers(self, timeout_s: float) -> None:
        """Apply the answers that came, waiting up to ``timeout_s`` for the first."""
        try:
            stamp = self._answers.get(timeout=timeout_s) if timeout_s > 0 else self._answers.get_nowait()
            while True:
                if self.window.acknowledge(stamp):
                    self._progress_ns = time.monotonic_ns()
                stamp = self._answers.get_nowait()
        except queue.Empty:
            pass

    def _stalled(self) -> bool:
        return bool(self.window.in_flight) and time.monotonic_ns() - self._progress_ns > self.timeout_s * 1e9

    def _stall_error(self) -> Stalled:
        answers = answer_topics()
        stage = answers[self.watched.name]
        alive = stage in live_services(self.session, self.robot, stage)
        state = "is alive but answered nothing" if alive else "is gone (its liveliness token went)"
        return Stalled(f"the pipeline stalled: no {self.watched.name} for {self.timeout_s:g} s with "
                       f"{self.window.in_flight} scans in flight ({self.window.acknowledged} of "
                       f"{self.window.sent} answered); {stage} {state}")

    def _wait_until(self, start_ns: int, due_ns: int) -> None:
        while not self.stop.is_set():
            left = start_ns + due_ns - time.monotonic_ns()
            if left <= 0:
                return
            self._take_answers(min(left / 1e9, 0.1))

    def _wait_for_room(self) -> None:
        """Until a scan may go out: the window has room and no live service has a backlog."""
        high_since = None
        while not self.stop.is_set():
            service, pending = self.backlog.highest() if self.backlog is not None else ("", 0)
            if not self.window.full and pending <= BACKLOG_HIGH:
                return
            self._take_answers(0.01 if pending > BACKLOG_HIGH else 0.1)
            if self._stalled():
                raise self._stall_error()
            if pending <= BACKLOG_HIGH:
                high_since = None
            elif high_since is None:
                high_since = time.monotonic()
                self.counts["held.backlog"] += 1
            elif time.monotonic() - high_since > self.timeout_s:
                raise Stalled(f"the pipeline stalled: {service} has had more than {BACKLOG_HIGH} inputs queued "
                              f"for {self.timeout_s:g} s ({pending} now)")

    def _scan_stamp(self, payload: bytes, schema: str) -> int | None:
        try:
            return topics.SCAN.codec.decode(payload, schema).stamp_ns
        except DecodeError as exc:
            self.counts["undecodable.scan"] += 1
            self._once.warning("undecodable", "scan", "a recorded scan does not decode (%s); played as recorded, "
                               "not waited for", exc)
            return None

    def run(self) -> Summary:
        """Play until the end (every loop until stopped with ``loop``); then wait for the last answers.

        Raises
        ------
        Stalled
            With ``--rate max``: no answer, or a backlog not going down, for the timeout.
        """
        started = time.monotonic_ns()
        try:
            self._play(started)
            self._drain()
        finally:
            self.summary.seconds = (time.monotonic_ns() - started) / 1e9
            if notes := {k: v for k, v in self.counts.items() if not k.startswith(counters.OUT)}:
                log.info("also: %s", ", ".join(f"{k} {v}" for k, v in sorted(notes.items())))
        return self.summary

    def _play(self, started: int) -> None:
        next_progress = time.monotonic() + PROGRESS_PERIOD_S
        last_ns = None
        while not self.stop.is_set():
            played_this_loop = 0
            for m in read_recording(self.source, list(self.played)):
                if self.stop.is_set():
                    break
                topic = self.played[m.topic]
                if m.schema != topic.schema:
                    self.counts[f"skipped.schema.{m.topic}"] += 1
                    self._once.warning("schema", m.topic, "skipping recorded %s messages of schema %r (this build "
                                       "publishes %s)", m.topic, m.schema, topic.schema)
                    continue
                if self.schedule is not None:
                    self._wait_until(started, self.schedule.due_ns(m.stamp_ns))
                if topic is topics.SCAN and self.watched is not None \
                        and (stamp := self._scan_stamp(m.data, m.schema)) is not None:
                    self._wait_for_room()
                    if self.stop.is_set():
                        break
                    if not self.window.in_flight:
                        self._progress_ns = time.monotonic_ns()
                    self.window.send(stamp)
                self._seq[m.topic] += 1
                self.bus.put(topic, m.data, m.stamp_ns, self._seq[m.topic])
                played_this_loop += 1
                self.summary.messages += 1
                self.summary.scans += topic is topics.SCAN
                if last_ns is not None and m.stamp_ns > last_ns:
                    self.summary.data_s += (m.stamp_ns - last_ns) / 1e9
                last_ns = m.stamp_ns
                self._take_answers(0)
                if time.monotonic() >= next_progress:
                    next_progress += PROGRESS_PERIOD_S
                    secs = (time.monotonic_ns() - started) / 1e9
                    log.info("played %d messages (%d scans) in %.0f s: %.1f scans/s", self.summary.messages,
                             self.summary.scans, secs, self.summary.scans / secs)
            if not self.loop or not played_this_loop or self.stop.is_set():
                break
            self.summary.loops += 1
            last_ns = None   # the next loop's stamps start over: no data time between the loops
            if self.schedule is not None:
                self.schedule.next_loop()

    def _drain(self) -> None:
        """Wait for the watched stage to answer the scans still in flight (up to the timeout without one)."""
        if self.watched is None:
            return
        if self.rate is not None:
            # Paced, nothing waited for answers so far: the timeout counts from the last message.
            self._progress_ns = time.monotonic_ns()
        while self.window.in_flight and not self.stop.is_set():
            self._take_answers(0.1)
            if self._stalled():
                if self.rate is None:
                    raise self._stall_error()
                log.warning("%s answered %d of the %d scans played; the last %d not within %g s",
                            self.watched.name, self.window.acknowledged, self.window.sent, self.window.in_flight,
                            self.timeout_s)
                return

    def close(self) -> None:
        if self.backlog is not None:
            self.backlog.close()
        if self._sub is not None:
            self._sub.undeclare()
        self.bus.close()


def summary_line(s: Summary, watched: Topic | None, window: CreditWindow, lost: dict[str, tuple[int, int]],
                 stopped: str | None) -> str:
    """The one line printed at the end."""
    secs = max(s.seconds, 1e-9)
    parts = [(f"lrfslam play: {s.messages} messages ({s.scans} scans) in {s.seconds:.2f} s: "
              f"{s.messages / secs:.1f} messages/s, {s.scans / secs:.1f} scans/s, "
              f"{s.data_s / secs:.2f} x the recorded pace")]
    if s.loops > 1:
        parts.append(f"{s.loops} loops")
    if watched is not None:
        parts.append(f"{watched.name} answered {window.acknowledged} of {window.sent} scans")
    if lost:
        dropped, gaps = sum(d for d, _ in lost.values()), sum(g for _, g in lost.values())
        where = [f"{name} {d}/{g}" for name, (d, g) in sorted(lost.items()) if d or g]
        parts.append(f"live services dropped {dropped}, gaps {gaps}" + (f" ({', '.join(where)})" if where else ""))
    if stopped:
        parts.append(f"stopped by {stopped}")
    return "; ".join(parts)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="lrfslam play", description=__doc__.splitlines()[0])
    p.add_argument("recording", nargs="+", type=Path, metavar="RECORDING",
                   help="an MCAP file, a recording folder, or several files (one stream)")
    p.add_argument("-r", "--rate", type=parse_rate, default=1.0, metavar="X|max",
                   help="X times the recorded pace (default 1), or max: as fast as the live stages answer, "
                        "without drops")
    p.add_argument("--topics", nargs="+", metavar="TOPIC",
                   help="topics to play (default: the sensor's, scan odom truth, those the recording holds)")
    p.add_argument("-l", "--loop", action="store_true", help="play again from the start, until Ctrl-C")
    p.add_argument("--robot", help="robot namespace of the keys (default: the recording's robot, else "
                                   f"{BusConfig.robot})")
    p.add_argument("-e", "--connect", action="append", metavar="ENDPOINT",
                   help="Zenoh router to join (repeatable; default tcp/127.0.0.1:7447)")
    p.add_argument("--zenoh-config", metavar="FILE", help="Zenoh JSON5 config applied first (TLS, ...)")
    p.add_argument("--wait-for", metavar="TOPIC",
                   help="the stage output whose messages answer for the scans (default: the deepest live "
                        "stage's: map/pose, slam/state, features or scan/filtered)")
    p.add_argument("--window", type=int, default=DEFAULT_WINDOW, metavar="N",
                   help=f"with --rate max: scans in flight at most (default {DEFAULT_WINDOW}; keep it below the "
                        "scans the slam waits for odometry, 20, for results independent of timing)")
    p.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT_S, metavar="S",
                   help=f"seconds without an answer that count as a stall (default {DEFAULT_TIMEOUT_S:g})")
    p.add_argument("--log-level", default=None, help="DEBUG, INFO, WARNING, ERROR")
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    setup_logging("play", args.log_level)
    if args.window < 1:
        raise ConfigError(f"--window must be at least 1, got {args.window}")
    if not args.timeout > 0:
        raise ConfigError(f"--timeout must be > 0 s, got {args.timeout}")
    source = args.recording[0] if len(args.recording) == 1 else args.recording
    recording_files(source)   # missing, empty or not MCAP: one line before anything goes out
    played = played_topics(args.topics)
    robot = topics.check_robot(args.robot or read_metadata(source).get("lrfslam", {}).get("robot")
                               or BusConfig.robot)
    endpoints = args.connect or list(BusConfig.connect)
    zenoh.init_log_from_env_or("error")
    try:
        session = zenoh.open(client_config(endpoints, args.zenoh_config))
    except zenoh.ZError as exc:
        raise StartupError(f"cannot reach {','.join(endpoints)}: {str(exc).split(' at /')[0].rstrip('! ')}") from None
    stop = threading.Event()
    signals: list[int] = []

    def on_signal(signum, _frame) -> None:
        signals.append(signum)
        if not stop.is_set():   # a stop that hangs says where (as a service's does)
            faulthandler.dump_traceback_later(STOP_STACKS_AFTER_S)
        stop.set()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)
    with closing(session):
        alive = set(live_services(session, robot))
        check_collisions(played, alive)
        watched = choose_watched(args.wait_for, played, alive)
        if args.rate is None and watched is None:
            raise ConfigError(f"--rate max waits for a live stage, and robot {robot!r} has none fed by "
                              f"{', '.join(tp.name for tp in played)} (start them, e.g. lrfslam up --skip sensor, "
                              "or play with --rate X)")
        if args.rate is None and topics.SCAN not in played:
            raise ConfigError("--rate max counts scans in flight: play scan too")
        log.info("playing %s to robot %s via %s: %s at %s%s", source if isinstance(source, Path) else
                 ", ".join(map(str, source)), robot, ",".join(endpoints), ", ".join(tp.name for tp in played),
                 "max rate" if args.rate is None else f"{args.rate:g} x", f", waiting for {watched.name}"
                 if watched is not None else "")
        before = query_status(session, robot, 2.0)[1] if alive else []
        player = Player(session, robot, source, played, args.rate, watched, args.window, args.timeout, args.loop,
                        stop)
        code = 0
        try:
            player.wait_for_subscribers(alive)
            player.run()
        except Stalled as exc:
            log.error("%s", exc)
            code = 1
        finally:
            player.close()
        lost = losses(before, query_status(session, robot, 2.0)[1]) if alive else {}
    faulthandler.cancel_dump_traceback_later()
    stopped = signal.Signals(signals[0]).name if signals else None
    print(summary_line(player.summary, watched, player.window, lost, stopped), flush=True)
    if stopped:
        return 128 + signals[0]
    if code == 0 and args.rate is None and any(d or g for d, g in lost.values()):
        log.error("with --rate max nothing may be lost, yet live services dropped or missed messages (see above)")
        code = 1
    return code
