"""Localization on saved maps of the real logs: a map of each log's first half, its second half localized in it.

    python -m lrfslam.tools.localization_logs DIR --work W [--logs intel,aces]

``DIR`` holds the logs as ``lrfslam eval relations --all`` takes them (one folder per log, its
CARMEN log and relations). For each log with relations:

1. the stages (denoise → features → slam → mapper, the defaults) run over the whole log: the
   reference, its final trajectory (``eval relations``'s "mapper, final");
2. they run over the first half of the scans, and what the mapper leaves is the saved map
   (:class:`~lrfslam.evaluation.localization_sim.MapTaker`, as ``lrfslam map save`` keeps it);
3. the second half runs through fresh stages — no state from the first — with the mapper
   localizing on that map.

The whole run's trajectory is laid on the half map's keyframes (a rigid motion, least squares),
so the two frames agree to the maps' own errors. Reported:
the share of the second half's scans published as localized, the travel (on the reference) to the
first fix, *wrong fixes* (localized scans more than :data:`WRONG_M` or :data:`WRONG_RAD` from the
reference), and the mean translational error on the relations both of whose scans are
localized, beside the whole mapping run's on the same relations.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

from lrfslam import services
from lrfslam.algo.geometry import relative, wrap_angle
from lrfslam.evaluation.localization_sim import MapTaker, chain_with, localize_stage
from lrfslam.evaluation.map_trajectory import FinalTrajectoryBuilder
from lrfslam.evaluation.relations import load_relations, relation_errors, stamp_s
from lrfslam.io.textfile import open_log
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.runtime.decoding import LogOnce, decode_message
from lrfslam.runtime.recording import read_recording
from lrfslam.tools.eval_logs import find_logs
from lrfslam.tools.importers import import_carmen

#: A localized scan this far from the reference is a wrong fix (m, rad).
WRONG_M = 1.0
WRONG_RAD = 0.1


def _inputs(path: Path) -> list:
    """The recording's scans and odometry, decoded, in order."""
    wanted = {tp.name: tp for tp in (topics.SCAN, topics.ODOM)}
    once, counts = LogOnce(logging.getLogger("lrfslam.localization_logs")), Counter()
    return [decode_message(wanted[r.topic], r.data, r.schema, counts, once, r.topic)
            for r in read_recording(path, list(wanted))]


def _run(messages: list, mapper, robot: str, taker: MapTaker | None = None, search_s: list | None = None,
         stats: dict | None = None) -> list:
    """Every output of denoise → features → slam → ``mapper`` over ``messages`` (and the stages' last);
    with ``search_s``, the wall time of each message that ran a localizer's search is added to it."""
    out = []
    with chain_with(mapper, robot) as chain:
        localizer = getattr(chain.step("mapper"), "localizer", None)
        for m in messages:
            searches, begun = (localizer.searches if localizer else 0), time.perf_counter()
            got = chain.push(m)
            if search_s is not None and localizer is not None and localizer.searches != searches:
                search_s.append(time.perf_counter() - begun)
            out += got
            if taker is not None:
                taker.take([m, *got])
        if stats is not None and localizer is not None:
            stats.update(localizer.refused, candidates=localizer.candidates, fixes=localizer.fixes,
                         lost=localizer.lost, gated=localizer.gated, doubted=localizer.doubted)
        last = [it.msg for it in chain.finish_items()]
        out += last
        if taker is not None:
            taker.take(last)
    return out


def _final(outputs: list) -> tuple[np.ndarray, np.ndarray]:
    """The mapper's final trajectory from its outputs: stamps (T,) ns and poses (T, 3)."""
    builder = FinalTrajectoryBuilder()
    for m in outputs:
        builder.add(m.name, m.value)
    return builder.result()


