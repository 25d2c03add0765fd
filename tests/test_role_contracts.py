"""One contract per role of xmalign/roles.py, every implementation through it (issue 23,
item 4), as tests/firmware_iface/test_unit_contract.py does for the positioning units:

- machine position sources and movers: a tool point standing still, a file the CNC
  writes, the simulated CNC, the checked mover over it, the operator typing the
  position and the operator confirming while a source reports it;
- environment sources: typed values, a logger's file, the serial XC-80-class station
  (on a pty served by the simulator), the Modbus station's registers and the
  simulated station;
- clocks: the wall clock, the simulated clock and the lockstep clock.

A new implementation gets its factory in the lists below and passes the same tests.
"""

from __future__ import annotations

import math
import re
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import serial

from firmware_iface.machine_position import CheckedMover, FilePositions, OperatorPrompt
from firmware_iface.modbus import ModbusUnit
from firmware_iface.unit import AxisGroup
from firmware_iface.weather_station import (
    FileEnvironment,
    FixedEnvironment,
    ModbusWeatherStation,
    SerialWeatherStation,
    encode_registers,
)
from sim.clock import LockstepClock, SimClock
from sim.cnc import SimulatedCnc
from sim.environment import ShopClimate, SimEnvironment, SimWeatherStation
from sim.servers.weather_station import PtyStationServer
from sim.units import SimPositioningUnit, SimUnit
from sim.world import FixedPosition
from xmalign.errors import OutOfRangeError
from xmalign.formats.measurements import ENVIRONMENT_LIMITS
from xmalign.machine import Machine
from xmalign.roles import (
    Clock,
    ClosesOnExit,
    EnvironmentReading,
    EnvironmentSource,
    MachineMover,
    MachinePositionSource,
    PositioningUnit,
    WallClock,
)

START_MM = np.array([100.0, 200.0, -100.0])


@dataclass
class Position:
    role: MachinePositionSource
    #: where the source says the tool point is at the start
    start_mm: np.ndarray


def _fixed(machine: Machine, tmp_path: Path) -> Iterator[Position]:
    yield Position(FixedPosition(START_MM), START_MM)


def _file(machine: Machine, tmp_path: Path) -> Iterator[Position]:
    path = tmp_path / "position.txt"
    path.write_text("# written by the CNC\n0 0 0\n100.0, 200.0; -100.0\n")
    yield Position(FilePositions(path), START_MM)


def _cnc(machine: Machine, tmp_path: Path) -> Iterator[Position]:
    yield Position(SimulatedCnc(machine, SimClock(), START_MM), START_MM)


def _checked(machine: Machine, tmp_path: Path) -> Iterator[Position]:
    clock = SimClock()
    cnc = SimulatedCnc(machine, clock, START_MM)
    yield Position(CheckedMover(cnc, machine, "simulated CNC", clock=clock), START_MM)


def _operator_typing(machine: Machine, tmp_path: Path) -> Iterator[Position]:
    answers = iter(["100 200 -100"])
    prompt = OperatorPrompt(machine, ask=lambda text: next(answers, ""), tell=lambda text: None)
    yield Position(prompt, START_MM)


def _operator_with_source(machine: Machine, tmp_path: Path) -> Iterator[Position]:
    source = FixedPosition(START_MM)
    asked: list[np.ndarray] = []

    def tell(text: str) -> None:  # the operator reads the target and moves the machine there
        if text.startswith("Move the machine to "):
            asked.append(np.array([float(v) for v in re.findall(r"[XYZ](-?[\d.]+)", text)]))

    def ask(prompt: str) -> str:
        source.position = asked[-1]
        return ""

    yield Position(OperatorPrompt(machine, ask, tell, source=source), START_MM)


MOVERS: list[Callable[[Machine, Path], Iterator[Position]]] = [
    _cnc,
    _checked,
    _operator_typing,
    _operator_with_source,
]
POSITIONS = [_fixed, _file, *MOVERS]


@pytest.fixture(params=POSITIONS, ids=lambda f: f.__name__.lstrip("_"))
def position(request, reference_machine, tmp_path) -> Iterator[Position]:
    yield from request.param(reference_machine, tmp_path)


def test_a_position_source_reports_the_tool_point(position: Position) -> None:
    role = position.role
    assert isinstance(role, MachinePositionSource)
    first = role.position_mm()
    assert first.shape == (3,) and first.dtype == float
    np.testing.assert_allclose(first, position.start_mm, atol=1e-9)
    first[:] = 0.0  # the caller's copy
    np.testing.assert_allclose(role.position_mm(), position.start_mm, atol=1e-9)
    assert role.is_standstill() in (True, False)
    assert role.is_standstill()  # nothing was commanded: it stands


@pytest.fixture(params=MOVERS, ids=lambda f: f.__name__.lstrip("_"))
def moving(request, reference_machine, tmp_path) -> Iterator[Position]:
    yield from request.param(reference_machine, tmp_path)


def test_a_mover_stands_at_the_target_when_the_move_returns(moving: Position) -> None:
    mover = moving.role
    assert isinstance(mover, MachineMover)
    for target in ([1500.0, 700.0, -300.0], [10.0, 1400.0, -20.0]):
        mover.move_to(np.array(target), 2000.0)
        assert mover.is_standstill()
        np.testing.assert_allclose(mover.position_mm(), target, atol=0.05)


