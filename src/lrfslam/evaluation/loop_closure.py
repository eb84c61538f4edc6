"""The loop-closing back end over pipeline recordings, scored on the relation metric.

    python -m lrfslam.evaluation.loop_closure RUN.mcap RELATIONS [RUN.mcap RELATIONS ...]
        [--scan-matching] [--set NAME=VALUE ...]

Each recording is one made by ``lrfslam pipeline`` (topics ``scan``, the raw
laser scans, and ``slam/state``, the EKF's output, paired by the scan's
``seq``). :class:`lrfslam.algo.loop_closure.LoopClosingMapper` is fed every
scan with the EKF's pose, and three trajectories are scored against the
ground-truth relations (Kümmerle et al. 2009, :mod:`lrfslam.evaluation.relations`):
the EKF alone, the back end's online poses (as it would have published them at
each scan) and its final optimised trajectory; overall and per relation span
(< 2 s, 2–30 s, ≥ 30 s). Also the closures accepted and rejected and the back
end's time per scan (wall clock; this is a benchmark, not a test). With
``--scan-matching`` the slam service's scan matching alone
(:mod:`lrfslam.evaluation.laser_odometry`) is scored too: the back end must
never be worse than it on any span.

``--set NAME=VALUE`` sets a ``LoopClosureParams`` field (``correlative.cell_m``
for a nested one).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from lrfslam.algo.geometry import polar_to_xy
from lrfslam.algo.loop_closure import ClosureStats, LoopClosingMapper, LoopClosureParams
from lrfslam.algo.scan_match import ScanMatchParams
from lrfslam.errors import DecodeError, LrfSlamError
from lrfslam.evaluation.laser_odometry import scan_matched_trajectory
from lrfslam.evaluation.relations import (
    SPANS_S,
    Relations,
    RelationStats,
    load_relations,
    relation_errors,
    span_label,
    stamp_s,
)
from lrfslam.io.textfile import open_log
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.runtime import config as config_mod
from lrfslam.runtime.recording import read_recording

#: Relation spans reported separately: label -> [low, high) in seconds.
SPANS = {span_label(span): span for span in SPANS_S}


@dataclasses.dataclass(frozen=True, eq=False)
class RunResult:
    """The back end over one recording.

    Attributes
    ----------
    stamps_ns : ndarray of int, shape (T,)
    ekf, online, final : ndarray, shape (T, 3)
        Poses per scan: the EKF's, the back end's online ones, its final ones.
    stats : ClosureStats
    seconds_per_scan : ndarray, shape (T,)
        Wall-clock time of each ``add_scan`` (s).
    keyframes : int
    """

    stamps_ns: np.ndarray
    ekf: np.ndarray
    online: np.ndarray
    final: np.ndarray
    stats: ClosureStats
    seconds_per_scan: np.ndarray
    keyframes: int


def read_inputs(path: str | Path) -> list[tuple[int, np.ndarray, np.ndarray, np.ndarray]]:
    """(stamp_ns, EKF pose (3,), its cov (3, 3), scan points (N, 2)) per scan with a state, in log order."""
    scans: dict[int, np.ndarray] = {}
    out = []
    for rec in read_recording(path, [topics.SCAN.name, topics.SLAM_STATE.name]):
        topic = topics.by_name(rec.topic)
        try:
            value = topic.codec.decode(rec.data, rec.schema)
        except DecodeError:
            continue
        if topic is topics.SCAN:
            r = value.ranges_m
            ok = (value.status == t.BEAM_VALID) & np.isfinite(r)
            scans[value.seq] = polar_to_xy(r[ok], value.angles_rad[ok])
            continue
        pts = scans.pop(value.scan_seq, None)
        if pts is not None:
            out.append((value.stamp_ns, np.array(value.pose), np.array(value.pose_cov), pts))
    return out


def run(inputs, params: LoopClosureParams) -> RunResult:
    """Feed the mapper every scan of ``inputs`` (from :func:`read_inputs`)."""
    mapper = LoopClosingMapper(params)
    online, ekf, stamps, seconds = [], [], [], []
    for stamp_ns, pose, cov, pts in inputs:
        start = time.perf_counter()
        online.append(mapper.add_scan(stamp_ns, pose, cov, pts))
        seconds.append(time.perf_counter() - start)
        ekf.append(pose)
        stamps.append(stamp_ns)
    _, final = mapper.trajectory()
    return RunResult(np.array(stamps, dtype=np.int64), np.array(ekf).reshape(-1, 3),
                     np.array(online).reshape(-1, 3), final, mapper.stats, np.array(seconds),
                     mapper.keyframe_count)


def span_stats(stamps_s: np.ndarray, poses: np.ndarray, relations: Relations) -> dict[str, RelationStats]:
    """Relation statistics overall ("all") and per span of :data:`SPANS`."""
    out = {"all": relation_errors(stamps_s, poses, relations)}
    span = relations.stamp2_s - relations.stamp1_s
    for label, (lo, hi) in SPANS.items():
        keep = np.flatnonzero((span >= lo) & (span < hi))
        subset = Relations(relations.stamp1_s[keep], relations.stamp2_s[keep], relations.delta[keep],
                           relations.line_no[keep], ())
        out[label] = relation_errors(stamps_s, poses, subset)
    return out


def report(name: str, result: RunResult, relations: Relations,
           scan_matching: tuple[np.ndarray, np.ndarray] | None = None) -> str:
    """The table of one log; ``scan_matching``: (stamps ns (T,), poses (T, 3)) of scan matching alone, if scored."""
    stamps_s = np.array([stamp_s(s) for s in result.stamps_ns])
    rows = {"EKF alone": (stamps_s, result.ekf)}
    if scan_matching is not None:
        rows["scan matching"] = (np.array([stamp_s(s) for s in scan_matching[0]]), scan_matching[1])
    rows.update({"back end online": (stamps_s, result.online), "back end final": (stamps_s, result.final)})
    labels = ["all", *SPANS]
    lines = [f"{name}: {result.stamps_ns.size} scans, {result.keyframes} keyframes, {len(relations)} relations"]
    head = f"{'trajectory':16s}" + "".join(f" {lab + ' m':>16s} {'deg':>5s}" for lab in labels)
    lines += [head, "-" * len(head)]
    for label, (stamps, poses) in rows.items():
        stats = span_stats(stamps, poses, relations)
        cells = "".join(f" {stats[lab].trans_abs_m.mean:7.3f} ± {stats[lab].trans_abs_m.std:6.3f} "
                        f"{stats[lab].rot_abs_deg.mean:5.2f}" for lab in labels)
        lines.append(f"{label:16s}{cells}")
    counts = ", ".join(f"{f.name} {getattr(result.stats, f.name)}" for f in dataclasses.fields(result.stats))
    ms = 1e3 * result.seconds_per_scan
    lines.append(f"closures: {counts}")
    lines.append(f"back end time per scan: mean {ms.mean():.2f} ms, p99 {np.percentile(ms, 99):.1f} ms, "
                 f"max {ms.max():.0f} ms, total {ms.sum() / 1e3:.1f} s")
    return "\n".join(lines)


def apply_sets(params: LoopClosureParams, sets: Sequence[str]) -> LoopClosureParams:
    """``params`` with ``NAME=VALUE`` overrides (``outer.inner=VALUE`` for nested parameter tables),
    layered as every service's ``--set``."""
    return config_mod.load(LoopClosureParams, base=params, sets=list(sets))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m lrfslam.evaluation.loop_closure", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("pairs", nargs="+", metavar="RUN.mcap RELATIONS",
                        help="recordings of lrfslam pipeline, each followed by its relations file")
    parser.add_argument("--scan-matching", action="store_true",
                        help="also score scan matching alone (the slam service's tracker, no filter)")
    parser.add_argument("--set", dest="sets", action="append", default=[], metavar="NAME=VALUE")
    args = parser.parse_args(argv)
    if len(args.pairs) % 2:
        parser.error("give a relations file after every recording")
    try:
        params = apply_sets(LoopClosureParams(), args.sets)
        for rec_path, rel_path in zip(args.pairs[::2], args.pairs[1::2], strict=True):
            with open_log(rel_path) as f:
                relations = load_relations(f)
            result = run(read_inputs(rec_path), params)
            alone = None
            if args.scan_matching:
                sm_stamps, sm_poses, _ = scan_matched_trajectory(rec_path, ScanMatchParams())
                alone = (sm_stamps, sm_poses)
            print(report(Path(rec_path).name, result, relations, alone), flush=True)
    except (LrfSlamError, OSError, ValueError) as exc:
        print(f"loop closure evaluation: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
