"""The one service runner: arguments, config layering, logging, signals, Zenoh, replay.

``lrfslam <service> [options]`` ends up in :func:`main`. Live, it opens a Zenoh
session, refuses to start (one error line, exit 2) where the robot already has this
service alive, unless ``--join``, declares a liveliness token ``lrf/<robot>/alive/<service>``, answers
``lrf/<robot>/svc/<service>/status`` (and ``lrf/<robot>/latest/<topic>`` for the outputs its spec
names in ``latest``), publishes ``lrf/<robot>/health/<service>``
and drives the service's step until SIGTERM/SIGINT. With ``--replay IN`` (an MCAP
file, a recording folder, or several files) it drives the same step over the
recording, as fast as the CPU allows, and writes the outputs to ``--out OUT.mcap``.
Live, the step runs inside the same in-process chain as a replay (:func:`run_services`), which also
hosts several services in one process (``lrfslam group``, src/lrfslam/tools/group.py).
"""

from __future__ import annotations

import argparse
import faulthandler
import logging
import os
import signal
import socket
import threading
import time
from collections import Counter
from collections.abc import Collection, Mapping, Sequence
from pathlib import Path
from typing import Any

import zenoh

from lrfslam.errors import ConfigError, LrfSlamError, StartupError
from lrfslam.msgs import codec, counters, topics
from lrfslam.msgs import types as t
from lrfslam.runtime import config as config_mod
from lrfslam.runtime import health_file
from lrfslam.runtime.bus import (
    BusConfig,
    ZenohBus,
    attachment,
    closing,
    connected,
    open_session,
    zenoh_config,
)
from lrfslam.runtime.chain import Chain, Item, Stage, replay_recording
from lrfslam.runtime.decoding import LogOnce
from lrfslam.runtime.latency import LatencyWindow
from lrfslam.runtime.recording import RecordingSource, describe_source
from lrfslam.runtime.step import Message, ServiceSpec, Source

log = logging.getLogger("lrfslam")

LOG_FORMAT = "%(asctime)s %(levelname)s [{service}] %(name)s: %(message)s"

# A clean stop takes well under a second (the slam checkpoint a few). One still running after
# this long is stuck somewhere; its thread stacks go to stderr before the engine's SIGKILL
# (10 s by default) leaves nothing but exit code 137 to go on.
STOP_STACKS_AFTER_S = 5.0
#: On a stop, inputs already received are still handled for this long; the rest are counted
#: (``drop.stop``). Well inside ``lrfslam up``'s 15 s before SIGKILL.
STOP_DRAIN_S = 2.0
#: Status counter holding the service's input backlog: samples queued, not yet handled (a gauge).
BACKLOG = "queue.pending"
#: How long a same-named service's token that nobody answers for may stay before this one refuses to start, s
#: (a little over Zenoh's default lease, after which the token of a silently dead process goes).
STALE_TOKEN_S = 12.0


def add_common_arguments(parser: argparse.ArgumentParser) -> None:
    """Flags every service (and ``lrfslam up``) understands."""
    parser.add_argument("--config", metavar="FILE", help="TOML config file ([bus] and [<service>] tables)")
    parser.add_argument("--set", dest="sets", action="append", default=[], metavar="NAME=VALUE",
                        help="override one setting of the service (dotted for nested: histogram.bin_deg=10)")
    parser.add_argument("--robot", help="robot namespace (keys lrf/<robot>/...)")
    parser.add_argument("-m", "--mode", choices=("peer", "client", "router"), help="Zenoh mode")
    parser.add_argument("-e", "--connect", action="append", metavar="ENDPOINT",
                        help="Zenoh endpoint to connect to, e.g. tcp/zenohd:7447 (repeatable)")
    parser.add_argument("-l", "--listen", action="append", metavar="ENDPOINT",
                        help="Zenoh endpoint to listen on (repeatable)")
    parser.add_argument("--zenoh-config", metavar="FILE", help="Zenoh JSON5 config applied first")
    parser.add_argument("--join", action="store_true", default=None,
                        help="start even though the same service of the same robot is alive on the network "
                             "(without it: one error line, exit 2)")
    parser.add_argument("--log-level", default=None, help="DEBUG, INFO, WARNING, ERROR")


