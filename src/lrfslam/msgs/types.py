"""In-memory messages: frozen dataclasses holding numpy arrays.

Services and tests see these; only :mod:`lrfslam.msgs.codec` sees protobuf.
Field names carry units; shapes are given per field. Every message is built by keyword
(``kw_only``): with 5 to 15 fields, a message built by position would take a new field's
value in the wrong place without a word.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# Beam status codes; the values are those of BeamStatus in schemas/.../laser_scan.proto.
BEAM_VALID = 0
BEAM_NO_RETURN = 1
BEAM_DAZZLE = 2
BEAM_OVERFLOW = 3
BEAM_INVALID = 4

# Feature kinds; the values are those of FeatureKind in features.proto.
FEATURE_FORWARD = 1
FEATURE_BACKWARD = 2

HEALTH_OK, HEALTH_WARN, HEALTH_ERROR, HEALTH_STALE = 0, 1, 2, 3
# MapPose.localization
MAPPING, LOCALIZED, NOT_LOCALIZED = 0, 1, 2


def _array(values, dtype, shape=None) -> np.ndarray:
    a = np.array(values, dtype=dtype)
    if shape is not None:
        a = a.reshape(shape)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False, kw_only=True)
class LaserScan:
    """One laser sweep.

    ``ranges_m`` (N,) float64, +inf where the beam has no return, NaN where invalid;
    ``status`` (N,) uint8 BEAM_* codes; beam i points at
    ``angle_min_rad + i * angle_increment_rad`` in the laser frame.
    """

    stamp_ns: int
    seq: int
    ranges_m: np.ndarray
    status: np.ndarray
    angle_min_rad: float
    angle_increment_rad: float
    range_max_m: float = 8.0
    range_min_m: float = 0.0
    frame_id: str = "laser"
    scan_time_s: float = 0.0
    source: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "ranges_m", _array(self.ranges_m, np.float64))
        object.__setattr__(self, "status", _array(self.status, np.uint8))

    @property
    def angles_rad(self) -> np.ndarray:
        """Bearing of each beam, shape (N,), radians."""
        return self.angle_min_rad + self.angle_increment_rad * np.arange(self.ranges_m.size)

    def grid_ranges(self) -> np.ndarray:
        """The ranges as an occupancy grid takes them (``lrfslam.algo.occupancy_grid``): (N,) float32,
        a valid beam's range, +inf for no return, NaN for the rest (dazzle, overflow, invalid)."""
        return np.where(self.status == BEAM_VALID, self.ranges_m,
                        np.where(self.status == BEAM_NO_RETURN, np.inf, np.nan)).astype(np.float32)

    @classmethod
    def from_ranges(cls, stamp_ns: int, seq: int, ranges_m, angle_min_rad: float,
                    angle_increment_rad: float, range_max_m: float = 8.0, **kw) -> LaserScan:
        """Build a scan whose status is derived from the ranges (inf: no return, NaN: invalid)."""
        r = np.asarray(ranges_m, dtype=np.float64)
        status = np.where(np.isnan(r), BEAM_INVALID, np.where(np.isinf(r), BEAM_NO_RETURN, BEAM_VALID))
        return cls(stamp_ns=stamp_ns, seq=seq, ranges_m=r, status=status, angle_min_rad=angle_min_rad,
                   angle_increment_rad=angle_increment_rad, range_max_m=range_max_m, **kw)


@dataclass(frozen=True, eq=False, kw_only=True)
class Odometry:
    """Integrated wheel odometry; ``pose`` (3,) = (x_m, y_m, theta_rad) in the odom frame."""

    stamp_ns: int
    seq: int
    pose: np.ndarray
    linear_mps: float = 0.0
    angular_radps: float = 0.0
    frame_id: str = "odom"

    def __post_init__(self) -> None:
        object.__setattr__(self, "pose", _array(self.pose, np.float64, (3,)))


