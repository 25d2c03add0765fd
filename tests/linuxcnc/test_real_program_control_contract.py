"""The program-control contract (tests/firmware_iface/program_control_contract.py) against a
real headless LinuxCNC 2.9 over linuxcncrsh.

LinuxCNC (Debian ``linuxcnc-uspace``) runs with ``linuxcncrsh`` as its display
(harness.py) on a machine whose [TRAJ] LINEAR_UNITS are inches: the contract's
positions are in mm, so the driver converts (``abs_act_pos`` is in inches). An
operator session brings the machine up (E-stop reset, machine on, home); each
test then controls it through a session of its own. Through LinuxCNC's Python
module the contract runs in test_real_linuxcnc_module.py, on that file's LinuxCNC
(inches too, braking at the contract's rate while the contract runs): the
module's channels do not survive a restart of LinuxCNC within one process. The
simulated LinuxCNC passes the same contract over both channels in
tests/firmware_iface/test_program_control_contract.py.

The machine brakes at the contract's 100 mm/s^2. The E-stop and the dead task
run in test_real_faults.py, each on a LinuxCNC of its own (seen with 2.9: after
an E-stop during a program, linuxcncrsh refused to switch the machine on again).

Seen with 2.9 (not part of the contract, the simulated LinuxCNC differs): a
resume or a feed hold with no program running is accepted (``SET RESUME ACK``,
``RCS_DONE``), and a hold then shows the program status PAUSED.
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from cli_helpers import free_port
from harness import SimMachine, bring_up, linuxcnc_serving, write_sim_config

from firmware_iface.linuxcncrsh import LinuxCnc, open_linuxcnc
from tests.firmware_iface.program_control_contract import (  # noqa: F401 (the contract's tests, run here)
    ACCELERATION_MM_S2,
    ControlStand,
    interrupt_the_reply,
    test_a_feed_hold_in_the_braking_distance_stops_at_the_stop_and_needs_two_resumes,
    test_a_feed_hold_stops_on_the_path_and_a_resume_goes_on,
    test_a_program_it_cannot_open_is_refused_with_its_message,
    test_a_request_interrupted_before_its_reply_does_not_answer_the_next,
    test_a_start_runs_the_program_to_its_stop_at_rest,
    test_a_stop_ends_the_program_mid_move_and_a_start_begins_at_the_top,
    test_is_a_program_control,
)

pytestmark = pytest.mark.linuxcnc


class _Headless:
    """An inch LinuxCNC serving linuxcncrsh, and the operator's session that brought it up."""

    def __init__(self, folder: Path, port: int, operator: LinuxCnc) -> None:
        self.folder = folder
        self.port = port
        self.operator = operator


@pytest.fixture(scope="module")
def headless() -> Iterator[_Headless]:
    folder = Path(tempfile.mkdtemp(prefix="xmalign-linuxcnc-control-"))
    folder.chmod(0o777)
    port = free_port()
    machine = SimMachine(linear_units="inch", max_acceleration_mm_s2=ACCELERATION_MM_S2)
    ini = write_sim_config(folder / "cnc", machine, f"linuxcncrsh --port {port}")
    try:
        with linuxcnc_serving(ini, port):
            operator = open_linuxcnc("127.0.0.1", port, 5.0)
            try:
                bring_up(operator)
                yield _Headless(ini.parent, port, operator)
            finally:
                operator.close()
    finally:
        shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture
def control_stand(headless: _Headless) -> Iterator[ControlStand]:
    control = open_linuxcnc("127.0.0.1", headless.port, 5.0)
    try:
        yield ControlStand(
            control,
            headless.folder,
            interrupted=interrupt_the_reply(control),
        )
    finally:
        control.stop_program()
        control.close()
