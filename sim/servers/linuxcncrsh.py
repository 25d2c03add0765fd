"""The simulated CNC behind LinuxCNC's remote shell: what ``linuxcncrsh`` answers, served.

:class:`LinuxcncrshServer` speaks the part of linuxcncrsh's protocol (``man
linuxcncrsh``, LinuxCNC 2.9) that :mod:`firmware_iface.linuxcncrsh` uses, with
LinuxCNC's own replies (``get`` replies ``NAME value...`` ending ``\\r\\n``;
``set`` replies ``SET NAME ACK``/``NAK`` ending ``\\n\\r`` in verbose mode; the
echo until ``set echo off``; ``get error`` gives the last error once), in front
of a :class:`~sim.cnc.SimulatedCnc`: ``set mode auto`` + ``set open``/``set run``
run a program file (LinuxCNC dialect); ``set mode mdi`` + ``set mdi LINE`` runs
one line; ``M0`` pauses a program until ``set resume``; ``set pause`` is a feed
hold (the simulated machine stops where it is at once and goes on to the same
target on ``set resume``); ``set abort`` ends it. The machine is always out of
E-stop, on and homed. Each session is served in a thread of its own; unlike
LinuxCNC 2.9, concurrent sessions do not disturb each other.

The program runs on the wall clock (``xmalign sim serve --linuxcncrsh``) or,
with ``lockstep``, as a follower of a :class:`~sim.clock.LockstepClock` (the
served dry run): then every request is answered at the present virtual time,
and a hold, a resume or an abort acts at the virtual time it arrives.
"""

from __future__ import annotations

import contextlib
import logging
import socket
import threading
from pathlib import Path

import numpy as np

from sim.clock import Follower, LockstepClock
from sim.cnc import SimulatedCnc, read_program
from sim.cnc import _Dwell as Dwell
from sim.cnc import _End as End
from sim.cnc import _Move as Move
from sim.cnc import _Stop as Stop
from xmalign.errors import XmalignError
from xmalign.machine import Machine

logger = logging.getLogger(__name__)


class _Program:
    """A program running on the simulated CNC: M0, feed hold, abort.

    On the wall clock it runs in a thread of its own; on a
    :class:`~sim.clock.LockstepClock` as a follower of it (a move takes its
    time in virtual seconds; a hold, a resume or an abort lets it run at once,
    at the current virtual time).
    """

    def __init__(self, cnc: SimulatedCnc, steps: list, lockstep: LockstepClock | None) -> None:
        self.cnc = cnc
        self.steps = steps
        self.state = "running"
        self.lockstep = lockstep
        self._wake = threading.Condition()
        self._hold = False
        self._resume = False
        self._abort = False
        self._follower: Follower | None = None
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        if self.lockstep is not None:
            self._follower = self.lockstep.start_follower(self._run, "linuxcncrsh-program")
            return
        self._thread = threading.Thread(target=self._run, name="linuxcncrsh-program", daemon=True)
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
            self.cnc.stop()  # feed hold
            self._paused()


