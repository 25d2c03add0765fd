"""Program control of a LinuxCNC, whichever channel carries it (docs/hardware.md).

xmalign reaches a LinuxCNC in one of two ways: its remote shell ``linuxcncrsh``
over TCP (:mod:`firmware_iface.linuxcncrsh`) or, on the CNC's own computer,
LinuxCNC's Python module ``linuxcnc`` (:mod:`firmware_iface.linuxcnc_module`).
:class:`LinuxCncControl` holds what both share: the waits and checks of
standstill, readiness, the start of a program and an MDI move. A channel
implements only the primitive reads and commands (the abstract methods).

Both give the same quantities, those of LinuxCNC's status (``EMC_STAT``):
the actual position is ``motion.traj.actualPosition`` (linuxcncrsh's
``abs_act_pos``, the module's ``stat.actual_position``), the commanded one
``motion.traj.position``; the program state is ``task.interpState`` read as
linuxcncrsh's ``get program_status`` reads it (reading or waiting: running;
paused: paused; anything else: idle).

Units: LinuxCNC reports positions in its machine units, ``[TRAJ] LINEAR_UNITS``
of its INI (``traj.linearUnits``: machine units per mm), whatever the program's
G20/G21; each channel converts them to mm (linuxcncrsh's ``set
linear_unit_conversion mm`` does not: it converts only offsets, not
``abs_act_pos``; seen with 2.9). An MDI move states its own modes (:func:`mdi_move_line`).
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from typing import Literal

import numpy as np

from xmalign.errors import DeviceError, DeviceTimeoutError, DriveFaultError, OutOfRangeError
from xmalign.geometry import Vec
from xmalign.machine import Machine
from xmalign.roles import Clock, ProgramState, WallClock

log = logging.getLogger(__name__)

Mode = Literal["manual", "auto", "mdi"]
#: How long a program may take to show as running after ``run``, s (``start_timeout_s``).
START_TIMEOUT_S = 5.0
#: The modes an MDI move states: mm (G21), absolute (G90), feed per minute (G94).
MDI_MODES = "G21 G90 G94"


def mdi_move_line(target_mm: Vec, feed_mm_min: float) -> str:
    """The MDI line of a move to ``target_mm`` (3,), machine coordinates, mm, mm/min.

    It states its modes (:data:`MDI_MODES`) rather than trusting those in force:
    on an inch machine (or after a G20, a G91 or a G93) ``G53 G1 X10`` would
    mean 10 inch, an increment, or an inverse time. The modes are modal and stay
    in force after the move (LinuxCNC keeps an MDI line's modal state), until a
    program or another MDI line changes them; xmalign's own program states them too.
    """
    x, y, z = np.asarray(target_mm, dtype=float)
    return f"{MDI_MODES} G53 G1 X{x:.4f} Y{y:.4f} Z{z:.4f} F{feed_mm_min:.1f}"


class LinuxCncControl(ABC):
    """A LinuxCNC: position, standstill, program state and control (``MachinePositionSource``
    and ``ProgramControl`` of :mod:`xmalign.roles`).

    Positions are the actual position of the controlled point in machine
    coordinates (what ``G53`` addresses; no work offset, no G92 offset; the
    tool length offset is what the program sets, and xmalign's program cancels
    it with ``G49``), the coordinates of the plan. xmalign writes an axis
    position only in :meth:`move_mdi`, which :class:`MdiMover` uses, and only
    where ``units.yaml`` allows it (``allow_mdi_moves: true``); no jog, no homing.

    Parameters
    ----------
    name : str
        How errors name this LinuxCNC.
    joints : int
        How many joints must be homed and free of faults.
    in_position_mm : float
        Largest distance between the actual and the commanded position at a standstill.
    clock : Clock, optional
        What the waits run on (default the wall clock).
    start_timeout_s : float
        How long a program may take to show as running after the start, s.
    """

    def __init__(
        self,
        name: str,
        joints: int,
        in_position_mm: float,
        clock: Clock | None = None,
        start_timeout_s: float = START_TIMEOUT_S,
    ) -> None:
        self.name = name
        self.joints = joints
        self.in_position_mm = in_position_mm
        self.clock = clock or WallClock()
        self.start_timeout_s = start_timeout_s

    # -- primitives: what differs per channel -------------------------------------------
    @abstractmethod
    def position_mm(self) -> Vec:
        """Actual X Y Z in machine coordinates, mm, shape (3,)."""

    @abstractmethod
    def commanded_mm(self) -> Vec:
        """Commanded X Y Z in machine coordinates, mm, shape (3,)."""

    @abstractmethod
    def _commanded_at_rest_mm(self) -> Vec | None:
        """The commanded X Y Z (mm, (3,)) when the command stands still, None while it moves."""

    @abstractmethod
    def program_state(self) -> ProgramState:
        """``idle``, ``running`` or ``paused`` (an M0, or a feed hold)."""

    @abstractmethod
    def loaded_program(self) -> str | None:
        """The path of the open program, None when there is none."""

    @abstractmethod
    def _in_estop(self) -> bool: ...

    @abstractmethod
    def _machine_on(self) -> bool: ...

    @abstractmethod
    def _joints_homed(self) -> list[bool]:
        """Whether each joint is homed (at least the first ``joints``)."""

    @abstractmethod
    def _joints_faulted(self) -> list[bool]:
        """Whether each joint has a fault (at least the first ``joints``)."""

    @abstractmethod
    def _set_mode(self, mode: Mode) -> None: ...

    @abstractmethod
    def _open_program(self, path: str) -> None: ...

    @abstractmethod
    def _run_program(self) -> None:
        """Run the open program from its first line."""

    @abstractmethod
    def _mdi(self, line: str) -> None:
        """Execute one MDI line (in MDI mode)."""

    @abstractmethod
    def _error_text(self) -> str:
        """LinuxCNC's last error message, '' when it has none (reading it clears it)."""

    @abstractmethod
    def hold(self) -> None:
        """Feed hold (a pause of the program)."""

    @abstractmethod
    def resume(self) -> None:
        """Go on after an M0 or a feed hold."""

    @abstractmethod
    def stop_program(self) -> None:
        """Abort the program."""

    @abstractmethod
    def close(self) -> None:
        """Release the channel (the program and the machine go on as they are)."""

    # -- shared: the waits and checks ---------------------------------------------------
    def is_standstill(self) -> bool:
        """The command stands still and the actual position is within ``in_position_mm`` of it."""
        commanded = self._commanded_at_rest_mm()
        if commanded is None:
            return False
        miss = float(np.linalg.norm(self.position_mm() - commanded))
        return miss <= self.in_position_mm

    def check_ready(self) -> None:
        """Out of E-stop, machine on, the first ``joints`` joints homed and without fault.

        xmalign does none of this itself: the operator brings the machine up.
        """
        if self._in_estop():
            raise DriveFaultError(
                f"{self.name}: E-stop is pressed; release it, switch the machine on and home it"
            )
        if not self._machine_on():
            raise DriveFaultError(f"{self.name}: the machine is off; switch it on and home it")
        homed = self._joints_homed()[: self.joints]
        if len(homed) < self.joints or not all(homed):
            words = " ".join("YES" if flag else "NO" for flag in homed)
            raise DriveFaultError(
                f"{self.name}: not every joint is homed ({words}); home the machine first"
            )
        faulted = self._joints_faulted()[: self.joints]
        if any(faulted):
            words = " ".join("FAULT" if flag else "OK" for flag in faulted)
            raise DriveFaultError(f"{self.name}: joint fault ({words})")

    def start_program(self, path: str) -> None:
        """Auto mode, open ``path`` (as the LinuxCNC computer sees it), run from the top.

        Runs only once LinuxCNC reports ``path`` open: a LinuxCNC that cannot
        open a file keeps the program it had open, and a run would start that
        one (seen with 2.9 over linuxcncrsh). Returns once LinuxCNC reports the
        program running (its status lags the command); DeviceError with
        LinuxCNC's own message when it does not open or start ``path`` within
        ``start_timeout_s``.
        """
        self._set_mode("auto")
        self._open_program(path)
        self._wait_opened(path)
        self._run_program()
        deadline = self.clock.now() + self.start_timeout_s
        while self.program_state() == "idle":
            if self.clock.now() >= deadline:
                reason = self._error_text() or "no message"
                raise DeviceError(f"{self.name} did not start {path} ({reason})")
            self.clock.sleep(0.02)

    def _wait_opened(self, path: str) -> None:
        """Wait until LinuxCNC reports ``path`` as its open program (its message: refused)."""
        deadline = self.clock.now() + self.start_timeout_s
        while (loaded := self.loaded_program()) != path:
            reason = self._error_text()
            if reason or self.clock.now() >= deadline:
                has = f"; it has {loaded} open" if loaded else ""
                raise DeviceError(
                    f"{self.name} did not open {path} ({reason or 'no message'}){has}"
                )
            self.clock.sleep(0.02)

    def move_mdi(
        self, target_mm: Vec, feed_mm_min: float, tolerance_mm: float, timeout_s: float
    ) -> None:
        """Move the tool point to ``target_mm`` (3,), machine coordinates, with one MDI line.

        MDI mode, :func:`mdi_move_line` (``G21 G90 G94 G53 G1 X.. Y.. Z.. F..``);
        returns once no command runs and the machine is at rest within
        ``tolerance_mm`` of the target (as LinuxCNC reports its actual
        position). The controller's soft limits stay in force: a target beyond
        them is refused there. DeviceError when a program runs,
        DeviceTimeoutError (with LinuxCNC's last error) when the machine is not
        there within ``timeout_s``. Whatever ends the wait early (an error, a
        lost connection, Ctrl-C) aborts the move before it propagates: the
        machine never goes on moving while xmalign has stopped watching.
        """
        state = self.program_state()
        if state != "idle":
            raise DeviceError(f"{self.name}: a program is {state}; it moves the machine only idle")
        self._set_mode("mdi")
        self._error_text()  # reading LinuxCNC's last error clears it: only this move's is left
        try:
            self._mdi(mdi_move_line(target_mm, feed_mm_min))
            self._wait_mdi_move(target_mm, tolerance_mm, timeout_s)
        except BaseException:
            self._abort_quietly()
            raise

    def _abort_quietly(self) -> None:
        """Abort whatever moves, after a failure: a failing abort must not hide the failure."""
        try:
            self.stop_program()
        except Exception as error:  # the connection may be what failed
            log.warning("%s: could not abort the MDI move (%s)", self.name, error)

    def _wait_mdi_move(self, target_mm: Vec, tolerance_mm: float, timeout_s: float) -> None:
        """Wait until the machine is at rest within ``tolerance_mm`` of ``target_mm``."""
        target = f"{np.round(target_mm, 4).tolist()} mm"
        deadline = self.clock.now() + timeout_s
        while True:
            miss_mm = self._miss_at_rest_mm(target_mm)
            if miss_mm is not None and miss_mm <= tolerance_mm:
                return
            # at rest elsewhere: not started yet, or refused (a soft limit): LinuxCNC says which
            reason = self._error_text() if miss_mm is not None else ""
            if reason:
                where = np.round(self.position_mm(), 4).tolist()
                raise DeviceError(
                    f"{self.name} did not move to {target} ({reason}); the machine is at {where} mm"
                )
            if self.clock.now() >= deadline:
                where = np.round(self.position_mm(), 4).tolist()
                raise DeviceTimeoutError(
                    f"{self.name}: the machine is not at {target} {timeout_s:g} s after the"
                    f" MDI move; it is at {where} mm"
                )
            self.clock.sleep(0.05)

    def _miss_at_rest_mm(self, target_mm: Vec) -> float | None:
        """Distance of the machine from ``target_mm`` once no command runs and it is at
        rest, mm; None while it is not."""
        if self.program_state() != "idle" or not self.is_standstill():
            return None
        return float(np.linalg.norm(self.position_mm() - target_mm))


class MdiMover:
    """The ``MachineMover`` of a LinuxCNC that xmalign may move (``allow_mdi_moves: true``).

    :meth:`move_to` checks the target against the machine file's travel and
    the machine's readiness, then moves there with :meth:`LinuxCncControl.move_mdi`.
    """

    def __init__(
        self, cnc: LinuxCncControl, machine: Machine, tolerance_mm: float, timeout_s: float
    ) -> None:
        self.cnc = cnc
        self.machine = machine
        self.tolerance_mm = tolerance_mm
        self.timeout_s = timeout_s

    def position_mm(self) -> Vec:
        """The LinuxCNC's actual X Y Z in machine coordinates, mm, shape (3,)."""
        return self.cnc.position_mm()

    def is_standstill(self) -> bool:
        """The machine stands still within its ``in_position_mm``."""
        return self.cnc.is_standstill()

    def move_to(self, position_mm: Vec, feed_mm_min: float) -> None:
        """Move to ``position_mm`` (3,), machine coordinates, mm, at ``feed_mm_min``.

        OutOfRangeError outside the machine file's travel; DriveFaultError when
        the machine is not ready; the errors of :meth:`LinuxCncControl.move_mdi`
        (which aborts the move on any of them, Ctrl-C included).
        """
        target = np.asarray(position_mm, dtype=float)
        if not self.machine.within_travel(target):
            raise OutOfRangeError(
                f"{np.round(target, 3).tolist()} mm is outside the machine's travel"
            )
        self.cnc.check_ready()
        self.cnc.move_mdi(target, feed_mm_min, self.tolerance_mm, self.timeout_s)
