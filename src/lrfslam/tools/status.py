"""``lrfslam status``: which services are alive, and what their status queryables say.

``--watch`` repeats the table every ``--interval`` seconds (on a terminal, in place, as
``watch`` does), with each service's input and output rates since the last refresh, its health
message, and the SLAM's pose and landmarks from its latest-state queryable, until Ctrl-C.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import sys
import threading
import time

import zenoh

from lrfslam import services
from lrfslam.errors import DecodeError
from lrfslam.msgs import codec, counters, topics
from lrfslam.msgs import types as t
from lrfslam.msgs.topics import Topic
from lrfslam.runtime import health_file
from lrfslam.runtime.bus import base_config, closing
from lrfslam.viz.dashboard import rates as status_rates

LEVELS = {t.HEALTH_OK: "OK", t.HEALTH_WARN: "WARN", t.HEALTH_ERROR: "ERROR", t.HEALTH_STALE: "STALE"}


def client_config(connect: list[str], zenoh_config: str | None = None) -> zenoh.Config:
    """A client of ``connect``; ``zenoh_config`` (JSON5, e.g. TLS certificates) is applied first."""
    return base_config("client", connect, zenoh_config)


def query_status(session: zenoh.Session, robot: str, timeout_s: float) -> tuple[set[tuple[str, str]],
                                                                               list[t.ServiceStatus]]:
    """Live (robot, service) pairs from liveliness, and every status reply."""
    alive: set[tuple[str, str]] = set()
    for reply in session.liveliness().get(topics.alive(robot, topics.ANY), timeout=timeout_s):
        if reply.ok is not None:
            alive.add(topics.robot_and_service(str(reply.ok.key_expr)))
    statuses = []
    # Services reply on the query's own (wildcard) key, so the default consolidation would keep
    # one reply of the five; every queryable must be asked and every reply kept.
    for reply in session.get(topics.status(robot, topics.ANY), timeout=timeout_s,
                             target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE):
        if reply.ok is None:
            continue
        try:
            statuses.append(codec.SERVICE_STATUS.decode(reply.ok.payload.to_bytes(),
                                                        codec.parse_encoding(str(reply.ok.encoding))))
        except DecodeError:
            continue
    return alive, sorted(statuses, key=lambda s: (s.robot, s.service))


def latency_cell(counters: dict[str, int], name: str = "latency") -> str:
    """``p50/p99`` in ms from a status's ``<name>.*`` counters; "–" where it has none (``latency``:
    a service without inputs; ``age``: stamps not on the wall clock)."""
    if f"{name}.p50_us" not in counters:
        return "–"
    return f"{counters[f'{name}.p50_us'] / 1e3:.1f}/{counters[f'{name}.p99_us'] / 1e3:.1f}"


def status_table(alive: set[tuple[str, str]], statuses: list[t.ServiceStatus],
                 rates: dict[tuple[str, str], tuple[float, float]] | None = None) -> str:
    """One row per service. ``uptime_s`` is on the service's monotonic clock; ``dropped`` counts
    inputs it received but will not handle (``drop.*``), ``gaps``/``dups`` inputs that never reached it / came twice
    (sequence numbers, docs/delivery.md), ``restarts`` new producers it saw on its inputs;
    ``latency_ms`` the median/99th percentile from receiving an input to publishing its outputs,
    ``age_ms`` from the sensor stamp of the scan the outputs derive from to publishing them, on
    the wall clock (lrfslam/runtime/latency.py).

    With ``rates`` ((robot, service) -> inputs/s, outputs/s; ``--watch``), also those rates and
    each service's health message (its last error, where it has one)."""
    head = ["robot", "service", "alive", "health", "uptime_s", "in", "out", "latency_ms", "age_ms", "dropped", "gaps",
            "dups", "restarts", "errors", "pid@host"]
    if rates is not None:
        head[7:7] = ["in/s", "out/s"]
        head.append("message")
    rows = [tuple(head)]
    seen = set()
    for s in statuses:
        seen.add((s.robot, s.service))
        c = s.counters
        row = [s.robot, s.service, "yes" if (s.robot, s.service) in alive else "no",
               LEVELS.get(s.level, str(s.level)), f"{s.uptime_s:.0f}",
               str(counters.total(c, counters.IN)), str(counters.total(c, counters.OUT)), latency_cell(c), latency_cell(c, "age"),
               str(counters.total(c, counters.DROP)),
               str(counters.total(c, counters.GAP)), str(counters.total(c, counters.DUP)), str(counters.total(c, counters.RESTART)),
               str(counters.total(c, counters.ERROR, counters.STEP_ERROR)),
               f"{s.pid}@{s.host}"]
        if rates is not None:
            r = rates.get((s.robot, s.service))
            row[7:7] = ["–", "–"] if r is None else [f"{r[0]:.1f}", f"{r[1]:.1f}"]
            row.append(s.message)
        rows.append(tuple(row))
    for robot, service in sorted(alive - seen):
        rows.append((robot, service, "yes", "?", *[""] * (len(rows[0]) - 4)))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return "\n".join("  ".join(v.ljust(w) for v, w in zip(r, widths)) for r in rows)


