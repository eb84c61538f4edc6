"""LMS200 telegram framing: SICK's CRC, frame building and a resynchronising stream parser.

PURE: bytes in, bytes/objects out; stdlib only. No serial port, no clock, no logging.
Timing (the inter-byte stall rule) is the caller's job: it calls
:meth:`TelegramParser.on_stall` when its line has been quiet too long.

Frame layout, identical in both directions (docs/lms200-protocol.md, 'Framing')::

    STX(0x02) ADDR LEN_lo LEN_hi CMD DATA... [STATUS] CRC_lo CRC_hi

LEN counts CMD + DATA (+ STATUS in replies); the whole frame is LEN + 6 bytes.
There is no byte stuffing, so a resynchronising parser has to try every STX.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

STX = 0x02
ACK = 0x06
NAK = 0x15
REPLY_ADDRESS_BIT = 0x80  # the LMS answers with its address + 80h (TL p.24)
FRAME_OVERHEAD = 6  # STX, ADDR, LEN (2), CRC (2)
# 401 values with real-time indices (TL Table 10-16); anything longer is misframed.
MAX_FRAME_BYTES = 814
MAX_LEN = MAX_FRAME_BYTES - FRAME_OVERHEAD
_CRC_POLY = 0x8005


def crc16(data: bytes | bytearray | memoryview) -> int:
    """SICK's CRC-16 variant over ``data`` (docs/lms200-protocol.md, 'CRC').

    Not CRC-16/BUYPASS: each step XORs in the previous byte as the high half
    of the word, so a generic 0x8005 table gives wrong results.

    Parameters
    ----------
    data : bytes-like
        Every byte from STX up to and including the last data/status byte.

    Returns
    -------
    int
        The 16-bit checksum, sent low byte first.
    """
    crc = 0
    prev = 0
    for byte in data:
        carry = crc & 0x8000
        crc = (crc << 1) & 0xFFFF
        if carry:
            crc ^= _CRC_POLY
        crc ^= (prev << 8) | byte
        prev = byte
    return crc


def frame(address: int, payload: bytes) -> bytes:
    """Wrap ``payload`` (CMD + DATA [+ STATUS]) into a complete telegram.

    Parameters
    ----------
    address : int
        Raw address byte, 0..255 (host->LMS 0..7Fh; LMS->host 80h | address).
    payload : bytes
        Command byte, data and, for replies, the status byte; 1..808 bytes.

    Returns
    -------
    bytes
        STX, address, LEN (LE), payload, CRC (LE).

    Raises
    ------
    ValueError
        If the address or payload length is out of range (a programming error).
    """
    if not 0 <= address <= 0xFF:
        raise ValueError(f"address {address} is not a byte")
    if not 1 <= len(payload) <= MAX_LEN:
        raise ValueError(f"payload of {len(payload)} bytes; must be 1..{MAX_LEN}")
    body = bytes((STX, address)) + len(payload).to_bytes(2, "little") + bytes(payload)
    return body + crc16(body).to_bytes(2, "little")


def build_request(payload: bytes, address: int = 0) -> bytes:
    """Host->LMS telegram: ``payload`` = CMD + DATA; ``address`` 0 = broadcast (0..7Fh)."""
    if not 0 <= address < REPLY_ADDRESS_BIT:
        raise ValueError(f"LMS address {address} outside 0..127")
    return frame(address, payload)


def build_reply(payload: bytes, status: int = 0x10, address: int = 0) -> bytes:
    """LMS->host telegram: ``payload`` = response code + DATA, then the status byte.

    ``status`` 0x10 is what a healthy standard LMS200 reports
    (docs/lms200-protocol.md, 'Status byte').
    """
    if not 0 <= address < REPLY_ADDRESS_BIT:
        raise ValueError(f"LMS address {address} outside 0..127")
    if not 0 <= status <= 0xFF:
        raise ValueError(f"status {status} is not a byte")
    return frame(REPLY_ADDRESS_BIT | address, bytes(payload) + bytes((status,)))


class Handshake(IntEnum):
    """The bare, unframed bytes the LMS sends before its reply (TL p.23)."""

    ACK = ACK
    NAK = NAK


@dataclass(frozen=True)
class Telegram:
    """One CRC-valid telegram.

    ``status`` is the trailing status byte of an LMS->host telegram and None
    for a host->LMS one; ``data`` excludes the command and status bytes;
    ``raw`` is the complete frame including the CRC.
    """

    address: int
    command: int
    data: bytes
    status: int | None
    raw: bytes


# Symptom counters. A fault inside the span of an earlier one is counted once.
COUNTER_NAMES = (
    "telegrams",      # CRC-valid telegrams emitted
    "garbage_bytes",  # bytes discarded (outside every valid telegram; reported ACK/NAK excluded)
    "bad_length",     # header with a LEN outside the legal range
    "crc_errors",     # complete frame, bad CRC, no valid telegram started inside it
    "truncated",      # frame cut short: a valid telegram started inside it, or the line stalled
)


class TelegramParser:
    """Streaming parser: feed bytes, get complete CRC-valid telegrams.

    Resynchronises after garbage, bit flips and truncated telegrams. On any
    failure it resumes the search at the byte after the failed STX, never after
    the claimed length, so the telegram following a truncated one is not lost
    (docs/lms200-protocol.md, 'Quirks the driver handles'). It never raises on
    input content.

    Parameters
    ----------
    replies : bool
        True to parse LMS->host traffic (address byte 80h | ``address``, a
        status byte, bare ACK/NAK bytes reported as :class:`Handshake`);
        False for host->LMS traffic (the emulator's side).
    address : int
        LMS address 0..127; frames for another address are garbage.
    """

    def __init__(self, *, replies: bool = True, address: int = 0) -> None:
        if not 0 <= address < REPLY_ADDRESS_BIT:
            raise ValueError(f"LMS address {address} outside 0..127")
        self._replies = replies
        self._address_byte = (REPLY_ADDRESS_BIT | address) if replies else address
        self._min_len = 2 if replies else 1  # CMD (+ STATUS)
        self._buf = bytearray()
        self._pos = 0
        # (start, end) of the first failed frame not yet classified as CRC error or truncation.
        self._suspect: tuple[int, int] | None = None
        self.counters: dict[str, int] = dict.fromkeys(COUNTER_NAMES, 0)

    def feed(self, data: bytes | bytearray | memoryview) -> list[Telegram | Handshake]:
        """Append received bytes; return the telegrams and handshakes now complete.

        Raises
        ------
        TypeError
            If ``data`` is not bytes-like (the only exception; a programming error).
        """
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise TypeError(f"feed() wants bytes, got {type(data).__name__}")
        self._buf += data
        out: list[Telegram | Handshake] = []
        self._parse(out)
        self._compact()
        return out

    def on_stall(self, *, discard: bool = False) -> list[Telegram | Handshake]:
        """React to a quiet line while a frame is still waiting for bytes.

        Call this when the line has been quiet longer than the sender's
        inter-byte limit (14 ms for the LMS, 6 ms for the host; TL p.24). If a
        valid telegram starts inside the waiting frame, the frame was cut short
        (a truncated B0 followed by ACK and the reply to a request): it counts
        as truncated and the telegrams found are returned (ACK/NAK bytes inside
        the cut frame look like its data and are dropped). Otherwise the frame
        is kept, since the sender may only have paused, unless ``discard`` is
        set (the LMS's own rule for host telegrams): then every buffered byte is
        dropped, the frame counted as truncated. A failed frame still
        unclassified is settled as a CRC error here.
        """
        out: list[Telegram | Handshake] = []
        while self._waiting():
            if self._search_waiting_frame(out):
                continue  # what followed may end in another waiting frame
            if discard:
                self._classify_failure(self._pos, len(self._buf), stalled=True)
                self._discard(len(self._buf), out)
            break
        if not self._waiting():
            self._resolve_suspect(None)  # every byte after a failed frame has been searched
            if discard:
                self._discard(len(self._buf), out)  # a header cut before its length field
        self._compact()
        return out

    def _search_waiting_frame(self, out: list[Telegram | Handshake]) -> bool:
        """Look for telegrams inside the waiting frame; on success it is settled as truncated.

        Returns False, with the parser state untouched, when there is none.
        """
        saved = (self._pos, self._suspect, dict(self.counters))
        start = self._pos
        length = self._buf[start + 2] | (self._buf[start + 3] << 8)
        # As a suspect, the frame counts as truncated once a telegram is found inside it.
        self._classify_failure(start, start + length + FRAME_OVERHEAD, stalled=False)
        found: list[Telegram | Handshake] = []
        self._discard(start + 1, found)
        self._parse(found)
        if any(isinstance(item, Telegram) for item in found):
            out += found
            return True
        self._pos, self._suspect = saved[0], saved[1]
        self.counters.update(saved[2])
        return False

    def _waiting(self) -> bool:
        """True when a frame with a plausible header waits for more bytes."""
        return self._pos + 4 <= len(self._buf) and self._buf[self._pos] == STX

    def reset(self) -> None:
        """Drop buffered bytes without counting them (after a baud change or reopen)."""
        self._buf.clear()
        self._pos = 0
        self._suspect = None

    def _parse(self, out: list[Telegram | Handshake]) -> None:
        buf = self._buf
        while True:
            start = buf.find(STX, self._pos)
            if start < 0:
                self._discard(len(buf), out)
                return
            self._discard(start, out)
            if len(buf) - start < 4:
                return  # header incomplete
            if buf[start + 1] != self._address_byte:
                self._discard(start + 1, out)
                continue
            length = buf[start + 2] | (buf[start + 3] << 8)
            if not self._min_len <= length <= MAX_LEN:
                self.counters["bad_length"] += 1
                self._discard(start + 1, out)
                continue
            end = start + length + FRAME_OVERHEAD
            if len(buf) < end:
                return  # wait for the rest
            crc = buf[end - 2] | (buf[end - 1] << 8)
            if crc16(memoryview(buf)[start:end - 2]) != crc:
                self._classify_failure(start, end, stalled=False)
                self._discard(start + 1, out)
                continue
            self._resolve_suspect(start)
            out.append(self._telegram(bytes(buf[start:end])))
            self.counters["telegrams"] += 1
            self._pos = end

    def _telegram(self, raw: bytes) -> Telegram:
        if self._replies:
            return Telegram(raw[1], raw[4], raw[5:-3], raw[-3], raw)
        return Telegram(raw[1], raw[4], raw[5:-2], None, raw)

    def _classify_failure(self, start: int, end: int, *, stalled: bool) -> None:
        if self._suspect is not None and start < self._suspect[1]:
            return  # inside an earlier failed frame: the same fault
        self._resolve_suspect(start)
        if stalled:
            self.counters["truncated"] += 1
        else:
            self._suspect = (start, end)

    def _resolve_suspect(self, next_start: int | None) -> None:
        """Settle the pending failed frame once parsing has moved on to ``next_start``.

        A valid telegram starting inside the failed frame means the frame was cut
        short by it; otherwise its bytes were corrupted. None = no more data.
        """
        if self._suspect is None:
            return
        if next_start is not None and next_start < self._suspect[1]:
            self.counters["truncated"] += 1
        else:
            self.counters["crc_errors"] += 1
        self._suspect = None

    def _discard(self, stop: int, out: list[Telegram | Handshake]) -> None:
        """Skip bytes up to ``stop``; bare ACK/NAK bytes among them are reported.

        Inside a failed frame they are data, not handshakes: a B0 is full of 06h and 15h.
        """
        start = self._pos
        if stop <= start:
            return
        handshakes = 0
        if self._replies:
            for byte in self._buf[max(start, self._suspect[1] if self._suspect else start):stop]:
                if byte == ACK or byte == NAK:
                    out.append(Handshake(byte))
                    handshakes += 1
        self.counters["garbage_bytes"] += stop - start - handshakes
        self._pos = stop

    def _compact(self) -> None:
        if self._pos:
            shift = self._pos
            del self._buf[:shift]
            self._pos = 0
            if self._suspect is not None:
                self._suspect = (self._suspect[0] - shift, self._suspect[1] - shift)
