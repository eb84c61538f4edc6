"""Mapping on from a saved map (``LoopClosingMapper.seeded`` + ``join``): the simulator's hallway loop
mapped once, then driven again in a new run with its own frame, placed on the map by a fix as a
localizer gives it. Ground truth: the simulator's poses, carried into the map's frame."""

from __future__ import annotations

import numpy as np
import pytest
from test_loop_closure import sim_frames

from lrfslam.algo.geometry import compose, relative
from lrfslam.algo.loop_closure import LoopClosingMapper
from lrfslam.errors import InputError
from lrfslam.sim.simulator import SimConfig

LAP_M = 62.0          # the hallway loop's length (m)
RATE_HZ = 5.0
#: The new run's odometry frame, anywhere: a run starts its own.
NEW_FRAME = np.array([100.0, -50.0, 1.0])
FIX_COV = np.diag([0.05 ** 2, 0.05 ** 2, 0.01 ** 2])
#: The saved map's own error against the truth (m), the new run's measured beside it.
MAP_ERROR_M = 0.3


@pytest.fixture(scope="module")
def drive():
    """Two and a half laps of the hallway loop at 1 m/s: per scan (stamp ns, drifting odometry, points), truth (T, 3).

    The simulator's odometry stands in for the local trajectory (the service feeds the EKF's
    scan-matched motions, which drift less)."""
    return sim_frames(SimConfig(speed_mps=1.0, rate_hz=RATE_HZ, seed=5), int(2.5 * LAP_M * RATE_HZ))


@pytest.fixture(scope="module")
def saved(drive):
    """A map of the first lap and 15 m more (one closure round the loop): the graph as a saved map keeps it."""
    frames, truth = drive
    first = LoopClosingMapper()
    n = int((LAP_M + 15.0) * RATE_HZ)
    for f in frames[:n]:
        first.add_scan(*f, online_pose=f[1])
    first.solve()
    assert first.stats.accepted >= 1
    snap = first.snapshot()
    pts = np.split(snap["keyframe_points"], np.cumsum(snap["keyframe_point_counts"])[:-1])
    stamps = snap["keyframe_stamp_ns"]
    poses = first.keyframe_poses()
    # The simulator's frame laid on the map's: the rigid motion that best fits the keyframes'
    # true positions onto the map's (least squares), so the map's own errors are what remain.
    index = {s: i for i, (s, _, _) in enumerate(frames)}
    true_xy = truth[[index[int(s)] for s in stamps], :2]
    mt, mm = true_xy.mean(axis=0), poses[:, :2].mean(axis=0)
    u, _, vt = np.linalg.svd((true_xy - mt).T @ (poses[:, :2] - mm))
    rot = vt.T @ np.diag([1.0, np.sign(np.linalg.det(vt.T @ u.T))]) @ u.T
    shift = mm - rot @ mt
    map_from_world = np.array([shift[0], shift[1], np.arctan2(rot[1, 0], rot[0, 0])])
    assert np.hypot(*(poses[:, :2] - (true_xy @ rot.T + shift)).T).max() < MAP_ERROR_M
    return poses, pts, stamps, map_from_world, n


def on_map(drive, saved, i: int) -> np.ndarray:
    """Where scan ``i`` lies on the saved map (3,): the nearest keyframe's saved pose and the true motion
    from its scan. The map's own errors (its shape against the truth, up to ``MAP_ERROR_M``) are
    the map's: a localizer's fix and a closure find the robot on the map, not in the simulator."""
    frames, truth = drive
    poses, _, stamps, map_from_world, _ = saved
    here = compose(map_from_world, truth[i])
    k = int(np.argmin(np.hypot(*(poses[:, :2] - here[:2]).T)))
    index = {s: j for j, (s, _, _) in enumerate(frames)}
    return compose(poses[k], relative(truth[index[int(stamps[k])]], truth[i]))


def run_on(drive, saved, start: int, stop: int, fix_error=(0.0, 0.0, 0.0)):
    """A new run from scan ``start`` to ``stop`` on the saved map, its first scan placed by a fix ``fix_error``
    off (:func:`on_map`): the mapper and its pose of each scan as it came (T, 3)."""
    frames, _ = drive
    poses, pts, stamps, _, _ = saved
    mapper = LoopClosingMapper.seeded(None, poses, pts, stamps)
    odom0 = frames[start][1]
    out = []
    for i in range(start, stop):
        stamp, odom, xy = frames[i]
        local = compose(NEW_FRAME, relative(odom0, odom))
        if i == start:
            fix = compose(on_map(drive, saved, i), np.asarray(fix_error, dtype=float))
            out.append(mapper.join(stamp, local, xy, fix, FIX_COV, online_pose=local))
        else:
            out.append(mapper.add_scan(stamp, local, xy, online_pose=local))
    mapper.solve()
    return mapper, np.array(out)


