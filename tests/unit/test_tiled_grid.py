"""The live grid's tiles against the NumPy tracing export uses (the oracle), and its bookkeeping.

``batch_cells`` (lrfslam/algo/occupancy_grid.py) is the oracle: a scan's hits and misses as the
tiles count them (a compiled walk, lrfslam/algo/grid_kernel.py) must be its cells. The frames
differ (export's grid frame against a frame round each scan), so a beam that ends within
round-off of a grid line may enter the other cell: at most 1 in 10,000 counts may differ.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lrfslam.algo.keyframe_grid import KeyframeGrid
from lrfslam.algo.occupancy_grid import GridParams, batch_cells, build_grid, grid_frame
from lrfslam.algo.tiled_grid import TiledGrid, tiles_of
from lrfslam.errors import InputError

A0, DA, BEAMS = -np.pi / 2, np.pi / 180, 181


def scans(seed: int, n: int, spread_m: float = 6.0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` poses (n, 3) within ``spread_m`` of the origin and their ranges (n, BEAMS): returns from
    0.2 to 12 m (beyond the 8 m wall range: free space only), some no-return (+inf) and invalid (NaN)."""
    rng = np.random.default_rng(seed)
    poses = np.column_stack((rng.uniform(-spread_m, spread_m, (n, 2)), rng.uniform(-np.pi, np.pi, n)))
    ranges = rng.uniform(0.2, 12.0, (n, BEAMS)).astype(np.float32)
    ranges[rng.random((n, BEAMS)) < 0.05] = np.inf
    ranges[rng.random((n, BEAMS)) < 0.02] = np.nan
    return poses, ranges


def oracle_counts(poses, ranges, params: GridParams | None = None):
    """Hits and misses per cell, (2, H, W), by the NumPy tracing, and the frame's origin (2,)."""
    params = params or GridParams()
    angles = A0 + DA * np.arange(BEAMS)
    origin, (h, w), res = grid_frame(poses, ranges, angles, params)
    counts = np.zeros((2, h * w), np.int64)
    for i in range(poses.shape[0]):
        free, hit = batch_cells(poses[i:i + 1], ranges[i:i + 1], angles[None, :], params, origin, res, (h, w))
        np.add.at(counts[0], hit, 1)
        np.add.at(counts[1], free, 1)
    return counts.reshape(2, h, w), origin


def tiled_counts(grid: TiledGrid, origin, shape) -> np.ndarray:
    """The grid's hits and misses on the oracle's frame, (2, H, W); it must hold nothing outside it."""
    t, res = grid.tile_cells, grid.resolution_m
    r0, c0 = np.round(np.asarray(origin)[::-1] / res).astype(int)
    out = np.zeros((2, *shape), np.int64)
    for (tr, tc) in grid.tiles():
        counts = grid.counts((tr, tc))
        rows, cols = np.nonzero(counts.sum(axis=0))
        rr, cc = tr * t + rows - r0, tc * t + cols - c0
        assert ((rr >= 0) & (rr < shape[0]) & (cc >= 0) & (cc < shape[1])).all()
        out[:, rr, cc] = counts[:, rows, cols]
    return out


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_the_tiles_count_what_the_numpy_tracing_counts(seed):
    poses, ranges = scans(seed, 6)
    grid = TiledGrid()
    for i, (p, r) in enumerate(zip(poses, ranges)):
        grid.lay(i, p, r, A0, DA)
    want, origin = oracle_counts(poses, ranges)
    got = tiled_counts(grid, origin, want.shape[1:])
    assert np.count_nonzero(got != want) <= 1e-4 * np.count_nonzero(want) + 1
    # A cell a scan hits is not also its miss: the hits alone are each scan's hit cells.
    assert got[0].sum() <= 6 * BEAMS


