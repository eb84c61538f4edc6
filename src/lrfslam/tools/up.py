"""``lrfslam up``: the whole pipeline as separate processes, supervised, with a summary.

Checks every stage's settings, starts a Zenoh router, then recorder, mapper, slam,
features and denoise, waits until each has declared its liveliness token, then starts
the sensor. A stage that exits while starting (or has no token after 30 s) stops
everything at once: ``up`` exits with code 2 and removes the recording if it holds
nothing. A service that dies
is restarted (up to ``--max-restarts`` times). On Ctrl-C, SIGTERM or after
``--duration`` seconds the sensor stops first, the pipeline drains, the rest stop
in order, and a summary compares the SLAM estimate with the simulator's ground truth.
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zenoh

from lrfslam import services
from lrfslam.algo.geometry import compose, relative, wrap_angle
from lrfslam.errors import (
    ConfigError,
    DecodeError,
    LrfSlamError,
    RecordingError,
    StartupError,
)
from lrfslam.msgs import codec, topics
from lrfslam.runtime import config as config_mod
from lrfslam.runtime.bus import parse_attachment
from lrfslam.runtime.recording import ReadReport, read_recording
from lrfslam.runtime.runner import install_signal_handlers, setup_logging
from lrfslam.tools.info import segment_lines
from lrfslam.tools.status import client_config

log = logging.getLogger("lrfslam.up")

START_ORDER = ("recorder", "mapper", "slam", "features", "denoise", "sensor")
#: How long the stages before the sensor have to declare their liveliness tokens.
START_TIMEOUT_S = 30.0
#: Stages ``--skip`` may leave out (every other one is needed for SLAM to run at all).
OPTIONAL = ("mapper",)


@dataclass
class Child:
    """One supervised process."""

    name: str
    argv: list[str]
    proc: subprocess.Popen | None = None
    restarts: int = 0
    stopping: bool = False

    def start(self) -> None:
        self.proc = subprocess.Popen(self.argv, stdin=subprocess.DEVNULL)

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


@dataclass
class Observer:
    """What the supervisor hears on the bus: truth, SLAM states and each service's last health.

    ``health`` holds the last health of every run of a service (keyed by service and the
    producer id of its process), so the summary adds up the runs of a restarted service.
    """

    truth: dict[int, bytes] = field(default_factory=dict)
    states: deque = field(default_factory=lambda: deque(maxlen=100_000))
    health: dict[tuple[str, bytes], bytes] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_truth(self, sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        att = sample.attachment
        stamp = parse_attachment(att.to_bytes() if att is not None else None).stamp_ns
        with self.lock:
            self.truth[stamp] = data

    def on_state(self, sample: zenoh.Sample) -> None:
        with self.lock:
            self.states.append(sample.payload.to_bytes())

    def on_health(self, sample: zenoh.Sample) -> None:
        att = sample.attachment
        run = parse_attachment(att.to_bytes() if att is not None else None).producer
        with self.lock:
            self.health[(topics.robot_and_service(str(sample.key_expr))[1], run)] = sample.payload.to_bytes()

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

    def last_state_stamp(self) -> int:
        with self.lock:
            return codec.SLAM_STATE.decode(self.states[-1]).stamp_ns if self.states else 0


def child_argv(name: str, args: argparse.Namespace, endpoint: str, extra: list[str]) -> list[str]:
    argv = [sys.executable, "-m", "lrfslam.cli", name, "--robot", args.robot, "--mode", "client",
            "--connect", endpoint, "--log-level", args.log_level]
    if args.config:
        argv += ["--config", args.config]
    return argv + extra


def wait_alive(session: zenoh.Session, robot: str, children: list[Child], timeout_s: float,
               stop: threading.Event) -> bool:
    """Wait until every one of ``children`` has declared its liveliness token.

    Returns False if ``stop`` was set first.

    Raises
    ------
    StartupError
        One of them exited meanwhile (a bad setting, a file it cannot write), or
        ``timeout_s`` passed without all tokens.
    """
    deadline = time.monotonic() + timeout_s
    names = {c.name for c in children}
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


def check_configs(sets: dict[str, list[str]], config: str | None) -> None:
    """Layer every stage's config as its process will, so a bad setting stops ``up`` before it starts anything.

    Raises
    ------
    ConfigError
        Naming the stage.
    """
    file = config_mod.read_file(config, services.CONFIG_TABLES)
    for name, items in sets.items():
        try:
            config_mod.service_config(services.spec(name), sets=items, file=file, env=os.environ)
        except ConfigError as exc:
            raise ConfigError(f"{name}: {exc}") from exc


def remove_if_empty(recording: Path) -> None:
    """Delete the run's recording folder if it holds no data (only health), as after a failed start."""
    if not recording.is_dir():
        return
    try:
        empty = all(topics.is_health(m.topic) for m in read_recording(recording))
    except LrfSlamError:
        empty = True
    if empty:
        shutil.rmtree(recording)
        log.info("removed %s: nothing was recorded", recording)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lrfslam up", description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=0.0, help="seconds to run (default: until Ctrl-C)")
    parser.add_argument("--speedup", type=float, default=1.0, help="simulated seconds per wall second")
    parser.add_argument("--seed", type=int, default=1, help="simulator seed")
    parser.add_argument("--robot", default="robot1")
    parser.add_argument("--port", type=int, default=7447, help="router port on 127.0.0.1")
    parser.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                        help="extra router endpoint, e.g. tcp/0.0.0.0:7447 for remote monitoring")
    parser.add_argument("--config", help="TOML config passed to every service")
    parser.add_argument("--set", dest="sets", action="append", default=[], metavar="SERVICE.NAME=VALUE",
                        help="override one service setting, e.g. --set features.mode=paper")
    parser.add_argument("--skip", action="append", default=[], choices=OPTIONAL, metavar="SERVICE",
                        help="leave a stage out: --skip mapper runs the EKF without loop closing (with "
                             "--set slam.scan_matching=false, the paper's filter alone)")
    parser.add_argument("--recordings", default="recordings",
                        help="parent of the recording folder (<UTC time>_<robot>/, one MCAP segment per recorder start)")
    parser.add_argument("--max-restarts", type=int, default=3)
    parser.add_argument("--log-level", default="WARNING", help="log level of the services")
    args = parser.parse_args(argv)
    setup_logging("up", "INFO")

    order = tuple(n for n in START_ORDER if n not in args.skip)
    sets: dict[str, list[str]] = {n: [] for n in order}
    for item in args.sets:
        service, dot, rest = item.partition(".")
        if not dot or service not in sets:
            parser.error(f"--set expects SERVICE.NAME=VALUE with SERVICE in {', '.join(order)}: {item!r}")
        sets[service].append(rest)
    stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime())
    # One folder for the run: a restarted recorder adds the next segment to it.
    recording = Path(args.recordings) / f"{stamp}_{args.robot}"
    sets["recorder"] += [f"directory={recording.parent}", f"name={recording.name}"]
    sets["sensor"] += [f"speedup={args.speedup}", f"seed={args.seed}"]
    topics.check_robot(args.robot)
    check_configs(sets, args.config)
    extra = {n: [a for item in items for a in ("--set", item)] for n, items in sets.items()}

    endpoint = f"tcp/127.0.0.1:{args.port}"
    stop = threading.Event()
    install_signal_handlers(stop)
    router = Child("router", [sys.executable, "-m", "lrfslam.cli", "router", "--log-level", args.log_level]
                   + [a for ep in [endpoint, *args.listen] for a in ("--listen", ep)])
    router.start()
    children = {n: Child(n, child_argv(n, args, endpoint, extra[n])) for n in order}
    observer = Observer()
    counts: Counter = Counter()
    started = time.monotonic()
    try:
        session = _open_with_retry(endpoint, router, 10.0)
    except RuntimeError as exc:
        log.error("%s", exc)
        router.stop(5)
        return 2
    with session:
        subs = [session.declare_subscriber(topics.key(args.robot, topics.TRUTH.name), observer.on_truth),
                session.declare_subscriber(topics.key(args.robot, topics.SLAM_STATE.name), observer.on_state),
                session.declare_subscriber(topics.health_key(args.robot, topics.ANY), observer.on_health)]
        for name in order[:-1]:
            children[name].start()
        try:
            up = wait_alive(session, args.robot, [children[n] for n in order[:-1]], START_TIMEOUT_S, stop)
        except StartupError:
            for child in children.values():
                child.stop(5)
            for sub in subs:
                sub.undeclare()
            router.stop(5)
            remove_if_empty(recording)
            raise
        if up:
            children["sensor"].start()
        log.info("pipeline up: robot %s, router %s, recording %s", args.robot, endpoint, recording)
        deadline = started + args.duration if args.duration > 0 else None
        while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
            for child in children.values():
                if not child.alive() and not child.stopping:
                    code = child.proc.returncode if child.proc else None
                    if child.restarts >= args.max_restarts:
                        log.error("%s exited (%s) %d times; giving up on it", child.name, code, child.restarts + 1)
                        child.stopping = True
                        continue
                    child.restarts += 1
                    counts[f"restart.{child.name}"] += 1
                    log.warning("%s exited with %s; restarting (%d/%d)", child.name, code, child.restarts,
                                args.max_restarts)
                    child.start()
            stop.wait(0.2)
        log.info("stopping: sensor first, then draining the pipeline")
        children["sensor"].stop(10)
        _drain(observer, 5.0)
        for name in ("denoise", "features", "slam", "mapper", "recorder"):
            if name in children:
                children[name].stop(15)
        time.sleep(0.3)  # let the last health messages arrive
        for sub in subs:
            sub.undeclare()
    router.stop(5)
    print(summary(observer, children, recording, time.monotonic() - started))
    return 0


