"""Tests of the trigger line protocol: framing, checksum, streaming parser (fuzzed)."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from prism3d.capture.trigger_protocol import (
    MAX_LINE,
    FrameError,
    LineParser,
    Message,
    checksum,
    decode_line,
    encode,
    parse_kv,
)
from prism3d.errors import InputError


def test_checksum_known_answer() -> None:
    # NMEA reference sentence: $GPGLL,5057.970,N,00146.110,E,142451,A*27
    assert checksum(b"GPGLL,5057.970,N,00146.110,E,142451,A") == 0x27
    assert checksum(b"") == 0


def test_encode_known_line() -> None:
    line = encode(7, "ARM", 1)
    assert line == b"7 ARM 1 *%02X\n" % checksum(b"7 ARM 1")
    assert decode_line(line) == Message(7, "ARM", ("1",))


@pytest.mark.parametrize(
    ("args", "match"),
    [
        ((-1, "ID"), "seq"),
        ((65536, "ID"), "seq"),
        ((True, "ID"), "seq"),
        ((1, "id"), "word"),
        ((1, "ID", "a b"), "printable ASCII"),
        ((1, "ID", "a*b"), "printable ASCII"),
        ((1, "ID", "é"), "printable ASCII"),
        ((1, "ID", "x" * 200), "line too long"),
    ],
)
def test_encode_rejects(args: tuple, match: str) -> None:
    with pytest.raises(InputError, match=match):
        encode(*args)


@pytest.mark.parametrize(
    ("raw", "reason"),
    [
        (b"1 ID *00\n", "checksum error"),
        (b"1 ID\n", "malformed line"),
        (b"1 ID *ZZ\n", "malformed line"),
        (b"\xff\xfe *00\n", "non-ASCII bytes"),
        (b"x" * 300 + b"\n", "overlong line"),
    ],
)
def test_decode_errors(raw: bytes, reason: str) -> None:
    out = decode_line(raw)
    assert isinstance(out, FrameError)
    assert out.reason == reason


def test_decode_checksum_error_keeps_seq() -> None:
    good = encode(42, "STATUS")
    bad = good[:-3] + (b"00\n" if good[-3:-1] != b"00" else b"01\n")
    out = decode_line(bad)
    assert isinstance(out, FrameError) and out.seq == 42


def test_decode_malformed_after_valid_checksum() -> None:
    payload = b"abc ID"
    out = decode_line(payload + b" *%02X\n" % checksum(payload))
    assert isinstance(out, FrameError) and out.reason == "malformed line"


def test_decode_lowercase_checksum_and_crlf() -> None:
    payload = b"3 OK ID"
    msg = decode_line(payload + b" *%02x\r\n" % checksum(payload))
    assert msg == Message(3, "OK", ("ID",))
    assert msg.is_reply and not msg.is_event


def test_parser_splits_chunks_and_resyncs() -> None:
    p = LineParser()
    a, b = encode(1, "ID"), encode(2, "OK", "ARM", "pattern=1")
    stream = b"\x00garbage\n" + a + b"\n" + b
    items: list = []
    for i in range(len(stream)):  # one byte at a time
        items += p.feed(stream[i : i + 1])
    assert [type(x) for x in items] == [FrameError, Message, Message]
    assert items[1] == Message(1, "ID") and items[2].args == ("ARM", "pattern=1")
    assert p.pending == 0


def test_parser_overlong_reported_once_then_recovers() -> None:
    p = LineParser()
    out = p.feed(b"y" * 400)
    out += p.feed(b"y" * 400)
    out += p.feed(b"tail\n" + encode(5, "STATUS"))
    errs = [x for x in out if isinstance(x, FrameError)]
    assert len(errs) == 1 and errs[0].reason == "overlong line"
    assert out[-1] == Message(5, "STATUS")


def test_parser_accepts_max_length_line() -> None:
    arg = "x" * (MAX_LINE - len(b"1 OK  *00\n"))
    line = encode(1, "OK", arg)
    assert len(line) == MAX_LINE
    assert LineParser().feed(line) == [Message(1, "OK", (arg,))]


def test_parse_kv() -> None:
    assert parse_kv(("shot=3", "bare", "t=-1", "=x")) == {"shot": "3", "t": "-1"}


def test_parser_reset_drops_partial_line() -> None:
    p = LineParser()
    p.feed(b"12 OK")
    p.reset()
    assert p.feed(encode(1, "ID")) == [Message(1, "ID")]


@settings(max_examples=300, deadline=None)
@given(st.lists(st.binary(max_size=300), max_size=8))
def test_fuzz_parser_never_raises(chunks: list[bytes]) -> None:
    p = LineParser()
    for c in chunks:
        for item in p.feed(c):
            assert isinstance(item, (Message, FrameError))
    assert p.pending <= MAX_LINE


_token = st.text(
    alphabet=st.characters(min_codepoint=0x21, max_codepoint=0x7E, exclude_characters="*"),
    min_size=1,
    max_size=12,
)


@settings(max_examples=200, deadline=None)
@given(
    st.integers(0, 65535),
    st.from_regex(r"\A[A-Z][A-Z0-9_]{0,15}\Z"),
    st.lists(_token, max_size=5),
    st.binary(max_size=40),
)
def test_fuzz_roundtrip(seq: int, word: str, args: list[str], junk: bytes) -> None:
    line = encode(seq, word, *args)
    assert decode_line(line) == Message(seq, word, tuple(args))
    # After arbitrary junk and a newline the parser resynchronises on the next line.
    items = LineParser().feed(junk + b"\n" + line)
    assert items[-1] == Message(seq, word, tuple(args))
