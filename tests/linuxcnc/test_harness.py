"""The harness itself: a gantry sim runs a program with an M0 to its end."""

from __future__ import annotations

import pytest
from harness import SimMachine, run_linuxcnc, standard_start, write_sim_config

pytestmark = pytest.mark.linuxcnc


def test_gantry_sim_homes_runs_a_program_through_m0_and_reads_pins(linuxcnc_dir):
    ini = write_sim_config(linuxcnc_dir, SimMachine(coordinates="XYYZ"))
    program = linuxcnc_dir / "move.ngc"
    program.write_text("G21 G90\nG53 G1 X120 Y80 Z-30 F60000\nM0\nG53 G0 X40 Y250\nM2\n")
    program.chmod(0o644)
    watch = [f"joint.{j}.f-error" for j in range(4)]
    run = run_linuxcnc(
        ini,
        [
            *standard_start(),
            {"op": "run", "program": str(program), "watch": watch, "label": "program"},
            {"op": "pins", "names": [f"joint.{j}.pos-cmd" for j in range(4)], "label": "end"},
        ],
    )
    assert run.report is not None, run.describe()
    assert run.value("program")["resumes"] == 1
    assert run.value("end") == pytest.approx(
        {
            "joint.0.pos-cmd": 40.0,
            "joint.1.pos-cmd": 250.0,
            "joint.2.pos-cmd": 250.0,
            "joint.3.pos-cmd": -30.0,
        },
        abs=1e-9,
    )
    assert run.report["state"]["homed"] == [True] * 4
