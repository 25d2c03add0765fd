"""Each server driven by an independent client over loopback / a virtual bus / a pty."""

import socket
import time
import uuid

import canopen
import numpy as np
import pytest
import serial
from pymodbus.client import ModbusTcpClient

from firmware_iface.can_bus import DEFAULT_PORT, LocalUdpBus
from firmware_iface.interferometer import SerialInterferometer, open_serial
from firmware_iface.register_map import Control, Status, load_register_map
from firmware_iface.xm_line_protocol import Reply, decode_line
from sim.clock import LockstepClock, SimClock
from sim.servers.canopen_node import EDS_PATH, CanopenUnitServer
from sim.servers.modbus import ModbusUnitServer
from sim.servers.serial_pty import PtyInterferometerServer
from sim.units import SimUnit, rad_to_counts
from sim.world import build_world
from xmalign.roles import InterferometerReading

RMAP = load_register_map()


def words(value):
    value &= 0xFFFFFFFF
    return [value >> 16, value & 0xFFFF]


def wait_for(predicate, timeout_s=5.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return False


@pytest.fixture
def modbus(free_port):
    unit = SimUnit("receiver", SimClock(real_time=True), seed=1)
    server = ModbusUnitServer(unit, "127.0.0.1", free_port)
    server.start()
    client = ModbusTcpClient("127.0.0.1", port=free_port, timeout=2)
    assert client.connect()
    yield unit, client
    client.close()
    server.stop()


def mb_status(client, n):
    return Status(
        client.read_holding_registers(
            RMAP.axis(n, "status").address, count=1, device_id=1
        ).registers[0]
    )


def test_modbus_move_lock_and_refusals(modbus):
    unit, client = modbus
    assert client.read_holding_registers(0, count=3, device_id=1).registers == [2, 256, 3]
    target = RMAP.axis(2, "target").address
    refused = client.write_registers(target, words(rad_to_counts(2.0)), device_id=1)
    assert refused.isError() and refused.exception_code == 3
    read_only = client.write_registers(RMAP.axis(2, "status").address, [1], device_id=1)
    assert read_only.isError() and read_only.exception_code == 2
    control = RMAP.axis(2, "control").address
    assert not client.write_registers(target, words(rad_to_counts(0.05)), device_id=1).isError()
    client.write_registers(control, [Control.ENABLE | Control.UNLOCK], device_id=1)
    assert Status.ENABLED not in mb_status(client, 2)  # no heartbeat yet: not enabled
    client.write_registers(3, [1], device_id=1)
    client.write_registers(control, [Control.ENABLE | Control.FAULT_RESET], device_id=1)
    client.write_registers(control, [Control.ENABLE | Control.UNLOCK], device_id=1)
    client.write_registers(control, [Control.ENABLE | Control.UNLOCK | Control.START], device_id=1)
    assert Status.MOVING in mb_status(client, 2)
    beats = iter(range(2, 1000))

    def beating_in_position():  # the host beats while it waits (the move takes 360 ms)
        client.write_registers(3, [next(beats)], device_id=1)
        return Status.IN_POSITION in mb_status(client, 2)

    assert wait_for(beating_in_position)
    actual = client.read_holding_registers(RMAP.axis(2, "actual").address, count=2, device_id=1)
    high, low = actual.registers
    assert abs((high << 16 | low) - rad_to_counts(0.05)) <= 200  # encoder noise
    client.write_registers(control, [Control.ENABLE], device_id=1)
    assert Status.LOCKED in mb_status(client, 2)


def test_modbus_heartbeat_stall_stops_and_locks(modbus):
    unit, client = modbus
    control = RMAP.axis(1, "control").address
    client.write_registers(RMAP.axis(1, "target").address, words(rad_to_counts(3.0)), device_id=1)
    client.write_registers(3, [1], device_id=1)
    client.write_registers(control, [Control.ENABLE | Control.FAULT_RESET], device_id=1)
    client.write_registers(control, [Control.ENABLE | Control.UNLOCK], device_id=1)
    client.write_registers(control, [Control.ENABLE | Control.UNLOCK | Control.START], device_id=1)
    for beat in range(2, 10):
        time.sleep(0.15)
        client.write_registers(3, [beat], device_id=1)
    last_beat_s = unit.clock.now()  # just after the unit took the last heartbeat
    assert Status.MOVING in mb_status(client, 1)
    time.sleep(0.6)
    bits = mb_status(client, 1)
    at_rest_s = unit.axes[0].profile.end_s  # the firmware's own clock: when the stop ended
    assert at_rest_s - last_beat_s < 0.5
    assert Status.FAULT in bits and Status.LOCKED in bits and Status.MOVING not in bits
    fault = client.read_holding_registers(RMAP.axis(1, "fault_code").address, count=1, device_id=1)
    assert fault.registers == [4]


def test_canopen_nodes_move_refuse_and_watch_the_heartbeat():
    clock = SimClock(real_time=True)
    units = [SimUnit("launch", clock, seed=1), SimUnit("receiver", clock, seed=2)]
    server = CanopenUnitServer(units, "xmalign-test-bus", "virtual")
    server.start()
    network = canopen.Network()
    network.connect(interface="virtual", channel="xmalign-test-bus")
    try:
        assert server.node_ids == [1, 2, 3, 4, 5]
        node = canopen.RemoteNode(4, str(EDS_PATH))
        network.add_node(node)
        # The host heartbeat from the start: on a busy computer the 500 ms of the watchdog
        # after power-on may be gone before the first SDO answers (what a unit does without
        # a heartbeat: test_cia402_node.py, on a virtual clock).
        beat = network.send_periodic(0x77F, [0x05], 0.1)
        time.sleep(0.15)
        if node.sdo[0x6041].raw & 0x08:  # powered on long ago: the watchdog's fault 4
            node.sdo[0x6040].raw = 0x80
        assert node.sdo[0x6041].raw & 0x4F == 0x40  # switch on disabled
        for word in (0x06, 0x07, 0x0F):
            node.sdo[0x6040].raw = word
        assert node.sdo[0x6041].raw & 0x6F == 0x27  # operation enabled
        with pytest.raises(canopen.SdoAbortedError) as refused:
            node.sdo[0x607A].raw = rad_to_counts(2.0)
        assert refused.value.code == 0x06090030
        node.sdo[0x607A].raw = rad_to_counts(0.04)
        node.sdo[0x6040].raw = 0x1F
        assert wait_for(lambda: node.sdo[0x6041].raw & 0x400)
        assert abs(node.sdo[0x6064].raw - rad_to_counts(0.04)) <= 200
        node.sdo[0x6040].raw = 0x07  # disable operation = lock
        assert units[1].axes[1].is_locked()
        # the host heartbeat stops while a move runs
        node.sdo[0x6040].raw = 0x0F
        node.sdo[0x607A].raw = rad_to_counts(-1.0)
        node.sdo[0x6040].raw = 0x1F
        beat.stop()
        time.sleep(1.2)
        assert node.sdo[0x6041].raw & 0x08  # fault
        assert node.sdo[0x603F].raw == 0xFF04
        assert units[1].axes[1].is_locked()
    finally:
        network.disconnect()
        server.stop()


def test_interferometer_on_a_pty(machine):
    world = build_world(machine, seed=3, real_time=True)
    server = PtyInterferometerServer(world.interferometer, rate_hz=100.0)
    server.start()
    port = serial.Serial(server.port, timeout=2.0)
    try:

        def ask(text):
            port.write(text.encode() + b"\n")
            return decode_line(port.readline())

        assert ask("ID?") == Reply(True, "ID XMALIGN-SIM XM-60 class 1.0")
        assert ask("RATE 200") == Reply(True, "RATE 200")
        assert ask("BOGUS").ok is False
        assert ask("ZERO") == Reply(True, "ZERO")
        assert ask("READ") == Reply(True, "READ")
        sample = decode_line(port.readline())
        assert isinstance(sample, InterferometerReading)
        assert abs(sample.channels[0]) < 1.0  # just zeroed: noise only
        assert ask("STREAM ON") == Reply(True, "STREAM ON")
        lines = [decode_line(port.readline()) for _ in range(40)]
        samples = [line for line in lines if isinstance(line, InterferometerReading)]
        times = np.array([s.time_s for s in samples])
        assert len(samples) >= 39 and np.all(np.diff(times) > 0)
        # about 200 samples/s: the typical spacing (a busy computer delays a few samples)
        assert 0.0025 < np.median(np.diff(times)) < 0.01
        port.write(b"STREAM OFF\n")
    finally:
        port.close()
        server.stop()


def test_a_lockstep_pty_streams_one_sample_per_wait_the_host_announces(machine):
    """On a LockstepClock the stream sends a sample only for a wait the host announces on
    its clock (``Clock.await_stream``), the time advanced one period to it: an average of
    n samples takes n periods, and no sample the host would skip is ever sent."""
    clock = LockstepClock()
    world = build_world(machine, seed=3, clock=clock)
    server = PtyInterferometerServer(world.interferometer, rate_hz=50.0, lockstep=clock)
    server.start()
    port = open_serial(server.port, timeout_s=2.0)
    host = SerialInterferometer(port, "interferometer on the pty", clock)
    try:
        reading = host.average(0.1)
        assert clock.now() == pytest.approx(0.1) and reading.time_s == pytest.approx(0.1)
        clock.await_stream()  # a wait with the stream off: nothing comes
        time.sleep(0.2)  # wall time for a stray sample to arrive, were one sent
        assert port.in_waiting == 0 and clock.now() == pytest.approx(0.1)
        assert host.read().time_s == pytest.approx(0.1)  # the READ's sample, nothing before it
        assert host.average(0.06).time_s == pytest.approx(0.16)
    finally:
        port.close()
        server.stop()


def test_canopen_over_udp_local_stays_on_the_loopback():
    group = "239.74.{}.{}".format(*uuid.uuid4().bytes[:2])  # a group of its own per run
    server = CanopenUnitServer([SimUnit("launch", SimClock(real_time=True))], group, "udp_local")
    server.start()
    network = canopen.Network(LocalUdpBus(group))
    network.connect()
    try:
        sockets = [server.network.bus._sender, network.bus._sender]
        assert [s.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL) for s in sockets] == [0, 0]
        assert server.network.bus._receiver.getsockname() == (group, DEFAULT_PORT)
        node = canopen.RemoteNode(2, str(EDS_PATH))
        network.add_node(node)
        assert node.sdo[0x6502].raw == 0x121  # frames go round on loopback
    finally:
        network.disconnect()
        server.stop()