@dataclass(frozen=True, eq=False, kw_only=True)
class FilteredScan:
    """The denoiser's output.

    ``scan`` is the input after the range cut, ``kept_beams`` (K,) ascending beam
    indices that survived, ``points_xy_m`` (K, 2) their points in the laser frame.
    """

    stamp_ns: int
    seq: int
    scan: LaserScan
    kept_beams: np.ndarray
    points_xy_m: np.ndarray
    max_range_m: float
    mode: str

    def __post_init__(self) -> None:
        object.__setattr__(self, "kept_beams", _array(self.kept_beams, np.int64))
        object.__setattr__(self, "points_xy_m", _array(self.points_xy_m, np.float64, (-1, 2)))

    @property
    def kept_mask(self) -> np.ndarray:
        """Boolean mask over the scan's beams, shape (N,)."""
        mask = np.zeros(self.scan.ranges_m.size, dtype=bool)
        mask[self.kept_beams] = True
        return mask


@dataclass(frozen=True, eq=False, kw_only=True)
class Features:
    """Corner features of one scan, in the robot (laser) frame.

    ``kind`` (K,) FEATURE_* codes, ``xy_m`` (K, 2), ``cov_m2`` (K, 2, 2),
    ``beam`` (K,) source beam indices, ``angle_deg`` (K,) corner angle (NaN for backward).
    ``wall_direction_rad``: the dominant wall direction modulo 90° in [-pi/4, pi/4), and
    ``wall_direction_sigma_rad`` its standard deviation; both NaN when there is none.
    """

    stamp_ns: int
    seq: int
    scan_seq: int
    kind: np.ndarray
    xy_m: np.ndarray
    cov_m2: np.ndarray
    beam: np.ndarray
    angle_deg: np.ndarray
    wall_direction_rad: float = float("nan")
    wall_direction_sigma_rad: float = float("nan")

    @property
    def has_wall_direction(self) -> bool:
        """True when the scan has a dominant wall direction with a usable sigma."""
        return bool(np.isfinite(self.wall_direction_rad) and np.isfinite(self.wall_direction_sigma_rad)
                    and self.wall_direction_sigma_rad > 0)

    def __post_init__(self) -> None:
        object.__setattr__(self, "kind", _array(self.kind, np.int8))
        object.__setattr__(self, "xy_m", _array(self.xy_m, np.float64, (-1, 2)))
        object.__setattr__(self, "cov_m2", _array(self.cov_m2, np.float64, (-1, 2, 2)))
        object.__setattr__(self, "beam", _array(self.beam, np.int64))
        object.__setattr__(self, "angle_deg", _array(self.angle_deg, np.float64))

    def __len__(self) -> int:
        return int(self.kind.size)


@dataclass(frozen=True, eq=False, kw_only=True)
class MapPose:
    """The loop-closing back end after one scan: ``pose`` (3,) corrected by the closures so far,
    ``map_from_slam`` (3,), the transform with ``pose = map_from_slam ⊕ slam pose``, and
    ``local_pose`` (3,), the scan on the mapper's local trajectory (None in older recordings).

    On a saved map (the mapper's ``localize``), ``localization`` says whether this scan was placed on
    it (:data:`LOCALIZED`) or not (:data:`NOT_LOCALIZED`: ``pose`` is carried by the last fix, or is
    the slam pose before any), and ``pose_cov`` (3, 3) is the pose's covariance; while mapping
    ``localization`` is :data:`MAPPING` and ``pose_cov`` None."""

    stamp_ns: int
    seq: int
    scan_seq: int
    pose: np.ndarray
    map_from_slam: np.ndarray
    keyframes: int = 0
    closures: int = 0
    closures_rejected: int = 0
    local_pose: np.ndarray | None = None
    localization: int = 0
    pose_cov: np.ndarray | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "pose", _array(self.pose, np.float64, (3,)))
        object.__setattr__(self, "map_from_slam", _array(self.map_from_slam, np.float64, (3,)))
        if self.local_pose is not None:
            object.__setattr__(self, "local_pose", _array(self.local_pose, np.float64, (3,)))
        if self.pose_cov is not None:
            object.__setattr__(self, "pose_cov", _array(self.pose_cov, np.float64, (3, 3)))


