"""The occupancy grid (lrfslam.algo.occupancy_grid): single beams, no returns, sizing, and the true walls.

The oracle for the walls is the simulator's world: scans cast from the true poses must
put the occupied cells on its segments and the free cells in its corridors.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lrfslam.algo.occupancy_grid import (
    FREE,
    OCCUPIED,
    UNKNOWN,
    GridParams,
    build_grid,
    grid_frame,
)
from lrfslam.errors import ConfigError, InputError
from lrfslam.sim import SimConfig, Simulator
from lrfslam.sim.world import distance_to_segments, inside_polygons

RES = 0.05
coords = st.floats(-20.0, 20.0, allow_nan=False)
headings = st.floats(-np.pi, np.pi, allow_nan=False)


@settings(max_examples=60, deadline=None)
@given(x=coords, y=coords, theta=headings, bearing=st.floats(-np.pi / 2, np.pi / 2), r=st.floats(0.2, 7.9))
def test_a_single_beam_marks_its_end_occupied_and_the_cells_before_it_free(x, y, theta, bearing, r):
    p = GridParams(resolution_m=RES)
    grid = build_grid([[x, y, theta]], [[r]], [bearing], p)
    lo = grid.log_odds
    a = theta + bearing
    end = np.array([[x + r * np.cos(a), y + r * np.sin(a)]])
    end_cell = grid.cell_of(end)
    assert lo[end_cell] == pytest.approx(p.hit_log_odds) and grid.trinary()[end_cell] == OCCUPIED
    # Every point of the beam up to the end point's cell lies in a cell marked free once (a point
    # within rounding of a cell edge, as on a beam along a grid line, in one of the cells there) ...
    d = np.arange(0.0, r, RES / 4)
    points = np.column_stack((x + d * np.cos(a), y + d * np.sin(a)))
    ok = np.zeros(d.size, bool)
    for nudge in ((1e-9, 1e-9), (1e-9, -1e-9), (-1e-9, 1e-9), (-1e-9, -1e-9)):
        rows, cols = grid.cell_of(points + nudge)
        in_end = (rows == end_cell[0][0]) & (cols == end_cell[1][0])
        ok |= in_end | np.isclose(lo[rows, cols], p.miss_log_odds)
    assert ok.all(), points[~ok]
    # ... and the beam touched nothing else: one hit, and misses only along it.
    assert np.count_nonzero(lo > 0) == 1
    centres = grid.cell_centres_m(*np.nonzero(lo < 0))
    dist = distance_to_segments(centres, np.array([[x, y, end[0, 0], end[0, 1]]]))
    assert np.all(dist <= RES * np.sqrt(2) / 2 + 1e-9)


@settings(max_examples=40, deadline=None)
@given(x=coords, y=coords, theta=headings, far=st.floats(8.01, 80.0), free_m=st.floats(0.0, 5.0),
       n=st.integers(1, 20))
def test_beams_without_a_return_or_beyond_max_range_mark_no_hit(x, y, theta, far, free_m, n):
    ranges = np.where(np.arange(n) % 2 == 0, np.inf, far)[None, :]
    angles = np.linspace(-np.pi / 2, np.pi / 2, n)
    grid = build_grid([[x, y, theta]], ranges, angles, GridParams(resolution_m=RES, no_return_free_m=free_m))
    assert np.all(grid.log_odds <= 0)
    # A far return clears the space up to the cap; a no-return only no_return_free_m of it.
    p = GridParams(resolution_m=RES)
    nothing = build_grid([[x, y, theta]], np.full((1, n), np.inf), angles, p)
    assert np.count_nonzero(nothing.log_odds) == 0


def test_invalid_beams_are_skipped():
    grid = build_grid([[0, 0, 0]], [[np.nan, -1.0, 0.0, 2.0]], [-0.1, 0.0, 0.1, 0.2])
    tri = grid.trinary()
    assert np.count_nonzero(tri == OCCUPIED) == 1
    assert tri[grid.cell_of([[2 * np.cos(0.2), 2 * np.sin(0.2)]])] == OCCUPIED


def test_repeated_hits_saturate_and_a_cell_is_updated_once_per_scan():
    p = GridParams(resolution_m=RES)
    # 30 beams of one scan end in the same cell: one hit, not thirty.
    one = build_grid([[0, 0, 0]], np.full((1, 30), 3.0), np.zeros(30), p)
    assert one.log_odds.max() == pytest.approx(p.hit_log_odds)
    many = build_grid(np.zeros((100, 3)), np.full((100, 1), 3.0), [0.0], p)
    assert many.log_odds.max() == pytest.approx(p.max_log_odds)
    assert many.log_odds.min() == pytest.approx(p.min_log_odds)


@settings(max_examples=40, deadline=None)
@given(poses=st.lists(st.tuples(st.floats(-5, 5), st.floats(-5, 5), headings), min_size=1, max_size=5),
       r=st.floats(0.1, 30.0), res=st.sampled_from([0.05, 0.1, 0.25]))
def test_the_grid_is_sized_to_the_data(poses, r, res):
    p = GridParams(resolution_m=res)
    angles = np.linspace(-np.pi / 2, np.pi / 2, 7)
    grid = build_grid(poses, np.full((len(poses), 7), r), angles, p)
    xy = np.array(poses)[:, :2]
    reach = min(r, p.max_range_m)   # hits beyond max_range_m still clear up to free_range_m
    lo, hi = xy.min(axis=0) - reach - 2 * res - 1e-9, xy.max(axis=0) + reach + 2 * res + 1e-9
    x0, x1, y0, y1 = grid.extent_m
    assert lo[0] <= x0 and x1 <= hi[0] and lo[1] <= y0 and y1 <= hi[1]
    # Every pose lies inside, and the origin is a whole number of cells from (0, 0).
    assert x0 < xy[:, 0].min() and xy[:, 0].max() < x1 and y0 < xy[:, 1].min() and xy[:, 1].max() < y1
    np.testing.assert_allclose(grid.origin_xy_m / res, np.round(grid.origin_xy_m / res), atol=1e-6)
    assert grid.log_odds.dtype == np.float32


def test_bad_input_and_settings_are_refused():
    with pytest.raises(InputError, match="2 poses but 1 scans"):
        build_grid(np.zeros((2, 3)), np.ones((1, 3)), np.zeros(3))
    with pytest.raises(InputError, match="do not match"):
        build_grid(np.zeros((1, 3)), np.ones((1, 3)), np.zeros(4))
    with pytest.raises(InputError, match="exceeds"):
        grid_frame([[0, 0, 0], [1000, 1000, 0]], np.ones((2, 1)), [0.0], GridParams(resolution_m=0.05))
    with pytest.raises(InputError, match="no scans"):
        grid_frame(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(3), GridParams())
    with pytest.raises(InputError, match="finite"):
        build_grid([[np.nan, 0, 0]], [[1.0]], [0.0])
    for bad in ({"resolution_m": 0.0}, {"max_range_m": -1.0}, {"hit_log_odds": -0.1}, {"max_cells": 0}):
        with pytest.raises(ConfigError):
            GridParams(**bad)


def test_scans_from_the_true_poses_draw_the_true_walls():
    """The hallway loop from its true poses: occupied cells on the walls, free cells in the corridors.

    The world is shifted by a fraction of a cell so its walls (on whole metres) cross cells
    rather than run along their edges, where a cell on the wrong side could not be told.
    """
    sim = Simulator(SimConfig(seed=2))
    frames = [f for f, _ in zip(sim, range(300))]
    shift = np.array([0.013, 0.031])
    grid = build_grid([f.true_pose + (*shift, 0.0) for f in frames], [f.scan.ranges_m for f in frames],
                      sim.config.lidar.angles_rad(), GridParams(resolution_m=RES))
    walls = sim.world.opaque_segments_m + np.tile(shift, 2)
    tri = grid.trinary()
    occupied = grid.cell_centres_m(*np.nonzero(tri == OCCUPIED))
    free = grid.cell_centres_m(*np.nonzero(tri == FREE))
    assert len(occupied) > 800 and len(free) > 10_000 and np.count_nonzero(tri == UNKNOWN) > 0
    # Measured: 99.2 % within one cell, all within two (range noise 1 cm, mixed pixels).
    to_wall = distance_to_segments(occupied, walls) / RES
    assert np.mean(to_wall <= 1.0) >= 0.98 and np.mean(to_wall <= 2.0) >= 0.999
    # A free cell whose centre is within half a cell of a wall holds that wall (measured 0.25 %).
    assert np.mean(distance_to_segments(free, walls) < 0.5 * RES) <= 0.01
    assert inside_polygons(free, walls).mean() >= 0.999
