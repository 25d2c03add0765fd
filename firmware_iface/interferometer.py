"""Interferometer drivers: the serial line protocol, and replay of a recorded stream.

:class:`SerialInterferometer` speaks docs/serial-protocol.md (codec in
:mod:`firmware_iface.xm_line_protocol`) over any serial-like connection with
``write``, ``readline`` and ``reset_input_buffer`` (a ``serial.Serial`` from
:func:`open_serial`, or anything else, e.g. a socket wrapper). Averages are
taken over streamed samples, timed by the instrument's own sample times.

Recorded streams are CSV files (``xmalign.interferometer-stream``)::

    time_s,linear_um,straightness_v_um,straightness_w_um,angle_u_urad,angle_v_urad,angle_w_urad,beam_ok
    0.020000,0.0000,1.2000,-0.4000,0.0000,3.1000,-2.0000,1

:class:`RecordingInterferometer` writes one while it reads another
interferometer; :class:`ReplayInterferometer` plays one back through the same
role, so captured data can be re-run through alignment or a measurement.

Every line sent and received is logged on the ``firmware_iface.interferometer``
logger at DEBUG (``>`` host to instrument, ``<`` instrument to host).
"""

from __future__ import annotations

import csv
import logging
import math
from pathlib import Path
from typing import Protocol

import numpy as np
import serial

from firmware_iface.xm_line_protocol import Command, Reply, decode_line, encode_command
from xmalign.errors import DeviceError, DeviceTimeoutError, FormatError, TransportError
from xmalign.formats.common import read_text
from xmalign.roles import (
    CHANNELS,
    Clock,
    ClosesOnExit,
    Interferometer,
    InterferometerReading,
    WallClock,
    mean_reading,
)

STREAM_HEADER = ("time_s", *CHANNELS, "beam_ok")
#: Consecutive corrupted lines tolerated (each is discarded) before the line counts as broken.
MAX_CORRUPTED_LINES = 5
#: Sample times are rounded (to 1 µs in the line protocol): a duration is covered within this.
_TIME_TOLERANCE_S = 1e-5

log = logging.getLogger(__name__)


class LineConnection(Protocol):
    """The part of ``serial.Serial`` the driver uses."""

    def write(self, data: bytes) -> int | None: ...

    def readline(self) -> bytes: ...

    def reset_input_buffer(self) -> None: ...


def open_serial(port: str, baudrate: int = 115200, timeout_s: float = 1.0) -> serial.Serial:
    """Open a serial port (or a pyserial URL such as ``socket://host:port``)."""
    try:
        return serial.serial_for_url(port, baudrate=baudrate, timeout=timeout_s)
    except (serial.SerialException, OSError) as error:
        raise TransportError(f"cannot open the interferometer port {port}: {error}") from error


class SerialInterferometer:
    """The ``Interferometer`` role over the line protocol.

    Parameters
    ----------
    connection : LineConnection
        Open serial connection with a read timeout.
    device_name : str
        How errors name the instrument, e.g. ``"interferometer on /dev/ttyUSB0"``.
    clock : Clock, optional
        The host's clock, told before each wait for a streamed sample
        (``Clock.await_stream``; the wall clock, the default, does nothing).
    """

    def __init__(
        self,
        connection: LineConnection,
        device_name: str = "interferometer",
        clock: Clock | None = None,
    ) -> None:
        self.connection = connection
        self.device_name = device_name
        self.clock = clock or WallClock()
        self.corrupted_lines = 0
        self.connection.reset_input_buffer()

    def identify(self) -> str:
        return self._command(Command("ID?")).text.removeprefix("ID").strip()

    def set_rate(self, rate_hz: float) -> None:
        self._command(Command("RATE", f"{rate_hz:g}"))

    def zero(self) -> None:
        self._command(Command("ZERO"))

    def read(self) -> InterferometerReading:
        self._command(Command("READ"))
        return self._next_sample()

    def average(self, duration_s: float) -> InterferometerReading:
        """Mean of the streamed samples that cover ``duration_s`` (each covers one period)."""
        self._command(Command("STREAM", "ON"))
        try:
            samples = [self._next_streamed(), self._next_streamed()]
            while _covered_s(samples) < duration_s - _TIME_TOLERANCE_S:
                samples.append(self._next_streamed())
        finally:
            self._send(Command("STREAM", "OFF"))
            self._await_reply("STREAM")
        return mean_reading(samples)

    def _send(self, command: Command) -> None:
        line = encode_command(command)
        log.debug("%s > %r", self.device_name, line)
        try:
            self.connection.write(line)
        except (serial.SerialException, OSError) as error:
            raise TransportError(
                f"lost the connection to the {self.device_name}: {error}"
            ) from error

    def _command(self, command: Command) -> Reply:
        self._send(command)
        return self._await_reply(command.name.rstrip("?"))

    def _await_reply(self, word: str) -> Reply:
        while True:
            line = self._next_line()
            if not isinstance(line, Reply):
                continue
            if not line.ok:
                raise DeviceError(f"the {self.device_name} refused {word}: {line.text}")
            if line.text.split(" ", 1)[0].rstrip("?") == word:
                return line

    def _next_streamed(self) -> InterferometerReading:
        self.clock.await_stream()
        return self._next_sample()

    def _next_sample(self) -> InterferometerReading:
        while True:
            line = self._next_line()
            if isinstance(line, InterferometerReading):
                return line

    def _next_line(self) -> InterferometerReading | Reply:
        """The next decoded line; corrupted ones are discarded (and counted) up to a limit."""
        for _ in range(MAX_CORRUPTED_LINES + 1):
            try:
                raw = self.connection.readline()
            except (serial.SerialException, OSError) as error:
                raise TransportError(
                    f"lost the connection to the {self.device_name}: {error}"
                ) from error
            log.debug("%s < %r", self.device_name, raw)
            if not raw.endswith(b"\n"):
                raise DeviceTimeoutError(f"the {self.device_name} did not answer in time")
            try:
                return decode_line(raw)
            except FormatError as error:
                self.corrupted_lines += 1
                last = error
        raise TransportError(f"the line from the {self.device_name} is corrupted: {last}") from last


