"""Per-scan cost of noise reduction + feature extraction, both presets.

Simulates LMS200 scans (181 beams, σ = 10 mm, mixed pixels) round the hallway loop
and in a room, then times ``denoise`` and ``extract_features`` scan by scan. Prints
mean, median and p95 in milliseconds. Each scan is timed ``--repeat`` times and the
fastest run kept, so other processes on the machine inflate the figures less.

    python benchmarks/bench_features.py [--scans 200] [--repeat 5]
"""

from __future__ import annotations

import argparse
import platform
import time
from functools import partial

import numpy as np

from lrfslam.algo.corners import CornerParams, extract_features
from lrfslam.algo.histogram import DenoiseParams, denoise
from lrfslam.evaluation.features import build_scenes
from lrfslam.sim.lidar import LidarModel, simulate_scan


def scans(n: int, seed: int):
    sets = build_scenes(n, 4, max(1, n // 8), seed)
    rng = np.random.default_rng(seed)
    model = LidarModel(range_sigma_m=0.01)
    return [simulate_scan(s.world, p, model, rng) for scene in sets.values() for s in scene for p in s.poses]


def pipeline(ranges_m, angles_rad, dp: DenoiseParams, cp: CornerParams):
    return extract_features(ranges_m, angles_rad, denoise(ranges_m, angles_rad, dp).kept, cp)


def fastest(fn, repeat: int) -> float:
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scans", type=int, default=200, help="hallway poses (rooms add half as many)")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    data = scans(args.scans, args.seed)
    print(f"{len(data)} scans of {len(data[0].ranges_m)} beams; Python {platform.python_version()}, "
          f"numpy {np.__version__}, {platform.machine()} ({platform.processor() or 'unknown cpu'})\n")
    print("| mode | stage | mean ms | median ms | p95 ms |")
    print("|---|---|---|---|---|")
    for mode in ("paper", "default"):
        dp, cp = getattr(DenoiseParams, mode)(), getattr(CornerParams, mode)()
        t_den, t_feat, t_all = [], [], []
        for s in data:
            r, a = s.ranges_m, s.angles_rad
            kept = denoise(r, a, dp).kept
            t_den.append(fastest(partial(denoise, r, a, dp), args.repeat))
            t_feat.append(fastest(partial(extract_features, r, a, kept, cp), args.repeat))
            t_all.append(fastest(partial(pipeline, r, a, dp, cp), args.repeat))
        for stage, t in (("denoise", t_den), ("features", t_feat), ("denoise + features", t_all)):
            ms = 1e3 * np.asarray(t)
            print(f"| {mode} | {stage} | {ms.mean():.3f} | {np.median(ms):.3f} | {np.percentile(ms, 95):.3f} |")


if __name__ == "__main__":
    main()
