"""Coverage-guided fuzzing of the LMS200 stream parser and B0 decoder with atheris.

    pip install atheris
    python tests/fuzz/fuzz_lms200.py -runs=200000 [-max_len=4096] [corpus_dir]

The first input byte picks the parser direction, the next few the chunk sizes the
bytes are fed in; the rest is the stream. Checks are those of
tests/unit/test_lms200_fuzz.py: no exception but TelegramError from parse_scan,
every telegram CRC-valid, every byte accounted for exactly once.
Not collected by pytest (the file name does not start with test_).
"""

from __future__ import annotations

import sys

import atheris

with atheris.instrument_imports():
    import numpy as np

    from lrfslam.drivers.lms200 import protocol as p
    from lrfslam.errors import TelegramError


def check_scan(t: p.Telegram) -> None:
    try:
        scan = p.parse_scan(t)
    except TelegramError:
        return
    n = scan.ranges_m.size
    assert scan.status.shape == (n,) and len(t.data) in (2 + 2 * n, 4 + 2 * n)
    ok = scan.status == p.RangeStatus.OK
    assert np.all(np.isfinite(scan.ranges_m[ok]))


def test_one_input(data: bytes) -> None:
    fdp = atheris.FuzzedDataProvider(data)
    replies = fdp.ConsumeBool()
    cuts = [fdp.ConsumeIntInRange(1, 512) for _ in range(fdp.ConsumeIntInRange(0, 8))]
    stream = fdp.ConsumeBytes(fdp.remaining_bytes())
    parser = p.TelegramParser(replies=replies)
    items, pos = [], 0
    for cut in cuts:
        items += parser.feed(stream[pos:pos + cut])
        pos += cut
    items += parser.feed(stream[pos:])
    items += parser.on_stall()
    items += parser.on_stall(discard=True)
    found = [i for i in items if isinstance(i, p.Telegram)]
    for t in found:
        assert p.crc16(t.raw[:-2]) == int.from_bytes(t.raw[-2:], "little")
        if replies and t.command == p.REPLY_SCAN:
            check_scan(t)
    handshakes = len(items) - len(found)
    assert sum(len(t.raw) for t in found) + handshakes + parser.counters["garbage_bytes"] == len(stream)


if __name__ == "__main__":
    atheris.Setup(sys.argv, test_one_input)
    atheris.Fuzz()
