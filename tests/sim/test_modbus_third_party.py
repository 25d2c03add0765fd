"""The Modbus server against clients we did not write: mbpoll (Debian) and pyModbusTCP (PyPI).

Pinned: identity registers, 32-bit values high word first, exception 3 for an
out-of-range value, exception 6 for a write from a second connection while the
first one controls the unit, control passing on when it closes or when the
owner's heartbeat has been stale for the watchdog timeout; the watchdog after a
trip (no reset, no motion until the heartbeat changes again, and a trip again
when it goes stale again); the replies the Modbus specification gives (function
6 echoes the request: pyModbusTCP checks it; exception 1 for a function the unit
does not serve, 2 for one word of a 32-bit value, 3 for an undefined control
bit); on RTU (mbpoll, and raw frames with a CRC computed here) no reply to
another device id nor to a broadcast, which is not executed either.
"""

import math
import os
import select
import shutil
import struct
import subprocess
import time
import tty

import pytest
from pyModbusTCP.client import ModbusClient

from sim.clock import SimClock
from sim.servers.modbus import ModbusRtuUnitServer, ModbusUnitServer
from sim.units import COUNTS_PER_REV, SimUnit, rad_to_counts

TARGET_A4 = 16 * 2 + 2  # receiver axis 2 (a4) target, int32
CONTROL_A3, STATUS_A3, TARGET_A3, ACTUAL_A3, FAULT_A3 = 16, 17, 18, 20, 24
ENABLE, UNLOCK, START, FAULT_RESET = 1, 2, 4, 16
IN_POSITION, MOVING, FAULT, LOCKED = 2, 4, 8, 16


@pytest.fixture
def server(free_port):
    unit = SimUnit("receiver", SimClock(real_time=True), seed=1)
    server = ModbusUnitServer(unit, "127.0.0.1", free_port)
    server.start()
    yield unit, free_port
    server.stop()


needs_mbpoll = pytest.mark.skipif(
    shutil.which("mbpoll") is None, reason="mbpoll (Debian) is not installed; .ci/run installs it"
)


def mbpoll(port, *options, values=()):
    """One mbpoll request (0-based addresses, one poll); (exit code, output)."""
    command = ["mbpoll", "-m", "tcp", "-p", str(port), "-a", "1", "-0", "-1", *options]
    result = subprocess.run(
        [*command, "127.0.0.1", *values], capture_output=True, text=True, timeout=30
    )
    return result.returncode, result.stdout + result.stderr


def polled(output):
    """The ``[address]: value`` lines of mbpoll's output."""
    return {
        int(line.split("]")[0].strip("[")): int(line.split(":")[1])
        for line in output.splitlines()
        if line.startswith("[")
    }


@needs_mbpoll
def test_mbpoll_reads_identity_and_big_endian_32_bit(server):
    _, port = server
    code, output = mbpoll(port, "-r", "0", "-c", "3", "-t", "4")
    assert code == 0 and polled(output) == {0: 2, 1: 0x0100, 2: 3}
    code, output = mbpoll(port, "-r", "4", "-t", "4:int", "-B")  # high word first
    assert code == 0 and polled(output) == {4: COUNTS_PER_REV}


@needs_mbpoll
def test_mbpoll_out_of_range_is_exception_3_and_moves_nothing(server):
    unit, port = server
    code, output = mbpoll(
        port, "-r", str(TARGET_A4), "-t", "4:int", "-B", values=["--", "-100000000"]
    )
    assert code != 0 and "Illegal data value" in output
    assert unit.axes[1].target_rad == 0.0


