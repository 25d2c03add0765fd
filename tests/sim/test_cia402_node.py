"""The simulated CiA 402 node without a bus: the state diagram (canopen's table and the
CiA 402 command coding), the fault reaction on a virtual clock, and its objects.

canopen's ``BaseNode402`` driving the nodes in another process: test_canopen_processes.py.
"""

import itertools
import math

import canopen
import pytest
from canopen import SdoAbortedError
from canopen.profiles.p402 import State402

from sim.clock import SimClock
from sim.servers.canopen_node import (
    EDS_PATH,
    FAULT,
    FAULT_REACTION_ACTIVE,
    OPERATION_ENABLED,
    READY_TO_SWITCH_ON,
    STATE_BITS,
    SWITCH_ON_DISABLED,
    Cia402Axis,
    next_state,
)
from sim.units import SimUnit, rad_to_counts

OUR_STATES = set(STATE_BITS)
#: canopen's transition table lists 16 (quick stop active -> operation enabled), which CiA 402
#: allows only for quick stop option codes 5..8; the nodes have option code 2 (0x605A).
NOT_WITH_OPTION_CODE_2 = {("QUICK STOP ACTIVE", "OPERATION ENABLED")}
#: CiA 402's command coding: "switch on" with bit 3 set (0x0F) in Ready to switch on takes
#: transition 3 and then 4 (e.g. the table "3 (+4)" of the ABB FEPL-02 manual, p. 79, and
#: "Switch on + enable operation" of the Toshiba VF-S15 CANopen manual, from DSP 402 V3.0
#: table 27). canopen's table has only the single steps.
SWITCH_ON_AND_ENABLE = {("READY TO SWITCH ON", "OPERATION ENABLED"): 0x0F}
COMMANDS = sorted({*State402.TRANSITIONTABLE.values(), 0x0F, 0x07, 0x06, 0x02, 0x00, 0x80})


def diagram():
    """The commanded transitions between our states: canopen's CiA 402 table (without the
    automatic ones) and CiA 402's 3 + 4."""
    commanded = {
        pair: word
        for pair, word in State402.TRANSITIONTABLE.items()
        if set(pair) <= OUR_STATES
        and pair not in NOT_WITH_OPTION_CODE_2
        and (word != 0x00 or pair[1] == "SWITCH ON DISABLED")
    }
    return commanded | SWITCH_ON_AND_ENABLE


def test_the_diagram_has_the_fault_reaction_as_canopen_reads_it():
    for state in ("FAULT REACTION ACTIVE", "FAULT", "OPERATION ENABLED", "QUICK STOP ACTIVE"):
        mask, value = State402.SW_MASK[state]
        assert STATE_BITS[state] & mask == value
    assert STATE_BITS[FAULT_REACTION_ACTIVE] & 0x4F == 0x0F  # CiA 402: x0xx 1111


@pytest.mark.parametrize(("pair", "word"), sorted(diagram().items()))
def test_every_transition_of_the_diagram_is_taken(pair, word):
    state, target = pair
    previous = 0x00 if state == "FAULT" else 0x06  # a fault reset needs a rising edge of bit 7
    assert next_state(state, previous, word) == target


@pytest.mark.parametrize(("state", "word"), list(itertools.product(sorted(OUR_STATES), COMMANDS)))
def test_nothing_outside_the_diagram_is_taken(state, word):
    target = next_state(state, 0x00, word)
    assert target == state or diagram().get((state, target)) is not None
    if state == "FAULT":
        assert next_state(state, 0x80, 0x80) == "FAULT"  # bit 7 held high: no new edge
    if state == "FAULT REACTION ACTIVE":
        assert target == state  # it ends by itself, once the axis is at rest


def beating(unit, clock, seconds, step_s=0.1):
    """Let ``seconds`` pass with a host heartbeat every ``step_s``."""
    for _ in range(round(seconds / step_s)):
        clock.sleep(step_s)
        unit.heartbeat(unit.read_registers(3, 1)[0] % 0xFFFF + 1)


