"""``xmalign align`` as a user runs it: --sim, and --live against simulated servers."""

from __future__ import annotations

import math
import re
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import yaml
from cli_helpers import assert_one_line_error, run_cli

from sim.alignment_setup import point_by_truth
from sim.servers.modbus import ModbusUnitServer
from sim.servers.serial_pty import PtyInterferometerServer
from sim.units import SimPositioningUnit
from sim.world import FixedPosition, build_world
from xmalign.kinematics import receiver_cp
from xmalign.machine import load_machine

ROOT = Path(__file__).resolve().parents[2]


def test_align_sim_shows_convergence() -> None:
    result = run_cli("align", "--sim", "--seed", "3", "--distance-mm", "1000")
    assert result.returncode == 0, result.stderr
    assert "Fine alignment" in result.stdout
    assert "s of simulated time" in result.stdout and "units locked" in result.stdout


def test_align_refuses_bad_options(tmp_path) -> None:  # noqa: ANN001
    assert_one_line_error(run_cli("align"), "choose one of --sim and --live")
    assert_one_line_error(run_cli("align", "--live"), "--live needs --config")
    assert_one_line_error(
        run_cli("align", "--live", "--config", str(tmp_path / "u.yaml")), "u.yaml: cannot read"
    )
    assert_one_line_error(run_cli("align", "--sim", "--at", "1,2"), "option --at")


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_align_live_over_modbus_and_the_serial_line(tmp_path) -> None:  # noqa: ANN001
    # a spindle angle that turns the receiver almost straight at the launch unit keeps the
    # real-time pre-positioning of the simulated units short
    cnc = np.array([1900.0, 1400.0, -100.0])
    reference = yaml.safe_load((ROOT / "examples" / "fyxz.yaml").read_text())
    launch2mcs = np.array(reference["launch_unit"]["position_mm"], dtype=float)
    cp = receiver_cp(cnc, reference["receiver_offset_mm"], 0.0)
    azimuth = math.atan2(*(cp - launch2mcs)[1::-1])
    reference["spindle_angle_deg"] = math.degrees(azimuth) + 180.0
    machine_path = tmp_path / "machine.yaml"
    machine_path.write_text(yaml.safe_dump(reference))
    machine = load_machine(machine_path)
    world = build_world(machine, FixedPosition(cnc), seed=2, real_time=True, gamma_rad=azimuth)
    launch, receiver = SimPositioningUnit(world.launch), SimPositioningUnit(world.receiver)
    point_by_truth(world, machine, launch, receiver)  # the operator's coarse alignment
    launch.move_to(launch.angles_rad() + [3e-5, -3e-5], 10.0)
    servers = [
        ModbusUnitServer(world.launch, "127.0.0.1", _free_port()),
        ModbusUnitServer(world.receiver, "127.0.0.1", _free_port()),
    ]
    pty = PtyInterferometerServer(world.interferometer, rate_hz=200.0)
    try:
        for server in servers:
            server.start()
        pty.start()
        config = tmp_path / "units.yaml"
        config.write_text(
            textwrap.dedent(f"""\
            format: xmalign.units/1
            launch: {{transport: modbus-tcp, host: 127.0.0.1, port: {servers[0].port}}}
            receiver: {{transport: modbus-tcp, host: 127.0.0.1, port: {servers[1].port}}}
            interferometer: {{port: {pty.port}, rate_hz: 200}}
            """)
        )
        result = run_cli(
            "align",
            "--live",
            "--config",
            str(config),
            "--machine",
            str(machine_path),
            "--distance-mm",
            "1500",
            "--log-file",
            str(tmp_path / "wire.log"),
        )
        assert result.returncode == 0, result.stderr
        wire = (tmp_path / "wire.log").read_text()
        assert "firmware_iface.modbus DEBUG launch unit at 127.0.0.1" in wire
        assert "write axis1.control @16 <- [9] = 9" in wire  # the lock on exit
        assert "firmware_iface.interferometer DEBUG interferometer on" in wire
        assert "s of wall time" in result.stdout and "units locked" in result.stdout
        world.launch.check_watchdog()
        assert all(axis.is_locked() for axis in (*world.launch.axes, *world.receiver.axes))
        geometry = world.interferometer.geometry()
        assert np.all(np.abs(geometry.channels[1:3]) < 3.0)
    finally:
        pty.stop()
        for server in servers:
            server.stop()


def test_align_sim_refuses_a_tool_point_it_cannot_use() -> None:
    assert_one_line_error(run_cli("align", "--sim", "--at", "a,b,c"), "'a,b,c' is not 'x,y,z'")
    assert_one_line_error(
        run_cli("align", "--sim", "--at", "1,2,3000"), "1,2,3000 is outside the travel"
    )


def test_align_sim_manual_jog_loop_answers_the_operator() -> None:
    """In range from the start: a wrong command is explained, Enter hands over to fine
    alignment; without an operator (end of input) the command ends in one line."""
    answered = subprocess.run(
        [sys.executable, "-m", "xmalign", "align", "--sim", "--manual", "--seed", "3"],
        input="a2 far\na2 0.003\n\n",
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert answered.returncode == 0, answered.stderr
    assert "jog command 'a2 far': expected an axis a1..a5" in answered.stdout
    shown = [line for line in answered.stdout.splitlines() if "beam in range: sv" in line]
    assert len(shown) == 3  # before each answer
    used = [[int(v) for v in re.findall(r"(\d+)%", line)] for line in shown]
    # 52 µrad on a2 moves the channels by some 10 % of their ranges; noise by 1 %
    assert np.abs(np.subtract(used[2], used[1])).max() >= 5
    assert "units locked" in answered.stdout
    assert_one_line_error(
        run_cli("align", "--sim", "--manual"), "no answer from the operator (end of input)"
    )
