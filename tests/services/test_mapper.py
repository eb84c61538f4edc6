"""The mapper step: slam states placed with their scans on the local trajectory, map/pose per
state, map/keyframes that reproduce the mapper's own final trajectory from a recording, and the
live grid (map/grid) that ends as the grid of the graph's keyframes."""

from __future__ import annotations

import numpy as np
import pytest
from lrfslam.services import build_step, stage

from lrfslam.algo.geometry import compose, relative
from lrfslam.algo.loop_closure import LoopClosingMapper
from lrfslam.algo.occupancy_grid import OCCUPIED, GridParams, build_grid
from lrfslam.errors import ConfigError
from lrfslam.evaluation.map_trajectory import KeyframeHistory, final_poses
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.msgs.grid_replica import GridReplica
from lrfslam.runtime import checkpoints
from lrfslam.runtime.chain import Chain
from lrfslam.runtime.step import Message, Output
from lrfslam.sim.simulator import OdometryNoise, SimConfig, Simulator

msg = Message.of


#: Where the 'filter' of :func:`drifting_loop` corrects itself: its pose jumps by this much.
JUMP = np.array([0.3, -0.2, 0.05])


def drifting_loop(n: int, with_motion: bool = True):
    """(scan, slam state, true pose) per frame of the hallway loop.

    The states' motions are drifting odometry's increments; their poses are that odometry
    with a jump (:data:`JUMP`, as an EKF correcting itself) every 97 frames.
    """
    cfg = SimConfig(speed_mps=1.0, rate_hz=5.0, seed=3,
                    odometry=OdometryNoise(trans_sigma_per_sqrt_m=0.02, rot_sigma_per_sqrt_rad=0.03, rot_sigma_per_sqrt_m=0.02))
    lidar = cfg.lidar
    out = []
    previous, jumps = None, np.zeros(3)
    for frame, _ in zip(Simulator(cfg), range(n), strict=False):
        stamp, seq = round(frame.t_s * 1e9), frame.index + 1
        scan = t.LaserScan.from_ranges(stamp, seq, frame.scan.ranges_m, lidar.angle_min_rad,
                                       lidar.angle_increment_rad, lidar.max_range_m)
        motion = np.zeros(3) if previous is None else relative(previous, frame.odom_pose)
        previous = frame.odom_pose
        if frame.index % 97 == 50:
            jumps = compose(jumps, JUMP)
        state = t.SlamState(stamp_ns=stamp, seq=seq, scan_seq=seq, pose=compose(jumps, frame.odom_pose),
                            pose_cov=np.eye(3) * 1e-4,
                            motion=motion if with_motion else None)
        out.append((scan, state, frame))
    return out


@pytest.fixture(scope="module")
def mapped():
    frames = drifting_loop(620)   # two laps of the 62 m loop
    step = build_step("mapper")
    # The service's mapper keeps no per-scan history; this one does, for trajectory().
    step.mapper = LoopClosingMapper(step.mapper.params)
    outs = []
    for scan, state, _ in frames:
        outs += step.on_message(msg(Output(topics.SCAN, scan)))
        outs += step.on_message(msg(Output(topics.SLAM_STATE, state)))
    outs += step.finish()
    return frames, step, outs


def every_keyframe(outs) -> t.MapKeyframes:
    """Every keyframe the map/keyframes messages among ``outs`` told of, as a recording's reader keeps them."""
    history = KeyframeHistory()
    for o in outs:
        if o.topic is topics.MAP_KEYFRAMES:
            history.add(o.topic.codec.decode(o.topic.codec.encode(o.value)))
    return history.keyframes()


def test_every_state_gets_a_map_pose_and_the_closures_are_published(mapped):
    frames, step, outs = mapped
    poses = [o.value for o in outs if o.topic is topics.MAP_POSE]
    assert [p.scan_seq for p in poses] == [s.scan_seq for _, s, _ in frames]
    for p, (_, state, frame) in zip(poses, frames, strict=True):
        np.testing.assert_allclose(compose(p.map_from_slam, state.pose), p.pose, atol=1e-9)
        # The local trajectory is the chain of the motions (the odometry here), not the jumping poses.
        np.testing.assert_allclose(p.local_pose, frame.odom_pose, atol=1e-6)
    assert poses[-1].closures >= 5 and step.counts.get("scan_missing", 0) == 0
    assert sum(o.topic is topics.MAP_KEYFRAMES for o in outs) >= 2   # after optimisations, and at the end
    verified, nis_sum = step.mapper.closure_nis
    assert step.counts["closures_verified"] == verified >= step.mapper.stats.accepted
    assert 0 < nis_sum < 10 * verified and step.counts["closure_nis_milli"] == round(1000 * nis_sum)