def bus_config(args: argparse.Namespace, file: Mapping, env: Mapping[str, str]) -> BusConfig:
    """Defaults < file [bus] < LRFSLAM_BUS_* < flags."""
    sets = [f"{name}={value}" for name, value in (
        ("robot", args.robot), ("mode", args.mode), ("zenoh_config", args.zenoh_config),
        ("connect", ",".join(args.connect) if args.connect else None),
        ("listen", ",".join(args.listen) if args.listen else None),
        ("join", "true" if getattr(args, "join", None) else None),
        ("health_file", getattr(args, "health_file", None)),
        ("checkpoint_dir", getattr(args, "checkpoint_dir", None)),
    ) if value]
    return config_mod.load(BusConfig, table=file.get("bus", {}), env=env,
                           env_prefix=f"{config_mod.ENV_PREFIX}_BUS", sets=sets)


def flag_sets(spec: ServiceSpec, args: argparse.Namespace) -> list[str]:
    """``--set`` values, then the service's own flags (``--device X`` is ``--set device=X``)."""
    return list(args.sets) + [f"{name}={getattr(args, name)}" for _, name, _ in spec.flags
                              if getattr(args, name, None) is not None]


def setup_logging(service: str, level: str | None) -> None:
    logging.basicConfig(level=(level or os.environ.get("LRFSLAM_LOG_LEVEL", "INFO")).upper(),
                        format=LOG_FORMAT.format(service=service))


def service_parser(spec: ServiceSpec) -> argparse.ArgumentParser:
    """The arguments of ``lrfslam <service>``."""
    parser = argparse.ArgumentParser(prog=f"lrfslam {spec.name}", description=spec.summary)
    add_common_arguments(parser)
    parser.add_argument("--replay", nargs="+", metavar="IN",
                        help="run on a recording instead of the bus: an MCAP file, a recording folder, or "
                             "several files (one stream)")
    parser.add_argument("--out", metavar="OUT.mcap", help="with --replay: write the outputs here")
    parser.add_argument("--health-file", metavar="FILE",
                        help="also write the service's health to FILE every health period, for a container "
                             "healthcheck: lrfslam status --check-file FILE")
    parser.add_argument("--checkpoint-dir", metavar="DIR",
                        help="where a stage that keeps state (slam, mapper) saves it and resumes from, "
                             "DIR/<service>.checkpoint.npz (same as bus.checkpoint_dir)")
    for flag, name, help_text in spec.flags:
        parser.add_argument(flag, dest=name, help=f"{help_text} (same as --set {name}=...)")
    return parser


def main(spec: ServiceSpec, argv: list[str] | None = None, tables: Collection[str] | None = None) -> int:
    """``lrfslam <service>``; ``tables``: the config-file tables there may be (others are errors)."""
    parser = service_parser(spec)
    args = parser.parse_args(argv)
    setup_logging(spec.name, args.log_level)
    try:
        file = config_mod.read_file(args.config, tables)
        bus = bus_config(args, file, os.environ)
        cfg = config_mod.service_config(spec, sets=flag_sets(spec, args), file=file, env=os.environ)
        log.info("config %s", config_mod.to_json(cfg))
        if args.replay:
            counts = replay(spec, cfg, bus.robot, [Path(p) for p in args.replay], Path(args.out) if args.out else None)
            log.info("replay done: %s", ", ".join(f"{k}={v}" for k, v in sorted(counts.items())))
            return 0
        if args.out:
            raise ConfigError("--out needs --replay")
        return run_live(spec, cfg, bus)
    except (LrfSlamError, OSError) as exc:
        log.error("%s", exc)
        return 2


#: The stages a group may hold: those that take inputs and answer each at once (the sensor is a
#: source with its own device or simulator; the recorder takes everything in batches).
GROUPABLE = ("denoise", "features", "slam", "mapper")


def group_stages(text: str) -> list[str]:
    """``"slam,denoise"`` -> the stages in pipeline order.

    Raises
    ------
    ConfigError
        A name that is no groupable stage, a repeated one, or fewer than two.
    """
    names = [n.strip() for n in text.split(",") if n.strip()]
    bad = [n for n in names if n not in GROUPABLE]
    if bad or len(set(names)) != len(names) or len(names) < 2:
        raise ConfigError(f"a group is two or more different stages of {', '.join(GROUPABLE)}, comma-separated; "
                          f"got {text!r}")
    return sorted(names, key=GROUPABLE.index)


# ---- replay ------------------------------------------------------------------------------


def replay(spec: ServiceSpec, cfg: Any, robot: str, in_path: RecordingSource, out_path: Path | None) -> Counter:
    """Run ``spec``'s step over the recording ``in_path`` (file, folder or files); write its outputs to ``out_path``.

    A one-stage :func:`~lrfslam.runtime.chain.replay_recording`: the same input
    gives the same output bytes.
    """
    if not spec.inputs and not spec.raw_inputs:
        raise ConfigError(f"{spec.name} is a source; it has no inputs to replay")
    metadata = {"lrfslam": {"robot": robot, "service": spec.name, "replay_of": describe_source(in_path),
                            "config": config_mod.to_json(cfg)}}
    counts = replay_recording([Stage(spec, cfg)], robot, in_path, out_path, copy_inputs=False, metadata=metadata)
    merged = Counter(counts[spec.name])
    merged.update({f"input.{k}": v for k, v in counts["input"].items()})
    return merged


