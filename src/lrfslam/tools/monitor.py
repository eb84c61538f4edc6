"""``lrfslam monitor``: a robot's live streams served to Foxglove over WebSocket.

    lrfslam monitor --connect tcp/ROBOT:7447 [--robot R] [--port 8765] [--host 127.0.0.1]
                    [--dashboard [--http-port 8080]] [--token-file FILE | --insecure] [--health-file FILE]

Joins the robot's Zenoh network as a client, subscribes to every key of the robot
(``lrf/<robot>/**``), turns each message into Foxglove's views (lrfslam/viz/foxglove.py:
the channels a recording holds) and serves them with foxglove-sdk's WebSocket server;
Foxglove or Lichtblick open ``ws://HOST:PORT`` (docs/monitoring.md). The server sends
the data stamps as its time, so the app's clock follows the robot's data. Read-only: the
monitor publishes nothing on Zenoh, and its clients can only subscribe.

Whoever reaches the ports sees every stream of the robot. On loopback (the default ``--host``)
that is this machine's users, and nothing is asked of them. Beyond loopback the monitor wants a
token (``--token-file FILE``, or ``LRFSLAM_MONITOR_TOKEN``) and refuses to start without one
(exit 2, one line) unless told ``--insecure``; with a token, every page and WebSocket answers
only a request that presents it (``?token=TOKEN`` in the URL: src/lrfslam/tools/webserver.py,
where Foxglove's server, which cannot check one, is put behind a relay that does).

The monitor is one feed (the Zenoh subscription) handing every message to its sinks;
the Foxglove server is one sink, and with ``--dashboard`` a web page of the map and the
services' health (src/lrfslam/tools/dashboard.py, ``http://HOST:HTTP_PORT/``) is another.
A monitor that joins late starts from the current state: it asks which services are alive,
their status queryables, and the newest SLAM state and loop-closed map (``topics.latest``),
then follows the liveliness tokens as they come and go.

With ``--health-file`` the monitor rewrites FILE every health period as a service does
(src/lrfslam/runtime/health_file.py), so a container runs the same healthcheck on it:
``lrfslam status --check-file FILE`` (connected to the router, main loop turning).

Exit codes: 0 stopped by SIGTERM or Ctrl-C; 2 the server or the Zenoh session could
not start, or beyond loopback without a token or ``--insecure`` (one line).
"""

from __future__ import annotations

import argparse
import logging
import os
import threading
import time
from collections import Counter, deque
from collections.abc import Sequence
from typing import Protocol

import foxglove
import zenoh
from foxglove.websocket import Capability

from lrfslam.errors import (
    ConfigError,
    DecodeError,
    InputError,
    LrfSlamError,
    StartupError,
)
from lrfslam.msgs import codec, counters, topics
from lrfslam.msgs import types as t
from lrfslam.msgs.codec import parse_encoding
from lrfslam.runtime import health_file
from lrfslam.runtime.bus import (
    BusConfig,
    ZenohBus,
    closing,
    connected,
    open_session,
    parse_attachment,
    zenoh_config,
)
from lrfslam.runtime.decoding import LogOnce
from lrfslam.runtime.runner import (
    install_signal_handlers,
    setup_logging,
    stopped_cleanly,
)
from lrfslam.runtime.step import Message
from lrfslam.tools.dashboard import DEFAULT_HTTP_PORT, DashboardServer
from lrfslam.tools.exposure import TOKEN_ENV, is_loopback, read_token
from lrfslam.tools.webserver import FoxgloveRelay, TokenGate
from lrfslam.viz.foxglove import CHANNELS, FoxgloveViews, ViewConfig, schema_of

log = logging.getLogger("lrfslam.monitor")

DEFAULT_PORT = 8765

#: Live, nothing is stored and a viewer wants the newest state: trajectories twice a second (up to
#: ~44 kB/s each for a long one) and landmarks five times a second, where a recording takes 1 s and 0.5 s.
LIVE_VIEWS = ViewConfig(path_period_s=0.5, path_poses_per_s=1000.0, landmark_period_s=0.2)


class Sink(Protocol):
    """A consumer of the monitored stream: gets every message as received, undecoded, and every
    change of a service's liveliness."""

    def on_message(self, msg: Message) -> None: ...

    def on_alive(self, service: str, alive: bool) -> None: ...

    def close(self) -> None: ...