def test_the_last_keyframes_reproduce_the_mappers_final_trajectory(mapped):
    frames, step, outs = mapped
    stamps = np.array([s.stamp_ns for _, s, _ in frames])
    local = np.array([o.value.local_pose for o in outs if o.topic is topics.MAP_POSE])
    # Keyframes were retired from the graph (folded revisits): the last message alone is not all of them.
    assert step.counts["keyframes_retired"] > 0
    assert step.mapper.graph_keyframes < step.mapper.keyframe_count
    from_recording = final_poses(stamps, local, every_keyframe(outs))
    own_stamps, own = step.mapper.trajectory()
    np.testing.assert_array_equal(own_stamps, stamps)
    np.testing.assert_allclose(from_recording, own, atol=1e-9)
    # The service's own mapper, which keeps no per-scan history, publishes the same messages.
    service = build_step("mapper")
    again = [o for scan, state, _ in frames for o in (list(service.on_message(msg(Output(topics.SCAN, scan))))
                                                      + list(service.on_message(msg(Output(topics.SLAM_STATE, state)))))]
    again += service.finish()
    assert [(o.topic, o.topic.codec.encode(o.value)) for o in again] == \
        [(o.topic, o.topic.codec.encode(o.value)) for o in outs]
    with pytest.raises(ConfigError):
        service.mapper.trajectory()
    # And it is better than the drifting input, against the truth.
    truth = np.array([f.true_pose for _, _, f in frames])
    drift = np.hypot(*(np.array([s.pose for _, s, _ in frames])[:, :2] - truth[:, :2]).T)
    final = np.hypot(*(own[:, :2] - truth[:, :2]).T)
    assert drift.max() > 1.0 and final.max() < 0.5 * drift.max()


#: Of the live grid's occupied cells at the end, at least this fraction lie within one cell of an
#: occupied cell of the grid export draws from the same keyframes (and the other way round); the
#: rest are keyframes an optimisation moved by under a quarter of a cell, which stay where they lie.
GRID_AGREEMENT = 0.99


def occupied_near(cells: np.ndarray, origin: np.ndarray, res: float, other: np.ndarray, other_origin: np.ndarray):
    """Fraction of ``cells``' occupied cells (H, W int8, lower-left corner ``origin``) within one cell of
    an occupied cell of ``other`` (same resolution ``res``)."""
    rows, cols = np.nonzero(cells == OCCUPIED)
    at = np.floor((origin + res * (np.column_stack((cols, rows)) + 0.5) - other_origin) / res).astype(int)
    near = np.zeros(rows.size, bool)
    h, w = other.shape
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            r, c = at[:, 1] + dr, at[:, 0] + dc
            inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
            near[inside] |= other[r[inside], c[inside]] == OCCUPIED
    return float(near.mean())


def test_the_live_grid_ends_as_the_grid_of_the_graphs_keyframes(mapped):
    frames, step, outs = mapped
    grids = [topics.MAP_GRID.codec.decode(topics.MAP_GRID.codec.encode(o.value))
             for o in outs if o.topic is topics.MAP_GRID]
    stamps = np.array([g.stamp_ns for g in grids])
    assert len(grids) > 10 and np.all(np.diff(stamps[:-1]) >= 1_000_000_000)   # once a second of data at most
    replica = GridReplica()
    for g in grids:
        replica.apply(g)
    assert replica.pending == 0 and replica.keyframes == step.mapper.graph_keyframes
    # What export draws: the scans of the last map/keyframes at their poses.
    graph = [o.value for o in outs if o.topic is topics.MAP_KEYFRAMES][-1]
    scan_at = {s.stamp_ns: s for s, _, _ in frames}
    kf_scans = [scan_at[int(s)] for s in graph.scan_stamp_ns]
    want = build_grid(graph.map_pose, np.array([s.grid_ranges() for s in kf_scans]), kf_scans[0].angles_rad,
                      GridParams(), fit=True)
    live = replica.image()
    assert live.resolution_m == want.resolution_m
    exported = want.trinary()
    assert occupied_near(live.cells, live.origin_xy_m, live.resolution_m, exported, want.origin_xy_m) >= GRID_AGREEMENT
    assert occupied_near(exported, want.origin_xy_m, live.resolution_m, live.cells, live.origin_xy_m) >= GRID_AGREEMENT
    # A late joiner asks for the whole grid: the same tiles.
    whole = step.latest(topics.MAP_GRID)
    assert whole.whole and sorted(map(tuple, whole.tiles.tolist())) == sorted(replica.tiles)
    for tile, cells in zip(whole.tiles.tolist(), whole.cells):
        np.testing.assert_array_equal(cells, replica.tiles[tuple(tile)])


