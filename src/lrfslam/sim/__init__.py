"""Pure simulator of a SICK LMS200 robot driving round an indoor segment map.

``world`` (wall, glass and clutter segments and their corner ground truth),
``floor_plans`` (the registered worlds) and ``buildings`` (the large ones) hold the
maps, ``people`` the walkers that hide them, ``lidar`` the ray caster and scanner
error model, ``trajectory`` and ``odometry`` the true and measured motion (random
walks, calibration errors, slip), ``truth`` per-pose corner visibility, and
``simulator`` ties them into an endless, seeded stream of frames.
"""

from lrfslam.sim.lidar import LidarModel, SimScan, raycast, simulate_scan
from lrfslam.sim.odometry import (
    OdometryNoise,
    SystematicOdometryError,
    biased_increment,
    integrate_odometry,
    noisy_increment,
)
from lrfslam.sim.people import Walkers
from lrfslam.sim.simulator import SimConfig, SimFrame, Simulator
from lrfslam.sim.world import MapCorners, World

__all__ = [
    "LidarModel",
    "MapCorners",
    "OdometryNoise",
    "SimConfig",
    "SimFrame",
    "SimScan",
    "Simulator",
    "SystematicOdometryError",
    "Walkers",
    "World",
    "biased_increment",
    "integrate_odometry",
    "noisy_increment",
    "raycast",
    "simulate_scan",
]
