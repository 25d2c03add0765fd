"""The simulated LinuxCNC behind both of its simulated interfaces.

:class:`SimulatedLinuxcnc` is LinuxCNC's task as xmalign meets it, in front of a
:class:`~sim.cnc.SimulatedCnc`: a mode (manual, auto, MDI), the open program,
a program run (LinuxCNC dialect) with M0 pausing it until a resume, a feed
hold (the simulated machine stops where it is at once and goes on to the same
target on a resume; a hold that comes in a move's final deceleration stops it
at the move's end, as LinuxCNC 2.9's does: before a programmed stop, one resume
then leaves the program paused at that stop), an abort, one MDI line at a time,
and LinuxCNC's error slot (the last message, read once). The machine starts out
of E-stop, on and homed (joints 0 to 2 of 6); :meth:`SimulatedLinuxcnc.press_estop`
ends the program and refuses every command from then on;
after :meth:`~SimulatedLinuxcnc.kill_task` (milltask dead) the status stays as it
was and no command is taken, as LinuxCNC 2.9's.

Two interfaces serve it, as LinuxCNC serves its task: the remote shell
(:class:`sim.servers.linuxcncrsh.LinuxcncrshServer`) and the Python module
(:func:`sim.linuxcnc_module.simulated_module`). Each command returns whether
the task took it; a command it refuses leaves a message in the error slot
where LinuxCNC's would, and so does a program that cannot be opened or read.

The program runs on the wall clock or, with ``lockstep``, as a follower of a
:class:`~sim.clock.LockstepClock` (the served dry run): then a hold, a resume
or an abort acts at the virtual time it arrives.
"""

from __future__ import annotations

import logging
import re
import threading
from pathlib import Path
from typing import Literal

import numpy as np

from sim.clock import Follower, LockstepClock
from sim.cnc import DEFAULT_ACCELERATION_MM_S2, SimulatedCnc, read_program
from sim.cnc import _Dwell as Dwell
from sim.cnc import _End as End
from sim.cnc import _Move as Move
from sim.cnc import _Stop as Stop
from xmalign.errors import XmalignError
from xmalign.machine import Machine

logger = logging.getLogger(__name__)

#: Joints of the simulated LinuxCNC (XYZABC); the first three are homed.
JOINTS = 6
HOMED_JOINTS = 3
#: Machine units per mm of each [TRAJ] LINEAR_UNITS the simulated LinuxCNC can have.
UNITS_PER_MM = {"mm": 1.0, "inch": 1.0 / 25.4}
#: How often a move that brakes to its end after a hold is checked, s.
COAST_STEP_S = 0.005
_UNITS_WORD = re.compile(r"(?i)\bG\s*0*(20|21)(?![\d.])")
_LENGTH_WORD = re.compile(r"(?i)\b([XYZF])\s*([-+]?(?:\d+\.?\d*|\.\d+))")


