"""Cost of the simulator's pieces on the built-in hallway loop.

Run: ``python -m lrfslam.bench.sim [--n 500]``. Prints mean and p95 milliseconds
per call, measured at poses spread round one lap.
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np

from lrfslam.sim.lidar import LidarModel, raycast, simulate_scan
from lrfslam.sim.simulator import SimConfig, Simulator
from lrfslam.sim.truth import eligible_corners, visible_corners


def _time_ms(fn, args_list) -> np.ndarray:
    out = np.empty(len(args_list))
    for i, args in enumerate(args_list):
        t0 = time.perf_counter()
        fn(*args)
        out[i] = (time.perf_counter() - t0) * 1e3
    return out


def main(n: int) -> None:
    sim = Simulator(SimConfig())
    world, model = sim.world, LidarModel()
    poses = sim.trajectory.pose(np.linspace(0, sim.trajectory.path.total_length_m / 0.05, n, endpoint=False))
    angles = model.angles_rad()
    rng = np.random.default_rng(0)

    rows = [
        ("raycast (181 beams)", _time_ms(lambda p: raycast(world.segments_m, p, angles, 8.0), [(p,) for p in poses])),
        ("simulate_scan", _time_ms(lambda p: simulate_scan(world, p, model, rng), [(p,) for p in poses])),
        ("visible_corners", _time_ms(lambda p: visible_corners(world, p), [(p,) for p in poses])),
        ("eligible_corners", _time_ms(lambda p: eligible_corners(world, p), [(p,) for p in poses])),
        ("Simulator frame", _time_ms(lambda: next(sim), [()] * n)),
    ]
    print(f"hallway_loop: {len(world.segments_m)} walls, {len(sim.map_corners)} corners; n = {n} poses")
    print(f"Python {platform.python_version()}, numpy {np.__version__}, {platform.machine()} {platform.processor()}")
    print(f"{'operation':<22}{'mean ms':>10}{'p95 ms':>10}")
    for name, ms in rows:
        print(f"{name:<22}{ms.mean():>10.3f}{np.percentile(ms, 95):>10.3f}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=500, help="poses per operation")
    main(parser.parse_args().n)
