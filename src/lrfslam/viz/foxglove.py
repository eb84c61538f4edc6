"""Foxglove's views of the pipeline: lrfslam messages in, Foxglove's well-known messages out.

Foxglove and Lichtblick draw in their 3D panel only their own well-known schemas, which they
recognise by name (``foxglove.LaserScan``, …). :class:`FoxgloveViews` turns each lrfslam
message into such messages, built with foxglove-sdk's message classes (``foxglove.messages``)
and encoded by it as protobuf. No transport: the recorder writes the views beside the raw
channels, ``lrfslam export --foxglove`` adds them to an older recording, and ``lrfslam monitor``
serves them live (docs/monitoring.md lists the channels).

=========================  ==============================  ========================  ===========
lrfslam topic              view channel                    schema                    frame
=========================  ==============================  ========================  ===========
scan                       /foxglove/scan                  foxglove.LaserScan        laser
scan/filtered              /foxglove/scan/filtered         foxglove.LaserScan        laser
features                   /foxglove/features              foxglove.SceneUpdate      laser
slam/state, slam/map       /foxglove/landmarks             foxglove.SceneUpdate      slam
slam/state                 /foxglove/trajectory/slam       foxglove.PosesInFrame     slam
map/pose, map/keyframes    /foxglove/trajectory/map        foxglove.PosesInFrame     map
map/grid                   /foxglove/map                   foxglove.Grid             map
map/pose (on a saved map)  /foxglove/localization          foxglove.SceneUpdate      map
odom                       /foxglove/trajectory/odom       foxglove.PosesInFrame     odom
truth                      /foxglove/trajectory/truth      foxglove.PosesInFrame     world
odom, slam/state, map/pose /foxglove/tf                    foxglove.FrameTransforms  (tree below)
health/<service>           /foxglove/log                   foxglove.Log              —
=========================  ==============================  ========================  ===========

The frame tree: ``world`` → ``map`` → ``odom`` → ``base_link`` → ``laser``, and ``map`` →
``slam``. ``map`` is the loop-closed map (the mapper's), ``slam`` the EKF's frame, which holds
its landmarks and trajectory (the mapper's correction ``map/pose.map_from_slam`` moves it; the
identity until a loop closes or where no mapper runs). ``map`` → ``odom`` is the EKF's pose
corrected by the mapper, against the odometry at the same stamp (interpolated); without
odometry, ``odom`` is the ``slam`` frame and the EKF's pose places ``base_link``. The laser is
the robot's reference point (odometry is the laser's path, lrfslam/tools/importers.py), so
``base_link`` → ``laser`` is the identity. ``world`` is the simulator's frame of the ground
truth, tied to ``map`` by the first EKF pose that has a true pose at its stamp.

Each view carries its source's data stamp (a health status's is the wall clock); a
recording writes it as the view's ``publish_time`` and gives the view its source's
``log_time`` (lrfslam/runtime/recording.py). Scans, their kept points and features are viewed at
most every ``frame_period_s`` of data time (20 Hz), and so are the transforms of odometry, slam
states and map poses, so a 75 Hz sensor's recorder does not decode every scan only to draw it.
Trajectories are thinned (a pose every ``path_step_m`` or ``path_turn_rad``) and sent
at most every ``path_period_s`` of data time, a long one less often, so that their cost stays
bounded (:class:`ViewConfig`). The map is the mapper's tiles put together (``msgs/grid_replica.py``)
as one ``foxglove.Grid`` (Foxglove's 3D panel draws the newest message of a channel), one int8
field ``occupancy``: 100 occupied, 0 free, -1 unknown, as ``nav_msgs/OccupancyGrid``; it goes out
after a change at most every ``map_period_s`` of data time, and a large map less often (a second
per ``map_cells_per_s`` cells). On a saved map (``lrfslam up --map MAP --localize``) the
localization view says at the robot whether it is localized, with its position's 95 % ellipse,
or "not localized" in red, when that changes and at most every ``path_period_s`` of data time
otherwise. A service's health is logged when its level or message changes.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import foxglove.messages as fm
import numpy as np

from lrfslam.algo.geometry import compose, inverse
from lrfslam.algo.geometry import ellipse_axes as geometry_ellipse_axes
from lrfslam.algo.stream_alignment import interpolate_pose
from lrfslam.errors import ConfigError
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.msgs.grid_replica import GridImage, GridReplica
from lrfslam.msgs.landmark_map import LandmarkMapReplica
from lrfslam.viz.keyframe_path import KeyframePath

P = topics.FOXGLOVE_PREFIX
SCAN = P + "scan"
SCAN_FILTERED = P + "scan/filtered"
FEATURES = P + "features"
LANDMARKS = P + "landmarks"
TRAJECTORY_SLAM = P + "trajectory/slam"
TRAJECTORY_MAP = P + "trajectory/map"
TRAJECTORY_ODOM = P + "trajectory/odom"
TRAJECTORY_TRUTH = P + "trajectory/truth"
TF = P + "tf"
GRID = P + "map"
LOCALIZATION = P + "localization"
LOG = topics.FOXGLOVE_LOG

#: Every view channel and the foxglove-sdk message class it carries.
CHANNELS: dict[str, type] = {
    SCAN: fm.LaserScan, SCAN_FILTERED: fm.LaserScan, FEATURES: fm.SceneUpdate, LANDMARKS: fm.SceneUpdate,
    TRAJECTORY_SLAM: fm.PosesInFrame, TRAJECTORY_MAP: fm.PosesInFrame, TRAJECTORY_ODOM: fm.PosesInFrame,
    TRAJECTORY_TRUTH: fm.PosesInFrame, TF: fm.FrameTransforms, GRID: fm.Grid, LOG: fm.Log,
    LOCALIZATION: fm.SceneUpdate,
}

WORLD, MAP, SLAM, ODOM, BASE, LASER = "world", "map", "slam", "odom", "base_link", "laser"

#: The 95 % quantile of chi-square with 2 degrees of freedom, -2 ln 0.05 (exact for 2 d.o.f.):
#: a 2-D Gaussian's 95 % ellipse has semi-axes sqrt(CHI2_2D_95 × eigenvalue).
CHI2_2D_95 = -2.0 * math.log(0.05)

#: Colours (r, g, b, a in [0, 1]).
CORNER_RGBA = (1.0, 0.55, 0.0, 1.0)
JUMP_EDGE_RGBA = (0.1, 0.5, 1.0, 1.0)
LANDMARK_RGBA = (0.85, 0.1, 0.1, 1.0)
TENTATIVE_RGBA = (1.0, 0.45, 0.75, 1.0)
POSE_RGBA = (0.2, 0.8, 0.2, 1.0)
NOT_LOCALIZED_RGBA = (0.85, 0.1, 0.1, 1.0)
ELLIPSE_ALPHA = 0.35
MARKER_M = 0.06          # diameter of the dot at a feature or landmark
ELLIPSE_THICKNESS_M = 0.005
LABEL_PX = 12.0

LOG_LEVELS = {t.HEALTH_OK: fm.LogLevel.Info, t.HEALTH_WARN: fm.LogLevel.Warning,
              t.HEALTH_ERROR: fm.LogLevel.Error, t.HEALTH_STALE: fm.LogLevel.Warning}

_ODOMETRY_KEPT = 256     # odometry samples held to find the one at an EKF stamp
#: Topics whose only views are drawn with every scan: between two, their messages are not decoded.
_UNDECODED_BETWEEN = (topics.SCAN.name, topics.SCAN_FILTERED.name, topics.FEATURES.name)


@dataclass(frozen=True)
class ViewConfig:
    """How often the growing views are sent (times are data time)."""

    path_period_s: float = 1.0       # a trajectory is sent at most this often ...
    path_poses_per_s: float = 100.0  # ... and one of n poses at most every n / this s (~44 B a pose: 4.4 kB/s)
    path_step_m: float = 0.1         # a pose joins a trajectory once the robot moved this far ...
    path_turn_rad: float = 0.1       # ... or turned this much since the last pose kept
    #: Past this many poses a path keeps every other one: memory and message size stay bounded
    #: however long the run (an hour of driving at 0.5 m/s is 18,000 poses at path_step_m).
    path_max_poses: int = 4000
    landmark_period_s: float = 0.5   # landmarks at most this often; 0: with every slam/state
    map_period_s: float = 5.0        # the map at most this often (slam_toolbox's map_update_interval) ...
    map_cells_per_s: float = 200_000.0   # ... and a map of n cells at most every n / this s (200 kB/s)
    #: A view drawn with every scan (the scan, its kept points, its features, the transforms of its
    #: odometry, slam state and map pose) at most this often, each (20 Hz: smooth to the eye, where
    #: an LMS200 sends 75 scans/s); skipped scans, kept points and features are not even decoded.
    #: 0: every one.
    frame_period_s: float = 0.05

    def __post_init__(self) -> None:
        if min(self.path_period_s, self.path_step_m, self.path_turn_rad, self.landmark_period_s,
               self.frame_period_s) < 0 \
                or not self.path_poses_per_s > 0 or self.path_max_poses < 2:
            raise ConfigError(f"view periods and steps must be ≥ 0 and path_poses_per_s > 0: {self}")


@dataclass(frozen=True)
class View:
    """One Foxglove message on view channel ``topic``, stamped ``stamp_ns`` (its source's data stamp, ns)."""

    topic: str
    message: Any
    stamp_ns: int

    @property
    def schema(self) -> str:
        """Foxglove schema name, e.g. ``foxglove.LaserScan``."""
        return SCHEMA_NAMES[type(self.message)]

    def encode(self) -> bytes:
        """The message as protobuf (foxglove-sdk's encoding)."""
        return self.message.encode()


def schema_of(cls: type) -> Any:
    """foxglove-sdk's ``Schema`` (name, encoding ``protobuf``, FileDescriptorSet) of a message class."""
    return cls.get_schema()


#: Schema name of each message class used by a view channel.
SCHEMA_NAMES: dict[type, str] = {cls: schema_of(cls).name for cls in set(CHANNELS.values())}


def schema_sets() -> dict[str, bytes]:
    """Protobuf FileDescriptorSet of every view schema, by schema name (to embed in a recording)."""
    return {schema_of(cls).name: bytes(schema_of(cls).data) for cls in set(CHANNELS.values())}


# ---- building blocks ---------------------------------------------------------------------------


def timestamp(stamp_ns: int) -> fm.Timestamp:
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    return fm.Timestamp(sec, nsec)


def quaternion(yaw_rad: float) -> fm.Quaternion:
    """Rotation by ``yaw_rad`` about z."""
    return fm.Quaternion(x=0.0, y=0.0, z=math.sin(0.5 * yaw_rad), w=math.cos(0.5 * yaw_rad))


def pose(x_m: float, y_m: float, yaw_rad: float = 0.0, z_m: float = 0.0) -> fm.Pose:
    return fm.Pose(position=fm.Vector3(x=float(x_m), y=float(y_m), z=float(z_m)), orientation=quaternion(float(yaw_rad)))


def color(rgba: tuple[float, float, float, float], alpha: float | None = None) -> fm.Color:
    r, g, b, a = rgba
    return fm.Color(r=r, g=g, b=b, a=a if alpha is None else alpha)


def ellipse_axes(cov_m2: np.ndarray) -> tuple[float, float, float]:
    """The 95 % ellipse of a 2-D Gaussian with covariance ``cov_m2`` (2, 2), m²: ``(major_m, minor_m,
    yaw_rad)``, semi-axes ``sqrt(CHI2_2D_95 × eigenvalue)`` (:func:`lrfslam.algo.geometry.ellipse_axes`)."""
    return geometry_ellipse_axes(cov_m2, CHI2_2D_95)


def ellipse(x_m: float, y_m: float, cov_m2: np.ndarray, rgba) -> fm.SpherePrimitive:
    """A flat ellipsoid whose x and y diameters are the 95 % ellipse's axes, around (x_m, y_m)."""
    major, minor, yaw = ellipse_axes(cov_m2)
    return fm.SpherePrimitive(pose=pose(x_m, y_m, yaw),
                              size=fm.Vector3(x=2 * major, y=2 * minor, z=ELLIPSE_THICKNESS_M),
                              color=color(rgba, ELLIPSE_ALPHA))


def marker(x_m: float, y_m: float, rgba) -> fm.SpherePrimitive:
    return fm.SpherePrimitive(pose=pose(x_m, y_m), size=fm.Vector3(x=MARKER_M, y=MARKER_M, z=MARKER_M),
                              color=color(rgba))


def label(x_m: float, y_m: float, text: str, rgba) -> fm.TextPrimitive:
    return fm.TextPrimitive(pose=pose(x_m, y_m, z_m=0.1), billboard=True, font_size=LABEL_PX, scale_invariant=True,
                            color=color(rgba), text=text)


def replace_all(stamp_ns: int, entities: list[fm.SceneEntity]) -> fm.SceneUpdate:
    """A scene update that replaces everything its channel showed before ``stamp_ns`` by ``entities``."""
    deletion = fm.SceneEntityDeletion(timestamp=timestamp(stamp_ns), type=fm.SceneEntityDeletionType.All)
    return fm.SceneUpdate(deletions=[deletion], entities=entities)


def transform(stamp_ns: int, parent: str, child: str, p) -> fm.FrameTransform:
    """``child``'s frame placed at pose ``p`` (x m, y m, theta rad) in ``parent``'s."""
    return fm.FrameTransform(timestamp=timestamp(stamp_ns), parent_frame_id=parent, child_frame_id=child,
                             translation=fm.Vector3(x=float(p[0]), y=float(p[1]), z=0.0), rotation=quaternion(float(p[2])))


# ---- stateless conversions ---------------------------------------------------------------------


def laser_scan(scan: t.LaserScan, ranges_m: np.ndarray | None = None) -> fm.LaserScan:
    """The scan as ``foxglove.LaserScan`` in its own frame; ``ranges_m`` replaces its ranges.

    Ranges are passed as they are: +inf where a beam had no return, NaN where it was
    invalid (the 3D panel draws neither).
    """
    ranges = scan.ranges_m if ranges_m is None else ranges_m
    n = ranges.size
    return fm.LaserScan(timestamp=timestamp(scan.stamp_ns), frame_id=scan.frame_id or LASER, pose=pose(0.0, 0.0),
                        start_angle=float(scan.angle_min_rad),
                        end_angle=float(scan.angle_min_rad + max(n - 1, 0) * scan.angle_increment_rad),
                        ranges=ranges.tolist())


def kept_scan(filtered: t.FilteredScan) -> fm.LaserScan:
    """The beams the denoiser kept, as a scan whose other beams are NaN."""
    ranges = np.full(filtered.scan.ranges_m.size, np.nan)
    ranges[filtered.kept_beams] = filtered.scan.ranges_m[filtered.kept_beams]
    return laser_scan(filtered.scan, ranges)


def features_scene(features: t.Features) -> fm.SceneUpdate:
    """Corners and jump edges of one scan with their 95 % ellipses, in the laser frame; replaces the last scan's."""
    ts = timestamp(features.stamp_ns)
    entities = []
    for i in range(len(features)):
        corner = features.kind[i] == t.FEATURE_FORWARD
        name, rgba = ("corner", CORNER_RGBA) if corner else ("jump_edge", JUMP_EDGE_RGBA)
        x, y = features.xy_m[i]
        meta = [fm.KeyValuePair(key="kind", value=name), fm.KeyValuePair(key="beam", value=str(int(features.beam[i])))]
        if corner:
            meta.append(fm.KeyValuePair(key="angle_deg", value=f"{features.angle_deg[i]:.1f}"))
        entities.append(fm.SceneEntity(timestamp=ts, frame_id=LASER, id=f"{name}/{i}", metadata=meta,
                                       spheres=[marker(x, y, rgba), ellipse(x, y, features.cov_m2[i], rgba)]))
    return replace_all(features.stamp_ns, entities)


def landmarks_scene(state: t.SlamState, landmarks: t.Landmarks) -> fm.SceneUpdate:
    """The EKF's ``landmarks`` (its map at ``state``) with 95 % ellipses and ids, and the robot's position
    ellipse, in the slam frame."""
    ts = timestamp(state.stamp_ns)
    entities = []
    for i, lid in enumerate(landmarks.ids):
        rgba = LANDMARK_RGBA if landmarks.confirmed[i] else TENTATIVE_RGBA
        x, y = landmarks.xy_m[i]
        meta = [fm.KeyValuePair(key="sightings", value=str(int(landmarks.sightings[i]))),
                fm.KeyValuePair(key="confirmed", value=str(bool(landmarks.confirmed[i])).lower()),
                fm.KeyValuePair(key="kind", value="corner" if landmarks.kind[i] == t.FEATURE_FORWARD
                                else "jump_edge")]
        entities.append(fm.SceneEntity(timestamp=ts, frame_id=SLAM, id=f"landmark/{int(lid)}", metadata=meta,
                                       spheres=[marker(x, y, rgba), ellipse(x, y, landmarks.cov_m2[i], rgba)],
                                       texts=[label(x, y, str(int(lid)), rgba)]))
    x, y, _ = state.pose
    entities.append(fm.SceneEntity(timestamp=ts, frame_id=SLAM, id="pose",
                                   spheres=[ellipse(x, y, state.pose_cov[:2, :2], POSE_RGBA)]))
    return replace_all(state.stamp_ns, entities)


def localization_scene(mp: t.MapPose) -> fm.SceneUpdate:
    """On a saved map: at the robot's pose in ``map``, its position's 95 % ellipse and "localized", or
    "not localized" in red (the pose is then the dead-reckoned guess)."""
    ts = timestamp(mp.stamp_ns)
    x, y, _ = mp.pose
    if mp.localization == t.LOCALIZED:
        spheres = [ellipse(x, y, mp.pose_cov[:2, :2], POSE_RGBA)] if mp.pose_cov is not None else []
        entity = fm.SceneEntity(timestamp=ts, frame_id=MAP, id="localization", spheres=spheres,
                                texts=[label(x, y, "localized", POSE_RGBA)])
    else:
        entity = fm.SceneEntity(timestamp=ts, frame_id=MAP, id="localization",
                                texts=[label(x, y, "not localized", NOT_LOCALIZED_RGBA)])
    return replace_all(mp.stamp_ns, [entity])


def occupancy_grid(stamp_ns: int, image: GridImage) -> fm.Grid:
    """``foxglove.Grid`` of the map in frame ``map``: one int8 field ``occupancy`` per cell (100, 0, -1)."""
    w = image.cells.shape[1]
    return fm.Grid(timestamp=timestamp(stamp_ns), frame_id=MAP, pose=pose(*image.origin_xy_m), column_count=w,
                   cell_size=fm.Vector2(x=image.resolution_m, y=image.resolution_m), row_stride=w, cell_stride=1,
                   fields=[fm.PackedElementField(name="occupancy", offset=0, type=fm.PackedElementFieldNumericType.Int8)],
                   data=image.cells.tobytes())


def health_log(status: t.ServiceStatus) -> fm.Log:
    return fm.Log(timestamp=timestamp(status.wall_stamp_ns), level=LOG_LEVELS.get(status.level, fm.LogLevel.Unknown),
                  message=status.message, name=status.service)


# ---- stateful views ----------------------------------------------------------------------------


class Trajectory:
    """A growing path sent as ``foxglove.PosesInFrame``: thinned, and sent at a bounded rate."""

    def __init__(self, frame: str, cfg: ViewConfig) -> None:
        self.frame = frame
        self.cfg = cfg
        self.fixed: list[np.ndarray] = []                 # poses set by :meth:`replace`, kept whole
        self.kept: list[tuple[int, np.ndarray]] = []      # (stamp ns, pose) thinned
        self.latest: tuple[int, np.ndarray] | None = None  # the newest pose, also when thinned away
        self.sent_ns: int | None = None
        # One of every ``stride`` poses that moved far enough is kept; it doubles whenever the
        # path is halved, so the thinning stays even along the whole path.
        self._stride = 1
        self._candidates = 0

    def add(self, stamp_ns: int, p: np.ndarray) -> fm.PosesInFrame | None:
        """Append pose ``p`` (3,) at ``stamp_ns``; the path if it is due."""
        p = np.array(p, float)
        last = self.kept[-1][1] if self.kept else None
        if last is None or (math.hypot(p[0] - last[0], p[1] - last[1]) >= self.cfg.path_step_m
                            or abs(math.remainder(p[2] - last[2], 2 * math.pi)) >= self.cfg.path_turn_rad):
            self._candidates += 1
        if last is None or self._candidates >= self._stride:
            self._candidates = 0
            self.kept.append((stamp_ns, p))
            if len(self.fixed) + len(self.kept) > self.cfg.path_max_poses:
                self.kept = self.kept[-1::-2][::-1]   # every other one, the newest kept
                self._stride *= 2
        self.latest = (stamp_ns, p)
        n = len(self.fixed) + len(self.kept)
        wait_ns = 1e9 * max(self.cfg.path_period_s, n / self.cfg.path_poses_per_s)
        # A stamp before the last one sent (a restarted source) sends at once.
        if self.sent_ns is None or not 0 <= stamp_ns - self.sent_ns < wait_ns:
            return self.message(stamp_ns)
        return None

    def replace(self, stamp_ns: int, poses: np.ndarray, until_ns: int) -> fm.PosesInFrame:
        """Make ``poses`` (K, 3) the path up to ``until_ns`` (the poses added since stay after them); send it."""
        poses = np.asarray(poses, float).reshape(-1, 3)
        step = -(-len(poses) // (self.cfg.path_max_poses // 2)) if len(poses) else 1
        self.fixed = [np.array(p) for p in poses[::-1][::step][::-1]]   # the newest kept
        self.kept = [(s, p) for s, p in self.kept if s > until_ns]
        if self.latest is not None and self.latest[0] <= until_ns:
            self.latest = None
        return self.message(stamp_ns)

    def message(self, stamp_ns: int) -> fm.PosesInFrame:
        """The path now, stamped ``stamp_ns``: ends at the newest pose."""
        self.sent_ns = stamp_ns
        poses = self.fixed + [p for _, p in self.kept]
        if self.latest is not None and (not self.kept or self.kept[-1][0] != self.latest[0]):
            poses.append(self.latest[1])
        return fm.PosesInFrame(timestamp=timestamp(stamp_ns), frame_id=self.frame,
                               poses=[pose(x, y, th) for x, y, th in poses])


class FoxgloveViews:
    """Turns the stream of one robot's messages into Foxglove views (see the module docstring).

    Feed every message in log-time order to :meth:`convert` (decoded) or :meth:`from_payload`
    (as recorded or received).
    """

    def __init__(self, cfg: ViewConfig | None = None) -> None:
        self.cfg = cfg or ViewConfig()
        self.paths = {name: Trajectory(frame, self.cfg) for name, frame in (
            (TRAJECTORY_SLAM, SLAM), (TRAJECTORY_MAP, MAP), (TRAJECTORY_ODOM, ODOM), (TRAJECTORY_TRUTH, WORLD))}
        self._odom: deque[tuple[int, np.ndarray]] = deque(maxlen=_ODOMETRY_KEPT)
        self._truth: deque[tuple[int, np.ndarray]] = deque(maxlen=_ODOMETRY_KEPT)
        self._map_from_slam = np.zeros(3)
        self._world_from_map: np.ndarray | None = None
        self._landmarks_sent_ns: int | None = None
        self._map = LandmarkMapReplica()
        self._keyframe_path = KeyframePath(self.cfg.path_max_poses // 4)
        self._grid = GridReplica()
        self._grid_due_ns: int | None = None
        self._health: dict[str, tuple[int, str]] = {}
        self._localization: tuple[int, int] | None = None   # (status, data stamp) last shown
        # topic drawn with every scan -> data stamp of its last view
        self._frame_sent_ns: dict[str, int | None] = dict.fromkeys(
            (*_UNDECODED_BETWEEN, topics.ODOM.name, topics.SLAM_STATE.name, topics.MAP_POSE.name))
        self._handlers: dict[str, Callable[[Any, int], list[View]]] = {
            topics.SCAN.name: self._scan, topics.SCAN_FILTERED.name: self._filtered,
            topics.FEATURES.name: self._features, topics.SLAM_STATE.name: self._slam, topics.SLAM_MAP.name: self._map_of,
            topics.ODOM.name: self._odometry, topics.TRUTH.name: self._ground_truth,
            topics.MAP_POSE.name: self._map_pose, topics.MAP_KEYFRAMES.name: self._keyframes,
            topics.MAP_GRID.name: self._map_grid,
        }

    def viewed(self, name: str) -> bool:
        """Whether messages on lrfslam topic ``name`` have views."""
        return name in self._handlers or topics.is_health(name)

    def _due(self, name: str, stamp_ns: int) -> bool:
        """Whether a view drawn with every scan is due for a message on ``name`` at ``stamp_ns``: at
        most every ``frame_period_s`` of data time (a step back starts afresh); other topics' always."""
        sent = self._frame_sent_ns.get(name)
        return sent is None or not 0 <= stamp_ns - sent < self.cfg.frame_period_s * 1e9

    def _frame_due(self, name: str, stamp_ns: int) -> bool:
        """:meth:`_due`, and if so, counted as sent."""
        if not self._due(name, stamp_ns):
            return False
        self._frame_sent_ns[name] = stamp_ns
        return True

    def from_payload(self, name: str, schema: str, data: bytes, stamp_ns: int) -> list[View]:
        """The views of one recorded or received payload on lrfslam topic ``name``; [] if it has none.

        Raises
        ------
        DecodeError
            The payload does not decode with ``schema`` (:class:`SchemaVersionError`: an unknown schema).
        """
        if not self.viewed(name) or (name in _UNDECODED_BETWEEN and not self._due(name, stamp_ns)):
            return []
        return self.convert(name, topics.by_name(name).codec.decode(data, schema), stamp_ns)

    def convert(self, name: str, value: Any, stamp_ns: int) -> list[View]:
        """The views of decoded message ``value`` on lrfslam topic ``name``, at its data stamp ``stamp_ns``."""
        if name in _UNDECODED_BETWEEN and not self._frame_due(name, stamp_ns):
            return []
        if topics.is_health(name):
            return self._status(value, stamp_ns)
        handler = self._handlers.get(name)
        return handler(value, stamp_ns) if handler else []

    # -- one handler per topic

    def _scan(self, scan: t.LaserScan, at: int) -> list[View]:
        return [View(SCAN, laser_scan(scan), at)]

    def _filtered(self, filtered: t.FilteredScan, at: int) -> list[View]:
        return [View(SCAN_FILTERED, kept_scan(filtered), at)]

    def _features(self, features: t.Features, at: int) -> list[View]:
        return [View(FEATURES, features_scene(features), at)]

    def _odometry(self, odom: t.Odometry, at: int) -> list[View]:
        self._odom.append((odom.stamp_ns, odom.pose))
        views = [View(TF, fm.FrameTransforms(transforms=[
            transform(odom.stamp_ns, ODOM, BASE, odom.pose), transform(odom.stamp_ns, BASE, LASER, np.zeros(3))]), at)
                 ] if self._frame_due(topics.ODOM.name, odom.stamp_ns) else []
        return views + self._path(TRAJECTORY_ODOM, odom.stamp_ns, odom.pose, at)

    def _ground_truth(self, truth: t.GroundTruth, at: int) -> list[View]:
        self._truth.append((truth.stamp_ns, truth.pose))
        return self._path(TRAJECTORY_TRUTH, truth.stamp_ns, truth.pose, at)

    def _map_of(self, landmarks: t.LandmarkMap, at: int) -> list[View]:
        self._map.apply_map(landmarks)   # drawn with the next state
        return []

    def _slam(self, state: t.SlamState, at: int) -> list[View]:
        self._map.apply_state(state)
        stamp = state.stamp_ns
        map_pose = compose(self._map_from_slam, state.pose)
        if self._world_from_map is None:
            true = next((p for s, p in self._truth if s == stamp), None)
            if true is not None:
                self._world_from_map = compose(true, inverse(map_pose))
        views = []
        if self._frame_due(topics.SLAM_STATE.name, stamp):
            tfs = [transform(stamp, MAP, SLAM, self._map_from_slam)]
            if self._odom:
                odom = self._odometry_at(stamp)
                tfs.append(transform(stamp, MAP, ODOM, compose(map_pose, inverse(odom))))
            else:  # no odometry: the EKF's pose places the robot
                tfs += [transform(stamp, MAP, ODOM, self._map_from_slam), transform(stamp, ODOM, BASE, state.pose),
                        transform(stamp, BASE, LASER, np.zeros(3))]
            if self._world_from_map is not None:
                tfs.append(transform(stamp, WORLD, MAP, self._world_from_map))
            views.append(View(TF, fm.FrameTransforms(transforms=tfs), at))
        sent = self._landmarks_sent_ns
        if sent is None or not 0 <= stamp - sent < self.cfg.landmark_period_s * 1e9:
            self._landmarks_sent_ns = stamp
            views.append(View(LANDMARKS, landmarks_scene(state, self._map.landmarks), at))
        return views + self._path(TRAJECTORY_SLAM, stamp, state.pose, at)

    def _odometry_at(self, stamp_ns: int) -> np.ndarray:
        """The odometry pose (3,) at ``stamp_ns``, as :func:`interpolate_pose` over every sample kept gives it.

        Found from the newest end: a state's stamp is among the last few odometry samples, and
        only the two bracketing it (or the nearest end) matter.
        """
        later = None
        for sample in reversed(self._odom):
            if sample[0] <= stamp_ns:
                near = [sample] if later is None else [sample, later]
                break
            later = sample
        else:
            near = [later]
        return interpolate_pose(np.array([s for s, _ in near], np.int64), np.array([p for _, p in near]), stamp_ns)

    def _map_pose(self, mp: t.MapPose, at: int) -> list[View]:
        self._map_from_slam = mp.map_from_slam
        views = [View(TF, fm.FrameTransforms(transforms=[transform(mp.stamp_ns, MAP, SLAM, mp.map_from_slam)]), at)
                 ] if self._frame_due(topics.MAP_POSE.name, mp.stamp_ns) else []
        if mp.localization != t.MAPPING:
            last = self._localization
            if last is None or last[0] != mp.localization or \
                    not 0 <= mp.stamp_ns - last[1] < self.cfg.path_period_s * 1e9:
                self._localization = (mp.localization, mp.stamp_ns)
                views.append(View(LOCALIZATION, localization_scene(mp), at))
        if mp.localization == t.NOT_LOCALIZED:   # on a saved map, not placed on it: no path point
            return views
        return views + self._path(TRAJECTORY_MAP, mp.stamp_ns, mp.pose, at)

    def _keyframes(self, kf: t.MapKeyframes, at: int) -> list[View]:
        # An optimisation moved the past: the path becomes the keyframes, then the poses since the last one.
        stamps, poses = self._keyframe_path.update(kf)
        if kf.scan_stamp_ns.size == 0:
            return []
        path = self.paths[TRAJECTORY_MAP].replace(kf.stamp_ns, poses, int(stamps.max()))
        return [View(TRAJECTORY_MAP, path, at)]

    def _map_grid(self, grid: t.MapGrid, at: int) -> list[View]:
        self._grid.apply(grid)
        due = self._grid_due_ns
        if not (due is None or grid.stamp_ns >= due or grid.stamp_ns < due - int(self.cfg.map_period_s * 1e9)):
            return []
        image = self._grid.image()
        if image is None:
            return []
        wait_s = max(self.cfg.map_period_s, image.cells.size / self.cfg.map_cells_per_s)
        self._grid_due_ns = grid.stamp_ns + int(wait_s * 1e9)
        return [View(GRID, occupancy_grid(grid.stamp_ns, image), at)]

    def _status(self, status: t.ServiceStatus, at: int) -> list[View]:
        now = (status.level, status.message)
        if self._health.get(status.service) == now:
            return []
        self._health[status.service] = now
        return [View(LOG, health_log(status), at)]

    def _path(self, channel: str, stamp_ns: int, p: np.ndarray, at: int) -> list[View]:
        msg = self.paths[channel].add(stamp_ns, p)
        return [] if msg is None else [View(channel, msg, at)]
