"""The exact register and SDO sequences of the firmware contract (docs/registers.md,
docs/canopen-axis.md), pinned with scripted protocols that fail on any other request
and on leftover steps."""

from __future__ import annotations

import math

import can
import canopen
import pytest

from firmware_iface.canopen_axis import CanopenAxis
from firmware_iface.modbus import ModbusUnit
from sim.clock import SimClock
from tests.firmware_iface.scripted import ExpectedRegisters, ExpectedSdo
from xmalign.errors import (
    DeviceError,
    DeviceTimeoutError,
    HeartbeatError,
    OutOfRangeError,
    TransportError,
)

ENABLE, UNLOCK, START, STOP, FAULT_RESET = 1, 2, 4, 8, 16
ENABLED, IN_POSITION, MOVING, FAULT, LOCKED, HOMED = 1, 2, 4, 8, 16, 32
TARGET_COUNTS = 133509  # 0.1 rad at 2**23 counts per revolution (133508.6)
OPEN_LAUNCH_UNIT = [
    ("read", 0, 1, [1]),  # device type: launch unit
    ("read", 4, 2, [0x0080, 0x0000]),  # counts per revolution, high word first
    ("read", 1, 1, [0x0100]),  # firmware version
    ("read", 2, 1, [2]),  # axis count
    ("write", 3, [1], None),  # first heartbeat: 1, never the power-on 0
    ("read", 24, 1, [4]),  # axis 1 fault code: the power-on watchdog
    # a fresh heartbeat right before the fault reset, which the unit refuses without one:
    # 1 then 2 is a change whatever value an earlier host left in the register
    ("write", 3, [2], None),
    ("write", 16, [ENABLE | FAULT_RESET], None),  # fault reset on the rising edge...
    ("write", 16, [ENABLE], None),  # ...and back, still locked
    ("read", 40, 1, [0]),  # axis 2 fault code: none
]


def opened(script: ExpectedRegisters, clock: SimClock) -> ModbusUnit:
    return ModbusUnit(script, clock=clock, poll_s=0.05)


def test_modbus_open_move_heartbeat_and_lock() -> None:
    clock = SimClock()
    move = [
        ("write", 18, [TARGET_COUNTS >> 16, TARGET_COUNTS & 0xFFFF], None),  # axis 1 target
        ("write", 16, [ENABLE | UNLOCK], None),
        ("write", 16, [ENABLE | UNLOCK | START], None),  # start acts on its rising edge
        ("write", 34, [0xFFFF, 0xFFFF], None),  # axis 2 target: -1 count, two's complement
        ("write", 32, [ENABLE | UNLOCK], None),
        ("write", 32, [ENABLE | UNLOCK | START], None),
        ("read", 17, 1, [ENABLED | MOVING | HOMED]),  # t = 0
        ("read", 17, 1, [ENABLED | MOVING | HOMED]),  # t = 0.05
        ("write", 3, [3], None),  # t = 0.1: half a heartbeat period since the last change
        ("read", 17, 1, [ENABLED | IN_POSITION | HOMED]),
        ("read", 33, 1, [ENABLED | IN_POSITION | HOMED]),
    ]
    lock = [("write", 16, [ENABLE | STOP], None), ("write", 32, [ENABLE | STOP], None)]
    with ExpectedRegisters([*OPEN_LAUNCH_UNIT, *move, *lock]) as script:
        unit = opened(script, clock)
        unit.move_to([0.1, -2 * 3.141592653589793 / 2**23], timeout_s=1.0)
        unit.lock()


def test_modbus_a_heartbeat_fault_is_read_and_named() -> None:
    clock = SimClock()
    check = [("read", 17, 1, [FAULT | LOCKED | HOMED]), ("read", 24, 1, [4])]
    with ExpectedRegisters([*OPEN_LAUNCH_UNIT, *check]) as script:
        unit = opened(script, clock)
        with pytest.raises(HeartbeatError, match="axis a1 .* heartbeat watchdog expired"):
            unit.axes[0].check()


