"""The program-control contract (program_control_contract.py) against the simulated LinuxCNC.

Over its remote shell (sim/servers/linuxcncrsh.py, answering as LinuxCNC 2.9's
linuxcncrsh did in tests/linuxcnc) and through the simulated ``linuxcnc`` Python
module (sim/linuxcnc_module.py), both in front of the same kind of simulated
LinuxCNC on the wall clock, its machine braking as the contract's do;
tests/linuxcnc/test_real_program_control_contract.py runs the same contract
against a real headless LinuxCNC.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from program_control_contract import (  # noqa: F401 (the contract's tests, run here)
    ACCELERATION_MM_S2,
    ControlStand,
    interrupt_the_reply,
    test_a_dead_task_keeps_its_last_status_and_a_command_names_it,
    test_a_feed_hold_in_the_braking_distance_stops_at_the_stop_and_needs_two_resumes,
    test_a_feed_hold_stops_on_the_path_and_a_resume_goes_on,
    test_a_program_it_cannot_open_is_refused_with_its_message,
    test_a_request_interrupted_before_its_reply_does_not_answer_the_next,
    test_a_start_runs_the_program_to_its_stop_at_rest,
    test_a_stop_ends_the_program_mid_move_and_a_start_begins_at_the_top,
    test_an_e_stop_ends_the_program_and_the_readiness_check_names_it,
    test_is_a_program_control,
)

from firmware_iface.linuxcnc_control import LinuxCncControl
from firmware_iface.linuxcnc_module import LocalLinuxCnc
from firmware_iface.linuxcncrsh import open_linuxcnc
from sim.cnc import SimulatedCnc
from sim.linuxcnc_module import simulated_module
from sim.servers.linuxcncrsh import LinuxcncrshServer
from xmalign.machine import Machine
from xmalign.roles import WallClock


@pytest.fixture(params=["linuxcncrsh", "module"])
def control_stand(
    request: pytest.FixtureRequest, tmp_path: Path, reference_machine: Machine
) -> Iterator[ControlStand]:
    cnc = reference_machine.cnc.model_copy(update={"acceleration_mm_s2": ACCELERATION_MM_S2})
    machine = reference_machine.model_copy(update={"cnc": cnc})
    server = LinuxcncrshServer(SimulatedCnc(machine, WallClock()), machine)
    server.start()
    linuxcnc = server.linuxcnc
    control: LinuxCncControl
    if request.param == "linuxcncrsh":
        control = open_linuxcnc("127.0.0.1", server.port, 2.0, start_timeout_s=0.5)
    else:
        control = LocalLinuxCnc(simulated_module(linuxcnc), timeout_s=1.0)
    stand = ControlStand(
        control,
        tmp_path,
        press_estop=linuxcnc.press_estop,
        kill_task=linuxcnc.kill_task,
    )
    if request.param == "linuxcncrsh":
        stand.interrupted = interrupt_the_reply(control)
    try:
        yield stand
    finally:
        control.close()
        server.stop()


@pytest.fixture
def dying_stand(control_stand: ControlStand) -> ControlStand:
    """A simulated LinuxCNC is made for each test: it may be left in E-stop or dead."""
    return control_stand
