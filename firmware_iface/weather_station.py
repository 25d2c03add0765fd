"""Environment sources of ``units.yaml``: typed values, a file, a station on serial or Modbus.

Every source implements :class:`xmalign.roles.EnvironmentSource`; a sensor that
reports nothing gives NaN, a source that does not answer raises a
``TransportError``. docs/environment.md describes the ``environment:`` section,
the file format, the serial line protocol and the Modbus registers:

Serial (ASCII, ``\\n``-terminated, the checksum of docs/serial-protocol.md)::

    host:    ENV?
    station: E,<air_c>,<air_hpa>,<humidity_percent>,<material1_c>,<material2_c>,<material3_c>*HH
    host:    ID?
    station: OK ID <identification>*HH

an empty field is a sensor that gave no reading.

Modbus holding registers from 0 (one 16-bit register each; 0x8000: no reading)::

    0 air temperature, 0.01 °C (signed)     3-5 material 1-3, 0.01 °C (signed)
    1 air pressure, 0.1 hPa (unsigned)
    2 humidity, 0.01 % (unsigned)
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field

from firmware_iface.interferometer import LineConnection, open_serial
from firmware_iface.modbus import RegisterTransport, rtu_transport, tcp_transport
from firmware_iface.xm_line_protocol import checksum
from xmalign.environment import check_sensor
from xmalign.errors import DeviceTimeoutError, FormatError, TransportError
from xmalign.formats.common import StrictFileModel
from xmalign.roles import Clock, EnvironmentReading, EnvironmentSource, WallClock

_log = logging.getLogger(__name__)

MATERIAL_SENSORS = 3
#: Register value of a sensor without a reading.
NO_READING = 0x8000
#: Scale of each register (value = register / scale) and whether it is signed.
REGISTERS: tuple[tuple[str, float, bool], ...] = (
    ("air_temp_c", 100.0, True),
    ("air_pressure_hpa", 10.0, False),
    ("air_humidity_percent", 100.0, False),
    ("material_temp_c1", 100.0, True),
    ("material_temp_c2", 100.0, True),
    ("material_temp_c3", 100.0, True),
)


def reading_from_values(values: Sequence[float], time_s: float) -> EnvironmentReading:
    """A reading from [air °C, hPa, %, material 1-3 °C] (NaN: no reading), trailing NaN dropped."""
    air, pressure, humidity, *material = (float(v) for v in values)
    while material and math.isnan(material[-1]):
        material.pop()
    return EnvironmentReading(time_s, air, pressure, humidity, tuple(material))


# ---------------------------------------------------------------- fixed values


class FixedEnvironment:
    """Values typed in by the operator (checked against the sensor limits)."""

    def __init__(
        self,
        air_temp_c: float,
        air_pressure_hpa: float,
        air_humidity_percent: float,
        material_temp_c: Sequence[float] = (),
        source: str = "environment",
        clock: Clock | None = None,
    ) -> None:
        self.clock = clock or WallClock()
        self.values = [
            check_sensor("air_temp_c", air_temp_c, source),
            check_sensor("air_pressure_hpa", air_pressure_hpa, source),
            check_sensor("air_humidity_percent", air_humidity_percent, source),
            *(check_sensor("material_temp_c", t, source) for t in material_temp_c),
        ]

    def read(self) -> EnvironmentReading:
        return reading_from_values(self.values, self.clock.now())


# ---------------------------------------------------------------- a file


def parse_environment_line(line: str, where: str) -> list[float]:
    """``air hPa % [m1 [m2 [m3]]]`` (spaces, commas or semicolons; ``nan`` or empty: none)."""
    fields = [f.strip() for f in line.replace(";", ",").replace("\t", " ").split(",")]
    if len(fields) == 1:
        fields = fields[0].split()
    if not 3 <= len(fields) <= 3 + MATERIAL_SENSORS:
        raise FormatError(
            f"{where}: expected 3 to 6 values 'air_c hpa humidity_percent [material_c ...]'"
        )
    try:
        return [float(f) if f else math.nan for f in fields]
    except ValueError as error:
        raise FormatError(f"{where}: {error}") from error


class FileEnvironment:
    """The last line of a text file that another program keeps up to date.

    Lines starting with ``#`` are comments. A file older than ``max_age_s``
    counts as a station that stopped answering.
    """

    def __init__(
        self, path: str | Path, max_age_s: float = 60.0, now: Callable[[], float] = time.time
    ) -> None:
        self.path = Path(path)
        self.max_age_s = max_age_s
        self._now = now

    def read(self) -> EnvironmentReading:
        try:
            modified = self.path.stat().st_mtime
            lines = self.path.read_text(encoding="utf-8-sig").splitlines()
        except OSError as error:
            raise TransportError(
                f"cannot read the environment file {self.path} ({error.strerror})"
            ) from error
        age = self._now() - modified
        if age > self.max_age_s:
            raise DeviceTimeoutError(
                f"the environment file {self.path} was not updated for {age:.0f} s"
                f" (limit {self.max_age_s:g} s)"
            )
        numbered = [
            (n, text)
            for n, text in enumerate(lines, start=1)
            if text.strip() and not text.lstrip().startswith("#")
        ]
        if not numbered:
            raise FormatError(f"{self.path}: no reading in the file")
        number, text = numbered[-1]
        return reading_from_values(
            parse_environment_line(text, f"{self.path}: line {number}"), modified
        )


# ---------------------------------------------------------------- serial line


def _frame(payload: str) -> bytes:
    data = payload.encode("ascii")
    return data + b"*" + checksum(data).encode("ascii") + b"\n"


def encode_environment(reading: EnvironmentReading) -> bytes:
    """The station's ``E`` line for a reading."""
    material = list(reading.material_temp_c) + [math.nan] * (
        MATERIAL_SENSORS - len(reading.material_temp_c)
    )
    values = [reading.air_temp_c, reading.air_pressure_hpa, reading.air_humidity_percent]
    fields = ["" if math.isnan(v) else f"{v:.3f}" for v in (*values, *material)]
    return _frame("E," + ",".join(fields))


