"""The served CNC of ``sim serve --position-file``: cycle start, M0, the position file."""

from __future__ import annotations

import queue
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import assert_one_line_error, run_cli

from firmware_iface.machine_position import FilePositions
from sim.clock import SimClock
from sim.cnc import SimulatedCnc
from sim.servers.served_cnc import WAITING, ServedCnc
from xmalign.errors import InputError
from xmalign.machine import Machine

PROGRAM = "G71 G90\nSUPA G0 X10 Y20 Z-30\nM0\nSUPA G0 X11 Y20 Z-30\nM30\n"


def _served(machine: Machine, path: Path, program: str = PROGRAM) -> tuple[ServedCnc, queue.Queue]:
    said: queue.Queue[str] = queue.Queue()
    clock = SimClock(real_time=True)
    cnc = SimulatedCnc(machine, clock, position_mm=[0.0, 0.0, 0.0])
    return ServedCnc(cnc, machine, clock, program, "sinumerik", path, said.put), said


def _next(said: queue.Queue) -> str:
    return said.get(timeout=10)


def test_cycle_start_runs_to_each_m0_and_again_after_the_end(reference_machine, tmp_path):
    path = tmp_path / "position.txt"
    served, said = _served(reference_machine, path)
    served.start()
    try:
        assert np.allclose(FilePositions(path).position_mm(), [0, 0, 0])  # written at once
        assert _next(said) == WAITING  # nothing moves before cycle start
        served.cycle_start()
        assert [_next(said), _next(said)] == ["cnc: program started", WAITING]  # at the M0
        assert np.allclose(FilePositions(path).position_mm(), [10, 20, -30], atol=1e-3)
        served.cycle_start()
        assert [_next(said), _next(said)] == ["cnc: program end", WAITING]
        assert np.allclose(FilePositions(path).position_mm(), [11, 20, -30], atol=1e-3)
        served.cycle_start()  # after the end: from the top again
        assert [_next(said), _next(said)] == ["cnc: program started", WAITING]
        assert np.allclose(FilePositions(path).position_mm(), [10, 20, -30], atol=1e-3)
    finally:
        served.stop()


def test_a_program_the_cnc_refuses_is_refused_before_serving(reference_machine, tmp_path):
    with pytest.raises(InputError, match="line 2"):
        _served(reference_machine, tmp_path / "p.txt", "G71 G90\nSUPA G0 X99999\nM30\n")


def test_sim_serve_refuses_what_does_not_go_together(tmp_path):
    assert_one_line_error(
        run_cli("sim", "serve", "--position-file", str(tmp_path / "p.txt")),
        "--position-file and --program go together",
    )
    assert_one_line_error(
        run_cli("sim", "serve", "--unit", "receiver", "--modbus-receiver", "5021"),
        "--modbus-receiver serves the receiver: --unit must be launch",
    )
    program = tmp_path / "run.nc"
    program.write_text("G71 G90\nSUPA G0 X99999\nM30\n")
    assert_one_line_error(
        run_cli("sim", "serve", "--position-file", "p.txt", "--program", str(program)),
        "line 2",
    )
