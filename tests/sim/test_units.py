import math

import numpy as np
import pytest

from firmware_iface.register_map import Control, Status, load_register_map
from sim.clock import SimClock
from sim.imperfections import UnitImperfections
from sim.units import COUNTS_PER_REV, SimPositioningUnit, SimUnit, rad_to_counts
from xmalign.errors import DeviceTimeoutError, HeartbeatError, InputError, OutOfRangeError
from xmalign.roles import PositioningUnit

RMAP = load_register_map()


def words(value):
    value &= 0xFFFFFFFF
    return [value >> 16, value & 0xFFFF]


def status(unit, n=1):
    return Status(unit.read_registers(RMAP.axis(n, "status").address, 1)[0])


class Host:
    """A host at the register level: it changes the heartbeat every 100 ms of simulated time."""

    def __init__(self, unit):
        self.unit = unit
        self.beats = 0
        self.beat()

    def beat(self):
        self.beats += 1
        self.unit.write_registers(3, [self.beats])

    def run_for(self, seconds):
        for _ in range(round(seconds / 0.1)):
            self.unit.clock.sleep(0.1)
            self.beat()


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
    host = Host(unit)
    start_move(unit, 2, 0.3)
    host.run_for(0.1)
    assert Status.MOVING in status(unit, 2) and Status.LOCKED not in status(unit, 2)
    host.run_for(20.0)
    assert Status.IN_POSITION in status(unit, 2)
    actual = unit.read_registers(RMAP.axis(2, "actual").address, 2)
    assert (actual[0] << 16 | actual[1]) == rad_to_counts(0.3)
    unit.write_registers(RMAP.axis(2, "control").address, [Control.ENABLE])
    assert Status.LOCKED in status(unit, 2)


def test_velocity_limit_sets_the_move_time():
    clock = SimClock()
    unit = SimUnit("launch", clock)
    host = Host(unit)
    unit.write_registers(RMAP.axis(1, "velocity_limit").address, words(rad_to_counts(0.1)))
    start_move(unit, 1, 1.0)
    host.run_for(9.0)
    assert Status.MOVING in status(unit)
    host.run_for(2.0)
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


@pytest.mark.parametrize("name", ["target", "velocity_limit"])
@pytest.mark.parametrize("word", [0, 1])
def test_a_32_bit_value_is_written_whole_or_refused(name, word):
    unit = SimUnit("launch", SimClock())
    Host(unit)
    address = RMAP.axis(1, name).address
    before = unit.read_registers(16, 9)
    with pytest.raises(InputError, match=f"is 32 bits: write both words \\({address}-"):
        unit.write_registers(address + word, [0x0001])
    assert unit.read_registers(16, 9) == before
    unit.write_registers(address, words(rad_to_counts(0.1)))
    assert unit.read_registers(address, 2) == words(rad_to_counts(0.1))


@pytest.mark.parametrize("bits", [1 << 7, 1 << 15, 0x0083])
def test_undefined_control_bits_are_refused(bits):
    unit = SimUnit("launch", SimClock())
    Host(unit)
    control = RMAP.axis(1, "control").address
    with pytest.raises(OutOfRangeError, match="control bits .* not defined"):
        unit.write_registers(control, [bits])
    assert unit.read_registers(control, 1) == [0]
    assert Status.ENABLED not in status(unit)


def test_read_only_and_unknown_registers():
    unit = SimUnit("launch", SimClock())
    with pytest.raises(InputError, match="read-only"):
        unit.write_registers(RMAP.axis(1, "status").address, [1])
    with pytest.raises(InputError):
        unit.write_registers(10, [1])
    with pytest.raises(InputError):
        unit.read_registers(40, 10)


def test_no_enable_before_the_first_heartbeat_and_power_on_watchdog():
    clock = SimClock()
    unit = SimUnit("launch", clock)
    start_move(unit, 1, 1.0)  # no heartbeat yet: enable and unlock are ignored
    clock.sleep(0.1)
    assert status(unit) & (Status.ENABLED | Status.MOVING | Status.LOCKED) == Status.LOCKED
    unit.write_registers(3, [0])  # the power-on value: not a change, not a heartbeat
    clock.sleep(0.35)
    bits = status(unit)
    assert Status.FAULT in bits and Status.LOCKED in bits
    assert unit.read_registers(RMAP.axis(1, "fault_code").address, 1) == [4]
    host = Host(unit)
    unit.write_registers(16, [Control.ENABLE | Control.FAULT_RESET])
    start_move(unit, 1, 0.1)
    host.run_for(0.2)
    assert Status.MOVING in status(unit)