def test_a_mover_refuses_a_target_outside_the_travel(moving: Position) -> None:
    mover = moving.role
    assert isinstance(mover, MachineMover)
    with pytest.raises(OutOfRangeError, match=r"outside .*travel"):
        mover.move_to(np.array([2500.0, 700.0, -300.0]), 2000.0)
    np.testing.assert_allclose(mover.position_mm(), moving.start_mm, atol=1e-9)


def _fixed_environment(tmp_path: Path) -> Iterator[EnvironmentSource]:
    yield FixedEnvironment(21.0, 1000.0, 40.0, [20.5])


def _file_environment(tmp_path: Path) -> Iterator[EnvironmentSource]:
    path = tmp_path / "environment.txt"
    path.write_text("# logger\n21.0 1000 40 20.5\n")
    yield FileEnvironment(path)


def _simulated_station(tmp_path: Path) -> Iterator[EnvironmentSource]:
    yield SimWeatherStation(SimEnvironment(SimClock(), ShopClimate.drifting()), seed=3)


def _serial_station(tmp_path: Path) -> Iterator[EnvironmentSource]:
    station = SimWeatherStation(SimEnvironment(SimClock(), ShopClimate.drifting()), seed=3)
    server = PtyStationServer(station)
    server.start()
    try:
        with serial.Serial(server.port, timeout=1.0) as port:
            yield SerialWeatherStation(port, f"weather station on {server.port}")
    finally:
        server.stop()


class _Registers:
    """The station's input registers as a Modbus transport returns them."""

    def __init__(self) -> None:
        self.words = encode_registers(EnvironmentReading(0.0, 21.0, 1000.0, 40.0, (20.5,)))

    def read_registers(self, address: int, count: int) -> list[int]:
        return self.words[address : address + count]

    def write_registers(self, address: int, values: list[int]) -> None:
        raise AssertionError("the station is read only")


def _modbus_station(tmp_path: Path) -> Iterator[EnvironmentSource]:
    yield ModbusWeatherStation(_Registers(), SimClock())


ENVIRONMENTS: list[Callable[[Path], Iterator[EnvironmentSource]]] = [
    _fixed_environment,
    _file_environment,
    _simulated_station,
    _serial_station,
    _modbus_station,
]


@pytest.fixture(params=ENVIRONMENTS, ids=lambda f: f.__name__.lstrip("_"))
def environment(request, tmp_path) -> Iterator[EnvironmentSource]:
    yield from request.param(tmp_path)


def test_an_environment_source_reads_the_air_and_the_material(environment) -> None:
    assert isinstance(environment, EnvironmentSource)
    readings = [environment.read() for _ in range(2)]
    for reading in readings:
        assert isinstance(reading, EnvironmentReading)
        for name in ("air_temp_c", "air_pressure_hpa", "air_humidity_percent"):
            low, high = ENVIRONMENT_LIMITS[name]
            assert low <= getattr(reading, name) <= high, name
        low, high = ENVIRONMENT_LIMITS["material_temp_c"]
        assert isinstance(reading.material_temp_c, tuple) and len(reading.material_temp_c) >= 1
        assert all(low <= value <= high for value in reading.material_temp_c)
        assert math.isfinite(reading.time_s)
    assert readings[1].time_s >= readings[0].time_s


def _lockstep() -> Clock:
    return LockstepClock(start_s=5.0)


CLOCKS: list[Callable[[], Clock]] = [WallClock, SimClock, _lockstep]


@pytest.mark.parametrize("make", CLOCKS, ids=["wall", "simulated", "lockstep"])
def test_a_clock_goes_forward_by_what_is_slept(make: Callable[[], Clock]) -> None:
    clock = make()
    assert isinstance(clock, Clock)
    started_s = clock.now()
    clock.sleep(0.02)
    slept_s = clock.now() - started_s
    assert slept_s >= 0.02 - 1e-9
    before_s = clock.now()
    clock.sleep(-1.0)  # nothing to wait: it returns and time does not go back
    clock.sleep(0.0)
    assert clock.now() >= before_s
    wall_started_s = time.monotonic()
    clock.sleep(0.01)
    if not isinstance(clock, WallClock):  # simulated time costs no wall time
        assert clock.now() - before_s == pytest.approx(0.01)
        assert time.monotonic() - wall_started_s < 0.5


@pytest.mark.parametrize("make", CLOCKS, ids=["wall", "simulated", "lockstep"])
def test_a_wait_for_a_stream_announced_alone_leaves_the_time(make: Callable[[], Clock]) -> None:
    """``await_stream`` only announces the caller's wait: with nothing streamed it returns at
    once (a served stream answers it, tests/sim/test_servers.py)."""
    clock = make()
    before_s = clock.now()
    wall_started_s = time.monotonic()
    clock.await_stream()
    assert time.monotonic() - wall_started_s < 0.5
    if not isinstance(clock, WallClock):
        assert clock.now() == before_s


def test_the_simulated_unit_is_the_role_without_the_drivers_base() -> None:
    unit = SimPositioningUnit(SimUnit("launch", SimClock(), seed=1))
    assert isinstance(unit, PositioningUnit)
    assert not isinstance(unit, AxisGroup)


def test_connection_holders_close_on_leaving_a_with_block() -> None:
    assert issubclass(ModbusUnit, ClosesOnExit)
    closed: list[str] = []

    class Held(ClosesOnExit):
        def close(self) -> None:
            closed.append("closed")

    with pytest.raises(RuntimeError), Held():
        raise RuntimeError("a fault inside")
    assert closed == ["closed"]
