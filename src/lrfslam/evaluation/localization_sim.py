"""Localization on a saved map, judged by the simulator's truth: random starts, no initial pose.

    python -m lrfslam.evaluation.localization_sim [--world large_building] [--starts 100] [--jobs 2]

First one run maps the world (denoise → features → slam → mapper, one lap, the defaults) and its
final keyframes with their scans become the saved map, as ``lrfslam map save`` makes it. Then each
start is another seeded run (other odometry and range noise, other people) from a random place
on the loop, driven through denoise → features → slam → mapper with ``localize`` on that map:
the service's own step, as ``lrfslam up --map MAP --localize`` runs it. Each run drives
:data:`MAX_TRAVEL_M`, or :data:`CHECK_AFTER_FIX_M` past its first fix.

Reported: the share of starts localized within 20 m of travel, the travel to the first fix, and
*wrong fixes*: scans published as localized more than :data:`WRONG_M` or :data:`WRONG_RAD` from the
truth (the map frame is the mapping run's, which started at the true pose; its own error is
centimetres). The position error of the localized scans is the accuracy.
"""

from __future__ import annotations

import argparse
import multiprocessing
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace

import numpy as np

from lrfslam import services
from lrfslam.algo.geometry import polar_to_xy, relative
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.msgs.grid_replica import GridReplica
from lrfslam.runtime.chain import Chain, Stage
from lrfslam.runtime.saved_map import SavedMap
from lrfslam.runtime.step import Message
from lrfslam.services.mapper import LocalizeStep, MapperConfig
from lrfslam.services.sensor import frame_outputs
from lrfslam.sim.simulator import SimConfig, Simulator

#: A start is driven this far at most (m), or this far past its first fix.
MAX_TRAVEL_M = 40.0
CHECK_AFTER_FIX_M = 15.0
#: A localized scan this far from the truth is a wrong fix (m, rad).
WRONG_M = 1.0
WRONG_RAD = 0.1
#: The target's travel (m): localized within this far of the start.
WITHIN_M = 20.0


def frame_messages(sim: Simulator, frame, offset_ns: int = 0) -> tuple[Message, Message]:
    """The frame's odometry and scan messages, as the sensor publishes them, stamped by data time
    (plus ``offset_ns``: another day's run)."""
    odom, scan = frame_outputs(frame, offset_ns + round(frame.t_s * 1e9), sim)
    return Message.of(odom), Message.of(scan)


def chain_with(mapper: Stage, robot: str) -> Chain:
    """denoise → features → slam → ``mapper``, in one process, as the pipeline runs them."""
    return Chain([*(services.stage(n) for n in ("denoise", "features", "slam")), mapper], robot=robot, wire=False)


class MapTaker:
    """What a mapping run leaves that ``map save`` keeps: each scan's valid points, the graph's
    keyframes at the end, the live grid, the laser's layout; :meth:`saved` makes the saved map (no
    landmarks: the localizer does not read them)."""

    def __init__(self) -> None:
        self.graph: t.MapKeyframes | None = None
        self.grid = GridReplica()
        self.scans: dict[int, np.ndarray] = {}
        self.laser: dict = {}

    def take(self, messages) -> None:
        """Keep what of ``messages`` (the chain's, inputs and outputs) a saved map is made of."""
        for m in messages:
            if m.topic is topics.SCAN:
                v = m.value
                ok = v.status == t.BEAM_VALID
                self.scans[v.stamp_ns] = polar_to_xy(v.ranges_m[ok], v.angles_rad[ok])
                self.laser = {"beams": int(v.ranges_m.size), "angle_min_rad": v.angle_min_rad,
                              "angle_increment_rad": v.angle_increment_rad, "range_max_m": v.range_max_m}
            elif m.topic is topics.MAP_KEYFRAMES:
                self.graph = m.value
            elif m.topic is topics.MAP_GRID:
                self.grid.apply(m.value)

    def saved(self) -> SavedMap:
        kf = self.graph
        blocks = [self.scans[int(s)] for s in kf.scan_stamp_ns]
        image = self.grid.image()
        none = np.zeros(0, np.int64)
        return SavedMap(manifest={"laser": self.laser}, stamp_ns=kf.scan_stamp_ns, map_pose=kf.map_pose,
                        local_pose=kf.local_pose,
                        local_edge=kf.local_edge, edge_from=none, edge_to=none, edge_motion=np.zeros((0, 3)),
                        points_xy_m=np.vstack(blocks), point_start=np.cumsum([0] + [b.shape[0] for b in blocks]),
                        landmark_ids=none, landmark_xy_m=np.zeros((0, 2)), landmark_cov_m2=np.zeros((0, 2, 2)),
                        landmark_kind=np.zeros(0, np.int8), landmark_sightings=none,
                        landmark_confirmed=np.zeros(0, bool), grid_cells=image.cells,
                        grid_resolution_m=image.resolution_m, grid_origin_xy_m=image.origin_xy_m)


def localize_stage(saved: SavedMap) -> Stage:
    """The mapper stage in localize mode on ``saved`` (in memory: the service's own step)."""
    spec = replace(services.spec("mapper"), build=lambda cfg, ctx: LocalizeStep(cfg, ctx, saved))
    return Stage(spec, MapperConfig(map="(in memory)", localize=True))