def check(alive: set[tuple[str, str]], statuses: list[t.ServiceStatus], wanted: list[str]) -> list[str]:
    """Why the services in ``wanted`` are not healthy (empty when they are).

    Healthy means a liveliness token is present and the status reply, if one came, is not
    ERROR. WARN and STALE pass: a stage waiting for its first input is still up, and a
    container healthcheck must not fail a pipeline whose sensor has not started yet.
    """
    problems = []
    alive_names = {service for _, service in alive}
    for name in wanted:
        if name not in alive_names:
            problems.append(f"{name}: no liveliness token")
        for s in statuses:
            if s.service == name and s.level == t.HEALTH_ERROR:
                problems.append(f"{name}@{s.robot}: ERROR {s.message}")
    return problems


def query_latest(session: zenoh.Session, robot: str, topic: Topic, timeout_s: float):
    """The newest ``topic`` message each live service of ``robot`` keeps for late joiners (its
    ``topics.latest`` queryable): ``(key, value)`` per answer, the value a :class:`DecodeError` where
    the payload does not decode (the caller counts it)."""
    for reply in session.get(topics.latest(robot, topic.name), timeout=timeout_s,
                             target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE):
        if reply.ok is None:
            continue
        try:
            value = topic.codec.decode(reply.ok.payload.to_bytes(), codec.parse_encoding(str(reply.ok.encoding)))
        except DecodeError as exc:
            value = exc
        yield str(reply.ok.key_expr), value


def query_latest_states(session: zenoh.Session, robot: str, timeout_s: float) -> dict[str, t.SlamState]:
    """Each robot's newest SLAM state, from its slam's latest-state queryable (none while it has none)."""
    return {key.split("/")[1]: state for key, state in query_latest(session, robot, topics.SLAM_STATE, timeout_s)
            if not isinstance(state, DecodeError)}


def slam_lines(states: dict[str, t.SlamState]) -> list[str]:
    """A line per robot: the SLAM's pose and landmarks."""
    return [f"slam {robot}: pose x {s.pose[0]:.2f} m, y {s.pose[1]:.2f} m, heading {math.degrees(s.pose[2]):.1f} deg; "
            f"{s.n_landmarks} landmarks ({s.n_confirmed} confirmed); state {s.seq}"
            for robot, s in sorted(states.items())]