@needs_mbpoll
def test_second_host_is_answered_exception_6_until_the_first_closes(server):
    unit, port = server
    first = ModbusClient(host="127.0.0.1", port=port, auto_open=True, auto_close=False)
    assert first.write_single_register(3, 1)  # the heartbeat: this connection controls the unit
    code, output = mbpoll(port, "-r", "3", "-t", "4", values=["7"])
    assert code != 0 and "busy" in output.lower()
    assert unit.read_registers(3, 1) == [1]
    # reads stay free for everyone
    code, output = mbpoll(port, "-r", "0", "-c", "1", "-t", "4")
    assert code == 0 and polled(output) == {0: 2}
    # a second pyModbusTCP connection is refused too, with the exception code it reports
    second = ModbusClient(host="127.0.0.1", port=port, auto_open=True, auto_close=False)
    assert second.write_single_register(3, 9) is False
    assert second.last_except == 6
    assert first.write_multiple_registers(TARGET_A4, [0x0000, 0x1000])  # the owner still writes
    first.close()
    deadline = time.monotonic() + 2.0
    while not second.write_single_register(3, 9):  # the unit is free once the owner closed
        assert time.monotonic() < deadline, f"still busy: exception {second.last_except}"
        time.sleep(0.05)
    assert unit.read_registers(3, 1) == [9]
    second.close()


def test_pymodbustcp_reads_and_is_refused_out_of_range(server):
    _, port = server
    client = ModbusClient(host="127.0.0.1", port=port, auto_open=True)
    assert client.read_holding_registers(0, 6) == [2, 0x0100, 3, 0, COUNTS_PER_REV >> 16, 0]
    assert client.write_multiple_registers(TARGET_A4, [0x7FFF, 0xFFFF]) is False
    assert client.last_except == 3
    client.close()


def _words(value):
    value &= 0xFFFFFFFF
    return [value >> 16, value & 0xFFFF]


def _wait_for(condition, timeout_s, what):
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.02)


def test_pymodbustcp_after_a_trip_nothing_moves_until_the_heartbeat_changes_again(server):
    """The reported sequence: one heartbeat, the watchdog trips, then fault reset,
    enable, unlock, start with no new heartbeat (it moved 90 deg at full speed)."""
    unit, port = server
    client = ModbusClient(host="127.0.0.1", port=port, auto_open=True, auto_close=False)
    assert client.write_multiple_registers(3, [1])
    _wait_for(lambda: client.read_holding_registers(FAULT_A3, 1) == [4], 2.0, "no trip")
    target = _words(rad_to_counts(math.radians(90.0)))
    for words in ([ENABLE | FAULT_RESET], [ENABLE], [ENABLE | UNLOCK], [ENABLE | UNLOCK | START]):
        assert client.write_multiple_registers(CONTROL_A3, words)
        if words == [ENABLE]:
            assert client.write_multiple_registers(TARGET_A3, target)
    time.sleep(0.5)
    status = client.read_holding_registers(STATUS_A3, 1)[0]
    assert status & (FAULT | LOCKED | MOVING) == FAULT | LOCKED
    assert client.read_holding_registers(FAULT_A3, 1) == [4]
    assert client.read_holding_registers(ACTUAL_A3, 2) == [0, 0]
    # the heartbeat changes: the reset is taken and the move runs
    assert client.write_multiple_registers(3, [2])
    assert client.write_multiple_registers(CONTROL_A3, [ENABLE | FAULT_RESET])
    assert client.read_holding_registers(FAULT_A3, 1) == [0]
    assert client.write_multiple_registers(CONTROL_A3, [ENABLE | UNLOCK])
    assert client.write_multiple_registers(CONTROL_A3, [ENABLE | UNLOCK | START])
    assert client.read_holding_registers(STATUS_A3, 1)[0] & MOVING
    # no further heartbeat: the watchdog trips again and the axis stops short, not in position
    _wait_for(lambda: client.read_holding_registers(FAULT_A3, 1) == [4], 2.0, "no second trip")
    _wait_for(lambda: client.read_holding_registers(STATUS_A3, 1)[0] & LOCKED, 1.0, "not locked")
    assert not client.read_holding_registers(STATUS_A3, 1)[0] & IN_POSITION
    assert client.read_holding_registers(TARGET_A3, 2) == target
    assert unit.axes[0].reported_rad() < math.radians(20.0)
    client.close()


