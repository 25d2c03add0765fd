"""The Modbus server against clients we did not write: mbpoll (Debian) and pyModbusTCP (PyPI).

Pinned: identity registers, 32-bit values high word first, exception 3 for an
out-of-range value, exception 6 for a write from a second connection while the
first one controls the unit, and control passing on when it closes; the watchdog
after a trip (no reset, no motion until the heartbeat changes again, and a trip
again when it goes stale again).
"""

import math
import shutil
import subprocess
import time

import pytest
from pyModbusTCP.client import ModbusClient

from sim.clock import SimClock
from sim.servers.modbus import ModbusUnitServer
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
