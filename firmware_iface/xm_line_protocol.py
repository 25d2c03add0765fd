"""Serial line protocol of the (simulated) XM-60-class interferometer (docs/serial-protocol.md).

ASCII, one message per line, ``\\n`` terminated (a ``\\r`` before it is ignored).
Every line from the instrument ends in ``*HH``, the XOR of all bytes before the
``*`` as two upper-case hex digits, so that a corrupted line is detected.

Instrument to host::

    S,<time_s>,<linear_um>,<sv_um>,<sw_um>,<au_urad>,<av_urad>,<aw_urad>,<beam>[,<signal>]*HH
    OK <COMMAND>[ <value>]*HH
    ERR <text>*HH

Host to instrument (no checksum; case-insensitive)::

    ID?            -> OK ID <identification>
    ZERO           -> OK ZERO             (linear datum at the present position)
    READ           -> OK READ, then one S line
    STREAM ON|OFF  -> OK STREAM ON|OFF    (S lines at the sample rate while on)
    RATE <hz>      -> OK RATE <hz>        (1 to 1000 samples/s)
    RATE?          -> OK RATE <hz>

Pure functions; no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from xmalign.errors import FormatError
from xmalign.roles import CHANNELS, InterferometerReading

RATE_MIN_HZ = 1.0
RATE_MAX_HZ = 1000.0
COMMANDS = ("ID?", "ZERO", "READ", "STREAM", "RATE", "RATE?")
_SAMPLE_FIELDS = 1 + 1 + len(CHANNELS) + 1
#: Signal strength, %: the optional last field of an ``S`` line.
SIGNAL_RANGE_PCT = (0.0, 100.0)


@dataclass(frozen=True)
class Command:
    """A host command: ``name`` one of :data:`COMMANDS`, ``argument`` as given ('' if none)."""

    name: str
    argument: str = ""


@dataclass(frozen=True)
class Reply:
    """An ``OK``/``ERR`` answer: ``ok``, and the rest of the line (``'RATE 100'``, error text)."""

    ok: bool
    text: str


def checksum(payload: bytes) -> str:
    """XOR of the payload bytes as two upper-case hex digits."""
    value = 0
    for byte in payload:
        value ^= byte
    return f"{value:02X}"


def _frame(payload: str) -> bytes:
    data = payload.encode("ascii")
    return data + b"*" + checksum(data).encode("ascii") + b"\n"


def encode_sample(reading: InterferometerReading) -> bytes:
    """One ``S`` line for a reading (µm and µrad with 4 decimals, time with 6)."""
    values = ",".join(f"{v:.4f}" for v in np.asarray(reading.channels, dtype=float))
    signal = "" if reading.signal_pct is None else f",{reading.signal_pct:.1f}"
    return _frame(f"S,{reading.time_s:.6f},{values},{int(reading.beam_ok)}{signal}")


def encode_reply(reply: Reply) -> bytes:
    """An ``OK``/``ERR`` line."""
    return _frame(f"{'OK' if reply.ok else 'ERR'} {reply.text}")


def _unframe(line: bytes) -> str:
    text = line.rstrip(b"\r\n")
    payload, star, received = text.rpartition(b"*")
    if not star:
        raise FormatError(f"interferometer line without checksum: {text[:60]!r}")
    if received.decode("ascii", "replace").upper() != checksum(payload):
        raise FormatError(f"interferometer line with a bad checksum: {text[:60]!r}")
    try:
        return payload.decode("ascii")
    except UnicodeDecodeError as error:
        raise FormatError(f"interferometer line is not ASCII: {text[:60]!r}") from error


def decode_line(line: bytes) -> InterferometerReading | Reply:
    """Decode one line from the instrument; raises FormatError for a corrupted one."""
    payload = _unframe(line)
    if payload.startswith("S,"):
        fields = payload.split(",")
        signal_pct = _signal_pct(fields, payload) if len(fields) == _SAMPLE_FIELDS + 1 else None
        fields = fields[:_SAMPLE_FIELDS] if signal_pct is not None else fields
        if len(fields) != _SAMPLE_FIELDS or fields[-1] not in ("0", "1"):
            raise FormatError(f"interferometer sample line with bad fields: {payload[:60]!r}")
        try:
            numbers = [float(f) for f in fields[1:-1]]
        except ValueError as error:
            raise FormatError(f"interferometer sample line: {error}") from error
        return InterferometerReading(
            time_s=numbers[0],
            channels=np.array(numbers[1:]),
            beam_ok=fields[-1] == "1",
            signal_pct=signal_pct,
        )
    status, _, text = payload.partition(" ")
    if status not in ("OK", "ERR"):
        raise FormatError(f"unknown interferometer line: {payload[:60]!r}")
    return Reply(ok=status == "OK", text=text)


def _signal_pct(fields: list[str], payload: str) -> float:
    """The signal strength of an ``S`` line's last field, checked against 0..100 %."""
    try:
        signal = float(fields[-1])
    except ValueError as error:
        raise FormatError(f"interferometer sample line: {error}") from error
    low, high = SIGNAL_RANGE_PCT
    if not low <= signal <= high:
        raise FormatError(f"interferometer sample line with bad signal: {payload[:60]!r}")
    return signal


def encode_command(command: Command) -> bytes:
    """A host command line."""
    text = f"{command.name} {command.argument}" if command.argument else command.name
    return text.encode("ascii") + b"\n"


def parse_command(line: bytes) -> Command:
    """Parse a host command line; raises FormatError naming what is wrong."""
    words = line.decode("ascii", "replace").strip().upper().split()
    if not words or words[0] not in COMMANDS:
        raise FormatError(f"unknown command {' '.join(words)!r}")
    name, arguments = words[0], words[1:]
    if name == "STREAM":
        if arguments not in (["ON"], ["OFF"]):
            raise FormatError("STREAM takes ON or OFF")
    elif name == "RATE":
        if len(arguments) != 1:
            raise FormatError("RATE takes one number (samples per second)")
        rate_hz(arguments[0])
    elif arguments:
        raise FormatError(f"{name} takes no argument")
    return Command(name, " ".join(arguments))


def rate_hz(argument: str) -> float:
    """The sample rate of a ``RATE`` argument, checked against the allowed range."""
    try:
        rate = float(argument)
    except ValueError as error:
        raise FormatError(f"RATE {argument!r} is not a number") from error
    if not RATE_MIN_HZ <= rate <= RATE_MAX_HZ:
        raise FormatError(f"RATE {rate:g} outside {RATE_MIN_HZ:g} to {RATE_MAX_HZ:g} samples/s")
    return rate