def _open_with_retry(endpoint: str, router: Child, timeout_s: float) -> zenoh.Session:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return zenoh.open(client_config([endpoint]))
        except zenoh.ZError as exc:
            if time.monotonic() > deadline or not router.alive():
                raise RuntimeError(f"cannot reach the router at {endpoint}: {exc}") from exc
            time.sleep(0.2)


def _drain(observer: Observer, timeout_s: float) -> None:
    """Wait until the SLAM state has caught up with the last ground truth (or ``timeout_s``)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with observer.lock:
            last_truth = max(observer.truth) if observer.truth else 0
        if observer.last_state_stamp() >= last_truth:
            return
        time.sleep(0.1)


def pose_errors(observer: Observer) -> dict[str, float] | None:
    """Final-pose and trajectory errors of SLAM against truth, both anchored at SLAM's first pose."""
    with observer.lock:
        states = [codec.SLAM_STATE.decode(b) for b in observer.states]
        truth = {k: codec.GROUND_TRUTH.decode(v) for k, v in observer.truth.items()}
    pairs = [(s, truth[s.stamp_ns]) for s in states if s.stamp_ns in truth]
    if not pairs:
        return None
    # SLAM's map frame is its first pose; express its estimates in the world frame.
    first_est, first_true = pairs[0]
    anchor = compose(first_true.pose, relative(first_est.pose, np.zeros(3)))
    est = np.array([compose(anchor, s.pose) for s, _ in pairs])
    tru = np.array([g.pose for _, g in pairs])
    d = np.linalg.norm(est[:, :2] - tru[:, :2], axis=1)
    last = pairs[-1][0]
    return {
        "scans": float(len(pairs)),
        "final_xy_m": float(d[-1]),
        "final_heading_deg": float(np.degrees(abs(wrap_angle(est[-1, 2] - tru[-1, 2])))),
        "ate_rmse_m": float(np.sqrt(np.mean(d ** 2))),
        "landmarks": float(last.landmark_ids.size),
        "confirmed": float(last.landmark_confirmed.sum()),
    }


