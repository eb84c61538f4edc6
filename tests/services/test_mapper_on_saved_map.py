"""The mapper stage mapping on from a saved map (``lrfslam up --map MAP``), through the pipeline's own
chain: the simulator's hallway loop mapped once, then driven again twice from elsewhere, each run
found on the map, joined to it and saved again. Ground truth: the simulator's, in the map's frame
(the mapping run's slam frame starts at the true pose, so the two are one)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from lrfslam.services.mapper import MapperConfig, MapperStep
from lrfslam.services.sensor import frame_outputs

from lrfslam import services
from lrfslam.evaluation.localization_sim import MapTaker, chain_with
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.msgs.grid_replica import GridReplica
from lrfslam.runtime.chain import Stage
from lrfslam.runtime.step import Message
from lrfslam.sim.simulator import SimConfig, Simulator

pytestmark = pytest.mark.slow   # three days of the hallway through the whole chain: ~30 s

LAP_M = 62.0
#: Each run's stamps start this much after the last one's (ns): another day's data.
DAY_NS = 86_400 * 10**9


def drive(mapper: Stage, metres: float, seed: int, start_m: float, day: int, saved=None):
    """``metres`` of the hallway loop from ``start_m`` through denoise → features → slam → ``mapper``:
    (every map/pose with its true pose, the saved map the run leaves, the mapper's step, the grid
    the mapper published before the robot was found on the map)."""
    sim = Simulator(SimConfig(seed=seed, start_m=start_m))
    taker, before_fix = MapTaker(), GridReplica()
    if saved is not None:   # the saved map's keyframes keep their scans in the map (lrfslam map save --base)
        taker.scans.update({int(s): saved.keyframe_points(k) for k, s in enumerate(saved.stamp_ns)})
    poses = []
    with chain_with(mapper, f"day{day}") as chain:
        if saved is None:
            chain.step("slam").slam.start_at(sim.trajectory.pose(0))
        step = chain.step("mapper")
        for _ in range(int(metres / sim.config.speed_mps * sim.config.rate_hz)):
            frame = next(sim)
            odom, scan = (Message.of(o) for o in frame_outputs(frame, day * DAY_NS + round(frame.t_s * 1e9), sim))
            outs = chain.push(odom) + chain.push(scan)
            taker.take([scan, *outs])
            poses += [(m.value, frame.true_pose) for m in outs if m.topic is topics.MAP_POSE]
            if not poses or poses[-1][0].localization == t.NOT_LOCALIZED:
                for m in outs:
                    if m.topic is topics.MAP_GRID:
                        before_fix.apply(m.value)
        taker.take([it.msg for it in chain.finish_items()])
    return poses, taker.saved(), step, before_fix


def on(saved) -> Stage:
    spec = replace(services.spec("mapper"), build=lambda cfg, ctx: MapperStep(cfg, ctx, saved))
    return Stage(spec, MapperConfig(map="(in memory)"))


@pytest.fixture(scope="module")
def days():
    """Day 0 maps 1.3 laps; days 1 and 2 start 20 and 40 m along, other noise, and map on for 1.5 laps each."""
    _, first, _, _ = drive(services.stage("mapper"), 1.3 * LAP_M, seed=1, start_m=0.0, day=0)
    day1 = drive(on(first), 1.5 * LAP_M, seed=2, start_m=20.0, day=1, saved=first)
    day2 = drive(on(day1[1]), 1.5 * LAP_M, seed=3, start_m=40.0, day=2, saved=day1[1])
    return first, day1, day2


def test_each_run_is_found_on_the_map_then_maps_on_it_where_the_truth_is(days):
    for poses, _, step, _ in days[1:]:
        states = [p.localization for p, _ in poses]
        found = states.index(t.MAPPING)
        # Not localized first (searching the saved map), then mapping on it, never lost again.
        assert 0 < found < len(poses) / 3 and set(states[:found]) == {t.NOT_LOCALIZED}
        assert set(states[found:]) == {t.MAPPING}
        err = np.array([np.hypot(*(p.pose[:2] - true[:2])) for p, true in poses[found:]])
        assert err.max() < 0.3 and np.median(err) < 0.1, (err.max(), np.median(err))
        assert step.mapper.stats.accepted > 20 and step.counts["global_searches"] > 0


def test_the_map_grows_with_the_place_not_with_the_runs(days):
    first, (_, second, step1, _), (_, third, step2, _) = days
    k0, k1, k2 = (m.stamp_ns.size for m in (first, second, third))
    # A lap and a half over the mapped loop adds little: its revisits fold into the saved keyframes.
    assert k1 - k0 < 0.25 * k0 and k2 - k1 < 0.25 * k0, (k0, k1, k2)
    for step in (step1, step2):
        made = step.mapper.keyframe_count - step.saved.stamp_ns.size
        assert step.mapper.stats.folded > 0.6 * made
    # Every saved keyframe is still in the next map, where it was (the new closures move it little).
    for before, after in ((first, second), (second, third)):
        at = {int(s): p for s, p in zip(after.stamp_ns, after.map_pose)}
        assert set(before.stamp_ns.tolist()) <= set(at)
        moved = [np.hypot(*(p[:2] - at[int(s)][:2])) for s, p in zip(before.stamp_ns, before.map_pose)]
        assert max(moved) < 0.1


def test_before_the_fix_the_grid_published_is_the_saved_maps(days):
    first, (_, _, _, before_fix), _ = days
    image = before_fix.image()
    assert image is not None and image.resolution_m == first.grid_resolution_m
    # The saved map's walls, cell by cell, on the grid the viewers got while the robot was searched for.
    rows, cols = np.nonzero(first.grid_cells == 100)
    xy = first.grid_origin_xy_m + (np.column_stack((cols, rows)) + 0.5) * first.grid_resolution_m
    at = np.floor((xy - image.origin_xy_m) / image.resolution_m).astype(int)
    inside = (at >= 0).all(axis=1) & (at[:, 0] < image.cells.shape[1]) & (at[:, 1] < image.cells.shape[0])
    walls = np.zeros(len(xy), bool)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            r = np.clip(at[:, 1] + dr, 0, image.cells.shape[0] - 1)
            c = np.clip(at[:, 0] + dc, 0, image.cells.shape[1] - 1)
            walls |= inside & (image.cells[r, c] == 100)
    assert walls.mean() > 0.95, walls.mean()
