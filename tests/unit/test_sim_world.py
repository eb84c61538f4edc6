"""Segment worlds: corner and free-endpoint ground truth, and the built-in maps."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lrfslam.errors import ConfigError
from lrfslam.sim.floor_plans import (
    build_world,
    corridor_end,
    doorway_room,
    hallway_loop,
    hallway_loop_path,
    l_corner,
    straight_wall,
    waypoints,
)
from lrfslam.sim.world import World, closed_polygon, polyline


def test_l_corner_has_one_concave_corner_at_the_vertex():
    c = l_corner().corners()
    assert len(c) == 1
    np.testing.assert_allclose(c.xy_m, [[2.0, 0.0]], atol=1e-12)
    assert c.kind.tolist() == ["concave"]
    np.testing.assert_allclose(c.angle_deg, [90.0])
    np.testing.assert_allclose(c.wall_lengths_m, [[4.0, 4.0]])


@pytest.mark.parametrize("angle_deg, expected", [(60.0, 0), (69.0, 0), (71.0, 1), (90.0, 1), (109.0, 1), (111.0, 0)])
def test_corner_needs_ninety_plus_minus_twenty_degrees(angle_deg, expected):
    c = l_corner(angle_deg=angle_deg).corners()
    assert len(c) == expected
    if expected:
        np.testing.assert_allclose(c.angle_deg, [angle_deg])


def test_corridor_end_has_two_corners_at_the_end_wall():
    c = corridor_end(width_m=1.6, length_m=6.0, end_x_m=3.0).corners()
    assert len(c) == 2
    np.testing.assert_allclose(sorted(c.xy_m.tolist()), [[3.0, -0.8], [3.0, 0.8]])
    assert set(c.kind) == {"concave"}
    np.testing.assert_allclose(np.sort(corridor_end().free_endpoints(), axis=0), [[-3.0, -0.8], [-3.0, 0.8]])


def test_straight_wall_and_doorway_have_no_corners_only_free_ends():
    assert len(straight_wall().corners()) == 0
    free = doorway_room().free_endpoints()
    assert len(free) == 6
    jambs = free[np.isclose(free[:, 0], 1.0) & (np.abs(free[:, 1]) < 1.0)]
    np.testing.assert_allclose(np.sort(jambs[:, 1]), [-0.5, 0.5])


def test_convex_corner_of_a_solid_block():
    block = World(closed_polygon([(0, 0), (2, 0), (2, 1), (0, 1)], free_inside=False), "block")
    room = World(closed_polygon([(0, 0), (2, 0), (2, 1), (0, 1)], free_inside=True), "room")
    assert block.corners().kind.tolist() == ["convex"] * 4
    assert room.corners().kind.tolist() == ["concave"] * 4


def test_endpoints_within_one_centimetre_snap_to_one_vertex():
    seg = np.array([[0.0, -2.0, 2.0, 0.0], [2.006, 0.004, 0.0, 2.0]])
    c = World(seg, "snapped").corners()
    assert len(c) == 1
    assert np.hypot(*(c.xy_m[0] - (2.0, 0.0))) < 0.01
    far = np.array([[0.0, -2.0, 2.0, 0.0], [2.02, 0.0, 0.0, 2.0]])
    assert len(World(far, "apart").corners()) == 0
    assert len(World(far, "apart").free_endpoints()) == 4


def test_vertex_shared_by_three_walls_is_neither_corner_nor_free():
    seg = polyline([(-1, 0), (0, 0), (0, 1)])
    t = np.vstack((seg, [[0.0, 0.0, 1.0, 0.0]]))
    w = World(t, "tee")
    assert len(w.corners()) == 0
    assert not np.any(np.all(np.isclose(w.free_endpoints(), 0.0), axis=1))


def test_inconsistent_orientation_is_a_config_error():
    seg = np.array([[0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])  # both start at the vertex
    with pytest.raises(ConfigError):
        World(seg, "bad").corners()


@pytest.mark.parametrize(
    "bad", [np.zeros((0, 4)), np.zeros((3, 3)), np.array([[0, 0, 0, 0.001]]), np.array([[0, 0, np.nan, 1]])]
)
def test_malformed_segments_are_rejected(bad):
    with pytest.raises(ConfigError):
        World(bad, "bad")


@settings(max_examples=40, deadline=None)
@given(
    theta=st.floats(-np.pi, np.pi),
    shift=st.tuples(st.floats(-50, 50), st.floats(-50, 50)),
)
def test_corners_are_invariant_to_rigid_motion(theta, shift):
    base = corridor_end()
    c, s = np.cos(theta), np.sin(theta)
    rot = np.array([[c, -s], [s, c]])
    pts = base.segments_m.reshape(-1, 2) @ rot.T + shift
    moved = World(pts.reshape(-1, 4), "moved").corners()
    expected = base.corners().xy_m @ rot.T + shift
    np.testing.assert_allclose(moved.xy_m, expected, atol=1e-9)
    assert moved.kind.tolist() == base.corners().kind.tolist()


# --- the built-in hallway loop -----------------------------------------------------


def _point_segment_distance(points, seg):
    a, b = seg[None, :, :2], seg[None, :, 2:]
    p = points[:, None, :]
    ab = b - a
    u = np.clip(np.sum((p - a) * ab, axis=-1) / np.sum(ab * ab, axis=-1), 0.0, 1.0)
    closest = a + u[..., None] * ab
    return np.hypot(*(p - closest).transpose(2, 0, 1))


def test_hallway_walls_are_axis_aligned_and_every_vertex_a_right_angle_corner():
    w = hallway_loop()
    seg = w.segments_m
    dx, dy = seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1]
    assert np.all((dx == 0) ^ (dy == 0))
    c = w.corners()
    assert len(c) == len(seg) == 96
    np.testing.assert_allclose(c.angle_deg, 90.0)
    assert (c.kind == "concave").sum() == 48 and (c.kind == "convex").sum() == 48
    assert len(w.free_endpoints()) == 0


def test_hallway_has_corners_the_forward_search_can_see_all_along_the_loop():
    # Bays and alcoves: both walls of a corner at least as long as the paper's
    # longest 1.2 m search arm, spaced so that no stretch of the loop is blind.
    c = hallway_loop().corners()
    long_armed = c.xy_m[np.all(c.wall_lengths_m >= 1.2, axis=1)]
    assert len(long_armed) >= 60
    path = hallway_loop_path()
    closed = np.vstack((path, path[:1]))
    s = np.linspace(0.0, 1.0, 200)[:, None]
    samples = np.vstack([a + s * (b - a) for a, b in itertools.pairwise(closed)])
    nearest = np.hypot(*(samples[:, None, :] - long_armed[None, :, :]).transpose(2, 0, 1)).min(axis=1)
    assert nearest.max() < 3.0


def test_hallway_path_closes_and_keeps_the_corridor_width():
    w = hallway_loop()
    path = hallway_loop_path()
    closed = np.vstack((path, path[:1]))
    # Sample the straight legs densely: every point is at least half a 1.5 m hallway from any wall.
    s = np.linspace(0.0, 1.0, 400)[:, None]
    samples = np.vstack([a + s * (b - a) for a, b in itertools.pairwise(closed)])
    clearance = _point_segment_distance(samples, w.segments_m).min(axis=1)
    assert clearance.min() >= 0.75
    legs = np.diff(closed, axis=0)
    assert np.all((legs[:, 0] == 0) | (legs[:, 1] == 0))
    np.testing.assert_allclose(legs.sum(axis=0), 0.0, atol=1e-12)


def test_hallway_has_door_recesses_and_open_doorways():
    seg = hallway_loop().segments_m
    lengths = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1])
    door_backs = np.flatnonzero((lengths >= 0.89) & (lengths <= 1.01))
    assert len(door_backs) >= 4
    # An open doorway: a scan from the corridor in front of it sees a >1.5 m depth step.
    from lrfslam.sim.lidar import LidarModel, raycast

    r = raycast(seg, (10.5, -1.0, -np.pi / 2), LidarModel().angles_rad(), 8.0)
    finite = r[np.isfinite(r)]
    assert np.max(np.abs(np.diff(finite))) > 1.5


def test_registry_builds_by_name_and_rejects_unknown_names():
    assert build_world("hallway_loop").name == "hallway_loop"
    np.testing.assert_array_equal(waypoints("hallway_loop"), hallway_loop_path())
    with pytest.raises(ConfigError):
        build_world("no_such_world")
