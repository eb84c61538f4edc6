"""``lrfslam eval``: accuracy evaluations of recordings.

    lrfslam eval relations --all DIR [--work DIR] [--set STAGE.NAME=VALUE ...]
        Every CARMEN log in the folders under DIR through the whole pipeline with one
        configuration; one table of relation errors (overall and by span) for those
        with relations, a map for those without (lrfslam.tools.eval_logs).
    lrfslam eval closures RECORDING RELATIONS [--work DIR] [--set STAGE.NAME=VALUE ...]
        Every loop closure the mapper tried on RECORDING (an imported log), judged by the
        relations: false accepts, precision and recall (lrfslam.evaluation.closure_audit).
    lrfslam eval relations RECORDING RELATIONS [--max-gap-s S] [--scan-matching [--set NAME=VALUE ...]]
        Kümmerle et al. (2009) relation metric of the SLAM estimate (``slam/state``)
        and of the raw odometry (``odom``) of a recording (an MCAP file or a recording
        folder), as a table; with
        ``--scan-matching`` also of the slam service's scan matching alone, run on
        the recording's ``scan`` and ``odom`` (NAME: a ``ScanMatchParams`` field).
    lrfslam eval features ...    corner-feature accuracy (lrfslam.evaluation.features)
    lrfslam eval slam ...        SLAM Monte-Carlo evaluation (lrfslam.evaluation.slam_mc)
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from pathlib import Path

import numpy as np

from lrfslam.algo.scan_match import ScanMatchParams
from lrfslam.errors import LrfSlamError
from lrfslam.evaluation.laser_odometry import scan_matched_trajectory
from lrfslam.evaluation.recording_relations import (
    TRAJECTORIES,
    evaluate_relations,
    read_trajectories,
    relations_table,
)
from lrfslam.evaluation.relations import (
    DEFAULT_MAX_STAMP_GAP_S,
    load_relations,
    stamp_s,
)
from lrfslam.io.textfile import open_log
from lrfslam.msgs import topics
from lrfslam.runtime import config as config_mod

#: Subcommands implemented elsewhere: name -> module whose ``main(argv)`` runs it.
DELEGATED = {"features": "lrfslam.evaluation.features", "slam": "lrfslam.evaluation.slam_mc"}


def audit_closures(recording: str, relations_path: str, work: Path, sets: list[str], max_gap_s: float) -> int:
    """``lrfslam eval closures``: run the pipeline with the mapper observed; print the audit."""
    from lrfslam.evaluation import closure_audit
    from lrfslam.tools import pipeline

    with open_log(relations_path) as f:
        relations = load_relations(f)
    journal: list = []
    stages = closure_audit.observed_stages(
        pipeline.build_stages(pipeline.DEFAULT_STAGES, sets, {}, os.environ), journal)
    work.mkdir(parents=True, exist_ok=True)
    out = work / (Path(recording).name.split(".")[0] + ".closures.mcap")
    pipeline.run_pipeline(stages, "audit", recording, out)
    traj, _ = read_trajectories(out, {"slam": topics.SLAM_STATE})
    noise = closure_audit.reference_noise(relations, *traj["slam"], max_gap_s)
    judged = closure_audit.judge(journal, relations, *traj["slam"], max_gap_s, noise)
    print(f"{recording} vs {relations_path}: {len(journal)} closure attempts, "
          f"{sum(j.covered for j in judged)} covered by a relation within {closure_audit.BRIDGE_S} s")
    print(f"the reference's own error (fitted on the relations under {closure_audit.SHORT_SPAN_S:g} s): a relation "
          f"sigma {1e3 * np.sqrt(noise.relation[0]):.1f} {1e3 * np.sqrt(noise.relation[1]):.1f} mm "
          f"{np.degrees(np.sqrt(noise.relation[2])):.2f} deg; the EKF's bridge sigma per sqrt(s) "
          f"{1e3 * np.sqrt(noise.per_s[0]):.1f} {1e3 * np.sqrt(noise.per_s[1]):.1f} mm "
          f"{np.degrees(np.sqrt(noise.per_s[2])):.2f} deg")
    print(closure_audit.report(judged))
    return 0


def _delegate(name: str, argv: list[str]) -> int:
    module = DELEGATED[name]
    try:
        target = importlib.import_module(module)
    except ModuleNotFoundError as exc:
        # Only the module itself being absent means "not available"; a missing
        # dependency inside it is a real error and must surface.
        if exc.name != module:
            raise
        print(f"lrfslam eval {name}: not available in this installation ({module} is missing)", file=sys.stderr)
        return 2
    return int(target.main(argv) or 0)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in DELEGATED:
        return _delegate(argv[0], argv[1:])
    parser = argparse.ArgumentParser(prog="lrfslam eval", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True, metavar="{relations,closures,features,slam}")
    rel = sub.add_parser("relations", help="relation metric of the SLAM estimate and of raw odometry")
    rel.add_argument("recording", metavar="RECORDING", nargs="?",
                     help="recording with slam/state and odom: an MCAP file or a recording folder")
    rel.add_argument("relations", metavar="RELATIONS", nargs="?",
                     help="ground-truth relations file (t1 t2 x y z roll pitch yaw)")
    rel.add_argument("--all", metavar="DIR", type=Path, dest="all_logs",
                     help="every CARMEN log in the folders under DIR (e.g. ../shared/datasets): import, "
                          "run the pipeline with one configuration, score those with relations, one table")
    rel.add_argument("--work", metavar="DIR", type=Path, default=Path("recordings") / "eval",
                     help="with --all: where the imported logs, pipeline outputs and maps go")
    rel.add_argument("--config", metavar="FILE", help="with --all: TOML config file for every stage")
    rel.add_argument("--jobs", type=int, default=len(os.sched_getaffinity(0)), metavar="N",
                     help="with --all: logs run at once, each in a process of its own (default: this "
                          "process's CPUs)")
    rel.add_argument("--trials", type=int, default=1, metavar="N",
                     help="with --all: run each log with relations N times under perturbations that must not "
                          "matter (other floating-point paths, 1e-6 m of seeded range noise) and report each "
                          "figure's mean, minimum, maximum and spread")
    rel.add_argument("--max-gap-s", type=float, default=DEFAULT_MAX_STAMP_GAP_S, dest="max_gap_s",
                     help=f"stamp-matching tolerance in s (default {DEFAULT_MAX_STAMP_GAP_S})")
    rel.add_argument("--scan-matching", action="store_true",
                     help="also score scan matching alone (the slam service's tracker, no filter)")
    rel.add_argument("--set", dest="sets", action="append", default=[], metavar="NAME=VALUE",
                     help="with --scan-matching: a scan-matching setting, e.g. max_point_range_m=4; "
                          "with --all: a stage's setting for every log, e.g. slam.scan_matching=false")
    clo = sub.add_parser("closures", help="every loop closure the mapper tried, judged by the relations")
    clo.add_argument("recording", metavar="RECORDING", help="an imported log (lrfslam import carmen): scans and odometry")
    clo.add_argument("relations", metavar="RELATIONS", help="its ground-truth relations file")
    clo.add_argument("--work", metavar="DIR", type=Path, default=Path("recordings") / "eval",
                     help="where the pipeline's output goes")
    clo.add_argument("--set", dest="sets", action="append", default=[], metavar="STAGE.NAME=VALUE",
                     help="a stage's setting, e.g. mapper.loop_closure.min_score=0.6")
    clo.add_argument("--max-gap-s", type=float, default=DEFAULT_MAX_STAMP_GAP_S, dest="max_gap_s",
                     help=f"stamp-matching tolerance in s (default {DEFAULT_MAX_STAMP_GAP_S})")
    args = parser.parse_args(argv)
    if args.command == "closures":
        try:
            return audit_closures(args.recording, args.relations, args.work, args.sets, args.max_gap_s)
        except (LrfSlamError, OSError) as exc:
            print(f"lrfslam eval closures: {exc}", file=sys.stderr)
            return 2
    if args.all_logs is not None:
        if args.recording or args.relations or args.scan_matching:
            parser.error("--all takes no recording, relations file or --scan-matching")
        if args.jobs < 1 or args.trials < 1:
            parser.error(f"--jobs and --trials must be >= 1, got {args.jobs} and {args.trials}")
        from lrfslam.tools import eval_logs
        try:
            return eval_logs.main_all(args.all_logs, args.work, args.sets, args.config, args.jobs, args.trials)
        except (LrfSlamError, OSError) as exc:
            print(f"lrfslam eval relations: {exc}", file=sys.stderr)
            return 2
    if not (args.recording and args.relations):
        parser.error("give a recording and its relations file, or --all DIR")
    try:
        extra, bad = {}, 0
        if args.scan_matching:
            stamps_ns, poses, bad = scan_matched_trajectory(args.recording,
                                                            config_mod.load(ScanMatchParams, sets=args.sets))
            extra["scan matching"] = (np.array([stamp_s(s) for s in stamps_ns]), poses)
        results, undecodable = evaluate_relations(args.recording, args.relations, args.max_gap_s, extra)
        undecodable += bad
    except (LrfSlamError, OSError) as exc:
        print(f"lrfslam eval relations: {exc}", file=sys.stderr)
        return 2
    if undecodable:
        print(f"lrfslam eval relations: skipped {undecodable} undecodable messages", file=sys.stderr)
    if not results:
        print(f"lrfslam eval relations: {args.recording} has neither {topics.SLAM_STATE.name} nor "
              f"{topics.ODOM.name} messages", file=sys.stderr)
        return 2
    first = next(iter(results.values()))
    print(f"{args.recording} vs {args.relations}: {first.n_relations} relations, "
          f"stamps matched within {args.max_gap_s} s")
    with open_log(args.relations) as f:
        print(relations_table(results, load_relations(f)))
    missing = [label for label in TRAJECTORIES if label not in results]
    if missing:
        print(f"(no {', '.join(missing)} in the recording)")
    return 0
