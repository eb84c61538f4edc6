"""lrfslam's messages as ROS 2 messages (rosbags' Jazzy classes), and a ROS 2 robot's scans and odometry as ours.

Out (what ``lrfslam ros2`` publishes; frames per REP-105, each prefixed ``<ns>/``):

- :func:`laser_scan`, :func:`filtered_scan`: ``sensor_msgs/msg/LaserScan`` in ``<ns>/laser``;
  no return is +inf (REP-117), a beam the scanner or the denoiser judged wrong NaN;
- :func:`odometry`: ``nav_msgs/msg/Odometry``, ``<ns>/odom`` -> ``<ns>/base_link``;
- :func:`transform`, :func:`tf_message`: ``tf2_msgs/msg/TFMessage`` entries (planar: z 0, yaw only);
- :func:`pose_with_covariance`: ``geometry_msgs/msg/PoseWithCovarianceStamped`` (the 3×3 (x, y, θ)
  covariance placed in the 6×6 one, rows and columns 0, 1, 5);
- :func:`landmark_markers`: ``visualization_msgs/msg/MarkerArray``, a flat cylinder per landmark
  whose footprint is its 2-sigma ellipse;
- :func:`occupancy_grid`: ``nav_msgs/msg/OccupancyGrid`` of the live grid (:class:`~lrfslam.msgs.grid_replica.GridImage`).

In (``lrfslam ros2 --subscribe``): :func:`scan_from_ros`, :func:`odometry_from_ros`.

Times are the messages' own stamps (``builtin_interfaces/msg/Time``: seconds and nanoseconds).
"""

from __future__ import annotations

import math
import struct

import numpy as np
from rosbags.serde import SerdeError

from lrfslam.algo.geometry import ellipse_axes
from lrfslam.errors import InputError
from lrfslam.msgs import types as t
from lrfslam.msgs.grid_replica import GridImage
from lrfslam.ros2 import wire

_GOOD = t.BEAM_VALID
_NO_RETURN = (t.BEAM_NO_RETURN, t.BEAM_OVERFLOW)
#: Largest range or coordinate taken in, m (as lrfslam's decoders).
MAX_ABS_M = 1e6


def _types():
    return wire.typestore().types


