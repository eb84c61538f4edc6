"""Dominant wall direction modulo 90°: against the simulator's truth, scenes and edge cases."""

from __future__ import annotations

import numpy as np
import pytest

from lrfslam.algo.histogram import DenoiseParams, denoise
from lrfslam.algo.wall_direction import (
    WallDirectionParams,
    wall_direction,
    wrap_quarter,
)
from lrfslam.errors import ConfigError, InputError
from lrfslam.sim import SimConfig, Simulator
from lrfslam.sim.floor_plans import corridor_end, l_corner
from lrfslam.sim.lidar import LidarModel, simulate_scan
from lrfslam.sim.world import World, polyline

EXACT = LidarModel(range_sigma_m=0.0, quantum_m=0.0, mixed_pixel_prob=0.0)


def scan_points(world, pose, lidar=EXACT, seed=0):
    sim = simulate_scan(world, np.asarray(pose, dtype=float), lidar, np.random.default_rng(seed))
    res = denoise(sim.ranges_m, sim.angles_rad, DenoiseParams.default())
    return res.points_xy[res.kept]


def test_wrap_quarter_range_and_periodicity():
    a = np.array([0.0, np.pi / 4, -np.pi / 4, 0.3 + np.pi / 2, -0.3 - 3 * np.pi / 2, np.pi / 4 - 1e-9])
    np.testing.assert_allclose(wrap_quarter(a), [0.0, -np.pi / 4, -np.pi / 4, 0.3, -0.3, np.pi / 4 - 1e-9],
                               atol=1e-12)
    assert isinstance(wrap_quarter(1.0), float)


def test_hallway_loop_scans_against_the_true_heading():
    # Every wall of the hallway is axis-aligned, so the walls run at -theta (mod 90°)
    # in the robot frame. 300 scans (a quarter lap, one 90° turn), default noise.
    sim = Simulator(SimConfig(seed=5))
    params = WallDirectionParams()
    err, sig = [], []
    for _ in range(300):
        frame = next(sim)
        res = denoise(frame.scan.ranges_m, frame.scan.angles_rad, DenoiseParams.default())
        wd = wall_direction(res.points_xy[res.kept], params)
        if wd is not None:
            err.append(wrap_quarter(wd.direction_rad + frame.true_pose[2]))
            sig.append(wd.sigma_rad)
    err, sig = np.array(err), np.array(sig)
    nees = (err / sig) ** 2
    assert err.size >= 290  # a corridor always shows long walls
    # A few mrad, and a reported sigma that is honest: the 1-dof NEES averages
    # about 1 (0.78 over 2400 scans) with as many beyond the 99 % gate as chi2_1 has.
    assert np.sqrt(np.mean(err**2)) < 0.003 and np.abs(err).max() < 0.012
    assert 0.5 < nees.mean() < 1.3
    assert np.mean(nees > 6.63) < 0.02


@pytest.mark.parametrize("heading", [0.0, 0.3, -0.7, 1.2, np.pi - 0.1])
def test_noise_free_corridor_gives_the_exact_direction(heading):
    pts = scan_points(corridor_end(width_m=2.0), (-1.0, 0.2, heading))
    wd = wall_direction(pts, WallDirectionParams())
    assert wd is not None and wd.support_frac == pytest.approx(1.0)
    assert abs(wrap_quarter(wd.direction_rad + heading)) < 1e-6
    # Noise-free walls: the residual floor alone sets the error.
    assert wd.sigma_rad < 0.003


def test_direction_is_modulo_90_degrees():
    pts = scan_points(l_corner(), (0.0, 0.0, 0.2))
    params = WallDirectionParams()
    base = wall_direction(pts, params)
    c, s = np.cos(np.pi / 2), np.sin(np.pi / 2)
    turned = wall_direction(pts @ np.array([[c, s], [-s, c]]), params)  # points rotated by +90°
    assert base is not None and turned is not None
    assert turned.direction_rad == pytest.approx(base.direction_rad, abs=1e-9)
    assert base.sigma_rad == pytest.approx(turned.sigma_rad, rel=1e-6)


def test_clutter_has_no_dominant_direction():
    rng = np.random.default_rng(3)
    ang = np.sort(rng.uniform(-np.pi / 2, np.pi / 2, 181))
    rad = rng.uniform(0.5, 4.0, 181)
    assert wall_direction(np.column_stack((rad * np.cos(ang), rad * np.sin(ang))), WallDirectionParams()) is None


def test_two_wall_families_of_equal_length_are_rejected():
    # Two 2 m walls 30° apart modulo 90°: neither direction dominates.
    tip = (0.5 + 2.0 * np.cos(np.radians(30)), 1.5 + 2.0 * np.sin(np.radians(30)))
    world = World(segments_m=np.vstack((polyline([(2.0, -2.5), (2.0, -0.5)]), polyline([(0.5, 1.5), tip]))),
                  name="two_families")
    pts = scan_points(world, (0.0, 0.0, 0.0))
    lenient = wall_direction(pts, WallDirectionParams(min_support_frac=0.3))
    assert lenient is not None and 0.4 < lenient.support_frac < 0.6  # the lines are found ...
    assert wall_direction(pts, WallDirectionParams()) is None  # ... but no direction has 60 % of them


def test_scatter_between_lines_widens_sigma():
    # Two clean walls 0.04 rad apart (inside the alignment tolerance): each fit is
    # exact, so only the Birge ratio can make sigma reflect their disagreement.
    t = np.linspace(-1.5, 1.5, 60)
    a = np.column_stack((2.0 + 0 * t, t))
    tilt = 0.04
    b = np.column_stack((-2.0 + t * np.sin(tilt), 5.0 + t * np.cos(tilt)))
    wd = wall_direction(np.vstack((a, b)), WallDirectionParams())
    assert wd is not None and wd.n_lines == 2
    assert wrap_quarter(wd.direction_rad - np.pi / 2) == pytest.approx(-tilt / 2, abs=1e-6)
    assert 0.015 < wd.sigma_rad < 0.03  # the half-spread of two lines, not the 0.1 mrad of either fit
    precise = wall_direction(a, WallDirectionParams(min_support_length_m=0.5))
    assert precise is not None and precise.sigma_rad < 0.001


def test_too_few_points_and_bad_input():
    params = WallDirectionParams()
    assert wall_direction(np.zeros((0, 2)), params) is None
    assert wall_direction(np.column_stack((np.full(5, 2.0), np.linspace(0, 1, 5))), params) is None
    with pytest.raises(InputError):
        wall_direction(np.array([[1.0, np.nan]] * 10), params)


@pytest.mark.parametrize(
    "kwargs",
    [{"min_support_frac": 0.0}, {"min_support_frac": 1.5}, {"min_support_length_m": 0.0},
     {"min_support_length_m": float("nan")}],
)
def test_bad_params_raise(kwargs):
    with pytest.raises(ConfigError):
        WallDirectionParams(**kwargs)
