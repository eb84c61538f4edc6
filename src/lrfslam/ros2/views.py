"""What ``lrfslam ros2`` publishes for each lrfslam message: the ROS 2 topics and their messages.

One :class:`RosViews` per robot takes the robot's messages in the order they arrive and returns
the ROS messages to publish, each with its topic (fully qualified). Frames (REP-105, each
``<ns>/…``): ``map`` -> ``odom`` -> ``base_link`` -> ``laser``.

- ``scan`` -> ``/<ns>/scan``; ``scan/filtered`` -> ``/<ns>/scan_filtered`` (``LaserScan``);
- ``odom`` -> ``/<ns>/odom`` (``Odometry``) and ``/tf`` odom -> base_link; with the first one,
  ``/tf_static`` base_link -> laser (identity: lrfslam's scans are in the robot's frame);
- the robot's pose in the map, from the mapper's ``map/pose`` once one has come, else from the
  EKF's ``slam/state``: ``/<ns>/pose`` (``PoseWithCovarianceStamped``, in ``<ns>/map``, the EKF's
  covariance of that scan, turned into the mapper's frame) and ``/tf`` map -> odom, the
  correction that puts the odometry's pose of the same stamp (interpolated) on it;
- the EKF's landmarks (rebuilt from ``slam/state`` and ``slam/map``), in the map frame, at most
  every :data:`LANDMARK_PERIOD_S` of data time: ``/<ns>/landmarks`` (``MarkerArray``);
- the mapper's live occupancy grid, its ``map/grid`` tiles put together (``msgs/grid_replica.py``),
  after a change, at most every :data:`MAP_PERIOD_S` of data time, a map of n cells at most every
  n / :data:`MAP_CELLS_PER_S` s (whole, as ROS 2's ``/map`` goes: a large one must not flood the
  link): ``/<ns>/map`` (``OccupancyGrid``, transient local).
"""

from __future__ import annotations

from collections import OrderedDict, deque
from dataclasses import dataclass

import numpy as np

from lrfslam.algo.geometry import compose, from_frame, inverse, rotate_covariance
from lrfslam.algo.stream_alignment import interpolate_pose
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.msgs.grid_replica import GridReplica
from lrfslam.msgs.landmark_map import LandmarkMapReplica
from lrfslam.ros2 import convert, wire

#: Landmarks go out at most this often, s of data time.
LANDMARK_PERIOD_S = 0.5
#: Odometry poses kept for the map -> odom transform, and EKF covariances kept for the mapper's poses.
ODOM_KEPT = 256
COV_KEPT = 64
#: The map goes out at most this often, s of data time.
MAP_PERIOD_S = 1.0
#: ... and a map of n cells at most every n / this many s (Killian's 20 million cells: every 10 s).
MAP_CELLS_PER_S = 2_000_000


@dataclass(frozen=True)
class RosTopic:
    """A ROS 2 topic this bridge publishes: its name under the namespace (``scan``) or absolute
    (``/tf``), its message type and QoS."""

    name: str
    msgtype: str
    qos: wire.Qos = wire.STREAM_QOS
    latched: bool = False

    def qualified(self, namespace: str) -> str:
        """``/robot1/scan`` (``/tf`` stays ``/tf``)."""
        return self.name if self.name.startswith("/") else f"{namespace.rstrip('/')}/{self.name}"


SCAN = RosTopic("scan", wire.LASER_SCAN)
SCAN_FILTERED = RosTopic("scan_filtered", wire.LASER_SCAN)
ODOM = RosTopic("odom", wire.ODOMETRY)
POSE = RosTopic("pose", wire.POSE_WITH_COVARIANCE_STAMPED)
LANDMARKS = RosTopic("landmarks", wire.MARKER_ARRAY)
TF = RosTopic("/tf", wire.TF_MESSAGE, wire.TF_QOS)
TF_STATIC = RosTopic("/tf_static", wire.TF_MESSAGE, wire.LATCHED_QOS, latched=True)
MAP = RosTopic("map", wire.OCCUPANCY_GRID, wire.LATCHED_QOS, latched=True)
PUBLISHED = (SCAN, SCAN_FILTERED, ODOM, POSE, LANDMARKS, TF, TF_STATIC, MAP)
#: What ``--subscribe`` takes by default.
SUBSCRIBED = (RosTopic("scan", wire.LASER_SCAN, wire.SENSOR_QOS), RosTopic("odom", wire.ODOMETRY, wire.SENSOR_QOS))


@dataclass(frozen=True)
class Publication:
    """One ROS message to publish on ``topic``, with the data stamp it carries (ns)."""

    topic: RosTopic
    message: object
    stamp_ns: int