class FoxgloveServer:
    """Sink: Foxglove's views of every message, on a foxglove-sdk WebSocket server.

    Every view channel is advertised from the start, so a client sees the whole list at
    once; a message reaches only the clients subscribed to its channel. With ``gate`` the
    server listens on a free loopback port and a :class:`~lrfslam.tools.webserver.FoxgloveRelay`
    checking the token takes ``host``:``port``.

    Raises
    ------
    StartupError
        The server cannot listen on ``host``:``port``.
    """

    def __init__(self, host: str, port: int, name: str, cfg: ViewConfig = LIVE_VIEWS,
                 gate: TokenGate | None = None) -> None:
        self.context = foxglove.Context()
        inner_host, inner_port = ("127.0.0.1", 0) if gate is not None else (host, port)
        try:
            self.server = foxglove.start_server(name=name, host=inner_host, port=inner_port,
                                                capabilities=[Capability.Time], context=self.context)
        except RuntimeError as exc:
            reason = str(exc).removeprefix("FoxgloveError: ")
            hint = " (another monitor has it: pass another --port)" if "in use" in reason else ""
            raise StartupError(f"cannot serve Foxglove on {inner_host}:{inner_port}: {reason}{hint}") from None
        try:
            self.relay = FoxgloveRelay(host, port, self.server.port, gate) if gate is not None else None
        except StartupError:
            self.server.stop()
            raise
        self.channels = {topic: foxglove.Channel(topic, schema=schema_of(cls), message_encoding="protobuf",
                                                 context=self.context)
                         for topic, cls in CHANNELS.items()}
        self.views = FoxgloveViews(cfg)
        self.counts: Counter = Counter()
        self._once = LogOnce(log)
        self._time_ns = 0

    @property
    def port(self) -> int:
        return self.relay.port if self.relay is not None else self.server.port

    def on_message(self, msg: Message) -> None:
        stamp = msg.stamp_ns or time.time_ns()
        try:
            views = self.views.from_payload(msg.name, msg.schema, msg.value, stamp)
        except InputError as exc:
            self.counts["undecodable"] += 1
            self._once.warning("undecodable", f"{msg.name}:{msg.schema}", "no view of a message on %s: %s",
                               msg.name, exc)
            return
        for view in views:
            self.channels[view.topic].log(view.encode(), log_time=view.stamp_ns)
            self.counts["views"] += 1
        # The app's clock: the newest data stamp (a health status is stamped by the wall clock).
        if views and not topics.is_health(msg.name) and stamp > self._time_ns:
            self._time_ns = stamp
            self.server.broadcast_time(stamp)

    def on_alive(self, service: str, alive: bool) -> None:
        """The services' health reaches Foxglove as logs; liveliness has no view there."""

    def close(self) -> None:
        if self.relay is not None:
            self.relay.close()
        self.server.stop()


class Monitor:
    """The feed: the robot's keys over Zenoh, every message handed to each of ``sinks``."""

    def __init__(self, bus_cfg: BusConfig, sinks: Sequence[Sink]) -> None:
        self.bus_cfg = bus_cfg
        self.sinks = list(sinks)
        self.counts: Counter = Counter()
        self._once = LogOnce(log)

    def run(self, stop: threading.Event) -> int:
        """Until ``stop`` is set; waits for the router while it is unreachable."""
        zenoh.init_log_from_env_or("error")
        session = open_session(zenoh_config(self.bus_cfg), stop, self.bus_cfg.connect)
        if session is None:
            return 0
        with closing(session):
            robot = self.bus_cfg.robot
            bus = ZenohBus(session, robot, (), True, self.bus_cfg.queue_size, self.counts)
            changes: deque[tuple[str, bool]] = deque(maxlen=10_000)   # filled by Zenoh's callback thread
            tokens = session.liveliness().declare_subscriber(
                topics.alive(robot, topics.ANY), lambda sample: changes.append(
                    (topics.robot_and_service(str(sample.key_expr))[1], sample.kind == zenoh.SampleKind.PUT)),
                history=True)
            log.info("monitoring robot %s via %s", robot, ",".join(self.bus_cfg.connect))
            try:
                self.catch_up(session)
                next_health = 0.0
                while not stop.is_set():
                    while changes:
                        service, alive = changes.popleft()
                        for sink in self.sinks:
                            sink.on_alive(service, alive)
                    if (msg := bus.get(0.1)) is not None:
                        self.hand_on(msg)
                    if self.bus_cfg.health_file and (now := time.monotonic()) >= next_health:
                        next_health = now + self.bus_cfg.health_period_s
                        self.write_health(session)
            finally:
                tokens.undeclare()
                self.counts.update(bus.receive_counts())
                bus.close()
        return 0

    def hand_on(self, msg: Message) -> None:
        self.counts["handed_on"] += 1
        for sink in self.sinks:
            sink.on_message(msg)

    def write_health(self, session: zenoh.Session) -> None:
        """The health file (``--health-file``): rewritten while this loop turns, and says whether the
        session still has its router. A file that cannot be written is counted and logged once."""
        try:
            health_file.write(self.bus_cfg.health_file, health_file.HealthRecord(
                "monitor", self.bus_cfg.robot, t.HEALTH_OK, f"{self.counts['handed_on']} messages handed on",
                time.time_ns(), self.bus_cfg.health_period_s, connected(session), os.getpid()))
        except OSError as exc:
            self.counts[counters.ERROR_HEALTH_FILE] += 1
            self._once.warning(counters.ERROR_HEALTH_FILE, str(exc.errno), "cannot write the health file: %s", exc)

    def catch_up(self, session: zenoh.Session, timeout_s: float = 2.0) -> None:
        """The state before the first message: every service's status, then the newest of the outputs
        the services keep for late joiners (``topics.latest``), as if just received."""
        robot = self.bus_cfg.robot
        for key in (topics.status(robot, topics.ANY), topics.latest(robot, "**")):
            for reply in session.get(key, timeout=timeout_s, target=zenoh.QueryTarget.ALL,
                                     consolidation=zenoh.ConsolidationMode.NONE):
                if reply.ok is None:
                    continue
                sample = reply.ok
                att = sample.attachment
                seq, stamp_ns, _ = parse_attachment(att.to_bytes() if att is not None else None)
                payload, schema = sample.payload.to_bytes(), parse_encoding(str(sample.encoding))
                try:
                    if key.endswith("/status"):
                        name = topics.health(topics.robot_and_service(str(sample.key_expr))[1]).name
                        stamp_ns = codec.SERVICE_STATUS.decode(payload, schema).wall_stamp_ns
                    else:
                        name = str(sample.key_expr).removeprefix(topics.latest(robot, ""))
                        topics.by_name(name)
                except (KeyError, DecodeError):
                    self.counts["catch_up.undecodable"] += 1
                    continue
                self.counts["catch_up"] += 1
                self.hand_on(Message(None, payload, stamp_ns, schema, name, seq))


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="lrfslam monitor", description=__doc__.splitlines()[0])
    p.add_argument("-e", "--connect", action="append", metavar="ENDPOINT",
                   help="the robot's Zenoh router, e.g. tcp/robot:7447 (repeatable; default tcp/127.0.0.1:7447)")
    p.add_argument("--robot", default=BusConfig.robot, help="robot namespace (keys lrf/<robot>/...)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address the servers listen on (default loopback; beyond it, e.g. 0.0.0.0 for every "
                        "interface, only with --token-file or --insecure)")
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help="WebSocket port (0: any free one)")
    p.add_argument("--dashboard", action="store_true",
                   help="also serve a web dashboard (map and services) on http://HOST:HTTP_PORT/")
    p.add_argument("--http-port", type=int, default=DEFAULT_HTTP_PORT,
                   help=f"the dashboard's HTTP and WebSocket port (default {DEFAULT_HTTP_PORT}; 0: any free one)")
    p.add_argument("--token-file", metavar="FILE",
                   help=f"a file holding the token every page and WebSocket then requires (?token=TOKEN in the "
                        f"URL; default: ${TOKEN_ENV} if set); needed beyond loopback")
    p.add_argument("--insecure", action="store_true",
                   help="serve beyond loopback without a token: whoever reaches the ports sees every stream")
    p.add_argument("--zenoh-config", metavar="FILE", help="Zenoh JSON5 config applied first (TLS, ...)")
    p.add_argument("--health-file", metavar="FILE",
                   help="also write the monitor's health to FILE every second, for a container healthcheck: "
                        "lrfslam status --check-file FILE")
    p.add_argument("--log-level", default=None, help="DEBUG, INFO, WARNING, ERROR")
    return p


