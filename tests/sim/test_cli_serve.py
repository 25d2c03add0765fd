"""``xmalign sim serve`` as a separate process, driven over every protocol it serves."""

import os
import re
import signal
import subprocess
import sys
import textwrap
import uuid

import numpy as np
import pytest
import serial
from cli_helpers import assert_one_line_error, run_cli
from pymodbus.client import ModbusTcpClient

from firmware_iface.config import load_units_config, open_devices
from firmware_iface.modbus import ModbusUnit, rtu_transport
from firmware_iface.xm_line_protocol import Reply, decode_line
from xmalign.machine import default_machine_path, load_machine
from xmalign.safety import units_locked_on_exit


def test_sim_serve_over_every_protocol_until_sigint(free_port, tmp_path):
    log_file = tmp_path / "wire.log"
    group = "239.74.{}.{}".format(*uuid.uuid4().bytes[:2])  # a multicast group of its own
    process = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "from xmalign.cli import main; main()",
            "sim",
            "serve",
            "--unit",
            "launch",
            "--modbus",
            str(free_port),  # on --host, 127.0.0.1 by default
            "--rtu",
            "--canopen",
            group,  # udp_local: the loopback only, TTL 0
            "--interferometer-pty",
            "--log-file",
            str(log_file),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "COLUMNS": "200"},
    )
    try:
        lines = []
        while not any("serving" in line for line in lines):
            line = process.stdout.readline()
            assert line, process.stderr.read()
            lines.append(line)
        pty_path = next(line.split()[-1] for line in lines if line.startswith("interferometer"))
        rtu_path = next(line.split()[4] for line in lines if line.startswith("modbus-rtu"))
        assert f"modbus launch unit on 127.0.0.1:{free_port}" in "".join(lines)
        client = ModbusTcpClient("127.0.0.1", port=free_port, timeout=2)
        assert client.connect()
        assert client.read_holding_registers(0, count=3, device_id=1).registers == [1, 256, 2]
        client.close()
        with serial.Serial(pty_path, timeout=2.0) as port:
            port.write(b"ZERO\n")
            assert decode_line(port.readline()) == Reply(True, "ZERO")
        live_devices_of_a_units_yaml(tmp_path, free_port, group, pty_path)
        # the TCP host has closed: the unit is free for a host on the RTU line
        rtu = ModbusUnit(rtu_transport(rtu_path, "launch unit"), expected_kind="launch")
        assert [axis.name for axis in rtu.axes] == ["a1", "a2"]
        rtu.close()
        process.send_signal(signal.SIGINT)
        assert process.wait(timeout=10) == 0
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert "stopped" in process.stdout.read()
    logged = log_file.read_text().splitlines()
    # every request with a UTC timestamp, e.g. "2026-11-22T09:00:00.123Z sim.servers.modbus ..."
    assert all(re.match(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z ", line) for line in logged)
    assert any(
        "sim.servers.modbus DEBUG launch unit: fc 3 @0 x3 -> [1, 256, 2]" in line for line in logged
    )
    assert any("unit: fc 16 @3 <- [1]" in line for line in logged)  # the RTU host's first beat
    assert any(
        "sim.servers.canopen_node DEBUG node 3 SDO write 0x6040:0 <- 6" in line for line in logged
    )
    # the nodes booted into pre-operational; the driver started them
    assert any("canopen_node DEBUG node 3 NMT boot-up -> pre-operational" in x for x in logged)
    assert any("sim.servers.canopen_node DEBUG NMT command 0x01 for node 3" in x for x in logged)


def live_devices_of_a_units_yaml(tmp_path, modbus_port, group, pty_path):
    """Both drivers across processes, opened from a units.yaml: Modbus TCP for the launch
    unit, CANopen for the receiver."""
    config_path = tmp_path / "units.yaml"
    config_path.write_text(
        textwrap.dedent(f"""\
        format: xmalign.units/1
        launch: {{transport: modbus-tcp, host: 127.0.0.1, port: {modbus_port}}}
        receiver: {{transport: canopen, interface: udp_local, channel: "{group}"}}
        interferometer: {{port: {pty_path}}}
        """)
    )
    live = open_devices(load_units_config(config_path), load_machine(default_machine_path()))
    try:
        with units_locked_on_exit(live.launch, live.receiver):
            live.launch.move_to([0.01, -0.01], timeout_s=5.0)
            live.receiver.move_to([-0.01, 0.005, 0.002], timeout_s=5.0)
        np.testing.assert_allclose(live.launch.angles_rad(), [0.01, -0.01], atol=1e-4)
        np.testing.assert_allclose(live.receiver.angles_rad(), [-0.01, 0.005, 0.002], atol=1e-4)
        assert all(axis.is_locked() for axis in (*live.launch.axes, *live.receiver.axes))
        assert live.interferometer.read().channels.shape == (6,)
    finally:
        live.close()


def test_sim_serve_bad_option_is_one_line():
    result = subprocess.run(
        [
            sys.executable,
            "-c",
            "from xmalign.cli import main; main()",
            "sim",
            "serve",
            "--modbus",
            "nowhere",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0 and "HOST:PORT" in result.stderr


@pytest.mark.parametrize(
    ("options", "fragments"),
    [
        (
            ("--canopen", "x", "--can-interface", "nosuchbus"),
            ("--can-interface nosuchbus", "udp_local"),
        ),
        (("--canopen", "999.999.1.1"), ("--canopen 999.999.1.1", "not an IPv4 multicast group")),
        (("--canopen", "239.74.1.1", "--can-hop-limit", "256"), ("--can-hop-limit 256",)),
        (
            ("--canopen", "239.74.1.1", "--can-host", "192.0.2.254"),
            ("cannot open the CAN bus 239.74.1.1", "192.0.2.254"),
        ),
    ],
)
def test_sim_serve_bad_can_options_are_one_line(options, fragments):
    assert_one_line_error(run_cli("sim", "serve", *options), *fragments)


def test_a_server_thread_that_dies_stops_serve_with_one_line():
    """A device thread ended by an error (the interferometer's, say) must not leave
    ``sim serve`` saying "serving": the watch sets the stop and names the thread."""
    import threading

    from xmalign.cli.sim import stop_when_a_thread_dies

    stopped = threading.Event()
    before = threading.excepthook
    with stop_when_a_thread_dies(stopped) as died:

        def fail() -> None:
            raise ValueError("cannot convert float NaN to integer")

        thread = threading.Thread(target=fail, name="xm-commands")
        thread.start()
        thread.join()
    assert stopped.is_set()
    assert died == ["xm-commands: ValueError: cannot convert float NaN to integer"]
    assert threading.excepthook is before
