"""LinuxCNC's own Python module ``linuxcnc`` against a real headless LinuxCNC 2.9.

LinuxCNC (Debian ``linuxcnc-uspace``) runs as its own user with ``linuxcncrsh`` as
its display (tests/linuxcnc/harness.py); this process (root in CI) reads and
commands it through the module from /usr/lib/python3/dist-packages, loaded by
:func:`~firmware_iface.linuxcnc_module.find_linuxcnc_module`, through LinuxCNC's
NML shared memory, as xmalign on the CNC's own computer does. The tests run
the machine-position contract (tests/firmware_iface/machine_position_contract.py)
on it and on linuxcncrsh (a moving machine included), compare what the module and
linuxcncrsh report of the same machine,
hold and resume a program, MDI moves and refusals with LinuxCNC's own messages,
and an unattended ``xmalign run`` through the module (the Shop of
test_unattended_run.py with ``source: linuxcnc``).

The machine brakes at 10 000 mm/s^2 (the placements over metres take a second);
the program-control contract's tests run with it braking at the contract's
100 mm/s^2 (:func:`harness.braking_at`: LinuxCNC's ``ini.*`` HAL pins, set for
the test), so a feed hold in the last 2 mm before an M0 is one there too.

Seen with 2.9: a ``stat()`` opened while LinuxCNC runs keeps answering (stale)
after LinuxCNC has gone; a fresh one raises ``linuxcnc.error``. In a feed hold
``stat.inpos`` is false (the rest of the move is queued), ``stat.paused`` true.
"""

from __future__ import annotations

import shutil
import socket
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import free_port
from harness import SimMachine, braking_at, bring_up, linuxcnc_serving, write_sim_config
from test_unattended_run import LINES, Shop, _expected_keys, _keys, shop_running

from firmware_iface.linuxcnc_control import MdiMover, mdi_move_line
from firmware_iface.linuxcnc_module import LocalLinuxCnc, find_linuxcnc_module
from firmware_iface.linuxcncrsh import LinuxCnc, LinuxcncrshLink, open_linuxcnc
from tests.firmware_iface import machine_position_contract
from tests.firmware_iface.machine_position_contract import (  # noqa: F401 (the contract, run here)
    Stand,
    test_a_moving_machine_does_not_stand_still,
    test_an_operator_prompt_checks_the_confirmed_move_against_it,
    test_gives_the_actual_position_in_mm_as_three_floats,
    test_is_a_machine_position_source,
    test_stands_still_once_the_position_stays_put,
)
from tests.firmware_iface.program_control_contract import (  # noqa: F401 (run here)
    ACCELERATION_MM_S2,
    ControlStand,
    settled_mm,
    settles_at,
    test_a_feed_hold_in_the_braking_distance_stops_at_the_stop_and_needs_two_resumes,
    test_a_feed_hold_stops_on_the_path_and_a_resume_goes_on,
    test_a_program_it_cannot_open_is_refused_with_its_message,
    test_a_request_interrupted_before_its_reply_does_not_answer_the_next,
    test_a_start_runs_the_program_to_its_stop_at_rest,
    test_a_stop_ends_the_program_mid_move_and_a_start_begins_at_the_top,
    test_is_a_program_control,
)
from tests.sim.test_linuxcncrsh_server import _wait
from tests.xmalign.test_live_e2e import try_out_plan
from xmalign.errors import DeviceError
from xmalign.machine import Machine
from xmalign.roles import WallClock

pytestmark = pytest.mark.linuxcnc

#: Travel wide enough for the contract's points; homed at 0.
TRAVEL_MM = {axis: (-5000.0, 5000.0) for axis in "XYZ"}
RAPID_MM_MIN = 60_000.0


class HeadlessLinuxcnc:
    """One LinuxCNC for the tests of this file, its [TRAJ] LINEAR_UNITS inches (the
    positions compared in mm): started when first needed, started again after a test
    stopped it (the contract's lost source, this file's last test)."""

    def __init__(self, folder: Path) -> None:
        machine = SimMachine(
            travel_mm=TRAVEL_MM,
            max_velocity_mm_s=1000.0,
            max_acceleration_mm_s2=10000.0,
            linear_units="inch",
        )
        self.machine = machine
        self.port = free_port()
        self.ini = write_sim_config(folder, machine, f"linuxcncrsh --port {self.port}")
        self._running: ExitStack | None = None

    def start(self) -> None:
        if self._running is not None:
            return
        with ExitStack() as stack:
            stack.enter_context(linuxcnc_serving(self.ini, self.port))
            operator = open_linuxcnc("127.0.0.1", self.port, 5.0)
            stack.callback(operator.close)
            bring_up(operator)
            self._running = stack.pop_all()

    def stop(self) -> None:
        if self._running is not None:
            self._running.close()
            self._running = None