class LinuxcncrshServer:
    """linuxcncrsh's protocol on ``host:port`` for ``cnc`` (the world's simulated CNC)."""

    def __init__(
        self,
        cnc: SimulatedCnc,
        machine: Machine,
        host: str = "127.0.0.1",
        port: int = 0,
        connect_password: str = "EMC",
        enable_password: str = "EMCTOO",
        lockstep: LockstepClock | None = None,
    ) -> None:
        self.cnc = cnc
        self.lockstep = lockstep
        self.mode = "manual"
        self.machine = machine
        self.passwords = (connect_password, enable_password)
        self.listener = socket.create_server((host, port))
        self.port = self.listener.getsockname()[1]
        self.where = f"{host}:{self.port}"
        self.rapid_mm_min = machine.feed_mm_min.rapid
        self.program: _Program | None = None
        self.opened: str | None = None
        self.error = "OK"
        self._connections: set[socket.socket] = set()

    def start(self) -> None:
        threading.Thread(target=self._accept, name="linuxcncrsh", daemon=True).start()

    def stop(self) -> None:
        """Stop as LinuxCNC going down does: the program aborted, every session closed."""
        if self.program is not None:
            self.program.abort()
        self.listener.close()
        for connection in list(self._connections):
            with contextlib.suppress(OSError):
                connection.shutdown(socket.SHUT_RDWR)

    def _accept(self) -> None:
        while True:
            try:
                connection, _ = self.listener.accept()
            except OSError:
                return
            self._connections.add(connection)
            threading.Thread(target=self._session, args=(connection,), daemon=True).start()

    def _session(self, connection: socket.socket) -> None:
        session = {"hello": False, "echo": True, "verbose": False, "enabled": False}
        with contextlib.ExitStack() as closing:
            closing.callback(self._connections.discard, connection)
            closing.enter_context(contextlib.suppress(OSError))  # the client went away
            self._serve(connection, session)

    def _serve(self, connection: socket.socket, session: dict[str, bool]) -> None:
        with connection, connection.makefile("rb") as lines:
            for raw in lines:
                line = raw.decode("ascii", errors="replace").strip()
                if not line:
                    continue
                logger.debug("linuxcncrsh %s < %r", self.where, line.split(" ")[0])
                echo = f"{line}\r\n" if session["hello"] and session["echo"] else ""
                reply = self._answer(line, session)
                if line.lower() == "set echo off":
                    session["echo"] = False
                connection.sendall((echo + reply).encode("ascii"))

    def _answer(self, line: str, session: dict[str, bool]) -> str:
        words = line.split()
        command = words[0].lower()
        if command == "hello":
            session["hello"] = len(words) == 4 and words[1] == self.passwords[0]
            return "HELLO ACK EMCNETSVR 1.1\r\n" if session["hello"] else "HELLO NAK\r\n"
        if not session["hello"] or command not in ("get", "set") or len(words) < 2:
            return f"{line.upper()} NAK\r\n"
        name, args = words[1].lower(), words[2:]
        if command == "get":
            value = self._get(name)
            return f"GET {name.upper()} NAK\r\n\r\n" if value is None else f"{value}\r\n"
        ok = self._set(name, args, session)
        if ok and not session["verbose"]:
            return ""
        return f"SET {name.upper()} {'ACK' if ok else 'NAK'}\n\r"

    def _get(self, name: str) -> str | None:
        def axes(values: np.ndarray) -> str:
            return " ".join(f"{v:.6f}" for v in [*values, 0.0, 0.0, 0.0])

        program = self.program
        status = "idle" if program is None else program.state
        answers = {
            "abs_act_pos": f"ABS_ACT_POS {axes(self.cnc.position_mm())}",
            "abs_cmd_pos": f"ABS_CMD_POS {axes(self.cnc.position_mm())}",
            "program_status": f"PROGRAM_STATUS {status.upper()}",
            "program": f"PROGRAM {self.opened or 'NONE'}",
            "estop": "ESTOP OFF",
            "machine": "MACHINE ON",
            "joint_homed": "JOINT_HOMED YES YES YES NO NO NO",
            "joint_fault": "JOINT_FAULT OK OK OK OK OK OK",
            "error": f"ERROR {self.error}",
        }
        if name == "error":
            self.error = "OK"  # as LinuxCNC's: a message is read once
        return answers.get(name)

    def _set(self, name: str, args: list[str], session: dict[str, bool]) -> bool:
        if name in ("echo", "verbose"):
            session[name] = args[:1] == ["on"]
            return bool(args)
        if name == "enable":
            session["enabled"] = args[:1] == [self.passwords[1]]
            return session["enabled"]
        if not session["enabled"]:
            return False
        program = self.program
        running = program is not None and program.state != "idle"
        if name == "mode":
            if running or args[:1] not in (["manual"], ["auto"], ["mdi"]):
                return False
            self.mode = args[0]
            return True
        if name == "open" and args and not running:
            self.opened = " ".join(args)
            return True
        if name == "run" and self.opened is not None and not running and self.mode == "auto":
            try:
                text = Path(self.opened).read_text(encoding="utf-8")
            except OSError as error:
                self.error = f"Unable to open file <{self.opened}>: {error}"
                return True  # LinuxCNC acknowledges the run and reports the error after
            return self._run(text, f"file <{self.opened}>")
        if name == "mdi" and args and not running and self.mode == "mdi":
            return self._run(f"G21 G90\n{' '.join(args)}\nM2\n", "MDI command")
        if name in ("pause", "resume", "abort") and program is not None:
            getattr(program, {"pause": "hold"}.get(name, name))()
            return True
        return False

    def _run(self, text: str, what: str) -> bool:
        """Run a program (a file's, or one MDI command); a bad one sets LinuxCNC's error."""
        try:
            position_mm = self.cnc.position_mm()
            steps = read_program(text, "linuxcnc", self.machine, position_mm, self.rapid_mm_min)
        except XmalignError as error:
            self.error = f"Unable to run {what}: {error}"
            return True
        self.error = "OK"
        self.program = _Program(self.cnc, steps, self.lockstep)
        self.program.start()
        return True
