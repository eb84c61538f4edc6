"""sensor: laser scans and odometry, from the simulator or a real LMS200.

out: scan   LaserScan (181 beams at 1°, 8 m sensor limit; the 4 m cut happens downstream)
     odom   Odometry  (integrated wheel odometry, same stamp as its scan)
     truth  GroundTruth (simulator only: true pose and visible corners)

The sensor is the one stage that reads the clock: it stamps the data. Every
later stage takes time from these stamps.
"""

from __future__ import annotations

import math
import queue
import threading
import time
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from lrfslam.drivers.lms200.port import Lms200
from lrfslam.drivers.lms200.protocol import RangeStatus
from lrfslam.errors import ConfigError
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.runtime.step import Output, RunContext, ServiceSpec, StepBase
from lrfslam.sim.lidar import LidarModel
from lrfslam.sim.odometry import OdometryNoise
from lrfslam.sim.simulator import SimConfig, SimFrame, Simulator

SOURCES = ("auto", "sim", "lms200")


@dataclass(frozen=True)
class SensorConfig:
    source: str = "auto"                # "sim" (built-in world), "lms200" (serial), "auto": lms200 if device is set
    # -- simulator
    world: str = "hallway_loop"
    seed: int = 1
    rate_hz: float = 10.0               # scans per second of simulated time
    speed_mps: float = 0.5
    speedup: float = 1.0                # simulated seconds per wall second; 0 = as fast as possible
    range_sigma_m: float = 0.01
    mixed_pixel_prob: float = 0.3
    odom_trans_sigma_per_sqrt_m: float = 0.02   # the simulated odometry's random walks (σ·√m, σ·√rad)
    odom_rot_sigma_per_sqrt_rad: float = 0.02
    max_scans: int = 0                  # stop producing after this many (0 = endless)
    start_m: float = 0.0                # where along the world's loop the robot starts (m of arc length)
    # Wall-clock ns of the run's first frame; 0: now. A sensor restarted with its run's epoch
    # continues where the simulated robot is by now (lrfslam up passes it), skipping what it missed.
    epoch_ns: int = 0
    # -- LMS200
    device: str = ""                    # serial port, e.g. /dev/ttyUSB0 or an emulator's pty
    baud: int = 38400                   # 9600, 19200, 38400 or 500000

    RETIRED: ClassVar[dict[str, str]] = {
        old: f"renamed {old.replace('_per_', '_per_sqrt_')}: a random walk, its sigma grows with the square root "
             "of the motion" for old in ("odom_trans_sigma_per_m", "odom_rot_sigma_per_rad")}

    def __post_init__(self) -> None:
        if self.source not in SOURCES:
            raise ConfigError(f"sensor.source must be one of {SOURCES}, got {self.source!r}")
        if not self.rate_hz > 0 or self.speedup < 0:
            raise ConfigError("sensor.rate_hz must be > 0 and sensor.speedup >= 0")
        if self.epoch_ns < 0 or (self.epoch_ns and self.speedup == 0):
            raise ConfigError("sensor.epoch_ns must be >= 0, and needs a paced run (speedup > 0)")


def frame_outputs(frame: SimFrame, stamp_ns: int, sim: Simulator) -> tuple[Output, Output]:
    """A frame of ``sim`` as the sensor publishes it, stamped ``stamp_ns``: its odometry, then its scan
    (the in-process drivers — Monte Carlo, evaluations, benchmarks — feed the stages the same)."""
    lidar, seq = sim.config.lidar, frame.index + 1
    scan = t.LaserScan.from_ranges(stamp_ns, seq, frame.scan.ranges_m, lidar.angle_min_rad, lidar.angle_increment_rad,
                                   lidar.max_range_m, scan_time_s=1.0 / sim.config.rate_hz, source="sim")
    return Output(topics.ODOM, t.Odometry(stamp_ns=stamp_ns, seq=seq, pose=frame.odom_pose)), Output(topics.SCAN, scan)


class SimSource(StepBase):
    """Publishes simulator frames paced at ``rate_hz × speedup`` of wall time."""

    def __init__(self, cfg: SensorConfig) -> None:
        super().__init__()
        self.cfg = cfg
        lidar = LidarModel(range_sigma_m=cfg.range_sigma_m, mixed_pixel_prob=cfg.mixed_pixel_prob)
        odom = OdometryNoise(trans_sigma_per_sqrt_m=cfg.odom_trans_sigma_per_sqrt_m,
                             rot_sigma_per_sqrt_rad=cfg.odom_rot_sigma_per_sqrt_rad)
        self.sim = Simulator(SimConfig(world_name=cfg.world, lidar=lidar, odometry=odom, speed_mps=cfg.speed_mps,
                                       rate_hz=cfg.rate_hz, start_m=cfg.start_m, seed=cfg.seed))
        self.frames = iter(self.sim)
        self.corners_xy = self.sim.map_corners.xy_m
        # Whole milliseconds keep stamps readable; the rest of each stamp is simulated time.
        self.t0_ns = cfg.epoch_ns or time.time_ns() // 1_000_000 * 1_000_000
        behind_s = max(0.0, (time.time_ns() - self.t0_ns) / 1e9) if cfg.epoch_ns else 0.0
        self.t0_mono = time.monotonic() - behind_s
        self.produced = 0
        # The frames missed while down are computed, not published, so the noise that follows
        # (odometry drift above all) is the uninterrupted run's.
        for _ in range(math.ceil(behind_s * cfg.rate_hz * cfg.speedup)):
            next(self.frames)
            self.produced += 1
        if self.produced:
            self.counts["skipped"] = self.produced

    def poll(self, timeout_s: float):
        if self.cfg.max_scans and self.produced >= self.cfg.max_scans:
            time.sleep(timeout_s)
            return ()
        if self.cfg.speedup > 0:
            due = self.t0_mono + self.produced / self.cfg.rate_hz / self.cfg.speedup
            wait = due - time.monotonic()
            if wait > timeout_s:
                time.sleep(timeout_s)
                return ()
            if wait > 0:
                time.sleep(wait)
        frame = next(self.frames)
        self.produced += 1
        seq = frame.index + 1
        stamp = self.t0_ns + round(frame.t_s * 1e9)
        odom, scan = frame_outputs(frame, stamp, self.sim)
        ids = frame.visible_corner_ids
        self.counts["scans"] += 1
        return (
            odom,
            Output(topics.TRUTH, t.GroundTruth(stamp_ns=stamp, seq=seq, pose=frame.true_pose, corner_ids=ids,
                                               corners_xy_m=self.corners_xy[ids], world=self.cfg.world)),
            scan,
        )


