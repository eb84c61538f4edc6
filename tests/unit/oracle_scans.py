"""Random scans for the oracle tests (test_features_oracle.py, test_denoise_oracle.py).

Simulated LMS200 scans round the hallway loop and in random rotated rooms at several
noise levels, and scans of garbage: random ranges with NaN, ±inf, zeros and negative
values on random, non-uniform increasing bearings.
"""

from __future__ import annotations

import numpy as np

from lrfslam.evaluation.features import hallway_poses, random_room, room_poses
from lrfslam.sim.floor_plans import hallway_loop
from lrfslam.sim.lidar import LidarModel, simulate_scan


def simulated(n_hallway: int, n_rooms: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """(ranges_m, angles_rad) pairs, shape (181,) each, σ cycling through 0–20 mm."""
    rng = np.random.default_rng(seed)
    sigmas = (0.0, 0.005, 0.01, 0.02)
    hall = hallway_loop()
    out = []
    for i, pose in enumerate(hallway_poses(n_hallway, rng)):
        scan = simulate_scan(hall, pose, LidarModel(range_sigma_m=sigmas[i % 4]), rng)
        out.append((scan.ranges_m, scan.angles_rad))
    for i in range(n_rooms):
        room = random_room(rng)
        for pose in room_poses(room, 3, rng):
            scan = simulate_scan(room, pose, LidarModel(range_sigma_m=sigmas[i % 4]), rng)
            out.append((scan.ranges_m, scan.angles_rad))
    return out


def garbage(n: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """(ranges_m, angles_rad) pairs of 0–200 beams: mostly 0–5 m, with NaN, ±inf, 0 and negatives."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        k = int(rng.integers(0, 200))
        r = rng.uniform(0.0, 5.0, k)
        # Smooth stretches too, so that arms and corners occur, not only noise.
        r = np.where(rng.random(k) < 0.5, r, np.repeat(rng.uniform(0.5, 3.5, k // 10 + 1), 10)[:k])
        bad = rng.random(k)
        r[bad < 0.05] = np.nan
        r[(bad >= 0.05) & (bad < 0.08)] = np.inf
        r[(bad >= 0.08) & (bad < 0.10)] = 0.0
        r[(bad >= 0.10) & (bad < 0.11)] = -1.0
        a = np.cumsum(rng.uniform(0.002, 0.04, k)) - 1.5
        out.append((r, a))
    return out