def test_a_new_run_closes_into_the_saved_map_and_leaves_it_as_it_was(drive, saved):
    frames, truth = drive
    poses, _, _, _, n = saved
    start = n + int(10 * RATE_HZ)            # the second lap, 10 m on
    mapper, online = run_on(drive, saved, start, len(frames), fix_error=np.array([0.04, -0.03, 0.005]))
    k = poses.shape[0]
    # The saved map keeps its shape and place: its keyframes move by what the new closures say, little.
    assert np.hypot(*(mapper.keyframe_poses()[:k, :2] - poses[:, :2]).T).max() < 0.1
    # The run closed into it, rightly (the truth of both keyframes).
    index = {s: i for i, (s, _, _) in enumerate(frames)}
    kf_stamps = mapper.keyframe_stamped_local_poses()[0]
    into_saved = [(a, b, z) for a, b, z in mapper.closures() if a < k <= b]
    assert len(into_saved) >= 10
    for a, b, z in into_saved:
        err = relative(relative(truth[index[kf_stamps[a]]], truth[index[kf_stamps[b]]]), z)
        assert np.hypot(err[0], err[1]) < 0.1 and abs(err[2]) < 0.03
    # Every pose of the run, as known when its scan came, is on the map where it is.
    want = np.array([on_map(drive, saved, i) for i in range(start, len(frames))])
    err = np.hypot(*(online[:, :2] - want[:, :2]).T)
    assert err.max() < 0.2 and np.median(err) < 0.05, (err.max(), np.median(err))
    # The run's keyframes at the end.
    run_kf = np.arange(k, mapper.graph_keyframes)
    final = mapper.keyframe_poses()[run_kf]
    want = np.array([on_map(drive, saved, index[int(s)]) for s in kf_stamps[run_kf]])
    assert np.hypot(*(final[:, :2] - want[:, :2]).T).max() < 0.1


def test_driving_the_mapped_loop_again_leaves_the_graph_the_size_of_the_place(drive, saved):
    """A lap and a half over the mapped loop: its keyframes fold into the saved ones they revisit."""
    frames, _ = drive
    poses, _, _, _, n = saved
    mapper, _ = run_on(drive, saved, n, len(frames))
    made = mapper.keyframe_count - poses.shape[0]
    assert made > 100
    assert mapper.stats.folded > 0.6 * made, (mapper.stats.folded, made)
    assert mapper.graph_keyframes - poses.shape[0] < 0.3 * made


def test_a_seeded_mapper_takes_its_first_scan_only_by_join(saved):
    poses, pts, stamps, _, _ = saved
    mapper = LoopClosingMapper.seeded(None, poses, pts, stamps)
    with pytest.raises(InputError, match="join"):
        mapper.add_scan(1, np.zeros(3), np.zeros((0, 2)))
    mapper.join(1, np.zeros(3), np.zeros((0, 2)), poses[3], FIX_COV)
    with pytest.raises(InputError, match="join"):
        mapper.join(2, np.zeros(3), np.zeros((0, 2)), poses[3], FIX_COV)
    with pytest.raises(InputError, match="join"):
        LoopClosingMapper().join(1, np.zeros(3), np.zeros((0, 2)), np.zeros(3), FIX_COV)
    with pytest.raises(InputError):
        LoopClosingMapper.seeded(None, poses, pts[:-1], stamps)
    with pytest.raises(InputError):
        LoopClosingMapper.seeded(None, poses, pts, stamps).join(1, np.zeros(3), np.zeros((0, 2)), poses[0],
                                                                np.full((3, 3), np.nan))


def test_a_seeded_mappers_snapshot_restores_its_run_start(drive, saved):
    frames, _ = drive
    n = saved[-1]
    mapper, _ = run_on(drive, saved, n, n + 100)
    again = LoopClosingMapper.restore(None, mapper.snapshot())
    stamp, odom, xy = frames[n + 100]
    local = compose(NEW_FRAME, relative(frames[n][1], odom))
    np.testing.assert_array_equal(again.add_scan(stamp, local, xy, online_pose=local),
                                  mapper.add_scan(stamp, local, xy, online_pose=local))
    assert again.keyframe_count == mapper.keyframe_count
