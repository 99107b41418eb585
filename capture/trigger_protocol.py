"""The trigger-controller line protocol: framing, checksum and a streaming parser (no I/O).

Every line is ``<seq> <WORD> [args...] *<CK>\n``: ``seq`` 0..65535, an upper-case
command or reply kind (``OK``, ``ERR``, ``EV``), printable tokens without spaces or
``*``, and ``CK`` the NMEA 0183 XOR checksum of the bytes before ``" *"`` in two hex
digits (docs/trigger-protocol.md). The parser never raises on input bytes: bad
lines come out as :class:`FrameError` items and it resynchronises at the next newline.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

from prism3d.errors import InputError

__all__ = [
    "PROTOCOL_VERSION",
    "MAX_LINE",
    "MAX_SEQ",
    "REPLY_KINDS",
    "COMMANDS",
    "ERROR_CODES",
    "Message",
    "FrameError",
    "checksum",
    "encode",
    "decode_line",
    "parse_kv",
    "LineParser",
]

#: Protocol version reported by ``ID`` (``proto=``).
PROTOCOL_VERSION = 1
#: Maximum line length in bytes, including the checksum and the ``\n``.
MAX_LINE = 128
#: Sequence numbers are 0..MAX_SEQ; the host uses 1..MAX_SEQ (0 = "unknown").
MAX_SEQ = 65535
#: Words a device sends.
REPLY_KINDS = ("OK", "ERR", "EV")
#: Words a host sends.
COMMANDS = ("ID", "ARM", "DISARM", "FIRE", "STATUS")
#: Device error codes (``<seq> ERR <code> <text>``).
ERROR_CODES: dict[int, str] = {
    1: "checksum",
    2: "unknown command",
    3: "not armed",
    4: "bad argument",
    5: "busy",
    6: "flash not ready",
    7: "line too long",
}

_TOKEN = re.compile(rb"^[\x21-\x29\x2b-\x7e]+$")  # printable, no space, no '*'
_WORD = re.compile(rb"^[A-Z][A-Z0-9_]{0,15}$")
_SEQ = re.compile(rb"^[0-9]{1,5}$")
_CK = re.compile(rb"^[0-9A-Fa-f]{2}$")


@dataclass(frozen=True)
class Message:
    """One validated protocol line: ``seq`` 0..65535 (replies echo the command's, events
    carry the device's counter), ``word`` (``ID``, ``ARM``..., ``OK``, ``ERR``, ``EV``) and
    the remaining ``args``.
    """

    seq: int
    word: str
    args: tuple[str, ...] = ()

    @property
    def is_reply(self) -> bool:
        """True for ``OK`` and ``ERR`` lines (answers to a command)."""
        return self.word in ("OK", "ERR")

    @property
    def is_event(self) -> bool:
        """True for ``EV`` lines (unsolicited device events)."""
        return self.word == "EV"


@dataclass(frozen=True)
class FrameError:
    """A line (or run of bytes) that could not be accepted: ``reason`` (``"checksum
    error"``, ``"overlong line"``, ``"malformed line"``, ``"non-ASCII bytes"``), the
    ``raw`` bytes (at most :data:`MAX_LINE`) and ``seq`` when still readable.
    """

    reason: str
    raw: bytes = field(repr=False)
    seq: int | None = None


def checksum(payload: bytes) -> int:
    """XOR of all bytes of ``payload``, 0..255 (the NMEA 0183 sentence checksum)."""
    ck = 0
    for b in payload:
        ck ^= b
    return ck


def encode(seq: int, word: str, *args: object) -> bytes:
    """Frame one line ``b"<seq> <WORD> args... *CK\n"``; InputError for a bad ``seq``,
    word or argument, or a line longer than :data:`MAX_LINE`.
    """
    if isinstance(seq, bool) or not isinstance(seq, int) or not 0 <= seq <= MAX_SEQ:
        raise InputError(f"seq: expected an integer in [0, {MAX_SEQ}], got {seq!r}")
    wb = str(word).encode("ascii", "replace")
    if not _WORD.match(wb):
        raise InputError(f"word: expected an upper-case token like 'FIRE', got {word!r}")
    parts = [str(seq).encode(), wb]
    for a in args:
        text = str(a)
        ab = text.encode("ascii", "replace")
        if not text.isascii() or not _TOKEN.match(ab):
            raise InputError(
                f"argument {a!r}: expected printable ASCII without spaces or '*'"
            )
        parts.append(ab)
    payload = b" ".join(parts)
    line = payload + b" *%02X\n" % checksum(payload)
    if len(line) > MAX_LINE:
        raise InputError(f"line too long: {len(line)} bytes, the protocol allows {MAX_LINE}")
    return line


def decode_line(line: bytes) -> Message | FrameError:
    """Validate one line (with or without ``\n`` / ``\r\n``); never raises on bytes."""
    raw = bytes(line[: MAX_LINE + 2])
    body = raw.rstrip(b"\r\n")
    if len(body) + 1 > MAX_LINE:
        return FrameError("overlong line", raw[:MAX_LINE])
    try:
        body.decode("ascii")
    except UnicodeDecodeError:
        return FrameError("non-ASCII bytes", raw)
    star = body.rfind(b" *")
    if star < 0:
        return FrameError("malformed line", raw)
    payload, ck_text = body[:star], body[star + 2 :]
    tokens = payload.split(b" ")
    seq: int | None = int(tokens[0]) if _SEQ.match(tokens[0]) else None
    if seq is not None and seq > MAX_SEQ:
        seq = None
    if not _CK.match(ck_text):
        return FrameError("malformed line", raw, seq)
    if int(ck_text, 16) != checksum(payload):
        return FrameError("checksum error", raw, seq)
    if seq is None or len(tokens) < 2 or not _WORD.match(tokens[1]):
        return FrameError("malformed line", raw, seq)
    if not all(_TOKEN.match(t) for t in tokens[2:]):
        return FrameError("malformed line", raw, seq)
    return Message(seq, tokens[1].decode(), tuple(t.decode() for t in tokens[2:]))


def parse_kv(args: tuple[str, ...]) -> dict[str, str]:
    """``("a=1", "b=x")`` -> ``{"a": "1", "b": "x"}``; tokens without ``=`` are skipped."""
    out: dict[str, str] = {}
    for a in args:
        key, sep, value = a.partition("=")
        if sep and key:
            out[key] = value
    return out


class LineParser:
    """Streaming parser: feed byte chunks, get validated lines; an overlong line is
    reported once and skipped to the next ``\n``; empty lines are ignored; never raises.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self._discarding = False

    def reset(self) -> None:
        """Forget any partial line (after a reconnect or before a retry)."""
        self._buf.clear()
        self._discarding = False

    @property
    def pending(self) -> int:
        """Number of buffered bytes of an incomplete line."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[Message | FrameError]:
        """Add bytes; return the messages and frame errors completed by them."""
        out: list[Message | FrameError] = []
        start = 0
        n = len(data)
        while start < n:
            nl = data.find(b"\n", start)
            chunk = data[start:] if nl < 0 else data[start:nl]
            start = n if nl < 0 else nl + 1
            if self._discarding:
                if nl >= 0:
                    self._discarding = False
                continue
            self._buf += chunk
            if len(self._buf) > MAX_LINE:  # MAX_LINE counts the '\n'; allow one '\r'
                out.append(FrameError("overlong line", bytes(self._buf[:MAX_LINE])))
                self._buf.clear()
                self._discarding = nl < 0
                continue
            if nl >= 0:
                line = bytes(self._buf)
                self._buf.clear()
                if line.strip(b"\r") == b"":
                    continue
                out.append(decode_line(line))
        return out
