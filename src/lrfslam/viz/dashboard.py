"""The web dashboard's view of one robot: lrfslam messages in, a JSON-able snapshot out.

:class:`DashboardModel` keeps what ``lrfslam monitor --dashboard`` draws (src/lrfslam/tools/dashboard.py
serves it): the scan of the newest SLAM state (every beam, and the beams the denoiser kept) with
its corners, placed at that state's pose; the EKF's landmarks with their 95 % ellipses; the EKF's
trajectory, the mapper's loop-closed one and the simulator's ground truth; the mapper's live
occupancy grid (its ``map/grid`` tiles put together, served as a picture, :meth:`DashboardModel.grid_png`);
on a saved map, whether the robot is localized on it and how surely (the mapper's ``map/pose``);
and a row per service from its health (level, message, rates, drops, gaps, errors) and its
liveliness. Everything is drawn in the EKF's ``slam`` frame (x, y in m): the loop-closed trajectory
and the grid are moved there by the mapper's ``map_from_slam``, the truth by the first EKF pose that has a true pose at its stamp (as
lrfslam/viz/foxglove.py ties ``world`` to ``map``). No transport, no clock: rates come from the
services' own wall stamps.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np

from lrfslam.algo.geometry import compose, from_frame, inverse, polar_to_xy
from lrfslam.errors import ConfigError
from lrfslam.msgs import counters as names
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.msgs.grid_replica import GridReplica
from lrfslam.msgs.landmark_map import LandmarkMapReplica
from lrfslam.viz.foxglove import ellipse_axes
from lrfslam.viz.keyframe_path import KeyframePath
from lrfslam.viz.png import gray_alpha_png

LEVELS = {t.HEALTH_OK: "OK", t.HEALTH_WARN: "WARN", t.HEALTH_ERROR: "ERROR", t.HEALTH_STALE: "STALE"}

_KEPT_BY_STAMP = 64     # scans, kept scans and features waiting for the SLAM state of their stamp
_TRUTH_BY_STAMP = 256   # true poses kept to find the one at an EKF stamp


@dataclass(frozen=True)
class DashboardConfig:
    """How much the dashboard keeps: trajectories thinned to a pose every ``path_step_m``, at most ``max_path_poses``
    each (then every other pose is dropped, so a long run keeps its whole shape)."""

    path_step_m: float = 0.05
    max_path_poses: int = 4000

    def __post_init__(self) -> None:
        if not self.path_step_m >= 0 or self.max_path_poses < 2:
            raise ConfigError(f"path_step_m must be ≥ 0 and max_path_poses ≥ 2: {self}")


def counter_figures(counters: dict[str, int]) -> dict[str, int]:
    """A service's totals: inputs, outputs (health not counted), dropped (``drop.*``), gaps (``gap.*``),
    skipped (``skip.*``: stale inputs a stage behind skipped, lrfslam/runtime/bus.py), errors;
    its latency percentiles (ms) from receiving an input to publishing its outputs, when it has inputs; and
    the age percentiles (ms) of what it published, from the scan's sensor stamp on the wall clock, when it
    reports them (lrfslam/runtime/latency.py)."""
    def total(*prefixes: str) -> int:
        return names.total(counters, *prefixes)

    figures = {"in": total(names.IN), "out": total(names.OUT) - total(names.OUT_HEALTH), "dropped": total(names.DROP),
               "gaps": total(names.GAP), "skipped": total(names.SKIP), "errors": total(names.ERROR, names.STEP_ERROR)}
    for kind, label in ((names.LATENCY, "latency"), (names.AGE, "age")):
        if kind + "p50_us" in counters:
            figures |= {f"{label}_p50_ms": counters[kind + "p50_us"] / 1e3, f"{label}_p99_ms": counters[kind + "p99_us"] / 1e3}
    return figures


def rates(before: t.ServiceStatus | None, after: t.ServiceStatus) -> tuple[float, float] | None:
    """(inputs/s, outputs/s) of one service between two of its statuses, on its wall stamps; None
    when they are not two of the same process in order."""
    if before is None or before.pid != after.pid or before.host != after.host:
        return None
    dt = (after.wall_stamp_ns - before.wall_stamp_ns) / 1e9
    if dt <= 0:
        return None
    a, b = counter_figures(before.counters), counter_figures(after.counters)
    return (b["in"] - a["in"]) / dt, (b["out"] - a["out"]) / dt


class Path:
    """A thinned, bounded trajectory of (x, y) in one frame."""

    def __init__(self, cfg: DashboardConfig) -> None:
        self.cfg = cfg
        self.xy: list[tuple[float, float]] = []

    def add(self, x: float, y: float) -> None:
        if self.xy and math.hypot(x - self.xy[-1][0], y - self.xy[-1][1]) < self.cfg.path_step_m:
            return
        self.xy.append((float(x), float(y)))
        if len(self.xy) > self.cfg.max_path_poses:
            self.xy = self.xy[::2] if len(self.xy) % 2 else self.xy[:-1:2] + [self.xy[-1]]

    def replace(self, xy: np.ndarray) -> None:
        self.xy = []
        for x, y in np.asarray(xy, float).reshape(-1, 2):
            self.add(x, y)


def _moved(frame_from_points: np.ndarray, xy: list[tuple[float, float]] | np.ndarray) -> list[list[float]]:
    """Points ``xy`` (N, 2) moved by pose ``frame_from_points``, rounded to mm for the page."""
    pts = np.asarray(xy, float).reshape(-1, 2)
    if pts.size == 0:
        return []
    return np.round(from_frame(pts, frame_from_points), 3).tolist()


class DashboardModel:
    """What the dashboard shows of one robot; feed every message with :meth:`from_payload` or :meth:`add`."""

    def __init__(self, cfg: DashboardConfig | None = None) -> None:
        self.cfg = cfg or DashboardConfig()
        self.scans = 0                     # scans received
        self.states = 0                    # SLAM states received
        self.version = 0                   # bumped on every change the page would show
        self.state: t.SlamState | None = None
        self.map = LandmarkMapReplica()
        self._waiting: dict[str, OrderedDict[int, Any]] = {
            name: OrderedDict() for name in (topics.SCAN.name, topics.SCAN_FILTERED.name, topics.FEATURES.name)}
        self.scan_xy: np.ndarray = np.zeros((0, 2))      # laser frame, of the newest state's scan
        self.kept_xy: np.ndarray = np.zeros((0, 2))
        self.corners: np.ndarray = np.zeros((0, 3))      # x, y (laser frame), kind
        self.slam_path = Path(self.cfg)
        self.map_path = Path(self.cfg)                   # map frame
        self.truth_path = Path(self.cfg)                 # world frame
        self._truth: OrderedDict[int, np.ndarray] = OrderedDict()
        self._slam_from_world: np.ndarray | None = None
        self._map_from_slam = np.zeros(3)
        self._keyframes_until_ns = 0
        self._map_pose: t.MapPose | None = None            # the mapper's newest
        self._keyframe_path = KeyframePath(self.cfg.max_path_poses // 4)
        self.grid = GridReplica()
        self.grid_version = 0              # bumped with every map/grid
        self.status: dict[str, t.ServiceStatus] = {}
        self._rates: dict[str, tuple[float, float]] = {}
        self.alive: dict[str, bool] = {}

    # -- input

    def from_payload(self, name: str, schema: str, data: bytes) -> bool:
        """One received payload on relative key ``name``; whether the model changed.

        Raises
        ------
        DecodeError
            It does not decode with ``schema``.
        """
        try:
            topic = topics.by_name(name)
        except KeyError:
            return False
        return self.add(name, topic.codec.decode(data, schema))

    def add(self, name: str, value: Any) -> bool:
        """One decoded message on relative key ``name``; whether the model changed."""
        if topics.is_health(name):
            self._health(value)
        elif name == topics.SCAN.name:
            self.scans += 1
            self._wait(name, value.stamp_ns, value)
        elif name in self._waiting:
            self._wait(name, value.stamp_ns, value)
        elif name == topics.SLAM_STATE.name:
            self._slam(value)
        elif name == topics.SLAM_MAP.name:
            self.map.apply_map(value)
        elif name == topics.TRUTH.name:
            self._truth[value.stamp_ns] = np.asarray(value.pose, float)
            while len(self._truth) > _TRUTH_BY_STAMP:
                self._truth.popitem(last=False)
            self.truth_path.add(*value.pose[:2])
        elif name == topics.MAP_POSE.name:
            self._map_from_slam = np.asarray(value.map_from_slam, float)
            self._map_pose = value
            # On a saved map, a scan not localized is not drawn on it (its pose is a guess).
            if value.stamp_ns > self._keyframes_until_ns and value.localization != t.NOT_LOCALIZED:
                self.map_path.add(*value.pose[:2])
        elif name == topics.MAP_GRID.name:
            self.grid.apply(value)
            self.grid_version += 1
        elif name == topics.MAP_KEYFRAMES.name:
            stamps, poses = self._keyframe_path.update(value)
            if value.scan_stamp_ns.size:
                # An optimisation moved the past: the path becomes the keyframes, map poses add to it after.
                self.map_path.replace(poses[:, :2])
                self._keyframes_until_ns = int(stamps.max())
        else:
            return False
        self.version += 1
        return True

    def set_alive(self, service: str, alive: bool) -> None:
        """``service``'s liveliness token appeared (True) or went (False)."""
        if self.alive.get(service) != alive:
            self.alive[service] = alive
            self.version += 1

    def _wait(self, name: str, stamp_ns: int, value: Any) -> None:
        waiting = self._waiting[name]
        waiting[stamp_ns] = value
        while len(waiting) > _KEPT_BY_STAMP:
            waiting.popitem(last=False)

    def _slam(self, state: t.SlamState) -> None:
        self.states += 1
        self.state = state
        self.map.apply_state(state)
        stamp = state.stamp_ns
        scan = self._waiting[topics.SCAN.name].get(stamp)
        filtered = self._waiting[topics.SCAN_FILTERED.name].get(stamp)
        features = self._waiting[topics.FEATURES.name].get(stamp)
        if scan is not None or filtered is not None:
            raw = scan if scan is not None else filtered.scan
            ok = np.isfinite(raw.ranges_m)
            self.scan_xy = polar_to_xy(raw.ranges_m[ok], raw.angles_rad[ok])
            if filtered is not None:
                self.kept_xy = filtered.points_xy_m
            else:
                self.kept_xy = np.zeros((0, 2))
        if features is not None:
            self.corners = np.column_stack([features.xy_m, features.kind]) if len(features) else np.zeros((0, 3))
        for waiting in self._waiting.values():   # older ones will never be drawn
            while waiting and next(iter(waiting)) <= stamp:
                waiting.popitem(last=False)
        self.slam_path.add(*state.pose[:2])
        if self._slam_from_world is None and (true := self._truth.get(stamp)) is not None:
            self._slam_from_world = compose(state.pose, inverse(true))

    def _health(self, status: t.ServiceStatus) -> None:
        before = self.status.get(status.service)
        if before is not None and status.wall_stamp_ns <= before.wall_stamp_ns:
            return    # a status query's reply older than the health already shown
        r = rates(before, status)
        if r is not None:
            self._rates[status.service] = r
        elif before is not None:
            self._rates.pop(status.service, None)
        self.status[status.service] = status

    # -- output

    def services(self) -> list[dict[str, Any]]:
        """A row per service known from its health or its liveliness, in pipeline order then by name."""
        order = ("sensor", "denoise", "features", "slam", "mapper", "recorder")
        names = sorted(set(self.status) | set(self.alive), key=lambda n: (order.index(n) if n in order else 99, n))
        rows = []
        for name in names:
            st = self.status.get(name)
            row: dict[str, Any] = {"service": name, "alive": self.alive.get(name, False)}
            if st is not None:
                r = self._rates.get(name)
                row.update(counter_figures(st.counters), level=LEVELS.get(st.level, str(st.level)),
                           message=st.message, uptime_s=round(st.uptime_s, 1),
                           in_hz=None if r is None else round(r[0], 1), out_hz=None if r is None else round(r[1], 1),
                           pid=st.pid, host=st.host)
            rows.append(row)
        return rows

    def grid_png(self) -> bytes | None:
        """The grid as a PNG (walls black, free space white, unknown transparent; the top row the highest y),
        None before the first ``map/grid``."""
        image = self.grid.image()
        if image is None:
            return None
        cells = np.flipud(image.cells)
        gray = np.where(cells == 100, 0, 255).astype(np.uint8)
        return gray_alpha_png(gray, np.where(cells == -1, 0, 255).astype(np.uint8))

    def _grid_placement(self) -> dict[str, Any] | None:
        """Where the page draws :meth:`grid_png`: its lower-left corner and cell in the map frame, and the
        map frame in the ``slam`` frame."""
        frame = self.grid.frame()
        if frame is None:
            return None
        origin, (h, w) = frame
        return {"version": self.grid_version, "origin": [float(v) for v in origin],
                "resolution": self.grid.resolution_m, "width": int(w), "height": int(h),
                "slam_from_map": [round(float(v), 6) for v in inverse(self._map_from_slam)]}

    def _localization(self) -> dict[str, Any] | None:
        """On a saved map (``lrfslam up --map MAP --localize``): whether the newest scan is placed on
        it, and how sure (the 1-sigma position error, m, and heading error, degrees, of the pose's
        covariance); None while the mapper maps."""
        mp = self._map_pose
        if mp is None or mp.localization == t.MAPPING:
            return None
        located = mp.localization == t.LOCALIZED
        out: dict[str, Any] = {"localized": located, "sigma_m": None, "sigma_deg": None}
        cov = mp.pose_cov
        if located and cov is not None and np.all(np.isfinite(cov)):
            out["sigma_m"] = round(math.sqrt(max(float(cov[0, 0] + cov[1, 1]), 0.0)), 4)
            out["sigma_deg"] = round(math.degrees(math.sqrt(max(float(cov[2, 2]), 0.0))), 3)
        return out

    def snapshot(self) -> dict[str, Any]:
        """Everything the page draws, JSON-able; positions in the ``slam`` frame, m."""
        snap: dict[str, Any] = {"version": self.version, "scans": self.scans, "states": self.states,
                                "grid": self._grid_placement(), "localization": self._localization(),
                                "services": self.services(), "trajectory": _moved(np.zeros(3), self.slam_path.xy),
                                "map_trajectory": _moved(inverse(self._map_from_slam), self.map_path.xy),
                                "truth": [] if self._slam_from_world is None
                                else _moved(self._slam_from_world, self.truth_path.xy)}
        st = self.state
        if st is None:
            return snap | {"pose": None, "landmarks": [], "scan": [], "kept": [], "corners": []}
        landmarks = []
        lms = self.map.landmarks
        for i, lid in enumerate(lms.ids):
            major, minor, yaw = ellipse_axes(lms.cov_m2[i])
            landmarks.append([round(float(lms.xy_m[i, 0]), 3), round(float(lms.xy_m[i, 1]), 3),
                              round(major, 4), round(minor, 4), round(yaw, 4), int(lid), bool(lms.confirmed[i])])
        corners = _moved(st.pose, self.corners[:, :2]) if self.corners.size else []
        kinds = self.corners[:, 2].astype(int).tolist() if self.corners.size else []
        return snap | {
            "pose": [round(float(v), 4) for v in st.pose], "stamp_ns": int(st.stamp_ns), "landmarks": landmarks,
            "scan": _moved(st.pose, self.scan_xy), "kept": _moved(st.pose, self.kept_xy),
            "corners": [[x, y, k] for (x, y), k in zip(corners, kinds)]}