def test_a_state_waits_for_its_scan_and_one_without_a_scan_is_placed_when_a_newer_scan_comes():
    frames = drifting_loop(6)
    step = build_step("mapper")
    (scan1, state1, _), (_, state2, _), (scan3, state3, _) = frames[:3]   # scan 2 is lost
    assert list(step.on_message(msg(Output(topics.SLAM_STATE, state1)))) == []   # its scan is not there yet
    placed = step.on_message(msg(Output(topics.SCAN, scan1)))
    assert [o.value.scan_seq for o in placed if o.topic is topics.MAP_POSE] == [1]
    # scan 2 is lost: its state is placed once scan 3 shows it will not come.
    assert list(step.on_message(msg(Output(topics.SLAM_STATE, state2)))) == []
    placed = step.on_message(msg(Output(topics.SCAN, scan3)))
    assert [o.value.scan_seq for o in placed if o.topic is topics.MAP_POSE] == [2]
    assert step.counts["scan_missing"] == 1
    placed = step.on_message(msg(Output(topics.SLAM_STATE, state3)))
    assert [o.value.scan_seq for o in placed if o.topic is topics.MAP_POSE] == [3]


def test_the_slam_poses_are_the_local_trajectory_when_states_carry_no_motion():
    # States recorded before they carried their motion follow the filter's pose, jumps included.
    frames = drifting_loop(120, with_motion=False)
    step = build_step("mapper")
    outs = []
    for scan, state, _ in frames:
        outs += step.on_message(msg(Output(topics.SCAN, scan)))
        outs += step.on_message(msg(Output(topics.SLAM_STATE, state)))
    local = np.array([o.value.local_pose for o in outs if o.topic is topics.MAP_POSE])
    np.testing.assert_allclose(local, np.array([s.pose for _, s, _ in frames]), atol=1e-6)
    assert step.counts["motion_missing"] == len(frames) - 1


def frame_messages(frames) -> list[list[Message]]:
    """Per frame, its scan's and its state's messages."""
    return [[msg(Output(topics.SCAN, scan)), msg(Output(topics.SLAM_STATE, state))] for scan, state, _ in frames]


def encoded(messages) -> list[tuple[str, bytes]]:
    return [(m.topic.name, m.topic.codec.encode(m.value)) for m in messages]


@pytest.mark.slow   # end to end, long: the slow step (.ci/run step 3)
def test_a_restarted_mapper_continues_its_graph_exactly(mapped, tmp_path):
    frames, _, outs = mapped
    per_frame = frame_messages(frames)
    live = [stage("mapper")]
    cut = 400   # in the second lap: closures before and after
    with Chain(live, checkpoint_dir=tmp_path) as first:
        head = [o for pair in per_frame[:cut] for x in pair for o in first.push(x)]
        before = first.step("mapper").mapper.stats
    assert 0 < before.accepted and first.step("mapper").counts["checkpoints"] >= 2
    with Chain(live, checkpoint_dir=tmp_path) as second:
        step = second.step("mapper")
        assert step.counts["restored"] == 1 and step.mapper.keyframe_count == first.step("mapper").mapper.keyframe_count
        tail = [o for pair in per_frame[cut:] for x in pair for o in second.push(x)] + list(second.feed([]))
    # Stopped and started again (close() saved where it stood): every output as if never stopped.
    assert encoded(head + tail) == encoded(Message.of(o) for o in outs)
    assert step.mapper.stats.accepted > before.accepted and step.counts.get("motion_bridged", 0) == 0


