"""``lrfslam up``: the whole pipeline as separate processes, supervised, with a summary.

Checks every stage's settings, starts a Zenoh router (or, with ``--connect``, uses a
running one), refuses to start when services of the robot are already alive there
(unless ``--join``), then starts recorder, mapper, slam, features and denoise, waits
until each has declared its liveliness token, then starts the sensor. A stage that
exits while starting (or has no token after 30 s) stops everything at once: ``up``
exits with code 2 and removes the recording if it holds nothing. A process that dies,
the router included, is restarted (up to ``--max-restarts`` times); the services'
Zenoh sessions reconnect to a restarted router by themselves, the slam resumes from
its checkpoint (in the recording folder), the sensor from where the simulated robot
is now, and the recorder adds a segment. While it runs, a status line every
``--status-period`` seconds (scans, their rate, landmarks, the pose error against the truth;
``--quiet``: none); ``--monitor`` also runs ``lrfslam monitor --dashboard`` and ``--ros2``
``lrfslam ros2`` (the robot's topics for ROS 2 over rmw_zenoh, docs/ros2.md), each as one more
supervised process. ``--group STAGES`` runs those stages in one process (``lrfslam group``), supervised
as one. On Ctrl-C, SIGTERM or after ``--duration`` seconds the sensor stops
first, the pipeline drains, the rest stop in order, and a summary compares the SLAM estimate
with the simulator's ground truth. ``--skip sensor`` runs the pipeline without one, for a
recording played in (``lrfslam play RECORDING --robot R``, src/lrfslam/tools/play.py): the
summary then compares with the truth played, where the recording has it.

The router listens on loopback; ``--listen`` adds endpoints for other hosts. A plain one (tcp/,
udp/) beyond loopback lets whoever reaches it read and publish on the bus, so ``up`` refuses it
before starting anything unless told ``--insecure`` (src/lrfslam/tools/exposure.py); a tls/ one
takes the router's certificates from ``--zenoh-config`` (deploy/zenoh/router-tls.json5).
"""

from __future__ import annotations

import argparse
import logging
import os
import secrets
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections import Counter, deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zenoh

from lrfslam import services
from lrfslam.errors import (
    ConfigError,
    DecodeError,
    LrfSlamError,
    MapError,
    RecordingError,
    StartupError,
)
from lrfslam.evaluation.live_truth import LiveTruth
from lrfslam.msgs import codec, counters, topics
from lrfslam.ros2 import wire
from lrfslam.runtime import config as config_mod
from lrfslam.runtime.bus import BusConfig, closing, parse_attachment
from lrfslam.runtime.recording import ReadReport, count_messages, read_recording
from lrfslam.runtime.runner import (
    group_stages,
    install_signal_handlers,
    live_services,
    setup_logging,
)
from lrfslam.runtime.saved_map import SavedMap
from lrfslam.tools import maps
from lrfslam.tools.exposure import check_listen
from lrfslam.tools.info import segment_lines
from lrfslam.tools.status import client_config
from lrfslam.viz.dashboard import counter_figures

log = logging.getLogger("lrfslam.up")

#: Consumers before producers (``services.NAMES``).
START_ORDER = tuple(reversed(services.NAMES))
#: How long the stages before the sensor have to declare their liveliness tokens.
START_TIMEOUT_S = 30.0
#: Stages ``--skip`` may leave out (every other one is needed for SLAM to run at all; without the
#: sensor, the scans come from ``lrfslam play``).
OPTIONAL = ("mapper", "sensor")
#: How often the supervisor looks for dead children, s (a restart is that much late at most).
POLL_S = 0.05
#: Messages heard but not yet looked at by the supervisor's loop, at most.
MAX_INBOX = 100_000

#: glibc serves an allocation this large (bytes) from mmap, returned to the system when freed.
#: By default the threshold rises to the largest block freed so far, after which the
#: temporaries of a growing pose graph come from the heap and its high-water mark stays:
#: the mapper grew 245-343 B per scan in a 45,000-scan soak, 145 with the threshold fixed
#: (docs/operations.md, Soak). deploy/Dockerfile sets the same.
MMAP_THRESHOLD_BYTES = 131072
#: The variable that gives a stage ``bus.checkpoint_dir``.
CHECKPOINT_DIR_ENV = f"{config_mod.ENV_PREFIX}_BUS_CHECKPOINT_DIR"


