"""``lrfslam eval relations --all DIR``: every log under DIR through the whole pipeline, one table.

Each sub-folder of DIR holding a CARMEN log (``*.clf``, ``*.clf.gz``, ``*.clf.bz2``) is a
log; a ``*.relations`` file beside it makes it scored. Every log is imported (the importer
reads the no-return code, beam layout and laser mounting from the log itself), run through
``lrfslam pipeline`` with **one** configuration — the defaults, or ``--config`` / ``--set``
given once for all — and scored with the Kümmerle relation metric, overall and per relation
span. A log without relations runs end to end and gets its map drawn (``lrfslam export``).

Rows per scored log: the mapper's final trajectory (every loop closure solved for), the
mapper's and the EKF's estimates as published at each scan (``map/pose``, ``slam/state``),
scan matching alone (the slam stage's tracker without the filter), and raw odometry.

``--trials N`` runs every scored log N times under perturbations that must not matter — trial
0 as it is, trial k on another floating-point path (:data:`FP_PATHS`: numpy's SIMD dispatch
narrowed, other OpenBLAS kernels) with :data:`TRIAL_RANGE_NOISE_M` of noise seeded k on the
ranges — and reports each figure as the trials' mean, minimum, maximum and spread
((max − min) / mean): a figure a rounding moves is a sample, not a property of the method.
Every run is a process of its own, started with its trial's environment (numpy and OpenBLAS
read it only when loaded).
"""

from __future__ import annotations

import multiprocessing
import multiprocessing.connection
import os
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from lrfslam import services
from lrfslam.algo.scan_match import ScanMatchParams
from lrfslam.errors import ConfigError
from lrfslam.evaluation.laser_odometry import scan_matched_trajectory
from lrfslam.evaluation.recording_relations import MAPPER_FINAL, evaluate_relations
from lrfslam.evaluation.relations import (
    ErrorSummary,
    RelationStats,
    errors_by_span,
    load_relations,
    stamp_s,
)
from lrfslam.io.textfile import carmen_logs, open_log
from lrfslam.msgs import counters, topics
from lrfslam.runtime import chain
from lrfslam.runtime import config as config_mod
from lrfslam.runtime.recording import read_recording
from lrfslam.tools import pipeline
from lrfslam.tools.importers import import_carmen

SCAN_MATCHING = "scan matching alone"

#: Rows of the table, per log with relations: the mapper's final trajectory (every closure solved
#: for), the mapper and the EKF as published at each scan, and the references.
ROWS = (MAPPER_FINAL, "mapper online", "slam estimate", SCAN_MATCHING, "raw odometry")

#: The floating-point paths trials run on, trial k on ``FP_PATHS[k % len(FP_PATHS)]``: this
#: machine's own, then numpy's SIMD dispatch narrowed (no AVX-512; nor AVX2) and other OpenBLAS
#: kernels. numpy ignores the names of features a CPU lacks, so these hold on any x86-64 machine.
FP_PATHS: tuple[dict[str, str], ...] = (
    {},
    {"NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR", "OPENBLAS_CORETYPE": "Haswell"},
    {"NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4 AVX512_ICL AVX512_SPR", "OPENBLAS_CORETYPE": "Prescott"},
    {"OPENBLAS_CORETYPE": "Sandybridge"},
    {"NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR", "OPENBLAS_CORETYPE": "Zen"},
)

#: Standard deviation (m) of the range noise trials after the first add: a thousandth of a
#: millimetre, four orders below the LMS200's own noise; only rounding-sized effects can follow.
TRIAL_RANGE_NOISE_M = 1e-6


@dataclass(frozen=True)
class Trial:
    """One run of a log under perturbations that must not matter (trial 0: none)."""

    index: int

    @property
    def env(self) -> dict[str, str]:
        """Environment variables this trial's process starts with."""
        return FP_PATHS[self.index % len(FP_PATHS)]

    @property
    def range_noise_m(self) -> float:
        return TRIAL_RANGE_NOISE_M if self.index else 0.0

    def describe(self) -> str:
        path = " ".join(f"{k}={v!r}" for k, v in self.env.items()) or "this machine's floating-point path"
        noise = f", {self.range_noise_m:g} m range noise seeded {self.index}" if self.index else ""
        return f"trial {self.index}: {path}{noise}"


@dataclass(frozen=True)
class Log:
    """One log found under the datasets folder."""

    name: str
    path: Path
    relations: Path | None


