"""Soak: a long accelerated run of the whole pipeline under ``lrfslam up``, every process's memory sampled.

    python -m lrfslam.bench.soak [--scans 270000] [--rate-hz 75] [--speedup 1.0] [--interval 5]

Runs ``lrfslam up`` (router, sensor, denoise, features, slam, mapper, recorder, each its own
process) on the simulator at ``--rate-hz`` scans per simulated second, ``--speedup`` times faster
than real time, until the sensor has published ``--scans`` scans (``sensor.max_scans``). Every
``--interval`` seconds it reads each process's resident memory (``VmRSS`` of /proc/<pid>/status;
the processes are ``up`` itself, which holds the ground truth, and its children). The run's
producing span is from the sensor's start to its last scan (scans / rate / speedup, wall s);
warm-up ends at ``--warmup`` of it. The table: per process, RSS at the end of warm-up and at the
end of the span (the medians of the samples in the ``--window`` seconds after the one and before
the other, so a transient is not read as growth), the growth between them (%), the peak after warm-up, and the
slope fitted after warm-up (bytes per scan); then up's summary and the verdict. Exit 1 if any process grew by ``--max-growth`` % or
more after warm-up, or any stage dropped or missed (gap) an input, or the recording lost a scan,
or any process restarted. docs/operations.md holds the figures. Timing lives here, not in the tests.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lrfslam.bench.live import (
    StageRow,
    children_of,
    free_port,
    memory_kb,
    parse_summary,
)

ROBOT = "soak"
#: Seconds of samples whose median is a process's RSS at the end of warm-up and at the end (``--window``).
WINDOW_S = 60.0
#: Wall seconds given to ``up`` beyond the producing span: starting every stage, then draining.
START_MARGIN_S = 25.0


@dataclass
class Series:
    """One process's memory over the run: (wall s since up started, kB, pid) samples."""

    name: str
    samples: list[tuple[float, int, int]] = field(default_factory=list)

    def level(self, t0_s: float, t1_s: float) -> int | None:
        """Median RSS (kB) of the samples between ``t0_s`` and ``t1_s``; the last sample before
        ``t1_s`` if none falls between. A median, so that one sample taken during a transient (a
        graph optimisation's working memory) is not read as growth."""
        inside = [kb for t, kb, _ in self.samples if t0_s <= t <= t1_s]
        if inside:
            return int(np.median(inside))
        before = [kb for t, kb, _ in self.samples if t <= t1_s]
        return before[-1] if before else None

    def peak(self, t0_s: float, t1_s: float) -> int | None:
        """Largest RSS (kB) sampled between ``t0_s`` and ``t1_s``."""
        inside = [kb for t, kb, _ in self.samples if t0_s <= t <= t1_s]
        return max(inside) if inside else None

    def pids(self) -> set[int]:
        return {pid for _, _, pid in self.samples}


@dataclass
class SoakResult:
    command: list[str]
    scans: int
    scans_per_s: float
    returncode: int
    stdout: str
    series: dict[str, Series]
    span: tuple[float, float]            # wall s since up started: sensor start, its last scan due
    stages: dict[str, StageRow]
    published: int
    recorded: int
    lost: int

    def rss_between(self, start_frac: float, end_frac: float = 1.0,
                    window_s: float = WINDOW_S) -> dict[str, tuple[int, int]]:
        """Per process: RSS (kB) at ``start_frac`` and at ``end_frac`` of the producing span, each the
        median of the samples (:meth:`Series.level`) in the ``window_s`` seconds after the start and
        before the end, both inside the span compared (at most half of it each)."""
        a, b = self.span
        t0, t1 = a + start_frac * (b - a), a + end_frac * (b - a)
        w = min(window_s, 0.5 * (t1 - t0))
        out = {}
        for name, s in self.series.items():
            first, last = s.level(t0, t0 + w), s.level(t1 - w, t1)
            if first and last:
                out[name] = (first, last)
        return out

    def bytes_per_scan(self, start_frac: float) -> dict[str, float]:
        """Per process: least-squares slope of RSS over scans published, after ``start_frac`` of the span."""
        a, b = self.span
        out = {}
        for name, s in self.series.items():
            pts = [(t, kb) for t, kb, _ in s.samples if a + start_frac * (b - a) <= t <= b]
            if len(pts) >= 3:
                t, kb = np.array(pts, dtype=float).T
                slope_kb_per_s = np.polyfit(t, kb, 1)[0]
                out[name] = slope_kb_per_s * 1024.0 / self.scans_per_s
        return out

    def problems(self, warmup: float, max_growth_pct: float, window_s: float = WINDOW_S) -> list[str]:
        """Every failed condition of the soak, one line each (empty: passed)."""
        found = []
        if self.returncode != 0:
            found.append(f"lrfslam up exited with {self.returncode}")
        for name, row in self.stages.items():
            for what, n in (("dropped", row.dropped), ("gaps", row.gaps), ("errors", row.errors),
                            ("restarts", row.restarts)):
                if n:
                    found.append(f"{name}: {what} {n}")
        if not self.stages:
            found.append("no summary table from lrfslam up")
        if self.published != self.scans:
            found.append(f"the sensor published {self.published} scans, not {self.scans}")
        if self.lost or self.recorded != self.published:
            found.append(f"recording: {self.recorded} of {self.published} scans (lost {self.lost})")
        for name, s in self.series.items():
            if len(s.pids()) > 1:
                found.append(f"{name}: {len(s.pids())} different processes (restarted)")
        for name, (first, last) in self.rss_between(warmup, window_s=window_s).items():
            growth = 100.0 * (last - first) / first
            if growth >= max_growth_pct:
                found.append(f"{name}: RSS grew {growth:.1f} % after warm-up ({first} -> {last} kB)")
        return found