def child_environment() -> dict[str, str]:
    """The environment of every process ``up`` starts: its own, with glibc's mmap threshold fixed
    unless the caller set one."""
    env = dict(os.environ)
    env.setdefault("MALLOC_MMAP_THRESHOLD_", str(MMAP_THRESHOLD_BYTES))
    return env


@dataclass(eq=False)   # one process, whichever stages it runs: compared (and hashed) by identity
class Child:
    """One supervised process.

    ``down_since`` (monotonic s) is set when it was found dead and restarted, and
    cleared when it is back (its liveliness token, or for the router every service's,
    seen again); ``downtimes`` holds how long each restart took.
    """

    name: str
    argv: list[str]
    proc: subprocess.Popen | None = None
    restarts: int = 0
    stopping: bool = False
    down_since: float | None = None
    downtimes: list[float] = field(default_factory=list)
    waiting_for: set[str] = field(default_factory=set)   # router: services not reconnected yet
    gave_up: bool = False
    env: dict[str, str] = field(default_factory=dict)   # set in its environment beside up's own

    def start(self, extra: list[str] | tuple[str, ...] = ()) -> None:
        self.proc = subprocess.Popen(self.argv + list(extra), stdin=subprocess.DEVNULL,
                                     env=child_environment() | self.env)

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def stop(self, timeout_s: float) -> int | None:
        """SIGTERM, then SIGKILL after ``timeout_s``; the exit code."""
        self.stopping = True
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                log.warning("%s did not stop in %.0f s; killing it", self.name, timeout_s)
                self.proc.kill()
                self.proc.wait()
        return self.proc.returncode


class Observer:
    """What the supervisor hears on the bus: truth, SLAM states, each service's last health, liveliness.

    Zenoh's callbacks only queue what arrives; :meth:`process` (the supervisor's loop)
    decodes it: truth and SLAM states go to ``truth`` (:class:`~lrfslam.evaluation.live_truth.LiveTruth`),
    which matches them as they come. ``health`` holds the last health of every run of a service
    (keyed by service and the producer id of its process), so the summary adds up a restarted
    service's runs.
    """

    def __init__(self) -> None:
        self._inbox: deque = deque(maxlen=MAX_INBOX)
        self.truth = LiveTruth()
        self.health: dict[tuple[str, bytes], bytes] = {}   # (service, producer id) -> last health
        self.alive_events: deque = deque(maxlen=MAX_INBOX)   # (service, present, monotonic s)
        self.lock = threading.Lock()

    # -- Zenoh callbacks: queue only
    def on_truth(self, sample: zenoh.Sample) -> None:
        att = sample.attachment
        self._inbox.append(("truth", sample.payload.to_bytes(), att.to_bytes() if att is not None else None))

    def on_state(self, sample: zenoh.Sample) -> None:
        self._inbox.append(("state", sample.payload.to_bytes(), None))

    def on_health(self, sample: zenoh.Sample) -> None:
        att = sample.attachment
        self._inbox.append(("health", sample.payload.to_bytes(),
                            (str(sample.key_expr), att.to_bytes() if att is not None else None)))

    def counters(self, service: str) -> Counter:
        """``service``'s counters summed over its runs (a restarted process counts from zero)."""
        with self.lock:
            runs = [data for (name, _), data in self.health.items() if name == service]
        total: Counter = Counter()
        for data in runs:
            try:
                total.update(codec.SERVICE_STATUS.decode(data).counters)
            except DecodeError:
                continue
        return total

    def on_alive(self, sample: zenoh.Sample) -> None:
        self.alive_events.append((topics.robot_and_service(str(sample.key_expr))[1],
                                  sample.kind == zenoh.SampleKind.PUT, time.monotonic()))

    # -- the supervisor's loop
    def process(self) -> None:
        """Decode and match everything queued since the last call."""
        while self._inbox:
            kind, data, extra = self._inbox.popleft()
            try:
                if kind == "truth":
                    att = parse_attachment(extra)
                    self.truth.add_truth(att.seq, att.stamp_ns, codec.GROUND_TRUTH.decode(data).pose)
                elif kind == "state":
                    self.truth.add_state(data)
                else:
                    key, att = extra
                    with self.lock:
                        self.health[(topics.robot_and_service(key)[1], parse_attachment(att).producer)] = data
            except DecodeError:
                continue