@dataclass
class LogResult:
    """What one log gave: timings, counts, and the scores of each trajectory (if it has relations)."""

    log: Log
    scans: int = 0
    landmarks: int = 0
    pipeline_s: float = 0.0
    scores: dict[str, RelationStats] = field(default_factory=dict)
    by_span: dict[str, dict[str, tuple[int, ErrorSummary]]] = field(default_factory=dict)
    sensor: dict[str, str] = field(default_factory=dict)
    map_png: Path | None = None
    slam_counts: dict[str, int] = field(default_factory=dict)
    mapper_counts: dict[str, int] = field(default_factory=dict)

    @property
    def closure_nis(self) -> tuple[float, int]:
        """Mean NIS of the loop closures that passed verification (3 if consistent), and how many."""
        n = self.mapper_counts.get(counters.STEP + "closures_verified", 0)
        return (self.mapper_counts.get(counters.STEP + "closure_nis_milli", 0) / 1000.0 / n if n else float("nan")), n

    @property
    def closure_nis_band(self) -> tuple[float, float]:
        """95 % band of :attr:`closure_nis`'s mean if the closures were consistent: the mean of
        N chi-squared variables of 3 dof is chi-squared with 3 N dof, divided by N."""
        return nis_mean_band(3, self.closure_nis[1])

    @property
    def matched_nis(self) -> tuple[float, float, int]:
        """Mean NIS of the EKF's matched observations (2 if consistent), the share inside the
        95 % bound (0.95 if consistent), and how many there were."""
        n = self.slam_counts.get(counters.STEP + "matched", 0)
        if not n:
            return float("nan"), float("nan"), 0
        return (self.slam_counts.get(counters.STEP + "nis_matched_milli", 0) / 1000.0 / n,
                self.slam_counts.get(counters.STEP + "nis_matched_within_95", 0) / n, n)