@pytest.fixture(scope="module")
def headless() -> Iterator[HeadlessLinuxcnc]:
    folder = Path(tempfile.mkdtemp(prefix="xmalign-linuxcnc-module-"))
    folder.chmod(0o777)
    linuxcnc = HeadlessLinuxcnc(folder / "cnc")
    try:
        yield linuxcnc
    finally:
        linuxcnc.stop()
        shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture
def local(headless: HeadlessLinuxcnc) -> Iterator[LocalLinuxCnc]:
    """The running LinuxCNC through the real module."""
    headless.start()
    cnc = LocalLinuxCnc(find_linuxcnc_module(), clock=WallClock())
    yield cnc
    cnc.close()


@pytest.fixture
def control_stand(headless: HeadlessLinuxcnc, local: LocalLinuxCnc) -> Iterator[ControlStand]:
    """The program-control contract's stand: the module (linuxcncrsh's:
    test_real_program_control_contract.py, a LinuxCNC of its own), the machine braking at
    the contract's rate (the feed hold in the braking distance)."""
    with braking_at(headless.machine, ACCELERATION_MM_S2):
        yield ControlStand(local, headless.ini.parent)


@pytest.fixture
def rsh(headless: HeadlessLinuxcnc, local: LocalLinuxCnc) -> Iterator[LinuxCnc]:
    """The same LinuxCNC over linuxcncrsh."""
    client = open_linuxcnc("127.0.0.1", headless.port, 5.0)
    yield client
    client.close()


def _placer(cnc: LocalLinuxCnc) -> Callable[[float, float, float], None]:
    def place(x: float, y: float, z: float) -> None:  # an MDI move, waited out
        cnc.move_mdi(np.array([x, y, z]), RAPID_MM_MIN, 1e-6, 30.0)

    return place


def _mover(cnc: LocalLinuxCnc) -> Callable[[float, float, float], None]:
    def move(x: float, y: float, z: float) -> None:  # a slow MDI move, returns once under way
        before = cnc.commanded_mm()
        cnc._set_mode("mdi")
        cnc._mdi(mdi_move_line(np.array([x, y, z]), 120.0))  # 1 mm: 0.5 s
        _wait(lambda: not np.array_equal(cnc.commanded_mm(), before))

    return move


@pytest.fixture(params=["module", "linuxcncrsh"])
def stand(
    request: pytest.FixtureRequest, headless: HeadlessLinuxcnc, local: LocalLinuxCnc
) -> Iterator[Stand]:
    """The contract's source: the module, or linuxcncrsh on the same LinuxCNC (the
    machine placed and moved through the module either way)."""
    if request.param == "module":
        yield Stand(
            local,
            _placer(local),
            headless.stop,
            find_linuxcnc_module().nmlfile,
            WallClock(),
            move=_mover(local),
        )
        return
    client = open_linuxcnc("127.0.0.1", headless.port, 5.0)

    def cut() -> None:  # the connection dropped (stopping LinuxCNC a second time in a row
        # left the module's error channel invalid in this process: "Error buffer invalid")
        assert isinstance(client.link, LinuxcncrshLink) and client.link._socket is not None
        client.link._socket.shutdown(socket.SHUT_RDWR)

    try:
        yield Stand(
            client,
            _placer(local),
            cut,
            f"127.0.0.1:{headless.port}",
            WallClock(),
            move=_mover(local),
        )
    finally:
        client.close()


def _program(folder: Path, text: str) -> str:
    path = folder / "p.ngc"
    path.write_text(text)
    path.chmod(0o644)
    return str(path)


