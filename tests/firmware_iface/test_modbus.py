"""The Modbus driver: register codec, firmware semantics in-process, and over TCP on loopback."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from firmware_iface.modbus import (
    ModbusTransport,
    ModbusUnit,
    decode,
    encode,
    rtu_transport,
    tcp_transport,
)
from firmware_iface.register_map import load_register_map
from sim.clock import SimClock
from sim.units import SimUnit
from xmalign.errors import (
    DeviceError,
    DriveFaultError,
    HeartbeatError,
    OutOfRangeError,
    TransportError,
)
from xmalign.safety import units_locked_on_exit

RMAP = load_register_map()


@given(st.integers(min_value=-(2**31), max_value=2**31 - 1))
def test_int32_round_trip(value: int) -> None:
    register = RMAP.axis(1, "target")
    words = encode(register, value)
    assert all(0 <= w < 2**16 for w in words)
    assert decode(register, words) == value


def test_32_bit_values_are_high_word_first() -> None:
    assert encode(RMAP.axis(1, "target"), -2) == [0xFFFF, 0xFFFE]
    assert encode(RMAP.device["counts_per_rev"], 1 << 23) == [0x0080, 0x0000]


def in_process(kind: str = "launch") -> tuple[SimUnit, ModbusUnit]:
    """The driver on a simulated unit's register API, in virtual time."""
    sim = SimUnit(kind, SimClock(), seed=3)
    return sim, ModbusUnit(sim, f"{kind} unit", clock=sim.clock)


def test_reads_the_device_and_names_axes_as_conventions() -> None:
    _, launch = in_process("launch")
    _, receiver = in_process("receiver")
    assert launch.kind == "launch" and [a.name for a in launch.axes] == ["a1", "a2"]
    assert receiver.kind == "receiver" and [a.name for a in receiver.axes] == ["a3", "a4", "a5"]
    assert launch.counts_per_rev == 1 << 23


def test_move_wait_and_lock() -> None:
    sim, unit = in_process()
    unit.move_to([0.2, -0.1], timeout_s=5.0)
    np.testing.assert_allclose(unit.angles_rad(), [0.2, -0.1], atol=2e-6)
    assert not any(axis.is_locked() for axis in unit.axes)
    unit.lock()
    sim.clock.sleep(0.5)
    assert all(axis.is_locked() for axis in unit.axes)


def test_move_refused_out_of_range_names_the_axis() -> None:
    _, unit = in_process()
    with pytest.raises(OutOfRangeError, match="axis a2 of the launch unit.*100.0000 deg"):
        unit.axes[1].move_to(math.radians(100.0))


def test_wrong_device_kind_is_refused() -> None:
    sim = SimUnit("receiver", SimClock())
    with pytest.raises(DeviceError, match="is a receiver unit, expected a launch unit"):
        ModbusUnit(sim, "launch unit", expected_kind="launch", clock=sim.clock)


def test_drive_fault_is_reported_and_reset() -> None:
    sim, unit = in_process()
    unit.axes[0].move_to(1.0)
    sim.axes[0].fault(2)
    with pytest.raises(DriveFaultError, match="axis a1 of the launch unit reports fault 2: drive"):
        unit.axes[0].wait_in_position(5.0)
    unit.reset_faults()
    unit.move_to([0.1, 0.1], timeout_s=5.0)
    np.testing.assert_allclose(unit.angles_rad(), [0.1, 0.1], atol=2e-6)


def test_stalled_heartbeat_stops_and_locks_the_axes() -> None:
    sim, unit = in_process()
    unit.axes[0].move_to(2.0)  # a long move; the host then goes silent
    sim.clock.sleep(1.0)
    with pytest.raises(HeartbeatError, match="axis a1 of the launch unit stopped: heartbeat"):
        unit.axes[0].wait_in_position(10.0)
    assert all(axis.is_locked() for axis in sim.axes)
    assert sim.axes[0].motor_rad() < 1.0


