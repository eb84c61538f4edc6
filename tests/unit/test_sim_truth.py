"""Per-pose corner visibility and forward-search eligibility."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from lrfslam.algo.geometry import from_frame
from lrfslam.sim.floor_plans import corridor_end, doorway_room, hallway_loop, l_corner
from lrfslam.sim.truth import (
    corners_in_robot_frame,
    eligible_corners,
    jump_edge_vertices,
    visible_corners,
    visible_points,
)
from lrfslam.sim.world import World, closed_polygon

ORIGIN = (0.0, 0.0, 0.0)


def test_l_corner_ahead_is_visible_and_eligible():
    w = l_corner()
    assert visible_corners(w, ORIGIN).tolist() == [0]
    assert eligible_corners(w, ORIGIN).tolist() == [0]
    np.testing.assert_allclose(corners_in_robot_frame(w, ORIGIN, [0]), [[2.0, 0.0]], atol=1e-12)


def test_corner_behind_or_out_of_range_is_not_visible():
    w = l_corner()
    assert len(visible_corners(w, (0.0, 0.0, np.pi))) == 0
    assert len(visible_corners(w, (-2.5, 0.0, 0.0))) == 0  # 4.5 m away
    assert visible_corners(w, (-2.5, 0.0, 0.0), max_range_m=5.0).tolist() == [0]


def test_fov_edges_are_inclusive():
    # Corner exactly at bearing +90°, the LMS200's last beam.
    w = l_corner(corner_xy_m=(0.0, 2.0))
    assert visible_corners(w, (0.0, 0.0, 0.0), fov_rad=np.pi).tolist() == [0]
    assert len(visible_corners(w, (0.0, 0.0, 0.0), fov_rad=np.pi * 0.9)) == 0


def test_occluding_wall_hides_the_corner():
    seg = np.vstack((l_corner().segments_m, [[1.0, -0.5, 1.0, 0.5]]))
    w = World(seg, "occluded")
    assert len(visible_corners(w, ORIGIN)) == 0


def test_corridor_end_corners_are_eligible_only_if_the_end_wall_is_long_enough():
    wide = corridor_end(width_m=1.6)
    assert visible_corners(wide, ORIGIN).tolist() == [0, 1]
    assert eligible_corners(wide, ORIGIN).tolist() == [0, 1]
    narrow = corridor_end(width_m=1.0)
    assert visible_corners(narrow, ORIGIN).tolist() == [0, 1]
    assert len(eligible_corners(narrow, ORIGIN)) == 0  # a 1.0 m end wall is shorter than the 1.2 m arm
    assert eligible_corners(narrow, ORIGIN, arm_dists_m=(0.3, 0.6, 0.9)).tolist() == [0, 1]


def test_convex_corner_with_one_hidden_face_is_visible_but_not_eligible():
    block = World(closed_polygon([(0, 0), (3, 0), (3, 3), (0, 3)], free_inside=False), "block")
    ids_both_faces = eligible_corners(block, (4.0, -1.0, np.pi / 2))
    xy = block.corners().xy_m
    corner = int(np.flatnonzero(np.all(np.isclose(xy, (3.0, 0.0)), axis=1))[0])
    assert corner in ids_both_faces
    one_face = (4.0, 1.0, np.pi)
    assert corner in visible_corners(block, one_face)
    assert corner not in eligible_corners(block, one_face)


def test_jump_edge_vertices_are_convex_corners_and_free_ends():
    assert len(jump_edge_vertices(hallway_loop())) == 48
    v = jump_edge_vertices(doorway_room())
    assert len(v) == 6
    assert np.any(np.all(np.isclose(v, (1.0, 0.5)), axis=1))


@settings(max_examples=40, deadline=None)
@given(x=st.floats(-0.8, 16.8), y=st.floats(-0.8, 10.8), theta=st.floats(-np.pi, np.pi))
def test_visible_corners_in_the_hallway_are_in_view_and_unoccluded(x, y, theta):
    # Sample the corridor ring round the block (the block itself is solid).
    if 0.2 < x < 15.8 and 0.2 < y < 9.8:
        x = -0.8
    w = hallway_loop()
    pose = (x, y, theta)
    ids = visible_corners(w, pose)
    eligible = eligible_corners(w, pose)
    assert set(eligible) <= set(ids)
    local = corners_in_robot_frame(w, pose, ids)
    assert np.all(np.hypot(local[:, 0], local[:, 1]) <= 4.0)
    # Within the 180° field of view, to the truth's 1e-9 rad slack for the extreme beams
    # (a bearing test: an x bound would depend on the range).
    assert np.all(np.abs(np.arctan2(local[:, 1], local[:, 0])) <= np.pi / 2 + 1e-9)
    np.testing.assert_allclose(from_frame(local, pose), w.corners().xy_m[ids], atol=1e-9)
    # 10 cm beyond a visible concave corner, along its bearing, lies behind the walls.
    concave = w.corners().kind[ids] == "concave"
    r = np.hypot(local[concave, 0], local[concave, 1])
    beyond = from_frame(local[concave] * ((r + 0.1) / r)[:, None], pose)
    assert not np.any(visible_points(w, pose, beyond, max_range_m=5.0))
