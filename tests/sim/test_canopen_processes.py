"""canopen's own BaseNode402, SDO, PDO, NMT and EMCY against the nodes of
``xmalign sim serve --canopen GROUP``, a separate process, over the udp_local bus.

The client here is the ``canopen`` library unchanged (it only gets the bus object); the
server there is the command a user runs. Every check goes over the bus.
"""

from __future__ import annotations

import os
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import can
import canopen
import pytest
from can.interfaces.udp_multicast.utils import pack_message
from canopen.profiles.p402 import BaseNode402, State402

from firmware_iface.can_bus import DEFAULT_PORT, LocalUdpBus
from firmware_iface.canopen_axis import EDS_PATH

NODE_IDS = (1, 2, 3, 4, 5)
HOST_HEARTBEAT = 0x77F
FAULT_MASK, FAULT_STATE = 0x4F, 0x08
#: The served units' encoders read with 10 µrad rms noise (13 counts): "the same position"
#: within 7 sigma. A move at the speeds here covers this in a few milliseconds.
SAME_COUNTS = 100


def near(counts: int, expected: int) -> bool:
    return abs(counts - expected) <= SAME_COUNTS


@dataclass
class Frame:
    time_s: float
    can_id: int
    data: bytes


@dataclass
class Recorder(can.Listener):
    """Every frame the client's bus receives, in order."""

    frames: list[Frame] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_message_received(self, msg: can.Message) -> None:
        with self.lock:
            self.frames.append(Frame(time.monotonic(), msg.arbitration_id, bytes(msg.data)))

    def since(self, start_s: float, can_id: int | None = None) -> list[Frame]:
        with self.lock:
            return [
                f
                for f in self.frames
                if f.time_s >= start_s and (can_id is None or f.can_id == can_id)
            ]


@dataclass
class Served:
    network: canopen.Network
    nodes: dict[int, BaseNode402]
    recorder: Recorder
    at_start: list[Frame]
    states_at_start: dict[int, str]
    group: str


@pytest.fixture(scope="module")
def served() -> Iterator[Served]:
    group = "239.74.{}.{}".format(*uuid.uuid4().bytes[:2])  # a bus of its own per run
    network = canopen.Network(LocalUdpBus(group))
    network.connect()
    recorder = Recorder()
    network.notifier.add_listener(recorder)
    nodes = {node_id: BaseNode402(node_id, str(EDS_PATH)) for node_id in NODE_IDS}
    for node in nodes.values():
        network.add_node(node)
        # BaseNode402 waits 0.2-0.8 s for a state's TPDO; a loaded test machine may need longer
        node.TIMEOUT_SWITCH_STATE_SINGLE = node.TIMEOUT_SWITCH_STATE_FINAL = 3.0
        node.TIMEOUT_CHECK_TPDO = node.TIMEOUT_RESET_FAULT = 1.0
    command = [sys.executable, "-m", "xmalign", "sim", "serve", "--canopen", group]
    process = subprocess.Popen(
        command,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "COLUMNS": "200"},
    )
    try:
        lines = []
        while not any("serving" in line for line in lines):
            line = process.stdout.readline()  # type: ignore[union-attr]
            assert line, process.stderr.read()  # type: ignore[union-attr]
            lines.append(line)
        assert f"udp_local {group}:{DEFAULT_PORT} on 127.0.0.1 (TTL 0)" in "".join(lines)
        time.sleep(0.2)  # frames in flight
        at_start = recorder.since(0.0)
        states = {node_id: node.nmt.state for node_id, node in nodes.items()}
        yield Served(network, nodes, recorder, at_start, states, group)
    finally:
        process.send_signal(signal.SIGINT)
        _, errors = process.communicate(timeout=30)
        network.disconnect()
    assert process.returncode == 0, errors


def wait_until(condition: Callable[[], object], timeout_s: float = 3.0, what: str = "") -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"not within {timeout_s} s: {what}"
        time.sleep(0.01)


def sdo_state(node: BaseNode402) -> int:
    return node.sdo[0x6041].raw


