"""LinuxCNC over its remote shell ``linuxcncrsh`` (TCP, plain text; docs/hardware.md).

Two layers, as for every device:

* :class:`LinuxcncrshLink` carries lines over TCP: one request, one reply
  line (the session is set up so that every request has exactly one), with a
  timeout; each reply is matched to its request (:func:`answers`): a reply left
  over from a request that was interrupted (Ctrl-C, SIGTERM) or timed out is
  skipped, never taken for the next request's. Every line crossing the
  connection is logged at DEBUG with the passwords replaced by ``****``.
* :class:`LinuxCnc` speaks the commands of ``man linuxcncrsh`` (LinuxCNC 2.9)
  on such a link: the actual position in machine coordinates
  (``get abs_act_pos``), standstill, the program state
  (``get program_status``), and program control (``set open``, ``set run``,
  ``set pause``, ``set resume``, ``set abort``; MDI moves with ``set mode
  mdi`` and ``set mdi G21 G90 G94 G53 G1 ...``), in mm whatever the
  machine's units (``get user_linear_units``). Only these primitives are its own: the
  waits and checks are :class:`~firmware_iface.linuxcnc_control.LinuxCncControl`'s,
  which the ``linuxcnc`` Python module's driver shares.

Replies as LinuxCNC 2.9 sends them (seen on a headless ``linuxcnc-uspace``):
``get`` replies end with ``\\r\\n`` and start with the subcommand in capitals
(``ABS_ACT_POS 1.000000 2.000000 ...``, one value per axis of XYZABC);
``set`` replies (with ``set verbose on``) are ``SET <CMD> ACK`` or
``SET <CMD> NAK`` ending with ``\\n\\r``; a session echoes every request until
``set echo off``.
"""

from __future__ import annotations

import logging
import re
import socket
from typing import Protocol

import numpy as np

from firmware_iface.linuxcnc_control import START_TIMEOUT_S, LinuxCncControl, Mode
from xmalign.errors import (
    DeviceError,
    DeviceTimeoutError,
    InputError,
    TransportError,
    XmalignError,
)
from xmalign.geometry import Vec
from xmalign.roles import Clock, ProgramState

log = logging.getLogger(__name__)

#: linuxcncrsh's defaults (``-p``, ``-w``, ``-e``; man linuxcncrsh).
DEFAULT_PORT = 5007
DEFAULT_CONNECT_PASSWORD = "EMC"
DEFAULT_ENABLE_PASSWORD = "EMCTOO"
#: What xmalign calls itself in ``hello``.
CLIENT = "xmalign"
PROTOCOL_VERSION = "1.0"
#: Earlier requests without their reply whose replies are still recognised, at most.
MAX_STALE_REPLIES = 16
#: Time between the two reads of the commanded position that tell a standstill, s.
STANDSTILL_PROBE_S = 0.02
_MASK = "****"
_LINE_END = re.compile(rb"[\r\n]")


#: linuxcncrsh's units of ``get user_linear_units`` ([TRAJ] LINEAR_UNITS), in mm.
MM_PER_UNIT = {"MM": 1.0, "INCH": 25.4, "CM": 10.0}
_HELLO = re.compile(r"(?i)(hello\s+)(.*?)((?:\s+\S+){2})?$")
_ENABLE = re.compile(r"(?i)(set\s+enable\s+)(.*)$")


def masked(line: str) -> str:
    """A request with its password replaced by ``****``: everything between ``hello``
    and its last two words (client, version), everything after ``set enable`` but ``off``."""
    if match := _HELLO.match(line):
        return f"{match[1]}{_MASK}{match[3] or ''}"
    if (match := _ENABLE.match(line)) and match[2].strip().lower() != "off":
        return f"{match[1]}{_MASK}"
    return line


def check_password(password: str, what: str) -> None:
    """InputError unless linuxcncrsh can take ``password``: one word of printable ASCII
    (it splits requests on spaces and tabs; ``off`` disables rather than enables)."""
    if not password or any(
        not char.isascii() or not char.isprintable() or char.isspace() for char in password
    ):
        raise InputError(
            f"the {what} must be one word of printable ASCII without spaces"
            " (linuxcncrsh splits its requests on spaces)"
        )
    if what == "enable password" and password.lower() == "off":
        raise InputError("the enable password cannot be 'off' (linuxcncrsh: it disables)")


