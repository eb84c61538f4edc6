"""CPU time per scan of each stage of ``lrfslam pipeline --replay``, in one process.

    OPENBLAS_NUM_THREADS=1 python -m lrfslam.bench.stages RECORDING [--stages denoise,features,slam,mapper]

Runs the stages as ``lrfslam pipeline --replay RECORDING`` does (no output file) and charges
``time.process_time`` to each stage's steps and, separately, to encoding (and decoding for the
later stages) their outputs (``codec``); the rest (reading the recording) is the total's
remainder. Process CPU time, not wall time, so other work on the machine inflates the figures
less; compare before and after in the same run (two checkouts side by side). Per-function
figures: ``python -m cProfile -o run.prof -m lrfslam.cli pipeline --replay RECORDING -q``.
docs/delivery.md ("Where the time goes") holds the figures. Timing lives here, not in the tests.
"""

from __future__ import annotations

import argparse
import time
from collections import Counter
from pathlib import Path

from lrfslam.msgs import counters
from lrfslam.runtime import chain
from lrfslam.tools.pipeline import (
    DEFAULT_STAGES,
    build_stages,
    run_pipeline,
    stage_names,
)

spent: Counter[str] = Counter()
_through, _item = chain.Chain._through, chain.Chain._item


def _timed_through(self, i, lk, stream):
    t0 = time.process_time()
    out = _through(self, i, lk, stream)
    spent[lk.name] += time.process_time() - t0
    return out


def _timed_item(self, i, out):
    t0 = time.process_time()
    item = _item(self, i, out)
    dt = time.process_time() - t0
    spent["codec"] += dt
    spent[self._links[i].name] -= dt   # inside that stage's _through
    return item


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("recording", type=Path)
    parser.add_argument("--stages", default=",".join(DEFAULT_STAGES))
    args = parser.parse_args()
    stages = build_stages(stage_names(args.stages), [], {}, {})
    chain.Chain._through, chain.Chain._item = _timed_through, _timed_item
    t0 = time.process_time()
    counts = run_pipeline(stages, "bench", [args.recording], None)
    total = time.process_time() - t0
    scans = max(c for name, c in counts[stages[0].spec.name].items() if name.startswith(counters.IN))
    print(f"{scans} scans, {args.stages}")
    print("| stage | ms CPU / scan | share |")
    print("|---|---|---|")
    for name in [*(s.spec.name for s in stages), "codec"]:
        print(f"| {name} | {1e3 * spent[name] / scans:.3f} | {100 * spent[name] / total:.1f} % |")
    rest = total - sum(spent.values())
    print(f"| reading the recording, the rest | {1e3 * rest / scans:.3f} | {100 * rest / total:.1f} % |")
    print(f"| total | {1e3 * total / scans:.3f} | |")


if __name__ == "__main__":
    main()