class HostHeartbeat:
    """The host's heartbeat (node 127, 100 ms) while the context is open."""

    def __init__(self, network: canopen.Network) -> None:
        self.network = network

    def __enter__(self) -> HostHeartbeat:
        self.task = self.network.send_periodic(HOST_HEARTBEAT, b"\x05", 0.1)
        time.sleep(0.25)  # seen by the nodes
        return self

    def stop(self) -> None:
        self.task.stop()

    def __exit__(self, *exc: object) -> None:
        self.task.stop()


def started(node: BaseNode402) -> BaseNode402:
    """NMT start, PDO set-up as canopen reads it from the node, any fault reset."""
    node.setup_402_state_machine()  # reads the PDO configuration over SDO
    node.nmt.state = "OPERATIONAL"
    wait_until(lambda: node.tpdo_values.get(0x6041), what="a TPDO")
    if sdo_state(node) & FAULT_MASK == FAULT_STATE:  # the watchdog's fault from power-on
        node.sdo[0x6040].raw = 0x00
        node.sdo[0x6040].raw = 0x80
    wait_until(lambda: node.state == "SWITCH ON DISABLED", what="fault reset")
    return node


def test_the_nodes_boot_up_in_pre_operational_and_pdos_wait_for_nmt_start(served):
    boot_ups = {(f.can_id, f.data) for f in served.at_start if 0x701 <= f.can_id <= 0x705}
    assert boot_ups == {(0x700 + node_id, b"\x00") for node_id in NODE_IDS}
    assert set(served.states_at_start.values()) == {"PRE-OPERATIONAL"}  # canopen's reading
    assert not [f for f in served.at_start if 0x181 <= f.can_id <= 0x185 or f.can_id < 0x80]
    node = served.nodes[5]
    with HostHeartbeat(served.network):
        node.sdo[0x6040].raw = 0x00
        node.sdo[0x6040].raw = 0x80  # the power-on fault of the watchdog
        assert sdo_state(node) & FAULT_MASK == 0x40
        node.rpdo.read()
        node.rpdo[1]["Controlword"].raw = 0x06
        node.rpdo[1].transmit()  # pre-operational: the node ignores PDOs
        time.sleep(0.2)
        assert sdo_state(node) & FAULT_MASK == 0x40
        node.nmt.state = "OPERATIONAL"
        node.rpdo[1].transmit()
        wait_until(lambda: sdo_state(node) & 0x6F == 0x21, what="shutdown by RPDO 1")
        start_s = time.monotonic()
        wait_until(lambda: served.recorder.since(start_s, 0x185), what="TPDO 1 of node 5")
        start_s = time.monotonic()
        node.nmt.state = "RESET COMMUNICATION"
        wait_until(lambda: served.recorder.since(start_s, 0x705), what="a new boot-up")
        time.sleep(0.2)
        frames = [(f.can_id, f.data) for f in served.recorder.since(start_s)]
        after_boot_up = frames[frames.index((0x705, b"\x00")) + 1 :]
        assert 0x185 not in {can_id for can_id, _ in after_boot_up}  # TPDO 1 came every 50 ms
        assert sdo_state(node) & 0x6F == 0x21  # the drive kept its state
        node.nmt.state = "STOPPED"  # only NMT and heartbeat: no SDO answer, no PDO
        with pytest.raises(canopen.SdoCommunicationError):
            sdo_state(node)
        node.nmt.state = "RESET"  # reset node: the drive too
        wait_until(lambda: sdo_state(node) & FAULT_MASK == 0x40, what="switch on disabled")


