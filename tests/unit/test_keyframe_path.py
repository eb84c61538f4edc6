"""The display's keyframe path: the graph's keyframes and the retired ones, merged by stamp, bounded."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from lrfslam.algo.geometry import compose
from lrfslam.msgs import types as t
from lrfslam.viz.keyframe_path import KeyframePath


def test_retired_keyframes_stay_on_the_path_where_their_anchor_placed_them():
    path = KeyframePath(max_retired=10)
    graph = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, np.pi / 2]])
    kf = t.MapKeyframes(stamp_ns=5, seq=1, scan_stamp_ns=[10, 40], local_pose=np.zeros((2, 3)), map_pose=graph,
                        retired_scan_stamp_ns=[20, 30],
                        retired_local_pose=np.zeros((2, 3)), retired_local_edge=[True, True],
                        retired_anchor_stamp_ns=[10, 40], retired_offset=[[0.5, 0.0, 0.0], [0.0, 1.0, 0.0]])
    stamps, poses = path.update(kf)
    np.testing.assert_array_equal(stamps, [10, 20, 30, 40])
    np.testing.assert_allclose(poses[1], [0.5, 0.0, 0.0])
    np.testing.assert_allclose(poses[2], compose(graph[1], [0.0, 1.0, 0.0]))
    # The next message moves the graph; the retired ones stay, and are not told again.
    moved = t.MapKeyframes(stamp_ns=6, seq=2, scan_stamp_ns=[10, 40, 50], local_pose=np.zeros((3, 3)),
                           map_pose=graph[[0, 1, 1]] + 0.1)
    stamps, poses = path.update(moved)
    np.testing.assert_array_equal(stamps, [10, 20, 30, 40, 50])
    np.testing.assert_allclose(poses[1], [0.5, 0.0, 0.0])


@settings(max_examples=30, deadline=None)
@given(st.integers(2, 20), st.lists(st.integers(0, 30), min_size=1, max_size=30))
def test_the_retired_keyframes_kept_are_bounded_and_in_order(cap, batches):
    path = KeyframePath(max_retired=cap)
    stamp = 1
    for r in batches:
        retired = np.arange(stamp + 1, stamp + 1 + r)
        stamp += r + 1
        kf = t.MapKeyframes(stamp_ns=stamp, seq=1, scan_stamp_ns=[0, stamp], local_pose=np.zeros((2, 3)),
                            map_pose=np.zeros((2, 3)),
                            retired_scan_stamp_ns=retired, retired_local_pose=np.zeros((r, 3)),
                            retired_local_edge=np.ones(r, bool), retired_anchor_stamp_ns=np.zeros(r, np.int64),
                            retired_offset=np.ones((r, 3)))
        stamps, poses = path.update(kf)
        assert stamps.size <= cap + 2 and np.all(np.diff(stamps) > 0) and poses.shape == (stamps.size, 3)
        assert stamps[0] == 0 and stamps[-1] == stamp
