"""The live pipeline as ``lrfslam bench`` (src/lrfslam/bench/command.py) measures it: real processes.

* :func:`run_up`: ``lrfslam up`` (router, sensor, denoise, features, slam, mapper, recorder, each its
  own process) on the simulator at a given scan rate for a given time. The sensor runs at speedup 1
  with ``sensor.rate_hz`` set to the rate and the robot's speed scaled with it (``SCAN_SPACING_M``
  per scan, the default 0.5 m/s at 10 Hz), so every rate gives the path and scan spacing of
  ``lrfslam up --speedup X``, stamped on the wall clock: the stages report their ``age`` (sensor
  stamp to output, src/lrfslam/runtime/latency.py), which they do not under a speedup. While it runs, a
  :class:`Sampler` asks every service's status once a second (``queue.pending``, the ``age``
  percentiles) and reads every process's peak resident memory; up's summary gives drops and gaps.
* :func:`run_play`: ``lrfslam up --skip sensor`` and ``lrfslam play RECORDING --rate max`` into it
  (src/lrfslam/tools/play.py): the whole pipeline at the pace of its slowest stage, with play's
  figures (monotonic clock) and the same memory sampling.

The process helpers (:func:`free_port`, :func:`children_of`, :func:`memory_kb`,
:func:`parse_summary`) serve src/lrfslam/bench/soak.py, src/lrfslam/bench/play.py and
src/lrfslam/bench/delivery.py too.
"""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zenoh

from lrfslam.errors import StartupError
from lrfslam.msgs import counters
from lrfslam.msgs import types as t
from lrfslam.runtime.runner import BACKLOG
from lrfslam.tools.status import client_config, query_status

ROBOT = "bench"
#: Metres the simulated robot moves per scan at every rate (0.5 m/s at the sensor's default 10 Hz).
SCAN_SPACING_M = 0.05
#: A queue grows when its median over the last quarter of the run is this many inputs above its
#: median over the first half (a steady backlog of a few scans is no growth; 1 input/s over 60 s is).
QUEUE_GROWTH = 16
#: Seconds between status and memory samples.
SAMPLE_PERIOD_S = 1.0
#: The stages ``lrfslam up --skip sensor`` starts, which must be alive before play starts.
PLAY_STAGES = ("recorder", "mapper", "slam", "features", "denoise")


def free_port() -> int:
    """A TCP port free on 127.0.0.1 right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def memory_kb(pid: int, field_name: str = "VmRSS") -> int | None:
    """``field_name`` of /proc/<pid>/status in kB (``VmRSS`` resident now, ``VmHWM`` its peak), None if gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(f"{field_name}:"):
                return int(line.split()[1])
    except (OSError, ValueError):
        return None
    return None


