"""The program-control contract's faults against a real headless LinuxCNC 2.9 over linuxcncrsh.

Each test gets a LinuxCNC of its own (harness.py; inches, braking at the
contract's 100 mm/s^2), brought up by an operator session and left as the fault
leaves it: the E-stop as a broken E-stop chain would press it (halcmd: LinuxCNC's
``iocontrol.0.emc-enable-in`` taken off the E-stop loop and set false; seen with
2.9: linuxcncrsh then refuses to switch the machine on again while the aborted
program's state lingers), the dead task as a crash would (``milltask`` of this
LinuxCNC killed by its process id; linuxcncrsh goes on answering ``get`` from the
status the task last wrote, and no ``set``).
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from cli_helpers import free_port
from harness import (
    SimMachine,
    bring_up,
    halcmd,
    linuxcnc_serving,
    run_as_user,
    write_sim_config,
)

from firmware_iface.linuxcncrsh import open_linuxcnc
from tests.firmware_iface.program_control_contract import (  # noqa: F401 (the contract's tests, run here)
    ACCELERATION_MM_S2,
    ControlStand,
    interrupt_the_reply,
    test_a_dead_task_keeps_its_last_status_and_a_command_names_it,
    test_an_e_stop_ends_the_program_and_the_readiness_check_names_it,
)

pytestmark = pytest.mark.linuxcnc


def press_estop() -> None:
    """The E-stop chain opens: LinuxCNC's enable input taken off the loop and set false."""
    halcmd("unlinkp", "iocontrol.0.emc-enable-in")
    halcmd("setp", "iocontrol.0.emc-enable-in", "0")


def kill_milltask() -> None:
    """SIGKILL to this LinuxCNC's task (the only LinuxCNC on the host: the host lock)."""
    user = run_as_user()
    found = subprocess.run(
        ["pgrep", "-x", "milltask", *(["-u", user] if user else [])],
        capture_output=True,
        text=True,
        check=True,
    )
    (pid,) = found.stdout.split()
    os.kill(int(pid), signal.SIGKILL)


@pytest.fixture
def dying_stand() -> Iterator[ControlStand]:
    folder = Path(tempfile.mkdtemp(prefix="xmalign-linuxcnc-faults-"))
    folder.chmod(0o777)
    port = free_port()
    machine = SimMachine(linear_units="inch", max_acceleration_mm_s2=ACCELERATION_MM_S2)
    ini = write_sim_config(folder / "cnc", machine, f"linuxcncrsh --port {port}")
    try:
        with linuxcnc_serving(ini, port):
            operator = open_linuxcnc("127.0.0.1", port, 5.0)
            bring_up(operator)
            operator.close()
            control = open_linuxcnc("127.0.0.1", port, 2.0)
            try:
                yield ControlStand(
                    control,
                    ini.parent,
                    press_estop=press_estop,
                    kill_task=kill_milltask,
                    interrupted=interrupt_the_reply(control),
                )
            finally:
                control.close()
    finally:
        shutil.rmtree(folder, ignore_errors=True)
