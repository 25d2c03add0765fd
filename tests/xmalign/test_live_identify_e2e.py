"""``xmalign identify --live`` end to end against an ``xmalign sim serve`` process.

The served world's CNC runs a program that goes to each identification position and
stops (M0); the test plays the operator: it presses cycle start when told to move the
machine and Enter when the CNC stands there; it would jog the units where asked, but
the first alignment (no azimuth in the machine file) finds the beam by itself. Four
alignments (the fewest for the quick identification to point the last) with the CNC at
60 m/min; the units' own moves (30 °/s) and the first alignment's search (one turn of
the launch unit) make most of its some 80 s. The harness is test_live_e2e.py's.
"""

from __future__ import annotations

import math
import subprocess
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from pymodbus.client import ModbusTcpClient

from firmware_iface.machine_position import FilePositions
from sim.alignment_setup import point_by_truth
from sim.units import SimPositioningUnit
from sim.world import FixedPosition, build_world
from tests.xmalign.test_live_e2e import GAMMA_DEG, SEED, Process, World
from xmalign.formats.pose import read_pose
from xmalign.formats.session import read_session
from xmalign.machine import Machine, load_machine
from xmalign.steps import design_step


def _identification_program(positions_mm: np.ndarray) -> str:
    """The operator's program for an identification: to each position, then stop (M0)."""
    moves = "".join(f"SUPA G0 X{x:.4f} Y{y:.4f} Z{z:.4f}\nM0\n" for x, y, z in positions_mm)
    return f"G71 G90 G94\n{moves}M30\n"


def _read_units(served: World) -> tuple[np.ndarray, list[bool]]:
    """a1..a5 as the units' displays show them and whether each axis moves (read by a
    second, monitoring Modbus client: axis n's block at 16 n, 'status' then 'actual')."""
    angles, moving = [], []
    for port, axes in zip(served.ports, (2, 3), strict=True):
        client = ModbusTcpClient("127.0.0.1", port=port, timeout=2)
        assert client.connect()
        try:
            for n in range(1, axes + 1):
                status = client.read_holding_registers(16 * n + 1, count=1).registers[0]
                high, low = client.read_holding_registers(16 * n + 4, count=2).registers
                counts = (high << 16 | low) - (1 << 32 if high & 0x8000 else 0)
                angles.append(2 * math.pi * counts / 2**23)
                moving.append(bool(status & 1 << 2))
        finally:
            client.close()
    return np.array(angles), moving


class Operator:
    """The person at the machine during ``identify --live``: presses cycle start when told
    to move the machine, and jogs the units by eye where asked (to where the true pose
    points them: the served world's, built again from the same seed)."""

    def __init__(self, served: World, machine: Machine, identify: Process) -> None:
        self.served, self.machine, self.identify = served, machine, identify
        self.truth = build_world(machine, seed=SEED, gamma_rad=math.radians(GAMMA_DEG))
        self.units = SimPositioningUnit(self.truth.launch), SimPositioningUnit(self.truth.receiver)

    def answer(self, line: str) -> None:
        if "Move the machine to" in line:
            self.served.cycle_start()
            self.served.server.wait_for("waiting for cycle start")  # at the next M0
            self.type("")
        elif "Jog: " in line:
            self.type(self._jogs())  # the jogs, then Enter
        elif "not in range yet" in line or "move it there first" in line:
            raise AssertionError(f"the operator was refused:\n{self.identify.said()}")

    def type(self, text: str) -> None:
        stdin = self.identify.popen.stdin
        assert stdin is not None
        stdin.write(text + "\n")
        stdin.flush()

    def cnc_position_mm(self) -> np.ndarray:
        """Where the CNC stands (its position file)."""
        return FilePositions(self.served.position_file).position_mm()

    def _jogs(self) -> str:
        angles_rad, moving = _read_units(self.served)
        assert not any(moving), f"the jog prompt came before the units stood still: {moving}"
        self.truth.interferometer.position = FixedPosition(self.cnc_position_mm())
        launch, receiver = self.units
        point_by_truth(self.truth, self.machine, launch, receiver)
        aligned_rad = np.concatenate([launch.angles_rad(), receiver.angles_rad()])
        return "".join(
            f"a{n} {math.degrees(step):.6f}\n"
            for n, step in enumerate(aligned_rad - angles_rad, start=1)
        )


def quick_machine(tmp_path: Path, reference_machine_path: Path) -> Machine:
    """The reference machine with a 60 m/min rapid, as tmp_path/machine.yaml."""
    quick = yaml.safe_load(reference_machine_path.read_text())
    quick["feed_mm_min"] = {"rapid": 60000, "measure": 2000}
    quick["cnc"] = {"acceleration_mm_s2": 5000}
    (tmp_path / "machine.yaml").write_text(yaml.safe_dump(quick))
    return load_machine(tmp_path / "machine.yaml")


def identify_live(
    served: Any, make_operator: Callable[..., Any], machine: Machine, tmp_path: Path
) -> tuple[Process, Any]:
    """``identify --live`` with four alignments against ``served``, every prompt answered by
    ``make_operator(served, machine, process)``, to a successful end."""
    identify = Process(
        ["identify", "--live", "--config", "units.yaml", "--machine", "machine.yaml"]
        + ["--alignments", "4", "--session", "session.json", "--out", "pose.json"]
        + ["--log-file", "wire.log"],
        tmp_path,
        stdin=subprocess.PIPE,
    )
    operator = make_operator(served, machine, identify)
    try:
        while (line := identify.next_line()) is not None:
            operator.answer(line)
        assert identify.finish() == 0, identify.said() + served.server.said()
    finally:
        identify.stop()
        served.server.stop()
    return identify, operator


def assert_within_its_uncertainty(pose: Any, truth: Any) -> None:
    """The squared Mahalanobis distance of x, y, z, gamma from the truth below the
    chi-squared 99.9 % point for 4 degrees of freedom."""
    error = np.array([*(pose.position_mm - truth.launch2mcs_mm), 0.0])
    error[3] = math.remainder(pose.gamma_rad - truth.gamma_rad, math.tau)
    assert error @ np.linalg.solve(pose.covariance, error) < 18.47, (error, pose.covariance)


def test_identify_live_with_a_cnc_and_an_operator_against_sim_serve(
    tmp_path: Path, reference_machine_path: Path
) -> None:
    """``identify --live``: the operator runs the CNC to each position; the first alignment
    (no azimuth in the machine file) finds the beam by itself, the others are pointed from
    the alignments before: nobody jogs. The pose found is the served world's within its
    uncertainty."""
    machine = quick_machine(tmp_path, reference_machine_path)
    positions = design_step(machine, 4).machine_mm
    (tmp_path / "ident.nc").write_text(_identification_program(positions))
    served = World(tmp_path, tmp_path / "ident.nc")
    identify, operator = identify_live(served, Operator, machine, tmp_path)
    said = "".join(identify.lines)
    moves = [n for n, line in enumerate(identify.lines) if "Move the machine to" in line]
    jogs = [n for n, line in enumerate(identify.lines) if "Jog: " in line]
    # the first alignment searches the beam itself (no azimuth yet); the others are pointed
    assert len(moves) == 4 and not jogs, said
    assert "Traceback" not in identify.stderr
    assert len(read_session(tmp_path / "session.json").alignments) == 4
    pose = read_pose(tmp_path / "pose.json")
    assert_within_its_uncertainty(pose, operator.truth)
    assert np.all(np.sqrt(np.diag(pose.covariance)) < [0.05, 0.05, 0.05, 50e-6]), pose.covariance