def _aligned(stamps_ns: np.ndarray, poses: np.ndarray, saved) -> np.ndarray:
    """The whole run's poses (T, 3) moved into the saved map's frame: the rigid motion that best
    lays them on the saved keyframes at the same scans (least squares over the positions). The two
    maps' frames differ by what each optimisation let float, not by their own errors."""
    at = {s: k for k, s in enumerate(stamps_ns.tolist())}
    pairs = [(poses[at[s]], p) for s, p in zip(saved.stamp_ns.tolist(), saved.map_pose, strict=True) if s in at]
    a = np.array([q[:2] for q, _ in pairs])
    b = np.array([p[:2] for _, p in pairs])
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    h = (a - ca).T @ (b - cb)
    theta = float(np.arctan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1]))
    c, s_ = np.cos(theta), np.sin(theta)
    rot = np.array([[c, -s_], [s_, c]])
    out = poses.copy()
    out[:, :2] = (poses[:, :2] - ca) @ rot.T + cb
    out[:, 2] = wrap_angle(poses[:, 2] + theta)
    return out


def evaluate(log, work: Path) -> str:
    """One log: the lines of its report."""
    robot = log.name.replace(" ", "_")
    imported = work / f"{log.name}.mcap"
    import_carmen(log.path, imported, robot=robot)
    messages = _inputs(imported)
    scan_stamps = [m.stamp_ns for m in messages if m.topic is topics.SCAN]
    split_ns = scan_stamps[len(scan_stamps) // 2]
    started = time.monotonic()
    ref_stamps, ref_poses = _final(_run(messages, services.stage("mapper"), robot))
    taker = MapTaker()
    _run([m for m in messages if m.stamp_ns < split_ns], services.stage("mapper"), robot, taker)
    saved = taker.saved()
    search_s: list[float] = []
    stats: dict = {}
    placed = [m.value for m in _run([m for m in messages if m.stamp_ns >= split_ns], localize_stage(saved), robot,
                                    search_s=search_s, stats=stats) if m.topic is topics.MAP_POSE]
    ref_poses = _aligned(ref_stamps, ref_poses, saved)
    reference = dict(zip(ref_stamps.tolist(), ref_poses, strict=True))
    placed = [p for p in placed if p.stamp_ns in reference]
    ref = np.array([reference[p.stamp_ns] for p in placed])
    localized = np.array([p.localization == t.LOCALIZED for p in placed])
    poses = np.array([p.pose for p in placed])
    d = np.array([relative(a, b) for a, b in zip(ref, poses, strict=True)])
    wrong = localized & ((np.hypot(d[:, 0], d[:, 1]) > WRONG_M) | (np.abs(d[:, 2]) > WRONG_RAD))
    travel = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(ref[:, :2], axis=0).T))))
    first = travel[np.argmax(localized)] if localized.any() else float("nan")
    with open_log(log.relations) as f:
        relations = load_relations(f)
    secs = np.array([stamp_s(p.stamp_ns) for p in placed])
    on_map = relation_errors(secs[localized], poses[localized], relations)
    mapping = relation_errors(secs[localized], ref[localized], relations)
    return (f"{log.name}: map of the first half ({saved.map_pose.shape[0]} keyframes); second half "
            f"{len(placed)} scans, {travel[-1]:.0f} m: localized {localized.mean():.1%}, first fix after "
            f"{first:.1f} m, wrong fixes {int(wrong.sum())} scans (> {WRONG_M} m or {WRONG_RAD} rad from the "
            f"whole run's map); relations with both scans localized: {on_map.n_used}, error "
            f"{on_map.trans_abs_m.mean:.3f} m localized against {mapping.trans_abs_m.mean:.3f} m in the whole "
            f"mapping run; {len(search_s)} searches, wall time median {np.median(search_s) if search_s else 0:.2f} s, "
            f"max {max(search_s, default=0.0):.2f} s; {', '.join(f'{k} {v}' for k, v in stats.items())} "
            f"({time.monotonic() - started:.0f} s)")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m lrfslam.tools.localization_logs", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("root", type=Path, metavar="DIR")
    parser.add_argument("--work", type=Path, required=True, help="a folder for the imported recordings")
    parser.add_argument("--logs", help="comma-separated log names (folders of DIR); default every one with relations")
    args = parser.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    logs = [g for g in find_logs(args.root) if g.relations is not None]
    if args.logs:
        logs = [g for g in logs if g.name in args.logs.split(",")]
    for log in logs:
        print(evaluate(log, args.work), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