def stamp(stamp_ns: int):
    """``builtin_interfaces/msg/Time`` of a stamp in ns since the epoch."""
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return _types()["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)


def stamp_ns(time) -> int:
    """ns since the epoch of a ``builtin_interfaces/msg/Time``."""
    return int(time.sec) * 1_000_000_000 + int(time.nanosec)


def header(stamp_ns_: int, frame_id: str):
    return _types()["std_msgs/msg/Header"](stamp=stamp(stamp_ns_), frame_id=frame_id)


def frame(namespace: str, name: str) -> str:
    """``robot1/odom`` for namespace ``/robot1`` and frame ``odom`` (tf2 frame ids have no leading ``/``)."""
    return f"{namespace.strip('/')}/{name}" if namespace.strip("/") else name


def quaternion(theta_rad: float):
    """``geometry_msgs/msg/Quaternion`` of a rotation by ``theta_rad`` about z."""
    return _types()["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(theta_rad / 2), w=math.cos(theta_rad / 2))


def yaw(q) -> float:
    """The rotation about z of quaternion ``q`` (rad, in (-pi, pi]): the heading of a planar robot."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def pose(xyt) -> object:
    """``geometry_msgs/msg/Pose`` of a planar pose ``(x_m, y_m, theta_rad)``."""
    x, y, theta = (float(v) for v in xyt)
    return _types()["geometry_msgs/msg/Pose"](position=_types()["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
                                              orientation=quaternion(theta))


def covariance6(cov3: np.ndarray | None) -> np.ndarray:
    """A (36,) row-major 6×6 covariance (x, y, z, roll, pitch, yaw) holding the (3, 3) one of (x, y, θ)
    in rows and columns 0, 1, 5; zero elsewhere, and all zero (unknown) for None."""
    out = np.zeros((6, 6))
    if cov3 is not None:
        idx = np.array([0, 1, 5])
        out[np.ix_(idx, idx)] = np.asarray(cov3, float).reshape(3, 3)
    return out.reshape(36)


def _ranges(scan: t.LaserScan) -> np.ndarray:
    """(N,) float32: the range of a valid beam, +inf for no return or overflow, NaN for the rest."""
    r = np.where(scan.status == _GOOD, scan.ranges_m, np.nan)
    r = np.where(np.isin(scan.status, _NO_RETURN), np.inf, r)
    return r.astype(np.float32)


def _laser_scan(scan: t.LaserScan, ranges: np.ndarray, range_max_m: float, frame_id: str):
    n = ranges.size
    return _types()[wire.LASER_SCAN](
        header=header(scan.stamp_ns, frame_id),
        angle_min=float(scan.angle_min_rad),
        angle_max=float(scan.angle_min_rad + (n - 1) * scan.angle_increment_rad),
        angle_increment=float(scan.angle_increment_rad),
        time_increment=0.0,   # unknown: beams are taken as simultaneous
        scan_time=float(scan.scan_time_s),
        range_min=float(scan.range_min_m),
        range_max=float(range_max_m),
        ranges=ranges,
        intensities=np.zeros(0, np.float32))


def laser_scan(scan: t.LaserScan, namespace: str):
    """The raw scan as ``sensor_msgs/msg/LaserScan`` in ``<ns>/<scan's frame>``; angle_max is
    ``angle_min + (N - 1)·increment``; ``time_increment`` 0 (not known)."""
    return _laser_scan(scan, _ranges(scan), scan.range_max_m, frame(namespace, scan.frame_id))


def filtered_scan(filtered: t.FilteredScan, namespace: str):
    """The denoiser's output as a ``LaserScan`` over all N beams: those it kept with their range,
    those it removed NaN (judged wrong), no return +inf; ``range_max`` its range cut."""
    scan = filtered.scan
    ranges = _ranges(scan)
    removed = ~filtered.kept_mask & np.isfinite(ranges)
    ranges[removed] = np.nan
    return _laser_scan(scan, ranges, filtered.max_range_m, frame(namespace, scan.frame_id))


def odometry(odom: t.Odometry, namespace: str, pose_cov: np.ndarray | None = None):
    """``nav_msgs/msg/Odometry``: ``<ns>/odom`` -> ``<ns>/base_link``, the speeds in base_link
    (``linear.x``, ``angular.z``); ``pose_cov`` (3, 3) or None (unknown: all zero)."""
    ty = _types()
    vector = ty["geometry_msgs/msg/Vector3"]
    return ty[wire.ODOMETRY](
        header=header(odom.stamp_ns, frame(namespace, odom.frame_id)),
        child_frame_id=frame(namespace, "base_link"),
        pose=ty["geometry_msgs/msg/PoseWithCovariance"](pose=pose(odom.pose), covariance=covariance6(pose_cov)),
        twist=ty["geometry_msgs/msg/TwistWithCovariance"](
            twist=ty["geometry_msgs/msg/Twist"](linear=vector(x=float(odom.linear_mps), y=0.0, z=0.0),
                                                angular=vector(x=0.0, y=0.0, z=float(odom.angular_radps))),
            covariance=np.zeros(36)))


def transform(stamp_ns_: int, parent: str, child: str, xyt):
    """``geometry_msgs/msg/TransformStamped``: ``child``'s pose ``(x_m, y_m, theta_rad)`` in ``parent``."""
    ty = _types()
    x, y, theta = (float(v) for v in xyt)
    return ty["geometry_msgs/msg/TransformStamped"](
        header=header(stamp_ns_, parent), child_frame_id=child,
        transform=ty["geometry_msgs/msg/Transform"](translation=ty["geometry_msgs/msg/Vector3"](x=x, y=y, z=0.0),
                                                    rotation=quaternion(theta)))


def tf_message(transforms: list):
    """``tf2_msgs/msg/TFMessage`` of ``TransformStamped`` entries."""
    return _types()[wire.TF_MESSAGE](transforms=list(transforms))


def pose_with_covariance(stamp_ns_: int, frame_id: str, xyt, cov3: np.ndarray | None):
    """``geometry_msgs/msg/PoseWithCovarianceStamped`` of a planar pose and its (3, 3) covariance."""
    ty = _types()
    return ty[wire.POSE_WITH_COVARIANCE_STAMPED](
        header=header(stamp_ns_, frame_id),
        pose=ty["geometry_msgs/msg/PoseWithCovariance"](pose=pose(xyt), covariance=covariance6(cov3)))


#: Height of a landmark's cylinder, m (it is drawn flat on the floor).
MARKER_HEIGHT_M = 0.05
#: The ellipse drawn: this many standard deviations.
ELLIPSE_SIGMAS = 2.0


def ellipse(cov2: np.ndarray) -> tuple[float, float, float]:
    """``(major_m, minor_m, angle_rad)``: the full axes of the :data:`ELLIPSE_SIGMAS`-sigma ellipse of a
    (2, 2) covariance, and the major axis' direction."""
    major, minor, angle = ellipse_axes(cov2, ELLIPSE_SIGMAS**2)
    return 2 * major, 2 * minor, angle


def landmark_markers(landmarks: t.Landmarks, stamp_ns_: int, frame_id: str):
    """``visualization_msgs/msg/MarkerArray``: first a DELETEALL (landmarks the map dropped go), then
    one CYLINDER per landmark (id its landmark id, namespace ``landmarks``) at ``xy_m``, its
    footprint the 2-sigma ellipse of ``cov_m2``; confirmed ones orange, tentative ones grey."""
    ty = _types()
    marker = ty["visualization_msgs/msg/Marker"]
    zero = ty["builtin_interfaces/msg/Duration"](sec=0, nanosec=0)
    color = ty["std_msgs/msg/ColorRGBA"]

    def base(**kw):
        return marker(header=header(stamp_ns_, frame_id), ns="landmarks", lifetime=zero, frame_locked=False,
                      points=[], colors=[], texture_resource="",
                      texture=ty["sensor_msgs/msg/CompressedImage"](header=header(0, ""), format="",
                                                                    data=np.zeros(0, np.uint8)),
                      uv_coordinates=[], text="", mesh_resource="",
                      mesh_file=ty["visualization_msgs/msg/MeshFile"](filename="", data=np.zeros(0, np.uint8)),
                      mesh_use_embedded_materials=False, **kw)

    out = [base(id=0, type=marker.CYLINDER, action=marker.DELETEALL, pose=pose((0, 0, 0)),
                scale=ty["geometry_msgs/msg/Vector3"](x=1.0, y=1.0, z=1.0), color=color(r=0.0, g=0.0, b=0.0, a=0.0))]
    for i in range(len(landmarks)):
        major, minor, angle = ellipse(landmarks.cov_m2[i])
        x, y = landmarks.xy_m[i]
        rgba = (1.0, 0.5, 0.0, 0.8) if landmarks.confirmed[i] else (0.6, 0.6, 0.6, 0.6)
        out.append(base(id=int(landmarks.ids[i]), type=marker.CYLINDER, action=marker.ADD, pose=pose((x, y, angle)),
                        scale=ty["geometry_msgs/msg/Vector3"](x=major, y=minor, z=MARKER_HEIGHT_M),
                        color=color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])))
    return ty[wire.MARKER_ARRAY](markers=out)