def run_soak(scans: int, rate_hz: float, speedup: float, interval_s: float, workdir: Path,
             seed: int = 1, extra: tuple[str, ...] = ()) -> SoakResult:
    """Run ``lrfslam up`` until the sensor has published ``scans``, sampling every process's RSS."""
    scans_per_s = rate_hz * speedup
    producing_s = scans / scans_per_s
    cmd = [sys.executable, "-m", "lrfslam.cli", "up", "--duration", f"{producing_s + START_MARGIN_S:.0f}",
           "--speedup", str(speedup), "--seed", str(seed), "--robot", ROBOT, "--port", str(free_port()),
           "--recordings", str(workdir), "--set", f"sensor.rate_hz={rate_hz}",
           "--set", f"sensor.max_scans={scans}", *extra]
    series: dict[str, Series] = {}
    up = subprocess.Popen(cmd, cwd=workdir, stdout=subprocess.PIPE, text=True)
    started = time.monotonic()
    sensor_at: float | None = None
    try:
        while up.poll() is None:
            now = time.monotonic() - started
            procs = {"up": up.pid, **children_of(up.pid)}
            if sensor_at is None and "sensor" in procs:
                sensor_at = now
            for name, pid in procs.items():
                kb = memory_kb(pid)
                if kb is not None:
                    series.setdefault(name, Series(name)).samples.append((now, kb, pid))
            # Sample densely while starting (to find the sensor's start), then every interval.
            time.sleep(0.2 if sensor_at is None else interval_s)
        stdout = up.stdout.read()
    finally:
        if up.poll() is None:
            up.kill()
        up.wait()
    stages, (published, recorded, lost) = parse_summary(stdout)
    start = sensor_at if sensor_at is not None else 0.0
    return SoakResult(cmd, scans, scans_per_s, up.returncode, stdout, series, (start, start + producing_s),
                      stages, published, recorded, lost)


def table(result: SoakResult, warmup: float, window_s: float = WINDOW_S) -> str:
    """The per-process memory table (Markdown) and the summary's counts."""
    rss = result.rss_between(warmup, window_s=window_s)
    slopes = result.bytes_per_scan(warmup)
    a, b = result.span
    lines = [(f"| process | RSS at {warmup:.0%} (MB) | RSS at end (MB) | growth | peak after warm-up (MB) "
              "| slope after warm-up (B/scan) |"),
             "|---|---|---|---|---|---|"]
    for name in ("up", "router", "sensor", "denoise", "features", "slam", "mapper", "recorder"):
        if name not in rss:
            continue
        first, last = rss[name]
        peak = result.series[name].peak(a + warmup * (b - a), b) or last
        lines.append(f"| {name} | {first / 1024:.1f} | {last / 1024:.1f} | {100.0 * (last - first) / first:+.1f} % "
                     f"| {peak / 1024:.1f} | {slopes.get(name, float('nan')):.0f} |")
    dropped = sum(r.dropped for r in result.stages.values())
    gaps = sum(r.gaps for r in result.stages.values())
    restarts = sum(r.restarts for r in result.stages.values())
    lines += ["", (f"stages: dropped {dropped}, gaps {gaps}, restarts {restarts}; scans published "
                  f"{result.published} / in the recording {result.recorded} / lost {result.lost}")]
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scans", type=int, default=270_000, help="scans the sensor publishes (default: 1 h at 75 Hz)")
    parser.add_argument("--rate-hz", type=float, default=75.0, help="scans per simulated second (LMS200: 75)")
    parser.add_argument("--speedup", type=float, default=1.0, help="simulated seconds per wall second")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--interval", type=float, default=5.0, help="seconds between RSS samples")
    parser.add_argument("--warmup", type=float, default=0.1, help="fraction of the run before the first RSS compared")
    parser.add_argument("--window", type=float, default=WINDOW_S,
                        help="RSS at the end of warm-up is the median of the samples in this many seconds after it, "
                        "and at the end the median of those in as many seconds before it")
    parser.add_argument("--max-growth", type=float, default=10.0, help="RSS growth after warm-up that fails (%%)")
    parser.add_argument("--csv", metavar="FILE", help="also write every sample (process, s, kB, pid)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        result = run_soak(args.scans, args.rate_hz, args.speedup, args.interval, Path(tmp), args.seed)
    print("$", " ".join(["lrfslam", *result.command[3:]]).replace(tmp, "<tmp>"))
    print(result.stdout)
    if args.csv:
        with open(args.csv, "w") as f:
            f.write("process,s,kB,pid\n")
            for s in result.series.values():
                f.writelines(f"{s.name},{t:.1f},{kb},{pid}\n" for t, kb, pid in s.samples)
    print(f"{result.scans} scans at {args.rate_hz:g} Hz x {args.speedup:g} ({result.scans_per_s:g} scans per "
          f"wall s); RSS sampled every {args.interval:g} s, read as medians over {args.window:g} s; "
          f"warm-up {args.warmup:.0%} of the producing span\n")
    print(table(result, args.warmup, args.window))
    problems = result.problems(args.warmup, args.max_growth, args.window)
    print("\n" + ("\n".join(f"FAIL {p}" for p in problems) if problems else "PASS"))
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