def cpu_seconds(pid: int) -> float | None:
    """User + system CPU time process ``pid`` has used so far (s), None if gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    # utime and stime are the 14th and 15th fields of stat(5); the 3rd is the first after the name.
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def children_of(pid: int) -> dict[str, int]:
    """``{lrfslam command: pid}`` of the processes ``pid`` started (up's router and services)."""
    found = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            argv = (entry / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        # The parent pid is the second field after the command name, which may hold spaces.
        if int(stat.rsplit(")", 1)[1].split()[1]) == pid and b"lrfslam.cli" in argv:
            found[argv[argv.index(b"lrfslam.cli") + 1].decode()] = int(entry.name)
    return found


@dataclass
class StageRow:
    """One line of up's summary table."""

    name: str
    ins: int
    outs: int
    dropped: int
    gaps: int
    skipped: int
    errors: int
    restarts: int
    exit: str


def parse_summary(stdout: str) -> tuple[dict[str, StageRow], tuple[int, int, int]]:
    """up's stage table and its ``scans published … / … in the recording … / lost …`` line (zeros without one)."""
    stages = {}
    for m in re.finditer(r"^(\w+)\s+(\d+)\s+(\d+)\s+(\d+)\s+(\d+)\s+(\d+)\s+(\d+)\s+(\d+)\s+(\S+)$", stdout, re.MULTILINE):
        name, *nums, code = m.groups()
        stages[name] = StageRow(name, *map(int, nums), code)
    m = re.search(r"scans published by the sensor (\d+) / scans in the recording (\d+) / lost (-?\d+)", stdout)
    counts = tuple(map(int, m.groups())) if m else (0, 0, 0)
    return stages, counts


def queue_growing(pending: list[int], min_growth: int = QUEUE_GROWTH) -> bool:
    """Whether a series of ``queue.pending`` samples grows: the median of its last quarter at least
    ``min_growth`` above the median of its first half (fewer than four samples: no verdict, False)."""
    if len(pending) < 4:
        return False
    return float(np.median(pending[-max(1, len(pending) // 4):])) - float(np.median(pending[:len(pending) // 2])) \
        >= min_growth


class Sampler:
    """Once every :data:`SAMPLE_PERIOD_S` in a thread: the robot's service statuses (kept while
    ``while_alive`` answers, or always if it is empty), and the peak resident memory (``VmHWM``) and
    CPU time used so far of process ``root_pid`` (as ``up``) and of every lrfslam process it started
    (the CPU time as last seen: a process's last second may be missing)."""

    def __init__(self, endpoint: str, robot: str, root_pid: int, while_alive: str = "") -> None:
        self.endpoint, self.robot, self.root_pid, self.while_alive = endpoint, robot, root_pid, while_alive
        self.snapshots: list[dict[str, t.ServiceStatus]] = []
        self.alive: set[str] = set()
        self.peak_kb: dict[str, int] = {}
        self.cpu_s: dict[str, float] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="bench-sampler", daemon=True)
        self._thread.start()

    def _memory(self) -> None:
        for name, pid in {"up": self.root_pid, **children_of(self.root_pid)}.items():
            kb = memory_kb(pid, "VmHWM")
            if kb is not None:
                self.peak_kb[name] = max(kb, self.peak_kb.get(name, 0))
            cpu = cpu_seconds(pid)
            if cpu is not None:
                self.cpu_s[name] = max(cpu, self.cpu_s.get(name, 0.0))

    def _run(self) -> None:
        session = None
        while not self._stop.is_set():
            self._memory()
            if session is None:
                try:
                    session = zenoh.open(client_config([self.endpoint]))
                except zenoh.ZError:
                    self._stop.wait(0.2)
                    continue
            alive, statuses = query_status(session, self.robot, 1.0)
            self.alive = {service for _, service in alive}
            by_service = {s.service: s for s in statuses}
            if not self.while_alive or self.while_alive in by_service:
                self.snapshots.append(by_service)
            self._stop.wait(SAMPLE_PERIOD_S)
        if session is not None:
            session.close()

    def wait_alive(self, names: tuple[str, ...], timeout_s: float, proc: subprocess.Popen) -> None:
        """Until every service of ``names`` has its liveliness token.

        Raises
        ------
        StartupError
            ``proc`` (up) exited meanwhile, or ``timeout_s`` passed.
        """
        deadline = time.monotonic() + timeout_s
        while not set(names) <= self.alive:
            if proc.poll() is not None:
                raise StartupError(f"lrfslam up exited with {proc.returncode} while starting")
            if time.monotonic() > deadline:
                raise StartupError(f"not alive after {timeout_s:.0f} s: {', '.join(sorted(set(names) - self.alive))}")
            time.sleep(0.2)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(10.0)
        self._memory()


@dataclass
class LiveRun:
    """What ``lrfslam up`` at ``rate_hz`` for ``duration_s`` did."""

    rate_hz: float
    duration_s: float
    returncode: int
    stages: dict[str, StageRow]
    published: int
    recorded: int
    lost: int
    pending: dict[str, list[int]]               # per service: queue.pending while the sensor ran
    age_us: dict[str, tuple[int, int]]          # per service: age p50, p99 (µs) at the sensor's last status
    peak_rss_kb: dict[str, int] = field(default_factory=dict)
    cpu_s: dict[str, float] = field(default_factory=dict)   # per process: CPU time used (s)

    def cpu_ms_per_scan(self) -> dict[str, float]:
        """Per process, CPU time per scan the sensor published (ms), and their ``total``."""
        if not self.published:
            return {}
        per = {name: 1e3 * s / self.published for name, s in self.cpu_s.items()}
        return {**per, "total": sum(per.values())}

    @property
    def dropped(self) -> int:
        return sum(r.dropped for r in self.stages.values())

    @property
    def gaps(self) -> int:
        return sum(r.gaps for r in self.stages.values())

    @property
    def skipped(self) -> int:
        return sum(r.skipped for r in self.stages.values())

    @property
    def growing(self) -> list[str]:
        """Services whose input queue grew while the sensor ran."""
        return sorted(name for name, series in self.pending.items() if queue_growing(series))

    @property
    def held(self) -> bool:
        """The rate was held: up ran and summarised, nothing dropped, skipped, missed or lost, no queue grew."""
        return (self.returncode == 0 and bool(self.stages) and self.published > 0 and not self.dropped
                and not self.skipped and not self.gaps and not self.lost and not self.growing)

    def verdict(self) -> str:
        """``held``, or why not."""
        if self.held:
            return "held"
        why = [f"up exited {self.returncode}"] if self.returncode else []
        why += ["no summary"] if not self.stages else []
        why += [f"dropped {self.dropped}"] if self.dropped else []
        why += [f"gaps {self.gaps}"] if self.gaps else []
        why += [f"skipped {self.skipped}"] if self.skipped else []
        why += [f"lost {self.lost}"] if self.lost else []
        why += [f"queue growing in {', '.join(self.growing)}"] if self.growing else []
        return "not held: " + "; ".join(why)


def _stop(proc: subprocess.Popen, timeout_s: float) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def run_up(rate_hz: float, duration_s: float, workdir: Path, seed: int = 1, group: str = "") -> LiveRun:
    """``lrfslam up`` on the simulator at ``rate_hz`` scans per wall second for ``duration_s``, sampled
    (``group``: ``up --group``)."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    cmd = [sys.executable, "-m", "lrfslam.cli", "up", "--duration", f"{duration_s:g}", "--seed", str(seed),
           "--robot", ROBOT, "--port", str(port), "--recordings", str(workdir), "-q",
           "--set", f"sensor.rate_hz={rate_hz:g}", "--set", f"sensor.speed_mps={SCAN_SPACING_M * rate_hz:g}",
           *(["--group", group] if group else [])]
    up = subprocess.Popen(cmd, cwd=workdir, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    sampler = Sampler(endpoint, ROBOT, up.pid, while_alive="sensor")
    try:
        stdout, _ = up.communicate(timeout=duration_s + 180)
    except subprocess.TimeoutExpired:   # stopped below: the run did not hold, its verdict says why
        stdout = ""
    finally:
        _stop(up, 30)
        sampler.stop()
    stages, (published, recorded, lost) = parse_summary(stdout or "")
    pending: dict[str, list[int]] = {}
    for snap in sampler.snapshots:
        for name, st in snap.items():
            pending.setdefault(name, []).append(int(st.counters.get(BACKLOG, 0)))
    last = sampler.snapshots[-1] if sampler.snapshots else {}
    age = {name: (st.counters[counters.AGE + "p50_us"], st.counters[counters.AGE + "p99_us"]) for name, st in last.items()
           if counters.AGE + "p50_us" in st.counters}
    return LiveRun(rate_hz, duration_s, up.returncode, stages, published, recorded, lost, pending, age,
                   dict(sampler.peak_kb), dict(sampler.cpu_s))


@dataclass
class PlayRun:
    """``lrfslam play RECORDING --rate max`` through the whole pipeline."""

    name: str
    returncode: int
    scans: int
    seconds: float
    scans_per_s: float
    pace: float          # times the recorded pace
    dropped: int
    gaps: int
    line: str            # play's summary line
    peak_rss_kb: dict[str, int] = field(default_factory=dict)


PLAY_LINE = re.compile(r"\((\d+) scans\) in ([\d.]+) s: [\d.]+ messages/s, ([\d.]+) scans/s, ([\d.]+) x the "
                       r"recorded pace")
PLAY_LOSSES = re.compile(r"live services dropped (\d+), gaps (\d+)")


def parse_play_line(name: str, returncode: int, line: str) -> PlayRun:
    """Play's one summary line as a :class:`PlayRun` (zeros where it does not say)."""
    m, lost = PLAY_LINE.search(line), PLAY_LOSSES.search(line)
    scans, seconds, rate, pace = (int(m[1]), float(m[2]), float(m[3]), float(m[4])) if m else (0, 0.0, 0.0, 0.0)
    dropped, gaps = (int(lost[1]), int(lost[2])) if lost else (0, 0)
    return PlayRun(name, returncode, scans, seconds, rate, pace, dropped, gaps, line.strip())


def run_play(recording: Path, name: str, workdir: Path, timeout_s: float = 3600.0, group: str = "") -> PlayRun:
    """``lrfslam up --skip sensor``, then ``lrfslam play recording --rate max`` into it; up stopped by SIGTERM."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    cmd = [sys.executable, "-m", "lrfslam.cli", "up", "--skip", "sensor", "--robot", ROBOT, "--port", str(port),
           "--recordings", str(workdir), "-q", *(["--group", group] if group else [])]
    up = subprocess.Popen(cmd, cwd=workdir, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    sampler = Sampler(endpoint, ROBOT, up.pid)
    try:
        sampler.wait_alive(PLAY_STAGES, 90.0, up)
        play = subprocess.run([sys.executable, "-m", "lrfslam.cli", "play", str(recording), "--rate", "max",
                               "--robot", ROBOT, "--connect", endpoint, "--log-level", "WARNING"],
                              cwd=workdir, capture_output=True, text=True, timeout=timeout_s, check=False)
    finally:
        _stop(up, 60)
        sampler.stop()
    lines = [ln for ln in play.stdout.splitlines() if ln.startswith("lrfslam play:")]
    result = parse_play_line(name, play.returncode, lines[-1] if lines else play.stderr.strip()[-300:])
    result.peak_rss_kb = dict(sampler.peak_kb)
    return result