@dataclass(frozen=True, eq=False, kw_only=True)
class MapGrid:
    """Tiles of the live occupancy grid (``map/grid``): ``tiles`` (n, 2) int64 (row, col) of each,
    ``cells`` (n, T, T) int8 its cells (100 occupied, 0 free, -1 unknown; row 0 the lowest y), at
    ``resolution_m`` metres a cell. Tile (row, col) starts at cell (row·T, col·T) from the map
    origin. ``whole``: every tile of the grid is here (else only those that changed since the
    previous message). ``keyframes`` laid; ``pending``: moved by an optimisation, not yet laid again."""

    stamp_ns: int
    seq: int
    resolution_m: float
    tile_cells: int
    tiles: np.ndarray
    cells: np.ndarray
    whole: bool = False
    keyframes: int = 0
    pending: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "tiles", _array(self.tiles, np.int64, (-1, 2)))
        n, side = self.tiles.shape[0], int(self.tile_cells)
        object.__setattr__(self, "cells", _array(self.cells, np.int8, (n, side, side)))


@dataclass(frozen=True, eq=False, kw_only=True)
class MapKeyframes:
    """The pose graph's K keyframes after an optimisation: ``scan_stamp_ns`` (K,) of the scan
    that made each, its ``local_pose`` (K, 3) on the mapper's local trajectory, its optimised
    ``map_pose`` (K, 3), and ``local_edge`` (K,) bool, whether the edge into it is the local
    motion (no jump).

    Then the R keyframes *retired* from the graph since the previous message, each told once:
    ``retired_scan_stamp_ns`` (R,), ``retired_local_pose`` (R, 3), ``retired_local_edge`` (R,),
    and ``retired_anchor_stamp_ns`` (R,), the older keyframe each was folded into, whose pose
    composed with ``retired_offset`` (R, 3) is its pose ever after
    (``lrfslam.evaluation.map_trajectory.KeyframeHistory`` keeps them)."""

    stamp_ns: int
    seq: int
    scan_stamp_ns: np.ndarray
    local_pose: np.ndarray
    map_pose: np.ndarray
    local_edge: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    retired_scan_stamp_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    retired_local_pose: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    retired_local_edge: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    retired_anchor_stamp_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    retired_offset: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    def __post_init__(self) -> None:
        object.__setattr__(self, "scan_stamp_ns", _array(self.scan_stamp_ns, np.int64))
        k = self.scan_stamp_ns.size
        object.__setattr__(self, "local_pose", _array(self.local_pose, np.float64, (k, 3)))
        object.__setattr__(self, "map_pose", _array(self.map_pose, np.float64, (k, 3)))
        edge = np.zeros(k, bool) if np.size(self.local_edge) == 0 else self.local_edge
        object.__setattr__(self, "local_edge", _array(edge, bool, (k,)))
        object.__setattr__(self, "retired_scan_stamp_ns", _array(self.retired_scan_stamp_ns, np.int64))
        r = self.retired_scan_stamp_ns.size
        object.__setattr__(self, "retired_local_pose", _array(self.retired_local_pose, np.float64, (r, 3)))
        object.__setattr__(self, "retired_local_edge", _array(self.retired_local_edge, bool, (r,)))
        object.__setattr__(self, "retired_anchor_stamp_ns", _array(self.retired_anchor_stamp_ns, np.int64, (r,)))
        object.__setattr__(self, "retired_offset", _array(self.retired_offset, np.float64, (r, 3)))


@dataclass(frozen=True, eq=False, kw_only=True)
class Landmarks:
    """A set of the EKF's landmarks, one row each, sorted by id or in the filter's order.

    ``ids`` (L,) stable ids, ``xy_m`` (L, 2) map frame, ``cov_m2`` (L, 2, 2), ``kind`` (L,)
    FEATURE_* codes, ``sightings`` (L,), ``confirmed`` (L,) bool (false while tentative).
    """

    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    xy_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    cov_m2: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    kind: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int8))
    sightings: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    confirmed: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))

    def __post_init__(self) -> None:
        object.__setattr__(self, "ids", _array(self.ids, np.int64))
        n = self.ids.size
        object.__setattr__(self, "xy_m", _array(self.xy_m, np.float64, (n, 2)))
        object.__setattr__(self, "cov_m2", _array(self.cov_m2, np.float64, (n, 2, 2)))
        object.__setattr__(self, "kind", _array(self.kind, np.int8, (n,)))
        object.__setattr__(self, "sightings", _array(self.sightings, np.int64, (n,)))
        object.__setattr__(self, "confirmed", _array(self.confirmed, bool, (n,)))

    def __len__(self) -> int:
        return int(self.ids.size)

    def take(self, rows) -> Landmarks:
        """The landmarks at ``rows`` (an index array or a boolean mask over the rows)."""
        return Landmarks(ids=self.ids[rows], xy_m=self.xy_m[rows], cov_m2=self.cov_m2[rows], kind=self.kind[rows],
                         sightings=self.sightings[rows], confirmed=self.confirmed[rows])