def child_argv(name: str, args: argparse.Namespace, endpoint: str, extra: list[str]) -> list[str]:
    argv = [sys.executable, "-m", "lrfslam.cli", name, "--robot", args.robot, "--mode", "client",
            "--connect", endpoint, "--log-level", args.log_level]
    if args.config:
        argv += ["--config", args.config]
    if args.join:
        argv += ["--join"]
    return argv + extra


def wait_alive(session: zenoh.Session, robot: str, names: Sequence[str], children: list[Child], timeout_s: float,
               stop: threading.Event) -> bool:
    """Wait until every service of ``names``, run by ``children``, has declared its liveliness token.

    Returns False if ``stop`` was set first.

    Raises
    ------
    StartupError
        One of them exited meanwhile (a bad setting, a file it cannot write), or
        ``timeout_s`` passed without all tokens.
    """
    deadline = time.monotonic() + timeout_s
    names = set(names)
    seen: set[str] = set()
    while not names <= seen:
        for child in children:
            if not child.alive():
                raise StartupError(f"{child.name} exited with code {child.proc.returncode} while starting "
                                   "(its error is above)")
        if stop.is_set():
            return False
        if time.monotonic() > deadline:
            raise StartupError(f"no liveliness token from {', '.join(sorted(names - seen))} within "
                               f"{timeout_s:.0f} s")
        for reply in session.liveliness().get(topics.alive(robot, topics.ANY), timeout=0.5):
            if reply.ok is not None:
                seen.add(topics.robot_and_service(str(reply.ok.key_expr))[1])
        time.sleep(0.1)
    return True


def bus_settings(config: str | None) -> BusConfig:
    """The bus settings the config file and the environment give every stage."""
    return config_mod.load(BusConfig, table=config_mod.read_file(config, services.CONFIG_TABLES).get("bus", {}),
                           env=os.environ, env_prefix=f"{config_mod.ENV_PREFIX}_BUS")


def check_configs(sets: dict[str, list[str]], config: str | None) -> dict:
    """Layer every stage's config as its process will, so a bad setting stops ``up`` before it starts anything.

    Returns each stage's config.

    Raises
    ------
    ConfigError
        Naming the stage.
    """
    file = config_mod.read_file(config, services.CONFIG_TABLES)
    configs = {}
    for name, items in sets.items():
        try:
            configs[name] = config_mod.service_config(services.spec(name), sets=items, file=file, env=os.environ)
        except ConfigError as exc:
            raise ConfigError(f"{name}: {exc}") from exc
    return configs


