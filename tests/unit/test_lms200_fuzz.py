"""Fuzzing the LMS200 stream parser with hypothesis: it never raises on content, every
telegram it emits is CRC-valid and every scan decoded from one is self-consistent.

Derandomised, so a run is repeatable: a random mutation can, with probability 2^-16,
yield a CRC-valid frame, and a failure must not come and go between runs.
tests/fuzz/fuzz_lms200.py is the coverage-guided (atheris) version of the same checks.
"""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from lrfslam.drivers.lms200 import protocol as p
from lrfslam.errors import TelegramError

FUZZ = settings(max_examples=300, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow])
RS = p.RangeStatus


def run_parser(parser: p.TelegramParser, data: bytes, cuts: list[int]):
    items, last = [], 0
    for cut in sorted(c % (len(data) + 1) for c in cuts):
        items += parser.feed(data[last:cut])
        last = cut
    items += parser.feed(data[last:])
    items += parser.on_stall()
    return items


def check_items(items, parser: p.TelegramParser) -> list[p.Telegram]:
    """Invariants every emitted item must satisfy; returns the telegrams."""
    found = [i for i in items if isinstance(i, p.Telegram)]
    assert all(isinstance(i, (p.Telegram, p.Handshake)) for i in items)
    for t in found:
        assert p.crc16(t.raw[:-2]) == int.from_bytes(t.raw[-2:], "little")
        assert t.raw[0] == p.STX and t.address == 0x80
        assert int.from_bytes(t.raw[2:4], "little") + 6 == len(t.raw)
        assert t.raw[5:-3] == t.data and t.status == t.raw[-3]
        if t.command == p.REPLY_SCAN:
            check_scan(t)
    assert all(v >= 0 for v in parser.counters.values())
    assert parser.counters["telegrams"] == len(found)
    return found


def check_scan(t: p.Telegram) -> None:
    try:
        scan = p.parse_scan(t)
    except TelegramError:
        return  # the documented outcome for a CRC-valid but inconsistent B0
    n = scan.ranges_m.size
    assert n >= 1 and scan.status.shape == scan.flags.shape == (n,)
    assert len(t.data) in (2 + 2 * n, 4 + 2 * n)
    ok = scan.status == RS.OK
    no_return = (scan.status == RS.NO_ECHO) | (scan.status == RS.BEYOND_MAX)
    assert np.all(np.isfinite(scan.ranges_m[ok])) and np.all(scan.ranges_m[ok] >= 0)
    assert np.all(scan.ranges_m[no_return] == np.inf)
    assert np.all(np.isnan(scan.ranges_m[~ok & ~no_return]))


@FUZZ
@given(data=st.binary(max_size=3000), cuts=st.lists(st.integers(0, 3000), max_size=30))
@example(data=bytes.fromhex("42 ff 10 02 ff"), cuts=[])  # found by atheris: a header cut before LEN
def test_arbitrary_bytes(data, cuts):
    parser = p.TelegramParser()
    items = run_parser(parser, data, cuts)
    check_items(items, parser)
    # Every byte is accounted for once: telegram, reported handshake, or garbage (nothing left waiting
    # after a discarding stall).
    items += parser.on_stall(discard=True)
    found = [i for i in items if isinstance(i, p.Telegram)]
    handshakes = sum(isinstance(i, p.Handshake) for i in items)
    assert sum(len(t.raw) for t in found) + handshakes + parser.counters["garbage_bytes"] == len(data)


def header_dense_bytes():
    # Random bytes rich in STX, reply address and handshake values, to hit resync paths often.
    return st.lists(st.one_of(st.sampled_from([0x02, 0x80, 0x06, 0x15, 0x00, 0xB0]), st.integers(0, 255)),
                    max_size=400).map(bytes)


@FUZZ
@given(data=header_dense_bytes(), cuts=st.lists(st.integers(0, 400), max_size=30))
def test_header_dense_noise(data, cuts):
    parser = p.TelegramParser()
    check_items(run_parser(parser, data, cuts), parser)


@st.composite
def valid_telegrams(draw):
    kind = draw(st.sampled_from(["scan", "mode", "type"]))
    if kind == "scan":
        raw = np.array(draw(st.lists(st.integers(0, 0xFFFF), min_size=1, max_size=401)), np.uint16)
        return p.build_scan_reply(raw, units=draw(st.sampled_from(list(p.Units))),
                                  indices=draw(st.one_of(st.none(), st.tuples(st.integers(0, 255),
                                                                              st.integers(0, 255)))))
    if kind == "mode":
        return p.build_reply(bytes((0xA0, draw(st.integers(0, 1)))))
    return p.build_reply(b"\xBA" + b"LMS200;301063;V02.10 ")


def mutate(telegram: bytes, how: str, pos: int, value: int) -> bytes:
    if not telegram:
        return bytes((value,))
    pos %= len(telegram)
    if how == "flip":
        return telegram[:pos] + bytes((telegram[pos] ^ (1 << (value % 8)),)) + telegram[pos + 1:]
    if how == "delete":
        return telegram[:pos] + telegram[pos + 1:]
    if how == "insert":
        return telegram[:pos] + bytes((value,)) + telegram[pos:]
    return telegram[:pos]  # truncate


@FUZZ
@given(frames=st.lists(valid_telegrams(), min_size=1, max_size=6),
       mutations=st.lists(st.tuples(st.integers(0, 5), st.sampled_from(["flip", "delete", "insert", "truncate"]),
                                    st.integers(0, 900), st.integers(0, 255)), max_size=4),
       gaps=st.lists(st.binary(max_size=12), min_size=6, max_size=6),
       cuts=st.lists(st.integers(0, 5000), max_size=30))
def test_mutated_valid_telegrams(frames, mutations, gaps, cuts):
    sent = list(frames)
    touched = set()
    for index, how, pos, value in mutations:
        if index < len(sent):
            sent[index] = mutate(sent[index], how, pos, value)
            touched.add(index)
    parser = p.TelegramParser()
    found = check_items(run_parser(parser, b"".join(g + f for g, f in zip(gaps, sent)), cuts), parser)
    # Resynchronisation: every untouched telegram comes out, in order.
    expected = [f for i, f in enumerate(frames) if i not in touched]
    got = iter(t.raw for t in found)
    assert all(any(raw == f for raw in got) for f in expected)