def summary(observer: Observer, children: dict[str, Child], recording: Path, wall_s: float) -> str:
    """The table of stages (counters summed over restarts), SLAM against truth, and the recording.

    ``wall_s`` is the run's duration on the monotonic clock. ``dropped`` counts inputs a stage
    received but never handled (its full queue refused them, or they were still queued when it
    was stopped), ``gaps`` inputs that never reached it (sequence numbers skipped; docs/delivery.md).
    """
    lines = ["", f"lrfslam up: ran {wall_s:.1f} s (monotonic clock)", "",
             "stage      in          out         dropped  gaps    errors  restarts  exit"]
    for name, child in children.items():
        c = observer.counters(name)
        ins = sum(v for k, v in c.items() if k.startswith("in."))
        outs = sum(v for k, v in c.items() if k.startswith("out.") and not k.startswith("out.health"))
        gaps = sum(v for k, v in c.items() if k.startswith("gap."))
        dropped = sum(v for k, v in c.items() if k.startswith("drop."))
        errs = sum(v for k, v in c.items() if k.startswith("error.") or ".error" in k)
        code = child.proc.returncode if child.proc else None
        lines.append(f"{name:10s} {ins:<11d} {outs:<11d} {dropped:<8d} {gaps:<7d} {errs:<7d} "
                     f"{child.restarts:<9d} {code}")
    err = pose_errors(observer)
    lines.append("")
    if err is None:
        lines.append("SLAM: no state matched to ground truth")
    else:
        lines.append(f"SLAM: {err['scans']:.0f} scans, {err['landmarks']:.0f} landmarks "
                     f"({err['confirmed']:.0f} confirmed)")
        lines.append(f"      final pose error {err['final_xy_m'] * 100:.1f} cm, {err['final_heading_deg']:.2f} deg; "
                     f"trajectory RMSE {err['ate_rmse_m'] * 100:.1f} cm (first pose anchored)")
    lines += recording_lines(recording, observer.counters("sensor").get(f"out.{topics.SCAN.name}", 0))
    return "\n".join(lines)


def recording_lines(recording: Path, published_scans: int) -> list[str]:
    """Scans published against scans recorded; the folder: messages per topic, then each segment
    (size, messages, whether it needs recovering)."""
    report = ReadReport()

    def lost(recorded: int) -> str:
        return (f"scans published by the sensor {published_scans} / scans in the recording {recorded} / "
                f"lost {published_scans - recorded}")
    try:
        per_topic = Counter(m.topic for m in read_recording(recording, report=report))
    except RecordingError as exc:
        return [lost(0), f"recording: {recording} was not written ({exc})"]
    size = sum(seg.path.stat().st_size for seg in report.segments)
    return [lost(per_topic[topics.SCAN.name]),
            f"recording: {recording}/ ({len(report.segments)} segment{'s' * (len(report.segments) > 1)}, "
            f"{size / 1e6:.1f} MB, {sum(per_topic.values())} messages: "
            + ", ".join(f"{k} {v}" for k, v in sorted(per_topic.items()) if not topics.is_health(k)) + ")",
            *segment_lines(report)]