def remove_if_empty(recording: Path) -> None:
    """Delete the run's recording folder if it holds no data (only health and its views), as after a failed start."""
    if not recording.is_dir():
        return
    try:
        empty = all(topics.is_health(name) or topics.is_foxglove(name) for name in count_messages(recording))
    except LrfSlamError:
        empty = True
    if empty:
        shutil.rmtree(recording)
        log.info("removed %s: nothing was recorded", recording)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lrfslam up", description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=0.0, help="seconds to run once the pipeline is up (default: until Ctrl-C)")
    parser.add_argument("--speedup", type=float, default=1.0, help="simulated seconds per wall second")
    parser.add_argument("--seed", type=int, default=1, help="simulator seed")
    parser.add_argument("--robot", default="robot1")
    parser.add_argument("--port", type=int, default=7447, help="router port on 127.0.0.1")
    parser.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                        help="extra router endpoint for other hosts, e.g. tls/0.0.0.0:7448 with --zenoh-config; "
                             "a plain tcp/ or udp/ one beyond loopback only with --insecure")
    parser.add_argument("--zenoh-config", metavar="FILE",
                        help="Zenoh JSON5 config of up's router, e.g. deploy/zenoh/router-tls.json5 for a tls/ "
                             "--listen endpoint (mutual TLS: only holders of a certificate of your CA get in)")
    parser.add_argument("--insecure", action="store_true",
                        help="allow a plain --listen endpoint beyond loopback: whoever reaches it reads and "
                             "publishes on the bus (a closed network where that is wanted)")
    parser.add_argument("--connect", metavar="ENDPOINT",
                        help="use the router at ENDPOINT (e.g. another up's, tcp/127.0.0.1:7447) instead of "
                             "starting one; robots with different --robot names share it without crosstalk")
    parser.add_argument("--join", action="store_true",
                        help="start even though services of this robot are alive on the router (each "
                             "service too); without it up stops with one error line, exit 2")
    parser.add_argument("--config", help="TOML config passed to every service")
    parser.add_argument("--set", dest="sets", action="append", default=[], metavar="SERVICE.NAME=VALUE",
                        help="override one service setting, e.g. --set features.mode=paper")
    parser.add_argument("--skip", action="append", default=[], choices=OPTIONAL, metavar="SERVICE",
                        help="leave a stage out: --skip mapper runs the EKF without loop closing (with "
                             "--set slam.scan_matching=false, the paper's filter alone); --skip sensor waits for "
                             "scans from lrfslam play")
    parser.add_argument("--group", metavar="STAGES",
                        help="run these stages in one process (lrfslam group) on a small computer, e.g. "
                             "denoise,features,slam: less CPU and memory, fresher answers; each is still its own "
                             "service on the bus, restarted with the others (docs/delivery.md, Stages sharing a "
                             "process)")
    parser.add_argument("--recordings", default="recordings",
                        help="parent of the recording folder (<UTC time>_<robot>/, one MCAP segment per recorder start)")
    parser.add_argument("--max-restarts", type=int, default=3, help="restarts of each process (the router too)")
    parser.add_argument("--log-level", default="WARNING", help="log level of the services")
    parser.add_argument("-q", "--quiet", action="store_true", help="no live status line while running")
    parser.add_argument("--status-period", type=float, default=5.0, metavar="S",
                        help="seconds between live status lines (default 5)")
    parser.add_argument("--monitor", action="store_true",
                        help="also run lrfslam monitor --dashboard (Foxglove on --monitor-port, the web "
                             "dashboard on --http-port, both on 127.0.0.1), supervised like the services")
    parser.add_argument("--monitor-port", type=int, default=8765, help="with --monitor: Foxglove WebSocket port")
    parser.add_argument("--http-port", type=int, default=8080, help="with --monitor: the dashboard's port")
    parser.add_argument("--ros2", action="store_true",
                        help="also run lrfslam ros2 (the robot's topics for ROS 2 over rmw_zenoh on this router, "
                             "domain --domain-id; docs/ros2.md), supervised like the services")
    parser.add_argument("--domain-id", type=int, default=0, help="with --ros2: the ROS_DOMAIN_ID (default 0)")
    parser.add_argument("--save-map", type=Path, metavar="MAP",
                        help="when the run ends, save its map into the folder MAP as lrfslam map save does "
                             "(docs/maps.md); MAP must not exist or be empty")
    parser.add_argument("--map", type=Path, metavar="MAP",
                        help="a saved map (lrfslam map save): map on from it — the robot is found on it, then "
                             "new places are added and revisits close into it (with --save-map, the map grown); "
                             "with --localize, only localize in it")
    parser.add_argument("--localize", action="store_true",
                        help="find the robot on --map by a global search and track it there, the map unchanged "
                             "(docs/maps.md); map/pose says whether each scan is localized")
    args = parser.parse_args(argv)
    if args.localize and args.map is None:
        parser.error("--localize needs --map, the saved map to localize in")
    if args.localize and args.save_map:
        parser.error("--localize changes no map: not with --save-map (without --localize, --map maps on from it)")
    if args.map is not None and "mapper" in args.skip:
        parser.error("--map is the mapper's: not with --skip mapper")
    if not args.status_period > 0:
        parser.error(f"--status-period must be > 0 s, got {args.status_period}")
    if args.ros2:
        from lrfslam.tools.ros2 import Ros2Config  # (rosbags only when asked for)
        try:   # refused before anything starts, with the bridge's own check
            Ros2Config(domain_id=args.domain_id)
        except ConfigError as exc:
            parser.error(str(exc))
    if args.connect and (args.listen or args.zenoh_config):
        parser.error("--listen and --zenoh-config set up's own router; with --connect up starts no router")
    if args.save_map and "mapper" in args.skip:
        parser.error("--save-map saves the mapper's map: not with --skip mapper")
    if args.save_map:
        try:
            maps.check_target(args.save_map)
        except MapError as exc:
            print(f"lrfslam up: error: {exc}", file=sys.stderr)
            return 1
    setup_logging("up", "INFO")
    check_listen(args.listen, args.insecure, None)   # before anything starts; its router warns

    order = tuple(n for n in START_ORDER if n not in args.skip)
    try:
        sets = config_mod.by_service(args.sets, order)
        group = group_stages(args.group) if args.group else []
    except ConfigError as exc:
        parser.error(str(exc))
    if skipped := [n for n in group if n not in order]:
        parser.error(f"--group {args.group}: {', '.join(skipped)} is left out by --skip")
    stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime())
    # One folder for the run: a restarted recorder adds the next segment to it.
    recording = Path(args.recordings) / f"{stamp}_{args.robot}"
    sets["recorder"] += [f"directory={recording.parent}", f"name={recording.name}"]
    if "sensor" in sets:
        sets["sensor"] += [f"speedup={args.speedup}", f"seed={args.seed}"]
    base = None
    if args.map is not None:
        try:
            base = maps.load_map(args.map)   # refused before anything starts, as the mapper would refuse it
        except MapError as exc:
            print(f"lrfslam up: error: {exc}", file=sys.stderr)
            return 1
        sets["mapper"] += [f"map={args.map.resolve()}", *(["localize=true"] if args.localize else [])]
    if args.speedup != 1 or "sensor" not in sets:
        # Simulated stamps (or a recording's, played in) leave the wall clock: no stage reports
        # their age (docs/monitoring.md). Through the environment every process up starts shares
        # it, as it shares the router.
        os.environ.setdefault(f"{config_mod.ENV_PREFIX}_BUS_WALL_CLOCK_STAMPS", "false")
    topics.check_robot(args.robot)
    configs = check_configs(sets, args.config)
    # A killed stage that keeps state resumes from its checkpoint in the recording folder (its
    # first start finds none: the folder is new), unless the config puts checkpoints elsewhere.
    stage_env = {} if bus_settings(args.config).checkpoint_dir else {CHECKPOINT_DIR_ENV: str(recording)}
    extra = {n: [a for item in items for a in ("--set", item)] for n, items in sets.items()}

    endpoint = args.connect or f"tcp/127.0.0.1:{args.port}"
    stop = threading.Event()
    install_signal_handlers(stop)
    router = None if args.connect else Child(
        "router", [sys.executable, "-m", "lrfslam.cli", "router", "--log-level", args.log_level]
        + (["--zenoh-config", args.zenoh_config] if args.zenoh_config else [])
        + [a for ep in [endpoint, *args.listen] for a in ("--listen", ep)]
        + (["--insecure"] if args.insecure else []))
    router_id = start_router(router) if router else None
    together = Child("+".join(group), child_argv("group", args, endpoint, [
        ",".join(group), *(a for n in group for item in sets[n] for a in ("--set", f"{n}.{item}"))]),
        env=stage_env) if group else None
    children = {n: together if n in group else Child(n, child_argv(n, args, endpoint, extra[n]), env=stage_env)
                for n in order}
    processes = list(dict.fromkeys(children.values()))   # a group is one process for several stages
    monitor = Child("monitor", [sys.executable, "-m", "lrfslam.cli", "monitor", "--connect", endpoint, "--robot",
                                args.robot, "--dashboard", "--port", str(args.monitor_port), "--http-port",
                                str(args.http_port), "--log-level", args.log_level]) if args.monitor else None
    ros2 = Child("ros2", [sys.executable, "-m", "lrfslam.cli", "ros2", "--connect", endpoint, "--robot", args.robot,
                          "--domain-id", str(args.domain_id), "--log-level", args.log_level]) if args.ros2 else None
    viewers = [c for c in (monitor, ros2) if c]
    supervised = ([router] if router else []) + processes + viewers
    observer = Observer()
    started = time.monotonic()
    try:
        session = open_own_session(endpoint, router, router_id, 10.0)
    except StartupError:
        if router:
            router.stop(5)
        raise
    with closing(session):
        subs = [session.declare_subscriber(topics.key(args.robot, topics.TRUTH.name), observer.on_truth),
                session.declare_subscriber(topics.key(args.robot, topics.SLAM_STATE.name), observer.on_state),
                session.declare_subscriber(topics.health_key(args.robot, topics.ANY), observer.on_health),
                session.liveliness().declare_subscriber(topics.alive(args.robot, topics.ANY), observer.on_alive)]

        def abort() -> None:
            for child in children.values():
                child.stop(5)
            for sub in subs:
                sub.undeclare()
            if router:
                router.stop(5)

        try:
            if not args.join and (found := live_services(session, args.robot)):
                raise StartupError(
                    f"robot {args.robot!r} already has services running on {endpoint}: "
                    + ", ".join(f"{n} ({w})" if w else n for n, w in sorted(found.items()))
                    + "; start with another --robot, or with --join to run beside them")
            stages = [n for n in order if n != "sensor"]
            for child in dict.fromkeys(children[n] for n in stages):
                child.start()
            up = wait_alive(session, args.robot, stages, [children[n] for n in stages], START_TIMEOUT_S, stop)
        except StartupError:
            abort()
            remove_if_empty(recording)
            raise
        if up:
            if "sensor" in children:
                children["sensor"].start()
            for viewer in viewers:
                viewer.start()
        log.info("pipeline up: robot %s, router %s, recording %s", args.robot, endpoint, recording)
        if "sensor" not in children:
            log.info("no sensor: play a recording in with lrfslam play RECORDING --robot %s --connect %s",
                     args.robot, endpoint)
        if monitor:
            log.info("monitor: Foxglove ws://127.0.0.1:%d, dashboard http://127.0.0.1:%d/", args.monitor_port,
                     args.http_port)
        if ros2:
            log.info("ros2: node /%s/lrfslam on ROS domain %d via %s (RMW_IMPLEMENTATION=rmw_zenoh_cpp)",
                     wire.namespace_of(args.robot), args.domain_id, endpoint)
        live = LiveLine(time.monotonic())
        next_line = time.monotonic() + args.status_period
        # The run's length counts from here: starting the processes can take seconds on a busy machine.
        deadline = time.monotonic() + args.duration if args.duration > 0 else None
        rate_hz = configs["sensor"].rate_hz if "sensor" in configs else 0.0
        while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
            observer.process()
            note_returns(observer, router, children)
            for child in supervised:
                if child.alive() or child.stopping:
                    continue
                code = child.proc.returncode if child.proc else None
                if child.restarts >= args.max_restarts:
                    log.error("%s exited (%s) %d times; giving up on it", child.name, code, child.restarts + 1)
                    child.stopping = child.gave_up = True
                    if child is router:
                        log.error("without its router the pipeline cannot run: stopping")
                        stop.set()
                    continue
                child.restarts += 1
                child.down_since = time.monotonic()
                log.warning("%s exited with %s; restarting (%d/%d)", child.name, code, child.restarts,
                            args.max_restarts)
                if child is router:
                    router.waiting_for = {c.name for c in children.values() if c.alive()}
                    start_router(router)
                elif child.name == "sensor" and (epoch := observer.truth.epoch_ns(rate_hz)) is not None:
                    # The simulated robot kept moving while its sensor was down, as a real one would.
                    child.start(["--set", f"epoch_ns={epoch}"])
                else:
                    child.start()
            if not args.quiet and time.monotonic() >= next_line:
                next_line += args.status_period
                print(live.line(observer, time.monotonic()), flush=True)
            stop.wait(POLL_S)
        if "sensor" in children:
            log.info("stopping: sensor first, then draining the pipeline")
            children["sensor"].stop(10)
        else:
            log.info("stopping: draining the pipeline")
        _drain(observer, 5.0)
        for name in services.NAMES:
            if name != "sensor" and name in children:
                children[name].stop(15)
        for viewer in viewers:
            viewer.stop(10)
        time.sleep(0.3)  # let the last health messages arrive
        observer.process()
        for sub in subs:
            sub.undeclare()
    if router:
        router.stop(5)
    print(summary(observer, children, recording, time.monotonic() - started, router, viewers))
    saved = save_map(recording, args.save_map, base) if args.save_map else True
    return 1 if any(c.gave_up for c in supervised) or not saved else 0