def _full_speed_stale_heartbeat(unit, clock):
    """Axis 1 cruising at full speed when the heartbeat stops; the time of its last change."""
    host = Host(unit)
    start_move(unit, 1, 4.0)
    host.run_for(2.0)
    assert unit.axes[0].profile.state(clock.now())[1] == pytest.approx(math.radians(30.0))
    return clock.now()


@pytest.mark.parametrize("looked_at_after_s", [0.3, 0.4, 0.5, 3.0])
def test_stale_heartbeat_at_full_speed_is_stopped_and_locked_within_500_ms(looked_at_after_s):
    clock = SimClock()
    unit = SimUnit("launch", clock)
    last_beat_s = _full_speed_stale_heartbeat(unit, clock)
    clock.sleep(looked_at_after_s)
    bits = status(unit)
    if looked_at_after_s < RMAP.quick_stop_start_s:
        assert bits & (Status.MOVING | Status.FAULT) == Status.MOVING
        return
    assert Status.FAULT in bits
    assert unit.read_registers(RMAP.axis(1, "fault_code").address, 1) == [4]
    at_rest_s = unit.axes[0].profile.end_s - last_beat_s
    assert at_rest_s <= RMAP.watchdog_timeout_s
    if looked_at_after_s >= RMAP.watchdog_timeout_s:
        assert Status.LOCKED in bits and Status.MOVING not in bits
    # a quick stop begun at the expiry, however late it is looked at
    v, a = math.radians(30.0), RMAP.quick_stop_rad_s2
    assert unit.axes[0].profile.end_s == pytest.approx(
        last_beat_s + RMAP.quick_stop_start_s + v / a
    )


def test_watchdog_budget_covers_every_axis_at_full_speed():
    from sim.units import AXIS_LIMITS

    for limits in (limit for kind in AXIS_LIMITS.values() for limit in kind):
        stop_s = limits.max_velocity_rad_s / RMAP.quick_stop_rad_s2
        assert RMAP.quick_stop_start_s + stop_s <= RMAP.watchdog_timeout_s


def test_fault_reset_after_the_heartbeat_resumes():
    clock = SimClock()
    unit = SimUnit("launch", clock)
    _full_speed_stale_heartbeat(unit, clock)
    clock.sleep(1.0)
    unit.write_registers(3, [999])
    unit.write_registers(16, [Control.ENABLE | Control.FAULT_RESET])
    assert unit.axes[0].fault_code == 0
    assert Status.LOCKED in status(unit)


def _watchdog_tripped_after_one_heartbeat(unit, clock):
    unit.write_registers(3, [1])  # one heartbeat, then the host goes silent
    clock.sleep(RMAP.watchdog_timeout_s)
    assert unit.read_registers(RMAP.axis(1, "fault_code").address, 1) == [4]


def test_no_reset_nor_motion_after_a_trip_until_the_heartbeat_changes_again():
    """The sequence of the report: one heartbeat, a trip, then reset, enable, unlock,
    start with no new heartbeat moved 90 deg at full speed. Now nothing moves."""
    clock = SimClock()
    unit = SimUnit("launch", clock)
    _watchdog_tripped_after_one_heartbeat(unit, clock)
    control = RMAP.axis(1, "control").address
    unit.write_registers(control, [Control.ENABLE | Control.FAULT_RESET])
    assert unit.read_registers(RMAP.axis(1, "fault_code").address, 1) == [4]  # refused
    start_move(unit, 1, math.radians(90.0))
    clock.sleep(5.0)
    bits = status(unit)
    assert bits & (Status.ENABLED | Status.MOVING | Status.FAULT | Status.LOCKED) == (
        Status.FAULT | Status.LOCKED
    )
    assert unit.reported_rad()[0] == 0.0
    unit.write_registers(3, [1])  # the value it holds: not a change
    unit.write_registers(control, [Control.ENABLE | Control.FAULT_RESET])
    assert unit.axes[0].fault_code == 4
    # the host beats again: the reset is taken, the move runs...
    host = Host(unit)
    host.beat()
    unit.write_registers(control, [Control.ENABLE | Control.FAULT_RESET])
    assert unit.axes[0].fault_code == 0
    start_move(unit, 1, math.radians(90.0))
    host.run_for(0.5)
    assert Status.MOVING in status(unit)
    # ...and the watchdog trips again once the heartbeat goes stale again
    clock.sleep(RMAP.watchdog_timeout_s)
    bits = status(unit)
    assert Status.FAULT in bits and Status.LOCKED in bits and Status.MOVING not in bits
    assert unit.axes[0].fault_code == 4
    unit.write_registers(control, [Control.ENABLE | Control.FAULT_RESET])
    assert unit.axes[0].fault_code == 4


