"""The whole simulated robot: true loop motion, drifting odometry, LMS200 scans, corner truth.

Scan noise, odometry noise, wheel slip and the people's walks come from independent
generators spawned from the one seed, so changing the scanner model leaves the
odometry drift of a run unchanged (and vice versa), and the same config always gives
the same frames. Worlds without slip or people give the frames they gave before
those existed.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from lrfslam.algo.geometry import compose, relative
from lrfslam.sim.floor_plans import scenario
from lrfslam.sim.lidar import LidarModel, SimScan, simulate_scan
from lrfslam.sim.odometry import (
    OdometryNoise,
    SystematicOdometryError,
    biased_increment,
    noisy_increment,
)
from lrfslam.sim.people import Walkers, draw_walkers
from lrfslam.sim.trajectory import LoopTrajectory, loop_path
from lrfslam.sim.truth import corners_in_robot_frame, visible_corners
from lrfslam.sim.world import MapCorners, World


@dataclass(frozen=True)
class SimConfig:
    """Everything that determines a simulated run.

    Attributes
    ----------
    world_name : str
        A name from :func:`lrfslam.sim.floor_plans.world_names`.
    lidar : LidarModel
    odometry : OdometryNoise
        The random walks of the odometry error.
    odometry_error : SystematicOdometryError or None
        Calibration errors and slip; None takes the world's (``floor_plans.Scenario``).
    n_walkers : int or None
        People pacing the world's corridors; None takes the world's number.
    speed_mps : float
        Forward speed along the loop, m/s.
    rate_hz : float
        Scan and odometry rate, Hz.
    corner_radius_m : float
        Radius of the rounded loop corners; the turn rate is ``speed_mps / corner_radius_m``.
    truth_max_range_m : float
        Range within which corners count as visible (the paper's 4 m cut), metres.
    start_m : float
        Where along the loop the run starts, metres of arc length (0: the first waypoint).
    seed : int
    """

    world_name: str = "hallway_loop"
    lidar: LidarModel = field(default_factory=LidarModel)
    odometry: OdometryNoise = field(default_factory=OdometryNoise)
    odometry_error: SystematicOdometryError | None = None
    n_walkers: int | None = None
    speed_mps: float = 0.5
    rate_hz: float = 10.0
    corner_radius_m: float = 0.8
    truth_max_range_m: float = 4.0
    start_m: float = 0.0
    seed: int = 0


@dataclass(frozen=True, eq=False)
class SimFrame:
    """One simulation step.

    Attributes
    ----------
    index : int
        Step number, from 0.
    t_s : float
        Simulated time ``index / rate_hz``, seconds.
    true_pose : ndarray, shape (3,)
        ``(x_m, y_m, theta_rad)`` in the world frame.
    odom_pose : ndarray, shape (3,)
        Integrated noisy odometry; equals ``true_pose`` at step 0.
    odom_delta : ndarray, shape (3,)
        Noisy increment from the previous step's odometry pose, in its frame; zeros at step 0.
    scan : SimScan
        Scan taken at ``true_pose``.
    visible_corner_ids : ndarray of int, shape (K,)
        Indices into :attr:`Simulator.map_corners` visible within ``truth_max_range_m``
        (people may hide them; glass does not).
    visible_corners_robot_xy : ndarray, shape (K, 2)
        Those corners in the true robot frame, metres.
    walkers_xy : ndarray, shape (P, 2)
        Where the people are, world frame, metres.
    """

    index: int
    t_s: float
    true_pose: np.ndarray
    odom_pose: np.ndarray
    odom_delta: np.ndarray
    scan: SimScan
    visible_corner_ids: np.ndarray
    visible_corners_robot_xy: np.ndarray
    walkers_xy: np.ndarray


class Simulator:
    """Endless iterator of :class:`SimFrame` for one :class:`SimConfig`.

    Parameters
    ----------
    config : SimConfig
        Raises :class:`~lrfslam.errors.ConfigError` for an unknown world or bad values.

    Attributes
    ----------
    world : World
    map_corners : MapCorners
        Ground-truth corners; ``SimFrame.visible_corner_ids`` index into them.
    trajectory : LoopTrajectory
    range_bias_m : float
        The run's systematic range offset, drawn once from ``lidar.range_bias_sigma_m``.
    odometry_error : SystematicOdometryError
        The calibration errors and slip in force (the config's, else the world's).
    walkers : Walkers
        The people of this run, drawn from the seed.
    """

    def __init__(self, config: SimConfig) -> None:
        self.config = config
        place = scenario(config.world_name)
        self.world: World = place.build()
        self.map_corners: MapCorners = self.world.corners()
        self.trajectory = LoopTrajectory(
            loop_path(place.path(), config.corner_radius_m), config.speed_mps, config.rate_hz, config.start_m
        )
        self.odometry_error = place.odometry_error if config.odometry_error is None else config.odometry_error
        root = np.random.default_rng(config.seed)
        # Spawned after the first two, so the scan and odometry streams are what they were before slip and people.
        self._scan_rng, self._odom_rng = root.spawn(2)
        self._slip_rng, walker_rng = root.spawn(2)
        n_walkers = place.n_walkers if config.n_walkers is None else config.n_walkers
        self.walkers: Walkers = draw_walkers(place.walker_lanes_m, n_walkers, walker_rng)
        self.range_bias_m = float(self._scan_rng.standard_normal() * config.lidar.range_bias_sigma_m)
        self._index = 0
        self._true_pose = self.trajectory.pose(0)
        self._odom_pose = self._true_pose.copy()

    def __iter__(self) -> Iterator[SimFrame]:
        return self

    def __next__(self) -> SimFrame:
        index = self._index
        true_pose = self.trajectory.pose(index)
        odom_delta = np.zeros(3)
        if index > 0:
            wheels = biased_increment(relative(self._true_pose, true_pose), self.odometry_error, self._slip_rng)
            odom_delta = noisy_increment(wheels, self.config.odometry, self._odom_rng)
            self._odom_pose = compose(self._odom_pose, odom_delta)
        self._true_pose = true_pose
        self._index += 1

        cfg = self.config
        t_s = index / cfg.rate_hz
        movers = self.walkers.segments(t_s)
        ids = visible_corners(self.world, true_pose, cfg.truth_max_range_m, movers_m=movers)
        return SimFrame(
            index=index,
            t_s=t_s,
            true_pose=true_pose,
            odom_pose=self._odom_pose.copy(),
            odom_delta=odom_delta,
            scan=simulate_scan(self.world, true_pose, cfg.lidar, self._scan_rng, self.range_bias_m, movers),
            visible_corner_ids=ids,
            visible_corners_robot_xy=corners_in_robot_frame(self.world, true_pose, ids),
            walkers_xy=self.walkers.positions(t_s),
        )