def test_taking_scans_out_and_moving_them_is_exact():
    poses, ranges = scans(1, 8)
    grid = TiledGrid()
    for i, (p, r) in enumerate(zip(poses, ranges)):
        grid.lay(i, p, r, A0, DA)
    moved = poses + [0.37, -0.21, 0.3]
    for i in range(4):
        grid.move(i, moved[i])
    for i in range(4, 8):
        grid.remove(i)
    fresh = TiledGrid()
    for i in range(4):
        fresh.lay(i, moved[i], ranges[i], A0, DA)
    assert len(grid) == 4 and 4 not in grid and 3 in grid
    for tile in set(grid.tiles()) | set(fresh.tiles()):
        np.testing.assert_array_equal(grid.counts(tile), fresh.counts(tile))
    np.testing.assert_array_equal(grid.laid(0).pose, moved[0])
    for i in range(4):
        grid.remove(i)
    assert all(not grid.counts(tile).any() for tile in grid.tiles())


def test_the_changed_tiles_are_those_a_scan_touched():
    poses, ranges = scans(2, 2, spread_m=30.0)
    grid = TiledGrid()
    grid.lay(0, poses[0], ranges[0], A0, DA)
    first = grid.take_changed()
    assert first == grid.tiles() and grid.take_changed() == []
    grid.lay(1, poses[1], ranges[1], A0, DA)
    second = grid.take_changed()
    assert second and set(second) <= set(grid.tiles())
    grid.remove(1)
    assert grid.take_changed() == second


def test_the_trinary_and_log_odds_follow_the_counts():
    p, grid = GridParams(), TiledGrid()
    grid.lay(0, [0.0, 0.0, 0.0], np.full(BEAMS, 2.0, np.float32), A0, DA)
    odds = np.concatenate([grid.log_odds(t).ravel() for t in grid.tiles()])
    assert {round(float(v), 5) for v in np.unique(odds)} == {0.0, round(p.miss_log_odds, 5), round(p.hit_log_odds, 5)}
    # One miss (log-odds -0.4) is not yet free (p < 0.196 is below -1.41); four are (-1.6). Five hits clamp.
    for key in range(1, 5):
        grid.lay(key, [0.0, 0.0, 0.0], np.full(BEAMS, 2.0, np.float32), A0, DA)
    odds = np.concatenate([grid.log_odds(t).ravel() for t in grid.tiles()])
    assert {round(float(v), 5) for v in np.unique(odds)} == {0.0, round(-2.0, 5), round(p.max_log_odds, 5)}
    values = np.concatenate([grid.trinary(t).ravel() for t in grid.tiles()])
    assert set(np.unique(values).tolist()) == {-1, 0, 100}
    assert (values == 100).sum() == np.count_nonzero(odds == p.max_log_odds)


def test_a_grid_grown_too_large_doubles_its_resolution_as_export_would():
    params = GridParams(max_cells=200_000)
    poses, ranges = scans(3, 6, spread_m=14.0)
    grid = TiledGrid(params)
    for i, (p, r) in enumerate(zip(poses, ranges)):
        grid.lay(i, p, r, A0, DA)
    built = build_grid(poses, ranges, A0 + DA * np.arange(BEAMS), params, fit=True)
    assert grid.resolution_m == built.resolution_m > params.resolution_m
    assert grid.resolution_changes == round(np.log2(built.resolution_m / params.resolution_m))
    # At the coarser resolution the counts are again the tracing's.
    want, origin = oracle_counts(poses, ranges, GridParams(resolution_m=grid.resolution_m, max_cells=10**8))
    got = tiled_counts(grid, origin, want.shape[1:])
    assert np.count_nonzero(got != want) <= 1e-4 * np.count_nonzero(want) + 1


def test_a_tile_side_must_be_a_power_of_two():
    with pytest.raises(InputError):
        TiledGrid(tile_cells=48)


# ---- keyframes ----------------------------------------------------------------------------------


def keyframe_grid(n: int = 6, seed: int = 4) -> tuple[KeyframeGrid, np.ndarray, np.ndarray]:
    poses, ranges = scans(seed, n)
    kg = KeyframeGrid(relays_per_call=1)
    for i in range(n):
        kg.add_scan(100 + i, ranges[i], A0, DA)
        assert kg.add_keyframe(100 + i, poses[i])
    return kg, poses, ranges


