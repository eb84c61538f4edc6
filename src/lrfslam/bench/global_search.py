"""What a localizer's global search costs on a saved map: queries from the map's own keyframes.

    OPENBLAS_NUM_THREADS=1 python -m lrfslam.bench.global_search MAP/ [--queries 16] [--seed 0]

MAP/ is a saved map (``lrfslam map save`` or ``lrfslam up --save-map``). A Killian-sized one:
``lrfslam eval relations --all DIR --work W`` leaves MIT Killian's run in
``W/mit-killian/mit-killian.run.mcap``; ``lrfslam map save`` that ``-o MAP/``.

Each query is built as the localizer builds one (:class:`lrfslam.algo.localization.Localizer`):
the scans of the last :data:`~lrfslam.algo.localization.QUERY_TRAVEL_M` of travel — here the
keyframes before a randomly drawn one — merged in the drawn keyframe's frame and thinned. Each is
searched for over the whole map, as before the first fix, and timed (wall clock, one thread).
Prints one line per query (time, score, second peak, how far the best pose lies from the drawn
keyframe) and the times' median and maximum. Timing lives here, not in the tests.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from lrfslam.algo import correlative_match as cm
from lrfslam.algo import localization as loc
from lrfslam.algo.geometry import from_frame, relative
from lrfslam.runtime.saved_map import load_map


def query_before(poses: np.ndarray, points: list[np.ndarray], k: int) -> np.ndarray:
    """The localizer's query at keyframe ``k``: the keyframes over the travel before it, merged in
    its frame (M, 2), thinned as the localizer thins (m)."""
    first, travel = k, 0.0
    while first > 0 and travel < loc.QUERY_TRAVEL_M:
        travel += float(np.hypot(*(poses[first, :2] - poses[first - 1, :2])))
        first -= 1
    merged = np.vstack([from_frame(points[i], relative(poses[k], poses[i])) for i in range(first, k + 1)])
    return loc.query_of(merged[np.hypot(merged[:, 0], merged[:, 1]) <= loc.QUERY_TRAVEL_M + loc.MAX_RANGE_M])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("map", help="a saved map folder")
    parser.add_argument("--queries", type=int, default=16)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    saved = load_map(args.map)
    poses = saved.map_pose
    points = [saved.keyframe_points(k) for k in range(poses.shape[0])]
    t0 = time.perf_counter()
    place = loc.LocalizationMap(poses, points, loc.Walls(saved.grid_cells, saved.grid_resolution_m,
                                                         saved.grid_origin_xy_m))
    side = 2 * place.half_width_m
    print(f"{args.map}: {poses.shape[0]} keyframes; search window {side:.0f} × {side:.0f} m, "
          f"{place.grid.params.levels} levels; made ready in {time.perf_counter() - t0:.1f} s")
    rng = np.random.default_rng(args.seed)
    drawn = rng.choice(np.arange(1, poses.shape[0]), size=min(args.queries, poses.shape[0] - 1), replace=False)
    times = []
    for k in drawn:
        query = query_before(poses, points, int(k))
        t0 = time.perf_counter()
        found = cm.search(place.grid, query, place.centre, place.half_width_m, np.pi, loc.MIN_SCORE,
                          loc.MAX_FRONTIER, loc.GREEDY_STARTS, loc.MAX_SECOND_RATIO, where=place.free)
        times.append(time.perf_counter() - t0)
        off = float(np.hypot(*(found.pose[:2] - poses[k, :2]))) if found.score else float("nan")
        print(f"keyframe {k:5d}: {times[-1]:6.2f} s, {query.shape[0]} points, score {found.score:.3f}, "
              f"second {found.second_score:.3f}, best {off:.2f} m from the keyframe, exact {found.exact}")
    print(f"{len(times)} searches: median {np.median(times):.2f} s, max {max(times):.2f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