def test_modbus_a_live_host_recovers_from_a_trip_with_a_heartbeat_before_each_reset() -> None:
    """The unit refuses a fault reset until the heartbeat changes after a trip: the
    driver changes it right before each reset, even 0 s after the last beat."""
    clock = SimClock()
    check = [("read", 17, 1, [FAULT | LOCKED | HOMED]), ("read", 24, 1, [4])]
    reset = [
        ("write", 3, [3], None),
        ("write", 16, [ENABLE | FAULT_RESET], None),
        ("write", 16, [ENABLE], None),
        ("write", 3, [4], None),
        ("write", 32, [ENABLE | FAULT_RESET], None),
        ("write", 32, [ENABLE], None),
    ]
    with ExpectedRegisters([*OPEN_LAUNCH_UNIT, *check, *reset]) as script:
        unit = opened(script, clock)
        with pytest.raises(HeartbeatError):
            unit.axes[0].check()
        unit.reset_faults()


def test_modbus_an_axis_stopped_short_never_arrives() -> None:
    """After a stop the unit keeps the host's target: at rest but not in position, the
    wait polls (and beats) to its deadline."""
    clock = SimClock()
    wait = [
        ("write", 16, [ENABLE | UNLOCK | STOP], None),
        ("read", 17, 1, [ENABLED | HOMED]),  # t = 0: at rest, short of the target
        ("read", 17, 1, [ENABLED | HOMED]),  # t = 0.05
        ("write", 3, [3], None),
        ("read", 17, 1, [ENABLED | HOMED]),  # t = 0.1: the deadline
    ]
    with ExpectedRegisters([*OPEN_LAUNCH_UNIT, *wait]) as script:
        unit = opened(script, clock)
        unit.axes[0].stop()
        with pytest.raises(DeviceTimeoutError, match="a1 .* did not reach its target in 0.1 s"):
            unit.axes[0].wait_in_position(0.1)


def test_a_leftover_step_fails() -> None:
    clock = SimClock()
    with pytest.raises(AssertionError, match="1 scripted steps left over"):  # noqa: SIM117
        with ExpectedRegisters([*OPEN_LAUNCH_UNIT, ("read", 17, 1, [0])]) as script:
            opened(script, clock)


def test_a_different_request_fails() -> None:
    with pytest.raises(AssertionError, match=r"step 1: expected \('read', 1, 1\)"):
        ModbusUnit(ExpectedRegisters([("read", 1, 1, [1])]), clock=SimClock())


def test_modbus_exception_6_names_the_other_host() -> None:
    from firmware_iface.modbus import ModbusTransport

    class Busy:
        exception_code = 6

        def isError(self) -> bool:  # noqa: N802 (pymodbus's name)
            return True

    class Client:
        connected = True

        def write_registers(self, *args: object, **kwargs: object) -> Busy:
            return Busy()

    transport = ModbusTransport(Client(), "launch unit at 10.0.0.5:502")  # type: ignore[arg-type]
    with pytest.raises(DeviceError, match="another host controls it .*exception 6"):
        transport.write_registers(3, [1])


SWITCH_ON_DISABLED, OPERATION_ENABLED = 0x0240, 0x0237