def encode_station_reply(ok: bool, text: str) -> bytes:
    return _frame(f"{'OK' if ok else 'ERR'} {text}")


def decode_station_line(line: bytes, time_s: float) -> EnvironmentReading | str:
    """An ``E`` line as a reading, an ``OK`` line as its text; FormatError otherwise."""
    text = line.rstrip(b"\r\n")
    payload, star, received = text.rpartition(b"*")
    if not star or received.decode("ascii", "replace").upper() != checksum(payload):
        raise FormatError(f"weather station line with a bad or missing checksum: {text[:60]!r}")
    message = payload.decode("ascii", "replace")
    if message.startswith("E,"):
        fields = message.split(",")[1:]
        if len(fields) != 3 + MATERIAL_SENSORS:
            raise FormatError(f"weather station line with bad fields: {message[:60]!r}")
        return reading_from_values(parse_environment_line(",".join(fields), "station"), time_s)
    status, _, rest = message.partition(" ")
    if status == "OK":
        return rest
    raise FormatError(f"weather station answered: {message[:60]!r}")


class SerialWeatherStation:
    """``EnvironmentSource`` over the serial line protocol (one query per reading)."""

    def __init__(
        self, connection: LineConnection, device_name: str, clock: Clock | None = None
    ) -> None:
        self.connection = connection
        self.device_name = device_name
        self.clock = clock or WallClock()

    def _ask(self, command: bytes) -> EnvironmentReading | str:
        self.connection.reset_input_buffer()
        self.connection.write(command)
        line = self.connection.readline()
        _log.debug("%s: %r -> %r", self.device_name, command, line)
        if not line.endswith(b"\n"):
            raise DeviceTimeoutError(f"the {self.device_name} did not answer")
        try:
            return decode_station_line(line, self.clock.now())
        except FormatError as error:
            raise TransportError(f"the {self.device_name}: {error}") from error

    def identify(self) -> str:
        answer = self._ask(b"ID?\n")
        if not isinstance(answer, str):
            raise TransportError(f"the {self.device_name} answered ID? with a reading")
        return answer.removeprefix("ID ").strip()

    def read(self) -> EnvironmentReading:
        answer = self._ask(b"ENV?\n")
        if isinstance(answer, str):
            raise TransportError(f"the {self.device_name} answered ENV? with '{answer}'")
        return answer


# ---------------------------------------------------------------- Modbus


def encode_registers(reading: EnvironmentReading) -> list[int]:
    """The six station registers of a reading."""
    material = list(reading.material_temp_c) + [math.nan] * (
        MATERIAL_SENSORS - len(reading.material_temp_c)
    )
    values = [reading.air_temp_c, reading.air_pressure_hpa, reading.air_humidity_percent]
    words = []
    for (_, scale, _signed), value in zip(REGISTERS, (*values, *material), strict=True):
        words.append(NO_READING if math.isnan(value) else round(value * scale) & 0xFFFF)
    return words


