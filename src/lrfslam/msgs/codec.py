"""Codecs between :mod:`lrfslam.msgs.types` and the versioned protobuf schemas.

Decoding also checks what the consumers rely on (finite poses and points within
:data:`MAX_ABS`, positive definite feature covariances, bearings that start within a turn,
no negative range): a payload that breaks it is a :class:`DecodeError`, so a
hostile or corrupted message is counted and skipped instead of poisoning a filter.

Every payload on the bus and in a recording is named by its schema's full name,
which carries the version (``lrfslam.msgs.v1.LaserScan``). A decoder is chosen
by that name: the current version decodes directly; an older version, once a v2
exists, decodes with its own generated class and goes through an upgrade
function registered in :data:`UPGRADES`, so old recordings keep replaying.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

import numpy as np
from google.protobuf.message import DecodeError as ProtobufDecodeError
from google.protobuf.message import Message as ProtobufMessage

from lrfslam.errors import DecodeError, SchemaVersionError
from lrfslam.msgs import types as t
from lrfslam.msgs.v1 import (
    features_pb2,
    filtered_scan_pb2,
    ground_truth_pb2,
    laser_scan_pb2,
    map_pb2,
    odometry_pb2,
    service_status_pb2,
    slam_state_pb2,
)
from lrfslam.msgs.v2 import slam_state_pb2 as slam_state_v2_pb2

T = TypeVar("T")

#: The farthest a scan's first bearing may lie from 0, and its widest step between beams (rad).
MAX_TURN_RAD = 2 * np.pi

#: The largest magnitude a decoded coordinate or range (m), pose angle (rad) or velocity may have;
#: a covariance entry may be its square. Far beyond any sensor or map, and far enough below
#: the float limit that the filters' squares and sums stay finite.
MAX_ABS = 1e6

#: The largest tile side (cells) and the most cells a ``MapGrid`` may decode to: a hostile message
#: cannot make a decoder inflate gigabytes (a whole grid at export's default limit is 25 million).
MAX_TILE_CELLS = 1024
MAX_GRID_CELLS = 64_000_000

#: Zenoh encoding prefix; the schema name follows the ``;`` (``application/protobuf;<schema>``).
ENCODING_PREFIX = "application/protobuf"


@dataclass(frozen=True)
class Codec(Generic[T]):
    """Converts one message type to and from its protobuf schema."""

    proto: type
    to_proto: Callable[[T], ProtobufMessage]
    from_proto: Callable[[Any], T]

    @property
    def schema(self) -> str:
        """Full schema name with version, e.g. ``lrfslam.msgs.v1.LaserScan``."""
        return self.proto.DESCRIPTOR.full_name

    @property
    def encoding(self) -> str:
        """Zenoh encoding string naming this schema."""
        return f"{ENCODING_PREFIX};{self.schema}"

    def encode(self, value: T) -> bytes:
        return self.to_proto(value).SerializeToString()

    def decode(self, data: bytes, schema: str | None = None) -> T:
        """Decode ``data`` written with ``schema`` (default: this codec's schema).

        Raises
        ------
        SchemaVersionError
            ``schema`` is neither this codec's nor an older version with an upgrade.
        DecodeError
            The bytes do not parse, or parse into an inconsistent message.
        """
        convert: Callable[[Any], T] = self.from_proto
        proto, name = self.proto, self.schema
        if schema is not None and schema != self.schema:
            upgrade = UPGRADES.get((schema, self.schema))
            if upgrade is None:
                raise SchemaVersionError(schema, f"expected {self.schema}; no upgrade path known")
            (proto, convert), name = upgrade, schema
        msg = _parse(proto, data, name)
        try:
            # A float32 signalling NaN (a flipped bit) warns when widened; the checks reject NaN
            # wherever it is not a legal value.
            with np.errstate(invalid="ignore"):
                return convert(msg)
        except (ValueError, TypeError, OverflowError) as exc:  # OverflowError: an enum value beyond int8
            raise DecodeError(name, str(exc)) from exc


def _parse(proto: type, data: bytes, schema: str) -> Any:
    msg = proto()
    try:
        msg.ParseFromString(bytes(data))
    except (ProtobufDecodeError, RuntimeWarning, ValueError) as exc:
        raise DecodeError(schema, f"malformed payload ({exc})") from exc
    return msg


def _bounded(name: str, values, limit: float = MAX_ABS) -> np.ndarray:
    """``values`` as a float array, if every one is finite and within ±``limit``; else ValueError."""
    a = np.asarray(values, np.float64)
    if a.size and not np.all(np.abs(a) <= limit):   # NaN compares False too
        raise ValueError(f"{name} must be finite and within ±{limit:g}")
    return a


def _covariances(name: str, values, k: int) -> np.ndarray:
    """``values`` as (k, 2, 2) positive definite covariances; else ValueError."""
    c = _bounded(name, values, MAX_ABS ** 2).reshape(k, 2, 2)
    a, b, d = c[:, 0, 0], 0.5 * (c[:, 0, 1] + c[:, 1, 0]), c[:, 1, 1]
    if not np.all((a > 0) & (d > 0) & (a * d - b * b > 0)):
        raise ValueError(f"{name}: a covariance is not positive definite")
    return c


def parse_encoding(encoding: str) -> str:
    """Schema name carried in a Zenoh encoding string, ``""`` if there is none."""
    prefix, _, schema = str(encoding).partition(";")
    return schema if prefix == ENCODING_PREFIX else ""


# ---- v1 mappings -------------------------------------------------------------------------


def _header(h, stamp_ns: int, seq: int, frame_id: str = "") -> None:
    h.stamp_ns = int(stamp_ns)
    h.seq = int(seq)
    h.frame_id = frame_id


def _scan_to(m: t.LaserScan, out=None):
    p = out if out is not None else laser_scan_pb2.LaserScan()
    _header(p.header, m.stamp_ns, m.seq, m.frame_id)
    p.angle_min_rad = m.angle_min_rad
    p.angle_increment_rad = m.angle_increment_rad
    p.range_min_m = m.range_min_m
    p.range_max_m = m.range_max_m
    p.ranges_m.extend(m.ranges_m.tolist())
    p.status.extend(m.status.tolist())
    p.scan_time_s = m.scan_time_s
    p.source = m.source
    return p


def _scan_from(p) -> t.LaserScan:
    if len(p.status) != len(p.ranges_m):
        raise ValueError(f"{len(p.ranges_m)} ranges but {len(p.status)} status codes")
    if not p.angle_increment_rad > 0:
        raise ValueError(f"angle_increment_rad must be > 0, got {p.angle_increment_rad}")
    # numpy would wrap a code of 256 round to 0, BEAM_VALID.
    status = np.array(p.status, np.int64)
    if status.size and not (0 <= status.min() and status.max() <= 255):
        raise ValueError("a beam status code is outside 0..255")
    # Bearings in the laser frame: the first within a turn either way, a step of at most a turn.
    if not (abs(p.angle_min_rad) <= MAX_TURN_RAD and p.angle_increment_rad <= MAX_TURN_RAD):
        raise ValueError(f"beams from {p.angle_min_rad} rad in steps of {p.angle_increment_rad} rad: "
                         "not within a turn")
    ranges = np.array(p.ranges_m, np.float64)
    if np.any(ranges < 0) or np.any(np.isfinite(ranges) & (ranges > MAX_ABS)):
        raise ValueError(f"a range is negative or beyond {MAX_ABS:g} m (no return is +inf)")
    return t.LaserScan(stamp_ns=p.header.stamp_ns, seq=p.header.seq, ranges_m=ranges, status=status.astype(np.uint8),
                       angle_min_rad=p.angle_min_rad, angle_increment_rad=p.angle_increment_rad,
                       range_max_m=p.range_max_m, range_min_m=p.range_min_m, frame_id=p.header.frame_id,
                       scan_time_s=p.scan_time_s, source=p.source)


def _odom_to(m: t.Odometry):
    p = odometry_pb2.Odometry()
    _header(p.header, m.stamp_ns, m.seq, m.frame_id)
    p.pose.x_m, p.pose.y_m, p.pose.theta_rad = (float(v) for v in m.pose)
    p.linear_mps = m.linear_mps
    p.angular_radps = m.angular_radps
    return p


def _odom_from(p) -> t.Odometry:
    pose = _bounded("pose", (p.pose.x_m, p.pose.y_m, p.pose.theta_rad))
    _bounded("velocity", (p.linear_mps, p.angular_radps))
    return t.Odometry(stamp_ns=p.header.stamp_ns, seq=p.header.seq, pose=pose, linear_mps=p.linear_mps,
                      angular_radps=p.angular_radps, frame_id=p.header.frame_id)


def _filtered_to(m: t.FilteredScan):
    p = filtered_scan_pb2.FilteredScan()
    _header(p.header, m.stamp_ns, m.seq, m.scan.frame_id)
    _scan_to(m.scan, p.scan)
    p.kept_beams.extend(m.kept_beams.tolist())
    p.x_m.extend(m.points_xy_m[:, 0].tolist())
    p.y_m.extend(m.points_xy_m[:, 1].tolist())
    p.max_range_m = m.max_range_m
    p.mode = m.mode
    return p


def _filtered_from(p) -> t.FilteredScan:
    scan = _scan_from(p.scan)
    k = len(p.kept_beams)
    if len(p.x_m) != k or len(p.y_m) != k:
        raise ValueError("kept_beams, x_m and y_m differ in length")
    kept = np.array(p.kept_beams, np.int64)
    if k and (kept.max() >= scan.ranges_m.size or np.any(np.diff(kept) <= 0)):
        raise ValueError("kept_beams must be ascending indices into the scan")
    points = _bounded("points", np.column_stack((p.x_m, p.y_m))) if k else np.zeros((0, 2))
    return t.FilteredScan(stamp_ns=p.header.stamp_ns, seq=p.header.seq, scan=scan, kept_beams=kept,
                          points_xy_m=points, max_range_m=p.max_range_m, mode=p.mode)


def _features_to(m: t.Features):
    p = features_pb2.Features()
    _header(p.header, m.stamp_ns, m.seq, "laser")
    p.scan_seq = m.scan_seq
    for i in range(len(m)):
        f = p.features.add()
        f.kind = int(m.kind[i])
        f.x_m, f.y_m = float(m.xy_m[i, 0]), float(m.xy_m[i, 1])
        f.covariance_m2.extend(m.cov_m2[i].ravel().tolist())
        f.beam = int(m.beam[i])
        f.angle_deg = float(m.angle_deg[i])
    if m.has_wall_direction:
        p.wall_direction.direction_rad = float(m.wall_direction_rad)
        p.wall_direction.sigma_rad = float(m.wall_direction_sigma_rad)
    return p


def _features_from(p) -> t.Features:
    fs = p.features
    if any(len(f.covariance_m2) != 4 for f in fs):
        raise ValueError("a feature covariance is not 2x2")
    # Absent in scans without a dominant direction and in recordings made before the field existed.
    wall, wall_sigma = float("nan"), float("nan")
    if p.HasField("wall_direction"):
        wall, wall_sigma = p.wall_direction.direction_rad, p.wall_direction.sigma_rad
        # An angle modulo 90°: within [-pi/4, pi/4] (with rounding), and a sigma no wider than a turn.
        if not (abs(wall) <= np.pi / 4 * (1 + 1e-9) and 0 < wall_sigma <= 2 * np.pi):
            raise ValueError("wall_direction needs a direction within ±pi/4 and a sigma in (0, 2 pi]")
    return t.Features(stamp_ns=p.header.stamp_ns, seq=p.header.seq, scan_seq=p.scan_seq, kind=[f.kind for f in fs],
                      xy_m=_bounded("feature xy", [(f.x_m, f.y_m) for f in fs]),
                      cov_m2=_covariances("feature covariance", [list(f.covariance_m2) for f in fs], len(fs)),
                      beam=[f.beam for f in fs], angle_deg=[f.angle_deg for f in fs], wall_direction_rad=wall,
                      wall_direction_sigma_rad=wall_sigma)


def _landmarks_to(target, lms: t.Landmarks) -> None:
    for i in range(len(lms)):
        lm = target.add()
        lm.id = int(lms.ids[i])
        lm.x_m, lm.y_m = float(lms.xy_m[i, 0]), float(lms.xy_m[i, 1])
        lm.covariance_m2.extend(lms.cov_m2[i].ravel().tolist())
        lm.kind = int(lms.kind[i])
        lm.sightings = int(lms.sightings[i])
        lm.confirmed = bool(lms.confirmed[i])


def _landmarks_from(lms) -> t.Landmarks:
    if any(len(lm.covariance_m2) != 4 for lm in lms):
        raise ValueError("a landmark covariance is not 2x2")
    ids = [lm.id for lm in lms]
    if len(set(ids)) != len(ids):
        raise ValueError("a landmark id appears twice")
    return t.Landmarks(
        ids=ids, xy_m=_bounded("landmark xy", [(lm.x_m, lm.y_m) for lm in lms]).reshape(-1, 2),
        cov_m2=_bounded("landmark covariance", [list(lm.covariance_m2) for lm in lms], MAX_ABS ** 2).reshape(-1, 2, 2),
        kind=[lm.kind for lm in lms], sightings=[lm.sightings for lm in lms], confirmed=[lm.confirmed for lm in lms])


def _pose_covariance(p) -> np.ndarray:
    if len(p.pose_covariance) != 9:
        raise ValueError("pose_covariance is not 3x3")
    return _bounded("pose_covariance", p.pose_covariance, MAX_ABS ** 2).reshape(3, 3)


def _slam_to(m: t.SlamState):
    if m.landmarks_complete:
        raise ValueError("a v2 slam state carries changes, not a whole map (a v1 state's landmarks)")
    p = slam_state_v2_pb2.SlamState(
        scan_seq=m.scan_seq, landmarks=m.n_landmarks, confirmed_landmarks=m.n_confirmed,
        associated=m.associated, added=m.added, rejected=m.rejected, motion_matched=bool(m.motion_matched))
    _header(p.header, m.stamp_ns, m.seq, "map")
    _pose2d(p.pose, m.pose)
    p.pose_covariance.extend(m.pose_cov.ravel().tolist())
    _landmarks_to(p.changed_landmarks, m.landmarks)
    p.removed_landmark_ids.extend(m.removed_landmark_ids.tolist())
    if m.motion is not None:
        _pose2d(p.motion, m.motion)
    return p


def _slam_from(p) -> t.SlamState:
    changed = _landmarks_from(p.changed_landmarks)
    if np.intersect1d(changed.ids, np.asarray(p.removed_landmark_ids, np.int64)).size:
        raise ValueError("a landmark is both changed and removed")
    return t.SlamState(stamp_ns=p.header.stamp_ns, seq=p.header.seq, scan_seq=p.scan_seq,
                       pose=_bounded("pose", (p.pose.x_m, p.pose.y_m, p.pose.theta_rad)),
                       pose_cov=_pose_covariance(p), landmarks=changed,
                       removed_landmark_ids=list(p.removed_landmark_ids), landmarks_complete=False,
                       n_landmarks=p.landmarks, n_confirmed=p.confirmed_landmarks, associated=p.associated,
                       added=p.added, rejected=p.rejected, motion=_pose2d_or_none(p, "motion"),
                       motion_matched=p.motion_matched)


def _slam_from_v1(p) -> t.SlamState:
    """A v1 state: every message held the whole map."""
    lms = _landmarks_from(p.landmarks)
    return t.SlamState(stamp_ns=p.header.stamp_ns, seq=p.header.seq, scan_seq=p.scan_seq,
                       pose=_bounded("pose", (p.pose.x_m, p.pose.y_m, p.pose.theta_rad)),
                       pose_cov=_pose_covariance(p), landmarks=lms, removed_landmark_ids=(), landmarks_complete=True,
                       n_landmarks=len(lms), n_confirmed=int(np.count_nonzero(lms.confirmed)),
                       associated=p.associated, added=p.added, rejected=p.rejected,
                       motion=_pose2d_or_none(p, "motion"), motion_matched=p.motion_matched)


def _landmark_map_to(m: t.LandmarkMap):
    p = slam_state_v2_pb2.LandmarkMap(state_seq=m.state_seq, tolerance_m=m.tolerance_m)
    _header(p.header, m.stamp_ns, m.seq, "map")
    _landmarks_to(p.landmarks, m.landmarks)
    return p


def _landmark_map_from(p) -> t.LandmarkMap:
    if not 0 <= p.tolerance_m <= MAX_ABS:
        raise ValueError("tolerance_m must be finite and not negative")
    return t.LandmarkMap(stamp_ns=p.header.stamp_ns, seq=p.header.seq, state_seq=p.state_seq,
                         landmarks=_landmarks_from(p.landmarks), tolerance_m=p.tolerance_m)


def _pose2d(target, pose) -> None:
    target.x_m, target.y_m, target.theta_rad = (float(v) for v in pose)


def _pose2d_or_none(p, name: str) -> np.ndarray | None:
    """The optional Pose2D field ``name`` of ``p`` as (x, y, theta) (3,), checked as any pose; None where absent."""
    if not p.HasField(name):
        return None
    q = getattr(p, name)
    return _bounded(name, (q.x_m, q.y_m, q.theta_rad))


def _map_pose_to(m: t.MapPose):
    p = map_pb2.MapPose(scan_seq=m.scan_seq, keyframes=m.keyframes, closures=m.closures,
                        closures_rejected=m.closures_rejected, localization=m.localization)
    _header(p.header, m.stamp_ns, m.seq, "map")
    if m.pose_cov is not None:
        p.pose_covariance.extend(m.pose_cov.ravel().tolist())
    _pose2d(p.pose, m.pose)
    _pose2d(p.map_from_slam, m.map_from_slam)
    if m.local_pose is not None:
        _pose2d(p.local_pose, m.local_pose)
    return p


def _localization(value: int) -> int:
    if value not in (t.MAPPING, t.LOCALIZED, t.NOT_LOCALIZED):
        raise ValueError(f"localization {value} is none of 0 (mapping), 1 (localized), 2 (not localized)")
    return value


def _map_pose_from(p) -> t.MapPose:
    pose = _bounded("pose", (p.pose.x_m, p.pose.y_m, p.pose.theta_rad))
    t_map = _bounded("map_from_slam", (p.map_from_slam.x_m, p.map_from_slam.y_m, p.map_from_slam.theta_rad))
    return t.MapPose(stamp_ns=p.header.stamp_ns, seq=p.header.seq, scan_seq=p.scan_seq, pose=pose,
                     map_from_slam=t_map, keyframes=p.keyframes, closures=p.closures,
                     closures_rejected=p.closures_rejected, local_pose=_pose2d_or_none(p, "local_pose"),
                     localization=_localization(p.localization),
                     pose_cov=_pose_covariance(p) if len(p.pose_covariance) else None)


def _keyframes_to(m: t.MapKeyframes):
    p = map_pb2.MapKeyframes()
    _header(p.header, m.stamp_ns, m.seq, "map")
    p.scan_stamp_ns.extend(m.scan_stamp_ns.tolist())
    p.local_pose.extend(m.local_pose.ravel().tolist())
    p.map_pose.extend(m.map_pose.ravel().tolist())
    p.local_edge.extend(m.local_edge.tolist())
    p.retired_scan_stamp_ns.extend(m.retired_scan_stamp_ns.tolist())
    p.retired_local_pose.extend(m.retired_local_pose.ravel().tolist())
    p.retired_local_edge.extend(m.retired_local_edge.tolist())
    p.retired_anchor_stamp_ns.extend(m.retired_anchor_stamp_ns.tolist())
    p.retired_offset.extend(m.retired_offset.ravel().tolist())
    return p


def _keyframes_from(p) -> t.MapKeyframes:
    k, r = len(p.scan_stamp_ns), len(p.retired_scan_stamp_ns)
    if len(p.local_pose) != 3 * k or len(p.map_pose) != 3 * k or len(p.local_edge) not in (0, k):
        raise ValueError("keyframe poses are not K x 3, or the edge flags not K")
    if not (len(p.retired_local_pose) == len(p.retired_offset) == 3 * r
            and len(p.retired_local_edge) == len(p.retired_anchor_stamp_ns) == r):
        raise ValueError("retired keyframes' arrays are not R and R x 3")
    return t.MapKeyframes(stamp_ns=p.header.stamp_ns, seq=p.header.seq, scan_stamp_ns=list(p.scan_stamp_ns),
                          local_pose=_bounded("local_pose", p.local_pose).reshape(k, 3),
                          map_pose=_bounded("map_pose", p.map_pose).reshape(k, 3), local_edge=list(p.local_edge),
                          retired_scan_stamp_ns=list(p.retired_scan_stamp_ns),
                          retired_local_pose=_bounded("retired_local_pose", p.retired_local_pose),
                          retired_local_edge=list(p.retired_local_edge),
                          retired_anchor_stamp_ns=list(p.retired_anchor_stamp_ns),
                          retired_offset=_bounded("retired_offset", p.retired_offset))


def _grid_to(m: t.MapGrid):
    p = map_pb2.MapGrid()
    _header(p.header, m.stamp_ns, m.seq, "map")
    p.resolution_m, p.tile_cells, p.whole = float(m.resolution_m), int(m.tile_cells), bool(m.whole)
    p.tile_row.extend(m.tiles[:, 0].tolist())
    p.tile_col.extend(m.tiles[:, 1].tolist())
    p.cells = zlib.compress(m.cells.tobytes(), 1)
    p.keyframes, p.pending = int(m.keyframes), int(m.pending)
    return p


def _grid_from(p) -> t.MapGrid:
    n, side = len(p.tile_row), p.tile_cells
    if len(p.tile_col) != n or not 1 <= side <= MAX_TILE_CELLS or n * side * side > MAX_GRID_CELLS:
        raise ValueError(f"{n} tiles of {side} x {side} cells: rows and columns differ in number, or too large")
    if not (np.isfinite(p.resolution_m) and 0 < p.resolution_m <= MAX_ABS):
        raise ValueError("resolution_m must be > 0 and finite")
    inflate = zlib.decompressobj()
    try:
        raw = inflate.decompress(p.cells, n * side * side + 1)
    except zlib.error as exc:
        raise ValueError(f"cells: {exc}") from exc
    if len(raw) != n * side * side or inflate.unconsumed_tail:
        raise ValueError(f"cells: {len(raw)} bytes for {n} tiles of {side} x {side}")
    cells = np.frombuffer(raw, np.int8)
    if cells.size and not np.all((cells == -1) | ((cells >= 0) & (cells <= 100))):
        raise ValueError("cells must be -1 or 0..100")
    return t.MapGrid(stamp_ns=p.header.stamp_ns, seq=p.header.seq, resolution_m=p.resolution_m, tile_cells=side,
                     tiles=np.column_stack((list(p.tile_row), list(p.tile_col))).reshape(n, 2),
                     cells=cells.reshape(n, side, side), whole=p.whole, keyframes=p.keyframes, pending=p.pending)


def _truth_to(m: t.GroundTruth):
    p = ground_truth_pb2.GroundTruth()
    _header(p.header, m.stamp_ns, m.seq, "map")
    p.pose.x_m, p.pose.y_m, p.pose.theta_rad = (float(v) for v in m.pose)
    for cid, (x, y) in zip(m.corner_ids.tolist(), m.corners_xy_m.tolist()):
        c = p.visible_corners.add()
        c.id, c.x_m, c.y_m = cid, x, y
    p.world = m.world
    return p


def _truth_from(p) -> t.GroundTruth:
    cs = p.visible_corners
    return t.GroundTruth(stamp_ns=p.header.stamp_ns, seq=p.header.seq,
                         pose=_bounded("pose", (p.pose.x_m, p.pose.y_m, p.pose.theta_rad)),
                         corner_ids=[c.id for c in cs],
                         corners_xy_m=_bounded("corners", [(c.x_m, c.y_m) for c in cs]), world=p.world)


def _status_to(m: t.ServiceStatus):
    p = service_status_pb2.ServiceStatus(
        service=m.service, robot=m.robot, level=m.level, message=m.message,
        wall_stamp_ns=m.wall_stamp_ns, uptime_s=m.uptime_s, last_data_stamp_ns=m.last_data_stamp_ns,
        config_json=m.config_json, pid=m.pid, host=m.host,
    )
    p.counters.update({k: int(v) for k, v in m.counters.items()})
    p.schemas.extend(m.schemas)
    return p


def _status_from(p) -> t.ServiceStatus:
    return t.ServiceStatus(service=p.service, robot=p.robot, level=p.level, message=p.message,
                           wall_stamp_ns=p.wall_stamp_ns, uptime_s=p.uptime_s, counters=dict(p.counters),
                           last_data_stamp_ns=p.last_data_stamp_ns, config_json=p.config_json,
                           schemas=tuple(p.schemas), pid=p.pid, host=p.host)


LASER_SCAN: Codec[t.LaserScan] = Codec(laser_scan_pb2.LaserScan, _scan_to, _scan_from)
ODOMETRY: Codec[t.Odometry] = Codec(odometry_pb2.Odometry, _odom_to, _odom_from)
FILTERED_SCAN: Codec[t.FilteredScan] = Codec(filtered_scan_pb2.FilteredScan, _filtered_to, _filtered_from)
FEATURES: Codec[t.Features] = Codec(features_pb2.Features, _features_to, _features_from)
SLAM_STATE: Codec[t.SlamState] = Codec(slam_state_v2_pb2.SlamState, _slam_to, _slam_from)
LANDMARK_MAP: Codec[t.LandmarkMap] = Codec(slam_state_v2_pb2.LandmarkMap, _landmark_map_to, _landmark_map_from)
GROUND_TRUTH: Codec[t.GroundTruth] = Codec(ground_truth_pb2.GroundTruth, _truth_to, _truth_from)
SERVICE_STATUS: Codec[t.ServiceStatus] = Codec(service_status_pb2.ServiceStatus, _status_to, _status_from)
MAP_POSE: Codec[t.MapPose] = Codec(map_pb2.MapPose, _map_pose_to, _map_pose_from)
MAP_KEYFRAMES: Codec[t.MapKeyframes] = Codec(map_pb2.MapKeyframes, _keyframes_to, _keyframes_from)
MAP_GRID: Codec[t.MapGrid] = Codec(map_pb2.MapGrid, _grid_to, _grid_from)

#: Every codec of the current version, by schema name.
CODECS: dict[str, Codec] = {c.schema: c for c in
                            (LASER_SCAN, ODOMETRY, FILTERED_SCAN, FEATURES, SLAM_STATE, LANDMARK_MAP, GROUND_TRUTH,
                             SERVICE_STATUS, MAP_POSE, MAP_KEYFRAMES, MAP_GRID)}

#: (old schema, current schema) -> (old generated class, converter to the current type).
UPGRADES: dict[tuple[str, str], tuple[type, Callable[[Any], Any]]] = {
    # v1 states carried the whole map in every message; v2 carries the changes (and slam/map the whole).
    (slam_state_pb2.SlamState.DESCRIPTOR.full_name, SLAM_STATE.schema): (slam_state_pb2.SlamState, _slam_from_v1),
}