def test_cia402_profile_position_move_and_lock() -> None:
    steps = [
        ("read", 0x608F, 1, 2**23),  # encoder increments per revolution
        ("write", 0x6060, 0, 1, None),  # profile position
        ("read", 0x6041, 0, SWITCH_ON_DISABLED),
        ("write", 0x6040, 0, 0x06, None),  # shutdown (transition 2)
        ("write", 0x6040, 0, 0x07, None),  # switch on (transition 3): enabled, braked
        ("write", 0x607A, 0, TARGET_COUNTS, None),
        ("write", 0x6040, 0, 0x0F, None),  # enable operation (4): brake released
        ("write", 0x6040, 0, 0x1F, None),  # new set-point
        ("read", 0x6041, 0, OPERATION_ENABLED | 0x1000),  # set-point acknowledged
        ("write", 0x6040, 0, 0x0F, None),
        ("read", 0x6041, 0, OPERATION_ENABLED),
        ("read", 0x6041, 0, OPERATION_ENABLED | 0x0400),  # target reached
        ("write", 0x6040, 0, 0x07, None),  # disable operation (5) = lock
    ]
    with ExpectedSdo(1, steps) as node:
        axis = CanopenAxis(node, "a1", "launch unit", SimClock(), poll_s=0.01)  # type: ignore[arg-type]
        axis.move_to(0.1)
        axis.wait_in_position(1.0)
        axis.lock()


def test_cia402_heartbeat_fault_reads_the_error_code() -> None:
    steps = [
        ("read", 0x608F, 1, 2**23),
        ("read", 0x6041, 0, 0x0218),  # fault
        ("read", 0x603F, 0, 0xFF04),  # fault code 4 of registers.yaml
    ]
    with ExpectedSdo(3, steps) as node:
        axis = CanopenAxis(node, "a3", "receiver unit", SimClock())  # type: ignore[arg-type]
        with pytest.raises(HeartbeatError, match=r"a3 \(CANopen node 3\) .* stopped"):
            axis.wait_in_position(1.0)


def test_cia402_a_halted_axis_has_not_reached_its_target() -> None:
    """With halt (bit 8) set, CiA 402 sets statusword bit 10 for "velocity 0"."""
    steps = [
        ("read", 0x608F, 1, 2**23),
        ("write", 0x6040, 0, 0x010F, None),  # halt
        ("read", 0x6041, 0, OPERATION_ENABLED | 0x0400),  # t = 0: standing
        ("read", 0x6041, 0, OPERATION_ENABLED | 0x0400),  # t = 0.05
        ("read", 0x6041, 0, OPERATION_ENABLED | 0x0400),  # t = 0.1: the deadline
    ]
    with ExpectedSdo(1, steps) as node:
        axis = CanopenAxis(node, "a1", "launch unit", SimClock(), poll_s=0.05)  # type: ignore[arg-type]
        axis.stop()
        with pytest.raises(DeviceTimeoutError, match="a1 .* did not reach its target in 0.1 s"):
            axis.wait_in_position(0.1)


def test_cia402_fault_reset_waits_until_the_fault_reaction_is_over() -> None:
    steps = [
        ("read", 0x608F, 1, 2**23),
        ("read", 0x6041, 0, 0x021F),  # fault reaction active: the node takes no command
        ("read", 0x6041, 0, 0x021F),
        ("read", 0x6041, 0, 0x0218),  # fault: at rest
        ("write", 0x6040, 0, 0x00, None),
        ("write", 0x6040, 0, 0x80, None),  # fault reset on the rising edge of bit 7 (15)
        ("write", 0x6040, 0, 0x06, None),
        ("write", 0x6040, 0, 0x07, None),  # enabled, brake applied
    ]
    with ExpectedSdo(3, steps) as node:
        CanopenAxis(node, "a3", "receiver unit", SimClock()).reset_fault()  # type: ignore[arg-type]


HOME = 32


def test_modbus_home_stop_enable_and_velocity_limit() -> None:
    clock = SimClock()
    home = [
        ("write", 16, [ENABLE | UNLOCK], None),  # axis 1: unlock, then home on the rising edge
        ("write", 16, [ENABLE | UNLOCK | HOME], None),
        ("write", 32, [ENABLE | UNLOCK], None),
        ("write", 32, [ENABLE | UNLOCK | HOME], None),
        ("read", 17, 1, [ENABLED | MOVING]),
        ("read", 17, 1, [ENABLED | IN_POSITION | HOMED]),
        ("read", 33, 1, [ENABLED | IN_POSITION | HOMED]),
    ]
    others = [
        ("write", 16, [ENABLE | UNLOCK | STOP], None),  # stop: at rest, still unlocked
        ("write", 32, [ENABLE], None),  # enable: powered and locked
        ("write", 22, [0x0001, 0x0000], None),  # 65536 counts/s, high word first
    ]
    with ExpectedRegisters([*OPEN_LAUNCH_UNIT, *home, *others]) as script:
        unit = opened(script, clock)
        unit.home(timeout_s=1.0)
        unit.axes[0].stop()
        unit.axes[1].enable()
        unit.axes[0].set_velocity_limit(65536 * 2 * math.pi / 2**23)


