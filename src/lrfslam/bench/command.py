"""``lrfslam bench``: what the pipeline costs on this machine, as one Markdown table from one run.

    lrfslam bench [--only SECTIONS] [--quick] [--json] [--datasets DIR] [--rates HZ,HZ,...] [--duration S]
                  [--group STAGES]
    lrfslam bench --check ekf

The table's header names the machine (cores, CPU model, Python and numpy versions, BLAS threads,
load average) and the commit; its first rows time two fixed workloads (plain Python, small NumPy
calls), so figures from two machines can be compared. Sections (``--only``, comma-separated; default all, in this order):

``stages``
    Per-scan cost of denoise, corner extraction, wall direction and a scan-matching tracker step on
    simulated LMS200 scans (src/lrfslam/bench/cost.py); the scan matcher's kernels compiled in
    a fresh process with an empty cache, and loaded from it.
``ekf``
    One EKF observation update at 50, 200, 500 and 1,000 landmarks against filterpy's dense
    ``ExtendedKalmanFilter.update`` on the same filter (ratio), and the log-log slope of each.
``codecs``
    Protobuf encode + decode of every message the stages make, and of what the slam stage publishes
    per scan with a map of 50, 200 and 1,000 landmarks.
``live``
    ``lrfslam up`` (every stage, the recorder and the router as separate processes; ``--group STAGES``:
    those stages in one process, in every live section and the logs) at 75 scans/s for
    ``--duration`` s: the scan-to-output ``age`` p50/p99 the slam and mapper report, drops, gaps,
    skipped inputs, every process's CPU time per scan and peak resident memory
    (src/lrfslam/bench/live.py).
``rates``
    The same at each rate of ``--rates`` in turn (the 75 Hz run shared with ``live``), up to the
    first one not held for ``--duration`` s, then once halfway between the highest held and that
    one; held: nothing dropped, missed (gaps) or lost, and no service's ``queue.pending`` growing.
``logs``
    Every CARMEN log under ``--datasets`` (default ``../shared/datasets``), imported, then played
    with ``lrfslam play --rate max`` into ``lrfslam up --skip sensor``: wall time (play's monotonic
    clock), scans/s, drops and gaps, and peak memory.

``--quick``: a few scans, short runs (8 s, rates 75 and 150), the first log's first 1,000 scans:
for development and the tests, not for figures. ``--json``: the rows and the machine as JSON.
``--check ekf``: only the EKF's shape (issue 18, item 7): ours at least 10x faster than the dense
update at 400 landmarks and its log-log slope over 200-1,000 landmarks within 1.5-2.5 (medians of
repeated updates on the process's CPU clock; measured up to three times before it fails); exit 1
when it breaks. Absolute times are never checked. Run it single-threaded
(``OPENBLAS_NUM_THREADS=1``), as .ci/run does.

Exit codes: 0 done; 1 ``--check`` failed; 2 bad usage or input (one line).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from lrfslam.bench import cost, live
from lrfslam.errors import ConfigError
from lrfslam.io.carmen import LASER_MESSAGES
from lrfslam.io.textfile import carmen_logs, log_name, open_log
from lrfslam.runtime.runner import group_stages
from lrfslam.tools.importers import import_carmen

SECTIONS = ("stages", "ekf", "codecs", "live", "rates", "logs")
CHECKS = ("ekf",)
#: Measurements of a check before it fails.
CHECK_ATTEMPTS = 3
LIVE_RATE_HZ = 75.0
#: States at each end of a played log over which the slam's per-scan message is measured (flat in the map).
STATE_WINDOW = 1000
DEFAULT_RATES = (75.0, 150.0, 225.0, 300.0, 400.0)
#: Processes in the order of the memory rows (``group``: ``--group``'s stages in one process).
PROCESSES = ("up", "router", "sensor", "denoise", "features", "slam", "mapper", "group", "recorder")


@dataclass(frozen=True)
class Settings:
    """How much each section measures: simulated scans, calls per scan, EKF timing budget, run lengths."""

    scans: int = 400
    repeat: int = 3
    ekf_budget_s: float = 0.5
    ekf_min_reps: int = 5
    duration_s: float = 60.0
    rates: tuple[float, ...] = DEFAULT_RATES
    refine: int = 1
    max_logs: int | None = None
    log_scans: int | None = None
    seed: int = 0
    compile_kernels: bool = True   # time the scan matcher's kernels compiled afresh (~10 s)
    group: str = ""                # the live sections' ``lrfslam up --group`` (stages in one process); "": none

    @classmethod
    def quick(cls) -> Settings:
        return cls(scans=60, repeat=1, ekf_budget_s=0.02, ekf_min_reps=3, duration_s=8.0, rates=(75.0, 150.0), refine=0,
                   max_logs=1, log_scans=1000, compile_kernels=False)


# -- the machine and the table

def commit() -> str:
    """The checkout's commit (short hash, ``-dirty`` with uncommitted changes), or ``unknown``."""
    try:
        out = subprocess.run(["git", "describe", "--always", "--dirty", "--abbrev=7"], capture_output=True,
                             text=True, timeout=10, cwd=Path(__file__).resolve().parent, check=False)
    except OSError:
        return "unknown"
    return out.stdout.strip() if out.returncode == 0 and out.stdout.strip() else "unknown"


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine() -> dict:
    """What the figures were measured on."""
    return {"commit": commit(), "cores": os.cpu_count(), "cpu": cpu_model(), "python": platform.python_version(),
            "numpy": np.__version__, "blas_threads": os.environ.get("OPENBLAS_NUM_THREADS", "unset"),
            "load_average": round(os.getloadavg()[0], 2), "utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime())}


def fmt(value: float) -> str:
    """A figure with three significant digits (thousands grouped), "–" where there is none."""
    if value is None or not math.isfinite(value):
        return "–"
    if abs(value) >= 1000:
        return f"{value:,.0f}"
    return f"{value:.3g}" if abs(value) >= 0.001 else f"{value:.2g}"


def table(info: dict, rows: Sequence[cost.Row]) -> str:
    """The Markdown table: a header line naming the machine and the commit, then one line per row."""
    header = (f"**lrfslam bench** at `{info['commit']}`, {info['utc']} UTC: {info['cores']} cores ({info['cpu']}), "
              f"Python {info['python']}, numpy {info['numpy']}, OPENBLAS_NUM_THREADS={info['blas_threads']}, "
              f"load average {info['load_average']} at the start"
              + (f", {info['load_average_end']} at the end" if "load_average_end" in info else "")
              + (f"; stages in one process: {info['group']}" if info.get("group") else ""))
    lines = [header, "",
             "| section | measure | value | unit | compared with | ratio | note |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        ratio = f"{r.ratio:.1f}×" if r.ratio is not None and math.isfinite(r.ratio) else ""
        lines.append(f"| {r.section} | {r.measure} | {fmt(r.value)} | {r.unit} | {r.compared} | {ratio} | {r.note} |")
    return "\n".join(lines)


def as_json(info: dict, rows: Sequence[cost.Row], problems: Sequence[str]) -> str:
    def clean(v):
        return None if isinstance(v, float) and not math.isfinite(v) else v
    return json.dumps({"machine": info, "rows": [{k: clean(v) for k, v in asdict(r).items()} for r in rows],
                       "problems": list(problems)}, indent=1, ensure_ascii=False)


# -- the sections that run processes

def live_rows(run: live.LiveRun, section: str) -> list[cost.Row]:
    """The age percentiles each stage reports (scan stamp to its output) and the run's verdict."""
    rows = []
    for service, what in (("slam", "scan → slam/state"), ("mapper", "scan → map/pose")):
        if service in run.age_us:
            p50, p99 = run.age_us[service]
            rows += [cost.Row(section, f"{what} age p50", p50 / 1e3, "ms", note=f"{service}'s last 1,024 outputs"),
                     cost.Row(section, f"{what} age p99", p99 / 1e3, "ms", note=f"{service}'s last 1,024 outputs")]
    rows.append(cost.Row(section, f"{run.rate_hz:g} Hz for {run.duration_s:g} s: drops + gaps + skipped + lost",
                         run.dropped + run.gaps + run.skipped + run.lost, "", note=f"{run.published} scans; {run.verdict()}"))
    return rows + cpu_rows(run, section)


def cpu_rows(run: live.LiveRun, section: str) -> list[cost.Row]:
    """CPU time per scan of every process of the run (router, each service, up) and their sum."""
    per = run.cpu_ms_per_scan()
    return [cost.Row(section, f"CPU per scan: {name}", per[name], "ms",
                     note="all processes: the machine's CPU time per scan" if name == "total"
                     else "user + system, threads included, over the whole run")
            for name in (*PROCESSES, "total") if name in per]


def rate_rows(runs: Sequence[live.LiveRun]) -> list[cost.Row]:
    """One row per rate tried, ascending (the slam's age p99 and the verdict), then the highest held."""
    rows = []
    for run in sorted(runs, key=lambda r: r.rate_hz):
        p99 = run.age_us.get("slam", (0, float("nan")))[1] / 1e3
        backlog, where = max(((max(s), name) for name, s in run.pending.items() if s), default=(0, ""))
        rows.append(cost.Row("max rate", f"{run.rate_hz:g} scans/s for {run.duration_s:g} s", p99, "ms",
                             note=f"slam age p99; largest queue.pending {backlog}" + (f" ({where})" if where else "")
                                  + f"; {run.verdict()}"))
    held = [r.rate_hz for r in runs if r.held]
    rows.append(cost.Row("max rate", "highest rate held", max(held) if held else float("nan"), "scans/s",
                         note=f"tried {', '.join(f'{r.rate_hz:g}' for r in runs)}"))
    return rows


def search_rates(rates: Sequence[float], refine: int, at: Callable[[float], live.LiveRun]) -> list[live.LiveRun]:
    """The runs of ``at(rate)`` over ``rates`` in ascending order up to the first not held, then ``refine``
    times halfway (to 5 Hz) between the highest held and the lowest not held; in the order run."""
    tried = []
    for rate in rates:
        tried.append(at(rate))
        if not tried[-1].held:
            break
    for _ in range(refine):
        held = [r.rate_hz for r in tried if r.held]
        failed = [r.rate_hz for r in tried if not r.held]
        if not held or not failed:
            break
        mid = 5.0 * round((max(held) + min(failed)) / 10.0)
        if mid <= max(held) or mid >= min(failed):
            break
        tried.append(at(mid))
    return tried


def head_of_log(path: Path, scans: int, out: Path) -> Path:
    """The lines of CARMEN log ``path`` up to its ``scans``-th laser line, as ``out``."""
    seen = 0
    with open_log(path) as src, open(out, "w", encoding="utf-8") as dst:
        for line in src:
            dst.write(line)
            seen += line.split(" ", 1)[0] in LASER_MESSAGES
            if seen >= scans:
                break
    return out


def play_rows(runs: Sequence[live.PlayRun]) -> list[cost.Row]:
    return [cost.Row("logs, play --rate max", f"{r.name} ({r.scans:,} scans): wall time", r.seconds, "s",
                     note=(f"{r.scans_per_s:.0f} scans/s, {r.pace:.1f}× the recorded pace; dropped {r.dropped}, "
                           f"gaps {r.gaps}" if r.returncode == 0 else f"play exited {r.returncode}: {r.line}"))
            for r in runs]


def memory_rows(sources: Sequence[tuple[str, dict[str, int]]]) -> list[cost.Row]:
    """Peak resident memory per process: the first source's as the value, the others beside it."""
    if not sources:
        return []
    (first, peaks), others = sources[0], sources[1:]
    rows = []
    for proc in PROCESSES:
        beside = "; ".join(f"{name}: {p[proc] / 1024:.0f} MB" for name, p in others if proc in p)
        if proc in peaks or beside:
            rows.append(cost.Row("peak RSS", proc, peaks.get(proc, float("nan")) / 1024, "MB", beside,
                                 note=f"VmHWM during {first}"))
    return rows


def run(sections: Sequence[str], s: Settings, datasets: Path, progress: Callable[[str], None]) -> list[cost.Row]:
    """The rows of ``sections``."""
    progress("calibration")
    rows: list[cost.Row] = cost.calibration_rows(s.repeat)
    memory: list[tuple[str, dict[str, int]]] = []
    if "stages" in sections:
        progress("stages")
        rows += cost.stage_rows(s.scans, s.seed, s.repeat)
        rows += cost.kernel_compile_rows() if s.compile_kernels else []
    if "ekf" in sections:
        progress("ekf")
        rows += cost.ekf_rows(cost.ekf_shape(cost.EKF_TABLE_SIZES, cost.EKF_TABLE_SIZES, s.seed, s.ekf_budget_s,
                                             s.ekf_min_reps))
    if "codecs" in sections:
        progress("codecs")
        rows += cost.codec_rows(s.scans, s.seed, s.repeat)
    with tempfile.TemporaryDirectory(prefix="lrfslam_bench_") as tmp:
        work = Path(tmp)
        runs: dict[float, live.LiveRun] = {}
        if "live" in sections:
            progress(f"live at {LIVE_RATE_HZ:g} Hz for {s.duration_s:g} s")
            runs[LIVE_RATE_HZ] = live.run_up(LIVE_RATE_HZ, s.duration_s, work, group=s.group)
            rows += live_rows(runs[LIVE_RATE_HZ], f"live {LIVE_RATE_HZ:g} Hz")
            memory.append((f"up at {LIVE_RATE_HZ:g} Hz, {s.duration_s:g} s", runs[LIVE_RATE_HZ].peak_rss_kb))
        if "rates" in sections:
            def at(rate: float) -> live.LiveRun:
                if rate not in runs:
                    progress(f"rate {rate:g} Hz for {s.duration_s:g} s")
                    runs[rate] = live.run_up(rate, s.duration_s, work, group=s.group)
                return runs[rate]
            rows += rate_rows(search_rates(s.rates, s.refine, at))
        if "logs" in sections:
            logs = carmen_logs(datasets)[:s.max_logs] if datasets.is_dir() else []
            if not logs:
                rows.append(cost.Row("logs, play --rate max", f"no CARMEN logs under {datasets}", float("nan"), ""))
            played, states = [], []
            for path in logs:
                name = log_name(path)
                progress(f"log {name}: import, then play --rate max")
                source = head_of_log(path, s.log_scans, work / f"{name}.clf") if s.log_scans else path
                mcap = work / f"{name}.mcap"
                import_carmen(source, mcap, robot=live.ROBOT)
                before = set(work.iterdir())
                played.append(live.run_play(mcap, name, work, group=s.group))
                for recording in sorted(p for p in set(work.iterdir()) - before if p.is_dir()):
                    states += cost.state_rows(name, recording, STATE_WINDOW, s.repeat)
            rows += play_rows(played) + states
            memory += [(f"play {r.name}", r.peak_rss_kb) for r in played]
    return rows + memory_rows(memory)


def parse_list(text: str, known: Sequence[str], what: str) -> list[str]:
    items = [x.strip() for x in text.split(",") if x.strip()]
    unknown = [x for x in items if x not in known]
    if unknown or not items:
        raise ConfigError(f"{what}: unknown {', '.join(unknown) or 'empty list'}; choose from {', '.join(known)}")
    return items


def parse_rates(text: str) -> tuple[float, ...]:
    try:
        rates = tuple(sorted(float(x) for x in text.split(",") if x.strip()))
    except ValueError:
        raise ConfigError(f"--rates: numbers separated by commas, got {text!r}") from None
    if not rates or min(rates) <= 0:
        raise ConfigError(f"--rates: positive scan rates, got {text!r}")
    return rates


def check(name: str, seed: int, attempts: int = CHECK_ATTEMPTS) -> tuple[list[cost.Row], list[str]]:
    """The rows and the problems of check ``name`` (one of :data:`CHECKS`: the EKF's shape), measured
    up to ``attempts`` times until it holds: a shape that breaks breaks every time, while a burst of
    load from another job spoils one measurement at most. Timed on the process's CPU clock, which
    leaves out the time other jobs take from it."""
    for attempt in range(attempts):
        shape = cost.ekf_shape(cost.EKF_CHECK_SIZES, (cost.CHECK_AT_LANDMARKS,), seed + attempt, 0.3, 7,
                               time.process_time)
        problems = cost.check_ekf(shape)
        if not problems:
            break
    return cost.ekf_rows(shape), problems


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lrfslam bench", description=__doc__.splitlines()[0],
                                     epilog="sections: " + ", ".join(SECTIONS))
    parser.add_argument("--only", metavar="SECTIONS", help="comma-separated sections to run (default all)")
    parser.add_argument("--quick", action="store_true", help="short runs and one short log (development, tests)")
    parser.add_argument("--json", action="store_true", help="print the rows and the machine as JSON")
    parser.add_argument("--check", metavar="NAME", help="check a shape instead, exit 1 if it breaks: ekf")
    parser.add_argument("--datasets", type=Path, default=Path("../shared/datasets"),
                        help="folder searched for CARMEN logs (default ../shared/datasets)")
    parser.add_argument("--rates", help="scan rates tried by the rates section, ascending "
                                        f"(default {','.join(f'{r:g}' for r in DEFAULT_RATES)})")
    parser.add_argument("--duration", type=float, help="seconds of each live run (default 60; --quick 8)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--group", metavar="STAGES", default="",
                        help="run the live sections with lrfslam up --group STAGES (e.g. denoise,features,slam,mapper)")
    args = parser.parse_args(argv)
    info = machine()
    if args.check:
        parse_list(args.check, CHECKS, "--check")
        rows, problems = check(args.check, args.seed)
        print(as_json(info, rows, problems) if args.json else table(info, rows))
        for p in problems:
            print(f"lrfslam bench: check {args.check} failed: {p}", file=sys.stderr)
        if not problems:
            print(f"lrfslam bench: check {args.check} passed", file=sys.stderr)
        return 1 if problems else 0
    sections = parse_list(args.only, SECTIONS, "--only") if args.only else list(SECTIONS)
    settings = Settings.quick() if args.quick else Settings()
    if args.rates:
        settings = replace(settings, rates=parse_rates(args.rates))
    if args.duration is not None:
        if not args.duration > 0:
            raise ConfigError(f"--duration must be > 0 s, got {args.duration}")
        settings = replace(settings, duration_s=args.duration)
    if args.group:
        settings = replace(settings, group=",".join(group_stages(args.group)))
        info["group"] = settings.group
    started = time.monotonic()

    def progress(what: str) -> None:
        print(f"lrfslam bench: [{time.monotonic() - started:6.0f} s] {what}", file=sys.stderr, flush=True)

    rows = run(sections, settings, args.datasets, progress)
    info["load_average_end"] = round(os.getloadavg()[0], 2)
    print(as_json(info, rows, []) if args.json else table(info, rows))
    return 0
