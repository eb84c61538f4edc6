"""LMS200 serial protocol: the commands the driver sends, the replies it reads, B0 scans.

PURE: bytes/numpy in, bytes/numpy out; stdlib + numpy only. No serial port,
no clock, no environment, no logging. Framing, CRC and the stream parser live
in :mod:`.framing` and are re-exported here. The protocol is described in
``docs/lms200-protocol.md``; TL = SICK Telegram Listing LMS2xx 8007954/Q501.

All multi-byte fields are little-endian WORDs (TL p.22).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np

# Framing is re-exported so callers need one module for the whole protocol.
from lrfslam.drivers.lms200.framing import (  # noqa: F401
    ACK,
    NAK,
    REPLY_ADDRESS_BIT,
    STX,
    Handshake,
    Telegram,
    TelegramParser,
    build_reply,
    build_request,
    crc16,
    frame,
)
from lrfslam.errors import TelegramError

# Command codes (host->LMS); the reply code is command | 80h
# (docs/lms200-protocol.md, 'Commands and replies').
CMD_MODE = 0x20
CMD_SCAN = 0x30
CMD_TYPE = 0x3A
CMD_VARIANT = 0x3B
CMD_CONFIG_READ = 0x74
CMD_CONFIG_WRITE = 0x77
REPLY_POWER_ON = 0x90  # sent after power-on or reset, at the power-on baud rate
REPLY_REFUSED = 0x92  # correct frame, logically invalid command
REPLY_SCAN = 0xB0


def reply_code(command: int) -> int:
    """Response code the LMS uses to answer ``command`` (command + 80h)."""
    return command | 0x80


# 20h sub-commands (docs/lms200-protocol.md, 'Operating modes (20h)').
MODE_INSTALLATION = 0x00
MODE_CONTINUOUS = 0x24  # stream every scan as B0
MODE_ON_REQUEST = 0x25  # factory default; the only way to stop a stream
BAUD_CODES = {9600: 0x42, 19200: 0x41, 38400: 0x40, 500_000: 0x48}
BAUD_RATES = tuple(sorted(BAUD_CODES))
DEFAULT_PASSWORD = b"SICK_LMS"


class Units(IntEnum):
    """Measurement units: config byte 6 and B0 count-word bits 14-15 use the same codes."""

    CM = 0
    MM = 1

    @property
    def metres(self) -> float:
        """Size of one raw range count in metres."""
        return 0.01 if self is Units.CM else 0.001


@dataclass(frozen=True)
class Variant:
    """Angular range and resolution, as set with command 3Bh.

    See docs/lms200-protocol.md, 'Variant (3Bh)'.

    ``fov_deg`` is 100 or 180; ``resolution_cdeg`` is in 1/100 degree
    (100 = 1°, 50 = 0.5°, 25 = 0.25°).
    """

    fov_deg: int
    resolution_cdeg: int

    @property
    def n_values(self) -> int:
        """Number of range values per complete scan (181, 361, 101, 201 or 401)."""
        return self.fov_deg * 100 // self.resolution_cdeg + 1

    @property
    def resolution_deg(self) -> float:
        """Angle between consecutive values, degrees."""
        return self.resolution_cdeg / 100.0

    @property
    def start_angle_deg(self) -> float:
        """Direction of value 0 in the 180° frame: the 100° variant starts at 40° (TL p.48)."""
        return (180 - self.fov_deg) / 2.0


VARIANT_180_1 = Variant(180, 100)
VARIANT_180_05 = Variant(180, 50)
VARIANT_100_1 = Variant(100, 100)
VARIANT_100_05 = Variant(100, 50)
VARIANT_100_025 = Variant(100, 25)
VARIANTS = (VARIANT_180_1, VARIANT_180_05, VARIANT_100_1, VARIANT_100_05, VARIANT_100_025)
_VARIANT_BY_COUNT = {v.n_values: v for v in VARIANTS}

# --- fixed host requests (address 0, what every surveyed driver uses) -------------------
REQUEST_TYPE = build_request(bytes((CMD_TYPE,)))
REQUEST_CONFIG = build_request(bytes((CMD_CONFIG_READ,)))
REQUEST_SCAN = build_request(bytes((CMD_SCAN, 0x01)))  # one complete scan, as B0
START_CONTINUOUS = build_request(bytes((CMD_MODE, MODE_CONTINUOUS)))
STOP_CONTINUOUS = build_request(bytes((CMD_MODE, MODE_ON_REQUEST)))


def baud_request(baud: int) -> bytes:
    """Telegram switching the LMS to ``baud`` (9600, 19200, 38400 or 500000 Bd).

    The LMS acknowledges at the old rate, then switches
    (docs/lms200-protocol.md, 'Baud rates and switching').
    """
    if baud not in BAUD_CODES:
        raise ValueError(f"baud {baud} not one of {BAUD_RATES}")
    return build_request(bytes((CMD_MODE, BAUD_CODES[baud])))


def installation_request(password: bytes = DEFAULT_PASSWORD) -> bytes:
    """Telegram entering installation mode, which 77h configuration writes need."""
    if len(password) != 8:
        raise ValueError("the LMS password is exactly 8 bytes")
    return build_request(bytes((CMD_MODE, MODE_INSTALLATION)) + password)


def variant_request(variant: Variant) -> bytes:
    """Telegram 3Bh selecting ``variant`` (one of :data:`VARIANTS`)."""
    if variant not in VARIANTS:
        raise ValueError(f"{variant} is not a standard LMS200 variant")
    data = variant.fov_deg.to_bytes(2, "little") + variant.resolution_cdeg.to_bytes(2, "little")
    return build_request(bytes((CMD_VARIANT,)) + data)


# --- configuration block (docs/lms200-protocol.md, 'Configuration block (74h/77h)') ---
CONFIG_AVAILABILITY = 4
CONFIG_MEASURING_MODE = 5
CONFIG_UNITS = 6
AVAILABILITY_INDICES = 0x02  # bit 1: real-time scan/telegram indices in every B0
CONFIG_LENGTHS = (32, 34)  # old LMS200 firmware / current firmware
# TL p.102 default block (34 bytes): measuring mode 00h (8 m, 13 bits), units mm.
DEFAULT_CONFIG = bytes.fromhex(
    "0000 46 00 00 00 01 00 00 02 02 02 00"  # bytes 0-12: blanking .. multiple evaluation
    " 000a0a5064 000a0a5080 000a0a5064"      # contours A, B, C
    " 00 00 0000 0200"                        # pixel/single-value evaluation, restart times, dazzle
)


def config_write_request(config: bytes) -> bytes:
    """Telegram 77h writing a whole configuration block (installation mode only)."""
    if len(config) not in CONFIG_LENGTHS:
        raise ValueError(f"configuration block of {len(config)} bytes; expected 32 or 34")
    return build_request(bytes((CMD_CONFIG_WRITE,)) + bytes(config))


def config_with(config: bytes, *, units: Units, measuring_mode: int) -> bytes:
    """Copy of ``config`` with the units and measuring-mode bytes replaced.

    Read-modify-write keeps the thresholds a canned block would overwrite.
    """
    if measuring_mode not in _RANGE_BITS:
        raise ValueError(f"measuring mode {measuring_mode:#x} not supported")
    patched = bytearray(config)
    patched[CONFIG_MEASURING_MODE] = measuring_mode
    patched[CONFIG_UNITS] = int(units)
    return bytes(patched)


# --- reply decoding ----------------------------------------------------------------------
# A0h answers 00 for success; BBh, F7h and E6h answer 01: opposite polarities.
_SUCCESS_BYTE = {reply_code(CMD_MODE): 0x00, reply_code(CMD_VARIANT): 0x01,
                 reply_code(CMD_CONFIG_WRITE): 0x01}


def is_accepted(reply: Telegram) -> bool:
    """Whether an A0h / BBh / F7h reply reports success.

    Raises
    ------
    TelegramError
        If ``reply`` is not one of those replies or carries no result byte.
    """
    if reply.command not in _SUCCESS_BYTE or not reply.data:
        raise TelegramError(f"{reply.command:#04x} reply carries no result byte")
    return reply.data[0] == _SUCCESS_BYTE[reply.command]


def type_string(reply: Telegram) -> str:
    """ASCII type/version string of a 90h (power-on) or BAh (type) reply, e.g. ``LMS200;301063;V02.10``."""
    if reply.command not in (REPLY_POWER_ON, reply_code(CMD_TYPE)):
        raise TelegramError(f"{reply.command:#04x} reply carries no type string")
    return reply.data.decode("ascii", errors="replace").strip()


def variant_of(reply: Telegram) -> Variant:
    """Variant echoed by a BBh reply (the active one, whether or not the change was accepted)."""
    if reply.command != reply_code(CMD_VARIANT) or len(reply.data) != 5:
        raise TelegramError("not a 5-byte BBh variant reply")
    d = reply.data
    return Variant(d[1] | (d[2] << 8), d[3] | (d[4] << 8))


def config_of(reply: Telegram) -> bytes:
    """Configuration block carried by an F4h reply (32 or 34 bytes)."""
    if reply.command != reply_code(CMD_CONFIG_READ) or len(reply.data) not in CONFIG_LENGTHS:
        raise TelegramError("not an F4h configuration reply of 32 or 34 bytes")
    return reply.data


# --- B0 measured values (docs/lms200-protocol.md, 'Measured values (B0)') ---
class RangeStatus(IntEnum):
    """Per-value status codes of a scan: the special range codes made explicit.

    See docs/lms200-protocol.md, 'Special codes'.
    """

    OK = 0
    NO_ECHO = 1        # top code: no stop signal; range +inf
    BEYOND_MAX = 2     # top - 8: beyond the largest representable range; range +inf
    DAZZLE = 3         # top - 1, or the bit-15 dazzle flag of measuring mode 00h; NaN
    OVERFLOW = 4       # top - 2: operation overflow; NaN
    LOW_SNR = 5        # top - 4: signal-to-noise too small; NaN
    CHANNEL_ERROR = 6  # top - 5: error reading channel 1; NaN
    RESERVED = 7       # top - 3, top - 6, top - 7: undocumented codes; NaN


# Status by (top - raw) for raw >= top - 8: index 0 = top code (0x1FFF in 13-bit modes).
_SPECIAL = np.array([RangeStatus.NO_ECHO, RangeStatus.DAZZLE, RangeStatus.OVERFLOW,
                     RangeStatus.RESERVED, RangeStatus.LOW_SNR, RangeStatus.CHANNEL_ERROR,
                     RangeStatus.RESERVED, RangeStatus.RESERVED, RangeStatus.BEYOND_MAX],
                    dtype=np.uint8)
_BEYOND_OFFSET = 8
# Range bits per measuring mode (config byte 5, TL Table 7-122 block D); the rest are flags.
_RANGE_BITS = {0x00: 13, 0x01: 13, 0x02: 13, 0x03: 14, 0x04: 14, 0x05: 15, 0x06: 15}
MEASURING_MODES = tuple(_RANGE_BITS)  # 0Fh (16 bits) and 3Fh (reflectivity) are not decoded
_DAZZLE_FLAG_MODE = 0x00  # only mode 00h uses bit 15 for dazzle
_DAZZLE_FLAG = 0b100  # bit 15, seen as bit 2 of the flags

# Bits 0-9; bits 11 and 13 must not leak into N (docs/lms200-protocol.md, 'Count word').
_COUNT_MASK = 0x03FF
_RASTER_SHIFT = 11
_PARTIAL_BIT = 1 << 13
_UNITS_SHIFT = 14
_FIXED_BYTES = 4  # LEN of a B0 without values: response code, count word, status


@dataclass(frozen=True, eq=False)
class ScanTelegram:
    """One decoded B0 measured-value telegram.

    Attributes
    ----------
    ranges_m : ndarray, shape (N,), float64
        Range per value in metres, ascending angle; +inf = no return
        (no echo or beyond range), NaN = invalid (dazzle, overflow, ...).
    status : ndarray, shape (N,), uint8
        :class:`RangeStatus` code per value.
    flags : ndarray, shape (N,), uint8
        The bits above the range bits: field A/B/C or reflector level,
        depending on the measuring mode.
    units : Units
        Units the LMS reported in the count word.
    resolution_deg, fov_deg, start_angle_deg : float or None
        Angle step, covered angle and direction of value 0 in the LMS's 180°
        frame, degrees; None when N is not a standard variant's count.
    partial : bool
        True for a partial (interlaced) scan; ``start_angle_deg`` then holds its raster offset.
    scan_index, telegram_index : int or None
        Real-time indices modulo 256, when the LMS is configured to send them.
    status_byte : int
        The telegram's trailing status byte, 0x10 when healthy
        (docs/lms200-protocol.md, 'Status byte').
    """

    ranges_m: np.ndarray
    status: np.ndarray
    flags: np.ndarray
    units: Units
    resolution_deg: float | None
    fov_deg: float | None
    start_angle_deg: float | None
    partial: bool
    scan_index: int | None
    telegram_index: int | None
    status_byte: int


def range_bits(measuring_mode: int) -> int:
    """Number of range bits in a value WORD for ``measuring_mode`` 00h..06h."""
    if measuring_mode not in _RANGE_BITS:
        raise ValueError(f"measuring mode {measuring_mode:#x} not supported")
    return _RANGE_BITS[measuring_mode]


def decode_values(raw: np.ndarray, units: Units, measuring_mode: int = 0x00):
    """Split raw value WORDs into ranges, status codes and flag bits.

    Parameters
    ----------
    raw : ndarray, shape (N,), uint16
        Measured-value WORDs as sent.
    units : Units
        Units of the range bits.
    measuring_mode : int
        Config byte 5 (00h..06h); sets the range-bit width and flag meaning.

    Returns
    -------
    ranges_m : ndarray, shape (N,), float64
        Metres; +inf for NO_ECHO / BEYOND_MAX, NaN for every other special status.
    status : ndarray, shape (N,), uint8
        :class:`RangeStatus` codes.
    flags : ndarray, shape (N,), uint8
        Bits above the range bits.
    """
    bits = range_bits(measuring_mode)
    raw = np.asarray(raw, dtype=np.uint16)
    top = (1 << bits) - 1
    value = (raw & top).astype(np.int64)
    flags = (raw >> bits).astype(np.uint8)
    special = value >= top - _BEYOND_OFFSET
    status = np.zeros(raw.shape, dtype=np.uint8)
    status[special] = _SPECIAL[top - value[special]]
    if measuring_mode == _DAZZLE_FLAG_MODE:
        status[~special & ((flags & _DAZZLE_FLAG) != 0)] = RangeStatus.DAZZLE
    ranges = value * Units(units).metres
    no_return = (status == RangeStatus.NO_ECHO) | (status == RangeStatus.BEYOND_MAX)
    ranges[no_return] = np.inf
    ranges[(status != RangeStatus.OK) & ~no_return] = np.nan
    return ranges, status, flags


def encode_ranges(ranges_m: np.ndarray, units: Units, measuring_mode: int = 0x00) -> np.ndarray:
    """Quantise ranges to raw value WORDs, as the LMS would send them (no flag bits).

    Parameters
    ----------
    ranges_m : ndarray, shape (N,)
        Metres, >= 0; +inf = no echo. Ranges at or past the largest
        representable value become the "beyond maximum" code.
    units : Units
    measuring_mode : int

    Returns
    -------
    ndarray, shape (N,), uint16

    Raises
    ------
    ValueError
        On NaN or negative ranges: they have no single LMS code.
    """
    r = np.asarray(ranges_m, dtype=np.float64)
    if np.isnan(r).any() or (r < 0).any():
        raise ValueError("ranges must be >= 0 or +inf; NaN has no single LMS code")
    top = (1 << range_bits(measuring_mode)) - 1
    beyond = top - _BEYOND_OFFSET
    counts = np.full(r.shape, top, dtype=np.int64)
    finite = np.isfinite(r)
    counts[finite] = np.minimum(np.rint(r[finite] / Units(units).metres), beyond)
    return counts.astype(np.uint16)


def build_scan_reply(raw: np.ndarray, *, units: Units, raster_qdeg: int | None = None,
                     indices: tuple[int, int] | None = None, status: int = 0x10,
                     address: int = 0) -> bytes:
    """B0 telegram carrying the value WORDs ``raw``, as the emulator sends it.

    Parameters
    ----------
    raw : ndarray, shape (N,), uint16
        Value WORDs, 1 <= N <= 401.
    units : Units
    raster_qdeg : int or None
        None for a complete scan; 0..3 (x.00°, x.25°, x.50°, x.75°) for a partial one.
    indices : (int, int) or None
        (scan index, telegram index), each 0..255, when real-time indices are on.
    status, address : int
        Trailing status byte and LMS address.
    """
    raw = np.asarray(raw, dtype=np.uint16)
    if not 1 <= raw.size <= max(_VARIANT_BY_COUNT):
        raise ValueError(f"{raw.size} values; the LMS sends 1..401")
    count = raw.size | (int(units) << _UNITS_SHIFT)
    if raster_qdeg is not None:
        if not 0 <= raster_qdeg <= 3:
            raise ValueError("raster_qdeg is 0..3")
        count |= _PARTIAL_BIT | (raster_qdeg << _RASTER_SHIFT)
    payload = bytes((REPLY_SCAN,)) + count.to_bytes(2, "little") + raw.astype("<u2").tobytes()
    if indices is not None:
        payload += bytes(indices)
    return build_reply(payload, status=status, address=address)


def parse_scan(reply: Telegram, measuring_mode: int = 0x00) -> ScanTelegram:
    """Decode a B0 telegram into a :class:`ScanTelegram`.

    Parameters
    ----------
    reply : Telegram
        A CRC-valid LMS->host telegram with command B0h.
    measuring_mode : int
        Config byte 5 (00h..06h), which the telegram itself does not carry.

    Raises
    ------
    TelegramError
        If the telegram is not a B0, its length disagrees with its value count
        (with or without the two index bytes), or it reports reserved units or
        a raster on a complete scan.
    """
    if reply.command != REPLY_SCAN or reply.status is None or len(reply.data) < 2:
        raise TelegramError(f"{reply.command:#04x} telegram is not a B0 scan")
    count = reply.data[0] | (reply.data[1] << 8)
    n = count & _COUNT_MASK
    units_code = count >> _UNITS_SHIFT
    partial = bool(count & _PARTIAL_BIT)
    raster_qdeg = (count >> _RASTER_SHIFT) & 0b11
    if units_code not in (Units.CM, Units.MM):
        raise TelegramError(f"B0 reports reserved units code {units_code}")
    if raster_qdeg and not partial:
        raise TelegramError("B0 carries a raster on a complete scan")
    extra = len(reply.data) - 2 - 2 * n
    if n == 0 or extra not in (0, 2):
        raise TelegramError(f"B0 with {n} values has {len(reply.data)} data bytes")
    raw = np.frombuffer(reply.data, dtype="<u2", count=n, offset=2)
    ranges, status, flags = decode_values(raw, Units(units_code), measuring_mode)
    if partial:
        resolution, start = 1.0, raster_qdeg * 0.25
        fov: float | None = float(n - 1)
    elif n in _VARIANT_BY_COUNT:
        variant = _VARIANT_BY_COUNT[n]
        resolution, start, fov = variant.resolution_deg, variant.start_angle_deg, float(variant.fov_deg)
    else:
        resolution = start = fov = None
    scan_index, telegram_index = (reply.data[-2], reply.data[-1]) if extra else (None, None)
    return ScanTelegram(ranges, status, flags, Units(units_code), resolution, fov, start, partial,
                        scan_index, telegram_index, reply.status)
