import os
import signal
import subprocess
import sys

import serial
from pymodbus.client import ModbusTcpClient

from firmware_iface.xm_line_protocol import Reply, decode_line


def test_sim_serve_runs_until_sigint(free_port):
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
            f"127.0.0.1:{free_port}",
            "--interferometer-pty",
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
        client = ModbusTcpClient("127.0.0.1", port=free_port, timeout=2)
        assert client.connect()
        assert client.read_holding_registers(0, count=3, device_id=1).registers == [1, 256, 2]
        client.close()
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