def watch(session: zenoh.Session, args: argparse.Namespace, stop: threading.Event) -> int:
    """The table every ``args.interval`` s until ``stop``; 0."""
    before: dict[tuple[str, str], t.ServiceStatus] = {}
    clear = sys.stdout.isatty()
    while not stop.is_set():
        alive, statuses = query_status(session, args.robot, args.timeout)
        if args.service:
            alive = {(r, s) for r, s in alive if s in args.service}
            statuses = [s for s in statuses if s.service in args.service]
        rates = {}
        for s in statuses:
            if (r := status_rates(before.get((s.robot, s.service)), s)) is not None:
                rates[(s.robot, s.service)] = r
            before[(s.robot, s.service)] = s
        lines = [f"lrfslam status, every {args.interval:g} s (Ctrl-C stops): {time.strftime('%H:%M:%S')}", ""]
        lines.append(status_table(alive, statuses, rates) if alive or statuses else "no lrfslam service answered")
        lines += ["", *slam_lines(query_latest_states(session, args.robot, args.timeout))]
        print(("\x1b[H\x1b[2J" if clear else "\n") + "\n".join(lines), flush=True)
        stop.wait(args.interval)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lrfslam status", description=__doc__)
    parser.add_argument("-e", "--connect", action="append", metavar="ENDPOINT",
                        help="router to ask (default tcp/127.0.0.1:7447); works from another host")
    parser.add_argument("--robot", default="*", help="robot namespace (default: all)")
    parser.add_argument("--timeout", type=float, default=2.0, help="seconds to wait for replies")
    parser.add_argument("--json", action="store_true", help="print the raw status records as JSON")
    parser.add_argument("-w", "--watch", action="store_true",
                        help="refresh the table (with rates, health messages, the SLAM's pose and landmarks) "
                             "until Ctrl-C")
    parser.add_argument("--interval", type=float, default=2.0, help="with --watch: seconds between refreshes")
    parser.add_argument("--zenoh-config", metavar="FILE",
                        help="Zenoh JSON5 config applied first, e.g. TLS certificates (deploy/zenoh/)")
    parser.add_argument("-s", "--service", action="append", default=[], choices=services.NAMES,
                        help="only this service (repeatable)")
    parser.add_argument("--check", action="store_true",
                        help="exit 0 if the router answers and every --service is alive and not in ERROR, "
                             "else 1 (for container healthchecks; without --service: the router only)")
    parser.add_argument("--check-file", metavar="FILE",
                        help="exit 0 if the service that writes FILE (its --health-file) is connected, its "
                             "main loop turning and it is not in ERROR, else 1; asks no router (for container "
                             "healthchecks)")
    args = parser.parse_args(argv)
    if args.watch and (args.check or args.check_file or args.json):
        parser.error("--watch shows the table; it does not go with --check, --check-file or --json")
    if not args.interval > 0:
        parser.error(f"--interval must be > 0 s, got {args.interval}")
    if args.check_file:
        problems = health_file.problems(args.check_file, time.time_ns())
        print("; ".join(problems) if problems else f"ok: {args.check_file}")
        return 1 if problems else 0
    zenoh.init_log_from_env_or("error")
    endpoints = args.connect or ["tcp/127.0.0.1:7447"]
    try:
        session = zenoh.open(client_config(endpoints, args.zenoh_config))
    except zenoh.ZError as exc:
        print(f"lrfslam status: cannot reach {','.join(endpoints)}: {exc}", file=sys.stderr)
        return 2
    with closing(session):
        if args.watch:
            stop = threading.Event()
            for sig in (signal.SIGINT, signal.SIGTERM):
                signal.signal(sig, lambda *_: stop.set())
            return watch(session, args, stop)
        if args.check and not args.service:
            # A client session opens only once its endpoint answered, so this is the router check.
            print(f"ok: router at {','.join(endpoints)}")
            return 0
        alive, statuses = query_status(session, args.robot, args.timeout)
    if args.service:
        alive = {(r, s) for r, s in alive if s in args.service}
        statuses = [s for s in statuses if s.service in args.service]
    if args.check:
        problems = check(alive, statuses, args.service)
        print("; ".join(problems) if problems else f"ok: {', '.join(args.service)}")
        return 1 if problems else 0
    if args.json:
        print(json.dumps([s.__dict__ for s in statuses], indent=2, default=list))
    elif not alive and not statuses:
        print("no lrfslam service answered")
        return 1
    else:
        print(status_table(alive, statuses))
    return 0