# ---- live --------------------------------------------------------------------------------


def install_signal_handlers(stop: threading.Event) -> None:
    """SIGTERM and SIGINT set ``stop``; the loop finishes its message and exits cleanly.

    A stop that has not finished ``STOP_STACKS_AFTER_S`` later prints every thread's stack.
    """
    def handler(signum, _frame) -> None:
        log.info("received %s, stopping", signal.Signals(signum).name)
        if not stop.is_set():
            faulthandler.dump_traceback_later(STOP_STACKS_AFTER_S)
        stop.set()
    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGINT, handler)


class _Hosted:
    """One service of a live process: its step's status, health, liveliness and latest answers.

    A process hosts one service, or several sharing one Zenoh session (``lrfslam group``): each
    keeps its own token, status queryable, health and counters, so supervisors and viewers see the
    same services either way.
    """

    def __init__(self, session: zenoh.Session, robot: str, spec: ServiceSpec, cfg: Any, wall_clock: bool) -> None:
        self.spec = spec
        self.cfg = cfg
        self.name = spec.name
        self.health_topic = topics.health(spec.name)
        self.counts: Counter = Counter()
        self.latency = LatencyWindow("latency")
        self.age = LatencyWindow("age") if wall_clock else None
        self.takes = {tp.name for tp in spec.inputs}
        #: When the input being handled was received (monotonic ns; None: a source's poll, no latency),
        #: cleared once the first output for it went out.
        self.pending_ns: int | None = None
        self.answering = False
        self.last_data = 0
        self.status_q = session.declare_queryable(topics.status(robot, spec.name))
        # The newest of the outputs a late viewer needs, kept encoded.
        self.newest: dict[str, tuple[bytes, int, int]] = {}   # topic name -> (payload, seq, stamp ns)
        self.latest_qs = {tp.name: session.declare_queryable(topics.latest(robot, tp.name)) for tp in spec.latest}
        self.token = None
        self.next_health = 0.0   # monotonic s

    def close(self) -> None:
        self.status_q.undeclare()
        for queryable in self.latest_qs.values():
            queryable.undeclare()
        if self.token is not None:
            self.token.undeclare()


def run_live(spec: ServiceSpec, cfg: Any, bus_cfg: BusConfig, stop: threading.Event | None = None) -> int:
    """Run ``spec`` on Zenoh until ``stop`` is set (by a signal, unless given)."""
    return run_services([(spec, cfg)], bus_cfg, stop)