def token_gate(args: argparse.Namespace) -> TokenGate | None:
    """The gate of the monitor's servers: with a token (given on loopback too), None without one.

    Raises
    ------
    ConfigError
        Beyond loopback without a token or ``--insecure``; a token file that cannot be read or a bad token.
    """
    token = read_token(args.token_file, os.environ)
    if token is not None:
        return TokenGate(token)
    if not is_loopback(args.host):
        if not args.insecure:
            raise ConfigError(f"--host {args.host} is beyond loopback: whoever reaches it would see every stream; "
                              f"give a token (--token-file FILE or {TOKEN_ENV}), or pass --insecure on a network "
                              "where everyone may see everything")
        log.warning("--host %s: beyond loopback without a token (--insecure): whoever reaches the ports sees "
                    "every stream", args.host)
    return None


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    setup_logging("monitor", args.log_level)
    stop = threading.Event()
    install_signal_handlers(stop)
    try:
        gate = token_gate(args)
        bus_cfg = BusConfig(robot=args.robot, mode="client", connect=tuple(args.connect or BusConfig.connect),
                            zenoh_config=args.zenoh_config or "", health_file=args.health_file or "")
        server = FoxgloveServer(args.host, args.port, f"lrfslam {args.robot}", gate=gate)
    except (LrfSlamError, OSError) as exc:
        log.error("%s", exc)
        return 2
    sinks: list[Sink] = [server]
    query = "/?token=TOKEN" if gate is not None else ""
    log.info("serving Foxglove on ws://%s:%d%s (pid %d)", args.host, server.port, query, os.getpid())
    if args.dashboard:
        try:
            dashboard = DashboardServer(args.host, args.http_port, f"lrfslam {args.robot}", gate=gate)
        except LrfSlamError as exc:
            server.close()
            log.error("%s", exc)
            return 2
        sinks.append(dashboard)
        log.info("serving the dashboard on http://%s:%d%s", args.host, dashboard.port, query or "/")
    try:
        Monitor(bus_cfg, sinks).run(stop)
    except LrfSlamError as exc:
        log.error("%s", exc)
        return 2
    finally:
        for sink in sinks:
            sink.close()
    if server.counts["undecodable"]:
        log.warning("%d messages had no view (undecodable)", server.counts["undecodable"])
    stopped_cleanly("monitor")
    return 0