def same_counts(a: TiledGrid, b: TiledGrid) -> None:
    for tile in set(a.tiles()) | set(b.tiles()):
        np.testing.assert_array_equal(a.counts(tile), b.counts(tile))


def test_moved_keyframes_are_laid_again_a_few_per_call_and_retired_ones_taken_out():
    kg, poses, ranges = keyframe_grid()
    target = poses + [0.2, 0.1, 0.05]
    target[0] = poses[0] + [0.004, 0.0, 0.0]   # under a quarter of a cell: stays where it is
    kg.set_poses(np.arange(100, 105), target[:5])   # keyframe 105 left the graph
    assert kg.keyframes == 5 and kg.pending == 4
    assert kg.work() == 1 and kg.pending == 3
    assert kg.work(-1) == 3 and kg.pending == 0
    fresh = TiledGrid()
    fresh.lay(100, poses[0], ranges[0], A0, DA)
    for i in range(1, 5):
        fresh.lay(100 + i, target[i], ranges[i], A0, DA)
    same_counts(kg.grid, fresh)


def test_a_keyframe_whose_scan_was_not_held_is_counted_missing():
    kg = KeyframeGrid(recent=2)
    for i in range(3):
        kg.add_scan(i, np.full(BEAMS, 3.0, np.float32), A0, DA)
    assert not kg.add_keyframe(0, [0.0, 0.0, 0.0]) and kg.missing == 1
    assert kg.add_keyframe(2, [0.0, 0.0, 0.0]) and kg.keyframes == 1


def test_a_snapshot_restores_the_same_grid_and_what_is_pending():
    kg, poses, _ = keyframe_grid()
    kg.set_poses(np.arange(100, 106), poses + [0.3, 0.0, 0.0])
    kg.work()
    again = KeyframeGrid()
    again.restore(kg.snapshot())
    assert again.pending == kg.pending == 5 and again.keyframes == 6
    same_counts(again.grid, kg.grid)
    kg.work(-1)
    again.work(-1)
    same_counts(again.grid, kg.grid)
    broken = kg.snapshot()
    broken["grid_laid_pose"] = broken["grid_laid_pose"][:2]
    with pytest.raises(InputError):
        KeyframeGrid().restore(broken)


@settings(max_examples=30, deadline=None)
@given(h=st.integers(1, 150), w=st.integers(1, 150), r0=st.integers(-300, 300), c0=st.integers(-300, 300),
       shift=st.floats(-0.49, 0.49), seed=st.integers(0, 2**32 - 1))
def test_a_saved_grid_cut_into_tiles_keeps_every_cell(h, w, r0, c0, shift, seed):
    """``tiles_of`` (a saved map's grid on ``map/grid``): every known cell lands in the tile cell
    holding its centre, nothing else is known, and tiles without a known cell are not sent."""
    rng = np.random.default_rng(seed)
    cells = rng.choice(np.array([-1, 0, 100], np.int8), size=(h, w), p=[0.5, 0.3, 0.2])
    res = 0.05
    origin = (np.array([c0, r0]) + shift) * res
    tiles, blocks = tiles_of(cells, res, origin, tile_cells=16)
    assert tiles.shape[0] == blocks.shape[0] and np.all(np.any(blocks != -1, axis=(1, 2)))
    got = {}
    for (tr, tc), block in zip(tiles.tolist(), blocks):
        for r, c in zip(*np.nonzero(block != -1)):
            got[(tr * 16 + r, tc * 16 + c)] = block[r, c]
    rows, cols = np.nonzero(cells != -1)
    want = {(int(np.floor(origin[1] / res + r + 0.5)), int(np.floor(origin[0] / res + c + 0.5))): cells[r, c]
            for r, c in zip(rows, cols)}
    assert got == want
