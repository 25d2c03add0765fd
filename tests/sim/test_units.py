import math

import numpy as np
import pytest

from firmware_iface.register_map import Control, Status, load_register_map
from sim.clock import SimClock
from sim.imperfections import UnitImperfections
from sim.units import COUNTS_PER_REV, SimPositioningUnit, SimUnit, rad_to_counts
from xmalign.errors import DeviceTimeoutError, DriveFaultError, InputError, OutOfRangeError
from xmalign.roles import PositioningUnit

RMAP = load_register_map()


def words(value):
    value &= 0xFFFFFFFF
    return [value >> 16, value & 0xFFFF]


def status(unit, n=1):
    return Status(unit.read_registers(RMAP.axis(n, "status").address, 1)[0])


def start_move(unit, n, angle_rad):
    unit.write_registers(RMAP.axis(n, "target").address, words(rad_to_counts(angle_rad)))
    unit.write_registers(RMAP.axis(n, "control").address, [Control.ENABLE | Control.UNLOCK])
    unit.write_registers(
        RMAP.axis(n, "control").address, [Control.ENABLE | Control.UNLOCK | Control.START]
    )


def test_device_registers():
    unit = SimUnit("receiver", SimClock())
    device_type, _, axis_count, _, high, low = unit.read_registers(0, 6)
    assert (device_type, axis_count) == (2, 3)
    assert (high << 16) | low == COUNTS_PER_REV
    assert SimUnit("launch").read_registers(2, 1) == [2]


def test_move_lock_and_status_sequence():
    clock = SimClock()
    unit = SimUnit("launch", clock)
    start_move(unit, 2, 0.3)
    clock.sleep(0.1)
    assert Status.MOVING in status(unit, 2) and Status.LOCKED not in status(unit, 2)
    clock.sleep(20.0)
    assert Status.IN_POSITION in status(unit, 2)
    actual = unit.read_registers(RMAP.axis(2, "actual").address, 2)
    assert (actual[0] << 16 | actual[1]) == rad_to_counts(0.3)
    unit.write_registers(RMAP.axis(2, "control").address, [Control.ENABLE])
    assert Status.LOCKED in status(unit, 2)


def test_velocity_limit_sets_the_move_time():
    clock = SimClock()
    unit = SimUnit("launch", clock)
    unit.write_registers(RMAP.axis(1, "velocity_limit").address, words(rad_to_counts(0.1)))
    start_move(unit, 1, 1.0)
    clock.sleep(9.0)
    assert Status.MOVING in status(unit)
    clock.sleep(2.0)
    assert Status.IN_POSITION in status(unit)
    with pytest.raises(OutOfRangeError):
        unit.write_registers(RMAP.axis(1, "velocity_limit").address, words(rad_to_counts(10.0)))


def test_out_of_range_target_moves_nothing():
    unit = SimUnit("launch", SimClock())
    before = unit.read_registers(16, 9)
    with pytest.raises(OutOfRangeError, match="outside"):
        unit.write_registers(RMAP.axis(2, "target").address, words(rad_to_counts(math.pi)))
    with pytest.raises(InputError, match="read-only"):  # whole write refused, control untouched
        unit.write_registers(16, [int(Control.ENABLE), 0, *words(rad_to_counts(0.1))])
    assert unit.read_registers(16, 9) == before


def test_read_only_and_unknown_registers():
    unit = SimUnit("launch", SimClock())
    with pytest.raises(InputError, match="read-only"):
        unit.write_registers(RMAP.axis(1, "status").address, [1])
    with pytest.raises(InputError):
        unit.write_registers(10, [1])
    with pytest.raises(InputError):
        unit.read_registers(40, 10)


def test_heartbeat_watchdog_stops_and_locks():
    clock = SimClock()
    unit = SimUnit("launch", clock)
    start_move(unit, 1, 2.0)
    clock.sleep(2.0)  # no heartbeat yet: the watchdog is not armed
    assert Status.MOVING in status(unit)
    unit.write_registers(3, [1])
    clock.sleep(0.4)
    unit.write_registers(3, [2])
    clock.sleep(0.4)
    assert Status.MOVING in status(unit)
    clock.sleep(0.2)
    assert status(unit) & (Status.FAULT | Status.MOVING) == Status.FAULT | Status.MOVING
    clock.sleep(1.0)
    bits = status(unit)
    assert Status.LOCKED in bits and Status.MOVING not in bits
    assert unit.read_registers(RMAP.axis(1, "fault_code").address, 1) == [4]
    # stopped where a stop begun at the expiry (t = 2.9 s) ends, however late it is looked at
    limits = unit.axes[0].limits
    v, a = limits.max_velocity_rad_s, limits.acceleration_rad_s2
    expected = v * v / (2 * a) + v * (2.9 - v / a) + v * v / (2 * a)
    assert unit.axes[0].motor_rad() == pytest.approx(expected, abs=1e-9)
    unit.write_registers(3, [3])
    unit.write_registers(16, [Control.ENABLE | Control.FAULT_RESET])
    assert unit.axes[0].fault_code == 0


def test_homing_and_not_homed_fault():
    clock = SimClock()
    unit = SimUnit("receiver", clock, seed=3, homed=False)
    start_move(unit, 1, 0.1)
    assert unit.axes[0].fault_code == 6
    unit.write_registers(16, [Control.ENABLE | Control.FAULT_RESET])
    unit.write_registers(16, [Control.ENABLE | Control.UNLOCK])
    unit.write_registers(16, [Control.ENABLE | Control.UNLOCK | Control.HOME])
    clock.sleep(5.0)
    assert Status.HOMED in status(unit)
    assert unit.reported_rad()[0] == pytest.approx(0.0, abs=1e-12)


def test_positioning_unit_role_with_imperfections():
    clock = SimClock()
    imperfections = UnitImperfections(
        encoder_noise_rad=0.0, zero_offsets_rad=np.array([1e-3, 2e-3, 3e-3]), backlash_rad=1e-4
    )
    unit = SimUnit("receiver", clock, imperfections)
    role = SimPositioningUnit(unit)
    assert isinstance(role, PositioningUnit)
    role.move_to(np.array([0.5, -0.2, 0.1]), timeout_s=60.0)
    np.testing.assert_allclose(role.angles_rad(), [0.5, -0.2, 0.1], atol=2e-6)
    np.testing.assert_allclose(
        unit.true_rad(), [0.5 + 1e-3 - 5e-5, -0.2 + 2e-3 + 5e-5, 0.1 + 3e-3 - 5e-5], atol=2e-6
    )
    role.lock()
    assert all(axis.is_locked() for axis in role.axes)
    with pytest.raises(OutOfRangeError):
        role.move_to(np.array([0.0, 2.0, 0.0]), timeout_s=60.0)
    with pytest.raises(DeviceTimeoutError):
        role.move_to(np.array([-3.0, 0.0, 0.0]), timeout_s=1.0)


def test_role_raises_drive_fault():
    clock = SimClock()
    unit = SimUnit("launch", clock)
    role = SimPositioningUnit(unit)
    unit.heartbeat(1)
    clock.sleep(1.0)
    with pytest.raises(DriveFaultError, match="heartbeat"):
        role.move_to(np.array([0.1, 0.1]), timeout_s=10.0)
