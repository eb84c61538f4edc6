"""The mapper stage mapping on from a saved map (``lrfslam up --map MAP``), through the pipeline's own
chain (``lrfslam.evaluation.mapping_on``): the simulator's hallway loop mapped once, then driven
again on two more days from elsewhere, each found on the map, joined to it and saved again. Ground
truth: the simulator's, in the map's frame (day 0's slam frame starts at the true pose)."""

from __future__ import annotations

import numpy as np
import pytest

from lrfslam import services
from lrfslam.evaluation.localization_sim import frame_messages
from lrfslam.evaluation.mapping_on import DAY_NS, on
from lrfslam.evaluation.mapping_on import days as run_days
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.runtime.chain import Chain
from lrfslam.sim.simulator import SimConfig, Simulator

pytestmark = pytest.mark.slow   # three days of the hallway through the whole chain: ~30 s


@pytest.fixture(scope="module")
def days():
    """Day 0 maps 1.5 laps; days 1 and 2 start 20 and 40 m along, with other noise, and map on for 1.5 laps each."""
    return run_days(3, 1.5)


def test_each_run_is_found_on_the_map_then_maps_on_it_where_the_truth_is(days):
    for day in days[1:]:
        poses, step = day.poses, day.step
        states = [p.localization for p, _ in poses]
        found = states.index(t.MAPPING)
        # Not localized first (searching the saved map), then mapping on it, never lost again.
        assert 0 < found < len(poses) / 3 and set(states[:found]) == {t.NOT_LOCALIZED}
        assert set(states[found:]) == {t.MAPPING}
        err = np.array([np.hypot(*(p.pose[:2] - true[:2])) for p, true in poses[found:]])
        assert err.max() < 0.3 and np.median(err) < 0.1, (err.max(), np.median(err))
        assert step.mapper.stats.accepted > 20 and step.counts["global_searches"] > 0


def test_the_map_grows_with_the_place_not_with_the_runs(days):
    first, second, third = (day.saved for day in days)
    step1, step2 = days[1].step, days[2].step
    k0, k1, k2 = (m.stamp_ns.size for m in (first, second, third))
    # A lap and a half over the mapped loop adds nothing: its keyframes fold into the saved ones.
    assert k1 - k0 <= 0.02 * k0 and k2 - k1 <= 0.02 * k0, (k0, k1, k2)
    for step in (step1, step2):
        made = step.mapper.keyframe_count - step.saved.stamp_ns.size
        assert step.mapper.stats.folded > 0.95 * made
    # Every saved keyframe is still in the next map, where it was (the new closures move it little).
    for before, after in ((first, second), (second, third)):
        at = {int(s): p for s, p in zip(after.stamp_ns, after.map_pose)}
        assert set(before.stamp_ns.tolist()) <= set(at)
        moved = [np.hypot(*(p[:2] - at[int(s)][:2])) for s, p in zip(before.stamp_ns, before.map_pose)]
        assert max(moved) < 0.1


def test_before_the_fix_the_grid_published_is_the_saved_maps(days):
    first, before_fix = days[0].saved, days[1].before_fix
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


def test_a_mapper_restarted_while_mapping_on_continues_exactly(days, tmp_path):
    """Stopped after the fix and started again on its checkpoint, the mapper mapping on from a saved
    map gives every output the uninterrupted one gives (the saved map, the join and the run's
    graph are all in the checkpoint)."""
    saved = days[0].saved
    sim = Simulator(SimConfig(seed=2, start_m=20.0))
    inputs = []
    stages = [services.stage(n) for n in ("denoise", "features", "slam")]
    with Chain(stages, robot="inputs", wire=False) as chain:   # the mapper's inputs: raw scans, slam states
        for _ in range(900):
            frame = next(sim)
            odom, scan = frame_messages(sim, frame, DAY_NS)
            inputs += [scan, *(m for m in chain.push(odom) + chain.push(scan) if m.topic is topics.SLAM_STATE)]

    def run(parts, checkpoint_dir=None):
        out = []
        for part in parts:
            with Chain([on(saved)], checkpoint_dir=checkpoint_dir, wire=False) as mapper:
                out += [o for m in part for o in mapper.push(m)]
                restored = mapper.step("mapper").counts.get("restored", 0)
        return out, restored

    whole, _ = run([inputs])
    cut = len(inputs) // 2
    states = [o.value.localization for o in whole if o.topic is topics.MAP_POSE]
    assert t.MAPPING in states[: cut // 2]   # the cut falls after the fix
    again, restored = run([inputs[:cut], inputs[cut:]], checkpoint_dir=tmp_path)
    assert restored == 1
    assert [(o.topic.name, o.topic.codec.encode(o.value)) for o in again] == \
        [(o.topic.name, o.topic.codec.encode(o.value)) for o in whole]


def test_a_checkpoint_taken_while_searching_a_saved_map_is_refused_by_a_mapper_without_one(days):
    from lrfslam.services.mapper import MapperConfig, MapperStep

    from lrfslam.errors import InputError

    searching = MapperStep(MapperConfig(map="(in memory)"), None, days[0].saved)
    assert searching.mapper.waiting_for_join
    with pytest.raises(InputError, match="no map"):
        MapperStep(MapperConfig(), None).restore(searching.snapshot())
