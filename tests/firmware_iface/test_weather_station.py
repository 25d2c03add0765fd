"""Environment sources: typed values, a file, the serial station (on a pty) and Modbus."""

from __future__ import annotations

import contextlib
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import serial
from hypothesis import example, given
from hypothesis import strategies as st
from scripted import ExpectedLines

from firmware_iface.config import load_units_config, parse_units_config
from firmware_iface.weather_station import (
    NO_READING,
    FileEnvironment,
    FileEnvironmentConfig,
    FixedEnvironment,
    FixedEnvironmentConfig,
    ModbusRtuStationConfig,
    ModbusTcpStationConfig,
    ModbusWeatherStation,
    SerialStationConfig,
    SerialWeatherStation,
    decode_registers,
    decode_station_line,
    encode_environment,
    encode_registers,
    open_environment,
    record_serials,
    resolve_environment,
)
from firmware_iface.xm_line_protocol import checksum
from sim.clock import SimClock
from sim.environment import ShopClimate, SimEnvironment, SimWeatherStation
from sim.servers.weather_station import PtyStationServer
from xmalign.environment import EnvironmentMonitor
from xmalign.errors import DeviceTimeoutError, FormatError, InputError, TransportError
from xmalign.roles import EnvironmentReading, EnvironmentSource

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def test_fixed_values_are_checked() -> None:
    source = FixedEnvironment(21.0, 1000.0, 40.0, [20.5, 20.7])
    assert isinstance(source, EnvironmentSource)
    assert source.read().material_temp_c == (20.5, 20.7)
    with pytest.raises(InputError, match=r"units.yaml: air_humidity_percent 120 .*\(0 to 100\)"):
        FixedEnvironment(21.0, 1000.0, 120.0, source="units.yaml")


def test_file_source_reads_the_last_line(tmp_path: Path) -> None:
    path = tmp_path / "env.txt"
    path.write_text("# logger\n20.0 1000 40\n21.5, 1001.2, 45, 20.1, , 20.3\n")
    reading = FileEnvironment(path).read()
    assert (reading.air_temp_c, reading.air_pressure_hpa, reading.air_humidity_percent) == (
        21.5,
        1001.2,
        45.0,
    )
    assert reading.material_temp_c[0] == 20.1 and math.isnan(reading.material_temp_c[1])


def test_file_source_faults(tmp_path: Path) -> None:
    path = tmp_path / "env.txt"
    with pytest.raises(TransportError, match="cannot read the environment file"):
        FileEnvironment(path).read()
    path.write_text("21.5 1001\n")
    with pytest.raises(FormatError, match="line 1: expected 3 to 6 values"):
        FileEnvironment(path).read()
    path.write_text("21.5 1001 x\n")
    with pytest.raises(FormatError, match="line 1"):
        FileEnvironment(path).read()
    path.write_text("21.5 1001 40\n")
    stale = FileEnvironment(path, max_age_s=10.0, now=lambda: path.stat().st_mtime + 30.0)
    with pytest.raises(DeviceTimeoutError, match="not updated for 30 s"):
        stale.read()


@given(
    st.floats(-20, 60),
    st.floats(600, 1100),
    st.floats(0, 100),
    st.lists(st.floats(-20, 60), max_size=3),
)
@example(0.125, 1000.0, 0.125, [0.125])  # exactly half a step: rounded to even
def test_registers_round_trip(air: float, hpa: float, rh: float, material: list[float]) -> None:
    reading = EnvironmentReading(0.0, air, hpa, rh, tuple(material))
    back = decode_registers(encode_registers(reading), 0.0)
    # within half a register step (0.01, 0.1 hPa); 0.125 -> 0.12 misses by 0.005 + 4e-18
    half_step, float_slack = 0.005, 1e-12
    assert back.air_temp_c == pytest.approx(air, abs=half_step + float_slack)
    assert back.air_pressure_hpa == pytest.approx(hpa, abs=10 * half_step + float_slack)
    assert back.air_humidity_percent == pytest.approx(rh, abs=half_step + float_slack)
    assert back.material_temp_c == pytest.approx(tuple(material), abs=half_step + float_slack)


