"""LMS200 emulator on a pseudo-terminal, for tests and for running the pipeline without hardware.

    python -m lrfslam.drivers.lms200.emulator [--link PATH] [--dump-ranges FILE] ...

Prints the pty slave path on stdout (again after every replug), then behaves
like an LMS200 on the other end of that port (docs/lms200-protocol.md, 'Emulator'):

* powers on at ``--baud-initial`` and sends the 90h power-on telegram;
* ACKs (06h) each valid request and answers it after ``--reply-delay-ms``;
  NAKs (15h) a frame with our address and a bad CRC; drops a request whose
  bytes are more than 6 ms apart; a new request cuts off a B0 being sent;
* a pty has no physical baud rate, so output is paced at ``baud / 10`` bytes
  per second, and while the rate the driver set on the slave (read through
  the master) differs from the LMS's own, input is ignored and output
  garbled, as on a real line at the wrong rate;
* in continuous mode a scan completes every mirror cycle (13.32 ms per turn,
  2 turns at 0.5°, 4 at 0.25°) and the first cycle to end while the line is
  idle is sent: 181 values stream at ≈9.4 Hz at 38400 Bd and 75 Hz at 500 kBd
  (docs/lms200-protocol.md, 'Scan rate per baud rate');
* scans come from :mod:`lrfslam.sim`; scan ``k`` depends only on
  ``(--world, --seed, variant, k)``, see
  :class:`~lrfslam.drivers.lms200.device_model.SimScanSource`;
* optional faults on streamed scans: garbage before a telegram, one flipped
  bit, a truncated telegram (each a percentage of telegrams).

Signals: SIGUSR1 unplugs the cable (the pty goes away, ``--link`` is removed,
and after ``--replug-delay-s`` a new pty appears with the link pointing at it,
the LMS still running as before); SIGUSR2 power-cycles the LMS; SIGTERM and
SIGINT stop the emulator.

``--dump-ranges FILE`` appends one line per scan sent (streamed or polled):
``<scan number> <faults or none> <range_0 m> ... <range_N-1 m>``, ranges as
the driver will decode them (``inf`` = no return).
"""

from __future__ import annotations

import argparse
import math
import os
import select
import signal
import sys
import termios
import time
import tty
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import numpy as np

from lrfslam.drivers.lms200 import protocol as p
from lrfslam.drivers.lms200.device_model import (
    EmulatedLms200,
    ScanSource,
    SimScanSource,
    scan_period_s,
)
from lrfslam.errors import ConfigError

HOST_GAP_S = 0.006  # the LMS drops a request whose bytes are further apart (TL p.24)
BITS_PER_BYTE = 10  # 8N1
CHUNK_S = 0.004  # paced output goes out in slices this long: well under the 14 ms gap limit
MAX_GARBAGE_BYTES = 32
_SPEEDS = {termios.B9600: 9600, termios.B19200: 19200, termios.B38400: 38400, termios.B500000: 500_000}


@dataclass(frozen=True)
class EmulatorOptions:
    """Emulator settings; see ``--help`` for each."""

    baud_initial: int = 9600
    units_initial: p.Units = p.Units.MM
    seed: int = 0
    rate_limit: bool = True
    reply_delay_s: float = 0.005
    power_on_delay_s: float = 0.0
    fault_garbage_pct: float = 0.0
    fault_bitflip_pct: float = 0.0
    fault_truncate_pct: float = 0.0
    link: Path | None = None
    replug_delay_s: float = 0.5


class PtyLine:
    """Master side of a fresh pseudo-terminal standing in for the serial cable.

    The emulator keeps the slave open too, so a driver closing and reopening
    the port does not hang up the line.
    """

    def __init__(self, link: Path | None) -> None:
        self.master, self._slave = os.openpty()
        # Raw at once: echo would loop the driver's bytes back, ICRNL would turn 0Dh into
        # 0Ah, IXON would eat 11h/13h and ISIG would turn 03h into SIGINT.
        tty.setraw(self._slave)
        attrs = termios.tcgetattr(self._slave)
        attrs[4] = attrs[5] = termios.B9600  # a fresh serial port's default speed
        termios.tcsetattr(self._slave, termios.TCSANOW, attrs)
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self._slave)
        self._link = link
        if link is not None:
            tmp = link.with_name(link.name + ".new")
            tmp.unlink(missing_ok=True)
            tmp.symlink_to(self.path)
            tmp.replace(link)  # atomic, like udev updating /dev/serial/by-id

    def baud(self) -> int | None:
        """Rate the driver set on the slave (None for a rate the LMS does not have)."""
        return _SPEEDS.get(termios.tcgetattr(self.master)[5])

    def read(self) -> bytes:
        try:
            return os.read(self.master, 4096)
        except (BlockingIOError, OSError):
            return b""  # nothing there, or nobody has the slave open

    def write(self, data: bytes) -> int:
        """Write what the pty takes now; returns the byte count (0 while its buffer is full)."""
        try:
            return os.write(self.master, data)
        except BlockingIOError:
            return 0

    def close(self) -> None:
        if self._link is not None and self._link.is_symlink() and os.readlink(self._link) == self.path:
            self._link.unlink()
        os.close(self.master)
        os.close(self._slave)


