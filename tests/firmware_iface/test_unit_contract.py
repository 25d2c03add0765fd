"""One contract, every implementation of ``PositioningUnit``: Modbus TCP, Modbus RTU, CANopen
and the in-process simulated unit, each in front of the same simulated firmware.

The same assertions for all: the axes, opening over a power-on heartbeat fault,
moves, locking, refused targets, one deadline per move, a stale host
heartbeat reported as a ``HeartbeatError`` with every axis stopped and locked,
and a host that is alive again resetting the fault and moving on (an axis the
watchdog stopped short is not "in position").
"""

from __future__ import annotations

import math
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import canopen
import numpy as np
import pytest
from cli_helpers import free_port

from firmware_iface.canopen_axis import (
    HOST_HEARTBEAT_DATA,
    HOST_HEARTBEAT_ID,
    HOST_HEARTBEAT_PERIOD_S,
    CanopenUnit,
)
from firmware_iface.modbus import ModbusUnit, rtu_transport, tcp_transport
from sim.clock import SimClock
from sim.servers.canopen_node import CanopenUnitServer
from sim.servers.modbus import ModbusRtuUnitServer, ModbusUnitServer
from sim.units import SimPositioningUnit, SimUnit
from xmalign.errors import DeviceTimeoutError, DriveFaultError, HeartbeatError, OutOfRangeError
from xmalign.roles import Clock, PositioningUnit

KIND = "launch"


@dataclass
class Implementation:
    role: PositioningUnit
    firmware: SimUnit
    clock: Clock
    stall_heartbeat: Callable[[], None]
    resume_heartbeat: Callable[[], None]


def _powered_on_long_ago(clock: SimClock) -> SimUnit:
    firmware = SimUnit(KIND, clock, seed=7)
    clock.sleep(firmware.register_map.quick_stop_start_s + 0.01)  # the watchdog has tripped
    firmware.check_watchdog()
    assert all(axis.fault_code == 4 for axis in firmware.axes)
    return firmware


def modbus_tcp() -> Iterator[Implementation]:
    clock = SimClock(real_time=True)
    firmware = _powered_on_long_ago(clock)
    server = ModbusUnitServer(firmware, "127.0.0.1", free_port())
    server.start()
    transport = tcp_transport("127.0.0.1", server.port, "launch unit", timeout_s=2.0)
    unit = ModbusUnit(transport, expected_kind=KIND)
    unit.start_heartbeat()
    yield Implementation(unit, firmware, clock, unit.stop_heartbeat, unit.start_heartbeat)
    unit.close()
    server.stop()


def modbus_rtu() -> Iterator[Implementation]:
    clock = SimClock(real_time=True)
    firmware = _powered_on_long_ago(clock)
    server = ModbusRtuUnitServer(firmware)
    server.start()
    unit = ModbusUnit(
        rtu_transport(server.serial_port, "launch unit", timeout_s=2.0), expected_kind=KIND
    )
    unit.start_heartbeat()
    yield Implementation(unit, firmware, clock, unit.stop_heartbeat, unit.start_heartbeat)
    unit.close()
    server.stop()


def canopen_nodes() -> Iterator[Implementation]:
    clock = SimClock(real_time=True)
    firmware = _powered_on_long_ago(clock)
    channel = f"xmalign-{uuid.uuid4().hex}"
    server = CanopenUnitServer([firmware], channel, "virtual")
    server.start()
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel)
    unit = CanopenUnit(network, KIND, device_name="launch unit")
    resumed = []

    def resume() -> None:  # the host's heartbeat, produced again
        resumed.append(
            network.send_periodic(HOST_HEARTBEAT_ID, HOST_HEARTBEAT_DATA, HOST_HEARTBEAT_PERIOD_S)
        )

    yield Implementation(unit, firmware, clock, unit.close, resume)
    unit.close()
    for task in resumed:
        task.stop()
    network.disconnect()
    server.stop()


def simulated() -> Iterator[Implementation]:
    clock = SimClock()  # virtual time: the same assertions, evaluated in no time
    firmware = _powered_on_long_ago(clock)
    unit = SimPositioningUnit(firmware)
    yield Implementation(
        unit, firmware, clock, unit.stop_heartbeat, lambda: firmware.keep_heartbeat(True)
    )


