"""Mapping on from a saved map, day after day, on the simulator (docs/maps.md "Mapping on from a saved map").

    python -m lrfslam.evaluation.mapping_on [--days 5] [--laps 1.5] [--world hallway_loop]

Day 0 maps ``--laps`` of the world's loop from its start (denoise → features → slam → mapper, the
pipeline's chain, the service's own steps); each later day starts elsewhere on the loop (day d at
``d × 20 m``) with other noise, maps on from the map the day before left (as ``lrfslam up --map
MAP --save-map NEW`` does), and leaves the map grown. Per day: where the robot was found on the map,
the pose error of the scans mapped on it against the truth (the map's frame is day 0's slam frame,
which starts at the true pose), the closures, the revisits folded, and the saved map's keyframes:
a map that grows with the place, not with the days, stays the same size after day 0.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, replace

import numpy as np

from lrfslam import services
from lrfslam.evaluation.localization_sim import MapTaker, chain_with, frame_messages
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.msgs.grid_replica import GridReplica
from lrfslam.runtime.chain import Stage
from lrfslam.runtime.saved_map import SavedMap
from lrfslam.services.mapper import MapperConfig, MapperStep
from lrfslam.sim.simulator import SimConfig, Simulator

#: Each day's stamps start this much after the day before's (ns): the saved keyframes are older.
DAY_NS = 86_400 * 10**9
#: Day d starts this far along the loop per day (m).
START_STEP_M = 20.0


@dataclass
class Day:
    """One day's run: every ``map/pose`` with the true pose of its scan, the map it left, the
    mapper's step, and the grid it published while the robot was not found yet."""

    poses: list[tuple[t.MapPose, np.ndarray]]
    saved: SavedMap
    step: object
    before_fix: GridReplica


def on(saved: SavedMap) -> Stage:
    """The mapper stage mapping on from ``saved`` (in memory: the service's own step)."""
    spec = replace(services.spec("mapper"), build=lambda cfg, ctx: MapperStep(cfg, ctx, saved))
    return Stage(spec, MapperConfig(map="(in memory)"))


def drive(day: int, metres: float, world: str = "hallway_loop", saved: SavedMap | None = None) -> Day:
    """Day ``day``: ``metres`` of ``world``'s loop, from empty (``saved`` None) or mapping on from ``saved``."""
    sim = Simulator(SimConfig(world_name=world, seed=day + 1, start_m=START_STEP_M * day))
    taker, before_fix = MapTaker(), GridReplica()
    if saved is not None:   # the saved keyframes keep their scans in the grown map (lrfslam map save --base)
        taker.scans.update({int(s): saved.keyframe_points(k) for k, s in enumerate(saved.stamp_ns)})
    poses = []
    with chain_with(services.stage("mapper") if saved is None else on(saved), f"day{day}") as chain:
        if saved is None:
            chain.step("slam").slam.start_at(sim.trajectory.pose(0))
        step = chain.step("mapper")
        for _ in range(int(metres / sim.config.speed_mps * sim.config.rate_hz)):
            frame = next(sim)
            odom, scan = frame_messages(sim, frame, day * DAY_NS)
            outs = chain.push(odom) + chain.push(scan)
            taker.take([scan, *outs])
            poses += [(m.value, frame.true_pose) for m in outs if m.topic is topics.MAP_POSE]
            if poses and poses[-1][0].localization == t.NOT_LOCALIZED:
                for m in outs:
                    if m.topic is topics.MAP_GRID:
                        before_fix.apply(m.value)
        taker.take([it.msg for it in chain.finish_items()])
    return Day(poses, taker.saved(), step, before_fix)


def days(n: int, laps: float, world: str = "hallway_loop") -> list[Day]:
    """Day 0 and ``n − 1`` days mapping on, each from the map the day before left."""
    length = Simulator(SimConfig(world_name=world)).trajectory.path.total_length_m
    out = [drive(0, laps * length, world)]
    for d in range(1, n):
        out.append(drive(d, laps * length, world, out[-1].saved))
    return out


def row(d: int, day: Day, speed_mps: float, rate_hz: float) -> str:
    """One line of the table: see the module docstring."""
    states = [p.localization for p, _ in day.poses]
    found = states.index(t.MAPPING) if t.MAPPING in states else len(states)
    err = np.array([np.hypot(*(p.pose[:2] - true[:2])) for p, true in day.poses[found:]])
    stats = day.step.mapper.stats
    made = day.step.mapper.keyframe_count - (0 if day.step.saved is None else day.step.saved.stamp_ns.size)
    found_m = f"{found / rate_hz * speed_mps:.1f} m" if d else "-"
    errors = f"{np.median(err):.3f} / {err.max():.3f}" if err.size else "-"
    return (f"| {d} | {found_m} | {errors} | {stats.accepted - stats.removed} | {made} | {stats.folded} | "
            f"{day.saved.stamp_ns.size} |")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m lrfslam.evaluation.mapping_on", description=__doc__.splitlines()[0])
    parser.add_argument("--days", type=int, default=5)
    parser.add_argument("--laps", type=float, default=1.5, help="laps of the loop each day (default 1.5)")
    parser.add_argument("--world", default="hallway_loop")
    args = parser.parse_args(argv)
    if args.days < 1 or not args.laps > 0:
        parser.error("--days must be >= 1 and --laps > 0")
    cfg = SimConfig(world_name=args.world)
    print("| day | found after | error median / max, m | closures | keyframes made | folded | saved map's keyframes |")
    print("|---|---|---|---|---|---|---|")
    for d, day in enumerate(days(args.days, args.laps, args.world)):
        print(row(d, day, cfg.speed_mps, cfg.rate_hz), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
