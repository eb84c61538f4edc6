"""Thin pyserial driver for a SICK LMS200: find it, configure it, stream its scans.

All timing and I/O of the driver live here; the bytes come from
:mod:`.protocol`. The port is opened with ``serial.serial_for_url``, so a
pseudo-terminal path (the emulator) works like ``/dev/ttyUSB0``.

Init sequence (docs/lms200-protocol.md, 'Baud rates and switching'): probe the
current baud rate among 9600/19200/38400/500000 (the LMS powers on at 9600),
stop any stream left running, read the type string, switch to the requested rate, select the
variant, make sure the units are mm with measuring mode 00h (8 m, 13-bit
ranges), start continuous output. :meth:`Lms200.scans` runs it on connect,
again when the LMS reports a reset or goes quiet, and after reconnecting a
port that disappeared.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING

import serial

from lrfslam.drivers.lms200 import protocol as p
from lrfslam.errors import ConfigError, DeviceError, TelegramError

if TYPE_CHECKING:
    from typing import Self  # Python >= 3.11; annotations are not evaluated at run time

# Measuring mode 00h: 13-bit ranges (8.183 m in mm) with field A/B and dazzle flags.
MEASURING_MODE = 0x00
# Above 38400 Bd the LMS needs >= 55 us between host bytes (TL p.24); a burst at 500 kBd
# is ignored, so bytes go out one by one with this gap, as sicktoolbox and Player do.
_FAST_BYTE_GAP_S = 60e-6


@dataclass(frozen=True)
class Lms200Timeouts:
    """Timeouts and retry policy; all in seconds unless named otherwise.

    Defaults follow the LMS timing rules (TL p.24) with the margins other drivers use
    (docs/lms200-protocol.md, 'Timing').
    """

    reply_s: float = 0.5            # ACK <= 60 ms, reply <= 60 ms, plus 160 bytes at 9600 Bd
    mode_change_s: float = 3.0      # 20h replies may take up to 3 s
    config_write_s: float = 15.0    # 77h is an EEPROM write; sicktoolbox allows 15 s
    probe_s: float = 0.3            # per candidate baud rate and try
    probe_tries: int = 2
    retries: int = 3                # sends per command before the init fails
    nak_wait_s: float = 0.03        # the LMS wants >= 30 ms before a resend after NAK
    byte_gap_s: float = 0.035       # quiet line = stall: > the LMS's 14 ms inter-byte limit
    baud_settle_s: float = 0.05     # after switching our side of the line
    scan_s: float = 2.0             # no scan for this long while streaming: re-run the init
    reconnect_min_s: float = 0.1    # backoff after a failure, doubled per failure ...
    reconnect_max_s: float = 2.0    # ... up to this
    write_s: float = 1.0            # a write blocked this long means the port is gone


class Lms200:
    """One LMS200 on a serial port.

    Parameters
    ----------
    device : str
        Port path or pyserial URL (``/dev/ttyUSB0``, a pty path, ...).
    baud : int
        Rate to run at: 9600, 19200, 38400 or 500000 (RS-422 only on real hardware).
    timeouts : Lms200Timeouts
    variant : protocol.Variant
        Angular range and resolution; 180°/1° gives 181 values.

    Attributes
    ----------
    device_type : str
        Type string from the last init, e.g. ``LMS200;301063;V02.10``; "" before.
    last_stamp_ns : int
        ``time.time_ns()`` of the read that completed the newest yielded scan.
    """

    def __init__(self, device: str, baud: int = 38400, timeouts: Lms200Timeouts = Lms200Timeouts(),
                 variant: p.Variant = p.VARIANT_180_1) -> None:
        if baud not in p.BAUD_RATES:
            raise ConfigError(f"baud {baud} not one of {p.BAUD_RATES}")
        if variant not in p.VARIANTS:
            raise ConfigError(f"{variant} is not a standard LMS200 variant")
        self.device = device
        self.baud = baud
        self.timeouts = timeouts
        self.variant = variant
        self.device_type = ""
        self.last_stamp_ns = 0
        self._serial: serial.SerialBase | None = None
        self._streaming = False  # init done and the LMS streaming on the open port
        self._parser = p.TelegramParser()
        self._counts = dict.fromkeys((
            "scans", "bad_scans", "inits", "init_failures", "naks", "reply_timeouts",
            "refused", "scan_timeouts", "device_resets", "disconnects", "open_failures",
            "config_writes",
        ), 0)

    @property
    def counters(self) -> dict[str, int]:
        """Snapshot of every fault and event counter (driver and telegram parser)."""
        return {**self._parser.counters, **self._counts}

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Close the port; :meth:`scans` reopens it when iterated again."""
        if self._serial is not None:
            try:
                self._serial.close()
            except (serial.SerialException, OSError):
                pass  # the port is already gone; nothing left to release
            self._serial = None
        self._streaming = False

    def scans(self, stop: threading.Event) -> Iterator[p.ScanTelegram]:
        """Yield scans until ``stop`` is set, reconnecting and re-initialising as needed.

        Never raises for device trouble: a missing port, a silent or refusing
        LMS and a vanished port are counted and retried with exponential
        backoff. Returns within about ``timeouts.byte_gap_s`` of ``stop`` being
        set while streaming (longer during an init).
        """
        backoff = self.timeouts.reconnect_min_s
        while not stop.is_set():
            try:
                if self._serial is None:
                    self._open()
                if not self._streaming:
                    self._initialise(stop)
                    backoff = self.timeouts.reconnect_min_s
                yield from self._stream(stop)
            except (serial.SerialException, OSError):
                self._counts["disconnects" if self._serial is not None else "open_failures"] += 1
                self.close()
            except (DeviceError, TelegramError):  # silent, refusing or garbled init replies
                if not stop.is_set():
                    self._counts["init_failures"] += 1
                self.close()  # reopening also clears whatever state the port was in
            else:
                continue  # the stream ended on a reset or silence: re-initialise at once
            stop.wait(backoff)
            backoff = min(2 * backoff, self.timeouts.reconnect_max_s)

    # --- connection and init -------------------------------------------------------------
    def _open(self) -> None:
        self._serial = serial.serial_for_url(
            self.device, baudrate=9600, timeout=self.timeouts.byte_gap_s,
            write_timeout=self.timeouts.write_s)
        self._parser.reset()

    def _initialise(self, stop: threading.Event) -> None:
        """Run the init sequence; raises DeviceError if the LMS cannot be brought up."""
        self._streaming = False
        current = self._probe_baud(stop)
        self._expect_accepted(self._transact(p.STOP_CONTINUOUS, p.CMD_MODE, self.timeouts.mode_change_s))
        self.device_type = p.type_string(self._transact(p.REQUEST_TYPE, p.CMD_TYPE))
        if current != self.baud:
            # A late duplicate A0 would make us switch before the LMS does: start clean.
            self._drain()
            # The LMS answers at the old rate, then switches; we follow after its reply.
            self._expect_accepted(self._transact(p.baud_request(self.baud), p.CMD_MODE,
                                                 self.timeouts.mode_change_s))
            self._set_baud(self.baud)
            self._transact(p.REQUEST_TYPE, p.CMD_TYPE)  # proves the new rate works
        reply = self._transact(p.variant_request(self.variant), p.CMD_VARIANT)
        if not p.is_accepted(reply) or p.variant_of(reply) != self.variant:
            raise DeviceError(f"LMS refused variant {self.variant}")
        self._ensure_units()
        self._expect_accepted(self._transact(p.START_CONTINUOUS, p.CMD_MODE, self.timeouts.mode_change_s))
        self._counts["inits"] += 1
        self._streaming = True

    def _probe_baud(self, stop: threading.Event) -> int:
        """Find the rate the LMS talks at: one at which a CRC-valid telegram arrives.

        A bare ACK byte is not proof: at the wrong rate line noise can contain 06h.
        """
        # Power-on rate first, then ours (a restarted driver finds the LMS where it left it).
        candidates = list(dict.fromkeys((9600, self.baud, *p.BAUD_RATES)))
        for _ in range(self.timeouts.probe_tries):
            for baud in candidates:
                if stop.is_set():
                    raise DeviceError("stopped while probing")
                self._set_baud(baud)
                # 20 25 first: it stops a stream left running by an earlier client.
                self._write(p.STOP_CONTINUOUS)
                self._write(p.REQUEST_TYPE)
                if self._heard_type_reply():
                    return baud
        raise DeviceError(f"no LMS200 answer at any of {p.BAUD_RATES} Bd on {self.device}")

    def _heard_type_reply(self) -> bool:
        """Wait for the BAh reply closing a probe; any valid telegram proves the rate.

        Waiting for BAh (the last reply due) keeps the probe's replies from being
        taken for the answers to the init requests that follow.
        """
        heard = False
        deadline = time.monotonic() + self.timeouts.probe_s
        while time.monotonic() < deadline:
            for item in self._read_items():
                if isinstance(item, p.Telegram):
                    if item.command == p.reply_code(p.CMD_TYPE):
                        return True
                    heard = True
        return heard

    def _ensure_units(self) -> None:
        """Units mm and measuring mode 00h; writes the EEPROM only when they differ (TL p.25)."""
        config = p.config_of(self._transact(p.REQUEST_CONFIG, p.CMD_CONFIG_READ))
        wanted = p.config_with(config, units=p.Units.MM, measuring_mode=MEASURING_MODE)
        if wanted == config:
            return
        self._expect_accepted(self._transact(p.installation_request(), p.CMD_MODE,
                                             self.timeouts.mode_change_s))
        self._expect_accepted(self._transact(p.config_write_request(wanted), p.CMD_CONFIG_WRITE,
                                             self.timeouts.config_write_s))
        self._counts["config_writes"] += 1
        # Back to monitoring; START_CONTINUOUS follows in the init sequence.
        self._expect_accepted(self._transact(p.STOP_CONTINUOUS, p.CMD_MODE, self.timeouts.mode_change_s))

    def _expect_accepted(self, reply: p.Telegram) -> None:
        if not p.is_accepted(reply):
            raise DeviceError(f"LMS refused the request ({reply.raw.hex(' ')})")

    def _transact(self, request: bytes, command: int, timeout_s: float | None = None) -> p.Telegram:
        """Send ``request`` and return the reply to ``command``; resend on NAK or silence.

        Other telegrams arriving meanwhile (B0 from a running stream, late
        duplicates) are skipped. Raises DeviceError on 92h or when retries run out.
        """
        expected = p.reply_code(command)
        timeout_s = self.timeouts.reply_s if timeout_s is None else timeout_s
        for _ in range(self.timeouts.retries):
            self._write(request)
            deadline = time.monotonic() + timeout_s
            nak = False
            while not nak and time.monotonic() < deadline:
                for item in self._read_items():
                    if item is p.Handshake.NAK:
                        nak = True
                    elif isinstance(item, p.Telegram) and item.command == expected:
                        return item
                    elif isinstance(item, p.Telegram) and item.command == p.REPLY_REFUSED:
                        self._counts["refused"] += 1
                        raise DeviceError(f"LMS refused {request.hex(' ')} (92h)")
            if nak:
                self._counts["naks"] += 1
                time.sleep(self.timeouts.nak_wait_s)
            else:
                self._counts["reply_timeouts"] += 1
        raise DeviceError(f"no {expected:#04x} reply to {request.hex(' ')}")

    def _drain(self) -> None:
        """Discard input until the line is quiet for one stall period (at most one reply time)."""
        deadline = time.monotonic() + self.timeouts.reply_s
        while time.monotonic() < deadline and self._require_port().read(1):
            self._require_port().reset_input_buffer()
        self._parser.reset()

    # --- streaming -----------------------------------------------------------------------
    def _stream(self, stop: threading.Event) -> Iterator[p.ScanTelegram]:
        """Yield streamed scans; return when the LMS reset or went quiet (re-init needed).

        A consumer that stops iterating leaves the LMS streaming; the next
        :meth:`scans` call picks the stream up without a new init.
        """
        last_scan = time.monotonic()
        while not stop.is_set():
            for item in self._read_items():
                if not isinstance(item, p.Telegram):
                    continue  # ACK/NAK bytes mean nothing while streaming
                if item.command == p.REPLY_POWER_ON:
                    # The LMS restarted: it is back at its power-on rate and not streaming.
                    self._counts["device_resets"] += 1
                    self._streaming = False
                    return
                if item.command != p.REPLY_SCAN:
                    continue
                try:
                    scan = p.parse_scan(item, MEASURING_MODE)
                except TelegramError:
                    self._counts["bad_scans"] += 1
                    continue
                self._counts["scans"] += 1
                last_scan = time.monotonic()
                yield scan
            if time.monotonic() - last_scan > self.timeouts.scan_s:
                self._counts["scan_timeouts"] += 1
                self._streaming = False
                return

    # --- line I/O ------------------------------------------------------------------------
    def _read_items(self) -> list[p.Telegram | p.Handshake]:
        """Read what has arrived (waiting at most one stall period) and parse it."""
        port = self._require_port()
        chunk = port.read(max(1, port.in_waiting))
        if not chunk:
            return self._parser.on_stall()
        self.last_stamp_ns = time.time_ns()
        return self._parser.feed(chunk)

    def _write(self, telegram: bytes) -> None:
        port = self._require_port()
        if port.baudrate <= 38400:
            port.write(telegram)
            return
        for byte in telegram:
            port.write(bytes((byte,)))
            port.flush()
            _busy_wait(_FAST_BYTE_GAP_S)  # sleep() is too coarse for 60 us; spin instead

    def _set_baud(self, baud: int) -> None:
        port = self._require_port()
        if port.baudrate != baud:
            port.baudrate = baud
            time.sleep(self.timeouts.baud_settle_s)
        port.reset_input_buffer()
        self._parser.reset()

    def _require_port(self) -> serial.SerialBase:
        if self._serial is None:
            raise DeviceError("port is not open")
        return self._serial


def _busy_wait(seconds: float) -> None:
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        pass
