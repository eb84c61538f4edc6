"""Built-in worlds: the hallway loop driven by ``lrfslam up``, the large worlds, and small test scenes.

A registered world is a :class:`Scenario`: the map, the loop the robot drives, and
what comes with the place (people pacing its corridors, the robot's odometry
calibration), so a world name alone selects a whole experiment. The large worlds
are in ``buildings``.

All maps are Manhattan-style, as the paper assumes (straight walls, right-angle
corners, hallways at least 1.5 m wide). The small scenes put the robot at the
origin facing +x unless stated otherwise.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from lrfslam.errors import ConfigError
from lrfslam.sim import buildings
from lrfslam.sim.odometry import CALIBRATED, REALISTIC, SystematicOdometryError
from lrfslam.sim.world import World, closed_polygon, polyline

# fmt: off
# Outer boundary of the hallway loop, free space inside. Corridors: bottom 2.0 m,
# right 2.2 m, top 2.0 m, left 1.8 m, so widths vary but stay above the paper's 1.5 m.
# Bays and alcoves are at least 1.3 m deep and 2 m wide, so both walls of their
# corners reach past the 1.2 m search arms; door recesses (0.3-0.5 m) do not.
_HALLWAY_OUTER = (
    (-1.8, -2.0),
    # closed door, recessed 0.4 m
    (3.0, -2.0), (3.0, -2.4), (3.9, -2.4), (3.9, -2.0),
    # stair landing, 2 m x 1.3 m
    (5.0, -2.0), (5.0, -3.3), (7.0, -3.3), (7.0, -2.0),
    # open 1 m doorway through a 0.15 m wall into a 5 m x 2.35 m room: jump edges at the jambs
    (10.0, -2.0), (10.0, -2.15), (8.5, -2.15), (8.5, -4.5),
    (13.5, -4.5), (13.5, -2.15), (11.0, -2.15), (11.0, -2.0),
    (18.2, -2.0),
    # waiting bay, 2 m x 1.3 m
    (18.2, 0.8), (19.5, 0.8), (19.5, 2.8), (18.2, 2.8),
    # side corridor, 1.8 m wide, deeper than the 8 m scanner limit: finite/no-return edges
    (18.2, 4.0), (27.0, 4.0), (27.0, 5.8), (18.2, 5.8),
    # copier alcove, 2 m x 1.3 m
    (18.2, 8.0), (19.5, 8.0), (19.5, 10.0), (18.2, 10.0),
    (18.2, 12.0),
    # closed door recessed 0.35 m
    (12.95, 12.0), (12.95, 12.35), (12.0, 12.35), (12.0, 12.0),
    # alcove 2 m wide, 1.4 m deep
    (10.0, 12.0), (10.0, 13.4), (8.0, 13.4), (8.0, 12.0),
    # closed door recessed 0.5 m
    (5.9, 12.0), (5.9, 12.5), (5.0, 12.5), (5.0, 12.0),
    # stair landing, 2 m x 1.3 m
    (2.5, 12.0), (2.5, 13.3), (0.5, 13.3), (0.5, 12.0),
    (-1.8, 12.0),
    # closed door recessed 0.3 m
    (-1.8, 5.4), (-2.1, 5.4), (-2.1, 4.5), (-1.8, 4.5),
    # alcove 2.2 m wide, 1.3 m deep
    (-1.8, 3.2), (-3.1, 3.2), (-3.1, 1.0), (-1.8, 1.0),
)

# The 16 m x 10 m core the corridor runs round (lifts, stairs, services), solid
# inside, with two door recesses and a lift lobby and service alcoves 1.3 m deep.
_HALLWAY_BLOCK = (
    (0.0, 0.0),
    # service alcove
    (1.0, 0.0), (1.0, 1.3), (3.0, 1.3), (3.0, 0.0),
    # closed door recessed 0.4 m
    (6.0, 0.0), (6.0, 0.4), (6.9, 0.4), (6.9, 0.0),
    # lift lobby, 3 m wide
    (9.5, 0.0), (9.5, 1.3), (12.5, 1.3), (12.5, 0.0),
    (16.0, 0.0),
    # closed door recessed 0.3 m
    (16.0, 2.0), (15.7, 2.0), (15.7, 2.95), (16.0, 2.95),
    # service alcove
    (16.0, 5.5), (14.7, 5.5), (14.7, 7.5), (16.0, 7.5),
    (16.0, 10.0),
    # service alcove
    (14.0, 10.0), (14.0, 8.7), (12.0, 8.7), (12.0, 10.0),
    # lift lobby, 3 m wide
    (6.5, 10.0), (6.5, 8.7), (3.5, 8.7), (3.5, 10.0),
    (0.0, 10.0),
    # service alcove
    (0.0, 8.0), (1.3, 8.0), (1.3, 6.0), (0.0, 6.0),
    # service alcove
    (0.0, 3.5), (1.3, 3.5), (1.3, 1.5), (0.0, 1.5),
)
# fmt: on

# Corridor centrelines, counter-clockwise round the block; starts mid-corridor so the
# first scans are not taken in a turn.
_HALLWAY_PATH = ((8.0, -1.0), (17.1, -1.0), (17.1, 11.0), (-0.9, 11.0), (-0.9, -1.0))


def hallway_loop() -> World:
    """Office floor: a corridor loop round a 16 m x 10 m core, with doors, bays, alcoves, a room and a side corridor.

    The core holds two lift lobbies and five service alcoves, the outer wall two
    stair landings, a waiting bay, a copier alcove and two older alcoves (all at
    least 1.3 m deep and 2 m wide), besides four shallow door recesses, an open
    doorway into a room and a side corridor. Without them a 4 m scanner would see
    no corner with two 1.2 m walls along most of the loop (docs/slam.md).

    Returns
    -------
    World
        96 axis-aligned walls meeting in 96 right-angle corners (48 concave, 48 convex);
        no free wall ends.
    """
    segments = np.vstack(
        (closed_polygon(_HALLWAY_OUTER, free_inside=True), closed_polygon(_HALLWAY_BLOCK, free_inside=False))
    )
    return World(segments_m=segments, name="hallway_loop")


def hallway_loop_path() -> np.ndarray:
    """Closed loop through the corridor centrelines of :func:`hallway_loop`.

    Returns
    -------
    ndarray, shape (5, 2)
        Waypoints in metres, counter-clockwise; the loop closes from the last back to the first.
    """
    return np.array(_HALLWAY_PATH, dtype=float)


@dataclass(frozen=True)
class Scenario:
    """A registered world and what comes with it.

    Attributes
    ----------
    build : callable () -> World
    path : callable () -> ndarray, shape (P, 2)
        Closed-loop waypoints, metres.
    walker_lanes_m : ndarray, shape (L, 4)
        Lanes people may pace, metres (see ``people``).
    n_walkers : int
        People on those lanes unless ``SimConfig.n_walkers`` says otherwise.
    odometry_error : SystematicOdometryError
        The robot's calibration errors and slip unless ``SimConfig.odometry_error`` says otherwise.
    """

    build: Callable[[], World]
    path: Callable[[], np.ndarray]
    walker_lanes_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    n_walkers: int = 0
    odometry_error: SystematicOdometryError = CALIBRATED


_SCENARIOS = {
    "hallway_loop": Scenario(hallway_loop, hallway_loop_path),
    # What ACES is: a big building, people, clutter, glass, and an uncalibrated robot.
    "large_building": Scenario(buildings.large_building, buildings.large_building_path,
                               buildings.large_building_lanes(), n_walkers=6, odometry_error=REALISTIC),
    # The same map with one ingredient each, so a command line can tell which one breaks a filter.
    "large_building_empty": Scenario(buildings.large_building, buildings.large_building_path),
    "large_building_uncalibrated": Scenario(buildings.large_building, buildings.large_building_path,
                                            odometry_error=REALISTIC),
    "large_building_people": Scenario(buildings.large_building, buildings.large_building_path,
                                      buildings.large_building_lanes(), n_walkers=6),
    # Only the aliasing: a calibrated robot, nobody about.
    "twin_corridors": Scenario(buildings.twin_corridors, buildings.twin_corridors_path),
    # What MIT Killian Court is: alike corridors, a blind crossing, an uncalibrated robot, long laps.
    "campus": Scenario(buildings.campus, buildings.campus_path, odometry_error=REALISTIC),
}


def world_names() -> tuple[str, ...]:
    """Names accepted by :func:`scenario`, :func:`build_world` and :func:`waypoints`."""
    return tuple(_SCENARIOS)


def build_world(world_name: str) -> World:
    """Build a registered world by name; raises ConfigError for an unknown name."""
    return scenario(world_name).build()


def waypoints(world_name: str) -> np.ndarray:
    """Closed-loop waypoints (P, 2), metres, of a registered world."""
    return scenario(world_name).path()


def scenario(world_name: str) -> Scenario:
    """The registered :class:`Scenario` of that name; raises ConfigError for an unknown name."""
    try:
        return _SCENARIOS[world_name]
    except KeyError:
        raise ConfigError(f"unknown world {world_name!r}; known: {', '.join(world_names())}") from None


def l_corner(arm_m: float = 4.0, angle_deg: float = 90.0, corner_xy_m=(2.0, 0.0)) -> World:
    """Two walls meeting at ``corner_xy_m``, opening towards the origin.

    The walls leave the corner at bearings 180° ± angle_deg/2, so a robot at the origin
    facing +x looks straight into a concave corner.

    Parameters
    ----------
    arm_m : float
        Length of each wall, metres.
    angle_deg : float
        Angle between the walls, degrees.
    corner_xy_m : array_like, shape (2,)
        Corner position, metres.
    """
    c = np.asarray(corner_xy_m, dtype=float)
    half = np.radians(angle_deg) / 2.0
    lower = c + arm_m * np.array([np.cos(np.pi + half), np.sin(np.pi + half)])
    upper = c + arm_m * np.array([np.cos(np.pi - half), np.sin(np.pi - half)])
    return World(segments_m=polyline([lower, c, upper]), name=f"l_corner_{angle_deg:g}deg")


def straight_wall(length_m: float = 6.0, distance_m: float = 2.0) -> World:
    """One wall across the view at x = ``distance_m``, centred on y = 0, facing the origin."""
    half = length_m / 2.0
    return World(segments_m=polyline([(distance_m, -half), (distance_m, half)]), name="straight_wall")


def corridor_end(width_m: float = 1.6, length_m: float = 6.0, end_x_m: float = 3.0) -> World:
    """A corridor along +x closed by a short end wall at x = ``end_x_m``: two concave corners.

    Parameters
    ----------
    width_m : float
        Corridor width, metres; the side walls are at y = ±width_m/2.
    length_m : float
        Length of the side walls, metres, ending at the end wall.
    end_x_m : float
        Position of the end wall, metres.
    """
    half = width_m / 2.0
    start = end_x_m - length_m
    chain = [(start, -half), (end_x_m, -half), (end_x_m, half), (start, half)]
    return World(segments_m=polyline(chain), name="corridor_end")


def doorway_room(
    door_width_m: float = 1.0, wall_x_m: float = 1.0, room_depth_m: float = 2.5, half_width_m: float = 3.0
) -> World:
    """A thin wall ahead with a doorway centred on y = 0, and the room's far wall behind it.

    The door jambs are free wall ends at (wall_x_m, ±door_width_m/2); the far wall is at
    x = wall_x_m + room_depth_m. Walls span y = ±half_width_m.
    """
    h = door_width_m / 2.0
    far_x = wall_x_m + room_depth_m
    segments = np.vstack(
        (
            polyline([(wall_x_m, -half_width_m), (wall_x_m, -h)]),
            polyline([(wall_x_m, h), (wall_x_m, half_width_m)]),
            polyline([(far_x, -half_width_m), (far_x, half_width_m)]),
        )
    )
    return World(segments_m=segments, name="doorway_room")