@pytest.mark.slow   # end to end, long: the slow step (.ci/run step 3)
def test_a_killed_mapper_resumes_from_its_checkpoint_and_bridges_the_states_it_missed(mapped, tmp_path):
    frames, _, outs = mapped
    per_frame = frame_messages(frames)
    live = [stage("mapper")]
    killed, back = 420, 450   # down for 6 s, through one of the 'filter's jumps (frame 438)
    first = Chain(live, checkpoint_dir=tmp_path)   # never closed: killed, its last periodic checkpoint stays
    for pair in per_frame[:killed]:
        for x in pair:
            first.push(x)
    saved = first.step("mapper").counts["checkpoints"]
    with Chain(live, checkpoint_dir=tmp_path) as second:
        step = second.step("mapper")
        assert step.counts["restored"] == 1 and saved >= 1
        resumed_at = step.mapper.keyframe_count
        tail = [o for pair in per_frame[back:] for x in pair for o in second.push(x)] + list(second.feed([]))
    assert step.counts["motion_bridged"] == 1 and step.mapper.keyframe_count > resumed_at
    poses = [o.value for o in tail if o.topic is topics.MAP_POSE]
    assert [p.scan_seq for p in poses] == [s.scan_seq for _, s, _ in frames[back:]]
    # The jump the filter made while the mapper was down is not taken for motion: the resumed
    # graph stays as close to the truth as the uninterrupted one (its frames after the gap).
    truth = np.array([f.true_pose for _, _, f in frames])
    whole = final_poses(np.array([s.stamp_ns for _, s, _ in frames]),
                        np.array([o.value.local_pose for o in outs if o.topic is topics.MAP_POSE]),
                        every_keyframe(outs))
    resumed = final_poses(np.array([s.stamp_ns for _, s, _ in frames[back:]]),
                          np.array([p.local_pose for p in poses]),
                          every_keyframe(tail))
    # Both in the map frame of the first keyframe, placed on the truth by the first frame.
    to_truth = compose(truth[0], relative(whole[0], np.zeros(3)))

    def error_m(poses_: np.ndarray) -> float:
        placed = np.array([compose(to_truth, p) for p in poses_])
        return float(np.mean(np.hypot(*(placed[:, :2] - truth[back:, :2]).T)))
    assert error_m(resumed) < 1.5 * error_m(whole[back:]) + 0.05


def test_an_unreadable_mapper_checkpoint_is_counted_and_a_new_graph_started(tmp_path):
    ckpt = checkpoints.path_for(tmp_path, "mapper")
    ckpt.write_bytes(b"not a checkpoint")
    with Chain([stage("mapper")], checkpoint_dir=tmp_path) as chain:
        step = chain.step("mapper")
        assert step.counts["checkpoint_unreadable"] == 1 and step.mapper.keyframe_count == 0
    assert ckpt.read_bytes() == b"not a checkpoint"   # nothing to save: the file is left as it was


def test_a_scan_that_makes_a_keyframe_is_answered_before_the_keyframe_work():
    """Live, the runner puts each output as the step yields it: ``map/pose`` must come before the keyframe's
    closure search and optimisation, at the pose the graph gave before that work, and the next scan's pose
    carries what it found."""
    frames = drifting_loop(620)
    step = build_step("mapper")
    answered_first = 0
    for scan, state, _ in frames:
        list(step.on_message(msg(Output(topics.SCAN, scan))))
        made = step.mapper.keyframe_count
        outs = step.on_message(msg(Output(topics.SLAM_STATE, state)))
        first = next(iter(outs))
        assert first.topic is topics.MAP_POSE and first.value.scan_seq == state.scan_seq
        assert step.mapper.keyframe_count == made, "the keyframe's work ran before the answer"
        predicted = step.mapper.place(first.value.local_pose)
        np.testing.assert_allclose(first.value.pose, predicted, atol=1e-12)
        rest = list(outs)
        assert all(o.topic is not topics.MAP_POSE for o in rest)
        answered_first += step.mapper.keyframe_count != made
    assert answered_first > 50   # a keyframe every metre or so on the 62 m loop, twice
    assert step.mapper.stats.optimisations > 0


def test_each_scans_no_return_bearings_wait_for_its_state_and_are_bounded():
    """The localizer's open beams (services/mapper.py ``NoReturnBearings``): a scan's bearings with
    no return are handed once, to its own slam state; a scan whose state never comes is forgotten
    once as many scans wait as the aligner keeps."""
    from services.mapper import MAX_WAITING_STATES, NoReturnBearings

    angles = np.radians(np.arange(-90.0, 91.0))
    ranges = np.full(181, 2.0)
    ranges[[0, 90, 180]] = np.inf
    ranges[45] = np.nan   # invalid, not "no return"
    kept = NoReturnBearings()
    kept.add(t.LaserScan.from_ranges(1_000, 7, ranges, angles[0], angles[1] - angles[0]))
    np.testing.assert_allclose(kept.take(7), angles[[0, 90, 180]], atol=1e-12)
    assert kept.take(7).size == 0 and kept.take(8).size == 0
    for seq in range(3 * MAX_WAITING_STATES):
        kept.add(t.LaserScan.from_ranges(seq, seq, ranges, angles[0], angles[1] - angles[0]))
    assert kept.take(0).size == 0 and kept.take(3 * MAX_WAITING_STATES - 1).size == 3