def test_pymodbustcp_write_single_register_reply_echoes_the_request(server):
    """pyModbusTCP refuses a reply that does not echo the request ("server reply does
    not match the request"); the unit used to answer the value it kept."""
    unit, port = server
    client = ModbusClient(host="127.0.0.1", port=port, auto_open=True, auto_close=False)
    # no heartbeat yet: enable and unlock are ignored, but the write is answered as sent
    assert client.write_single_register(CONTROL_A3, ENABLE | UNLOCK) is True
    assert client.read_holding_registers(CONTROL_A3, 1) == [0]
    assert client.write_single_register(3, 1) is True
    assert client.write_single_register(CONTROL_A3, ENABLE) is True
    assert client.read_holding_registers(CONTROL_A3, 1) == [ENABLE]
    client.close()


@pytest.mark.parametrize("register", [TARGET_A3, 16 + 6])  # target, velocity_limit
def test_pymodbustcp_a_32_bit_value_is_written_whole_or_refused_with_exception_2(server, register):
    unit, port = server
    client = ModbusClient(host="127.0.0.1", port=port, auto_open=True, auto_close=False)
    before = client.read_holding_registers(register, 2)
    assert client.write_single_register(register, 0) is False
    assert client.last_except == 2
    assert client.write_multiple_registers(register + 1, [0x1000]) is False
    assert client.last_except == 2
    assert client.read_holding_registers(register, 2) == before
    assert client.write_multiple_registers(register, [0x0000, 0x1000])
    assert client.read_holding_registers(register, 2) == [0x0000, 0x1000]
    client.close()


def test_pymodbustcp_an_undefined_control_bit_is_exception_3(server):
    unit, port = server
    client = ModbusClient(host="127.0.0.1", port=port, auto_open=True, auto_close=False)
    assert client.write_single_register(3, 1)
    for bits in (1 << 7, ENABLE | 1 << 12):
        assert client.write_single_register(CONTROL_A3, bits) is False
        assert client.last_except == 3
    assert client.read_holding_registers(CONTROL_A3, 1) == [0]
    client.close()


def test_pymodbustcp_functions_the_unit_does_not_serve_are_exception_1(server):
    _, port = server
    client = ModbusClient(host="127.0.0.1", port=port, auto_open=True, auto_close=False)
    assert client.read_input_registers(0, 1) is None and client.last_except == 1
    assert client.read_coils(0, 1) is None and client.last_except == 1
    assert client.write_single_coil(0, True) is False and client.last_except == 1
    client.close()


def test_a_silent_owner_with_its_socket_open_lapses_after_the_watchdog_time(server):
    """A host that hung with its connection open used to hold the unit for ever."""
    unit, port = server
    owner = ModbusClient(host="127.0.0.1", port=port, auto_open=True, auto_close=False)
    other = ModbusClient(host="127.0.0.1", port=port, auto_open=True, auto_close=False)
    for beat in range(1, 10):  # a live owner: every other host is refused
        time.sleep(0.1)
        assert owner.write_single_register(3, beat)
        last_beat_s = time.monotonic()
        assert other.write_single_register(3, 100 + beat) is False and other.last_except == 6
    # the owner hangs, its socket open
    while not other.write_single_register(3, 200):
        assert other.last_except == 6
        assert time.monotonic() - last_beat_s < 3.0, "the silent owner still holds the unit"
        time.sleep(0.02)
    lapsed_s = time.monotonic() - last_beat_s
    assert lapsed_s >= 0.45  # the watchdog timeout, 500 ms, less the reply's way back
    assert owner.write_single_register(3, 11) is False and owner.last_except == 6
    # taking over moves nothing: the watchdog tripped with the old owner's heartbeat
    assert other.read_holding_registers(FAULT_A3, 1) == [4]
    assert other.write_single_register(3, 201)  # the new owner's own heartbeat...
    assert other.write_single_register(CONTROL_A3, ENABLE | FAULT_RESET)  # ...then the reset
    assert other.read_holding_registers(FAULT_A3, 1) == [0]
    owner.close()
    other.close()


