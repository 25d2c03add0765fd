"""The simulated CiA 402 nodes: the state diagram, and canopen's own BaseNode402 driving them."""

import itertools
import time
import uuid

import canopen
import pytest
from canopen.profiles.p402 import BaseNode402, State402

from sim.clock import SimClock
from sim.servers.canopen_node import EDS_PATH, STATE_BITS, CanopenUnitServer, next_state
from sim.units import SimUnit, rad_to_counts

OUR_STATES = set(STATE_BITS)
#: canopen's transition table lists 16 (quick stop active -> operation enabled), which CiA 402
#: allows only for quick stop option codes 5..8; the nodes have option code 2 (0x605A).
NOT_WITH_OPTION_CODE_2 = {("QUICK STOP ACTIVE", "OPERATION ENABLED")}
COMMANDS = sorted({*State402.TRANSITIONTABLE.values(), 0x0F, 0x07, 0x06, 0x02, 0x00, 0x80})


def diagram():
    """canopen's CiA 402 transition table, restricted to the transitions between our states."""
    return {
        pair: word
        for pair, word in State402.TRANSITIONTABLE.items()
        if set(pair) <= OUR_STATES
        and pair not in NOT_WITH_OPTION_CODE_2
        and word != 0x00
        or pair[1] == "SWITCH ON DISABLED"
        and pair[0] in OUR_STATES
        and word == 0x00
    }


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


@pytest.fixture
def bus():
    channel = f"xmalign-{uuid.uuid4().hex}"
    unit = SimUnit("launch", SimClock(real_time=True), seed=2)
    server = CanopenUnitServer([unit], channel, "virtual")
    server.start()
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel)
    node = BaseNode402(2, str(EDS_PATH))
    network.add_node(node)
    yield unit, network, node
    network.disconnect()
    server.stop()


def operational(node):
    node.nmt.state = "PRE-OPERATIONAL"
    node.setup_402_state_machine()  # reads the PDO configuration over SDO
    node.nmt.state = "OPERATIONAL"
    deadline = time.monotonic() + 2.0
    while not node.tpdo_values.get(0x6041):
        assert time.monotonic() < deadline, "no TPDO"
        time.sleep(0.01)


def test_base_node_402_sets_the_mode_enables_moves_and_locks(bus):
    unit, network, node = bus
    heartbeat = network.send_periodic(0x77F, b"\x05", 0.1)
    try:
        operational(node)
        assert set(node.tpdo_pointers) == {0x6041, 0x6064}
        assert set(node.rpdo_pointers) == {0x6040, 0x607A}
        if node.state == "FAULT":  # the unit was up for a while without a host heartbeat
            node.reset_from_fault()
        node.op_mode = "PROFILED POSITION"
        assert node.op_mode == "PROFILED POSITION"
        with pytest.raises(TypeError):  # 0x6502 says profile velocity is not supported
            node.op_mode = "PROFILED VELOCITY"
        node.state = "OPERATION ENABLED"
        assert not unit.axes[1].is_locked()
        target = rad_to_counts(-0.03)
        node.rpdo_pointers[0x607A].raw = target
        node.controlword = 0x1F  # new set-point, sent with the target in RPDO 1
        node.rpdo_pointers[0x607A].raw = target
        node.controlword = 0x0F
        deadline = time.monotonic() + 5.0
        while not node.statusword & 0x400 or abs(node.tpdo_values[0x6064] - target) > 10:
            assert time.monotonic() < deadline, hex(node.statusword)
            time.sleep(0.01)
        node.state = "SWITCHED ON"  # disable operation: stop and brake
        assert unit.axes[1].is_locked()
        node.op_mode = "HOMING"
        assert node.homing(timeout=5)
        node.op_mode = "CYCLIC SYNCHRONOUS VELOCITY"
        node.sdo[0x60FF].raw = rad_to_counts(0.2)
        node.state = "OPERATION ENABLED"
        time.sleep(0.3)
        assert node.sdo[0x606C].raw == rad_to_counts(0.2)
        node.controlword = 0x02  # quick stop while running
        deadline = time.monotonic() + 1.0
        while node.state != "SWITCH ON DISABLED":  # quick stop option code 2
            assert time.monotonic() < deadline, node.state
            time.sleep(0.01)
        assert unit.axes[1].is_locked()
    finally:
        heartbeat.stop()


def test_a_drive_refuses_to_skip_states(bus):
    unit, network, node = bus
    heartbeat = network.send_periodic(0x77F, b"\x05", 0.1)
    try:
        operational(node)
        if node.state == "FAULT":
            node.reset_from_fault()
        node.state = "SWITCH ON DISABLED"
        node.sdo[0x6040].raw = 0x0F  # enable operation from switch on disabled: ignored
        assert node.sdo[0x6041].raw & 0x4F == 0x40
        node.sdo[0x6040].raw = 0x07  # switch on from switch on disabled: ignored
        assert node.sdo[0x6041].raw & 0x4F == 0x40
        with pytest.raises(ValueError):  # canopen itself knows no such transition either
            node._change_state("OPERATION ENABLED")
        node.state = "SWITCHED ON"
        node.sdo[0x6040].raw = 0x02  # quick stop from switched on: transition 10
        assert node.sdo[0x6041].raw & 0x4F == 0x40
        assert unit.axes[1].is_locked()
    finally:
        heartbeat.stop()


def test_no_enable_without_a_host_heartbeat_and_a_stale_one_faults(bus):
    unit, network, node = bus
    operational(node)
    with pytest.raises(RuntimeError):  # stuck in ready to switch on, or in the power-on fault
        node.state = "OPERATION ENABLED"
    assert unit.axes[1].is_locked()
    heartbeat = network.send_periodic(0x77F, b"\x05", 0.1)
    time.sleep(0.15)
    if node.state == "FAULT":
        node.reset_from_fault()
    node.state = "OPERATION ENABLED"
    heartbeat.stop()
    deadline = time.monotonic() + 1.0
    while node.state != "FAULT":
        assert time.monotonic() < deadline, node.state
        time.sleep(0.01)
    assert node.sdo[0x603F].raw == 0xFF04
    assert unit.axes[1].is_locked()


def test_after_a_trip_a_fault_reset_waits_for_the_host_heartbeat(bus):
    """Reported on CANopen: fault reset and 06/07/0F/1F with no heartbeat on the bus moved
    68 deg at 20 deg/s. The reset stays refused (in Fault) until a heartbeat frame."""
    unit, network, node = bus
    heartbeat = network.send_periodic(0x77F, b"\x05", 0.1)
    time.sleep(0.15)
    heartbeat.stop()  # the host's last heartbeat
    deadline = time.monotonic() + 2.0
    while node.sdo[0x6041].raw & 0x4F != 0x08:  # Fault
        assert time.monotonic() < deadline, hex(node.sdo[0x6041].raw)
        time.sleep(0.02)
    node.sdo[0x607A].raw = rad_to_counts(1.2)
    for word in (0x00, 0x80, 0x06, 0x07, 0x0F, 0x1F):
        node.sdo[0x6040].raw = word
    time.sleep(0.5)
    assert node.sdo[0x6041].raw & 0x4F == 0x08 and node.sdo[0x603F].raw == 0xFF04
    assert not unit.axes[1].is_moving() and unit.axes[1].is_locked()
    assert node.sdo[0x6064].raw == 0
    network.send_message(0x77F, b"\x05")  # the host is back
    for word in (0x00, 0x80, 0x06, 0x07):
        node.sdo[0x6040].raw = word
    assert node.sdo[0x6041].raw & 0x6F == 0x23  # switched on
    assert node.sdo[0x603F].raw == 0