def save_map(recording: Path, out: Path, base: SavedMap | None) -> bool:
    """``--save-map``: the run's recording (its recorder stopped) saved as ``lrfslam map save`` does
    (``base``: the map it mapped on from, ``--map``); one line either way."""
    try:
        saved, notes = maps.save_map(recording, out, base=base)
    except (MapError, RecordingError) as exc:
        print(f"lrfslam up: error: the map was not saved: {exc}", file=sys.stderr)
        return False
    for note in notes:
        print(f"lrfslam up: map: {note}", file=sys.stderr)
    print(f"map: saved to {out}/ ({maps.summary_line(saved)})")
    return True


class LiveLine:
    """up's status line while it runs: scans published, their rate since the last line, landmarks,
    and the pose error against the truth where a simulator gives one."""

    def __init__(self, now_s: float) -> None:
        self.started_s = self.last_s = now_s
        self.last_scans = 0

    def line(self, observer: Observer, now_s: float) -> str:
        """The line at monotonic time ``now_s``."""
        observer.process()
        # Without a sensor (--skip sensor), the scans played in, as the first stage took them.
        scans = (observer.counters("sensor").get(f"{counters.OUT}{topics.SCAN.name}", 0)
                 or observer.counters("denoise").get(f"{counters.IN}{topics.SCAN.name}", 0))
        rate = (scans - self.last_scans) / (now_s - self.last_s) if now_s > self.last_s else 0.0
        self.last_s, self.last_scans = now_s, scans
        parts = [f"[{now_s - self.started_s:6.1f} s] scans {scans} ({rate:.1f}/s)"]
        if observer.truth.last_state is not None:
            try:
                state = codec.SLAM_STATE.decode(observer.truth.last_state)
                parts.append(f"landmarks {state.n_landmarks} ({state.n_confirmed} confirmed)")
            except DecodeError:
                pass
        if (errors := observer.truth.errors).matched:
            parts.append(f"pose error {errors.final[0] * 100:.1f} cm, {np.degrees(errors.final[1]):.2f} deg")
        return "  ".join(parts)


