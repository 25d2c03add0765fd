"""Every register, SDO and serial line that crosses the wire is logged at DEBUG by its driver."""

from __future__ import annotations

import logging
import uuid

import canopen
import pytest

from firmware_iface.canopen_axis import CanopenUnit
from firmware_iface.interferometer import SerialInterferometer
from firmware_iface.modbus import ModbusUnit
from firmware_iface.xm_line_protocol import Reply, encode_reply
from sim.clock import SimClock
from sim.servers.canopen_node import CanopenUnitServer
from sim.units import SimUnit
from tests.firmware_iface.test_interferometer_driver import ScriptedLine
from xmalign.cli.common import start_log_file, stop_log_file
from xmalign.errors import InputError


def messages(caplog, logger: str) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == logger]


def test_modbus_registers_are_logged_with_names_and_words(caplog) -> None:
    caplog.set_level(logging.DEBUG, logger="firmware_iface.modbus")
    unit = ModbusUnit(SimUnit("launch", SimClock()), "launch unit", clock=SimClock())
    unit.axes[0].move_to(0.1)
    logged = messages(caplog, "firmware_iface.modbus")
    assert "launch unit: read device_type @0 -> [1] = 1" in logged
    assert "launch unit: write heartbeat @3 <- [1] = 1" in logged
    assert "launch unit: write axis1.target @18 <- [2, 2437] = 133509" in logged
    assert "launch unit: write axis1.control @16 <- [7] = 7" in logged


def test_canopen_sdos_are_logged(caplog) -> None:
    caplog.set_level(logging.DEBUG, logger="firmware_iface.canopen_axis")
    channel = f"xmalign-{uuid.uuid4().hex}"
    server = CanopenUnitServer([SimUnit("launch", SimClock(real_time=True))], channel, "virtual")
    server.start()
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel)
    try:
        unit = CanopenUnit(network, "launch", device_name="launch unit")
        unit.axes[1].lock()
        unit.close()
    finally:
        network.disconnect()
        server.stop()
    logged = messages(caplog, "firmware_iface.canopen_axis")
    node2 = "axis a2 (CANopen node 2) of the launch unit"
    assert f"{node2}: SDO read 0x608F:1 -> 8388608 (0x800000)" in logged
    assert f"{node2}: SDO write 0x6040:0 <- 7 (0x7)" in logged


def test_serial_lines_are_logged_both_ways(caplog) -> None:
    caplog.set_level(logging.DEBUG, logger="firmware_iface.interferometer")
    line = ScriptedLine([encode_reply(Reply(True, "ZERO"))])
    SerialInterferometer(line, "interferometer on /dev/ttyX").zero()
    logged = messages(caplog, "firmware_iface.interferometer")
    assert logged[0] == "interferometer on /dev/ttyX > b'ZERO\\n'"
    assert logged[1].startswith("interferometer on /dev/ttyX < b'OK ZERO*")


def test_log_file_gets_timestamped_wire_lines_and_is_closed(tmp_path) -> None:
    path = tmp_path / "wire.log"
    handler = start_log_file(path)
    try:
        ModbusUnit(SimUnit("receiver", SimClock()), "receiver unit", clock=SimClock())
    finally:
        stop_log_file(handler)
    lines = path.read_text().splitlines()
    assert lines[0].endswith(
        "firmware_iface.modbus DEBUG receiver unit: read device_type @0 -> [2] = 2"
    )
    assert lines[0][10] == "T" and lines[0][23] == "Z"
    ModbusUnit(SimUnit("receiver", SimClock()), "receiver unit", clock=SimClock())
    assert len(path.read_text().splitlines()) == len(lines)  # detached: nothing more


def test_an_unwritable_log_file_is_one_clear_error(tmp_path) -> None:
    with pytest.raises(InputError, match=r"--log-file .*missing.*cannot write it"):
        start_log_file(tmp_path / "missing" / "wire.log")