def test_base_node_402_walks_the_state_machine_and_moves_by_pdo(served):
    node = served.nodes[2]
    with HostHeartbeat(served.network):
        started(node)
        assert set(node.tpdo_pointers) == {0x6041, 0x6064}
        assert set(node.rpdo_pointers) == {0x6040, 0x607A}
        for state in (
            "READY TO SWITCH ON",  # 2
            "SWITCHED ON",  # 3
            "OPERATION ENABLED",  # 4
            "SWITCHED ON",  # 5
            "READY TO SWITCH ON",  # 6
            "SWITCH ON DISABLED",  # 7
            "OPERATION ENABLED",  # 2, 3, 4
            "READY TO SWITCH ON",  # 8
            "SWITCHED ON",  # 3
            "SWITCH ON DISABLED",  # 10
            "OPERATION ENABLED",
            "SWITCH ON DISABLED",  # 9
            "READY TO SWITCH ON",
        ):
            node.state = state
            assert node.state == state  # canopen's reading of the TPDO ...
            mask, value = State402.SW_MASK[state]
            assert sdo_state(node) & mask == value  # ... and of the statusword by SDO
        node.controlword = 0x0F  # from ready to switch on: transitions 3 + 4 (CiA 402)
        wait_until(lambda: node.state == "OPERATION ENABLED", what="3 + 4")
        # the controlword went by RPDO every time: canopen never took it for a periodic PDO
        assert node.rpdo[1].period is None and not node.rpdo[1].is_periodic
        node.op_mode = "PROFILED POSITION"
        assert node.op_mode == "PROFILED POSITION"
        with pytest.raises(TypeError):  # 0x6502 says profile velocity is not supported
            node.op_mode = "PROFILED VELOCITY"
        target = node.tpdo_values[0x6064] - 300_000  # -12.9 deg
        node.rpdo_pointers[0x607A].raw = target
        node.rpdo_pointers[0x607A].pdo_parent.transmit()  # RPDO 2: the target
        node.controlword = 0x1F  # RPDO 1: new set-point
        wait_until(lambda: node.statusword & 0x1000, what="set-point acknowledge")
        node.controlword = 0x0F
        wait_until(
            lambda: node.statusword & 0x400 and near(node.tpdo_values[0x6064], target),
            timeout_s=5.0,
            what="target reached",
        )
        node.state = "SWITCHED ON"  # disable operation: stopped, brake applied
        node.op_mode = "HOMING"
        assert node.homing(timeout=5)
        node.op_mode = "CYCLIC SYNCHRONOUS VELOCITY"
        node.sdo[0x60FF].raw = 100_000
        node.state = "OPERATION ENABLED"
        wait_until(lambda: node.sdo[0x606C].raw == 100_000, what="running at 0x60FF")
        node.controlword = 0x02  # quick stop while running (11), then at rest 12 (code 2)
        wait_until(lambda: node.state == "SWITCH ON DISABLED", what="quick stop")
        moved_to = node.sdo[0x6064].raw
        time.sleep(0.2)
        assert near(node.sdo[0x6064].raw, moved_to)


def test_a_target_written_by_sdo_is_not_undone_by_a_pdo(served):
    node = served.nodes[3]
    with HostHeartbeat(served.network):
        started(node)
        node.op_mode = "PROFILED POSITION"
        node.state = "OPERATION ENABLED"
        target = node.sdo[0x6064].raw + 200_000
        node.sdo[0x607A].raw = target  # by SDO; the controlword by RPDO 1 (canopen's way)
        node.controlword = 0x1F
        wait_until(lambda: node.statusword & 0x1000, what="set-point acknowledge")
        node.controlword = 0x0F
        wait_until(lambda: node.statusword & 0x400, timeout_s=5.0, what="target reached")
        assert near(node.sdo[0x6064].raw, target)
        assert node.sdo[0x607A].raw == target
        node.state = "SWITCHED ON"


def test_profile_velocity_reads_back_what_it_takes(served):
    node = served.nodes[1]
    highest = node.sdo[0x6081].raw
    assert highest == node.object_dictionary[0x6081].max
    node.sdo[0x6081].raw = highest
    assert node.sdo[0x6081].raw == highest
    with pytest.raises(canopen.SdoAbortedError) as refused:
        node.sdo[0x6081].raw = highest + 1
    assert refused.value.code == 0x06090030