def _covered_s(samples: list[InterferometerReading]) -> float:
    """The time ``samples`` (two or more, evenly streamed) stand for: one period each, s.

    The same count as an instrument averaging ``duration_s`` at its rate takes
    (``duration_s * rate`` samples), not one more to span the duration.
    """
    span_s = samples[-1].time_s - samples[0].time_s
    return span_s * len(samples) / (len(samples) - 1)


class RecordingInterferometer(ClosesOnExit):
    """Reads another interferometer and appends every sample it returns to a stream CSV."""

    def __init__(self, inner: Interferometer, path: str | Path) -> None:
        self.inner = inner
        self.path = Path(path)
        self._file = self.path.open("w", newline="", encoding="utf-8")
        self._writer = csv.writer(self._file)
        self._writer.writerow(STREAM_HEADER)

    def zero(self) -> None:
        self.inner.zero()

    def read(self) -> InterferometerReading:
        return self._record(self.inner.read())

    def average(self, duration_s: float) -> InterferometerReading:
        return self._record(self.inner.average(duration_s))

    def close(self) -> None:
        self._file.close()

    def _record(self, reading: InterferometerReading) -> InterferometerReading:
        values = [f"{v:.4f}" for v in np.asarray(reading.channels, dtype=float)]
        self._writer.writerow([f"{reading.time_s:.6f}", *values, int(reading.beam_ok)])
        self._file.flush()
        return reading


def read_stream(path: str | Path) -> list[InterferometerReading]:
    """Read a recorded stream CSV; errors name the file and line."""
    path = Path(path)
    rows = list(csv.reader(read_text(path).splitlines()))
    if not rows or tuple(h.strip() for h in rows[0]) != STREAM_HEADER:
        raise FormatError(f"{path}: line 1: expected the header {','.join(STREAM_HEADER)}")
    readings = []
    for number, row in enumerate(rows[1:], start=2):
        if not row:
            continue
        if len(row) != len(STREAM_HEADER) or row[-1].strip() not in ("0", "1"):
            raise FormatError(f"{path}: line {number}: expected {len(STREAM_HEADER)} fields")
        try:
            values = [float(v) for v in row[:-1]]
        except ValueError as error:
            raise FormatError(f"{path}: line {number}: {error}") from error
        if not all(math.isfinite(v) for v in values):
            raise FormatError(f"{path}: line {number}: a value is not a finite number")
        beam_ok = row[-1].strip() == "1"
        readings.append(InterferometerReading(values[0], np.array(values[1:]), beam_ok))
    if not readings:
        raise FormatError(f"{path}: no samples")
    return readings


class ReplayInterferometer:
    """Plays a recorded stream back in order through the ``Interferometer`` role.

    :meth:`read` returns the next sample; :meth:`average` consumes the samples
    spanning ``duration_s`` of recorded time; :meth:`zero` makes ``linear_um``
    relative to the next sample. Reading past the end is a DeviceError.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._samples = read_stream(self.path)
        self._next = 0
        self._linear_datum_um = 0.0

    @property
    def remaining(self) -> int:
        return len(self._samples) - self._next

    def zero(self) -> None:
        self._linear_datum_um = self._peek().channels[0]

    def read(self) -> InterferometerReading:
        sample = self._peek()
        self._next += 1
        channels = sample.channels.copy()
        channels[0] -= self._linear_datum_um
        return InterferometerReading(sample.time_s, channels, sample.beam_ok)

    def average(self, duration_s: float) -> InterferometerReading:
        samples = [self.read()]
        while self.remaining and samples[-1].time_s - samples[0].time_s < duration_s:
            samples.append(self.read())
        return mean_reading(samples)

    def _peek(self) -> InterferometerReading:
        if self._next >= len(self._samples):
            raise DeviceError(f"the replayed stream {self.path} has no more samples")
        return self._samples[self._next]
