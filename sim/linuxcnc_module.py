"""A stand-in for LinuxCNC's Python module ``linuxcnc``, served by the simulated LinuxCNC.

:func:`simulated_module` gives a module with the part of the real module's API
that :mod:`firmware_iface.linuxcnc_module` uses (its ``MODULE_API``; the
constants carry the real module's values, LinuxCNC 2.9), in front of a
:class:`~sim.linuxcnc_task.SimulatedLinuxcnc`, the same simulated LinuxCNC the
simulated linuxcncrsh serves:

* ``stat()`` and ``stat.poll()``: a snapshot of the status (``actual_position``
  and ``position`` are 9-tuples XYZABCUVW in the machine's units, ``linear_units``
  machine units per mm; ``homed`` and ``joint`` one entry per
  joint of LinuxCNC's 16); ``stat()`` raises ``error`` once LinuxCNC has shut
  down, as the real one does (``emcStatusBuffer invalid err=3``);
* ``command()``: ``mode``, ``program_open``, ``auto``, ``abort``, ``mdi``; each
  takes the next serial number, which the status echoes with ``RCS_DONE``
  (``RCS_EXEC`` while a run or an MDI line it started goes on) or ``RCS_ERROR``
  when the task refused it (its message then on the error channel); a dead task
  (``kill_task``) echoes none; ``task_state`` is ``STATE_ESTOP`` in E-stop;
* ``error_channel().poll()``: ``(OPERATOR_ERROR, text)`` once per message, else None.

``inpos`` is true when nothing is left to move (not in a feed hold mid-move, as
LinuxCNC's); ``current_vel`` is the simulated path speed; ``paused`` is true at
an M0 and in a feed hold (as LinuxCNC's ``traj.paused``, seen with 2.9).
"""

from __future__ import annotations

import itertools
import types
from collections.abc import Callable
from typing import Any

from sim.linuxcnc_task import HOMED_JOINTS, JOINTS, SimulatedLinuxcnc

#: The real module's values (LinuxCNC 2.9; tests/firmware_iface/test_linuxcnc_module.py).
CONSTANTS = {
    "MODE_MANUAL": 1,
    "MODE_AUTO": 2,
    "MODE_MDI": 3,
    "AUTO_RUN": 0,
    "AUTO_PAUSE": 1,
    "AUTO_RESUME": 2,
    "INTERP_IDLE": 1,
    "INTERP_READING": 2,
    "INTERP_PAUSED": 3,
    "INTERP_WAITING": 4,
    "STATE_ESTOP": 1,
    "STATE_ON": 4,
    "RCS_DONE": 1,
    "RCS_EXEC": 2,
    "RCS_ERROR": 3,
    "OPERATOR_ERROR": 11,
}
MAX_JOINTS = 16
MODES = {CONSTANTS[f"MODE_{mode.upper()}"]: mode for mode in ("manual", "auto", "mdi")}
INTERP = {
    "idle": CONSTANTS["INTERP_IDLE"],
    "running": CONSTANTS["INTERP_WAITING"],
    "paused": CONSTANTS["INTERP_PAUSED"],
}
NML_FILE = "simulated LinuxCNC"


class LinuxcncError(RuntimeError):
    """The module's ``linuxcnc.error``."""


class _Echo:
    """The serial number and status of the last command the simulated task took."""

    def __init__(self) -> None:
        self.serial = 0
        self.state = CONSTANTS["RCS_DONE"]
        self.started = False  # a run or an MDI line: RCS_EXEC while it goes on
        self.serials = itertools.count(1)


def simulated_module(linuxcnc: SimulatedLinuxcnc) -> types.ModuleType:
    """A ``linuxcnc`` module whose ``stat``, ``command`` and ``error_channel`` reach
    ``linuxcnc``."""
    module = types.ModuleType("linuxcnc", "simulated LinuxCNC module (sim/linuxcnc_module.py)")
    echo = _Echo()

    def state() -> int:
        if echo.started and echo.state == CONSTANTS["RCS_DONE"] and linuxcnc.busy:
            return CONSTANTS["RCS_EXEC"]
        return echo.state

    class Stat:
        def __init__(self) -> None:
            if not linuxcnc.running:
                raise LinuxcncError("emcStatusBuffer invalid err=3")

        def poll(self) -> None:
            position = (
                *(float(v) for v in linuxcnc.position_units()),
                0.0,
                0.0,
                0.0,
                0.0,
                0.0,
                0.0,
            )
            self.linear_units = linuxcnc.units_per_mm
            self.actual_position = self.position = position
            self.inpos = linuxcnc.in_position
            self.current_vel = linuxcnc.cnc.speed_mm_s()
            self.interp_state = INTERP[linuxcnc.program_status]
            self.paused = linuxcnc.program_status == "paused"
            self.task_state = CONSTANTS["STATE_ESTOP" if linuxcnc.estop else "STATE_ON"]
            self.homed = tuple(int(j < HOMED_JOINTS) for j in range(MAX_JOINTS))
            self.joint = tuple({"fault": 0, "homed": self.homed[j]} for j in range(MAX_JOINTS))
            self.joints = JOINTS
            self.file = linuxcnc.opened or ""
            self.echo_serial_number = echo.serial
            self.state = state()

    class Command:
        serial = 0

        def _take(self, action: Callable[[], bool], starts: bool = False) -> None:
            self.serial = next(echo.serials)
            if not linuxcnc.task_alive:
                return  # a dead task receives nothing: the status never echoes it
            took = action()
            echo.serial = self.serial
            echo.state = CONSTANTS["RCS_DONE" if took else "RCS_ERROR"]
            echo.started = starts

        def mode(self, mode: int) -> None:
            self._take(lambda: linuxcnc.set_mode(MODES.get(mode, str(mode))))

        def program_open(self, path: str) -> None:
            self._take(lambda: linuxcnc.open(path))

        def auto(self, code: int, line: int = 0) -> None:
            action = {
                CONSTANTS["AUTO_RUN"]: linuxcnc.run,
                CONSTANTS["AUTO_PAUSE"]: linuxcnc.pause,
                CONSTANTS["AUTO_RESUME"]: linuxcnc.resume,
            }[code]
            self._take(action, starts=code == CONSTANTS["AUTO_RUN"])

        def abort(self) -> None:
            self._take(linuxcnc.abort)

        def mdi(self, line: str) -> None:
            self._take(lambda: linuxcnc.mdi(line), starts=True)

    class ErrorChannel:
        def poll(self) -> tuple[int, str] | None:
            text = linuxcnc.take_error()
            return None if text is None else (CONSTANTS["OPERATOR_ERROR"], text)

    names: dict[str, Any] = {
        **CONSTANTS,
        "stat": Stat,
        "command": Command,
        "error_channel": ErrorChannel,
        "error": LinuxcncError,
        "nmlfile": NML_FILE,
    }
    for name, value in names.items():
        setattr(module, name, value)
    return module
