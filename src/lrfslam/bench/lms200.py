"""LMS200 driver throughput: telegrams per second the protocol code handles, and scans per second per baud rate.

How many telegrams per second the pure protocol code handles and, with --rates, the scan rate
the emulator delivers per baud rate through the driver.

    python -m lrfslam.bench.lms200 [--telegrams 2000] [--rates]

Needed: 75 telegrams/s (181 values at 500 kBd). Timing lives here, not in tests.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import threading
import time
from functools import partial

import numpy as np

from lrfslam.drivers.lms200 import protocol as p
from lrfslam.drivers.lms200.port import Lms200


def scan_stream(n: int, n_values: int, seed: int = 0) -> list[bytes]:
    rng = np.random.default_rng(seed)
    return [p.build_scan_reply(rng.integers(0, 8000, n_values).astype(np.uint16), units=p.Units.MM)
            for _ in range(n)]


def with_faults(frames: list[bytes], seed: int = 1) -> bytes:
    """Garbage before 30 % of telegrams, one bit flipped in 5 %, 5 % truncated."""
    rng = np.random.default_rng(seed)
    out = bytearray()
    for frame in frames:
        frame = bytearray(frame)
        if rng.random() < 0.3:
            out += rng.bytes(int(rng.integers(1, 33)))
        if rng.random() < 0.05:
            frame[rng.integers(len(frame))] ^= 1 << int(rng.integers(8))
        if rng.random() < 0.05:
            frame = frame[:rng.integers(1, len(frame))]
        out += frame
    return bytes(out)


def crc_all(body: bytes, n: int) -> int:
    for _ in range(n):
        p.crc16(body)
    return n


def parse_all(data: bytes, chunk: int, decode: bool) -> int:
    parser = p.TelegramParser()
    scans = 0
    for i in range(0, len(data), chunk):
        for item in parser.feed(data[i:i + chunk]):
            if decode and isinstance(item, p.Telegram):
                p.parse_scan(item)
                scans += 1
    return parser.counters["telegrams"] if not decode else scans


def best_of(fn, repeat: int = 3) -> tuple[float, int]:
    best, result = float("inf"), 0
    for _ in range(repeat):
        t0 = time.perf_counter()
        result = fn()
        best = min(best, time.perf_counter() - t0)
    return best, result


def throughput(n: int) -> None:
    print(f"{'case':44} {'values':>6} {'telegrams':>9} {'s':>7} {'telegrams/s':>12} {'MB/s':>6}")
    for n_values in (181, 361, 401):
        frames = scan_stream(n, n_values)
        clean = b"".join(frames)
        faulty = with_faults(frames)
        body = frames[0][:-2]
        cases = [
            ("crc16 only", partial(crc_all, body, n), len(body) * n),
            ("parser, whole stream in one feed", partial(parse_all, clean, len(clean), False), len(clean)),
            ("parser, 64-byte reads", partial(parse_all, clean, 64, False), len(clean)),
            ("parser + parse_scan, 64-byte reads", partial(parse_all, clean, 64, True), len(clean)),
            ("parser + parse_scan, faults, 64-byte reads", partial(parse_all, faulty, 64, True), len(faulty)),
        ]
        for name, fn, size in cases:
            seconds, count = best_of(fn)
            print(f"{name:44} {n_values:6d} {count:9d} {seconds:7.3f} {count / seconds:12.0f} "
                  f"{size / seconds / 1e6:6.2f}")


def emulator_rates(seconds: float) -> None:
    print(f"\n{'baud':>7} {'scans':>6} {'Hz':>6}   (emulator process -> pty -> Lms200, 181 values)")
    for baud in (9600, 19200, 38400, 500_000):
        proc = subprocess.Popen([sys.executable, "-m", "lrfslam.drivers.lms200.emulator"],
                                stdout=subprocess.PIPE, text=True)
        try:
            path = proc.stdout.readline().strip()
            stop = threading.Event()
            with Lms200(path, baud) as lms:
                stamps = []
                for _ in lms.scans(stop):
                    stamps.append(time.monotonic())
                    if stamps[-1] - stamps[0] >= seconds:
                        break
            print(f"{baud:7d} {len(stamps):6d} {(len(stamps) - 1) / (stamps[-1] - stamps[0]):6.2f}")
        finally:
            proc.terminate()
            proc.wait()
            proc.stdout.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--telegrams", type=int, default=2000, help="telegrams per case")
    parser.add_argument("--rates", action="store_true", help="also measure emulator scan rates per baud")
    parser.add_argument("--rate-seconds", type=float, default=5.0, help="measuring time per baud rate")
    args = parser.parse_args()
    throughput(args.telegrams)
    if args.rates:
        emulator_rates(args.rate_seconds)


if __name__ == "__main__":
    main()