def test_no_track_nor_home_while_the_watchdog_is_not_armed():
    clock = SimClock()
    unit = SimUnit("launch", clock)
    _watchdog_tripped_after_one_heartbeat(unit, clock)
    control = RMAP.axis(1, "control").address
    unit.write_registers(control, [Control.ENABLE | Control.UNLOCK | Control.HOME])
    unit.write_registers(control, [Control.ENABLE | Control.UNLOCK | Control.TRACK])
    clock.sleep(1.0)
    assert unit.axes[0].fault_code == 4  # not overwritten by a track's fault 7
    assert not unit.axes[0].is_moving() and unit.read_registers(control, 1) == [0]


@pytest.mark.parametrize("stop", ["watchdog", "host stop", "unlock cleared"])
def test_an_axis_stopped_short_is_not_in_position(stop):
    """Reported: stopped at 95.18 deg of a 100 deg move by the watchdog, status 0x3b
    (in position). A stop never rewrites the target the host wrote."""
    clock = SimClock()
    unit = SimUnit("launch", clock)
    host = Host(unit)
    target_counts = rad_to_counts(math.radians(100.0))
    start_move(unit, 1, math.radians(100.0))
    host.run_for(3.0)
    control = RMAP.axis(1, "control").address
    if stop == "watchdog":
        clock.sleep(1.0)
    elif stop == "host stop":
        unit.write_registers(control, [Control.ENABLE | Control.UNLOCK | Control.STOP])
    else:
        unit.write_registers(control, [Control.ENABLE])
    if stop != "watchdog":
        host.run_for(1.0)
    bits = status(unit)
    assert Status.MOVING not in bits and Status.IN_POSITION not in bits
    assert unit.reported_rad()[0] < math.radians(99.0)
    target = unit.read_registers(RMAP.axis(1, "target").address, 2)
    assert target == words(target_counts)


def test_homing_and_not_homed_fault():
    clock = SimClock()
    unit = SimUnit("receiver", clock, seed=3, homed=False)
    host = Host(unit)
    start_move(unit, 1, 0.1)
    assert unit.axes[0].fault_code == 6
    unit.write_registers(16, [Control.ENABLE | Control.FAULT_RESET])
    unit.write_registers(16, [Control.ENABLE | Control.UNLOCK])
    unit.write_registers(16, [Control.ENABLE | Control.UNLOCK | Control.HOME])
    host.run_for(5.0)
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


def test_role_raises_heartbeat_error_when_the_host_stalls():
    clock = SimClock()
    unit = SimUnit("launch", clock)
    role = SimPositioningUnit(unit)
    role.stop_heartbeat()
    clock.sleep(1.0)  # the host does nothing for a second
    with pytest.raises(HeartbeatError, match="a1 of the simulated launch unit stopped: heartbeat"):
        role.move_to(np.array([0.1, 0.1]), timeout_s=10.0)


def test_role_opens_over_a_power_on_heartbeat_fault_and_moves_for_long():
    clock = SimClock()
    unit = SimUnit("launch", clock)
    clock.sleep(5.0)  # powered on long ago: fault 4 on every axis
    role = SimPositioningUnit(unit)
    role.stop_heartbeat()
    role.move_to(np.array([2.0, 0.5]), timeout_s=60.0)  # the calls beat while it waits
    np.testing.assert_allclose(role.angles_rad(), [2.0, 0.5], atol=1e-5)
