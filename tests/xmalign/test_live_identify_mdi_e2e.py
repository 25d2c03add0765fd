"""``xmalign identify --live`` moving the machine itself over linuxcncrsh (MDI).

``xmalign sim serve --linuxcncrsh`` serves the world's CNC as a LinuxCNC; the
``units.yaml`` allows MDI moves (``allow_mdi_moves: true``), so identify sends
``set mode mdi`` and ``set mdi G21 G90 G94 G53 G1 ...`` for every identification position and
never asks anyone to move the machine; the test only jogs the units into range
where no pose guess can point them (as in test_live_identify_e2e.py, whose harness
this is).
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np

from firmware_iface.linuxcncrsh import open_linuxcnc
from tests.xmalign.test_live_e2e import GAMMA_DEG, SEED, Process, _free_port
from tests.xmalign.test_live_identify_e2e import (
    Operator,
    assert_within_its_uncertainty,
    identify_live,
    quick_machine,
)
from xmalign.formats.pose import read_pose
from xmalign.formats.session import read_session
from xmalign.steps import design_step


class LinuxcncWorld:
    """``xmalign sim serve`` of a world with its CNC as a LinuxCNC on linuxcncrsh, and a
    ``units.yaml`` that lets xmalign move it."""

    def __init__(self, workdir: Path) -> None:
        self.ports = ports = [_free_port(), _free_port()]
        self.rsh_port = _free_port()
        args = ["sim", "serve", "--seed", str(SEED), "--gamma-deg", str(GAMMA_DEG)]
        args += ["--modbus", str(ports[0]), "--modbus-receiver", str(ports[1])]
        args += ["--interferometer-pty", "--machine", "machine.yaml"]
        args += ["--linuxcncrsh", str(self.rsh_port)]
        self.server = Process(args, workdir, stdin=subprocess.PIPE)
        pty = self.server.wait_for("interferometer on").split()[-1]
        self.server.wait_for_all("serving")
        (workdir / "units.yaml").write_text(
            "format: xmalign.units/1\n"
            f"launch: {{transport: modbus-tcp, host: 127.0.0.1, port: {ports[0]}}}\n"
            f"receiver: {{transport: modbus-tcp, host: 127.0.0.1, port: {ports[1]}}}\n"
            f"interferometer: {{port: {pty}, rate_hz: 50}}\n"
            "machine_position:\n  source: linuxcncrsh\n"
            f"  linuxcncrsh: {{host: 127.0.0.1, port: {self.rsh_port}, program: run.ngc,"
            " allow_mdi_moves: true}\n"
            "timeouts: {io_s: 1.0, move_s: 30.0, machine_s: 60.0}\n"
        )

    def position_mm(self) -> np.ndarray:
        """Where the CNC stands, read over a session of its own (no control)."""
        cnc = open_linuxcnc("127.0.0.1", self.rsh_port, 2.0, enable_password=None)
        try:
            return cnc.position_mm()
        finally:
            cnc.close()


class Jogger(Operator):
    """The person at the units: jogs them where asked; never moves the machine."""

    def answer(self, line: str) -> None:
        if "Move the machine to" in line:
            raise AssertionError(f"asked to move the machine:\n{self.identify.said()}")
        super().answer(line)

    def cnc_position_mm(self) -> np.ndarray:
        return self.served.position_mm()


def test_identify_live_moves_the_machine_over_mdi_where_units_yaml_allows_it(
    tmp_path: Path, reference_machine_path: Path
) -> None:
    machine = quick_machine(tmp_path, reference_machine_path)
    served = LinuxcncWorld(tmp_path)
    identify, operator = identify_live(served, Jogger, machine, tmp_path)
    assert "Traceback" not in identify.stderr
    wire = (tmp_path / "wire.log").read_text()
    positions = design_step(machine, 4).machine_mm
    for x, y, z in positions:  # each position sent as one MDI line, as LinuxCNC takes it
        assert f"set mdi G21 G90 G94 G53 G1 X{x:.4f} Y{y:.4f} Z{z:.4f}" in wire, wire[-2000:]
    assert "set mode mdi" in wire and "EMCTOO" not in wire
    session = read_session(tmp_path / "session.json")
    assert len(session.alignments) == 4
    assert_within_its_uncertainty(read_pose(tmp_path / "pose.json"), operator.truth)