@pytest.fixture(params=[modbus_tcp, modbus_rtu, canopen_nodes, simulated])
def implementation(request: pytest.FixtureRequest) -> Iterator[Implementation]:
    yield from request.param()


def test_is_a_positioning_unit_with_named_axes(implementation: Implementation) -> None:
    role = implementation.role
    assert isinstance(role, PositioningUnit)
    assert role.kind == KIND
    assert [axis.name for axis in role.axes] == ["a1", "a2"]


def test_moves_after_a_power_on_heartbeat_fault_and_locks(implementation: Implementation) -> None:
    role, firmware = implementation.role, implementation.firmware
    role.move_to(np.array([0.02, -0.01]), timeout_s=5.0)
    np.testing.assert_allclose(role.angles_rad(), [0.02, -0.01], atol=1e-5)
    role.lock()
    implementation.clock.sleep(0.05)
    assert all(axis.is_locked() for axis in role.axes)
    assert all(axis.is_locked() for axis in firmware.axes)


def test_a_target_out_of_range_is_refused(implementation: Implementation) -> None:
    role, firmware = implementation.role, implementation.firmware
    with pytest.raises(OutOfRangeError, match="a2"):
        role.move_to(np.array([0.0, math.radians(120.0)]), timeout_s=5.0)
    assert not firmware.axes[1].is_moving()
    role.lock()


def test_the_timeout_is_one_deadline_for_the_whole_move(implementation: Implementation) -> None:
    role, clock = implementation.role, implementation.clock
    start_s = clock.now()
    with pytest.raises(DeviceTimeoutError):  # two long moves: each would take seconds
        role.move_to(np.array([1.5, -1.5]), timeout_s=0.3)
    # one per axis would wait twice as long
    assert 0.3 - 1e-9 <= clock.now() - start_s < 0.55
    role.lock()


def test_a_stale_heartbeat_is_a_heartbeat_error_and_locks(implementation: Implementation) -> None:
    role, firmware, clock = implementation.role, implementation.firmware, implementation.clock
    for axis, target in zip(role.axes, (1.5, -1.5), strict=True):
        axis.move_to(target)  # both axes at speed
    clock.sleep(0.3)
    implementation.stall_heartbeat()
    clock.sleep(0.7)
    with pytest.raises(HeartbeatError, match="a1 .*stopped: heartbeat watchdog expired") as error:
        role.axes[0].wait_in_position(1.0)
    assert isinstance(error.value, DriveFaultError)
    assert all(axis.is_locked() and axis.fault_code == 4 for axis in firmware.axes)


def test_a_live_host_resets_a_trip_and_moves_on(implementation: Implementation) -> None:
    """A host stalled long enough to trip the watchdog, then beating again: the fault
    reset is taken, the axis the watchdog stopped short is not in position (the
    target stays the one the host wrote), and the next move runs."""
    role, firmware, clock = implementation.role, implementation.firmware, implementation.clock
    role.axes[0].move_to(1.5)
    clock.sleep(0.3)
    implementation.stall_heartbeat()
    clock.sleep(0.7)
    with pytest.raises(HeartbeatError):
        role.axes[0].wait_in_position(1.0)
    implementation.resume_heartbeat()
    role.reset_faults()
    assert [axis.fault_code for axis in firmware.axes] == [0, 0]
    assert firmware.axes[0].target_rad == pytest.approx(1.5, abs=1e-6)
    with pytest.raises(DeviceTimeoutError):  # stopped short of 1.5 rad: never arrives
        role.axes[0].wait_in_position(0.2)
    role.move_to(np.array([0.02, -0.01]), timeout_s=10.0)
    np.testing.assert_allclose(role.angles_rad(), [0.02, -0.01], atol=1e-5)
    role.lock()


def test_an_axis_the_host_stopped_short_never_arrives(implementation: Implementation) -> None:
    """'In position' means at the target the host wrote: after a stop mid-move the wait
    runs to its deadline instead of taking the rest for arrival."""
    role, firmware, clock = implementation.role, implementation.firmware, implementation.clock
    role.axes[0].move_to(1.5)
    clock.sleep(0.3)
    role.axes[0].stop()
    clock.sleep(0.5)
    assert not firmware.axes[0].is_moving()
    with pytest.raises(DeviceTimeoutError):
        role.axes[0].wait_in_position(0.2)
    role.lock()