def test_one_controlling_host_across_tcp_and_rtu(free_port):
    from pymodbus.client import ModbusSerialClient

    from sim.servers import modbus as servers

    unit = SimUnit("launch", SimClock(real_time=True))
    host = servers.ControllingHost()
    tcp = ModbusUnitServer(unit, "127.0.0.1", free_port, controlling_host=host)
    rtu = servers.ModbusRtuUnitServer(unit, controlling_host=host)
    tcp.start()
    rtu.start()
    tcp_client = ModbusTcpClient("127.0.0.1", port=free_port, timeout=2)
    rtu_client = ModbusSerialClient(rtu.serial_port, baudrate=115200, timeout=2)
    try:
        assert tcp_client.connect() and rtu_client.connect()
        assert not tcp_client.write_registers(3, [1], device_id=1).isError()
        assert rtu_client.write_registers(3, [2], device_id=1).exception_code == 6
        assert rtu_client.read_holding_registers(3, count=1, device_id=1).registers == [1]
        tcp_client.close()
        assert wait_for(lambda: not rtu_client.write_registers(3, [2], device_id=1).isError())
        assert tcp_client.connect()
        assert tcp_client.write_registers(3, [3], device_id=1).exception_code == 6
        rtu_client.read_holding_registers(0, count=1, device_id=1)  # reads do not hold the unit
        time.sleep(RMAP.watchdog_timeout_s + 0.1)  # the serial master's heartbeat went stale
        assert not tcp_client.write_registers(3, [3], device_id=1).isError()
        assert rtu_client.write_registers(3, [4], device_id=1).exception_code == 6
    finally:
        tcp_client.close()
        rtu_client.close()
        tcp.stop()
        rtu.stop()
