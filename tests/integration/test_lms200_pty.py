"""Driver <-> emulator over a real pseudo-terminal, the emulator a separate process.

Each test starts ``python -m lrfslam.drivers.lms200.emulator`` with ``--dump-ranges``,
so every scan the driver yields can be matched against what the emulator sent.
Timeouts here only guard against hangs; nothing asserts on elapsed time.
"""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import termios
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import serial

from lrfslam.drivers.lms200 import protocol as p
from lrfslam.drivers.lms200.device_model import SimScanSource
from lrfslam.drivers.lms200.port import Lms200, Lms200Timeouts

HANG_GUARD_S = 30.0
FAST = Lms200Timeouts(scan_s=0.5, reconnect_max_s=0.5)


@dataclass
class Emulator:
    proc: subprocess.Popen
    path: str
    dump: Path

    def sent(self) -> list[tuple[int, str, np.ndarray]]:
        """(scan number, faults, ranges) of every scan the emulator sent so far."""
        rows = []
        for line in self.dump.read_text().splitlines():
            k, faults, *ranges = line.split()
            rows.append((int(k), faults, np.array([float(r) for r in ranges])))
        return rows


@contextmanager
def emulator(tmp_path: Path, *args: str) -> Iterator[Emulator]:
    dump = tmp_path / "sent.txt"
    proc = subprocess.Popen(
        [sys.executable, "-m", "lrfslam.drivers.lms200.emulator", "--dump-ranges", str(dump), *args],
        stdout=subprocess.PIPE, text=True)
    try:
        ready, _, _ = select.select([proc.stdout], [], [], HANG_GUARD_S)
        assert ready, "emulator did not print its pty path"
        yield Emulator(proc, proc.stdout.readline().strip(), dump)
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        proc.stdout.close()


def collect(lms: Lms200, until) -> list[p.ScanTelegram]:
    """Iterate the driver until ``until(scans)`` is true; a watchdog stops a hung run."""
    stop = threading.Event()
    watchdog = threading.Timer(HANG_GUARD_S, stop.set)
    watchdog.start()
    scans: list[p.ScanTelegram] = []
    try:
        for scan in lms.scans(stop):
            scans.append(scan)
            if until(scans):
                break
    finally:
        watchdog.cancel()
    assert not stop.is_set(), f"hang guard fired; counters {lms.counters}"
    return scans


def match_in_order(scans: list[p.ScanTelegram], sent) -> list[int]:
    """Index into ``sent`` of each received scan, matching in order; fails on an unknown scan."""
    indices, j = [], 0
    for scan in scans:
        while j < len(sent) and not np.array_equal(sent[j][2], scan.ranges_m, equal_nan=True):
            j += 1
        assert j < len(sent), "driver yielded a scan the emulator never sent"
        indices.append(j)
        j += 1
    return indices


def line_speed(path: str) -> int:
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        return termios.tcgetattr(fd)[5]
    finally:
        os.close(fd)


def test_init_switches_baud_variant_and_units_and_scans_match(tmp_path):
    # cm units and the factory 180°/0.5° variant force the driver through every init step.
    with emulator(tmp_path, "--units-initial", "cm", "--seed", "7") as emu, Lms200(emu.path, 38400) as lms:
        scans = collect(lms, lambda s: len(s) >= 6)
        assert line_speed(emu.path) == termios.B38400
        sent = emu.sent()
    counters = lms.counters
    assert counters["inits"] == 1 and counters["config_writes"] == 1 and counters["bad_scans"] == 0
    assert counters["init_failures"] == counters["reply_timeouts"] == counters["naks"] == 0  # first time right
    assert lms.device_type.startswith("LMS200;")
    for scan in scans:
        assert scan.ranges_m.size == 181 and scan.units is p.Units.MM
        assert (scan.resolution_deg, scan.fov_deg) == (1.0, 180.0)
    indices = match_in_order(scans, sent)
    assert indices == list(range(indices[0], indices[0] + len(scans)))  # none lost
    # The dump is not the only witness: scan k is reproducible from the seed alone.
    k, _, ranges = sent[indices[-1]]
    expected = SimScanSource("hallway_loop", 7)(p.VARIANT_180_1, k)
    finite = np.isfinite(expected) & (expected < 8.18)
    assert np.allclose(ranges[finite], expected[finite], atol=0.0005)
    assert np.all(np.isinf(ranges[~finite]))


def test_500k_baud_and_a_driver_reconnecting_to_a_running_stream(tmp_path):
    with emulator(tmp_path) as emu:
        with Lms200(emu.path, 500_000) as lms:
            collect(lms, lambda s: len(s) >= 10)
            assert line_speed(emu.path) == termios.B500000
        # A new client finds the LMS still streaming at 500 kBd and takes over.
        with Lms200(emu.path, 500_000) as again:
            scans = collect(again, lambda s: len(s) >= 10)
        assert again.counters["inits"] == 1 and again.counters["config_writes"] == 0
        match_in_order(scans, emu.sent())