@dataclass(frozen=True, eq=False, kw_only=True)
class SlamState:
    """The EKF after one scan's features: the pose, and the landmarks that changed.

    ``pose`` (3,), ``pose_cov`` (3, 3); ``landmarks``: those new or changed (beyond the
    stage's tolerance) since the previous state, or, with ``landmarks_complete``, the whole
    map (states of v1 recordings); ``removed_landmark_ids`` (R,) those dropped since the
    previous state; ``n_landmarks`` and ``n_confirmed`` count the map after this update
    (``lrfslam.msgs.landmark_map`` rebuilds the map itself). ``motion`` (3,), what moved
    the filter to this scan (scan-matched, else odometry: dx m, dy m, dtheta rad in the
    previous pose's frame), zero where it did not move, None in recordings made before slam
    states carried it; ``motion_matched``, whether it was found by scan matching.
    """

    stamp_ns: int
    seq: int
    scan_seq: int
    pose: np.ndarray
    pose_cov: np.ndarray
    landmarks: Landmarks = field(default_factory=Landmarks)
    removed_landmark_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    landmarks_complete: bool = False
    n_landmarks: int = 0
    n_confirmed: int = 0
    associated: int = 0
    added: int = 0
    rejected: int = 0
    motion: np.ndarray | None = None
    motion_matched: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "pose", _array(self.pose, np.float64, (3,)))
        object.__setattr__(self, "pose_cov", _array(self.pose_cov, np.float64, (3, 3)))
        if self.motion is not None:
            object.__setattr__(self, "motion", _array(self.motion, np.float64, (3,)))
        object.__setattr__(self, "removed_landmark_ids", _array(self.removed_landmark_ids, np.int64))


@dataclass(frozen=True, eq=False, kw_only=True)
class LandmarkMap:
    """The whole landmark map as it stands after the slam state numbered ``state_seq``.

    ``tolerance_m``: how far a landmark may move, or its standard deviations change, before
    a slam state carries it again (so a map rebuilt from this one and the states after it
    is within it of the filter's).
    """

    stamp_ns: int
    seq: int
    state_seq: int
    landmarks: Landmarks = field(default_factory=Landmarks)
    tolerance_m: float = 0.0


@dataclass(frozen=True, eq=False, kw_only=True)
class GroundTruth:
    """Simulator truth at one instant: ``pose`` (3,) map frame, visible corners (K,) ids and (K, 2) map xy."""

    stamp_ns: int
    seq: int
    pose: np.ndarray
    corner_ids: np.ndarray
    corners_xy_m: np.ndarray
    world: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "pose", _array(self.pose, np.float64, (3,)))
        object.__setattr__(self, "corner_ids", _array(self.corner_ids, np.int64))
        object.__setattr__(self, "corners_xy_m", _array(self.corners_xy_m, np.float64, (-1, 2)))


@dataclass(frozen=True, kw_only=True)
class ServiceStatus:
    """Health and statistics of one service process (wall-clock based)."""

    service: str
    robot: str
    level: int
    message: str
    wall_stamp_ns: int
    uptime_s: float
    counters: dict
    last_data_stamp_ns: int = 0
    config_json: str = ""
    schemas: tuple = ()
    pid: int = 0
    host: str = ""

    @property
    def stamp_ns(self) -> int:
        """The stamp a received message carries (ns): for a status, its wall-clock time."""
        return self.wall_stamp_ns

    @property
    def seq(self) -> int:
        """Statuses are not numbered (their publisher's attachment is); 0."""
        return 0