def start_router(router: Child) -> str:
    """Start (or restart) ``router`` under a new Zenoh id; the id."""
    # Random, so up can tell its own router from one that already held the port.
    router_id = "1" + secrets.token_hex(7)
    router.start(["--id", router_id])
    return router_id


def open_own_session(endpoint: str, router: Child | None, router_id: str | None, timeout_s: float) -> zenoh.Session:
    """up's client session: to its own router (checked by Zenoh id), or with ``--connect`` to the given one.

    Raises
    ------
    StartupError
        The router exited (it cannot listen: its own error line is above), another
        router answers on the port, or nothing answers within ``timeout_s``.
    """
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            session = zenoh.open(client_config([endpoint]))
            break
        except zenoh.ZError as exc:
            if router is not None and not router.alive():
                raise StartupError(f"the router exited with code {router.proc.returncode} while starting "
                                   "(its error is above)") from None
            if time.monotonic() > deadline:
                raise StartupError(f"cannot reach the router at {endpoint}: {str(exc).split(' at /')[0]}") from None
            time.sleep(0.2)
    if router_id is not None and router_id not in {str(z) for z in session.info.routers_zid()}:
        session.close()
        try:
            router.proc.wait(5)   # a router that cannot listen exits with its own error line
        except subprocess.TimeoutExpired:
            pass
        raise StartupError(f"another router already listens on {endpoint} (another lrfslam up?); pass another "
                           "--port, or --connect to it with another --robot")
    return session