def test_tcp_round_trip_move_and_lock(served_launch) -> None:  # noqa: ANN001
    sim, server = served_launch
    transport = tcp_transport("127.0.0.1", server.port, "launch unit")
    unit = ModbusUnit(transport, expected_kind="launch")
    unit.start_heartbeat()
    try:
        with units_locked_on_exit(unit):
            unit.move_to([0.01, -0.02], timeout_s=5.0)
            np.testing.assert_allclose(unit.angles_rad(), [0.01, -0.02], atol=2e-6)
        time.sleep(0.05)
        assert all(axis.is_locked() for axis in sim.axes)
    finally:
        unit.close()


def test_connection_refused_names_the_device(free_port: int) -> None:
    transport = tcp_transport("127.0.0.1", free_port, "launch unit", timeout_s=0.2, retries=1)
    with pytest.raises(TransportError, match="launch unit at 127.0.0.1:.*"):
        ModbusUnit(transport)


def test_reconnects_after_a_dropped_connection(served_launch) -> None:  # noqa: ANN001
    _, server = served_launch
    transport = tcp_transport("127.0.0.1", server.port, "launch unit")
    unit = ModbusUnit(transport)
    transport.client.close()  # the link drops between two requests
    assert unit.axes[0].position_rad() == pytest.approx(0.0, abs=1e-4)


def test_connection_lost_mid_move_ends_locked_with_one_message(served_launch) -> None:  # noqa: ANN001
    sim, server = served_launch
    unit = ModbusUnit(
        tcp_transport("127.0.0.1", server.port, "launch unit", timeout_s=0.2, retries=1)
    )
    unit.start_heartbeat()
    try:
        with pytest.raises(TransportError) as caught, units_locked_on_exit(unit):
            unit.axes[0].move_to(1.5)
            server.stop()
            unit.axes[0].wait_in_position(5.0)
        message = str(caught.value)
        assert message.startswith("lost the connection to the launch unit at 127.0.0.1")
        assert "could not lock axis a1 of the launch unit" in message
        assert "\n" not in message
        # the firmware's watchdog stops and locks the axes once the heartbeat stops
        time.sleep(RMAP.watchdog_timeout_s + 0.6)
        sim.check_watchdog()  # the simulated firmware evaluates its state when asked
        assert all(axis.is_locked() for axis in sim.axes)
        assert sim.axes[0].fault_code == 4
    finally:
        unit.close()


def test_rtu_transport_on_a_missing_port_names_the_device(tmp_path) -> None:  # noqa: ANN001
    transport = rtu_transport(str(tmp_path / "ttyUSB9"), "receiver unit", timeout_s=0.1, retries=0)
    with pytest.raises(TransportError, match=r"receiver unit on .*ttyUSB9"):
        ModbusUnit(transport)


@pytest.mark.parametrize(
    ("code", "message"),
    [
        (2, "refused the read at register 99: no such register, .*32-bit value .*exception 2"),
        (11, "has no unit with device id 1 .*exception 11 .*check device_id"),
        (4, "answered the read at register 99 with Modbus exception 4"),
    ],
)
def test_exception_codes_are_named(code: int, message: str) -> None:
    class Refusal:
        exception_code = code

        def isError(self) -> bool:  # noqa: N802 (pymodbus's name)
            return True

    class Client:
        connected = True

        def read_holding_registers(self, *args: object, **kwargs: object) -> Refusal:
            return Refusal()

    transport = ModbusTransport(Client(), "launch unit at 10.0.0.5:502")  # type: ignore[arg-type]
    with pytest.raises(DeviceError, match=message):
        transport.read_registers(99, 1)


class _Answer:
    def __init__(self, code: int | None) -> None:
        self.exception_code = code

    def isError(self) -> bool:  # noqa: N802 (pymodbus's name)
        return self.exception_code is not None


class _Scripted:
    """A client answering writes from a script: an OSError (a timeout), or an exception code
    (None: done); it counts connects."""

    def __init__(self, script: list[object]) -> None:
        self.script, self.connected, self.connects = script, True, 0

    def connect(self) -> bool:
        self.connects += 1
        self.connected = True
        return True

    def close(self) -> None:
        self.connected = False

    def write_registers(self, *args: object, **kwargs: object) -> _Answer:
        step = self.script.pop(0)
        if isinstance(step, OSError):
            raise step
        assert step is None or isinstance(step, int)
        return _Answer(step)


