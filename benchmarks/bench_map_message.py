"""The slam stage's per-scan message against the size of the map, on a recording of its output.

For each ``slam/state`` of RECORDING (the output of ``lrfslam pipeline``): its payload size and
its decode + encode time, and the same for the v1 message that would have carried the whole map
rebuilt at that state (every landmark, as every state did before the map travelled as changes).
Prints the means over the first and the last ``--window`` states, and what the whole maps
(``slam/map``) add per state::

    lrfslam import carmen ../shared/datasets/intel/intel.clf.bz2 -o intel.mcap
    lrfslam pipeline --replay intel.mcap --out intel_out.mcap --stages denoise,features,slam -q
    python benchmarks/bench_map_message.py intel_out.mcap
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np

from lrfslam.msgs import codec, topics
from lrfslam.msgs import types as t
from lrfslam.msgs.landmark_map import LandmarkMapReplica
from lrfslam.msgs.v1 import slam_state_pb2 as v1
from lrfslam.runtime.recording import read_recording

V1 = v1.SlamState.DESCRIPTOR.full_name


def as_v1(state: t.SlamState, lms: t.Landmarks) -> bytes:
    """``state`` as a v1 message holding the whole map ``lms``."""
    p = v1.SlamState(scan_seq=state.scan_seq, associated=state.associated, added=state.added,
                     rejected=state.rejected)
    p.header.stamp_ns, p.header.seq, p.header.frame_id = state.stamp_ns, state.seq, "map"
    p.pose.x_m, p.pose.y_m, p.pose.theta_rad = (float(v) for v in state.pose)
    p.pose_covariance.extend(state.pose_cov.ravel().tolist())
    for i in range(len(lms)):
        p.landmarks.add(id=int(lms.ids[i]), x_m=float(lms.xy_m[i, 0]), y_m=float(lms.xy_m[i, 1]),
                        covariance_m2=lms.cov_m2[i].ravel().tolist(), kind=int(lms.kind[i]),
                        sightings=int(lms.sightings[i]), confirmed=bool(lms.confirmed[i]))
    return p.SerializeToString()


def best_us(fn: Callable[[], object], repeats: int = 3) -> float:
    """The fastest of ``repeats`` calls of ``fn``, µs."""
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("recording")
    parser.add_argument("--window", type=int, default=1000, help="states at each end (default 1000)")
    args = parser.parse_args()
    replica, rows, map_bytes = LandmarkMapReplica(), [], []
    for m in read_recording(args.recording, [topics.SLAM_STATE.name, topics.SLAM_MAP.name]):
        value = topics.by_name(m.topic).codec.decode(m.data, m.schema)
        replica.apply_message(value)
        if m.topic == topics.SLAM_MAP.name:
            map_bytes.append(len(m.data))
            continue
        old = as_v1(value, replica.landmarks)
        rows.append((value.n_landmarks, len(value.landmarks), len(m.data), len(old),
                     best_us(lambda data=m.data: codec.SLAM_STATE.encode(codec.SLAM_STATE.decode(data))),
                     best_us(lambda data=old: codec.SLAM_STATE.decode(data, V1))))
    a = np.array(rows, float)
    print(f"{args.recording}: {len(a)} states, {len(map_bytes)} whole maps (mean {np.mean(map_bytes):.0f} B, "
          f"largest {max(map_bytes)} B: {sum(map_bytes) / len(a):.0f} B per state on average)")
    print("| states | landmarks (mean) | landmarks sent per state | v2 state B | v2 decode + encode µs "
          "| v1 state B | v1 decode µs |")
    print("|---|---|---|---|---|---|---|")
    for name, part in ((f"first {args.window}", a[:args.window]), (f"last {args.window}", a[-args.window:])):
        n, sent, size, size_v1, cost, cost_v1 = part.mean(axis=0)
        print(f"| {name} | {n:.0f} | {sent:.2f} | {size:.0f} | {cost:.0f} | {size_v1:.0f} | {cost_v1:.0f} |")


if __name__ == "__main__":
    main()
