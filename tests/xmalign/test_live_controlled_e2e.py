"""``xmalign run`` running its program on the simulated CNC behind ``linuxcncrsh``'s protocol.

The same unattended run as tests/linuxcnc/test_unattended_run.py against a real
LinuxCNC, here against ``xmalign sim serve --linuxcncrsh`` (the simulator as
one more implementation of the controller, sim/servers/linuxcncrsh.py): one
short line, no one at the machine, in seconds and without LinuxCNC installed.
"""

from __future__ import annotations

import signal
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
from cli_helpers import Process, free_port

from tests.xmalign.test_live_e2e import GAMMA_DEG, SEED, _wait_for_rows, short_plan  # noqa: F401
from xmalign.calibration import capture_sequence
from xmalign.formats.measurements import load_measurements
from xmalign.formats.plan import read_plan

RUN = ["run", "--config", "units.yaml", "--machine", "machine.yaml", "--plan", "plan.json"]


@pytest.fixture
def served(short_plan: Path, tmp_path: Path) -> Iterator[Process]:  # noqa: F811
    """``sim serve`` with the CNC as a LinuxCNC over linuxcncrsh; its ``units.yaml``."""
    for name in ("machine.yaml", "plan.json"):
        (tmp_path / name).write_bytes((short_plan / name).read_bytes())
    ports = [free_port(), free_port(), free_port()]
    server = Process(
        ["sim", "serve", "--seed", str(SEED), "--gamma-deg", str(GAMMA_DEG)]
        + ["--modbus", str(ports[0]), "--modbus-receiver", str(ports[1])]
        + ["--interferometer-pty", "--machine", "machine.yaml", "--linuxcncrsh", str(ports[2])],
        tmp_path,
        stdin=subprocess.PIPE,
    )
    try:
        pty = server.wait_for("interferometer on").split()[-1]
        server.wait_for("serving")
        (tmp_path / "units.yaml").write_text(
            "format: xmalign.units/1\n"
            f"launch: {{transport: modbus-tcp, host: 127.0.0.1, port: {ports[0]}}}\n"
            f"receiver: {{transport: modbus-tcp, host: 127.0.0.1, port: {ports[1]}}}\n"
            f"interferometer: {{port: {pty}, rate_hz: 50}}\n"
            "machine_position:\n  source: linuxcncrsh\n"
            f"  linuxcncrsh: {{host: 127.0.0.1, port: {ports[2]}, program: run.ngc}}\n"
        )
        yield server
    finally:
        server.stop()


def test_unattended_run_on_the_simulated_linuxcncrsh(served: Process, tmp_path: Path) -> None:
    run = Process([*RUN, "--out", "m.csv", "--log-file", "wire.log"], tmp_path)
    assert run.finish(timeout_s=120) == 0, run.said() + served.said()
    line = read_plan(tmp_path / "plan.json").lines[0]
    rows = load_measurements(tmp_path / "m.csv").rows
    assert [r.key() for r in rows] == [p.key for p in capture_sequence(line)]
    assert max(abs(r.channels[0]) for r in rows) < 20.0  # captured at rest at each point
    said = run.said()
    assert "machine time" in said and "G-code estimate" in said
    wire = (tmp_path / "wire.log").read_text()
    assert wire.count("> 'set resume'") == len(rows) + 1  # each point's stop, the line's stop


def test_sigterm_sighup_and_ctrl_c_hold_the_feed_say_it_in_one_line_and_resume(
    served: Process, tmp_path: Path
) -> None:
    """A shutdown (SIGTERM), a closed ssh session (SIGHUP) and Ctrl-C during the unattended
    run: each ends it with the shell's code for the signal (128 + its number), one line
    that keeps the controller's note, no traceback; --resume goes on each time."""
    out = tmp_path / "m.csv"
    line = read_plan(tmp_path / "plan.json").lines[0]
    kept = 0
    for stop, code, name in [
        (signal.SIGTERM, 143, "SIGTERM: "),
        (signal.SIGHUP, 129, "SIGHUP: "),
        (signal.SIGINT, 130, ""),
    ]:
        run = Process([*RUN, "--out", "m.csv", *(["--resume"] if kept else [])], tmp_path)
        _wait_for_rows(out, kept + 1, timeout_s=120)  # of 7: one more point each time
        run.popen.send_signal(stop)
        assert run.finish(timeout_s=60) == code, run.said()
        kept = len(load_measurements(out, torn_ok=True).rows)
        assert run.stderr.splitlines() == [
            f"xmalign: {name}stopped: {kept} points kept in m.csv; go on with --resume; the"
            " feed is held on the controller"
        ], run.said()
    run = Process([*RUN, "--out", "m.csv", "--resume"], tmp_path)
    assert run.finish(timeout_s=120) == 0, run.said() + served.said()
    assert "the program was paused from an earlier run: aborted" in run.said()
    assert [r.key() for r in load_measurements(out).rows] == [p.key for p in capture_sequence(line)]