def note_returns(observer: Observer, router: Child | None, children: dict[str, Child]) -> None:
    """Log each restarted process once it is back: its liveliness token again, for the router every service's."""
    while observer.alive_events:
        name, present, at = observer.alive_events.popleft()
        if not present:
            continue
        child = children.get(name)
        if child is not None and child.down_since is not None and at >= child.down_since:
            child.downtimes.append(at - child.down_since)
            log.info("%s back after %.2f s (restart %d)", name, child.downtimes[-1], child.restarts)
            child.down_since = None
        if router is not None and router.down_since is not None and at >= router.down_since:
            router.waiting_for.discard(name)
            if not router.waiting_for:
                router.downtimes.append(at - router.down_since)
                log.info("router back after %.2f s (restart %d): every service reconnected",
                         router.downtimes[-1], router.restarts)
                router.down_since = None


def _drain(observer: Observer, timeout_s: float) -> None:
    """Wait until the SLAM state has caught up with the last ground truth (or ``timeout_s``)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        observer.process()
        if observer.truth.caught_up():
            return
        time.sleep(0.1)


def summary(observer: Observer, children: dict[str, Child], recording: Path, wall_s: float,
            router: Child | None = None, viewers: Sequence[Child] = ()) -> str:
    """The table of stages (counters summed over restarts), SLAM against truth, and the recording.

    ``wall_s`` is the run's duration on the monotonic clock. ``dropped`` counts inputs a stage
    received but never handled (its full queue refused them, or they were still queued when it
    was stopped), ``gaps`` inputs that never reached it (sequence numbers skipped; docs/delivery.md),
    ``skipped`` inputs a stage that fell behind skipped to answer the newest (bridged; not losses of
    the recording).
    """
    lines = ["", f"lrfslam up: ran {wall_s:.1f} s (monotonic clock)", "",
             "stage      in          out         dropped  gaps    skipped  errors  restarts  exit"]
    for name, child in children.items():
        f = counter_figures(observer.counters(name))
        code = child.proc.returncode if child.proc else None
        lines.append(f"{name:10s} {f['in']:<11d} {f['out']:<11d} {f['dropped']:<8d} {f['gaps']:<7d} "
                     f"{f['skipped']:<8d} {f['errors']:<7d} {child.restarts:<9d} {code}")
    err = observer.truth.pose_errors()
    lines.append("")
    if err is None:
        lines.append("SLAM: no state matched to ground truth")
    else:
        lines.append(f"SLAM: {err['scans']:.0f} scans, {err['landmarks']:.0f} landmarks "
                     f"({err['confirmed']:.0f} confirmed)")
        lines.append(f"      final pose error {err['final_xy_m'] * 100:.1f} cm, {err['final_heading_deg']:.2f} deg; "
                     f"trajectory RMSE {err['ate_rmse_m'] * 100:.1f} cm (first pose anchored)")
    lines += recording_lines(recording, observer.counters("sensor").get(f"{counters.OUT}{topics.SCAN.name}", 0)
                             if "sensor" in children else None)
    lines += unrecorded_lines(observer, recording, children.get("recorder"))
    lines += restart_lines(([router] if router else []) + list(dict.fromkeys(children.values())) + list(viewers))
    return "\n".join(lines)


def unrecorded_lines(observer: Observer, recording: Path, recorder: Child | None) -> list[str]:
    """Scans the sensor published (as up heard them) that the recording lacks, if any."""
    published = len(observer.truth.published)
    if not published or recorder is None:
        return []
    try:
        recorded = {m.sequence for m in read_recording(recording, [topics.SCAN.name])}
    except RecordingError:
        return []
    missing = observer.truth.published.missing_from(recorded)
    if not missing:
        return []
    why = (f" (the recorder restarted {recorder.restarts} time{'s' * (recorder.restarts > 1)}: each kill loses "
           "its last unflushed second, and the restart what came meanwhile)" if recorder.restarts else "")
    return [f"recording: {missing} of the {published} scans published are not in it{why}"]


def restart_lines(children: list[Child]) -> list[str]:
    """How long each restarted process took to be back."""
    parts = [f"{c.name} {c.restarts} (back after " + ", ".join(f"{d:.2f}" for d in c.downtimes) + " s)"
             if c.downtimes else f"{c.name} {c.restarts} (not back)" for c in children if c.restarts]
    return ["restarts: " + "; ".join(parts)] if parts else []


def recording_lines(recording: Path, published_scans: int | None) -> list[str]:
    """Scans published against scans recorded (``published_scans`` None: no sensor ran); the folder:
    messages per topic, then each segment (size, messages, whether it needs recovering)."""
    report = ReadReport()

    def lost(recorded: int) -> str:
        if published_scans is None:
            return f"scans in the recording {recorded} (no sensor: played in or published by another process)"
        return (f"scans published by the sensor {published_scans} / scans in the recording {recorded} / "
                f"lost {published_scans - recorded}")
    try:
        per_topic = count_messages(recording, report)
    except RecordingError as exc:
        return [lost(0), f"recording: {recording} was not written ({exc})"]
    size = sum(seg.path.stat().st_size for seg in report.segments)
    return [lost(per_topic[topics.SCAN.name]),
            f"recording: {recording}/ ({len(report.segments)} segment{'s' * (len(report.segments) > 1)}, "
            f"{size / 1e6:.1f} MB, {sum(per_topic.values())} messages: "
            + ", ".join(f"{k} {v}" for k, v in sorted(per_topic.items())
                        if not topics.is_health(k) and not topics.is_foxglove(k)) + ")",
            *segment_lines(report)]
