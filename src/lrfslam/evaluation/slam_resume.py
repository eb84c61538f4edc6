"""A killed slam stage, resumed from its checkpoint: how far from the truth, against its own uncertainty.

    python -m lrfslam.evaluation.slam_resume [--seed 5] [--scans 1200] [--kills 12]

What ``lrfslam up`` does when the slam process dies, in one process and without the clock: the
simulator's stream (the sensor service's messages) goes through the denoise and features steps
once; then, per kill, a slam step with a real checkpoint file (every 5 s of data time: 50 scans) takes the stream
until its state ``kill`` (drawn from 400–449), is dropped without closing (SIGKILL: no final
checkpoint), and a new slam step resumes from the file and takes the stream again from ``down``
scans (drawn from 60–159) after the kill. Printed per kill: the resumed filter's position NEES
right after the bridge and its largest over the rest of the run (2 if consistent; 13.8 is the
99.9 % bound), and the final position error against the filter's own final 1 σ (cm).
``docs/operations.md`` ("A killed slam") holds the figures.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lrfslam.algo.geometry import compose, inverse
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.runtime.chain import Chain
from lrfslam.runtime.step import Message
from lrfslam.services import build_step, stage


@dataclass(frozen=True)
class Resumed:
    """One kill. NEES of the position (x, y) against the state's own covariance; lengths in cm."""

    kill: int
    down_scans: int
    nees_after_bridge: float
    nees_max: float
    final_cm: float
    sigma_cm: float


def sim_stream(seed: int, scans: int) -> list[Message]:
    """The sensor service's messages for ``scans`` simulated frames, each scan followed by its features."""
    sensor = build_step("sensor", sets=["source=sim", "speedup=0", f"seed={seed}"])
    front = Chain([stage("denoise"), stage("features")])
    stream: list[Message] = []
    n_scans = 0
    while n_scans < scans:
        for out in sensor.poll(1.0):
            stream.append(Message.of(out))
            if out.topic is topics.SCAN:
                n_scans += 1
                stream += [m for m in front.push(stream[-1]) if m.topic is topics.FEATURES]
    return stream


def _states(outs: list[Message]) -> list[t.SlamState]:
    return [m.value for m in outs if m.topic is topics.SLAM_STATE]


def resume_once(stream: list[Message], kill: int, down_scans: int, folder: Path) -> Resumed:
    """Kill the slam at its state ``kill``, restart it ``down_scans`` scans later."""
    truth = {m.stamp_ns: m.value.pose for m in stream if m.topic is topics.TRUTH}
    scan_period_ns = int(np.diff([m.stamp_ns for m in stream if m.topic is topics.SCAN][:2])[0])
    slam = [stage("slam")]
    folder = folder / f"{kill}_{down_scans}"
    inputs = [m for m in stream if m.topic is not topics.TRUTH]
    first, before, i = Chain(slam, checkpoint_dir=folder), [], 0
    while len(before) < kill:
        before += _states(first.push(inputs[i]))
        i += 1
    back_ns = before[-1].stamp_ns + down_scans * scan_period_ns
    with Chain(slam, checkpoint_dir=folder) as second:
        after = _states(list(second.feed(m for m in inputs[i:] if m.stamp_ns >= back_ns)))
    # SLAM's map frame is its first pose: the truth in it, as lrfslam up scores a run.
    anchor = compose(truth[before[0].stamp_ns], inverse(before[0].pose))
    errors = [compose(anchor, s.pose)[:2] - truth[s.stamp_ns][:2] for s in after]
    nees = [float(e @ np.linalg.solve(s.pose_cov[:2, :2], e)) for e, s in zip(errors, after, strict=True)]
    sigma = float(np.sqrt(np.linalg.eigvalsh(after[-1].pose_cov[:2, :2]).max()))
    return Resumed(kill, down_scans, nees[0], max(nees), 100 * float(np.hypot(*errors[-1])), 100 * sigma)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m lrfslam.evaluation.slam_resume", description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=5, help="simulator seed (the supervision test's: 5)")
    ap.add_argument("--scans", type=int, default=1200)
    ap.add_argument("--kills", type=int, default=12)
    args = ap.parse_args(argv)
    stream = sim_stream(args.seed, args.scans)
    rng = np.random.default_rng(0)
    print("| kill at state | scans down | NEES after the bridge | NEES max | final cm | 1-sigma cm | final / sigma |")
    print("|---|---|---|---|---|---|---|")
    ratios = []
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(args.kills):
            r = resume_once(stream, int(rng.integers(400, 450)), int(rng.integers(60, 160)), Path(tmp))
            ratios.append(r.final_cm / r.sigma_cm)
            print(f"| {r.kill} | {r.down_scans} | {r.nees_after_bridge:.1f} | {r.nees_max:.1f} | {r.final_cm:.2f} "
                  f"| {r.sigma_cm:.2f} | {ratios[-1]:.2f} |", flush=True)
    print(f"largest final / sigma {max(ratios):.2f}; beyond 3 sigma: {sum(x > 3 for x in ratios)} of {len(ratios)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
