"""Instructions per scan of noise reduction + feature extraction, both presets, under callgrind.

Wall and CPU time on a shared VM move by 20 % from one run to the next
(``lrfslam.bench.features`` shows it); an instruction count does not: valgrind's callgrind
counts the same total for the same code, inputs and environment whatever else the
machine is doing. So this is the figure to compare two versions of the code by.

The scans are those of ``lrfslam.bench.features`` (hallway and rooms, σ = 10 mm). Each
preset runs the pipeline once (warm-up) plus ``loops`` passes in one process and once
plus ``3 * loops``; the difference over ``2 * loops`` passes is the steady-state cost,
without the interpreter's start-up and imports.

    python -m lrfslam.bench.instructions_features [--scans 40] [--loops 1] [--features-only]

``--features-only`` counts ``extract_features`` alone: the scans are denoised before the
passes.

Needs ``valgrind`` (Debian package ``valgrind``).
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys

import numpy as np


def _child(n_scans: int, loops: int, mode: str, features_only: bool) -> None:
    """Run denoise + extract_features (or extract_features alone) over the scans ``1 + loops`` times (inside valgrind)."""
    from lrfslam.algo.features import FeatureParams, extract_features
    from lrfslam.algo.histogram import DenoiseParams, denoise
    from lrfslam.bench.features import scans

    data = [(s.ranges_m, s.angles_rad) for s in scans(n_scans, 0)]
    dp, cp = getattr(DenoiseParams, mode)(), getattr(FeatureParams, mode)()
    if features_only:
        kept = [denoise(r, a, dp).kept for r, a in data]
        for _ in range(1 + loops):
            for (r, a), k in zip(data, kept):
                extract_features(r, a, k, cp)
        return
    for _ in range(1 + loops):
        for r, a in data:
            extract_features(r, a, denoise(r, a, dp).kept, cp)


def _instructions(n_scans: int, loops: int, mode: str, features_only: bool) -> int:
    env = dict(os.environ, PYTHONHASHSEED="0", OPENBLAS_NUM_THREADS="1")
    cmd = ["valgrind", "--tool=callgrind", "--callgrind-out-file=/dev/null", sys.executable, __file__,
           "--child", mode, "--scans", str(n_scans), "--loops", str(loops)] + ["--features-only"] * features_only
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True).stderr
    return int(re.search(r"Collected : (\d+)", out).group(1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scans", type=int, default=40, help="hallway poses (rooms add half as many)")
    ap.add_argument("--loops", type=int, default=1)
    ap.add_argument("--features-only", action="store_true", help="count extract_features alone")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        _child(args.scans, args.loops, args.child, args.features_only)
        return
    if shutil.which("valgrind") is None:
        sys.exit("valgrind not found (Debian package valgrind)")
    from lrfslam.bench.features import scans

    n = len(scans(args.scans, 0))
    print(f"{n} scans; numpy {np.__version__}; Python {sys.version.split()[0]}\n")
    print(f"| mode | instructions per scan ({'features' if args.features_only else 'denoise + features'}) |")
    print("|---|---|")
    for mode in ("paper", "default"):
        low = _instructions(args.scans, args.loops, mode, args.features_only)
        high = _instructions(args.scans, 3 * args.loops, mode, args.features_only)
        print(f"| {mode} | {(high - low) / (2 * args.loops * n):,.0f} |")


if __name__ == "__main__":
    main()