class _Program:
    """A program running on the simulated CNC: M0, feed hold, abort.

    On the wall clock it runs in a thread of its own; on a
    :class:`~sim.clock.LockstepClock` as a follower of it (a move takes its
    time in virtual seconds; a hold, a resume or an abort lets it run at once,
    at the current virtual time).
    """

    def __init__(
        self,
        cnc: SimulatedCnc,
        steps: list,
        lockstep: LockstepClock | None,
        acceleration_mm_s2: float,
    ) -> None:
        self.cnc = cnc
        self.steps = steps
        self.acceleration_mm_s2 = acceleration_mm_s2
        self.state = "running"
        self.lockstep = lockstep
        self._wake = threading.Condition()
        self._hold = False
        self._resume = False
        self._abort = False
        self._follower: Follower | None = None
        self._thread: threading.Thread | None = None
        #: Held mid-move (a feed hold; not an M0): the rest of the move is still queued.
        self.held_mid_move = False

    def start(self) -> None:
        if self.lockstep is not None:
            self._follower = self.lockstep.start_follower(self._run, "linuxcnc-program")
            return
        self._thread = threading.Thread(target=self._run, name="linuxcnc-program", daemon=True)
        self._thread.start()

    def _signal(self, flag: str) -> None:
        with self._wake:
            setattr(self, flag, True)
            self._wake.notify_all()
        if self.lockstep is not None and self._follower is not None:
            self.lockstep.wake(self._follower)

    def hold(self) -> None:
        self._signal("_hold")

    def resume(self) -> None:
        self._signal("_resume")

    def abort(self) -> None:
        self._signal("_abort")
        if self._thread is not None:
            self._thread.join(5.0)

    def _run(self) -> None:
        try:
            for step in self.steps:
                if self._abort:
                    break
                if isinstance(step, Move):
                    self._move(step.target_mm, step.feed_mm_min)
                elif isinstance(step, Stop):
                    self._paused()
                elif isinstance(step, Dwell):
                    if self._wait(step.seconds) and not self._abort:
                        self._paused()  # held while dwelling
                elif isinstance(step, End):
                    break
        except XmalignError as error:
            logger.warning("simulated LinuxCNC: program aborted: %s", error)
        finally:
            self.cnc.stop()
            self.state = "idle"

    def _wait(self, seconds: float) -> bool:
        """Let ``seconds`` pass unless a hold or an abort comes first (True: it came)."""
        if self.lockstep is not None:
            self.lockstep.sleep(seconds)
            return self._hold or self._abort
        with self._wake:
            return self._wake.wait_for(lambda: self._hold or self._abort, seconds)

    def _paused(self) -> None:
        with self._wake:
            self.state = "paused"
            self._resume = False
            if self.lockstep is None:
                self._wake.wait_for(lambda: self._resume or self._abort)
        while self.lockstep is not None and not (self._resume or self._abort):
            self.lockstep.wait_for_resume()
        with self._wake:
            self._hold = self._resume = False
            self.state = "running"

    def _move(self, target_mm: np.ndarray, feed_mm_min: float) -> None:
        while not self._abort:
            duration_s = self.cnc.start_move(target_mm, feed_mm_min)
            if not self._wait(duration_s):
                return
            if self._abort:
                return
            if self._braking(target_mm):
                self._coast()  # LinuxCNC: a hold in the final deceleration stops at the end
            else:
                self.cnc.stop()  # feed hold
            self.held_mid_move = True
            self._paused()
            self.held_mid_move = False

    def _braking(self, target_mm: np.ndarray) -> bool:
        """The machine is in its final deceleration to ``target_mm`` (it cannot stop sooner)."""
        speed = self.cnc.speed_mm_s()
        left_mm = float(np.linalg.norm(target_mm - self.cnc.position_mm()))
        return left_mm <= speed * speed / (2.0 * self.acceleration_mm_s2) * (1 + 1e-6) + 1e-9

    def _coast(self) -> None:
        """Let the move end (it brakes to its target) unless an abort comes."""
        while not self.cnc.is_standstill() and not self._abort:
            if self.lockstep is not None:
                self.lockstep.sleep(COAST_STEP_S)
                continue
            with self._wake:
                self._wake.wait_for(lambda: self._abort, COAST_STEP_S)