def map_world(world: str, seed: int) -> SavedMap:
    """One lap of ``world`` mapped; its saved map (:class:`MapTaker`)."""
    sim = Simulator(SimConfig(world_name=world, seed=seed))
    steps = int(np.ceil(sim.trajectory.path.total_length_m / sim.config.speed_mps * sim.config.rate_hz))
    taker = MapTaker()
    with chain_with(services.stage("mapper"), "map_world") as chain:
        chain.step("slam").slam.start_at(sim.trajectory.pose(0))
        for frame in (next(sim) for _ in range(steps)):
            odom, scan = frame_messages(sim, frame)
            taker.take([scan, *chain.push(odom), *chain.push(scan)])
        taker.take([it.msg for it in chain.finish_items()])
    return taker.saved()


@dataclass(frozen=True)
class StartResult:
    start_m: float
    fix_travel_m: float          # travel to the first localized scan; inf: none
    wrong: int                   # localized scans beyond WRONG_M / WRONG_RAD
    localized: int               # scans published as localized
    scans: int
    errors_m: np.ndarray         # position error of each localized scan
    search_s: np.ndarray         # wall time of each scan that ran a global search (s)


def run_start(world: str, saved: SavedMap, seed: int, start_m: float) -> StartResult:
    """One run from ``start_m`` along the loop, localized on ``saved``; see the module docstring."""
    sim = Simulator(SimConfig(world_name=world, seed=seed, start_m=start_m))
    with chain_with(localize_stage(saved), f"start{seed}") as chain:
        step = chain.step("mapper")
        travel, fix_at, wrong, localized, n = 0.0, np.inf, 0, 0, 0
        errors, search_s, last_true = [], [], None
        while travel < MAX_TRAVEL_M and travel < fix_at + CHECK_AFTER_FIX_M:
            frame = next(sim)
            if last_true is not None:
                travel += float(np.hypot(*relative(last_true, frame.true_pose)[:2]))
            last_true = frame.true_pose
            odom, scan = frame_messages(sim, frame)
            searches, started = step.localizer.searches, time.perf_counter()
            outs = chain.push(odom) + chain.push(scan)
            if step.localizer.searches != searches:
                search_s.append(time.perf_counter() - started)
            for m in outs:
                if m.topic is not topics.MAP_POSE:
                    continue
                n += 1
                if m.value.localization != t.LOCALIZED:
                    continue
                localized += 1
                fix_at = min(fix_at, travel)
                d = relative(frame.true_pose, m.value.pose)
                err = float(np.hypot(d[0], d[1]))
                errors.append(err)
                wrong += int(err > WRONG_M or abs(d[2]) > WRONG_RAD)
        return StartResult(start_m, fix_at, wrong, localized, n, np.array(errors),
                           np.array(search_s))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m lrfslam.evaluation.localization_sim", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--world", default="large_building")
    parser.add_argument("--starts", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--jobs", type=int, default=1)
    args = parser.parse_args(argv)
    t0 = time.monotonic()
    saved = map_world(args.world, args.seed)
    print(f"map: {args.world}, {saved.map_pose.shape[0]} keyframes ({time.monotonic() - t0:.0f} s)", flush=True)
    length = Simulator(SimConfig(world_name=args.world)).trajectory.path.total_length_m
    rng = np.random.default_rng(args.seed)
    starts = rng.uniform(0.0, length, args.starts)
    seeds = [args.seed + 1000 + i for i in range(args.starts)]
    # Spawned, not forked: this process has run the compiled kernels, whose threads a fork cannot copy.
    with ProcessPoolExecutor(args.jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
        results = list(pool.map(run_start, [args.world] * args.starts, [saved] * args.starts, seeds, starts))
    fix = np.array([r.fix_travel_m for r in results])
    within = int(np.sum(fix <= WITHIN_M))
    wrong_starts = sum(r.wrong > 0 for r in results)
    errs = np.concatenate([r.errors_m for r in results]) if results else np.zeros(0)
    search = np.concatenate([r.search_s for r in results])
    found = fix[np.isfinite(fix)]
    print(f"starts: {len(results)}; localized within {WITHIN_M:.0f} m: {within} ({100.0 * within / len(results):.0f} %); "
          f"ever: {found.size}")
    if found.size:
        print(f"travel to the first fix: median {np.median(found):.1f} m, max {found.max():.1f} m")
    print(f"wrong fixes (> {WRONG_M} m or {WRONG_RAD} rad while localized): {sum(r.wrong for r in results)} scans "
          f"in {wrong_starts} starts")
    print(f"localized scans: {sum(r.localized for r in results)} of {sum(r.scans for r in results)}; "
          f"position error mean {errs.mean() if errs.size else float('nan'):.3f} m, "
          f"p95 {np.percentile(errs, 95) if errs.size else float('nan'):.3f} m")
    if search.size:
        print(f"global searches: {search.size}, wall time median {np.median(search):.2f} s, max {search.max():.2f} s")
    for r in results:
        if r.wrong or not np.isfinite(r.fix_travel_m) or r.fix_travel_m > WITHIN_M:
            print(f"  start {r.start_m:.1f} m: first fix after {r.fix_travel_m:.1f} m, {r.wrong} wrong")
    print(f"({time.monotonic() - t0:.0f} s)")
    return 0 if results and wrong_starts == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
