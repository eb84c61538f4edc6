"""Streaming parser for CARMEN log files (CLF), e.g. the Freiburg/Radish SLAM logs.

Pure: it takes lines of text and returns records; opening (possibly compressed)
files is :func:`lrfslam.io.textfile.open_log`'s job.

Line formats handled (tokens separated by white space; ``ipc_ts host logger_ts``
close every message)::

    ODOM x y theta tv rv accel ipc_ts host logger_ts
    FLASER n r_0 .. r_{n-1} x y theta odom_x odom_y odom_theta ipc_ts host logger_ts
    RLASER (same layout as FLASER, rear laser)
    ROBOTLASERk type start_angle fov resolution max_range accuracy remission_mode
                n r_0 .. r_{n-1} m rem_0 .. rem_{m-1}
                laser_x laser_y laser_theta robot_x robot_y robot_theta
                tv rv forward_safety side_safety turn_axis ipc_ts host logger_ts

Every other message type (``PARAM``, ``SYNC``, ``NEFF``, ``RAWLASER1``, ...),
comments (``#``) and blank lines are skipped and counted. Units are metres,
radians and seconds throughout.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np

from lrfslam.errors import ConfigError, InputError

#: CARMEN's reader sets ``maximum_range = 80 m`` for FLASER/RLASER (the LMS200's
#: longest range mode); a reading at or beyond it is a "no return".
CARMEN_FLASER_MAX_RANGE_M = 80.0

#: A log's "no return" code is the most frequent reading within
#: :data:`NO_RETURN_SEARCH_M` of its largest, when at least this share of all readings
#: (and :data:`NO_RETURN_MIN_COUNT` of them) are exactly that value: a measured range
#: repeats to the centimetre on that many beams only when the sensor writes one number
#: for "nothing seen" (Intel 81.83 m on 2.8 % of its beams, MIT CSAIL 81.91 m on 3.3 %,
#: ACES 50.0 m on 0.84 %, MIT Killian 51.06 m on 1.0 %).
NO_RETURN_MIN_SHARE = 1e-3
NO_RETURN_MIN_COUNT = 10
#: How far below the largest reading the code is looked for (m).
NO_RETURN_SEARCH_M = 1.0
#: Readings from this far below the code (m) upward are "no return" too: some loggers write
#: the code with centimetres of jitter round it (MIT Killian: 51.01–51.22 m round 51.06 m, a
#: band of 1.26 % of its readings), where a real return so close to the sensor's limit, on
#: that many beams, would be a coincidence.
NO_RETURN_JITTER_M = 0.05

#: Message names this parser turns into records.
LASER_MESSAGES = ("FLASER", "RLASER", "ROBOTLASER1", "ROBOTLASER2")

_DEG = np.pi / 180.0

# CARMEN's carmen_laser_guess_fov / carmen_laser_guess_angle_increment table for
# old-style lasers, which store no angles: n -> increment (rad). The first beam
# is always at -pi/2, so the 180- and 360-beam scans simply lack the +90 deg beam.
_FLASER_INCREMENT_RAD = {
    180: 1.0 * _DEG,
    181: 1.0 * _DEG,
    360: 0.5 * _DEG,
    361: 0.5 * _DEG,
    400: 0.25 * _DEG,
    401: 0.25 * _DEG,
}

# Tokens after the ranges of a FLASER line: 6 pose values + ipc_ts + host + logger_ts.
_FLASER_TAIL = 9
# Tokens of a ROBOTLASER line besides the n ranges and m remissions: name, 8 header
# fields (type .. n), m, 11 pose/velocity/safety values, ipc_ts, host, logger_ts.
_ROBOTLASER_FIXED = 24
_ODOM_TOKENS = 10


class CarmenLineError(InputError):
    """A CLF line of a known message type is malformed.

    Parameters
    ----------
    line_no : int
        1-based line number in the log (0 when unknown).
    reason : str
        What was wrong.
    """

    def __init__(self, line_no: int, reason: str) -> None:
        self.line_no = line_no
        self.reason = reason
        super().__init__(f"line {line_no}: {reason}")


@dataclass(frozen=True, eq=False)
class LaserRecord:
    """One laser scan with the poses logged alongside it.

    ``eq=False``: records hold arrays, so equality is identity; compare fields.

    Attributes
    ----------
    line_no : int
        1-based line number in the log.
    source : str
        Message name: ``"FLASER"``, ``"RLASER"``, ``"ROBOTLASER1"`` or ``"ROBOTLASER2"``.
    stamp_s : float
        ipc timestamp (s); the key the relations files use.
    ranges_m : ndarray, shape (N,), read-only
        Ranges (m) in beam order; "no return" readings are ``np.inf``.
    angle_min_rad : float
        Bearing of beam 0 in the laser frame (rad, counter-clockwise, 0 ahead).
    angle_increment_rad : float
        Bearing step between consecutive beams (rad); beam i is at
        ``angle_min_rad + i * angle_increment_rad``.
    max_range_m : float
        Threshold used for "no return": readings ``>= max_range_m`` became inf.
    laser_pose : ndarray, shape (3,), read-only
        Laser pose ``(x_m, y_m, theta_rad)`` in the log's world frame.
    odom_pose : ndarray, shape (3,), read-only
        Robot (odometry) pose ``(x_m, y_m, theta_rad)`` at scan time.
    logger_stamp_s : float
        Logger's own clock (s since the logger started).
    """

    line_no: int
    source: str
    stamp_s: float
    ranges_m: np.ndarray
    angle_min_rad: float
    angle_increment_rad: float
    max_range_m: float
    laser_pose: np.ndarray
    odom_pose: np.ndarray
    logger_stamp_s: float

    @property
    def n_beams(self) -> int:
        """Number of beams N."""
        return int(self.ranges_m.shape[0])


@dataclass(frozen=True)
class OdomRecord:
    """One ``ODOM`` line: the integrated wheel-odometry pose (not an increment).

    Attributes
    ----------
    line_no : int
        1-based line number in the log.
    stamp_s : float
        ipc timestamp (s).
    x, y : float
        Position (m) in the odometry frame.
    theta : float
        Heading (rad), counter-clockwise from +x, as logged (not re-wrapped).
    tv : float
        Translational velocity (m/s); 0 in the Intel and ACES logs.
    rv : float
        Rotational velocity (rad/s); 0 in the Intel and ACES logs.
    accel : float
        Acceleration (m/s^2).
    logger_stamp_s : float
        Logger's own clock (s).
    """

    line_no: int
    stamp_s: float
    x: float
    y: float
    theta: float
    tv: float
    rv: float
    accel: float
    logger_stamp_s: float

    @property
    def pose(self) -> np.ndarray:
        """Pose ``(x_m, y_m, theta_rad)``, shape (3,)."""
        return np.array([self.x, self.y, self.theta])


@dataclass(frozen=True)
class CarmenIssue:
    """A line of a known message type that was malformed and skipped.

    Attributes
    ----------
    line_no : int
        1-based line number in the log.
    message_type : str
        First token of the line (``""`` if it was not text).
    reason : str
        What was wrong.
    """

    line_no: int
    message_type: str
    reason: str


CarmenRecord = LaserRecord | OdomRecord


def flaser_beam_geometry(n_beams: int) -> tuple[float, float]:
    """Beam angles CARMEN implies for an old-style (FLASER/RLASER) scan.

    Parameters
    ----------
    n_beams : int
        Number of readings on the line, >= 2.

    Returns
    -------
    angle_min_rad, angle_increment_rad : float
        Beam i lies at ``angle_min_rad + i * angle_increment_rad``: -90 deg then
        1 deg steps for 180/181 beams, 0.5 deg for 360/361, 0.25 deg for 400/401,
        otherwise 180 deg spread over ``n_beams - 1`` steps.

    Raises
    ------
    InputError
        If ``n_beams < 2`` (no increment can be implied).
    """
    if n_beams < 2:
        raise InputError(f"cannot imply beam angles for {n_beams} beam(s)")
    increment = _FLASER_INCREMENT_RAD.get(n_beams, np.pi / (n_beams - 1))
    return -np.pi / 2.0, float(increment)


def _floats(tokens: list[str], what: str, line_no: int) -> np.ndarray:
    """Parse tokens as finite floats, shape (len(tokens),), or raise CarmenLineError."""
    try:
        values = np.array(tokens, dtype=float)
    except ValueError:
        raise CarmenLineError(line_no, f"{what}: not a number") from None
    if not np.all(np.isfinite(values)):
        raise CarmenLineError(line_no, f"{what}: not finite")
    return values


def _int(token: str, what: str, line_no: int) -> int:
    try:
        return int(token)
    except ValueError:
        raise CarmenLineError(line_no, f"{what}: not an integer ({token[:20]!r})") from None


def _check_no_return(no_return_min_m: float | None) -> None:
    if no_return_min_m is not None and not no_return_min_m > 0.0:
        raise ConfigError(f"no_return_min_m must be > 0 m, got {no_return_min_m}")


def _frozen(a: np.ndarray) -> np.ndarray:
    # Records are frozen dataclasses; read-only arrays make the contents frozen too.
    a.setflags(write=False)
    return a


def _ranges(raw: np.ndarray, max_range_m: float, line_no: int) -> np.ndarray:
    if np.any(raw < 0.0):
        raise CarmenLineError(line_no, "negative range")
    return _frozen(np.where(raw >= max_range_m, np.inf, raw))


def _parse_flaser(tokens: list[str], line_no: int, no_return_min_m: float | None) -> LaserRecord:
    if len(tokens) < 2:
        raise CarmenLineError(line_no, "missing num_readings")
    n = _int(tokens[1], "num_readings", line_no)
    if n < 2:
        raise CarmenLineError(line_no, f"num_readings {n} < 2: beam angles undefined")
    expected = 2 + n + _FLASER_TAIL
    if len(tokens) != expected:
        raise CarmenLineError(line_no, f"expected {expected} tokens for {n} beams, got {len(tokens)}")
    raw = _floats(tokens[2 : 2 + n], "ranges", line_no)
    poses = _floats(tokens[2 + n : 8 + n], "poses", line_no)
    stamps = _floats([tokens[8 + n], tokens[10 + n]], "timestamps", line_no)
    max_range = CARMEN_FLASER_MAX_RANGE_M if no_return_min_m is None else no_return_min_m
    angle_min, increment = flaser_beam_geometry(n)
    return LaserRecord(
        line_no=line_no,
        source=tokens[0],
        stamp_s=float(stamps[0]),
        ranges_m=_ranges(raw, max_range, line_no),
        angle_min_rad=angle_min,
        angle_increment_rad=increment,
        max_range_m=float(max_range),
        laser_pose=_frozen(poses[:3].copy()),
        odom_pose=_frozen(poses[3:].copy()),
        logger_stamp_s=float(stamps[1]),
    )


def _parse_robotlaser(tokens: list[str], line_no: int, no_return_min_m: float | None) -> LaserRecord:
    if len(tokens) < 9:
        raise CarmenLineError(line_no, f"expected >= 9 header tokens, got {len(tokens)}")
    # laser_type, fov, accuracy and remission_mode are checked for well-formedness
    # only: the beam geometry is fully given by start_angle and the resolution.
    _int(tokens[1], "laser_type", line_no)
    _int(tokens[7], "remission_mode", line_no)
    start_angle, _fov, resolution, max_range_field, _accuracy = _floats(tokens[2:7], "laser config", line_no)
    n = _int(tokens[8], "num_readings", line_no)
    if n < 0 or len(tokens) < 10 + n:
        raise CarmenLineError(line_no, f"num_readings {n} does not fit a line of {len(tokens)} tokens")
    m = _int(tokens[9 + n], "num_remissions", line_no)
    expected = _ROBOTLASER_FIXED + n + m
    if m < 0 or len(tokens) != expected:
        raise CarmenLineError(
            line_no, f"expected {expected} tokens for {n} beams and {m} remissions, got {len(tokens)}"
        )
    raw = _floats(tokens[9 : 9 + n], "ranges", line_no)
    tail = 10 + n + m
    poses = _floats(tokens[tail : tail + 6], "poses", line_no)
    # tv, rv and the safety/turn-axis parameters are validated but not kept: the
    # SLAM pipeline derives motion from poses.
    _floats(tokens[tail + 6 : tail + 11], "velocities/safety", line_no)
    stamps = _floats([tokens[tail + 11], tokens[tail + 13]], "timestamps", line_no)
    if no_return_min_m is not None:
        max_range = no_return_min_m
    elif max_range_field > 0.0:
        max_range = float(max_range_field)
    else:
        raise CarmenLineError(line_no, f"maximum_range {max_range_field} <= 0")
    return LaserRecord(
        line_no=line_no,
        source=tokens[0],
        stamp_s=float(stamps[0]),
        ranges_m=_ranges(raw, max_range, line_no),
        angle_min_rad=float(start_angle),
        angle_increment_rad=float(resolution),
        max_range_m=float(max_range),
        laser_pose=_frozen(poses[:3].copy()),
        odom_pose=_frozen(poses[3:].copy()),
        logger_stamp_s=float(stamps[1]),
    )


def _parse_odom(tokens: list[str], line_no: int) -> OdomRecord:
    if len(tokens) != _ODOM_TOKENS:
        raise CarmenLineError(line_no, f"expected {_ODOM_TOKENS} tokens, got {len(tokens)}")
    x, y, theta, tv, rv, accel, stamp = _floats(tokens[1:8], "values", line_no)
    (logger_stamp,) = _floats(tokens[9:10], "logger timestamp", line_no)
    return OdomRecord(
        line_no=line_no,
        stamp_s=float(stamp),
        x=float(x),
        y=float(y),
        theta=float(theta),
        tv=float(tv),
        rv=float(rv),
        accel=float(accel),
        logger_stamp_s=float(logger_stamp),
    )


def parse_line(line: str, line_no: int = 0, *, no_return_min_m: float | None = None) -> CarmenRecord | None:
    """Parse one CLF line.

    Parameters
    ----------
    line : str
        One line, with or without its line break.
    line_no : int
        1-based line number, copied into the record or the error.
    no_return_min_m : float, optional
        Readings ``>= no_return_min_m`` (m) become ``np.inf``. Default: 80 m for
        FLASER/RLASER (CARMEN's value) and the line's ``maximum_range`` for
        ROBOTLASERk. :func:`survey` finds the code a log writes.

    Returns
    -------
    LaserRecord or OdomRecord or None
        None for comments, blank lines and message types this parser skips.

    Raises
    ------
    CarmenLineError
        If a line of a handled message type is malformed.
    ConfigError
        If ``no_return_min_m`` is not positive.
    """
    _check_no_return(no_return_min_m)
    tokens = line.split()
    if not tokens:
        return None
    name = tokens[0]
    if name == "ODOM":
        return _parse_odom(tokens, line_no)
    if name in ("FLASER", "RLASER"):
        return _parse_flaser(tokens, line_no, no_return_min_m)
    if name in ("ROBOTLASER1", "ROBOTLASER2"):
        return _parse_robotlaser(tokens, line_no, no_return_min_m)
    return None


def _skip_key(line: str) -> str:
    """Counter key of a skipped line: its message name, ``"#"`` or ``""`` (blank)."""
    tokens = line.split(maxsplit=1)
    if not tokens:
        return ""
    return "#" if tokens[0].startswith("#") else tokens[0]


class CarmenReader:
    """Single-pass reader over the lines of a CLF, in file order.

    Iterating yields :class:`LaserRecord`, :class:`OdomRecord` and, for each
    malformed line of a handled type, a :class:`CarmenIssue`; it never raises on
    bad content. Skipped lines are tallied in :attr:`skipped`.

    Parameters
    ----------
    lines : iterable of str, or str
        One line per item (e.g. an open text file). A single ``str`` is split
        into lines first.
    no_return_min_m : float, optional
        See :func:`parse_line`.

    Raises
    ------
    ConfigError
        If ``no_return_min_m`` is not positive (checked at construction).

    Notes
    -----
    Timestamps are passed through untouched; the Intel log's laser stamps run
    backwards 631 times, so callers must use file order, not stamp order.
    """

    def __init__(self, lines: Iterable[str] | str, *, no_return_min_m: float | None = None) -> None:
        _check_no_return(no_return_min_m)
        self._lines = lines.splitlines() if isinstance(lines, str) else lines
        self._no_return_min_m = no_return_min_m
        self._skipped: Counter[str] = Counter()
        self._params: dict[str, str] = {}
        self._lines_read = 0
        # One generator per reader: the input (often a file) can be read only once.
        self._records = self._run()

    def __iter__(self) -> Iterator[CarmenRecord | CarmenIssue]:
        return self._records

    @property
    def skipped(self) -> dict[str, int]:
        """Lines skipped so far, by message name (``"#"`` comments, ``""`` blank)."""
        return dict(self._skipped)

    @property
    def params(self) -> dict[str, str]:
        """``PARAM name value`` lines read so far (the lines still count as skipped)."""
        return dict(self._params)

    @property
    def lines_read(self) -> int:
        """Number of lines consumed so far."""
        return self._lines_read

    def _run(self) -> Iterator[CarmenRecord | CarmenIssue]:
        for line_no, line in enumerate(self._lines, start=1):
            self._lines_read = line_no
            if not isinstance(line, str):
                yield CarmenIssue(line_no, "", f"expected str, got {type(line).__name__}")
                continue
            try:
                record = parse_line(line, line_no, no_return_min_m=self._no_return_min_m)
            except CarmenLineError as exc:
                yield CarmenIssue(line_no, line.split(maxsplit=1)[0], exc.reason)
                continue
            if record is None:
                key = _skip_key(line)
                self._skipped[key] += 1
                if key == "PARAM" and len(tokens := line.split()) >= 3:
                    self._params[tokens[1]] = tokens[2]
            else:
                yield record


def iter_records(
    lines: Iterable[str] | str, *, no_return_min_m: float | None = None
) -> Iterator[CarmenRecord | CarmenIssue]:
    """Records and issues of a CLF in file order; see :class:`CarmenReader`.

    Use :class:`CarmenReader` directly when the counts of skipped lines matter.
    """
    return iter(CarmenReader(lines, no_return_min_m=no_return_min_m))


def laser_trajectory(items: Iterable[object], *, pose: str = "odom") -> tuple[np.ndarray, np.ndarray]:
    """Stamps and poses of the laser records in a stream, in file order.

    Parameters
    ----------
    items : iterable
        Output of :func:`iter_records`; anything but :class:`LaserRecord` is ignored.
    pose : {"odom", "laser"}
        Which pose of each scan to take: the robot odometry pose (raw logs) or the
        laser pose (what corrected/SLAM-output logs rewrite).

    Returns
    -------
    stamps_s : ndarray, shape (T,)
        ipc timestamps (s).
    poses : ndarray, shape (T, 3)
        ``(x_m, y_m, theta_rad)`` per scan.

    Raises
    ------
    ConfigError
        If ``pose`` is neither ``"odom"`` nor ``"laser"``.
    """
    if pose not in ("odom", "laser"):
        raise ConfigError(f"pose must be 'odom' or 'laser', got {pose!r}")
    stamps: list[float] = []
    rows: list[np.ndarray] = []
    for item in items:
        if isinstance(item, LaserRecord):
            stamps.append(item.stamp_s)
            rows.append(item.odom_pose if pose == "odom" else item.laser_pose)
    return np.array(stamps, dtype=float), np.array(rows, dtype=float).reshape(-1, 3)


#: How far (m, rad) the lines' laser-in-robot poses may scatter and still be one rigid mounting.
MOUNT_TOLERANCE = (0.01, 0.01)

#: CARMEN's parameter for the front laser's forward offset from the robot centre (m).
FRONT_LASER_OFFSET_PARAM = "robot_frontlaser_offset"


@dataclass(frozen=True, eq=False)
class LaserSurvey:
    """What one pass over a log says about its laser: the facts an importer must not guess.

    Attributes
    ----------
    scans : int
        Laser lines read.
    beam_counts : dict of int to int
        Lines per number of beams.
    readings : int
        Range readings over all lines.
    max_reading_m : float
        Largest reading (m); NaN without readings.
    top_counts : dict of float to int
        Readings within :data:`NO_RETURN_SEARCH_M` of ``max_reading_m``, counted by value.
    line_mount : ndarray, shape (3,)
        Median over the lines of the laser pose in the robot frame,
        ``(x_m, y_m, theta_rad)``, from each line's laser and odometry poses;
        zero when the lines disagree (9 in 10 within :data:`MOUNT_TOLERANCE`
        of the median), as in a log whose laser poses a SLAM run rewrote.
    params : dict of str to str
        The log's ``PARAM`` lines.
    """

    scans: int
    beam_counts: dict[int, int]
    readings: int
    max_reading_m: float
    top_counts: dict[float, int]
    line_mount: np.ndarray
    params: dict[str, str] = field(default_factory=dict)

    @property
    def no_return_code_m(self) -> float | None:
        """The value the log writes for "no return" (m), or None when it writes none.

        The most frequent reading near the largest is that code when it repeats on at least
        :data:`NO_RETURN_MIN_SHARE` of all readings (and :data:`NO_RETURN_MIN_COUNT`); ties
        go to the larger value.
        """
        if not self.top_counts:
            return None
        count, code = max((n, value) for value, n in self.top_counts.items())
        if count >= NO_RETURN_MIN_COUNT and count >= NO_RETURN_MIN_SHARE * self.readings:
            return code
        return None

    @property
    def no_return_m(self) -> float | None:
        """Readings at or above this (m) are "no return": the least reading of the log within
        :data:`NO_RETURN_JITTER_M` below the code (the code itself when none is); None without a code."""
        code = self.no_return_code_m
        if code is None:
            return None
        # The slack keeps a reading printed exactly at the band's edge (51.01 = 51.06 − 0.05) inside it.
        return min(value for value in self.top_counts if code - value <= NO_RETURN_JITTER_M + 1e-9)

    @property
    def no_return_count(self) -> int:
        """Readings at or above :attr:`no_return_m` (0 without a code)."""
        floor = self.no_return_m
        return 0 if floor is None else sum(n for value, n in self.top_counts.items() if value >= floor)

    @property
    def mount(self) -> np.ndarray:
        """Laser pose in the robot frame ``(x_m, y_m, theta_rad)``, shape (3,).

        The lines' laser poses say it when they differ from the odometry poses;
        where they coincide, a non-zero ``robot_frontlaser_offset`` parameter (a
        forward offset the logger did not apply) says it.
        """
        if np.any(np.abs(self.line_mount) > 1e-4):
            return self.line_mount.copy()
        try:
            forward = float(self.params.get(FRONT_LASER_OFFSET_PARAM, "0"))
        except ValueError:
            forward = 0.0
        return np.array([forward if math.isfinite(forward) else 0.0, 0.0, 0.0])


def laser_in_robot_frame(laser_pose: np.ndarray, odom_pose: np.ndarray) -> np.ndarray:
    """Pose (3,) of the laser in the robot frame, from both poses (3,) in the world frame."""
    c, s = math.cos(odom_pose[2]), math.sin(odom_pose[2])
    dx, dy = laser_pose[0] - odom_pose[0], laser_pose[1] - odom_pose[1]
    dtheta = (laser_pose[2] - odom_pose[2] + math.pi) % (2.0 * math.pi) - math.pi
    return np.array([c * dx + s * dy, -s * dx + c * dy, dtheta])


def survey(lines: Iterable[str] | str) -> LaserSurvey:
    """One pass over a CLF's lines: beam counts, the "no return" code, the laser mounting.

    Malformed lines are ignored here (the import pass reports them).
    """
    reader = CarmenReader(lines, no_return_min_m=math.inf)
    beam_counts: Counter[int] = Counter()
    readings = 0
    top = -math.inf
    near_top: Counter[float] = Counter()
    mounts: list[np.ndarray] = []
    for item in reader:
        if not isinstance(item, LaserRecord):
            continue
        ranges = item.ranges_m
        beam_counts[item.n_beams] += 1
        readings += ranges.size
        if ranges.size:
            top = max(top, float(ranges.max()))
            near_top.update(ranges[ranges >= top - NO_RETURN_SEARCH_M].tolist())
        mounts.append(laser_in_robot_frame(item.laser_pose, item.odom_pose))
    line_mount = np.zeros(3)
    if mounts:
        per_line = np.array(mounts)
        median = np.median(per_line, axis=0)
        off = np.abs(per_line - median)
        rigid = (np.hypot(off[:, 0], off[:, 1]) <= MOUNT_TOLERANCE[0]) & (off[:, 2] <= MOUNT_TOLERANCE[1])
        if np.mean(rigid) >= 0.9:
            line_mount = median
    return LaserSurvey(scans=sum(beam_counts.values()), beam_counts=dict(beam_counts), readings=readings,
                       max_reading_m=top if readings else math.nan,
                       top_counts={v: n for v, n in near_top.items() if v >= top - NO_RETURN_SEARCH_M},
                       line_mount=line_mount, params=reader.params)
