"""No one at the machine, from the first alignment to the last point, on a real headless LinuxCNC.

LinuxCNC 2.9 (Debian ``linuxcnc-uspace``) runs with ``linuxcncrsh`` as its display
(tests/linuxcnc/harness.py); the test plays the operator only to bring it up once
(E-stop reset, machine on, home). Then, with nothing typed (every xmalign process's
standard input closed):

* ``xmalign sim publish-position`` keeps LinuxCNC's actual position in a file, and
  ``xmalign sim serve --follow-position-file`` carries the virtual receiver there
  (the units and the interferometer served over Modbus TCP and a pty);
* ``xmalign identify --live`` moves the machine to the identification positions over
  MDI (``allow_mdi_moves: true``); the machine file gives the launch unit's rough place
  but no azimuth (the served world's is 137°), so the first alignment searches the beam
  itself; then it writes the pose;
* ``xmalign program --max-length-mm 20`` plans two lines cut to 20 mm (a try-out);
* ``xmalign run`` runs them on LinuxCNC and captures every point.

When LinuxCNC stops, the publisher ends by itself. About two to three minutes of
real time.
"""

from __future__ import annotations

import subprocess
import time
from pathlib import Path

import pytest
from cli_helpers import Process, free_port
from harness import SimMachine, bring_up, linuxcnc_publishing, write_sim_config

from firmware_iface.linuxcncrsh import open_linuxcnc
from tests.xmalign.test_live_e2e import quick_machine
from xmalign.calibration import capture_sequence
from xmalign.formats.measurements import load_measurements
from xmalign.formats.plan import read_plan
from xmalign.formats.session import read_session
from xmalign.machine import load_machine

pytestmark = pytest.mark.linuxcnc

#: The served world's launch azimuth: nowhere in what xmalign is given.
GAMMA_DEG = 137.0
SEED = 7


def _units_yaml(ports: list[int], pty: str, rsh_port: int) -> str:
    return (
        "format: xmalign.units/1\n"
        f"launch: {{transport: modbus-tcp, host: 127.0.0.1, port: {ports[0]}}}\n"
        f"receiver: {{transport: modbus-tcp, host: 127.0.0.1, port: {ports[1]}}}\n"
        f"interferometer: {{port: {pty}, rate_hz: 50}}\n"
        "machine_position:\n"
        "  source: linuxcncrsh\n"
        f"  linuxcncrsh: {{host: 127.0.0.1, port: {rsh_port}, program: run.ngc,"
        " allow_mdi_moves: true}\n"
        "timeouts: {io_s: 2.0, move_s: 30.0, machine_s: 120.0}\n"
    )


def test_identify_program_and_run_with_nothing_typed(
    linuxcnc_dir: Path, reference_machine_path: Path
) -> None:
    machine = load_machine(quick_machine(reference_machine_path, linuxcnc_dir))
    assert machine.launch_unit is not None  # the rough place, and nothing of the azimuth
    travel = {
        axis: (float(low), float(high))
        for axis, low, high in zip("XYZ", machine.travel_min_mm, machine.travel_max_mm, strict=True)
    }
    cnc = SimMachine(
        travel_mm=travel,
        max_velocity_mm_s=machine.feed_mm_min.rapid / 60.0,
        max_acceleration_mm_s2=5000.0,
    )
    rsh_port = free_port()
    ini = write_sim_config(linuxcnc_dir / "cnc", cnc, f"linuxcncrsh --port {rsh_port}")
    position_file = linuxcnc_dir / "position.txt"
    started = time.monotonic()
    with linuxcnc_publishing(ini, rsh_port, position_file) as publisher:
        operator = open_linuxcnc("127.0.0.1", rsh_port, 5.0)
        bring_up(operator)  # homed once: the operator's only part
        operator.close()
        ports = [free_port(), free_port()]
        server = Process(
            ["sim", "serve", "--seed", str(SEED), "--gamma-deg", str(GAMMA_DEG)]
            + ["--modbus", str(ports[0]), "--modbus-receiver", str(ports[1])]
            + ["--interferometer-pty", "--machine", "machine.yaml"]
            + ["--follow-position-file", str(position_file)],
            linuxcnc_dir,
            stdin=subprocess.PIPE,
        )
        try:
            pty = server.wait_for("interferometer on").split()[-1]
            server.wait_for("serving")
            (linuxcnc_dir / "units.yaml").write_text(_units_yaml(ports, pty, rsh_port))
            identify = Process(
                ["identify", "--live", "--config", "units.yaml", "--machine", "machine.yaml"]
                + ["--session", "session.json", "--alignments", "4", "--out", "pose.json"],
                linuxcnc_dir,
            )
            assert identify.finish(timeout_s=400) == 0, identify.said()
            identified_s = time.monotonic() - started
            assert "pose written to pose.json" in identify.said()
            assert len(read_session(linuxcnc_dir / "session.json").alignments) == 4
            program = Process(
                ["program", "--pose", "pose.json", "--machine", "machine.yaml", "--lines", "Z,X"]
                + ["--max-length-mm", "20", "--plan-out", "plan.json", "--out", "try.ngc"],
                linuxcnc_dir,
            )
            assert program.finish(timeout_s=120) == 0, program.said()
            run = Process(
                ["run", "--config", "units.yaml", "--machine", "machine.yaml"]
                + ["--plan", "plan.json", "--out", "m.csv"],
                linuxcnc_dir,
            )
            assert run.finish(timeout_s=300) == 0, run.said()
        finally:
            server.stop()
    plan = read_plan(linuxcnc_dir / "plan.json")
    assert all(line.targets_mm[-1] <= 20.0 for line in plan.lines)
    expected = [p.key for line in plan.lines for p in capture_sequence(line)]
    rows = load_measurements(linuxcnc_dir / "m.csv").rows
    assert [(r.line, r.run, r.direction, r.index) for r in rows] == expected
    assert f"{len(expected)} points captured" in run.said()
    # LinuxCNC has stopped: the publisher ended by itself, and says why
    assert publisher.popen.returncode == 0, publisher.said()
    assert "publishing ended" in publisher.said()
    print(
        f"identified after {identified_s:.0f} s; all {len(expected)} points after"
        f" {time.monotonic() - started:.0f} s of real time"
    )
    print(*(line for line in run.said().splitlines() if "machine time" in line))
