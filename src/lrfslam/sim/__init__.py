"""Pure simulator of a SICK LMS200 robot driving round an indoor segment map.

``world`` (wall segments and their corner ground truth) and ``floor_plans`` (the
built-in worlds) hold the maps, ``lidar`` the ray caster and scanner error model, ``trajectory`` and ``odometry`` the true and
measured motion, ``truth`` per-pose corner visibility, and ``simulator`` ties them
into an endless, seeded stream of frames.
"""

from lrfslam.sim.lidar import LidarModel, SimScan, raycast, simulate_scan
from lrfslam.sim.odometry import OdometryNoise, integrate_odometry, noisy_increment
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
    "World",
    "integrate_odometry",
    "noisy_increment",
    "raycast",
    "simulate_scan",
]
