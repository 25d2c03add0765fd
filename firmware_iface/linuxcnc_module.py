"""LinuxCNC through its own Python module ``linuxcnc``, where xmalign runs on the CNC's computer.

The module ships with LinuxCNC (Debian ``linuxcnc-uspace``:
``/usr/lib/python3/dist-packages/linuxcnc.cpython-3XX-....so``) and talks to
the running LinuxCNC through its NML shared memory: ``linuxcnc.stat()``
(status), ``linuxcnc.command()`` (commands) and ``linuxcnc.error_channel()``
(LinuxCNC's error messages). :func:`find_linuxcnc_module` loads it without
putting the rest of the system's packages on ``sys.path``.

:class:`LocalLinuxCnc` gives the primitives of
:class:`~firmware_iface.linuxcnc_control.LinuxCncControl` (the waits and
checks are shared with the linuxcncrsh driver) from the module:

* actual position ``stat.actual_position`` (``motion.traj.actualPosition``,
  what linuxcncrsh's ``abs_act_pos`` prints), commanded ``stat.position``,
  both in the machine's units ([TRAJ] LINEAR_UNITS), divided by
  ``stat.linear_units`` (machine units per mm) into mm;
* the command stands still when the trajectory planner has finished
  (``stat.inpos``, set by LinuxCNC's motion controller) or, in a feed hold,
  once it has brought the path to a stop (``stat.paused`` and
  ``stat.current_vel == 0``; ``inpos`` stays false while the rest of the move
  waits): LinuxCNC's own flags, no sampling as over linuxcncrsh;
* program state from ``stat.interp_state`` as linuxcncrsh's
  ``program_status`` maps it (reading or waiting: running; paused: paused);
* E-stop and machine on from ``stat.task_state``, as linuxcncrsh's
  ``estop`` / ``machine``; ``stat.homed``, ``stat.joint[i]['fault']``;
* commands ``mode``, ``program_open``, ``auto(AUTO_RUN, 0)``,
  ``auto(AUTO_PAUSE)``, ``auto(AUTO_RESUME)``, ``abort``, ``mdi``: a mode
  change, an open and an abort must complete (LinuxCNC's status ``RCS_DONE``);
  a run, a pause, a resume and an MDI line must have been received (the
  status echoes the command's serial number), as linuxcncrsh acknowledges
  them. ``RCS_ERROR`` for the command is a refusal, raised at once with
  LinuxCNC's own message (a resume with nothing to resume). A command never
  received while the status answers is a task that has stopped (milltask died:
  its status stays as it was), named as such.

Each command and its outcome, and each message taken from the error channel,
is logged at DEBUG. Every read takes a fresh ``stat()``: a stat opened while
LinuxCNC ran keeps answering from the shared memory after LinuxCNC has gone
(seen with 2.9), a fresh one then raises ``linuxcnc.error``, which becomes a
TransportError naming the NML file.
"""

from __future__ import annotations

import importlib.util
import logging
import sys
from collections.abc import Callable
from importlib.machinery import ModuleSpec, PathFinder
from pathlib import Path
from typing import Any

import numpy as np

from firmware_iface.linuxcnc_control import START_TIMEOUT_S, LinuxCncControl, Mode
from xmalign.errors import DeviceError, DeviceTimeoutError, InputError, TransportError
from xmalign.geometry import Vec
from xmalign.roles import Clock, ProgramState

log = logging.getLogger(__name__)

#: Where Debian's linuxcnc-uspace installs the module.
SYSTEM_MODULE_DIR = Path("/usr/lib/python3/dist-packages")
#: What xmalign uses of the module: the simulated module (sim/linuxcnc_module.py) offers
#: the same, and tests/firmware_iface/test_linuxcnc_module.py checks both against the real one.
MODULE_API = {
    "module": (
        "stat",
        "command",
        "error_channel",
        "error",
        "nmlfile",
        "MODE_MANUAL",
        "MODE_AUTO",
        "MODE_MDI",
        "AUTO_RUN",
        "AUTO_PAUSE",
        "AUTO_RESUME",
        "INTERP_IDLE",
        "INTERP_READING",
        "INTERP_PAUSED",
        "INTERP_WAITING",
        "STATE_ESTOP",
        "STATE_ON",
        "RCS_DONE",
        "RCS_EXEC",
        "RCS_ERROR",
    ),
    "stat": (
        "poll",
        "actual_position",
        "position",
        "inpos",
        "paused",
        "current_vel",
        "interp_state",
        "task_state",
        "homed",
        "joint",
        "linear_units",
        "file",
        "echo_serial_number",
        "state",
    ),
    "command": ("mode", "program_open", "auto", "abort", "mdi", "serial"),
    "error_channel": ("poll",),
}
#: Longest wait for a command to complete or be received, s (the module itself waits up to
#: 5 s for the reception before it returns); ``timeout_s`` in units.yaml.
COMMAND_TIMEOUT_S = 5.0
_POLL_S = 0.01


