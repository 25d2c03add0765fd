import os
import re
import signal
import subprocess
import sys

import serial
from pymodbus.client import ModbusTcpClient

from firmware_iface.modbus import ModbusUnit, rtu_transport
from firmware_iface.xm_line_protocol import Reply, decode_line


def test_sim_serve_runs_until_sigint(free_port, tmp_path):
    log_file = tmp_path / "wire.log"
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
        rtu = ModbusUnit(rtu_transport(rtu_path, "launch unit"), expected_kind="launch")
        assert [axis.name for axis in rtu.axes] == ["a1", "a2"]
        rtu.close()
        with serial.Serial(pty_path, timeout=2.0) as port:
            port.write(b"ZERO\n")
            assert decode_line(port.readline()) == Reply(True, "ZERO")
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
    assert any("sim.servers.modbus DEBUG fc 3 @0 x3 -> [1, 256, 2]" in line for line in logged)
    assert any("fc 16 @3 <- [1]" in line for line in logged)  # the RTU host's first heartbeat


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