def occupancy_grid(grid: GridImage, stamp_ns_: int, frame_id: str):
    """``nav_msgs/msg/OccupancyGrid``: cells 100 occupied, 0 free, -1 unknown (map_server's thresholds),
    row-major from row 0 at the lowest y, the origin the lower-left corner of cell [0, 0]."""
    ty = _types()
    h, w = grid.cells.shape
    x0, y0 = grid.origin_xy_m
    return ty[wire.OCCUPANCY_GRID](
        header=header(stamp_ns_, frame_id),
        info=ty["nav_msgs/msg/MapMetaData"](map_load_time=stamp(stamp_ns_), resolution=float(grid.resolution_m),
                                            width=int(w), height=int(h), origin=pose((x0, y0, 0.0))),
        data=grid.cells.reshape(-1))


def serialize(message) -> bytes:
    """CDR bytes (little endian, with the 4-byte encapsulation header ``00 01 00 00``)."""
    return bytes(wire.typestore().serialize_cdr(message, message.__msgtype__, little_endian=True))


def deserialize(payload: bytes, msgtype: str):
    """The ``msgtype`` message of CDR ``payload``.

    Raises
    ------
    InputError
        The payload is not a CDR ``msgtype``.
    """
    try:
        return wire.typestore().deserialize_cdr(payload, msgtype)
    except (SerdeError, struct.error, ValueError, IndexError) as exc:   # SerdeError wraps most
        raise InputError(f"not a CDR {msgtype}: {exc}") from None