def answers(request: str, reply: str) -> bool:
    """Whether ``reply`` is linuxcncrsh's reply to ``request``: ``HELLO ...`` to ``hello``,
    ``NAME ...`` (or ``GET NAME NAK``) to ``get name``, ``SET NAME ...`` to ``set name``,
    the echo of ``set echo off`` to itself (the last request it echoes)."""
    words, said = request.upper().split(), reply.upper().split()
    if not words or not said:
        return False
    if words[0] == "HELLO":
        return said[0] == "HELLO"
    if words[0] in ("GET", "SET") and len(words) > 1:
        if words[:2] == ["SET", "ECHO"] and said[:2] == ["SET", "ECHO"]:
            return True  # the echo of the request itself
        if words[0] == "GET" and said[0] == words[1]:
            return True
        return said[:2] == words[:2]
    return True


class LineLink(Protocol):
    """A request/reply line connection (:class:`LinuxcncrshLink`, or a scripted double)."""

    name: str

    def ask(self, line: str) -> str:
        """Send one request line, return its one reply line (without line ends)."""
        ...

    def close(self) -> None:
        """End the connection."""
        ...


class LinuxcncrshLink:
    """One TCP session with linuxcncrsh: :meth:`ask` sends a line and reads one reply line.

    Parameters
    ----------
    host, port : str, int
    timeout_s : float
        For the connection and for each reply.
    """

    def __init__(self, host: str, port: int, timeout_s: float) -> None:
        self.name = f"LinuxCNC at {host}:{port}"
        self.address = (host, port)
        self.timeout_s = timeout_s
        self._buffer = b""
        #: Requests sent whose replies have not been read (the last: the one asked now).
        self._unanswered: list[str] = []
        try:
            self._socket: socket.socket | None = socket.create_connection(
                (host, port), timeout=timeout_s
            )
        except OSError as error:
            raise TransportError(
                f"cannot connect to {self.name} (linuxcncrsh): {error.strerror or error}"
            ) from error
        log.debug("%s: connected", self.name)

    def ask(self, line: str) -> str:
        """Send one request line, return its one reply line (without line ends).

        A reply to an earlier request that never got its own (interrupted by
        Ctrl-C or SIGTERM, or timed out) is skipped when it comes (:func:`answers`),
        never taken for this one's. DeviceTimeoutError without a reply within
        ``timeout_s`` (the session stays open: the late reply is skipped when it
        comes), TransportError when the connection fails (it is closed).
        """
        if self._socket is None:
            raise TransportError(f"the connection to {self.name} is closed")
        log.debug("%s > %r", self.name, masked(line))
        self._unanswered = [*self._unanswered[-MAX_STALE_REPLIES:], line]
        try:
            self._socket.sendall(line.encode("ascii") + b"\r\n")
            reply = self._reply_to(line)
        except TimeoutError as error:
            raise DeviceTimeoutError(
                f"{self.name} did not answer '{masked(line)}' within {self.timeout_s:g} s"
            ) from error
        except OSError as error:
            self.close()
            raise TransportError(
                f"the connection to {self.name} failed ({error.strerror or error})"
            ) from error
        self._unanswered.pop()
        log.debug("%s < %r", self.name, reply)
        return reply

    def _reply_to(self, line: str) -> str:
        """The next reply but those answering an earlier unanswered request (skipped)."""
        while True:
            reply = self._read_line()
            earlier = self._unanswered[:-1]
            if answers(line, reply) or not any(answers(old, reply) for old in earlier):
                return reply
            self._unanswered.remove(next(old for old in earlier if answers(old, reply)))
            log.debug("%s < %r (skipped: the reply to an earlier request)", self.name, reply)

    def _read_line(self) -> str:
        """The next non-empty line (replies end with ``\\r\\n`` or ``\\n\\r``)."""
        assert self._socket is not None
        while True:
            self._buffer = self._buffer.lstrip(b"\r\n")
            end = _LINE_END.search(self._buffer)
            if end is not None:
                line, self._buffer = self._buffer[: end.start()], self._buffer[end.start() :]
                return line.decode("ascii", errors="replace")
            chunk = self._socket.recv(4096)
            if not chunk:
                self.close()
                raise TransportError(f"{self.name} closed the connection")
            self._buffer += chunk

    def close(self) -> None:
        """Close the TCP session (again: nothing)."""
        if self._socket is not None:
            self._socket.close()
            self._socket = None
            log.debug("%s: closed", self.name)