class RosViews:
    """The ROS 2 views of one robot's messages (the module's docstring), for namespace ``namespace``
    (fully qualified, ``/robot1``)."""

    def __init__(self, namespace: str) -> None:
        self.namespace = namespace
        self.frames = {name: convert.frame(namespace, name) for name in ("map", "odom", "base_link", "laser")}
        self._odom_stamps: deque[int] = deque(maxlen=ODOM_KEPT)
        self._odom_poses: deque[np.ndarray] = deque(maxlen=ODOM_KEPT)
        self._covs: OrderedDict[int, np.ndarray] = OrderedDict()
        self.mapper_seen = False
        self._map_from_slam = np.zeros(3)
        self._landmarks = LandmarkMapReplica()
        self._landmarks_due_ns: int | None = None
        self._static_sent = False
        self.grid = GridReplica()
        self._map_pending_ns: int | None = None   # the stamp of tiles not yet drawn
        self._map_due_ns: int | None = None

    def on_message(self, name: str, value) -> list[Publication]:
        """The publications for message ``value`` of relative topic ``name`` (none for the others)."""
        if name == topics.SCAN.name:
            return [Publication(SCAN, convert.laser_scan(value, self.namespace), value.stamp_ns), *self._map(value.stamp_ns)]
        if name == topics.MAP_GRID.name:
            self.grid.apply(value)
            self._map_pending_ns = value.stamp_ns
            return self._map(value.stamp_ns)
        if name == topics.SCAN_FILTERED.name:
            return [Publication(SCAN_FILTERED, convert.filtered_scan(value, self.namespace), value.stamp_ns)]
        if name == topics.ODOM.name:
            return self._odometry(value)
        if name == topics.SLAM_STATE.name:
            return self._slam_state(value)
        if name == topics.SLAM_MAP.name:
            self._landmarks.apply_map(value)
            return []
        if name == topics.MAP_POSE.name:
            self.mapper_seen = True
            if value.localization == t.NOT_LOCALIZED:
                return []   # on a saved map, not placed on it: no pose in map, no map -> odom (as AMCL before it converges)
            self._map_from_slam = value.map_from_slam
            cov = value.pose_cov   # localizing on a saved map: the localizer's own
            if cov is None and (cov := self._covs.get(value.stamp_ns)) is not None:
                cov = rotate_covariance(cov, value.map_from_slam[2])   # the EKF's, turned into the mapper's frame
            return self._map_pose(value.stamp_ns, value.pose, cov)
        return []

    def _map(self, stamp_ns: int) -> list[Publication]:
        """``/<ns>/map`` if tiles wait and :data:`MAP_PERIOD_S` of data time has passed (or time went back)."""
        due = self._map_due_ns
        if self._map_pending_ns is None or not (due is None or stamp_ns >= due
                                                or stamp_ns < due - int(MAP_PERIOD_S * 1e9)):
            return []
        grid = self.grid.image()
        if grid is None:
            return []
        self._map_pending_ns = None
        self._map_due_ns = stamp_ns + int(max(MAP_PERIOD_S, grid.cells.size / MAP_CELLS_PER_S) * 1e9)
        return [Publication(MAP, convert.occupancy_grid(grid, stamp_ns, self.frames["map"]), stamp_ns)]

    def _odometry(self, odom: t.Odometry) -> list[Publication]:
        if self._odom_stamps and odom.stamp_ns <= self._odom_stamps[-1]:
            self._odom_stamps.clear()   # data time went back (a replay's new loop): start afresh
            self._odom_poses.clear()
        self._odom_stamps.append(odom.stamp_ns)
        self._odom_poses.append(odom.pose)
        out = [Publication(ODOM, convert.odometry(odom, self.namespace), odom.stamp_ns),
               Publication(TF, convert.tf_message([convert.transform(
                   odom.stamp_ns, self.frames["odom"], self.frames["base_link"], odom.pose)]), odom.stamp_ns)]
        if not self._static_sent:
            self._static_sent = True
            out.append(Publication(TF_STATIC, convert.tf_message([convert.transform(
                odom.stamp_ns, self.frames["base_link"], self.frames["laser"], (0.0, 0.0, 0.0))]), odom.stamp_ns))
        return out

    def _slam_state(self, state: t.SlamState) -> list[Publication]:
        self._landmarks.apply_state(state)
        self._covs[state.stamp_ns] = state.pose_cov
        while len(self._covs) > COV_KEPT:
            self._covs.popitem(last=False)
        out = [] if self.mapper_seen else self._map_pose(state.stamp_ns, state.pose, state.pose_cov)
        due = self._landmarks_due_ns
        if due is None or state.stamp_ns >= due or state.stamp_ns < due - int(LANDMARK_PERIOD_S * 1e9):
            self._landmarks_due_ns = state.stamp_ns + int(LANDMARK_PERIOD_S * 1e9)
            out.append(Publication(LANDMARKS, convert.landmark_markers(self.landmarks_in_map(), state.stamp_ns,
                                                                       self.frames["map"]), state.stamp_ns))
        return out

    def landmarks_in_map(self) -> t.Landmarks:
        """The EKF's landmarks as held, in the published map frame (the mapper's, once it has spoken)."""
        held = self._landmarks.landmarks
        if not self.mapper_seen or len(held) == 0:
            return held
        frame = self._map_from_slam
        return t.Landmarks(ids=held.ids, xy_m=from_frame(held.xy_m, frame),
                           cov_m2=rotate_covariance(held.cov_m2, frame[2]),
                           kind=held.kind, sightings=held.sightings, confirmed=held.confirmed)

    def map_to_odom(self, stamp_ns: int, map_pose: np.ndarray) -> np.ndarray | None:
        """The ``odom`` frame's pose in ``map`` (3,): ``map_pose ⊕ ⊖odom_pose``, the odometry's pose at
        ``stamp_ns`` interpolated; None without odometry."""
        if not self._odom_stamps:
            return None
        odom_pose = interpolate_pose(np.array(self._odom_stamps), np.array(self._odom_poses), stamp_ns)
        return compose(map_pose, inverse(odom_pose))

    def _map_pose(self, stamp_ns: int, xyt: np.ndarray, cov: np.ndarray | None) -> list[Publication]:
        out = [Publication(POSE, convert.pose_with_covariance(stamp_ns, self.frames["map"], xyt, cov), stamp_ns)]
        correction = self.map_to_odom(stamp_ns, xyt)
        if correction is not None:
            out.append(Publication(TF, convert.tf_message([convert.transform(
                stamp_ns, self.frames["map"], self.frames["odom"], correction)]), stamp_ns))
        return out