@dataclass
class _Segment:
    data: bytes
    not_before: float
    is_scan: bool = False
    new_baud: int | None = None


class Emulator:
    """The emulator's event loop: one pty, one emulated LMS, paced output.

    Parameters
    ----------
    options : EmulatorOptions
    source : ScanSource
        Ranges for each streamed scan.
    announce : callable
        Called with the slave path whenever a pty appears.
    dump : text file or None
        Receives one line per scan sent (see the module docstring).
    """

    def __init__(self, options: EmulatorOptions, source: ScanSource, announce: Callable[[str], None],
                 dump: TextIO | None = None) -> None:
        self._opt = options
        self._source = source
        self._announce = announce
        self._dump = dump
        self._rng = np.random.default_rng(options.seed)
        self._device = EmulatedLms200(options.baud_initial, options.units_initial)
        self._line: PtyLine | None = None
        self._queue: deque[_Segment] = deque()
        self._offset = 0  # bytes of queue[0] already sent
        self._line_free_at = 0.0
        self._rx = p.TelegramParser(replies=False)
        self._last_rx: float | None = None  # time of the last host byte of an unfinished request
        self._origin = time.monotonic()  # mirror phase
        self._next_scan: tuple[float, int] | None = None  # (time, scan number)
        self._replug_at: float | None = None
        self._signals: list[int] = []
        self._stopped = False

    def run(self) -> None:
        """Serve until SIGTERM or SIGINT."""
        wake_r, wake_w = os.pipe()
        os.set_blocking(wake_r, False)
        os.set_blocking(wake_w, False)
        signal.set_wakeup_fd(wake_w)  # a signal wakes select() at once
        for sig in (signal.SIGUSR1, signal.SIGUSR2, signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda signum, _frame: self._signals.append(signum))
        now = time.monotonic()
        self._plug()
        self._queue.append(_Segment(self._device.power_on_telegram(), now + self._opt.power_on_delay_s))
        try:
            while not self._stopped:
                now = time.monotonic()
                self._handle_signals(now)
                self._tick(now)
                fds = [wake_r] + ([self._line.master] if self._line else [])
                ready, _, _ = select.select(fds, [], [], self._sleep_s(time.monotonic()))
                if wake_r in ready:
                    os.read(wake_r, 512)
                if self._line is not None and self._line.master in ready:
                    self._receive(self._line.read(), time.monotonic())
        finally:
            if self._line is not None:
                self._line.close()
            signal.set_wakeup_fd(-1)
            os.close(wake_r)
            os.close(wake_w)

    # --- events --------------------------------------------------------------------------
    def _handle_signals(self, now: float) -> None:
        while self._signals:
            signum = self._signals.pop(0)
            if signum in (signal.SIGTERM, signal.SIGINT):
                self._stopped = True
            elif signum == signal.SIGUSR1 and self._line is not None:
                self._line.close()
                self._line = None
                self._drop_output()
                self._replug_at = now + self._opt.replug_delay_s
            elif signum == signal.SIGUSR2:
                self._device.power_cycle()
                self._drop_output()
                self._queue.append(_Segment(self._device.power_on_telegram(), now + self._opt.power_on_delay_s))

    def _plug(self) -> None:
        self._line = PtyLine(self._opt.link)
        self._replug_at = None
        self._announce(self._line.path)

    def _drop_output(self) -> None:
        self._queue.clear()
        self._offset = 0
        self._next_scan = None
        self._rx.reset()
        self._last_rx = None

    def _tick(self, now: float) -> None:
        if self._replug_at is not None and now >= self._replug_at:
            self._plug()
        if self._last_rx is not None and now - self._last_rx > HOST_GAP_S:
            self._end_of_request_bytes()
        self._schedule_scan(now)
        self._pump(now)
        self._schedule_scan(now)  # the line may just have gone idle: know when to wake

    def _sleep_s(self, now: float) -> float:
        wake = [now + 0.1]
        if self._replug_at is not None:
            wake.append(self._replug_at)
        if self._last_rx is not None:
            wake.append(self._last_rx + HOST_GAP_S)
        if self._next_scan is not None:
            wake.append(self._next_scan[0])
        if self._queue:
            wake.append(self._segment_start(self._queue[0]))
        return max(0.0, min(wake) - now)

    # --- host -> LMS ---------------------------------------------------------------------
    def _receive(self, data: bytes, now: float) -> None:
        if not data:
            return
        if self._line is None or self._line.baud() != self._device.baud:
            self._rx.reset()  # at the wrong rate the LMS sees only framing errors
            return
        if self._last_rx is not None and now - self._last_rx > HOST_GAP_S:
            self._end_of_request_bytes()
        rejected = self._rx.counters["crc_errors"]
        items = self._rx.feed(data)
        self._last_rx = now
        for request in items:
            self._on_request(request, now)
        self._nak_if(self._rx.counters["crc_errors"] > rejected, now)

    def _end_of_request_bytes(self) -> None:
        """The host went quiet: drop an unfinished request, NAK a complete one with a bad CRC."""
        rejected = self._rx.counters["crc_errors"]
        now = time.monotonic()
        for request in self._rx.on_stall(discard=True):
            self._on_request(request, now)
        self._nak_if(self._rx.counters["crc_errors"] > rejected, now)
        self._last_rx = None

    def _nak_if(self, rejected: bool, now: float) -> None:
        if rejected:
            self._queue.append(_Segment(bytes((p.NAK,)), now))

    def _on_request(self, request: p.Telegram, now: float) -> None:
        # A host request interrupts any B0 in transmission (TL p.24).
        if self._queue and self._queue[0].is_scan:
            self._queue.popleft()
            self._offset = 0
        self._queue = deque(s for s in self._queue if not s.is_scan)
        self._next_scan = None
        reaction = self._device.handle(request)
        self._queue.append(_Segment(bytes((p.ACK,)), now))
        ready = now + self._opt.reply_delay_s
        segments = [_Segment(reply, ready) for reply in reaction.replies]
        if reaction.send_scan:
            k = math.floor((now - self._origin) / scan_period_s(self._device.variant))
            segments.append(_Segment(self._scan_telegram(k, faults=False), ready, is_scan=True))
        segments[-1].new_baud = reaction.new_baud
        self._queue.extend(segments)

    # --- LMS -> host ---------------------------------------------------------------------
    def _schedule_scan(self, now: float) -> None:
        """Continuous mode: send the first scan that completes while the line is idle."""
        if not self._device.streaming:
            self._next_scan = None
            return
        if self._queue:
            return
        if self._next_scan is None:
            period = scan_period_s(self._device.variant)
            idle_at = max(now, self._line_free_at) if self._opt.rate_limit else now
            k = math.ceil((idle_at - self._origin) / period)
            self._next_scan = (self._origin + k * period, k)
        at, k = self._next_scan
        if now >= at:
            self._next_scan = None
            self._queue.append(_Segment(self._scan_telegram(k, faults=True), at, is_scan=True))

    def _scan_telegram(self, k: int, *, faults: bool) -> bytes:
        device = self._device
        ranges = self._source(device.variant, k)
        telegram = bytearray(device.scan_telegram(ranges, k))
        labels = []
        if faults and self._chance(self._opt.fault_bitflip_pct):
            telegram[self._rng.integers(len(telegram))] ^= 1 << int(self._rng.integers(8))
            labels.append("bitflip")
        if faults and self._chance(self._opt.fault_truncate_pct):
            telegram = telegram[:self._rng.integers(1, len(telegram))]
            labels.append("truncate")
        if faults and self._chance(self._opt.fault_garbage_pct):
            telegram[:0] = self._rng.bytes(int(self._rng.integers(1, MAX_GARBAGE_BYTES + 1)))
            labels.append("garbage")
        if self._dump is not None:
            raw = p.encode_ranges(ranges, device.units, device.measuring_mode)
            sent = p.decode_values(raw, device.units, device.measuring_mode)[0]
            self._dump.write(f"{k} {'+'.join(labels) or 'none'} {' '.join(map(repr, sent.tolist()))}\n")
            self._dump.flush()
        return bytes(telegram)

    def _chance(self, pct: float) -> bool:
        return pct > 0 and self._rng.random() * 100.0 < pct

    def _segment_start(self, segment: _Segment) -> float:
        # Unpaced, _line_free_at only moves when the pty buffer was full.
        return max(segment.not_before, self._line_free_at)

    def _pump(self, now: float) -> None:
        """Write what the line can carry by ``now``, in slices of CHUNK_S when paced."""
        while self._queue:
            segment = self._queue[0]
            start = self._segment_start(segment)
            if now < start:
                return
            baud = self._device.baud
            remaining = len(segment.data) - self._offset
            n = min(remaining, max(1, int(baud / BITS_PER_BYTE * CHUNK_S))) if self._opt.rate_limit else remaining
            chunk = segment.data[self._offset:self._offset + n]
            # With the cable unplugged the LMS still transmits: the bytes are lost.
            if self._line is not None:
                if self._line.baud() != baud:
                    chunk = self._rng.bytes(n)  # the other end decodes noise at the wrong rate
                # A pty, unlike a real line, has flow control: when the reader lags and its
                # buffer fills, output waits instead of being lost, so tests stay exact.
                n = self._line.write(chunk)
                if n == 0:
                    self._line_free_at = now + CHUNK_S
                    return
            if self._opt.rate_limit:
                # Keep the schedule unless we woke late by more than a slice: no drift, no bursts.
                begin = start if now - start < CHUNK_S else now
                self._line_free_at = begin + n * BITS_PER_BYTE / baud
            self._offset += n
            if self._offset == len(segment.data):
                self._queue.popleft()
                self._offset = 0
                if segment.new_baud is not None:
                    self._device.baud = segment.new_baud