def decode_registers(words: Sequence[int], time_s: float) -> EnvironmentReading:
    """A reading from the six station registers."""
    values = []
    for (_, scale, signed), word in zip(REGISTERS, words, strict=True):
        if word == NO_READING:
            values.append(math.nan)
            continue
        number = word - 0x10000 if signed and word >= 0x8000 else word
        values.append(number / scale)
    return reading_from_values(values, time_s)


class ModbusWeatherStation:
    """``EnvironmentSource`` on a Modbus station (TCP or RTU transport)."""

    def __init__(self, transport: RegisterTransport, clock: Clock | None = None) -> None:
        self.transport = transport
        self.clock = clock or WallClock()

    def read(self) -> EnvironmentReading:
        return decode_registers(self.transport.read_registers(0, len(REGISTERS)), self.clock.now())


# ---------------------------------------------------------------- units.yaml


class _Common(StrictFileModel):
    #: Station serial and sensor serials, for the calibration record.
    serial: str | None = None
    sensor_serials: dict[str, str] = {}
    method: Literal["edlen", "ciddor"] = "edlen"


class FixedEnvironmentConfig(_Common):
    source: Literal["fixed"]
    air_temp_c: float
    air_pressure_hpa: float
    air_humidity_percent: float
    material_temp_c: Annotated[list[float], Field(max_length=MATERIAL_SENSORS)] = []


class FileEnvironmentConfig(_Common):
    source: Literal["file"]
    file: Path
    max_age_s: Annotated[float, Field(gt=0)] = 60.0


class SerialStationConfig(_Common):
    source: Literal["serial"]
    port: str
    baudrate: Annotated[int, Field(gt=0)] = 9600


class ModbusTcpStationConfig(_Common):
    source: Literal["modbus-tcp"]
    host: str
    port: Annotated[int, Field(ge=1, le=65535)] = 502
    device_id: Annotated[int, Field(ge=0, le=247)] = 1


class ModbusRtuStationConfig(_Common):
    source: Literal["modbus-rtu"]
    serial_port: str
    baudrate: Annotated[int, Field(gt=0)] = 9600
    device_id: Annotated[int, Field(ge=1, le=247)] = 1


EnvironmentConfig = Annotated[
    FixedEnvironmentConfig
    | FileEnvironmentConfig
    | SerialStationConfig
    | ModbusTcpStationConfig
    | ModbusRtuStationConfig,
    Field(discriminator="source"),
]


def resolve_environment(
    config: EnvironmentConfig | None, base_dir: Path
) -> EnvironmentConfig | None:
    """A relative ``file`` is taken from the directory of ``units.yaml``."""
    if isinstance(config, FileEnvironmentConfig):
        return config.model_copy(update={"file": base_dir / config.file})
    return config


def open_environment(
    config: EnvironmentConfig, io_timeout_s: float, closers: list[Callable[[], None]]
) -> EnvironmentSource:
    """Open the source a ``units.yaml`` ``environment:`` section names."""
    if isinstance(config, FixedEnvironmentConfig):
        return FixedEnvironment(
            config.air_temp_c,
            config.air_pressure_hpa,
            config.air_humidity_percent,
            config.material_temp_c,
            "units.yaml: environment",
        )
    if isinstance(config, FileEnvironmentConfig):
        return FileEnvironment(config.file, config.max_age_s)
    if isinstance(config, SerialStationConfig):
        try:
            connection = open_serial(config.port, config.baudrate, io_timeout_s)
        except TransportError as error:
            raise TransportError(f"weather station on {config.port}: {error}") from error
        closers.append(connection.close)
        return SerialWeatherStation(connection, f"weather station on {config.port}")
    if isinstance(config, ModbusTcpStationConfig):
        transport = tcp_transport(
            config.host, config.port, "weather station", config.device_id, io_timeout_s
        )
    else:
        transport = rtu_transport(
            config.serial_port, "weather station", config.baudrate, config.device_id, io_timeout_s
        )
    closers.append(transport.close)
    return ModbusWeatherStation(transport)


def record_serials(
    instruments: dict[str, str], environment: EnvironmentConfig | None
) -> dict[str, str]:
    """Serial numbers for the calibration record from ``units.yaml``'s sections."""
    serials = dict(instruments)
    if environment is not None:
        if environment.serial:
            serials["weather station"] = environment.serial
        serials.update({f"sensor {k}": v for k, v in environment.sensor_serials.items()})
    return serials
