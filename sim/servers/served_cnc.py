"""The simulated CNC served as a shop's CNC looks to xmalign: a position file and cycle start.

:class:`ServedCnc` runs a G-code program on a :class:`sim.cnc.SimulatedCnc` in a
background thread on the world's real-time clock and keeps a position file up
to date (last line ``x y z`` in mm, what
:class:`firmware_iface.machine_position.FilePositions` reads), the way a
controller's position export would. The program starts at the first cycle
start and halts at every programmed stop (``M0``) until the next one; a cycle
start after the program end runs it again from the top, as an operator
restarts a program on a control. Every change of state is reported through
``tell`` (``sim serve`` prints it), so an operator, or a test playing one,
knows when the CNC waits for cycle start.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable
from pathlib import Path

from sim.clock import Follower, LockstepClock
from sim.cnc import SimulatedCnc, read_program
from xmalign.errors import XmalignError
from xmalign.machine import Machine
from xmalign.roles import Clock

logger = logging.getLogger(__name__)

#: How often the position file is rewritten, s.
POSITION_PERIOD_S = 0.02
#: What ``tell`` says when the CNC waits for cycle start (an operator watches for it).
WAITING = "cnc: waiting for cycle start"
#: What ``tell`` says when the program has ended.
PROGRAM_END = "cnc: program end"


class ServedCnc:
    """A CNC that runs ``program`` on cycle start and writes its position to ``position_file``.

    Parameters
    ----------
    cnc : SimulatedCnc
        The CNC of the served world (the interferometer reads its position).
    program : str
        The G-code, checked at once (an :class:`~xmalign.errors.InputError` names the line).
    dialect : str
        Its dialect (sim.cnc.DIALECTS).
    position_file : Path
        Rewritten every ``POSITION_PERIOD_S`` with the tool point in mm.
    tell : callable
        ``tell(message)`` for every change of state.
    lockstep : LockstepClock, optional
        The virtual clock shared with the host in this process (``clock``): the
        program runs as a follower of it, and the position file is rewritten
        whenever the clock advances (when the position changed). Default: the
        program runs on the wall clock and the file is rewritten every
        ``POSITION_PERIOD_S``.
    """

    def __init__(
        self,
        cnc: SimulatedCnc,
        machine: Machine,
        clock: Clock,
        program: str,
        dialect: str,
        position_file: Path,
        tell: Callable[[str], None],
        lockstep: LockstepClock | None = None,
    ) -> None:
        read_program(program, dialect, machine, cnc.position_mm(), machine.feed_mm_min.rapid)
        self.cnc = cnc
        self.clock = clock
        self.program = program
        self.dialect = dialect
        self.position_file = position_file
        self.tell = tell
        self._cycle_start = threading.Event()
        self._stop = threading.Event()
        self._file_lock = threading.Lock()
        self._written = ""
        self.lockstep = lockstep
        self._follower: Follower | None = None
        self._stop_listening: Callable[[], None] | None = None
        self._threads = [
            threading.Thread(target=self._write_positions, name="cnc-position", daemon=True),
            threading.Thread(target=self._run_programs, name="cnc-program", daemon=True),
        ]

    def start(self) -> None:
        self._write_position()
        if self.lockstep is None:
            for thread in self._threads:
                thread.start()
            return
        self._stop_listening = self.lockstep.on_advance(self._write_position)
        self._follower = self.lockstep.start_follower(self._run_programs, "cnc-program")

    def stop(self) -> None:
        self._stop.set()
        self._cycle_start.set()
        if self.lockstep is not None and self._follower is not None:
            if self._stop_listening is not None:
                self._stop_listening()
            self.lockstep.release(self._follower)
            return
        for thread in self._threads:
            thread.join(5.0)

    def cycle_start(self) -> None:
        """The operator presses cycle start (in lockstep: returns once the CNC waits again)."""
        self._cycle_start.set()
        if self.lockstep is not None and self._follower is not None:
            self.lockstep.resume(self._follower)

    def _wait_for_cycle_start(self) -> bool:
        self._write_position()  # the file shows where it stops before anyone is told
        self.tell(WAITING)
        if self.lockstep is None:
            self._cycle_start.wait()
        while not self._cycle_start.is_set():
            assert self.lockstep is not None
            self.lockstep.wait_for_resume()
        self._cycle_start.clear()
        return not self._stop.is_set()

    def _run_programs(self) -> None:
        while self._wait_for_cycle_start():
            self.tell("cnc: program started")
            try:
                for event in self.cnc.run_program(self.program, self.dialect):
                    if self._stop.is_set():
                        return
                    if event.kind == "stop" and not self._wait_for_cycle_start():
                        return
            except XmalignError as error:
                self.tell(f"cnc: program aborted: {error}")
                continue
            self.tell(PROGRAM_END)

    def _write_position(self) -> None:
        with self._file_lock:
            x, y, z = self.cnc.position_mm()
            text = f"{x:.4f} {y:.4f} {z:.4f}\n"
            if text == self._written and self.lockstep is not None:
                return
            partial = self.position_file.with_name(self.position_file.name + ".part")
            partial.write_text(text, encoding="utf-8")
            os.replace(partial, self.position_file)
            self._written = text

    def _write_positions(self) -> None:
        while not self._stop.wait(POSITION_PERIOD_S):
            try:
                self._write_position()
            except OSError as error:
                logger.warning("cannot write the position file %s: %s", self.position_file, error)