def run_services(hosted: Sequence[tuple[ServiceSpec, Any]], bus_cfg: BusConfig,
                 stop: threading.Event | None = None) -> int:
    """Run the services ``hosted`` (in pipeline order) in this process on Zenoh until ``stop`` is set.

    One service is what ``lrfslam <service>`` runs. Several share one session and one in-process
    :class:`~lrfslam.runtime.chain.Chain`: an input from the bus goes through their steps in turn,
    each output put on the bus as its step yields it and handed to the later steps in memory (as
    the bus would deliver it, so the outputs are those of separate processes). Only the inputs
    none of them makes are subscribed to. What the process's subscribers count (gaps, drops,
    skipped inputs, undecodable ones) shows in the first service's status.
    """
    if stop is None:
        stop = threading.Event()
        install_signal_handlers(stop)
    names = [sp.name for sp, _ in hosted]
    label = "+".join(names)
    started = time.monotonic()
    bus_counts: Counter = Counter()
    once = LogOnce(log)
    zenoh.init_log_from_env_or("error")
    robot = bus_cfg.robot
    session = open_session(zenoh_config(bus_cfg), stop, bus_cfg.connect)
    if session is None:
        return 0
    with closing(session):
        if not bus_cfg.join and not all(wait_until_free(session, robot, name, stop) for name in names):
            return 0
        services = [_Hosted(session, robot, sp, cfg, bus_cfg.wall_clock_stamps) for sp, cfg in hosted]
        by_name = {h.name: h for h in services}
        first = services[0]
        made = {tp.name for sp, _ in hosted for tp in sp.outputs}
        inputs = tuple(dict.fromkeys(tp for sp, _ in hosted for tp in sp.inputs if tp.name not in made))
        lead_spec = first.spec
        skippable = tuple(tp for tp in lead_spec.skippable if tp.name not in made)
        bus = None

        def emit(name: str, item: Item) -> None:
            """Put a stage's output as its step yields it."""
            h = by_name[name]
            value = item.msg.value
            bus.put(item.msg.topic, item.payload, value.stamp_ns, value.seq)
            if item.msg.name in h.latest_qs:
                h.newest[item.msg.name] = (item.payload, value.seq, value.stamp_ns)
            h.last_data = max(h.last_data, int(value.stamp_ns))
            if h.answering:
                # One figure per input (or poll): from its receipt, and from its scan's stamp, to the first output.
                h.answering = False
                if h.pending_ns is not None:
                    h.latency.add(time.monotonic_ns() - h.pending_ns)
                if h.age is not None:
                    h.age.add(time.time_ns() - int(value.stamp_ns))

        # Built once the bus is known to be ours: a recorder opens its segment here, a slam reads its checkpoint.
        chain = Chain([Stage(sp, cfg) for sp, cfg in hosted], robot=robot,
                      checkpoint_dir=Path(bus_cfg.checkpoint_dir) if bus_cfg.checkpoint_dir else None,
                      checkpoint_period_s=bus_cfg.checkpoint_period_s, emit=emit)
        lead_step = chain.step(first.name)
        source = lead_step if isinstance(lead_step, Source) and not lead_spec.inputs and not lead_spec.raw_inputs else None
        bus = ZenohBus(session, robot, inputs, lead_spec.raw_inputs, bus_cfg.queue_size, bus_counts, skippable,
                       lead_spec.max_lag_s if bus_cfg.wall_clock_stamps and bus_cfg.skip_stale else 0.0,
                       lead_spec.batched)
        slow_s = max(bus_cfg.debug_delay_s(name) for name in names)
        if slow_s:
            log.warning("debug: sleeping %.0f ms after each input (bus.debug_slow)", slow_s * 1e3)
            first.counts["debug.slow_ms"] = round(slow_s * 1e3)
        # Last: a supervisor that sees the token may start the sensor, so the subscribers must exist by then.
        for h in services:
            h.token = session.liveliness().declare_token(topics.alive(robot, h.name))
        log.info("%s up: robot=%s mode=%s connect=%s", label, robot, bus_cfg.mode, ",".join(bus_cfg.connect))

        def status(h: _Hosted) -> t.ServiceStatus:
            step = chain.step(h.name)
            level, message = step.health()
            merged = chain.counts()[h.name]
            merged.update(h.counts)
            own_health = f"{counters.OUT}{h.health_topic.name}"
            merged.update({k: v for k, v in bus_counts.items() if k == own_health or (
                h is first and not k.startswith((counters.IN, counters.OUT)))})
            if h is first:
                merged.update(bus.receive_counts())
            merged.update(h.latency.counters())
            # A gauge, not a count: inputs received and not yet handled (lrfslam play --rate max holds back on it).
            merged[BACKLOG] = bus.pending()
            if h.age is not None:
                merged.update(h.age.counters())
            return t.ServiceStatus(service=h.name, robot=robot, level=level, message=message,
                                   wall_stamp_ns=time.time_ns(), uptime_s=time.monotonic() - started,
                                   counters=dict(merged), last_data_stamp_ns=h.last_data,
                                   config_json=config_mod.to_json(h.cfg),
                                   schemas=tuple(tp.schema for tp in h.spec.inputs + h.spec.outputs),
                                   pid=os.getpid(), host=socket.gethostname())

        def answer_queries(h: _Hosted) -> None:
            while (query := h.status_q.try_recv()) is not None:
                with query:
                    query.reply(query.key_expr, h.health_topic.codec.encode(status(h)),
                                encoding=zenoh.Encoding(h.health_topic.codec.encoding))
            for name, queryable in h.latest_qs.items():
                while (query := queryable.try_recv()) is not None:
                    with query:
                        topic = topics.by_name(name)
                        if (value := chain.step(h.name).latest(topic)) is not None:
                            h.newest[name] = (topic.codec.encode(value), value.seq, value.stamp_ns)
                        if name in h.newest:
                            payload, seq, stamp = h.newest[name]
                            query.reply(topics.latest(robot, name), payload,
                                        attachment=attachment(seq, stamp, bus.producer),
                                        encoding=zenoh.Encoding(topic.codec.encoding))

        def publish_health(h: _Hosted) -> None:
            h.counts["health"] += 1   # numbered from 1 like every stream
            st = status(h)
            bus.put(h.health_topic, h.health_topic.codec.encode(st), st.wall_stamp_ns, h.counts["health"])
            if bus_cfg.health_file and h is first:   # the process's: its loop turns and its session is connected
                try:
                    health_file.write(bus_cfg.health_file, health_file.HealthRecord(
                        h.name, robot, st.level, st.message, st.wall_stamp_ns, bus_cfg.health_period_s,
                        connected(session), st.pid))
                except OSError as exc:
                    h.counts[counters.ERROR_HEALTH_FILE] += 1
                    once.warning(counters.ERROR_HEALTH_FILE, str(exc.errno), "cannot write the health file: %s", exc)

        def handle(msg: Message) -> None:
            for h in services:
                h.pending_ns, h.answering = bus.received_ns, True
                if msg.name in h.takes or h.spec.raw_inputs:
                    h.last_data = max(h.last_data, int(msg.stamp_ns))
            chain.push_item(Item(msg))
            if slow_s:
                time.sleep(slow_s)

        # Each service's health a fraction of a period after the one before: Zenoh queues few express
        # samples at once (a burst of four lost two a second when every stage was busy).
        for i, h in enumerate(services):
            h.next_health = started + i * bus_cfg.health_period_s / len(services)
        next_tick = 0.0
        try:
            while not stop.is_set():
                if source is not None:
                    first.pending_ns, first.answering = None, True
                    chain.push_outputs(first.name, source.poll(0.1))
                elif (msg := bus.get(0.1)) is not None:
                    handle(msg)
                now = time.monotonic()
                if now >= next_tick:
                    next_tick = now + 0.1
                    for h in services:
                        chain.step(h.name).tick()
                        answer_queries(h)
                for h in services:
                    if now >= h.next_health:
                        h.next_health = now + bus_cfg.health_period_s
                        publish_health(h)
            # What arrived before the stop is handled (for a while), what remains is counted.
            bus.stop_receiving()
            drain_until = time.monotonic() + STOP_DRAIN_S
            while bus.pending() and time.monotonic() < drain_until:
                if (msg := bus.get(0.0)) is not None:
                    handle(msg)
            bus.discard_pending()
            chain.finish_items()
            chain.close()   # the checkpoints saved: a clean stop resumes where it stood
            for h in services:
                publish_health(h)  # the final counts, for supervisors and the recording
        finally:
            chain.close(save=False)   # after a failure, only the periodic checkpoints stay
            bus.close()
            for h in services:
                h.close()
    stopped_cleanly(label)
    return 0