def test_faults_never_yield_a_corrupt_scan_and_resync_within_one_telegram(tmp_path):
    faults = ("--fault-garbage", "30", "--fault-bitflip-pct", "8", "--fault-truncate", "8", "--seed", "3")
    with emulator(tmp_path, *faults) as emu, Lms200(emu.path, 500_000) as lms:
        scans = collect(lms, lambda s: len(s) >= 150)
        sent = emu.sent()
    indices = match_in_order(scans, sent)
    received = set(indices)
    for j in range(indices[0], indices[-1] + 1):
        faulty = {"bitflip", "truncate"} & set(sent[j][1].split("+"))
        assert (j in received) != bool(faulty), f"scan {j} ({sent[j][1]}) {'lost' if not faulty else 'passed'}"
    counters = lms.counters
    assert counters["crc_errors"] > 0 and counters["truncated"] > 0 and counters["garbage_bytes"] > 0
    assert counters["bad_scans"] == 0 and counters["inits"] == 1


def test_unplugged_cable_reconnects_and_reinitialises(tmp_path):
    link = tmp_path / "ttyLMS"
    with emulator(tmp_path, "--link", str(link), "--replug-delay-s", "0.3") as emu, \
            Lms200(str(link), 38400, timeouts=FAST) as lms:
        first = collect(lms, lambda s: len(s) >= 3)
        emu.proc.send_signal(signal.SIGUSR1)
        after = collect(lms, lambda s: lms.counters["inits"] >= 2 and len(s) >= 3)
        sent = emu.sent()
    assert lms.counters["disconnects"] >= 1
    match_in_order(first + after, sent)


@pytest.mark.parametrize(("baud", "detected_by"), [(9600, "device_resets"), (500_000, "scan_timeouts")])
def test_power_cycled_lms_is_reinitialised(tmp_path, baud, detected_by):
    # At 9600 Bd the driver reads the 90h power-on telegram; at 500 kBd it only hears noise
    # at the wrong rate and notices that scans stopped.
    with emulator(tmp_path) as emu, Lms200(emu.path, baud, timeouts=FAST) as lms:
        collect(lms, lambda s: len(s) >= 2)
        emu.proc.send_signal(signal.SIGUSR2)
        collect(lms, lambda s: lms.counters["inits"] >= 2 and len(s) >= 2)
        assert line_speed(emu.path) == {9600: termios.B9600, 500_000: termios.B500000}[baud]
    assert lms.counters[detected_by] >= 1, lms.counters


def run_for(lms: Lms200, seconds: float) -> list[p.ScanTelegram]:
    stop = threading.Event()
    timer = threading.Timer(seconds, stop.set)
    timer.start()
    try:
        return list(lms.scans(stop))
    finally:
        timer.cancel()


def test_missing_port_is_retried_not_raised(tmp_path):
    with Lms200(str(tmp_path / "ttyNone"), timeouts=FAST) as lms:
        assert run_for(lms, 0.5) == []
    assert lms.counters["open_failures"] >= 2  # retried with backoff until stopped


def test_silent_device_fails_init_and_is_retried():
    master, slave = os.openpty()  # a port with nothing behind it: every byte goes unanswered
    try:
        quick = Lms200Timeouts(probe_s=0.05, probe_tries=1, baud_settle_s=0.0, reconnect_max_s=0.2)
        with Lms200(os.ttyname(slave), timeouts=quick) as lms:
            assert run_for(lms, 1.0) == []
        assert lms.counters["init_failures"] >= 1 and lms.counters["inits"] == 0
    finally:
        os.close(master)
        os.close(slave)


def read_reply(port: serial.Serial, parser: p.TelegramParser, want: int, wait_s: float = 3.0) -> list:
    """Items read until ``want`` telegrams or a NAK arrived, or ``wait_s`` passed."""
    items: list = []
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        items += parser.feed(port.read(max(1, port.in_waiting)))
        if sum(isinstance(i, p.Telegram) for i in items) >= want or p.Handshake.NAK in items:
            break
    return items


def test_emulator_protocol_conformance_over_raw_pyserial(tmp_path):
    with emulator(tmp_path, "--power-on-delay-s", "0.3") as emu, \
            serial.serial_for_url(emu.path, baudrate=9600, timeout=0.05) as port:
        parser = p.TelegramParser()
        assert p.type_string(read_reply(port, parser, 1)[-1]) == "LMS200;301063;V02.10"  # 90h
        bad = bytearray(p.REQUEST_TYPE)
        bad[-2] ^= 0x40
        port.write(bytes(bad))
        assert read_reply(port, parser, 1) == [p.Handshake.NAK]
        port.write(p.REQUEST_SCAN)
        ack, b0 = read_reply(port, parser, 1)
        assert ack is p.Handshake.ACK and p.parse_scan(b0).ranges_m.size == 361  # factory 0.5°
        port.write(p.build_request(b"\x10"))  # reset: not emulated
        assert [i.command for i in read_reply(port, parser, 1) if isinstance(i, p.Telegram)] == [p.REPLY_REFUSED]
        port.baudrate = 38400  # wrong rate: the LMS hears noise and stays silent
        port.write(p.REQUEST_TYPE)
        assert [i for i in read_reply(port, parser, 1, wait_s=0.5) if isinstance(i, p.Telegram)] == []