def find_linuxcnc_module(module_dir: Path | None = None) -> Any:
    """LinuxCNC's ``linuxcnc`` module: from ``module_dir`` if given, else importable as
    it is, else from Debian's ``/usr/lib/python3/dist-packages`` (only that module is
    loaded from there). InputError in one line when it is absent or built for another Python.
    """
    if module_dir is None:
        spec = _module_spec(None) or _module_spec([str(SYSTEM_MODULE_DIR)])
        where, folder = f"on the Python path or in {SYSTEM_MODULE_DIR}", SYSTEM_MODULE_DIR
    else:
        spec = _module_spec([str(module_dir)])
        where, folder = f"in {module_dir}", module_dir
    if spec is None:
        built = sorted(path.name for path in folder.glob("linuxcnc.*.so"))
        python = f"{sys.version_info.major}.{sys.version_info.minor}"
        found = f"; found {', '.join(built)}, built for another Python than {python}"
        raise InputError(
            f"LinuxCNC's Python module 'linuxcnc' is not {where}{found if built else ''}:"
            " install LinuxCNC (Debian linuxcnc-uspace) or run xmalign with the Python"
            " LinuxCNC uses"
        )
    loaded = sys.modules.get(spec.name)
    if loaded is not None and getattr(loaded, "__file__", None) == spec.origin:
        return loaded
    module = importlib.util.module_from_spec(spec)
    assert spec.loader is not None
    spec.loader.exec_module(module)
    return module


def _module_spec(path: list[str] | None) -> ModuleSpec | None:
    """The spec of a module file ``linuxcnc`` on ``path`` (a folder named linuxcnc, such
    as tests/linuxcnc, is a namespace package: not it)."""
    spec = PathFinder.find_spec("linuxcnc", path)
    return spec if spec is not None and spec.has_location and spec.loader is not None else None