def live_services(session: zenoh.Session, robot: str, service: str = topics.ANY) -> dict[str, str]:
    """Services of ``robot`` (``service``, or all) whose liveliness token is on the network, each with where it runs.

    Where: ``pid N on HOST`` from its status queryable, or ``""`` if it did not answer.
    """
    names = set()
    for reply in session.liveliness().get(topics.alive(robot, service), timeout=2.0):
        if reply.ok is not None:
            names.add(topics.robot_and_service(str(reply.ok.key_expr))[1])
    where = dict.fromkeys(names, "")
    if names:
        for reply in session.get(topics.status(robot, service), timeout=1.0, target=zenoh.QueryTarget.ALL,
                                 consolidation=zenoh.ConsolidationMode.NONE):
            if reply.ok is None:
                continue
            try:
                st = codec.SERVICE_STATUS.decode(reply.ok.payload.to_bytes())
            except LrfSlamError:
                continue
            if st.service in where:
                where[st.service] = f"pid {st.pid} on {st.host}"
    return where


def wait_until_free(session: zenoh.Session, robot: str, service: str, stop: threading.Event) -> bool:
    """Stop a second ``service`` of ``robot`` from silently joining the first one's streams.

    True when no other is alive; False if ``stop`` was set first.

    A token whose service does not answer its status query may be a process that died
    without closing its session (a container killed with its network); such a token
    goes when Zenoh's lease expires (10 s by default), so it is given ``STALE_TOKEN_S``.

    Raises
    ------
    StartupError
        Its liveliness token is on the network and its service answers, or the token stays.
    """
    deadline = time.monotonic() + STALE_TOKEN_S
    while found := live_services(session, robot, service):
        if found[service] or time.monotonic() > deadline:
            where = f" ({found[service]})" if found[service] else " (its token stays, though it does not answer)"
            raise StartupError(f"{service} of robot {robot!r} is already running{where}; start this one with "
                               "another --robot, or with --join to run beside it")
        if stop.wait(0.5):
            return False
    return True


def stopped_cleanly(service: str) -> None:
    """The end of a clean stop: the stack dump armed by the signal handler is no longer due."""
    faulthandler.cancel_dump_traceback_later()
    log.info("%s stopped cleanly", service)