def crc16(frame: bytes) -> bytes:
    """The Modbus RTU CRC (polynomial 0xA001 reflected, initial 0xFFFF), low byte first."""
    crc = 0xFFFF
    for byte in frame:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return struct.pack("<H", crc)


def test_the_crc_of_the_specifications_example():
    # Modbus over serial line V1.02 / common worked example: read 1 register at 0 of slave 1
    assert crc16(bytes.fromhex("010300000001")) == bytes.fromhex("840a")


@pytest.fixture
def rtu():
    unit = SimUnit("receiver", SimClock(real_time=True), seed=1)
    server = ModbusRtuUnitServer(unit, device_id=1)
    server.start()
    yield unit, server.serial_port
    server.stop()


@pytest.fixture
def line(rtu):
    """The master's end of the serial line, raw: send a frame, collect what comes back."""
    unit, port = rtu
    fd = os.open(port, os.O_RDWR | os.O_NOCTTY)
    tty.setraw(fd)

    def ask(pdu_hex: str, listen_s: float = 0.5) -> bytes:
        frame = bytes.fromhex(pdu_hex)
        os.write(fd, frame + crc16(frame))
        reply = b""
        deadline = time.monotonic() + listen_s
        while time.monotonic() < deadline:
            if select.select([fd], [], [], 0.05)[0]:
                reply += os.read(fd, 256)
        return reply

    yield unit, ask
    os.close(fd)


def framed(pdu_hex):
    frame = bytes.fromhex(pdu_hex)
    return frame + crc16(frame)


def test_rtu_answers_its_own_id_only_and_never_a_broadcast(line):
    unit, ask = line
    assert ask("010300000001") == framed("0103020002")  # id 1: device type 2 (receiver)
    assert ask("070300000001") == b""  # another device on the line: silence
    assert ask("000600030005") == b""  # a broadcast heartbeat: no reply...
    assert unit.read_registers(3, 1) == [0]  # ...and not executed
    assert ask("070600030005") == b""
    assert unit.read_registers(3, 1) == [0]


def test_rtu_replies_are_the_specified_ones(line):
    unit, ask = line
    # function 6 echoes the request, even where the unit keeps another value (no
    # heartbeat yet: enable and unlock ignored)
    assert ask("010600100003") == framed("010600100003")
    assert unit.read_registers(16, 1) == [0]
    assert ask("011000030001020001") == framed("011000030001")  # function 16: address, count
    assert ask("010600120000") == framed("018602")  # one word of the 32-bit target
    assert ask("010600100080") == framed("018603")  # an undefined control bit
    assert ask("010400000001") == framed("018401")  # input registers: not served
    assert ask("010300000000") == framed("018303")  # a count outside 1..125


def mbpoll_rtu(port, device_id, *options, values=()):
    command = ["mbpoll", "-m", "rtu", "-b", "115200", "-P", "none", "-a", str(device_id)]
    command += ["-0", "-1", "-o", "0.5", *options, port, *values]
    result = subprocess.run(command, capture_output=True, text=True, timeout=30)
    return result.returncode, result.stdout + result.stderr


@needs_mbpoll
def test_mbpoll_rtu_other_id_times_out_and_half_a_target_is_refused(rtu):
    unit, port = rtu
    code, output = mbpoll_rtu(port, 1, "-r", "0", "-c", "3", "-t", "4")
    assert code == 0 and polled(output) == {0: 2, 1: 0x0100, 2: 3}
    code, output = mbpoll_rtu(port, 7, "-r", "0", "-c", "1", "-t", "4")
    assert code != 0 and "timed out" in output
    code, output = mbpoll_rtu(port, 1, "-r", "3", "-t", "4", values=["5"])
    assert code == 0 and unit.read_registers(3, 1) == [5]
    code, output = mbpoll_rtu(port, 1, "-r", str(TARGET_A3), "-t", "4", values=["5"])
    assert code != 0 and "Illegal data address" in output
    code, output = mbpoll_rtu(port, 1, "-r", str(TARGET_A3), "-t", "4:int", "-B", values=["5"])
    assert code == 0 and unit.read_registers(TARGET_A3, 2) == [0, 5]