def test_register_without_reading_is_nan() -> None:
    words = encode_registers(EnvironmentReading(0.0, math.nan, 1000.0, 50.0, (-1.5,)))
    assert words[0] == NO_READING and words[3] == (-150) & 0xFFFF
    back = decode_registers(words, 0.0)
    assert math.isnan(back.air_temp_c) and back.material_temp_c == (-1.5,)


class _Registers:
    def __init__(self, words: list[int]) -> None:
        self.words = words

    def read_registers(self, address: int, count: int) -> list[int]:
        return self.words[address : address + count]

    def write_registers(self, address: int, values: list[int]) -> None:
        raise AssertionError("the station is read only")


def test_modbus_station_reads_its_registers() -> None:
    words = encode_registers(EnvironmentReading(0.0, 22.5, 987.6, 48.0, (21.0, 21.5, 22.0)))
    reading = ModbusWeatherStation(_Registers(words)).read()
    assert reading.material_temp_c == pytest.approx((21.0, 21.5, 22.0))
    assert reading.air_pressure_hpa == pytest.approx(987.6)


@given(st.binary(max_size=80))
def test_random_bytes_give_a_format_error_or_a_reading(line: bytes) -> None:
    with contextlib.suppress(FormatError):
        decode_station_line(line, 0.0)


@given(st.integers(0, 60), st.integers(1, 255))
def test_a_damaged_byte_is_refused(position: int, flip: int) -> None:
    line = bytearray(encode_environment(EnvironmentReading(0.0, 22.5, 987.6, 48.0, (21.0,))))
    position %= len(line) - 1  # not the line end
    line[position] ^= flip
    if (
        bytes(line).upper()
        == bytes(encode_environment(EnvironmentReading(0.0, 22.5, 987.6, 48.0, (21.0,)))).upper()
    ):
        return  # only the case of a checksum digit changed
    with pytest.raises(FormatError):
        decode_station_line(bytes(line), 0.0)


def test_station_line_round_trip() -> None:
    reading = EnvironmentReading(0.0, 22.5, 987.6, 48.0, (21.0,))
    back = decode_station_line(encode_environment(reading), 0.0)
    assert back == reading


def test_serial_station_on_the_simulated_pty() -> None:
    clock = SimClock()
    station = SimWeatherStation(
        SimEnvironment(clock, ShopClimate.drifting()), material_sensors=2, seed=5
    )
    server = PtyStationServer(station)
    server.start()
    try:
        with serial.Serial(server.port, timeout=0.5) as port:
            driver = SerialWeatherStation(port, f"weather station on {server.port}")
            assert driver.identify().startswith("XMALIGN-SIM XC-80")
            reading = driver.read()
            assert reading.air_temp_c == pytest.approx(22.0, abs=0.1)
            assert len(reading.material_temp_c) == 2
            monitor = EnvironmentMonitor(driver, driver.device_name)
            monitor.prime()
            station.answering = False
            sample = monitor.sample()
            assert "did not answer" in sample.flag_text
            assert sample.values["air_temp_c"] == pytest.approx(22.0, abs=0.1)
    finally:
        server.stop()


def test_units_yaml_environment_section(tmp_path: Path) -> None:
    config = load_units_config(EXAMPLES / "units.yaml")
    assert config.environment is not None and config.environment.serial == "XC80-0042"
    assert config.instruments["interferometer"] == "XM60-1234"
    serials = record_serials(config.instruments, config.environment)
    assert serials["weather station"] == "XC80-0042" and serials["sensor air"] == "AT-1187"
    text = (EXAMPLES / "units.yaml").read_text().split("# Optional (docs/environment.md)")[0]
    path = tmp_path / "units.yaml"
    path.write_text(text + "environment:\n  source: file\n  file: env.txt\n")
    config = load_units_config(path)
    assert isinstance(config.environment, FileEnvironmentConfig)
    assert config.environment.file == tmp_path / "env.txt"
    (tmp_path / "env.txt").write_text("20 1013 50 20.1\n")
    source = open_environment(config.environment, 1.0, [])
    assert source.read().material_temp_c == (20.1,)


def test_units_yaml_bad_environment_names_the_key() -> None:
    data = {
        "format": "xmalign.units/1",
        "launch": {"transport": "modbus-tcp", "host": "h"},
        "receiver": {"transport": "modbus-tcp", "host": "h"},
        "interferometer": {"port": "/dev/null"},
        "environment": {"source": "fixed", "air_temp_c": 20, "air_pressure_hpa": 1000},
    }
    with pytest.raises(InputError, match="units.yaml.*environment.*air_humidity_percent"):
        parse_units_config(data, "units.yaml")