class LocalLinuxCnc(LinuxCncControl):
    """A LinuxCNC on this computer, through its Python module (see the module's docstring).

    Parameters
    ----------
    linuxcnc : module
        LinuxCNC's ``linuxcnc`` module (:func:`find_linuxcnc_module`), or the
        simulated one (``sim.linuxcnc_module``).
    joints, in_position_mm, clock, start_timeout_s
        As for :class:`~firmware_iface.linuxcnc_control.LinuxCncControl`.
    timeout_s : float
        Longest wait for a command to complete or be received.
    """

    def __init__(
        self,
        linuxcnc: Any,
        joints: int = 3,
        in_position_mm: float = 0.002,
        clock: Clock | None = None,
        timeout_s: float = COMMAND_TIMEOUT_S,
        start_timeout_s: float = START_TIMEOUT_S,
    ) -> None:
        name = f"LinuxCNC on this computer ({linuxcnc.nmlfile})"
        super().__init__(name, joints, in_position_mm, clock, start_timeout_s)
        self.lc = linuxcnc
        self.timeout_s = timeout_s
        self._stat()  # LinuxCNC runs, or TransportError now
        self._command = linuxcnc.command()
        self._errors = linuxcnc.error_channel()
        log.debug("%s: opened", self.name)

    def close(self) -> None:
        """Nothing to release (the module's channels need no closing); logged."""
        log.debug("%s: closed", self.name)

    # -- reading ------------------------------------------------------------------
    def _stat(self) -> Any:
        try:
            stat = self.lc.stat()
            stat.poll()
        except self.lc.error as error:
            raise TransportError(
                f"{self.name} could not be read ({error}); is LinuxCNC running?"
            ) from error
        return stat

    def position_mm(self) -> Vec:
        """Actual X Y Z in machine coordinates (``stat.actual_position``), mm, shape (3,)."""
        stat = self._stat()
        return _in_mm(stat.actual_position, stat)

    def commanded_mm(self) -> Vec:
        """Commanded X Y Z in machine coordinates (``stat.position``), mm, shape (3,)."""
        stat = self._stat()
        return _in_mm(stat.position, stat)

    def _commanded_at_rest_mm(self) -> Vec | None:
        stat = self._stat()
        at_rest = stat.inpos or (stat.paused and stat.current_vel == 0.0)
        return _in_mm(stat.position, stat) if at_rest else None

    def program_state(self) -> ProgramState:
        """``idle``, ``running`` or ``paused``: ``stat.interp_state`` as linuxcncrsh maps it."""
        state = self._stat().interp_state
        if state in (self.lc.INTERP_READING, self.lc.INTERP_WAITING):
            return "running"
        return "paused" if state == self.lc.INTERP_PAUSED else "idle"

    def loaded_program(self) -> str | None:
        """``stat.file``: the open program, None when there is none."""
        return self._stat().file or None

    def _in_estop(self) -> bool:
        return bool(self._stat().task_state == self.lc.STATE_ESTOP)

    def _machine_on(self) -> bool:
        return bool(self._stat().task_state == self.lc.STATE_ON)

    def _joints_homed(self) -> list[bool]:
        return [bool(flag) for flag in self._stat().homed[: self.joints]]

    def _joints_faulted(self) -> list[bool]:
        return [bool(joint["fault"]) for joint in self._stat().joint[: self.joints]]

    def _error_text(self) -> str:
        """Every message waiting on LinuxCNC's error channel, joined; '' when none."""
        texts = []
        while (message := self._errors.poll()) is not None:
            log.debug("%s < error channel: %r", self.name, message[1])
            texts.append(str(message[1]))
        return "; ".join(texts)

    # -- commands -----------------------------------------------------------------
    def _send(self, what: str, send: Callable[[], object], completes: bool) -> None:
        """Send a command; wait until LinuxCNC completed it (``completes``) or received it.

        DeviceError with LinuxCNC's message as soon as it reports an error for it
        (``RCS_ERROR`` with its serial number), whether or not the command
        completes; DeviceTimeoutError when it does not get that far within ``timeout_s``.
        """
        self._stat()  # LinuxCNC is there (a command to a gone LinuxCNC waits 5 s, silently)
        log.debug("%s > %s", self.name, what)
        send()
        serial = self._command.serial
        deadline = self.clock.now() + self.timeout_s
        while True:
            stat = self._stat()
            behind = stat.echo_serial_number - serial
            if behind > 0 or (behind == 0 and stat.state == self.lc.RCS_DONE):
                outcome = "done"
            elif behind == 0 and stat.state == self.lc.RCS_ERROR:
                reason = self._error_text() or "no message"
                log.debug("%s < %s: error", self.name, what)
                raise DeviceError(f"{self.name} refused '{what}' ({reason})")
            elif behind == 0 and not completes:
                outcome = "received"
            elif self.clock.now() >= deadline and behind < 0:
                # the status answers, the task takes no command: seen with 2.9 after milltask died
                raise DeviceError(
                    f"{self.name} did not receive '{what}' within {self.timeout_s:g} s although"
                    " its status answers: LinuxCNC's task (milltask) has stopped; restart LinuxCNC"
                )
            elif self.clock.now() >= deadline:
                raise DeviceTimeoutError(
                    f"{self.name} did not complete '{what}' within {self.timeout_s:g} s (received)"
                )
            else:
                self.clock.sleep(_POLL_S)
                continue
            log.debug("%s < %s: %s", self.name, what, outcome)
            return

    def _set_mode(self, mode: Mode) -> None:
        constant = f"MODE_{mode.upper()}"
        value = getattr(self.lc, constant)
        self._send(f"mode({constant})", lambda: self._command.mode(value), True)

    def _open_program(self, path: str) -> None:
        self._send(f"program_open({path!r})", lambda: self._command.program_open(path), True)

    def _run_program(self) -> None:
        self._send("auto(AUTO_RUN, 0)", lambda: self._command.auto(self.lc.AUTO_RUN, 0), False)

    def _mdi(self, line: str) -> None:
        self._send(f"mdi({line!r})", lambda: self._command.mdi(line), False)

    def hold(self) -> None:
        """Feed hold (``auto(AUTO_PAUSE)``)."""
        self._send("auto(AUTO_PAUSE)", lambda: self._command.auto(self.lc.AUTO_PAUSE), False)

    def resume(self) -> None:
        """Go on after an M0 or a feed hold (``auto(AUTO_RESUME)``)."""
        self._send("auto(AUTO_RESUME)", lambda: self._command.auto(self.lc.AUTO_RESUME), False)

    def stop_program(self) -> None:
        """Abort the program (``abort()``)."""
        self._send("abort()", self._command.abort, True)


def _in_mm(values: Any, stat: Any) -> Vec:
    """X Y Z of a position of ``stat`` (machine units) in mm, shape (3,)."""
    return np.array(values[:3], dtype=float) / float(stat.linear_units)


def open_local_linuxcnc(
    module_dir: Path | None = None,
    nml_file: Path | None = None,
    joints: int = 3,
    in_position_mm: float = 0.002,
    clock: Clock | None = None,
    timeout_s: float = COMMAND_TIMEOUT_S,
    start_timeout_s: float = START_TIMEOUT_S,
) -> LocalLinuxCnc:
    """The LinuxCNC running on this computer, through its module (``nml_file``: the
    NML configuration of that LinuxCNC, default the module's own)."""
    linuxcnc = find_linuxcnc_module(module_dir)
    if nml_file is not None:
        linuxcnc.nmlfile = str(nml_file)
    return LocalLinuxCnc(linuxcnc, joints, in_position_mm, clock, timeout_s, start_timeout_s)
