"""The slam stage's per-scan message against the size of the map, on a recording of its output.

Mean size and decode + encode of ``slam/state`` over the first and the last ``--window`` states
of RECORDING, beside the v1 message that carried the whole map with every state (the rows
``lrfslam bench --only logs`` prints for every log it plays)::

    lrfslam import carmen ../shared/datasets/intel/intel.clf.bz2 -o intel.mcap
    lrfslam pipeline --replay intel.mcap --out intel_out.mcap --stages denoise,features,slam -q
    python -m lrfslam.bench.map_message intel_out.mcap
"""

from __future__ import annotations

import argparse
from pathlib import Path

from lrfslam.bench.command import machine, table
from lrfslam.bench.cost import state_rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("recording", type=Path)
    parser.add_argument("--window", type=int, default=1000, help="states at each end (default 1000)")
    parser.add_argument("--repeat", type=int, default=3, help="calls per message, the fastest kept (default 3)")
    args = parser.parse_args()
    print(table(machine(), state_rows(args.recording.stem, args.recording, args.window, args.repeat)))


if __name__ == "__main__":
    main()
