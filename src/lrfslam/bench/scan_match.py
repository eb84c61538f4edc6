"""Cost of scan matching: one ICP match, and one ScanTracker step, in ms.

Three inputs: consecutive simulated LMS200 scans (181 beams, hallway loop), and
consecutive scans of the Intel Research Lab log (180 beams, cluttered) if a
recording of it is given. Reports the median time per call and the spread
(10th–90th percentile) over the scans, plus Gauss–Newton iterations:

* ``match`` — :func:`lrfslam.algo.scan_match.match` against the previous scan,
  the reference's normals built beforehand (the tracker builds them once per
  keyframe change);
* ``tracker`` — :meth:`ScanTracker.step`: the local map (recent and nearby
  keyframes, rebuilt when the set changes), the match, the bookkeeping.

Run single-threaded for stable numbers::

    OPENBLAS_NUM_THREADS=1 python -m lrfslam.bench.scan_match [--intel intel.mcap]

(``lrfslam import carmen intel.clf.bz2 -o intel.mcap`` makes the recording.) ``lrfslam bench
--only stages`` gives the tracker step on the simulated scans in its one table.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from lrfslam.algo.geometry import polar_to_xy, relative
from lrfslam.algo.scan_match import ReferenceScan, ScanMatchParams, ScanTracker, match
from lrfslam.bench.cost import ODOM_COV
from lrfslam.msgs import topics
from lrfslam.runtime.recording import read_recording
from lrfslam.sim.simulator import SimConfig, Simulator


def sim_scans(n: int):
    """Points (N, 2) and odometry increments (3,) of ``n`` consecutive simulated scans."""
    sim = Simulator(SimConfig(seed=0))
    out = []
    for frame in (next(sim) for _ in range(n)):
        out.append((polar_to_xy(frame.scan.ranges_m, frame.scan.angles_rad), frame.odom_delta))
    return out


def intel_scans(path: str, n: int):
    """The same from the first ``n`` scans of a recording (odometry differenced)."""
    out, last_pose, scans = [], None, {}
    for rec in read_recording(path, [topics.SCAN.name, topics.ODOM.name]):
        topic = topics.by_name(rec.topic)
        value = topic.codec.decode(rec.data, rec.schema)
        if topic is topics.SCAN:
            ok = np.isfinite(value.ranges_m) & (value.ranges_m < 80.0)
            scans[value.seq] = polar_to_xy(value.ranges_m[ok], value.angles_rad[ok])
        elif value.seq in scans:
            step = np.zeros(3) if last_pose is None else relative(last_pose, value.pose)
            out.append((scans.pop(value.seq), step))
            last_pose = value.pose
            if len(out) == n:
                break
    return out


def bench(scans, params: ScanMatchParams) -> dict[str, np.ndarray]:
    match_ms, tracker_ms, iterations = [], [], []
    refs = [ReferenceScan.build(p) for p, _ in scans]
    for k in range(1, len(scans)):
        t0 = time.perf_counter()
        res = match(refs[k - 1], scans[k][0], scans[k][1], params, ODOM_COV)
        match_ms.append(1e3 * (time.perf_counter() - t0))
        iterations.append(res.iterations)
    tracker = ScanTracker(params)
    for points, step in scans:
        t0 = time.perf_counter()
        tracker.step(points, step, ODOM_COV)
        tracker_ms.append(1e3 * (time.perf_counter() - t0))
    return {"match": np.array(match_ms), "tracker": np.array(tracker_ms[1:]), "iterations": np.array(iterations)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scans", type=int, default=1000, help="consecutive scans per input (default 1000)")
    parser.add_argument("--intel", metavar="FILE.mcap", help="recording of the Intel log (lrfslam import carmen)")
    args = parser.parse_args()
    params = ScanMatchParams()
    inputs = {"simulated hallway": sim_scans(args.scans)}
    if args.intel:
        inputs["Intel Research Lab"] = intel_scans(args.intel, args.scans)
    print("| input | scans | match ms (p10–p90) | tracker step ms (p10–p90) | GN iterations (median) |")
    print("|---|---|---|---|---|")
    for name, scans in inputs.items():
        r = bench(scans, params)
        m, t = r["match"], r["tracker"]
        print(f"| {name} | {len(scans)} | {np.median(m):.2f} ({np.percentile(m, 10):.2f}–{np.percentile(m, 90):.2f}) "
              f"| {np.median(t):.2f} ({np.percentile(t, 10):.2f}–{np.percentile(t, 90):.2f}) "
              f"| {np.median(r['iterations']):.0f} |")


if __name__ == "__main__":
    main()
