"""Per-scan cost of noise reduction + feature extraction, both presets.

Simulates LMS200 scans (181 beams, σ = 10 mm, mixed pixels) round the hallway loop
and in rooms, then times ``denoise`` and ``extract_features`` scan by scan, on two
clocks: wall time and the process's CPU time (which leaves out the time other jobs
on a loaded machine take from it). Each scan is timed ``--repeat`` times per round
and the fastest run kept; the rounds (``--rounds``) interleave the two presets and
show how much the machine's load moves the figures. Prints milliseconds per scan:
mean, median and p95 over scans of the fastest runs, and the spread of the per-round
means. ``--reference`` times the previous implementation instead
(``tests/unit/reference_features.py``, ``reference_histogram.py``, the oracles of the
tests), for a before/after comparison on the same machine.

    python -m lrfslam.bench.features [--scans 200] [--repeat 5] [--rounds 3] [--reference]
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from functools import partial
from pathlib import Path

import numpy as np

from lrfslam.algo.features import FeatureParams, extract_features
from lrfslam.algo.histogram import DenoiseParams, denoise
from lrfslam.evaluation.features import build_scenes
from lrfslam.sim.lidar import LidarModel, simulate_scan

CLOCKS = {"wall": time.perf_counter_ns, "cpu": time.process_time_ns}


def scans(n: int, seed: int):
    sets = build_scenes(n, 4, max(1, n // 8), seed)
    rng = np.random.default_rng(seed)
    model = LidarModel(range_sigma_m=0.01)
    return [simulate_scan(s.world, p, model, rng) for scene in sets.values() for s in scene for p in s.poses]


def implementation(reference: bool):
    """(DenoiseParams, denoise, FeatureParams, extract_features) of this or the previous implementation."""
    if not reference:
        return DenoiseParams, denoise, FeatureParams, extract_features
    oracles = Path(__file__).resolve().parents[3] / "tests" / "unit"   # the source checkout's
    if not (oracles / "reference_features.py").exists():
        raise SystemExit("--reference needs a source checkout: the reference implementations are the tests' oracles")
    sys.path.insert(0, str(oracles))
    import reference_features
    import reference_histogram

    return (reference_histogram.DenoiseParams, reference_histogram.denoise, reference_features.FeatureParams,
            reference_features.extract_features)


def fastest(fn, repeat: int, clock) -> float:
    """Fastest of ``repeat`` calls, seconds."""
    best = np.inf
    for _ in range(repeat):
        t0 = clock()
        fn()
        best = min(best, clock() - t0)
    return best * 1e-9


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scans", type=int, default=200, help="hallway poses (rooms add half as many)")
    ap.add_argument("--repeat", type=int, default=5, help="timed calls per scan and round; the fastest counts")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--reference", action="store_true", help="time the previous implementation")
    args = ap.parse_args()
    den_params, den, cor_params, extract = implementation(args.reference)
    data = scans(args.scans, args.seed)
    print(f"{len(data)} scans of {len(data[0].ranges_m)} beams; Python {platform.python_version()}, "
          f"numpy {np.__version__}, {platform.machine()} ({platform.processor() or 'unknown cpu'}); "
          f"{args.rounds} rounds × {args.repeat} calls per scan; "
          f"{'previous (reference) implementation' if args.reference else 'this implementation'}\n")

    def pipeline(r, a, dp, cp):
        return extract(r, a, den(r, a, dp).kept, cp)

    stages = {
        "denoise": lambda r, a, k, dp, cp: partial(den, r, a, dp),
        "features": lambda r, a, k, dp, cp: partial(extract, r, a, k, cp),
        "denoise + features": lambda r, a, k, dp, cp: partial(pipeline, r, a, dp, cp),
    }
    modes = ("paper", "default")
    # best[mode, stage, clock]: per scan, the fastest over all rounds; rounds[...]: each round's mean.
    best = {(m, s, c): np.full(len(data), np.inf) for m in modes for s in stages for c in CLOCKS}
    rounds = {key: [] for key in best}
    for _ in range(args.rounds):
        for mode in modes:
            dp, cp = getattr(den_params, mode)(), getattr(cor_params, mode)()
            for clock_name, clock in CLOCKS.items():
                this = {s: np.empty(len(data)) for s in stages}
                for i, scan in enumerate(data):
                    r, a = scan.ranges_m, scan.angles_rad
                    kept = den(r, a, dp).kept
                    for stage, make in stages.items():
                        this[stage][i] = fastest(make(r, a, kept, dp, cp), args.repeat, clock)
                for stage, t in this.items():
                    key = (mode, stage, clock_name)
                    best[key] = np.minimum(best[key], t)
                    rounds[key].append(t.mean())
    print("| mode | stage | clock | mean ms | median ms | p95 ms | round means ms |")
    print("|---|---|---|---|---|---|---|")
    for (mode, stage, clock_name), t in best.items():
        ms, rm = 1e3 * t, 1e3 * np.asarray(rounds[(mode, stage, clock_name)])
        print(f"| {mode} | {stage} | {clock_name} | {ms.mean():.3f} | {np.median(ms):.3f} | "
              f"{np.percentile(ms, 95):.3f} | {rm.min():.3f}–{rm.max():.3f} |")


if __name__ == "__main__":
    main()