def test_busy_right_after_its_own_reconnect_is_asked_again() -> None:
    """A write timed out, the transport reconnected, and the unit still holds the dropped
    connection as its owner: "busy" then is the host itself, asked again until it is free."""
    client = _Scripted([TimeoutError("no response"), 6, 6, None])
    transport = ModbusTransport(client, "launch unit at 10.0.0.5:502")  # type: ignore[arg-type]
    transport.write_registers(3, [7])
    assert client.script == [] and client.connects == 1


def test_busy_without_a_reconnect_is_another_host() -> None:
    client = _Scripted([6, None])
    transport = ModbusTransport(client, "launch unit at 10.0.0.5:502")  # type: ignore[arg-type]
    with pytest.raises(DeviceError, match="another host controls it"):
        transport.write_registers(3, [7])
    assert client.script == [None]


def test_busy_long_after_a_reconnect_is_another_host(monkeypatch: pytest.MonkeyPatch) -> None:
    client = _Scripted([TimeoutError("no response"), *[6] * 100])
    transport = ModbusTransport(client, "launch unit at 10.0.0.5:502")  # type: ignore[arg-type]
    monkeypatch.setattr("firmware_iface.modbus.BUSY_AFTER_RECONNECT_S", 0.12)
    with pytest.raises(DeviceError, match="another host controls it"):
        transport.write_registers(3, [7])
    assert 1 <= 100 - len(client.script) <= 5  # asked again for 0.12 s, every 0.05 s


class Unplugged:
    """The simulated unit's registers until ``unplugged`` is set; then every write fails."""

    def __init__(self, sim: SimUnit) -> None:
        self.sim, self.unplugged = sim, False
        self.device_name = "launch unit"

    def read_registers(self, address: int, count: int) -> list[int]:
        return self.sim.read_registers(address, count)

    def write_registers(self, address: int, values: list[int]) -> None:
        if self.unplugged:
            raise TransportError("lost the connection to the launch unit")
        self.sim.write_registers(address, values)


def test_a_failed_background_heartbeat_is_reported_on_the_next_beat() -> None:
    sim = SimUnit("launch", SimClock(real_time=True), seed=3)
    wire = Unplugged(sim)
    unit = ModbusUnit(wire, "launch unit", clock=sim.clock)
    unit.start_heartbeat()
    unit.start_heartbeat()  # already beating: no second thread
    wire.unplugged = True
    deadline = time.monotonic() + 2.0
    while unit._heartbeat_thread.is_alive() and time.monotonic() < deadline:  # it gives up
        time.sleep(0.02)
    with pytest.raises(HeartbeatError, match="heartbeat to the launch unit stalled: lost the"):
        unit.beat()
    unit.stop_heartbeat()
    unit.stop_heartbeat()  # stopped already: nothing to do


class TickingStop:
    """A stop event for the heartbeat loop: each wait advances ``clock`` by its timeout and
    counts; the ``ticks``-th wait stops the loop."""

    def __init__(self, clock: SimClock, ticks: int) -> None:
        self.clock, self.ticks, self.waits = clock, ticks, 0

    def wait(self, timeout_s: float) -> bool:
        self.clock.sleep(timeout_s)
        self.waits += 1
        return self.waits >= self.ticks


def test_the_background_heartbeat_beats_on_every_wake_a_quarter_period_apart() -> None:
    clock = SimClock()
    sim = SimUnit("launch", clock, seed=3)
    unit = ModbusUnit(sim, "launch unit", clock=clock)
    heartbeat = unit.register_map.device["heartbeat"].address
    before = sim.read_registers(heartbeat, 1)[0]
    stop = TickingStop(clock, ticks=9)
    unit._heartbeat_stop = stop  # type: ignore[assignment]
    unit._heartbeat_loop()
    # 8 wakes of 50 ms (the 9th stops): 8 beats, the value counting up by one each
    assert stop.waits == 9 and clock.now() == pytest.approx(0.45)
    assert sim.read_registers(heartbeat, 1)[0] == before + 8