def test_sim_serve_station_pty() -> None:
    process = subprocess.Popen(
        [sys.executable, "-c", "from xmalign.cli import main; main()", "sim", "serve"]
        + ["--station-pty"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "COLUMNS": "200"},
    )
    try:
        lines: list[str] = []
        while not any("serving" in line for line in lines):
            line = process.stdout.readline()  # type: ignore[union-attr]
            assert line, process.stderr.read()  # type: ignore[union-attr]
            lines.append(line)
        port_path = next(line.split()[-1] for line in lines if line.startswith("weather station"))
        with serial.Serial(port_path, timeout=2.0) as port:
            reading = SerialWeatherStation(port, "station").read()
        assert 21.5 < reading.air_temp_c < 25.5 and len(reading.material_temp_c) == 3
    finally:
        process.terminate()
        process.wait(timeout=10)


def _line(payload: str) -> bytes:
    return f"{payload}*{checksum(payload.encode())}\n".encode()


def test_file_source_without_a_reading(tmp_path: Path) -> None:
    path = tmp_path / "env.txt"
    path.write_text("# logger started\n\n")
    with pytest.raises(FormatError, match="env.txt: no reading in the file"):
        FileEnvironment(path).read()


@pytest.mark.parametrize(
    ("payload", "fragment"),
    [("E,21.0,1000.0,40.0", "bad fields"), ("ERR unknown command", "answered: 'ERR unknown")],
)
def test_station_lines_with_bad_fields_or_an_error_are_refused(payload: str, fragment: str) -> None:
    with pytest.raises(FormatError, match=fragment):
        decode_station_line(_line(payload), 0.0)


def test_serial_station_faults_are_transport_errors() -> None:
    reading = encode_environment(EnvironmentReading(0.0, 21.0, 1000.0, 40.0, ()))
    steps = [
        (b"ENV?\n", b""),  # silence: the read timed out
        (b"ENV?\n", b"E,21.0*00\n"),  # damaged
        (b"ENV?\n", _line("OK busy")),
        (b"ID?\n", reading),
    ]
    with ExpectedLines(steps) as line:
        station = SerialWeatherStation(line, "weather station on /dev/ttyS9", SimClock())
        with pytest.raises(DeviceTimeoutError, match="the weather station on /dev/ttyS9 did not"):
            station.read()
        with pytest.raises(TransportError, match="bad or missing checksum"):
            station.read()
        with pytest.raises(TransportError, match="answered ENV\\? with 'busy'"):
            station.read()
        with pytest.raises(TransportError, match="answered ID\\? with a reading"):
            station.identify()


def test_open_environment_of_each_source(tmp_path: Path) -> None:
    relative = FileEnvironmentConfig(source="file", file=Path("env.txt"))
    assert resolve_environment(relative, tmp_path).file == tmp_path / "env.txt"
    closers: list = []
    station = {"source": "serial", "port": str(tmp_path / "no-such-port")}
    with pytest.raises(TransportError, match="weather station on .*no-such-port"):
        open_environment(SerialStationConfig(**station), 0.1, closers)
    tcp = ModbusTcpStationConfig(source="modbus-tcp", host="127.0.0.1", port=1)
    rtu = ModbusRtuStationConfig(source="modbus-rtu", serial_port=str(tmp_path / "rtu"))
    for source in (open_environment(tcp, 0.1, closers), open_environment(rtu, 0.1, closers)):
        assert isinstance(source, ModbusWeatherStation)
        with pytest.raises(TransportError, match="weather station"):
            source.read()
    looped = open_environment(SerialStationConfig(source="serial", port="loop://"), 0.1, closers)
    assert isinstance(looped, SerialWeatherStation)
    assert looped.device_name == "weather station on loop://"
    fixed = FixedEnvironmentConfig(
        source="fixed", air_temp_c=20.5, air_pressure_hpa=1013.0, air_humidity_percent=45.0
    )
    assert open_environment(fixed, 0.1, closers).read().air_temp_c == 20.5
    assert len(closers) == 3
    for close in closers:
        close()
