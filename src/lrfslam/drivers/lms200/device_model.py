"""Behaviour of an LMS200 as the emulator plays it: request telegram in, reply telegrams out,
and the simulated scans it measures.

No I/O and no clock: :mod:`.emulator` owns the pseudo-terminal, the pacing and
the timing. It covers the commands :mod:`.port` sends plus 30h 01h (one scan
on request); any other request is answered with 92h, as a real unit answers a
logically invalid command (docs/lms200-protocol.md, 'Commands and replies').
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from lrfslam.drivers.lms200 import protocol as p
from lrfslam.sim.lidar import LidarModel, simulate_scan
from lrfslam.sim.simulator import SimConfig, Simulator

# ASCII type string, 21 characters, as in TL's example (TL p.65).
TYPE_STRING = b"LMS200;301063;V02.10 "
_BAUD_BY_CODE = {code: baud for baud, code in p.BAUD_CODES.items()}
_MODE_OK, _MODE_REFUSED = 0x00, 0x01  # A0h result byte
_REJECTED, _ACCEPTED = 0x00, 0x01  # BBh / F7h result byte
MIRROR_TURN_S = 0.01332  # one mirror revolution, 75 Hz (TL p.19)
_TURNS_PER_SCAN = {100: 1, 50: 2, 25: 4}  # resolution (1/100°) -> interlaced mirror turns per scan

# Ranges of scan number k for a variant, metres, +inf = no return.
ScanSource = Callable[[p.Variant, int], np.ndarray]


@dataclass(frozen=True)
class Reaction:
    """What the emulated LMS does about one request, after its ACK.

    ``replies`` go out in order; ``send_scan`` appends one B0 of the newest
    scan; ``new_baud`` takes effect once all of it has been sent (the LMS
    answers at the old rate, then switches).
    """

    replies: tuple[bytes, ...]
    send_scan: bool = False
    new_baud: int | None = None


class EmulatedLms200:
    """Protocol state of one emulated LMS200, in its power-on state.

    Parameters
    ----------
    baud : int
        Power-on rate (9600 on a unit without a stored permanent rate).
    units : protocol.Units
        Units in the configuration block (LMS200 factory default: mm).

    Attributes
    ----------
    baud : int
        Rate the LMS currently talks at.
    variant : protocol.Variant
        Active variant; factory default 180°/0.5°.
    config : bytes
        34-byte configuration block (74h/77h).
    streaming : bool
        True in mode 24h (continuous output).
    """

    def __init__(self, baud: int = 9600, units: p.Units = p.Units.MM) -> None:
        self._power_on_baud = baud
        self.config = p.config_with(p.DEFAULT_CONFIG, units=units, measuring_mode=0x00)
        self.power_cycle()

    def power_cycle(self) -> None:
        """Back to the power-on state; the configuration block lives in EEPROM and stays."""
        self.baud = self._power_on_baud
        self.variant = p.VARIANT_180_05
        self.streaming = False
        self._installation = False
        self._telegrams_sent = 0

    @property
    def units(self) -> p.Units:
        """Units of the range values, from the configuration block."""
        return p.Units(self.config[p.CONFIG_UNITS])

    @property
    def measuring_mode(self) -> int:
        """Value coding (config byte 5, 00h..06h)."""
        return self.config[p.CONFIG_MEASURING_MODE]

    def power_on_telegram(self) -> bytes:
        """90h telegram sent after power-on, at the power-on rate."""
        return p.build_reply(bytes((p.REPLY_POWER_ON,)) + TYPE_STRING)

    def handle(self, request: p.Telegram) -> Reaction:
        """React to one CRC-valid host telegram addressed to this LMS."""
        cmd, data = request.command, request.data
        if cmd == p.CMD_MODE and data:
            return self._mode(data)
        if cmd == p.CMD_TYPE and not data:
            return Reaction((p.build_reply(bytes((p.reply_code(cmd),)) + TYPE_STRING),))
        if cmd == p.CMD_VARIANT and len(data) == 4:
            return self._set_variant(data)
        if cmd == p.CMD_CONFIG_READ and not data:
            return Reaction((p.build_reply(bytes((p.reply_code(cmd),)) + self.config),))
        if cmd == p.CMD_CONFIG_WRITE and len(data) in p.CONFIG_LENGTHS:
            return self._write_config(data)
        if cmd == p.CMD_SCAN and data == b"\x01":
            return Reaction((), send_scan=True)
        return Reaction((p.build_reply(bytes((p.REPLY_REFUSED,))),))

    def scan_telegram(self, ranges_m: np.ndarray, scan_number: int) -> bytes:
        """B0 telegram for one complete scan in the configured units and measuring mode.

        Parameters
        ----------
        ranges_m : ndarray, shape (variant.n_values,)
            Metres, +inf = no return.
        scan_number : int
            Mirror-turn count of the scan, sent modulo 256 when indices are on.
        """
        raw = p.encode_ranges(ranges_m, self.units, self.measuring_mode)
        indices = None
        if self.config[p.CONFIG_AVAILABILITY] & p.AVAILABILITY_INDICES:
            indices = (scan_number % 256, self._telegrams_sent % 256)
        self._telegrams_sent += 1
        return p.build_scan_reply(raw, units=self.units, indices=indices)

    def _mode(self, data: bytes) -> Reaction:
        sub = data[0]
        if sub in _BAUD_BY_CODE and len(data) == 1:
            return self._mode_reply(_MODE_OK, new_baud=_BAUD_BY_CODE[sub])
        if sub == p.MODE_INSTALLATION and len(data) == 9:
            self._installation = data[1:] == p.DEFAULT_PASSWORD
            return self._mode_reply(_MODE_OK if self._installation else _MODE_REFUSED)
        if sub in (p.MODE_CONTINUOUS, p.MODE_ON_REQUEST) and len(data) == 1:
            self.streaming = sub == p.MODE_CONTINUOUS
            self._installation = False
            return self._mode_reply(_MODE_OK)
        return Reaction((p.build_reply(bytes((p.REPLY_REFUSED,))),))

    def _mode_reply(self, result: int, new_baud: int | None = None) -> Reaction:
        reply = p.build_reply(bytes((p.reply_code(p.CMD_MODE), result)))
        return Reaction((reply,), new_baud=new_baud)

    def _set_variant(self, data: bytes) -> Reaction:
        wanted = p.Variant(data[0] | (data[1] << 8), data[2] | (data[3] << 8))
        accepted = wanted in p.VARIANTS
        if accepted:
            self.variant = wanted
        echo = self.variant.fov_deg.to_bytes(2, "little") + self.variant.resolution_cdeg.to_bytes(2, "little")
        result = _ACCEPTED if accepted else _REJECTED
        return Reaction((p.build_reply(bytes((p.reply_code(p.CMD_VARIANT), result)) + echo),))

    def _write_config(self, data: bytes) -> Reaction:
        # Only installation mode may write, and only units / measuring modes we can encode.
        valid = (self._installation and data[p.CONFIG_UNITS] in (p.Units.CM, p.Units.MM)
                 and data[p.CONFIG_MEASURING_MODE] in p.MEASURING_MODES)
        if valid:
            self.config = bytes(data)
        result = _ACCEPTED if valid else _REJECTED
        return Reaction((p.build_reply(bytes((p.reply_code(p.CMD_CONFIG_WRITE), result)) + data),))


def scan_period_s(variant: p.Variant) -> float:
    """Time between complete scans of ``variant``: interlaced turns at finer resolutions."""
    return _TURNS_PER_SCAN[variant.resolution_cdeg] * MIRROR_TURN_S


class SimScanSource:
    """Scans of the simulated world along the simulator's loop, one pose per scan period.

    Scan ``k`` is drawn with its own generator seeded by ``(seed, k)``, so any
    scan can be regenerated from its number without replaying the ones before.

    Parameters
    ----------
    world_name : str
        A :func:`lrfslam.sim.floor_plans.world_names` entry.
    seed : int
    """

    def __init__(self, world_name: str = "hallway_loop", seed: int = 0) -> None:
        self._world_name = world_name
        self._seed = seed
        self._sims: dict[p.Variant, Simulator] = {}
        self._simulator(p.VARIANT_180_1)  # fail early on an unknown world

    def __call__(self, variant: p.Variant, k: int) -> np.ndarray:
        """Ranges of scan ``k`` of ``variant``, shape (variant.n_values,), metres."""
        sim = self._simulator(variant)
        rng = np.random.default_rng((self._seed, k))
        people = sim.walkers.segments(k / sim.config.rate_hz)
        return simulate_scan(sim.world, sim.trajectory.pose(k), sim.config.lidar, rng, movers_m=people).ranges_m

    def _simulator(self, variant: p.Variant) -> Simulator:
        if variant not in self._sims:
            # LMS value 0 points right (-90° in the robot frame), ascending counter-clockwise.
            lidar = LidarModel(n_beams=variant.n_values,
                               angle_min_rad=math.radians(variant.start_angle_deg - 90.0),
                               angle_increment_rad=math.radians(variant.resolution_deg))
            config = SimConfig(world_name=self._world_name, lidar=lidar,
                               rate_hz=1.0 / scan_period_s(variant), seed=self._seed)
            self._sims[variant] = Simulator(config)
        return self._sims[variant]
