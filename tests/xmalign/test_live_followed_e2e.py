"""``xmalign run`` following a controller that reports its program: a wrong one is refused,
xmalign's followed to the end.

As test_cli_live.py's run with a position file, in this process over the real protocols
(units on Modbus TCP, the interferometer on a pty), with the machine's position and
program served by the controller's own kind of server: the reference MTConnect agent's
documents (tests/mtconnect_agent.py) or the SINUMERIK OPC UA address space on asyncua's
server (tests/sinumerik_server.py). The machine is the script that runs the program
(``controller_running_the_plan``), on line Z cut to three targets.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from asyncua import ua
from cli_helpers import assert_one_line_error
from mtconnect_agent import TestAgent
from sinumerik_server import PART_PROGRAMS, SinumerikServer
from test_cli_live import (  # noqa: F401 (fixtures)
    Served,
    Terminal,
    _keys,
    _points,
    _run,
    controller_running_the_plan,
    plans,
    pre_position,
    served,
    short_plan,
)

from xmalign.formats.measurements import read_measurements

SELECTED = "/Channel/ProgramInfo/selectedWorkPProg[u1]"


@dataclass
class Followed:
    """A controller serving the machine's position and its program."""

    #: The ``machine_position`` of units.yaml (one YAML line).
    yaml: str
    report: Callable[[np.ndarray], None]
    #: The operator starts a program named ``name`` (bare) on the controller.
    run_program: Callable[[str], None]
    #: The operator presses Cycle Start after xmalign selected its program (SINUMERIK).
    cycle_start: Callable[[], None] | None = None
    #: What the controller holds after a run of xmalign's program, checked.
    check_after_run: Callable[[], None] = lambda: None
    agent: TestAgent | None = None


@contextlib.contextmanager
def _mtconnect() -> Iterator[Followed]:
    agent = TestAgent("linuxcnc", "LinuxCNC").start()

    def run_program(name: str) -> None:  # a LinuxCNC's adapter names the file it runs
        agent.program, agent.execution = f"/home/cnc/linuxcnc/nc_files/{name}.ngc", "ACTIVE"

    try:
        yield Followed(
            f"{{source: mtconnect, mtconnect: {{url: '{agent.url}', timeout_s: 2.0}}}}",
            lambda p: agent.set(X=p[0], Y=p[1], Z=p[2]),
            run_program,
            agent=agent,
        )
    finally:
        agent.stop()


@contextlib.contextmanager
def _sinumerik() -> Iterator[Followed]:
    """xmalign copies its program to the NC and selects it (units.yaml ``program``,
    ``copy_program``); the operator then presses Cycle Start."""
    server = SinumerikServer(users={"xmalign": "pw"}).start()

    def running(selected: str) -> None:
        server.set(SELECTED, selected, ua.VariantType.String)
        server.set("/Channel/State/chanStatus[u1]", 1, ua.VariantType.UInt16)
        server.set("/Channel/State/progStatus[u1]", 3, ua.VariantType.UInt16)

    def check_after_run() -> None:  # the plan's program, written to the NC by xmalign
        assert server.value(SELECTED) == "/_N_MPF_DIR/_N_RUN_MPF"
        program = server.programs[f"{PART_PROGRAMS}RUN.MPF"].decode()
        assert program.startswith("; RUN\n") and "SUPA G1" in program and "M30" in program

    try:
        yield Followed(
            f"{{source: sinumerik, sinumerik: {{endpoint: '{server.endpoint}', user: xmalign,"
            f" password: pw, program: '{PART_PROGRAMS}RUN.MPF', copy_program: true}}}}",
            lambda p: server.set_position(*p),
            lambda name: running(f"/_N_MPF_DIR/_N_{name.upper()}_MPF"),
            lambda: running(server.value(SELECTED)),
            check_after_run,
        )
    finally:
        server.stop()


@contextlib.contextmanager
def _mtconnect_without_program() -> Iterator[Followed]:
    """An agent whose device has no PROGRAM data item: the run says so once and goes on."""
    with _mtconnect() as followed:
        assert followed.agent is not None
        followed.agent.drop_program()
        yield followed


CONTROLLERS = {"mtconnect": _mtconnect, "sinumerik": _sinumerik}
EVERY_KIND = {**CONTROLLERS, "mtconnect-without-program": _mtconnect_without_program}


@contextlib.contextmanager
def _followed_world(
    kind: str,
    reference_machine,  # noqa: ANN001
    plan: Path,
    folder: Path,
) -> Iterator[tuple[Served, Followed]]:
    start_mm = pre_position(reference_machine, plan)
    with (
        EVERY_KIND[kind]() as followed,
        served(reference_machine, folder, plan, start_mm) as world,
    ):
        followed.report(start_mm)
        yaml = f"machine_position: {followed.yaml}\n"
        world.config.write_text(world.config.read_text() + yaml)
        yield world, followed


@pytest.mark.parametrize("kind", sorted(CONTROLLERS))
def test_a_stale_program_running_is_refused_before_any_capture(
    kind: str,
    reference_machine,
    short_plan: Path,  # noqa: F811
    tmp_path: Path,
) -> None:
    """The machine stands at the line's pre-position, where the run would set the units,
    but the controller runs an old program: one line, nothing captured, the units never
    moved."""
    out = tmp_path / "m.csv"
    with _followed_world(kind, reference_machine, short_plan, tmp_path) as (world, followed):
        followed.run_program("old")
        targets = [axis.target_rad for axis in world.axes()]
        result = _run(Terminal(lambda printed: None), world, short_plan, out)
        assert [axis.target_rad for axis in world.axes()] == targets
    expected = {
        "mtconnect": "is running with program /home/cnc/linuxcnc/nc_files/old.ngc, not"
        " xmalign's program run (machine_position.mtconnect.program_name, default: the"
        " program file's name): a stale or wrong program",
        "sinumerik": "channel 1 is not in reset (chanStatus 1 (active)) with program"
        f" /_N_MPF_DIR/_N_OLD_MPF, not xmalign's program {PART_PROGRAMS}RUN.MPF: a stale or"
        " wrong program? press Reset on the machine, then run again",
    }[kind]
    assert_one_line_error(result, expected, "0 points kept")
    assert not read_measurements(out)


@pytest.mark.parametrize("kind", sorted(EVERY_KIND))
def test_xmalign_s_program_is_followed_to_the_end(
    kind: str,
    reference_machine,
    short_plan: Path,  # noqa: F811
    tmp_path: Path,
) -> None:
    out = tmp_path / "m.csv"
    terminal = Terminal(lambda printed: None)
    overrun_mm = reference_machine.measurement.overrun_mm
    with _followed_world(kind, reference_machine, short_plan, tmp_path) as (world, followed):
        if followed.cycle_start is None:
            followed.run_program("run")
        with controller_running_the_plan(
            world, terminal, short_plan, overrun_mm, out, followed.report, followed.cycle_start
        ):
            result = _run(terminal, world, short_plan, out)
        assert result.returncode == 0, result.stderr
        followed.check_after_run()
    assert _keys(out) == _points(short_plan)
    unreported = terminal.out.getvalue().count("does not report its program: not checked")
    assert unreported == (kind == "mtconnect-without-program")
