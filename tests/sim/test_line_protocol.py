import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from firmware_iface.xm_line_protocol import (
    Command,
    Reply,
    checksum,
    decode_line,
    encode_command,
    encode_reply,
    encode_sample,
    parse_command,
)
from xmalign.errors import FormatError
from xmalign.roles import InterferometerReading

finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False)


@given(st.floats(0, 1e6), st.lists(finite, min_size=6, max_size=6), st.booleans())
def test_sample_round_trip(time_s, channels, beam_ok):
    line = encode_sample(InterferometerReading(time_s, np.array(channels), beam_ok))
    decoded = decode_line(line)
    assert isinstance(decoded, InterferometerReading)
    assert decoded.beam_ok == beam_ok
    assert decoded.time_s == pytest.approx(time_s, abs=1e-6)
    np.testing.assert_allclose(decoded.channels, channels, atol=5e-5)


@given(st.booleans(), st.text(alphabet="ABCXYZ 0123456789.", max_size=30))
def test_reply_round_trip(ok, text):
    assert decode_line(encode_reply(Reply(ok, text))) == Reply(ok, text)


def test_corrupted_line_is_refused():
    line = bytearray(encode_sample(InterferometerReading(1.0, np.arange(6.0), True)))
    line[5] ^= 0x01
    with pytest.raises(FormatError, match="checksum"):
        decode_line(bytes(line))
    with pytest.raises(FormatError, match="without checksum"):
        decode_line(b"S,1,2,3\n")


@pytest.mark.parametrize(
    "command",
    [
        Command("ID?"),
        Command("ZERO"),
        Command("READ"),
        Command("STREAM", "ON"),
        Command("RATE", "100"),
        Command("RATE?"),
    ],
)
def test_command_round_trip(command):
    assert parse_command(encode_command(command)) == command


@pytest.mark.parametrize("line", [b"JUMP", b"STREAM MAYBE", b"RATE 0", b"RATE x", b"ZERO 1", b""])
def test_bad_commands(line):
    with pytest.raises(FormatError):
        parse_command(line)


def test_lower_case_commands_are_accepted():
    assert parse_command(b"stream on\r\n") == Command("STREAM", "ON")


def _framed(payload: bytes) -> bytes:
    return payload + b"*" + checksum(payload).encode() + b"\n"


@pytest.mark.parametrize(
    ("payload", "fragment"),
    [
        (b"OK \xb5m", "not ASCII"),
        (b"S,1,2,3,1", "sample line with bad fields"),
        (b"S,0.1,1,2,x,4,5,6,1", "sample line: could not convert"),
        (b"HELLO there", "unknown interferometer line"),
    ],
)
def test_lines_with_a_good_checksum_but_bad_content_are_refused(payload, fragment):
    with pytest.raises(FormatError, match=fragment):
        decode_line(_framed(payload))


def test_rate_needs_exactly_one_number():
    with pytest.raises(FormatError, match="RATE takes one number"):
        parse_command(b"RATE 10 20\n")


@given(st.floats(0.0, 100.0), st.booleans())
def test_the_signal_strength_field_round_trips(signal_pct, beam_ok):
    """The optional 10th field (docs/serial-protocol.md): 0 to 100 %, 1 decimal."""
    reading = InterferometerReading(1.0, np.zeros(6), beam_ok, signal_pct)
    decoded = decode_line(encode_sample(reading))
    assert isinstance(decoded, InterferometerReading)
    assert decoded.signal_pct == pytest.approx(signal_pct, abs=0.05)
    assert decoded.sees_beam(1.0) == (beam_ok or decoded.signal_pct >= 1.0)


def test_a_line_without_the_signal_field_gives_none_and_beam_stands_for_it():
    decoded = decode_line(encode_sample(InterferometerReading(1.0, np.zeros(6), False)))
    assert isinstance(decoded, InterferometerReading)
    assert decoded.signal_pct is None and not decoded.sees_beam(1.0)


@pytest.mark.parametrize("signal", ["100.5", "-1", "x"])
def test_a_signal_out_of_its_range_is_a_corrupted_line(signal):
    payload = "S,1.000000," + ",".join(["0.0000"] * 6) + f",1,{signal}"
    with pytest.raises(FormatError):
        decode_line(f"{payload}*{checksum(payload.encode())}\n".encode())