def nis_mean_band(dof: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """Central ``level`` band of the mean of ``n`` independent chi-squared NIS values of ``dof``
    degrees of freedom (NaN, NaN for none)."""
    if n < 1:
        return float("nan"), float("nan")
    tail = (1.0 - level) / 2.0
    return float(chi2.ppf(tail, dof * n) / n), float(chi2.ppf(1.0 - tail, dof * n) / n)


def find_logs(root: Path) -> list[Log]:
    """The logs under ``root``: in each sub-folder, its first CARMEN log and relations file (sorted by name)."""
    logs: dict[Path, Log] = {}
    for path in carmen_logs(root):
        folder = path.parent
        if folder.parent == root and folder not in logs:
            relations = sorted(folder.glob("*.relations*"))
            logs[folder] = Log(folder.name, path, relations[0] if relations else None)
    if not logs:
        raise ConfigError(f"no CARMEN log (*.clf[.gz|.bz2]) in any folder under {root}")
    return list(logs.values())


def run_log(log: Log, work: Path, stages: list[chain.Stage], draw_map: bool = True, trial: Trial = Trial(0)) -> LogResult:
    """Import ``log`` (with ``trial``'s range noise), run ``stages`` over it, and score what it has ground truth for."""
    work.mkdir(parents=True, exist_ok=True)
    imported, out = work / f"{log.name}.mcap", work / f"{log.name}.run.mcap"
    found = import_carmen(log.path, imported, robot=log.name.replace(" ", "_"), range_noise_m=trial.range_noise_m,
                          seed=trial.index)
    result = LogResult(log, scans=found.scans, sensor=found.sensor)
    started = time.perf_counter()
    counts = pipeline.run_pipeline(stages, log.name.replace(" ", "_"), imported, out)
    result.slam_counts = dict(counts.get("slam", {}))
    result.mapper_counts = dict(counts.get("mapper", {}))
    result.pipeline_s = time.perf_counter() - started
    result.landmarks = _final_landmarks(out)
    if log.relations is not None:
        with open_log(log.relations) as f:
            relations = load_relations(f)
        slam_cfg = next((s.config for s in stages if s.spec.name == "slam"), None)
        match_params = slam_cfg.tracker if slam_cfg is not None else ScanMatchParams()
        stamps_ns, poses, _ = scan_matched_trajectory(imported, match_params)
        scores, _ = evaluate_relations(out, log.relations, extra={
            SCAN_MATCHING: (np.array([stamp_s(s) for s in stamps_ns]), poses)})
        for label in ROWS:
            if label in scores:
                result.scores[label] = scores[label]
                result.by_span[label] = errors_by_span(scores[label], relations)
    elif draw_map:
        from lrfslam.tools import (
            export,  # only here: it draws with the optional plotting extra
        )
        export.main([str(out), "-o", str(work / f"{log.name}-map")])
        result.map_png = work / f"{log.name}-map" / "map.png"
    return result


def _final_landmarks(path: Path) -> int:
    last = None
    for rec in read_recording(path, [topics.SLAM_STATE.name]):
        last = rec
    if last is None:
        return 0
    return topics.SLAM_STATE.codec.decode(last.data, last.schema).n_confirmed


def markdown(results: Iterable[LogResult]) -> str:
    """One table row per (log, trajectory): relation error overall and by span, and the time per scan."""
    results = list(results)
    spans = next((list(r.by_span[k]) for r in results for k in r.by_span), [])
    head = (["log", "trajectory", "relations", "trans. m (mean ± std)", "rot. deg"] + [f"{s} m (n)" for s in spans]
            + ["ms / scan"])
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in results:
        per_scan = f"{1e3 * r.pipeline_s / max(r.scans, 1):.2f}"
        if not r.scores:
            cells = [r.log.name, f"(no relations) {r.scans} scans, {r.landmarks} landmarks", "-", "-", "-"]
            lines.append("| " + " | ".join(cells + ["-"] * len(spans) + [per_scan]) + " |")
            continue
        for label, s in r.scores.items():
            cells = [r.log.name, label, str(s.n_used), f"{s.trans_abs_m.mean:.3f} ± {s.trans_abs_m.std:.3f}",
                     f"{s.rot_abs_deg.mean:.2f}"]
            cells += [f"{e.mean:.3f} ({n})" for n, e in r.by_span[label].values()]
            lines.append("| " + " | ".join(cells + [per_scan if label == next(iter(r.scores)) else ""]) + " |")
    return "\n".join(lines)


def _run_log_configured(log: Log, work: Path, sets: list[str], file: Mapping, env: Mapping[str, str],
                        draw_map: bool, trial: Trial = Trial(0)) -> LogResult:
    """:func:`run_log` with stages built from the configuration (in a worker process)."""
    return run_log(log, work, pipeline.build_stages(pipeline.DEFAULT_STAGES, sets, file, env), draw_map, trial)


@contextmanager
def _environment(extra: Mapping[str, str]) -> Iterator[None]:
    """``os.environ`` with ``extra`` set, as a child started meanwhile inherits it; restored after."""
    saved = {k: os.environ.get(k) for k in extra}
    os.environ.update(extra)
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _call_and_send(conn: multiprocessing.connection.Connection, fn: Callable, args: tuple) -> None:
    try:
        conn.send((True, fn(*args)))
    except BaseException as exc:  # noqa: BLE001 - handed to the parent, which raises it
        conn.send((False, exc))
    finally:
        conn.close()


def in_processes(calls: list[tuple[Callable, tuple, Mapping[str, str]]], jobs: int) -> list:
    """``fn(*args)`` for each ``(fn, args, env)`` of ``calls``, each in a new process started with
    ``env`` added to this one's environment, ``jobs`` at a time; the results in the calls' order.

    Raises
    ------
    Exception
        The first call that raised, once the running ones are stopped; :class:`RuntimeError` for
        a process that died without an answer.
    """
    context = multiprocessing.get_context("spawn")
    results: list = [None] * len(calls)
    waiting = list(enumerate(calls))
    running: dict[int, tuple[multiprocessing.process.BaseProcess, multiprocessing.connection.Connection]] = {}
    try:
        while waiting or running:
            while waiting and len(running) < jobs:
                i, (fn, args, env) = waiting.pop(0)
                receiver, sender = context.Pipe(duplex=False)
                with _environment(env):
                    process = context.Process(target=_call_and_send, args=(sender, fn, args))
                    process.start()
                sender.close()
                running[i] = (process, receiver)
            ready = multiprocessing.connection.wait([conn for _, conn in running.values()])
            for i, (process, conn) in list(running.items()):
                if conn not in ready:
                    continue
                try:
                    ok, value = conn.recv()
                except EOFError:
                    process.join()
                    ok, value = False, RuntimeError(f"a worker process died (exit code {process.exitcode})")
                process.join()
                del running[i]
                if not ok:
                    raise value
                results[i] = value
    finally:
        for process, _ in running.values():
            process.terminate()
            process.join()
    return results


def evaluate_all(root: Path, work: Path, sets: list[str], file: Mapping, env: Mapping[str, str],
                 draw_maps: bool = True, jobs: int = 1, trials: int = 1) -> list[list[LogResult]]:
    """Every log under ``root`` with the same stages and configuration, ``jobs`` runs at a time.

    Returns, in the logs' order, each log's results: one per trial for a log with relations
    (``trials`` of them, see the module's docstring), one for a log without (its map).
    With ``jobs`` 1 and one trial everything runs in this process.
    """
    logs = find_logs(root)
    if jobs <= 1 and trials == 1:
        return [[_run_log_configured(log, work / log.name, sets, file, env, draw_maps)] for log in logs]
    runs = [(log, Trial(k)) for log in logs for k in range(trials if log.relations else 1)]
    # Largest log first, so the longest runs do not start last.
    order = sorted(range(len(runs)), key=lambda i: (-runs[i][0].path.stat().st_size, i))
    calls = [(_run_log_configured, (log, work / log.name / (f"trial-{trial.index}" if trials > 1 else ""), sets,
                                    dict(file), dict(env), draw_maps, trial), trial.env)
             for log, trial in (runs[i] for i in order)]
    done = dict(zip(order, in_processes(calls, jobs)))
    return [[done[i] for i, (other, _) in enumerate(runs) if other is log] for log in logs]


def _spread(values: list[float]) -> str:
    """``mean [min, max] spread %``, the spread being (max − min) / mean."""
    mean = float(np.mean(values))
    spread = (max(values) - min(values)) / mean if mean else 0.0
    return f"{mean:.3f} [{min(values):.3f}, {max(values):.3f}] {100 * spread:.0f} %"


#: The mapper's inputs, which its final trajectory must not be worse than (issue 28: a closure never
#: makes the map worse), and by how much it may be: the larger of an absolute (m) and a relative margin.
MAPPER_INPUTS = ("slam estimate", SCAN_MATCHING)
NO_WORSE_M, NO_WORSE_FRAC = 0.001, 0.02


def worse_than_inputs(result: LogResult) -> list[str]:
    """Where the mapper's final trajectory is worse than one of its inputs (:data:`MAPPER_INPUTS`)
    beyond :data:`NO_WORSE_M` or :data:`NO_WORSE_FRAC`, whichever is larger: one line per
    (span, input), ``"<span>: <mapper> m against <input> <m> m"``; empty where it is no worse
    anywhere (or the log has no relations)."""
    if MAPPER_FINAL not in result.by_span:
        return []
    out = []
    for span, (_, mapper) in result.by_span[MAPPER_FINAL].items():
        for label in MAPPER_INPUTS:
            if label not in result.by_span:
                continue
            base = result.by_span[label][span][1].mean
            if mapper.mean > base + max(NO_WORSE_M, NO_WORSE_FRAC * base):
                out.append(f"{span}: {mapper.mean:.3f} m against {label} {base:.3f} m")
    return out


def trials_markdown(results: Iterable[list[LogResult]]) -> str:
    """One row per (scored log, trajectory): each relation error over the trials as
    ``mean [min, max] spread %``, overall and by span."""
    scored = [runs for runs in results if runs[0].scores]
    spans = next((list(r[0].by_span[k]) for r in scored for k in r[0].by_span), [])
    head = ["log", "trajectory", "trials", "trans. m: mean [min, max] spread"] + [f"{s} m" for s in spans]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for runs in scored:
        for label in runs[0].scores:
            cells = [runs[0].log.name, label, str(len(runs)),
                     _spread([r.scores[label].trans_abs_m.mean for r in runs])]
            cells += [_spread([r.by_span[label][span][1].mean for r in runs]) for span in spans]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main_all(root: Path, work: Path, sets: list[str], config_file: str | None, jobs: int = 1,
             trials: int = 1) -> int:
    """``lrfslam eval relations --all``: print the table (Markdown) and where the outputs are."""
    found = evaluate_all(root, work, sets, config_mod.read_file(config_file, services.CONFIG_TABLES), os.environ,
                         jobs=jobs, trials=trials)
    if trials > 1:
        print(trials_markdown(found))
        print("\n".join(Trial(k).describe() for k in range(trials)))
    print(markdown(runs[0] for runs in found) if trials == 1 else
          "trial 0 alone:\n" + markdown(runs[0] for runs in found))
    for r in (runs[0] for runs in found):
        facts = r.sensor
        nis, inside, n = r.matched_nis
        print(f"{r.log.name}: matched NIS mean {nis:.2f} (2.00 if consistent), {100 * inside:.1f} % inside "
              f"the 95 % bound, over {n} observations")
        closure_nis, closures = r.closure_nis
        lo, hi = r.closure_nis_band
        print(f"{r.log.name}: loop closure NIS mean {closure_nis:.2f} (3.00 if consistent; 95 % band of the mean "
              f"[{lo:.2f}, {hi:.2f}]) over {closures} verified closures")
        print(f"{r.log.name}: {r.scans} scans in {r.pipeline_s:.1f} s; laser {facts.get('beams', '?')}, "
              f"no return {facts.get('no_return_m') or '-'} m"
              + (f"; map {r.map_png}" if r.map_png else ""))
    for runs in (runs for runs in found if runs[0].scores):
        worse = [(k, line) for k, r in enumerate(runs) for line in worse_than_inputs(r)]
        verdict = "no worse than its inputs (EKF, scan matching alone) on every span"
        if worse:
            verdict = "worse than an input: " + "; ".join(f"trial {k} {line}" for k, line in worse)
        print(f"{runs[0].log.name}: mapper final {verdict} (margin {1e3 * NO_WORSE_M:g} mm or "
              f"{100 * NO_WORSE_FRAC:g} %), {len(runs) - len({k for k, _ in worse})} of {len(runs)} trials clean")
    return 0
