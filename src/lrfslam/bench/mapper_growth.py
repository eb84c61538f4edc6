"""How the mapper's cost grows with its graph: a robot driving the simulator's loop round and round.

    OPENBLAS_NUM_THREADS=1 python -m lrfslam.bench.mapper_growth [--scans 30000] [--buckets 10]

Runs the in-process chain (denoise, features, slam, mapper: ``lrfslam.evaluation.slam_mc``'s
pipeline, the services' own steps) on the built-in hallway loop at the simulator's default 10 Hz
and 0.5 m/s, so a keyframe comes every ~10 scans and 30,000 scans give the ~3,000-keyframe graph
of the one-hour soak (docs/operations.md). Prints, per slice of the run: the keyframes and closures
by then, the sparse factorisations of the whole graph in that slice, and the mapper step's CPU time
per scan (``time.process_time``: mean, p99 and max, ms). Timing lives here, not in the tests.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from lrfslam.algo import pose_graph
from lrfslam.evaluation.slam_mc import McConfig, _Pipeline
from lrfslam.runtime import chain
from lrfslam.sim.simulator import SimConfig, Simulator

_through = chain.Chain._through
_factorise = pose_graph._factorise
spent = {"mapper": 0.0}
factorisations = [0]


def _timed_through(self, i, lk, stream):
    t0 = time.process_time()
    out = _through(self, i, lk, stream)
    if lk.name == "mapper":
        spent["mapper"] += time.process_time() - t0
    return out


def _counted_factorise(h):
    factorisations[0] += 1
    return _factorise(h)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scans", type=int, default=30000)
    ap.add_argument("--buckets", type=int, default=10)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    chain.Chain._through = _timed_through
    pose_graph._factorise = _counted_factorise
    cfg = McConfig(mapper=True)
    sim = Simulator(SimConfig(world_name=cfg.world_name, odometry=cfg.odometry, seed=args.seed))
    frame = next(sim)
    pipeline = _Pipeline(sim, cfg, cfg.ekf_params(), frame.true_pose)
    mapper = pipeline.chain.step("mapper").mapper
    rows = []
    for _ in range(args.scans):
        spent["mapper"] = 0.0
        pipeline.step(frame)
        stats = mapper.stats
        rows.append((mapper.keyframe_count, stats.accepted - stats.removed, factorisations[0], spent["mapper"]))
        frame = next(sim)
    rows = np.array(rows)
    print(f"mapper cost per scan, {args.scans} scans of {cfg.world_name} (seed {args.seed})")
    print("| scans | keyframes | closures | factorisations in slice | mean ms | p99 ms | max ms |")
    print("|---|---|---|---|---|---|---|")
    previous = 0
    for part in np.array_split(np.arange(args.scans), args.buckets):
        s = rows[part]
        ms = s[:, 3] * 1e3
        print(f"| {part[-1] + 1} | {int(s[-1, 0])} | {int(s[-1, 1])} | {int(s[-1, 2]) - previous} | "
              f"{ms.mean():.2f} | {np.percentile(ms, 99):.1f} | {ms.max():.1f} |")
        previous = int(s[-1, 2])
    print(f"total mapper CPU {rows[:, 3].sum():.1f} s")


if __name__ == "__main__":
    main()