class LinuxCnc(LinuxCncControl):
    """A LinuxCNC seen through linuxcncrsh: the primitives of :class:`LinuxCncControl`.

    Positions are ``abs_act_pos`` (commanded: ``abs_cmd_pos``), which
    linuxcncrsh gives in the machine's units ([TRAJ] LINEAR_UNITS; its ``set
    linear_unit_conversion`` does not change them): :meth:`open` reads them
    (``get user_linear_units``) and the positions are converted to mm.
    linuxcncrsh has no in-position flag: the command stands still when two
    reads ``STANDSTILL_PROBE_S`` apart agree.

    Parameters
    ----------
    link : LineLink
        A fresh session (:meth:`open` says hello).
    joints, in_position_mm, clock, start_timeout_s
        As for :class:`~firmware_iface.linuxcnc_control.LinuxCncControl`.
    """

    def __init__(
        self,
        link: LineLink,
        joints: int = 3,
        in_position_mm: float = 0.002,
        clock: Clock | None = None,
        start_timeout_s: float = START_TIMEOUT_S,
    ) -> None:
        super().__init__(link.name, joints, in_position_mm, clock, start_timeout_s)
        self.link = link
        #: mm per machine unit (:meth:`open` reads it from LinuxCNC).
        self.mm_per_unit = 1.0
        #: The connect password :meth:`open` said hello with (a second session probes with it).
        self._connect_password: str | None = None

    def open(self, connect_password: str, enable_password: str | None) -> None:
        """Say hello; without echo, with a reply to every ``set``; enable control if
        asked; read the machine's linear units.

        InputError for a password linuxcncrsh cannot take (:func:`check_password`),
        before anything is sent.
        """
        check_password(connect_password, "connect password")
        if enable_password is not None:
            check_password(enable_password, "enable password")
        self._connect_password = connect_password
        reply = self.link.ask(f"hello {connect_password} {CLIENT} {PROTOCOL_VERSION}")
        if reply.upper().startswith("HELLO NAK"):
            raise DeviceError(f"{self.name} refused the connect password (hello: {reply})")
        if not reply.upper().startswith("HELLO ACK"):
            shown = reply if len(reply) <= 60 else reply[:57] + "..."
            raise DeviceError(
                f"{self.name} does not speak linuxcncrsh: answered '{shown}' to hello"
                " (another server on that port? linuxcncrsh listens on 5007 by default)"
            )
        self.link.ask("set echo off")  # the reply is the echo of this very request
        self._set("verbose on")
        if enable_password is not None:
            reply = self.link.ask(f"set enable {enable_password}")
            if reply.upper() != "SET ENABLE ACK":
                raise DeviceError(f"{self.name} refused the enable password (set enable)")
        self.mm_per_unit = self._mm_per_unit()

    def _mm_per_unit(self) -> float:
        """mm per machine unit, from ``get user_linear_units`` (MM, INCH or CM)."""
        (units,) = self._get("user_linear_units")[:1] or ["?"]
        if units.upper() not in MM_PER_UNIT:
            raise DeviceError(
                f"{self.name}: its linear units are {units} ([TRAJ] LINEAR_UNITS), not mm,"
                " inch or cm; xmalign cannot read its positions in mm"
            )
        return MM_PER_UNIT[units.upper()]

    def close(self) -> None:
        """End the session (the program and the machine go on as they are)."""
        self.link.close()

    # -- reading ------------------------------------------------------------------
    def _get(self, what: str) -> list[str]:
        """The words of the reply to ``get <what>`` after its name."""
        reply = self.link.ask(f"get {what}")
        words = reply.split()
        head = what.split()[0].upper()
        if not words or words[0].upper() != head:
            raise DeviceError(f"{self.name} refused 'get {what}' ({reply})")
        return words[1:]

    def _axes_mm(self, what: str) -> Vec:
        words = self._get(what)
        try:
            values = np.array([float(word) for word in words[:3]])
        except ValueError as error:
            raise DeviceError(f"{self.name}: unexpected reply to 'get {what}': {words}") from error
        if values.shape != (3,):
            raise DeviceError(f"{self.name}: 'get {what}' gave {len(words)} values, not X Y Z")
        return values * self.mm_per_unit

    def position_mm(self) -> Vec:
        """Actual X Y Z in machine coordinates (``abs_act_pos``), mm, shape (3,)."""
        return self._axes_mm("abs_act_pos")

    def commanded_mm(self) -> Vec:
        """Commanded X Y Z in machine coordinates (``abs_cmd_pos``), mm, shape (3,)."""
        return self._axes_mm("abs_cmd_pos")

    def _commanded_at_rest_mm(self) -> Vec | None:
        before = self.commanded_mm()
        self.clock.sleep(STANDSTILL_PROBE_S)
        commanded = self.commanded_mm()
        return commanded if np.array_equal(before, commanded) else None

    def program_state(self) -> ProgramState:
        """``idle``, ``running`` or ``paused`` (``get program_status``)."""
        (state,) = self._get("program_status")[:1] or ["?"]
        state = state.lower()
        if state not in ("idle", "running", "paused"):
            raise DeviceError(f"{self.name}: unknown program status '{state}'")
        return state  # type: ignore[return-value]

    def loaded_program(self) -> str | None:
        """The path of the open program, None when there is none."""
        words = self._get("program")
        return None if not words or words[0].lower() == "none" else " ".join(words)

    def _in_estop(self) -> bool:
        return self._get("estop")[:1] != ["OFF"]

    def _machine_on(self) -> bool:
        return self._get("machine")[:1] == ["ON"]

    def _joints_homed(self) -> list[bool]:
        return [word.upper() == "YES" for word in self._get("joint_homed")]

    def _joints_faulted(self) -> list[bool]:
        return [word.upper() != "OK" for word in self._get("joint_fault")]

    # -- commands -----------------------------------------------------------------
    def _set(self, what: str) -> None:
        try:
            reply = self.link.ask(f"set {what}")
        except DeviceTimeoutError as error:
            if not self._still_answers():
                raise
            raise DeviceError(
                f"{error} although linuxcncrsh answers: LinuxCNC's task (milltask) has"
                " stopped; restart LinuxCNC"
            ) from error
        head = what.split()[0].upper()
        if reply.upper() == f"SET {head} ACK":
            return
        reason = self._error_text()
        raise DeviceError(
            f"{self.name} refused 'set {what}' ({reply}{'; ' + reason if reason else ''})"
        )

    def _still_answers(self) -> bool:
        """linuxcncrsh answers a ``get`` in a session of its own (after a ``set`` it did
        not answer: LinuxCNC whose task, milltask, has stopped; seen with 2.9, its status
        then stays as it was, and the session that sent the ``set`` waits on it)."""
        address = getattr(self.link, "address", None)
        timeout_s = getattr(self.link, "timeout_s", None)
        if address is None or timeout_s is None or self._connect_password is None:
            return False
        host, port = address
        try:
            probe = open_linuxcnc(host, port, timeout_s, self._connect_password, None)
        except XmalignError:
            return False
        try:
            probe.program_state()
        except XmalignError:
            return False
        finally:
            probe.close()
        return True

    def _error_text(self) -> str:
        """LinuxCNC's last error message, '' when it has none."""
        try:
            text = " ".join(self._get("error"))
        except DeviceError:
            return ""
        return "" if text.upper() == "OK" else text

    def _set_mode(self, mode: Mode) -> None:
        self._set(f"mode {mode}")

    def _open_program(self, path: str) -> None:
        self._set(f"open {path}")

    def _run_program(self) -> None:
        self._set("run")

    def _mdi(self, line: str) -> None:
        self._set(f"mdi {line}")

    def hold(self) -> None:
        """Feed hold (``set pause``)."""
        self._set("pause")

    def resume(self) -> None:
        """Go on after an M0 or a feed hold (``set resume``)."""
        self._set("resume")

    def stop_program(self) -> None:
        """Abort the program (``set abort``)."""
        self._set("abort")


def open_linuxcnc(
    host: str,
    port: int,
    timeout_s: float,
    connect_password: str = DEFAULT_CONNECT_PASSWORD,
    enable_password: str | None = DEFAULT_ENABLE_PASSWORD,
    joints: int = 3,
    in_position_mm: float = 0.002,
    clock: Clock | None = None,
    start_timeout_s: float = START_TIMEOUT_S,
) -> LinuxCnc:
    """Connect to linuxcncrsh and open a session (enabled for control with a password);
    ``timeout_s``: for the connection and each reply; ``clock``: what it waits on
    (default the wall clock)."""
    link = LinuxcncrshLink(host, port, timeout_s)
    cnc = LinuxCnc(link, joints, in_position_mm, clock, start_timeout_s)
    try:
        cnc.open(connect_password, enable_password)
    except BaseException:
        link.close()
        raise
    return cnc
