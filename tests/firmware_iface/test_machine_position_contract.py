"""The contract every machine-position source passes (machine_position_contract.py).

Run against each implementation as a live run meets it: the position file a CNC
keeps up to date, an MTConnect agent (the reference agent's documents served on
127.0.0.1), a SINUMERIK's OPC UA server (asyncua's server carrying the
documented nodes), a LinuxCNC over linuxcncrsh (the simulated CNC speaking its
protocol, answering as a real LinuxCNC 2.9 did in tests/linuxcnc) and a LinuxCNC
through its Python module (the simulated module in front of the same simulated
LinuxCNC; tests/linuxcnc/test_real_linuxcnc_module.py runs this contract against the
real module and a real headless LinuxCNC). A followed controller that reports its
program (MTConnect's Program, the SINUMERIK's selectedWorkPProg) names it, spelled
its own way, with its state, and a followed run refuses another program running
(ProgramGuard).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from asyncua import ua
from machine_position_contract import (  # noqa: F401 (the contract's tests, run here)
    SETTLE_S,
    Stand,
    test_a_lost_source_is_a_transport_error_naming_it,
    test_a_moving_machine_does_not_stand_still,
    test_an_operator_prompt_checks_the_confirmed_move_against_it,
    test_gives_the_actual_position_in_mm_as_three_floats,
    test_is_a_machine_position_source,
    test_stands_still_once_the_position_stays_put,
)
from mtconnect_agent import TestAgent
from sinumerik_server import SinumerikServer

from firmware_iface.linuxcnc_module import LocalLinuxCnc
from firmware_iface.linuxcncrsh import open_linuxcnc
from firmware_iface.machine_position import FilePositions
from firmware_iface.mtconnect import open_mtconnect
from firmware_iface.sinumerik_opcua import OpcUaSecurity, open_sinumerik
from sim.clock import SimClock
from sim.cnc import SimulatedCnc
from sim.linuxcnc_module import NML_FILE, simulated_module
from sim.linuxcnc_task import SimulatedLinuxcnc
from sim.servers.linuxcncrsh import LinuxcncrshServer
from xmalign.errors import DeviceError
from xmalign.machine import Machine
from xmalign.program_check import ProgramGuard, same_program
from xmalign.roles import ReportsProgram


def _file_stand(tmp_path: Path) -> Iterator[Stand]:
    path = tmp_path / "position.txt"

    def place(x: float, y: float, z: float) -> None:
        path.write_text(f"# written by the CNC\n{x} {y} {z}\n", encoding="utf-8")

    place(0.0, 0.0, 0.0)
    yield Stand(FilePositions(path), place, path.unlink, str(path), SimClock(), sees_motion=False)


def _mtconnect_stand(tmp_path: Path) -> Iterator[Stand]:
    agent = TestAgent("linuxcnc", "LinuxCNC").start()
    clock = SimClock()
    machine = open_mtconnect(agent.url, 2.0, settle_s=SETTLE_S, clock=clock)

    def show_program(name: str, running: bool) -> None:  # LinuxCNC's adapter: the file
        agent.program = f"/home/cnc/linuxcnc/nc_files/{name.lower()}.ngc"
        agent.execution = "ACTIVE" if running else "READY"

    try:
        yield Stand(
            machine,
            lambda x, y, z: agent.set(X=x, Y=y, Z=z),
            agent.stop,
            agent.url,
            clock,
            show_program=show_program,
        )
    finally:
        machine.close()
        agent.stop()


def _sinumerik_stand(tmp_path: Path) -> Iterator[Stand]:
    server = SinumerikServer(users={"xmalign": "pw"}).start()
    clock = SimClock()
    security = OpcUaSecurity(identity="user", user="xmalign", password="pw")
    machine = open_sinumerik(server.endpoint, 2.0, security, settle_s=SETTLE_S, clock=clock)
    stopped = []

    def cut() -> None:
        server.stop()
        stopped.append(True)

    def show_program(name: str, running: bool) -> None:  # the NC notation
        nc_name = f"/_N_MPF_DIR/_N_{name.upper()}_MPF"
        server.set("/Channel/ProgramInfo/selectedWorkPProg[u1]", nc_name, ua.VariantType.String)
        server.set("/Channel/State/progStatus[u1]", 3 if running else 5, ua.VariantType.UInt16)

    try:
        yield Stand(
            machine, server.set_position, cut, server.endpoint, clock, show_program=show_program
        )
    finally:
        machine.close()
        if not stopped:
            server.stop()


def _simulated_cnc(reference_machine: Machine, clock: SimClock) -> tuple[SimulatedCnc, Machine]:
    roomy = {axis: [-5000.0, 5000.0] for axis in "XYZ"}  # the contract's points anywhere
    machine_model = reference_machine.model_copy(update={"travel_mm": roomy})
    return SimulatedCnc(machine_model, clock), machine_model


def _placer(cnc: SimulatedCnc, machine: Machine, clock: SimClock) -> Callable[..., None]:
    def place(x: float, y: float, z: float) -> None:  # a rapid move, waited out
        clock.sleep(cnc.start_move([x, y, z], machine.feed_mm_min.rapid))

    return place


#: The feed of a contract move that the source must see under way, mm/min (1 mm: 0.5 s).
MOVING_FEED_MM_MIN = 120.0


def _mover(cnc: SimulatedCnc) -> Callable[..., None]:
    def move(x: float, y: float, z: float) -> None:  # a slow move, not waited out
        cnc.start_move([x, y, z], MOVING_FEED_MM_MIN)

    return move


def _linuxcncrsh_stand(tmp_path: Path, reference_machine: Machine) -> Iterator[Stand]:
    clock = SimClock()
    cnc, machine_model = _simulated_cnc(reference_machine, clock)
    server = LinuxcncrshServer(cnc, machine_model)
    server.start()
    machine = open_linuxcnc("127.0.0.1", server.port, 2.0, clock=clock)
    place = _placer(cnc, machine_model, clock)
    try:
        yield Stand(machine, place, server.stop, server.where, clock, move=_mover(cnc))
    finally:
        machine.close()
        server.stop()


def _linuxcnc_module_stand(tmp_path: Path, reference_machine: Machine) -> Iterator[Stand]:
    """LinuxCNC's Python module, the simulated one (sim/linuxcnc_module.py) in front of the
    same simulated LinuxCNC; the real module against a real LinuxCNC: tests/linuxcnc."""
    clock = SimClock()
    cnc, machine_model = _simulated_cnc(reference_machine, clock)
    linuxcnc = SimulatedLinuxcnc(cnc, machine_model)
    machine = LocalLinuxCnc(simulated_module(linuxcnc), clock=clock)
    place = _placer(cnc, machine_model, clock)
    try:
        yield Stand(machine, place, linuxcnc.shut_down, NML_FILE, clock, move=_mover(cnc))
    finally:
        machine.close()


STANDS = {
    "file": _file_stand,
    "mtconnect": _mtconnect_stand,
    "sinumerik": _sinumerik_stand,
    "linuxcncrsh": _linuxcncrsh_stand,
    "linuxcnc-module": _linuxcnc_module_stand,
}


@pytest.fixture(params=sorted(STANDS))
def stand(
    request: pytest.FixtureRequest, tmp_path: Path, reference_machine: Machine
) -> Iterator[Stand]:
    make = STANDS[request.param]
    if make in (_linuxcncrsh_stand, _linuxcnc_module_stand):
        yield from make(tmp_path, reference_machine)  # type: ignore[call-arg]
    else:
        yield from make(tmp_path)


def _reporting(stand: Stand) -> Callable[[str, bool], None]:
    if stand.show_program is None:
        pytest.skip("this source does not report a program (a file; LinuxCNC runs its own)")
    assert isinstance(stand.source, ReportsProgram)
    return stand.show_program


def test_a_controller_reporting_its_program_names_it_with_its_state(stand: Stand) -> None:
    show = _reporting(stand)
    assert isinstance(stand.source, ReportsProgram)
    show("run", True)
    report = stand.source.program_report()
    assert report is not None and report.state == "running"
    assert report.name is not None and same_program(report.name, "run")
    show("other", False)
    report = stand.source.program_report()
    assert report is not None and report.state == "idle"
    assert report.name is not None and not same_program(report.name, "run")


def test_another_program_running_stops_a_followed_run_with_one_line(stand: Stand) -> None:
    """A stale or wrong program running (or stopped mid-way) is refused; xmalign's running,
    or another one idle, is not."""
    show = _reporting(stand)
    assert isinstance(stand.source, ReportsProgram)
    told: list[str] = []
    guard = ProgramGuard(stand.source, "run", "machine_position.x.program_name", told.append)
    show("run", True)
    guard.check()
    show("old", False)
    guard.check()
    show("old", True)
    with pytest.raises(DeviceError) as caught:
        guard.check()
    message = str(caught.value)
    assert "\n" not in message and "OLD" in message.upper()
    assert "not xmalign's program run (machine_position.x.program_name)" in message
    assert not told