@pytest.fixture
def running():
    """Axis a1 of a launch unit on a virtual clock, moving at 30 deg/s in profile position."""
    clock = SimClock()
    unit = SimUnit("launch", clock, seed=1)
    node = Cia402Axis(unit, 1)
    unit.heartbeat(1)
    for word in (0x06, 0x0F):  # shutdown, then switch on + enable operation (3 + 4)
        node.write_controlword(word)
    assert node.state == OPERATION_ENABLED
    node.write(0x607A, 0, rad_to_counts(math.radians(120.0)))
    node.write_controlword(0x1F)
    beating(unit, clock, 1.0)
    assert unit.axes[0].is_moving()
    return clock, unit, node


def test_a_fault_shows_fault_reaction_active_until_the_axis_is_at_rest(running):
    clock, unit, node = running
    expiry_s = clock.now() + unit.register_map.quick_stop_start_s  # the heartbeat stops here
    samples = []
    while clock.now() < expiry_s + 0.3:
        clock.sleep(0.005)
        samples.append((clock.now(), node.statusword(), unit.axes[0].is_moving()))
        if node.state == FAULT_REACTION_ACTIVE:
            node.write_controlword(0x00)  # ignored while the reaction runs
            node.write_controlword(0x80)
    reacting = [t for t, word, _ in samples if word & 0x4F == 0x0F]
    # 30 deg/s to rest at the quick-stop deceleration (360 deg/s²): 83 ms of fault reaction
    stop_s = math.radians(30.0) / unit.register_map.quick_stop_rad_s2
    assert reacting[0] == pytest.approx(expiry_s, abs=0.006)
    assert reacting[-1] - reacting[0] == pytest.approx(stop_s, abs=0.011)
    assert all(not moving for _, word, moving in samples if word & 0x4F == 0x08)  # Fault at rest
    assert samples[-1][1] & 0x4F == 0x08
    assert node.read(0x603F, 0) == 0xFF04
    assert node.read(0x1001, 0) == 0x11  # generic + communication error


def test_a_fault_reset_is_refused_until_the_heartbeat_is_back(running):
    clock, unit, node = running
    clock.sleep(1.0)  # the watchdog trips: fault 4, at rest
    assert node.read(0x6041, 0) & 0x4F == 0x08
    position = node.read(0x6064, 0)
    for word in (0x00, 0x80, 0x06, 0x07, 0x0F, 0x1F):  # fault reset, then a move: refused
        node.write_controlword(word)
        assert node.state == FAULT
    clock.sleep(1.0)
    assert node.read(0x6064, 0) == position
    assert node.read(0x603F, 0) == 0xFF04
    unit.heartbeat(unit.read_registers(3, 1)[0] + 1)  # the host is back
    node.write_controlword(0x00)
    node.write_controlword(0x80)
    assert node.state == SWITCH_ON_DISABLED
    assert node.read(0x603F, 0) == 0 and node.read(0x1001, 0) == 0


def test_switch_on_and_enable_needs_the_host_heartbeat():
    unit = SimUnit("receiver", SimClock(), seed=2)
    node = Cia402Axis(unit, 2)
    node.write_controlword(0x06)
    node.write_controlword(0x0F)  # 3 + 4 refused: no host heartbeat yet
    assert node.state == READY_TO_SWITCH_ON
    unit.heartbeat(1)
    node.write_controlword(0x0F)
    assert node.state == OPERATION_ENABLED and not unit.axes[1].is_locked()


@pytest.mark.parametrize(("kind", "n"), [("launch", 1), ("launch", 2), ("receiver", 3)])
def test_profile_velocity_round_trips_within_the_eds_limits(kind, n):
    node = Cia402Axis(SimUnit(kind, SimClock()), n)
    od = canopen.import_od(str(EDS_PATH), n)[0x6081]
    highest = node.read(0x6081, 0)  # the power-on value: the axis's maximum
    assert highest == od.default == od.max == node.max_profile_velocity_counts_s()
    node.write(0x6081, 0, highest)  # what it reads back it takes
    assert node.read(0x6081, 0) == highest
    node.write(0x6081, 0, od.min)
    assert node.read(0x6081, 0) == od.min == 1
    for refused in (od.max + 1, od.min - 1):
        with pytest.raises(SdoAbortedError) as error:
            node.write(0x6081, 0, refused)
        assert error.value.code == 0x06090030
    assert node.read(0x6081, 0) == 1
