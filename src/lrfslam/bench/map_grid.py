"""What the live grid costs as the map grows: the mapper step on a recording, its grid's share timed.

    OPENBLAS_NUM_THREADS=1 python -m lrfslam.bench.map_grid RUN.mcap [--slices 10]

RUN.mcap holds a log's ``scan`` and ``slam/state`` (a pipeline output: ``lrfslam pipeline --replay
LOG.mcap --out RUN.mcap``). The mapper step (services/mapper.py) takes them in order, as in every
replay; the grid's part of each step (``lrfslam.algo.keyframe_grid`` and the tiles' message, not
its encoding) is timed with ``time.process_time`` apart from the rest. Prints, per slice of the
run: scans, keyframes laid, the moved ones waiting and how far the farthest of them is from its
pose in the graph, the grid's resolution, tiles and memory, the
tiles published and their bytes (encoded, zlib), and CPU ms per scan of the mapper step and of the
grid within it (mean and the slice's worst scan). Timing lives here, not in the tests.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from lrfslam.algo.keyframe_grid import KeyframeGrid
from lrfslam.msgs import topics
from lrfslam.runtime.recording import read_recording
from lrfslam.runtime.step import Message
from lrfslam.services import build_step

spent = {"grid": 0.0}


def _timed(cls, name: str) -> None:
    inner = getattr(cls, name)

    def timed(*args, **kwargs):
        t0 = time.process_time()
        try:
            return inner(*args, **kwargs)
        finally:
            spent["grid"] += time.process_time() - t0
    setattr(cls, name, timed)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recording", type=Path)
    ap.add_argument("--slices", type=int, default=10)
    args = ap.parse_args(argv)
    step = build_step("mapper")
    for name in ("add_scan", "add_keyframe", "set_poses", "work"):
        _timed(KeyframeGrid, name)
    _timed(type(step), "_grid_changes")
    wanted = [topics.SCAN.name, topics.SLAM_STATE.name]
    total = sum(1 for m in read_recording(args.recording, [topics.SLAM_STATE.name]))
    per_slice = max(1, -(-total // args.slices))
    print(f"{args.recording}: {total} scans, slices of {per_slice}")
    print("| scans | keyframes | waiting | farthest waiting m | resolution m | tiles | grid MB | tiles sent "
          "| sent kB | mapper ms/scan | grid ms/scan | grid worst ms |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    states = 0
    mapper_s = grid_s = worst = 0.0
    sent_tiles = sent_bytes = 0
    for m in read_recording(args.recording, wanted):
        topic = topics.by_name(m.topic)
        value = topic.codec.decode(m.data, m.schema)
        spent["grid"] = 0.0
        t0 = time.process_time()
        outs = list(step.on_message(Message(topic, value, value.stamp_ns, m.schema, m.topic, value.seq)))
        mapper_s += time.process_time() - t0
        grid_s += spent["grid"]
        worst = max(worst, spent["grid"])
        for out in outs:
            if out.topic is topics.MAP_GRID:
                sent_tiles += out.value.tiles.shape[0]
                sent_bytes += len(out.topic.codec.encode(out.value))
        if topic is topics.SLAM_STATE:
            states += 1
            if states % per_slice == 0 or states == total:
                grid = step.grid.grid
                n = states % per_slice or per_slice
                print(f"| {states} | {step.grid.keyframes} | {step.grid.pending} | {step.grid.largest_pending_m:.3f} "
                      f"| {grid.resolution_m:g} "
                      f"| {len(grid.tiles())} | {grid.nbytes / 1e6:.1f} | {sent_tiles} | {sent_bytes / 1e3:.0f} "
                      f"| {1e3 * mapper_s / n:.2f} | {1e3 * grid_s / n:.2f} | {1e3 * worst:.1f} |", flush=True)
                mapper_s = grid_s = worst = 0.0
                sent_tiles = sent_bytes = 0
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
