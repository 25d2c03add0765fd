"""The simulated CNC behind LinuxCNC's remote shell: what ``linuxcncrsh`` answers, served.

:class:`LinuxcncrshServer` speaks the part of linuxcncrsh's protocol (``man
linuxcncrsh``, LinuxCNC 2.9) that :mod:`firmware_iface.linuxcncrsh` uses, with
LinuxCNC's own replies (``get`` replies ``NAME value...`` ending ``\\r\\n``;
``set`` replies ``SET NAME ACK``/``NAK`` ending ``\\n\\r`` in verbose mode; the
echo until ``set echo off``; ``get error`` gives the last error once), in front
of a :class:`~sim.linuxcnc_task.SimulatedLinuxcnc` (which the simulated Python
module ``linuxcnc`` serves too): ``set mode auto`` + ``set open``/``set run``
run a program file (LinuxCNC dialect); positions in the machine's units
(``get user_linear_units``: MM or INCH); ``set mode mdi`` + ``set mdi LINE`` runs
one line; ``M0`` pauses a program until ``set resume``; ``set pause`` is a feed
hold; ``set abort`` ends it; in E-stop ``get estop`` says ON and every command
is refused; with the task dead no ``set`` is answered. As linuxcncrsh, ``set
open`` is acknowledged when LinuxCNC received it; a file it cannot open shows in ``get error``. Each
session is served in a thread of its own; unlike LinuxCNC 2.9, concurrent
sessions do not disturb each other.

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
from typing import Literal

import numpy as np

from sim.clock import LockstepClock
from sim.cnc import SimulatedCnc
from sim.linuxcnc_task import HOMED_JOINTS, JOINTS, SimulatedLinuxcnc
from xmalign.machine import Machine

logger = logging.getLogger(__name__)


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
        linear_units: Literal["mm", "inch"] = "mm",
    ) -> None:
        self.linuxcnc = SimulatedLinuxcnc(cnc, machine, lockstep, linear_units)
        self.passwords = (connect_password, enable_password)
        self.listener = socket.create_server((host, port))
        self.port = self.listener.getsockname()[1]
        self.where = f"{host}:{self.port}"
        self._connections: set[socket.socket] = set()

    @property
    def mode(self) -> str:
        return self.linuxcnc.mode

    def start(self) -> None:
        threading.Thread(target=self._accept, name="linuxcncrsh", daemon=True).start()

    def stop(self) -> None:
        """Stop as LinuxCNC going down does: the program aborted, every session closed."""
        self.linuxcnc.shut_down()
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
        if name not in ("echo", "verbose", "enable") and not self.linuxcnc.task_alive:
            return ""  # a dead task takes no command: linuxcncrsh never answers (2.9)
        ok = self._set(name, args, session)
        if ok and not session["verbose"]:
            return ""
        return f"SET {name.upper()} {'ACK' if ok else 'NAK'}\n\r"

    def _get(self, name: str) -> str | None:
        def axes(values: np.ndarray) -> str:
            return " ".join(f"{v:.6f}" for v in [*values, 0.0, 0.0, 0.0])

        linuxcnc = self.linuxcnc
        if name == "error":  # as LinuxCNC's: a message is read once
            return f"ERROR {linuxcnc.take_error() or 'OK'}"
        homed = ["YES"] * HOMED_JOINTS + ["NO"] * (JOINTS - HOMED_JOINTS)
        answers = {
            "abs_act_pos": f"ABS_ACT_POS {axes(linuxcnc.position_units())}",
            "abs_cmd_pos": f"ABS_CMD_POS {axes(linuxcnc.position_units())}",
            "user_linear_units": f"USER_LINEAR_UNITS {linuxcnc.linear_units.upper()}",
            "program_status": f"PROGRAM_STATUS {linuxcnc.program_status.upper()}",
            "program": f"PROGRAM {linuxcnc.opened or 'NONE'}",
            "estop": f"ESTOP {'ON' if linuxcnc.estop else 'OFF'}",
            "machine": f"MACHINE {'OFF' if linuxcnc.estop else 'ON'}",
            "joint_homed": f"JOINT_HOMED {' '.join(homed)}",
            "joint_fault": f"JOINT_FAULT {' '.join(['OK'] * JOINTS)}",
        }
        return answers.get(name)

    def _set(self, name: str, args: list[str], session: dict[str, bool]) -> bool:
        if name in ("echo", "verbose"):
            session[name] = args[:1] == ["on"]
            return bool(args)
        if name == "enable":
            session["enabled"] = args[:1] == [self.passwords[1]]
            return session["enabled"]
        if not session["enabled"] or (not args and name in ("mode", "open", "mdi")):
            return False
        linuxcnc = self.linuxcnc
        if name == "open":  # acknowledged as received; a file LinuxCNC cannot open: get error
            return linuxcnc.open(" ".join(args)) or not linuxcnc.busy
        commands = {
            "mode": lambda: linuxcnc.set_mode(args[0]),
            "run": linuxcnc.run,
            "mdi": lambda: linuxcnc.mdi(" ".join(args)),
            "pause": linuxcnc.pause,
            "resume": linuxcnc.resume,
            "abort": linuxcnc.abort,
        }
        command = commands.get(name)
        return command is not None and command()