def test_the_module_and_linuxcncrsh_agree_on_one_machine(
    local: LocalLinuxCnc, rsh: LinuxCnc, headless: HeadlessLinuxcnc
) -> None:
    local.check_ready()
    rsh.check_ready()
    _placer(local)(120.25, -80.5, 30.125)
    for cnc in (local, rsh):
        assert np.allclose(cnc.position_mm(), [120.25, -80.5, 30.125], atol=1e-6)
        assert np.allclose(cnc.commanded_mm(), [120.25, -80.5, 30.125], atol=1e-6)
        assert cnc.is_standstill() and cnc.program_state() == "idle"
    program = _program(
        headless.ini.parent,
        "G21 G90 G49\nG53 G1 X10 Y20 Z-30 F60000\nM0\nG53 G1 X400 F3000\nM0\nM2\n",
    )
    local.start_program(program)
    _wait(lambda: local.program_state() == "paused" and local.is_standstill())  # the M0
    # at rest within in_position_mm, the actual may still lag by the last servo period's
    # step (0.54 um seen); xmalign captures within tolerance_mm and averages for the dwell
    settles_at(local, [10, 20, -30])
    for cnc in (local, rsh):
        assert cnc.program_state() == "paused" and cnc.is_standstill()
        assert np.allclose(cnc.position_mm(), [10, 20, -30], atol=1e-6)
        assert cnc.loaded_program() == program
    local.resume()
    _wait(lambda: local.position_mm()[0] > 60.0)  # 50 mm/s on the way to X 400
    assert local.program_state() == rsh.program_state() == "running"
    assert not local.is_standstill() and not rsh.is_standstill()
    local.hold()  # feed hold mid-move
    _wait(lambda: local.program_state() == "paused" and local.is_standstill())
    held = settled_mm(local)
    assert rsh.program_state() == "paused" and rsh.is_standstill()
    assert np.allclose(rsh.position_mm(), held, atol=1e-6) and 60.0 < held[0] < 400.0
    time.sleep(0.2)
    assert np.array_equal(local.position_mm(), held)
    local.resume()
    _wait(lambda: local.program_state() == "paused" and local.is_standstill(), 30.0)  # next M0
    settles_at(local, [400, 20, -30])
    local.stop_program()
    assert local.program_state() == rsh.program_state() == "idle"


def test_refusals_carry_linuxcncs_message(local: LocalLinuxCnc) -> None:
    refused = r"refused 'program_open\('/nowhere.ngc'\)' \(Unable to open file </nowhere.ngc>"
    with pytest.raises(DeviceError, match=refused):
        local.start_program("/nowhere.ngc")
    _placer(local)(10.0, 20.0, -5.0)
    # refused at once (RCS_ERROR for the MDI line), or once at rest short of the target
    beyond = (
        r"(refused 'mdi\('G21 G90 G94 G53 G1 X6000.0000 Y20.0000 Z-5.0000 F60000.0'\)'"
        r"|did not move to \[6000.0, 20.0, -5.0\] mm) \(.*would exceed X's positive limit"
    )
    with pytest.raises(DeviceError, match=beyond):
        local.move_mdi(np.array([6000.0, 20.0, -5.0]), RAPID_MM_MIN, 0.005, 30.0)
    assert np.allclose(local.position_mm(), [10.0, 20.0, -5.0], atol=1e-6)


def test_mdi_moves_through_the_module(local: LocalLinuxCnc, reference_machine: Machine) -> None:
    mover = MdiMover(local, reference_machine, 0.005, 60.0)
    for target in ([150.0, 100.0, -50.0], [320.0, 40.0, -150.0]):
        mover.move_to(np.array(target), 6000.0)
        assert np.linalg.norm(local.position_mm() - target) <= 0.005
        assert local.program_state() == "idle" and local.is_standstill()


@pytest.fixture
def module_shop(
    headless: HeadlessLinuxcnc,
    tmp_path_factory: pytest.TempPathFactory,
    reference_machine_path: Path,
    linuxcnc_dir: Path,
) -> Iterator[Shop]:
    headless.stop()  # one LinuxCNC per host: the shop starts its own
    plan_dir = try_out_plan(tmp_path_factory.mktemp("plan"), reference_machine_path, LINES)
    with shop_running(plan_dir, linuxcnc_dir, source="linuxcnc") as served:
        yield served


def test_an_unattended_run_through_the_module(module_shop: Shop) -> None:
    """Lines Z and X with no one at the machine: xmalign starts its program through the
    module, sets the units at each line's stop, captures at each point's stop, resumes."""
    shop = module_shop
    run = shop.run()
    assert run.finish(timeout_s=300) == 0, run.said()
    expected = _expected_keys(shop.workdir / "plan.json")
    assert {key[0] for key in expected} == set(LINES)
    assert _keys(shop.workdir / "m.csv") == expected
    said = run.said()
    assert f"{len(expected)} points captured; {len(expected)} points in m.csv" in said
    wire = (shop.workdir / "wire.log").read_text()
    assert "LinuxCNC on this computer" in wire and "> auto(AUTO_RESUME)" in wire, wire[-2000:]
    assert "> 'set " not in wire  # nothing went over linuxcncrsh
    print(*(line for line in said.splitlines() if "machine time" in line))


# Last of this file's tests (pytest runs a module's tests in the order they are defined):
# it stops LinuxCNC. The module's channels do not survive a restart of LinuxCNC within
# one process (seen with 2.9: afterwards the error channel answers "Error buffer invalid",
# or a fresh stat reads task_state 0); a new process is not affected (xmalign run
# --resume is one). So every test of this worker that uses the module in this process
# uses this file's LinuxCNC, before this test.
test_a_lost_source_is_a_transport_error_naming_it = (
    machine_position_contract.test_a_lost_source_is_a_transport_error_naming_it
)