def _strip(frame_id: str, namespace: str) -> str:
    """A ROS frame id without its namespace prefix (``robot1/laser`` -> ``laser``)."""
    prefix = namespace.strip("/") + "/"
    name = frame_id.lstrip("/")
    return name[len(prefix):] if prefix != "/" and name.startswith(prefix) else name


def scan_from_ros(msg, seq: int, namespace: str = "", source: str = "") -> t.LaserScan:
    """A ROS ``sensor_msgs/msg/LaserScan`` of any 2D laser as lrfslam's scan.

    The beam count, first angle and step come from the message; a beam turning clockwise
    (negative increment) is reversed so the angles ascend. A range that is finite and within
    ``[range_min, range_max]`` is a return; anything else (beyond range_max, below range_min,
    ±inf or NaN) is no return (+inf, ``BEAM_NO_RETURN``).

    Raises
    ------
    InputError
        No beams, a non-finite or zero step, a first angle or step beyond a turn, or
        non-finite range limits.
    """
    ranges = np.asarray(msg.ranges, np.float64)
    inc, first = float(msg.angle_increment), float(msg.angle_min)
    if ranges.size == 0:
        raise InputError("a LaserScan without ranges")
    if not (math.isfinite(inc) and inc != 0 and abs(inc) <= 2 * math.pi and math.isfinite(first)
            and abs(first) <= 2 * math.pi):
        raise InputError(f"a LaserScan from {first} rad in steps of {inc} rad")
    lo, hi = float(msg.range_min), float(msg.range_max)
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo <= hi <= MAX_ABS_M):
        raise InputError(f"a LaserScan with range limits {lo}..{hi} m")
    if inc < 0:
        ranges, first, inc = ranges[::-1], first + (ranges.size - 1) * inc, -inc
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(ranges) & (ranges >= lo) & (ranges <= hi)
    return t.LaserScan(stamp_ns=stamp_ns(msg.header.stamp), seq=seq, ranges_m=np.where(valid, ranges, np.inf),
                       status=np.where(valid, t.BEAM_VALID, t.BEAM_NO_RETURN), angle_min_rad=first,
                       angle_increment_rad=inc, range_max_m=hi, range_min_m=lo,
                       frame_id=_strip(msg.header.frame_id, namespace) or "laser",
                       scan_time_s=float(msg.scan_time) if math.isfinite(msg.scan_time) else 0.0, source=source)


def odometry_from_ros(msg, seq: int, namespace: str = "") -> t.Odometry:
    """A ROS ``nav_msgs/msg/Odometry`` as lrfslam's: x, y and the yaw of the orientation, the
    forward speed (``twist.linear.x``) and the turn rate (``twist.angular.z``).

    Raises
    ------
    InputError
        A non-finite or absurd (beyond 1e6 m) pose, or a zero quaternion.
    """
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    values = np.array([p.x, p.y, q.x, q.y, q.z, q.w, msg.twist.twist.linear.x, msg.twist.twist.angular.z])
    if not np.all(np.abs(values) <= MAX_ABS_M):
        raise InputError("an Odometry with a non-finite or absurd value")
    if q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w == 0:
        raise InputError("an Odometry with a zero quaternion")
    return t.Odometry(stamp_ns=stamp_ns(msg.header.stamp), seq=seq, pose=(p.x, p.y, yaw(q)),
                      linear_mps=float(msg.twist.twist.linear.x), angular_radps=float(msg.twist.twist.angular.z),
                      frame_id=_strip(msg.header.frame_id, namespace) or "odom")