def test_modbus_homing_that_never_ends_times_out() -> None:
    clock = SimClock()
    home = [
        ("write", 16, [ENABLE | UNLOCK], None),
        ("write", 16, [ENABLE | UNLOCK | HOME], None),
        ("write", 32, [ENABLE | UNLOCK], None),
        ("write", 32, [ENABLE | UNLOCK | HOME], None),
        ("read", 17, 1, [ENABLED | MOVING]),  # t = 0
        ("read", 17, 1, [ENABLED | MOVING]),  # t = 0.05
        ("write", 3, [3], None),  # the heartbeat goes on while waiting
        ("read", 17, 1, [ENABLED | MOVING]),  # t = 0.1: past the deadline
    ]
    with ExpectedRegisters([*OPEN_LAUNCH_UNIT, *home]) as script:
        unit = opened(script, clock)
        with pytest.raises(DeviceTimeoutError, match="axis a1 .* did not finish homing in 0.1 s"):
            unit.home(timeout_s=0.1)


def test_modbus_unknown_device_type_is_refused() -> None:
    with (
        ExpectedRegisters([("read", 0, 1, [7])]) as script,
        pytest.raises(DeviceError, match="reports an unknown device type 7"),
    ):
        ModbusUnit(script, clock=SimClock())


def test_cia402_home_on_the_current_position_and_stop() -> None:
    steps = [
        ("read", 0x608F, 1, 2**23),
        ("write", 0x6060, 0, 6, None),  # homing mode
        ("read", 0x6041, 0, 0x0233),  # switched on already: no shutdown / switch on
        ("write", 0x6040, 0, 0x0F, None),  # enable operation
        ("write", 0x6040, 0, 0x1F, None),  # start homing
        ("read", 0x6041, 0, OPERATION_ENABLED),
        ("read", 0x6041, 0, OPERATION_ENABLED | 0x1000),  # homing attained
        ("write", 0x6040, 0, 0x0F, None),
        ("write", 0x6040, 0, 0x10F, None),  # halt: at rest, the brake still released
    ]
    with ExpectedSdo(2, steps) as node:
        axis = CanopenAxis(node, "a2", "launch unit", SimClock(), poll_s=0.01)  # type: ignore[arg-type]
        axis.home(timeout_s=1.0)
        axis.stop()


@pytest.mark.parametrize(
    ("failure", "error", "fragment"),
    [
        (
            canopen.SdoAbortedError(0x06010002),
            DeviceError,
            "write of 0x6040: Code 0x06010002",
        ),
        (canopen.SdoAbortedError(0x06090030), OutOfRangeError, "refused the value: out of range"),
        (canopen.SdoCommunicationError("No SDO response"), DeviceTimeoutError, "did not answer"),
        (can.CanOperationError("bus off"), TransportError, "lost the CAN bus of axis a1"),
    ],
)
def test_cia402_sdo_failures_name_the_axis(
    failure: Exception, error: type[Exception], fragment: str
) -> None:
    steps = [("read", 0x608F, 1, 2**23), ("write", 0x6040, 0, 0x10F, failure)]
    with ExpectedSdo(1, steps) as node:
        axis = CanopenAxis(node, "a1", "launch unit", SimClock())  # type: ignore[arg-type]
        with pytest.raises(error, match=fragment):
            axis.stop()