def test_heartbeat_loss_faults_and_a_reset_needs_the_heartbeat_back(served):
    node = served.nodes[4]
    with HostHeartbeat(served.network) as heartbeat:
        started(node)
        node.op_mode = "PROFILED POSITION"
        node.state = "OPERATION ENABLED"
        node.sdo[0x607A].raw = node.sdo[0x6064].raw + 2_000_000  # 86 deg at 30 deg/s
        node.controlword = 0x1F
        time.sleep(0.6)  # at full speed
        stop_s, emcy_before = time.monotonic(), len(node.emcy.log)
        heartbeat.stop()
        wait_until(lambda: node.state == "FAULT", timeout_s=1.0, what="fault")
        wait_until(lambda: node.emcy.log[emcy_before:], timeout_s=1.0, what="EMCY")
        assert [(e.code, e.register) for e in node.emcy.log[emcy_before:]] == [(0xFF04, 0x11)]
        assert node.sdo[0x603F].raw == 0xFF04
        tpdos = [
            struct.unpack("<Hi", f.data) for f in served.recorder.since(stop_s, 0x184)
        ]  # (statusword, position)
        at_rest = node.sdo[0x6064].raw
        faults = [p for word, p in tpdos if word & FAULT_MASK == FAULT_STATE]
        assert faults and all(near(p, at_rest) for p in faults)  # Fault only once at rest
        # no heartbeat: a fault reset and a move change nothing
        for word in (0x00, 0x80, 0x06, 0x07, 0x0F, 0x1F):
            node.sdo[0x6040].raw = word
        time.sleep(1.0)
        assert node.sdo[0x6041].raw & FAULT_MASK == FAULT_STATE
        assert near(node.sdo[0x6064].raw, at_rest) and node.sdo[0x603F].raw == 0xFF04
        assert len(node.emcy.log) == emcy_before + 1 and node.emcy.active  # no "error reset"
    with HostHeartbeat(served.network):  # the host is back: now the reset takes
        node.sdo[0x6040].raw = 0x00
        node.sdo[0x6040].raw = 0x80
        wait_until(lambda: node.state == "SWITCH ON DISABLED", what="fault reset")
        wait_until(lambda: not node.emcy.active, timeout_s=1.0, what="EMCY error reset")
        assert node.emcy.log[-1].code == 0x0000 and node.sdo[0x603F].raw == 0
        node.state = "OPERATION ENABLED"
        node.sdo[0x607A].raw = at_rest - 100_000
        node.controlword = 0x1F
        node.controlword = 0x0F
        wait_until(
            lambda: node.statusword & 0x400 and near(node.tpdo_values[0x6064], at_rest - 100_000),
            timeout_s=5.0,
            what="moved again",
        )
        node.state = "SWITCHED ON"


def _this_computer_off_loopback() -> str | None:
    """An IPv4 address of this computer on another interface than the loopback, if any."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.connect(("192.0.2.1", 9))  # no datagram is sent: the route picks the address
        except OSError:
            return None
        address = probe.getsockname()[0]
    return None if address.startswith("127.") else address


def test_the_nodes_answer_on_the_loopback_only(served):
    node = served.nodes[1]
    assert node.sdo[0x1000].raw == 0x00020192  # over the bus: answered
    request = can.Message(
        arbitration_id=0x601, data=b"\x40\x00\x10\x00\x00\x00\x00\x00", is_extended_id=False
    )
    addresses = ["127.0.0.1", *filter(None, [_this_computer_off_loopback()])]
    start_s = time.monotonic()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
        for address in addresses:  # an SDO request as a unicast datagram
            sender.sendto(pack_message(request), (address, DEFAULT_PORT))
    time.sleep(0.5)
    assert not served.recorder.since(start_s, 0x581)
    igmp = Path("/proc/net/igmp")
    if igmp.exists():  # Linux: which interfaces joined the group
        group = f"{struct.unpack('=I', socket.inet_aton(served.group))[0]:08X}"
        joined_on, device = set(), ""
        for line in igmp.read_text().splitlines()[1:]:
            if not line.startswith("\t"):
                device = line.split()[1]
            elif line.split()[0] == group:
                joined_on.add(device)
        assert joined_on == {"lo"}