class SimulatedLinuxcnc:
    """LinuxCNC's task for ``cnc`` (the world's simulated CNC); see the module docstring."""

    def __init__(
        self,
        cnc: SimulatedCnc,
        machine: Machine,
        lockstep: LockstepClock | None = None,
        linear_units: Literal["mm", "inch"] = "mm",
    ) -> None:
        self.cnc = cnc
        self.linear_units = linear_units
        #: G20/G21 in force for MDI lines (LinuxCNC starts in the machine's units).
        self.program_units = linear_units
        self.machine = machine
        self.lockstep = lockstep
        self.rapid_mm_min = machine.feed_mm_min.rapid
        self.mode: Literal["manual", "auto", "mdi"] = "manual"
        self.program: _Program | None = None
        self.opened: str | None = None
        self._last_opened: str | None = None
        self.error: str | None = None
        #: False once shut down (:meth:`shut_down`): its interfaces then fail as LinuxCNC's do.
        self.running = True
        #: E-stop pressed (:meth:`press_estop`); the machine is on while not.
        self.estop = False
        self.acceleration_mm_s2 = machine.cnc.acceleration_mm_s2 or DEFAULT_ACCELERATION_MM_S2
        #: The status its task last wrote, once the task is dead (:meth:`kill_task`).
        self._last_status: tuple[str, np.ndarray, bool] | None = None

    # -- status -------------------------------------------------------------------
    @property
    def program_status(self) -> Literal["idle", "running", "paused"]:
        if self._last_status is not None:
            return self._last_status[0]  # type: ignore[return-value]
        return "idle" if self.program is None else self.program.state  # type: ignore[return-value]

    @property
    def task_alive(self) -> bool:
        """False once its task is dead (:meth:`kill_task`): no command is taken."""
        return self._last_status is None

    @property
    def busy(self) -> bool:
        return self.program_status != "idle"

    def position_mm(self) -> np.ndarray:
        """Actual and commanded position alike (the simulated drives follow exactly), mm (3,)."""
        if self._last_status is not None:
            return self._last_status[1].copy()
        return self.cnc.position_mm()

    @property
    def units_per_mm(self) -> float:
        """LinuxCNC's ``linear_units``: machine units per mm."""
        return UNITS_PER_MM[self.linear_units]

    def position_units(self) -> np.ndarray:
        """The position in the machine's units, as LinuxCNC reports it (3,)."""
        return self.position_mm() * self.units_per_mm

    @property
    def in_position(self) -> bool:
        """As LinuxCNC's ``inpos``: nothing left to move (false in a feed hold mid-move)."""
        if self._last_status is not None:
            return self._last_status[2]
        held = self.program is not None and self.program.held_mid_move
        return self.cnc.is_standstill() and not held

    def take_error(self) -> str | None:
        """LinuxCNC's last error message, once (None when there is none)."""
        error, self.error = self.error, None
        return error

    def _refuse(self, message: str) -> bool:
        self.error = message
        return False

    # -- commands -----------------------------------------------------------------
    def set_mode(self, mode: str) -> bool:
        if self.estop:
            return self._refuse("can't do that in E-stop")
        if mode not in ("manual", "auto", "mdi"):
            return self._refuse(f"unknown mode {mode}")
        if self.busy:
            return self._refuse(f"can't switch to {mode} mode while a program runs")
        self.mode = mode  # type: ignore[assignment]
        return True

    def open(self, path: str) -> bool:
        if self.busy:
            return self._refuse("can't open a program while one runs")
        self._last_opened = path
        if not Path(path).is_file():
            self.opened = None
            return self._refuse(f"Unable to open file <{path}>")
        self.opened = path
        return True

    def run(self) -> bool:
        """Run the open program (or the last one asked for, as LinuxCNC reopens it)."""
        path = self.opened or self._last_opened
        if self.estop:
            return self._refuse("can't do that in E-stop")
        if path is None or self.busy or self.mode != "auto":
            return self._refuse("can't run: no program open, a program runs, or not in auto mode")
        try:
            text = Path(path).read_text(encoding="utf-8")
        except OSError as error:
            self.error = f"Unable to open file <{path}>: {error}"
            return True  # LinuxCNC takes the run and reports the error after
        return self._start(text, f"file <{path}>")

    def mdi(self, line: str) -> bool:
        if self.estop:
            return self._refuse("can't do that in E-stop")
        if self.busy or self.mode != "mdi":
            return self._refuse("can't execute MDI: a program runs, or not in MDI mode")
        return self._start(f"G21 G90\n{self._mdi_in_mm(line)}\nM2\n", "MDI command")

    def _mdi_in_mm(self, line: str) -> str:
        """``line`` with the program units in force applied (G20/G21 modal): in mm."""
        for match in _UNITS_WORD.finditer(line):
            self.program_units = "inch" if match[1] == "20" else "mm"
        line = _UNITS_WORD.sub("", line)
        if self.program_units == "mm":
            return line
        return _LENGTH_WORD.sub(lambda word: f"{word[1]}{float(word[2]) * 25.4:.6f}", line)

    def pause(self) -> bool:
        return self._to_program("hold")

    def press_estop(self) -> None:
        """E-stop (halcmd, a button): the program is aborted, the machine off."""
        self.estop = True
        if self.program is not None:
            self.program.abort()

    def kill_task(self) -> None:
        """Its task dies: the status stays as it was, no command is taken any more."""
        self._last_status = (self.program_status, self.position_mm(), self.in_position)
        if self.program is not None:
            self.program.abort()

    def resume(self) -> bool:
        return self._to_program("resume")

    def abort(self) -> bool:
        if self.estop:
            return self._refuse("can't do that in E-stop")
        if self.program is not None:
            self.program.abort()
        return True

    def shut_down(self) -> None:
        """Stop as LinuxCNC going down does: the program aborted, nothing answers any more."""
        self.abort()
        self.running = False

    def _to_program(self, action: Literal["hold", "resume"]) -> bool:
        if self.estop:
            return self._refuse("can't do that in E-stop")
        if self.program is None:
            return self._refuse(f"no program to {action}")
        getattr(self.program, action)()
        return True

    def _start(self, text: str, what: str) -> bool:
        """Run a program (a file's, or one MDI command); a bad one sets LinuxCNC's error."""
        try:
            position_mm = self.cnc.position_mm()
            steps = read_program(text, "linuxcnc", self.machine, position_mm, self.rapid_mm_min)
        except XmalignError as error:
            self.error = f"Unable to run {what}: {error}"
            return True
        self.error = None
        self.program = _Program(self.cnc, steps, self.lockstep, self.acceleration_mm_s2)
        self.program.start()
        return True