def _parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="lrfslam emulate-lms200", description=__doc__.split("\n\n")[0])
    parser.add_argument("--baud-initial", type=int, default=9600, choices=p.BAUD_RATES,
                        help="power-on baud rate (default 9600, as a real LMS200)")
    parser.add_argument("--units-initial", choices=("mm", "cm"), default="mm",
                        help="units in the stored configuration (default mm)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the simulated scans and of the faults")
    parser.add_argument("--world", default="hallway_loop", help="simulated world (lrfslam.sim.floor_plans)")
    parser.add_argument("--rate-limit", action=argparse.BooleanOptionalAction, default=True,
                        help="pace output at baud/10 bytes per second (default on)")
    parser.add_argument("--reply-delay-ms", type=float, default=5.0,
                        help="delay between ACK and reply; a real LMS takes up to 3000 for mode changes")
    parser.add_argument("--power-on-delay-s", type=float, default=0.0,
                        help="delay before the 90h power-on telegram (a real LMS: up to 60)")
    parser.add_argument("--fault-garbage", type=float, default=0.0, metavar="PCT",
                        help="percent of streamed telegrams preceded by 1-32 random bytes")
    parser.add_argument("--fault-bitflip-pct", type=float, default=0.0, metavar="PCT",
                        help="percent of streamed telegrams with one flipped bit")
    parser.add_argument("--fault-truncate", type=float, default=0.0, metavar="PCT",
                        help="percent of streamed telegrams cut short")
    parser.add_argument("--dump-ranges", type=Path, metavar="FILE",
                        help="append one line per scan sent: number, faults, ranges in m")
    parser.add_argument("--link", type=Path, metavar="PATH",
                        help="keep a symlink PATH -> current pty (a stable name across replugs)")
    parser.add_argument("--replug-delay-s", type=float, default=0.5,
                        help="time between SIGUSR1 unplug and the new pty (default 0.5)")
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the emulator until SIGTERM/SIGINT; returns the exit status."""
    args = _parse_args(argv)
    options = EmulatorOptions(
        baud_initial=args.baud_initial, units_initial=p.Units[args.units_initial.upper()], seed=args.seed,
        rate_limit=args.rate_limit, reply_delay_s=args.reply_delay_ms / 1000.0,
        power_on_delay_s=args.power_on_delay_s, fault_garbage_pct=args.fault_garbage,
        fault_bitflip_pct=args.fault_bitflip_pct, fault_truncate_pct=args.fault_truncate,
        link=args.link, replug_delay_s=args.replug_delay_s)
    try:
        source = SimScanSource(args.world, args.seed)
    except ConfigError as exc:
        print(f"emulate-lms200: {exc}", file=sys.stderr)
        return 2
    dump = args.dump_ranges.open("a", encoding="ascii") if args.dump_ranges else None
    try:
        Emulator(options, source, lambda path: print(path, flush=True), dump).run()
    finally:
        if dump is not None:
            dump.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