# LMS200 per-value status -> the scan schema's BeamStatus.
_BEAM_STATUS = {
    RangeStatus.OK: t.BEAM_VALID, RangeStatus.NO_ECHO: t.BEAM_NO_RETURN, RangeStatus.BEYOND_MAX: t.BEAM_NO_RETURN,
    RangeStatus.DAZZLE: t.BEAM_DAZZLE, RangeStatus.OVERFLOW: t.BEAM_OVERFLOW,
}
_STATUS_LUT = np.array([_BEAM_STATUS.get(RangeStatus(i), t.BEAM_INVALID) for i in range(len(RangeStatus))],
                       dtype=np.uint8)


class Lms200Source(StepBase):
    """Scans from an LMS200 on a serial port (or the emulator's pseudo-terminal).

    The driver blocks on the port, so it runs in a thread that hands scans over a
    queue; the runner's loop stays responsive to SIGTERM and status queries. The
    driver never raises for device trouble: it reconnects, and its fault counters
    show in this service's status.
    """

    def __init__(self, cfg: SensorConfig) -> None:
        super().__init__()
        self.driver = Lms200(cfg.device, cfg.baud)
        self.stop = threading.Event()
        self.scans: queue.Queue = queue.Queue(maxsize=64)
        self.seq = 0
        self.thread = threading.Thread(target=self._read, name="lms200", daemon=True)
        self.thread.start()

    def _read(self) -> None:
        for telegram in self.driver.scans(self.stop):
            try:
                self.scans.put_nowait((self.driver.last_stamp_ns, telegram))
            except queue.Full:
                self.counts["dropped_scans"] += 1

    def poll(self, timeout_s: float):
        try:
            read_ns, tg = self.scans.get(timeout=timeout_s)
        except queue.Empty:
            return ()
        if tg.partial or tg.resolution_deg is None or tg.start_angle_deg is None:
            self.counts["unsupported_scans"] += 1  # interlaced or non-standard counts: not a full sweep
            return ()
        # Stamp the first beam: the telegram's last byte arrived after its transmission time.
        wire_s = (tg.ranges_m.size * 2 + 10) * 10 / self.driver.baud
        self.seq += 1
        self.counts["scans"] += 1
        scan = t.LaserScan(stamp_ns=read_ns - int(wire_s * 1e9), seq=self.seq, ranges_m=tg.ranges_m,
                           status=_STATUS_LUT[tg.status], angle_min_rad=math.radians(tg.start_angle_deg - 90.0),
                           angle_increment_rad=math.radians(tg.resolution_deg), range_max_m=8.183, source="lms200")
        return (Output(topics.SCAN, scan),)

    def health(self) -> tuple[int, str]:
        c = self.driver.counters
        self.counts.update({f"lms200.{k}": v for k, v in c.items() if v})
        if not self.driver.device_type:
            return t.HEALTH_WARN, f"waiting for an LMS200 on {self.driver.device}"
        return t.HEALTH_OK, f"{self.driver.device_type} on {self.driver.device} at {self.driver.baud} Bd"

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=5)
        self.driver.close()


def build(cfg: SensorConfig, ctx: RunContext):
    if cfg.source == "sim" or (cfg.source == "auto" and not cfg.device):
        return SimSource(cfg)
    if not cfg.device:
        raise ConfigError("sensor.source=lms200 needs sensor.device (e.g. --device /dev/ttyUSB0)")
    return Lms200Source(cfg)


SPEC = ServiceSpec(
    name="sensor",
    summary="Laser scans + odometry from the simulated hallway (default) or an LMS200 on a serial port.",
    config_type=SensorConfig,
    inputs=(),
    outputs=(topics.SCAN, topics.ODOM, topics.TRUTH),
    build=build,
    flags=(("--source", "source", "sim or lms200"), ("--device", "device", "LMS200 serial port"),
           ("--baud", "baud", "LMS200 baud rate"), ("--seed", "seed", "simulator seed"),
           ("--speedup", "speedup", "simulated seconds per wall second, 0 = as fast as possible")),
)
