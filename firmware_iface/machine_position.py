"""Where the machine is: position sources and movers for the identification routine.

* :class:`CheckedMover` wraps any ``MachineMover`` (the simulated CNC, later a
  networked CNC): it refuses targets outside the travel and checks that the
  machine arrived and stands still.
* :class:`OperatorPrompt` is a ``MachineMover`` made of a person: it asks the
  operator to move the machine and to type the position the CNC displays (or
  takes it from another source, e.g. a file, once the operator confirms).
* :class:`FilePositions` reads the position from a text file that the CNC or
  another program keeps up to date (last line ``x y z`` in mm).

A network source only has to implement ``MachinePositionSource``
(``position_mm``, ``is_standstill``) to plug into the same places.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from xmalign.errors import (
    DeviceTimeoutError,
    FormatError,
    InputError,
    OutOfRangeError,
    TransportError,
    XmalignError,
)
from xmalign.geometry import Vec
from xmalign.machine import Machine
from xmalign.roles import Clock, MachineMover, MachinePositionSource, WallClock

_NUMBER = r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?"
_POSITION = re.compile(rf"^\s*({_NUMBER})[\s,;]+({_NUMBER})[\s,;]+({_NUMBER})\s*$")


def parse_position(text: str) -> Vec | None:
    """Three numbers ``x y z`` (separated by spaces, commas or semicolons), or None."""
    match = _POSITION.match(text)
    return None if match is None else np.array([float(g) for g in match.groups()])


def _format(position_mm: ArrayLike) -> str:
    x, y, z = np.asarray(position_mm, dtype=float)
    return f"X{x:.3f} Y{y:.3f} Z{z:.3f}"


class FilePositions:
    """The CNC tool point read from a text file on every call (``MachinePositionSource``).

    The file's last non-empty line holds ``x y z`` in mm (spaces, commas or
    semicolons between them); lines starting with ``#`` are comments. Whoever
    writes the file writes it when the machine stands still, so
    :meth:`is_standstill` is always True.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    def position_mm(self) -> Vec:
        try:
            lines = self.path.read_text(encoding="utf-8").splitlines()
        except OSError as error:
            raise TransportError(
                f"cannot read the machine position file {self.path} ({error.strerror})"
            ) from error
        except UnicodeDecodeError as error:
            raise FormatError(f"{self.path}: not UTF-8 text (byte {error.start})") from error
        numbered = [
            (n, line)
            for n, line in enumerate(lines, start=1)
            if line.strip() and not line.lstrip().startswith("#")
        ]
        if not numbered:
            raise FormatError(f"{self.path}: no position in the file (expected a line 'x y z')")
        number, line = numbered[-1]
        position = parse_position(line)
        if position is None:
            raise FormatError(f"{self.path}: line {number}: expected three numbers 'x y z' in mm")
        return position

    def is_standstill(self) -> bool:
        return True


class CheckedMover:
    """A ``MachineMover`` that checks travel, arrival and standstill of another one.

    Parameters
    ----------
    mover : MachineMover
    machine : Machine
        Travel limits.
    name : str
        How errors name the machine, e.g. ``"simulated CNC"``.
    tolerance_mm : float
        Largest distance between target and reported position after the move.
    """

    def __init__(
        self,
        mover: MachineMover,
        machine: Machine,
        name: str = "CNC",
        tolerance_mm: float = 0.05,
        clock: Clock | None = None,
        standstill_timeout_s: float = 10.0,
    ) -> None:
        self.mover = mover
        self.machine = machine
        self.name = name
        self.tolerance_mm = tolerance_mm
        self.clock = clock or WallClock()
        self.standstill_timeout_s = standstill_timeout_s

    def position_mm(self) -> Vec:
        return np.asarray(self.mover.position_mm(), dtype=float)

    def is_standstill(self) -> bool:
        return self.mover.is_standstill()

    def move_to(self, position_mm: ArrayLike, feed_mm_min: float) -> None:
        target = np.asarray(position_mm, dtype=float)
        if not self.machine.within_travel(target):
            raise OutOfRangeError(f"{_format(target)} is outside the travel of the {self.name}")
        self.mover.move_to(target, feed_mm_min)
        deadline = self.clock.now() + self.standstill_timeout_s
        while not self.mover.is_standstill():
            if self.clock.now() >= deadline:
                raise DeviceTimeoutError(
                    f"the {self.name} did not come to a standstill at {_format(target)}"
                )
            self.clock.sleep(0.05)
        miss = float(np.linalg.norm(self.position_mm() - target))
        if miss > self.tolerance_mm:
            raise OutOfRangeError(f"the {self.name} stopped {miss:.3f} mm from {_format(target)}")


class OperatorPrompt:
    """A ``MachineMover`` for machines xmalign cannot command: the operator moves them.

    :meth:`move_to` asks the operator to move the machine to the target and
    then reads the position: typed by the operator (Enter alone accepts the
    target as typed-in position), or, with ``source``, read from it after the
    operator confirms. A typed position must be three numbers inside the
    travel and within ``max_deviation_mm`` of the target; otherwise the
    operator is asked again. A position read from ``source`` is checked the same way
    after each Enter (pressed before the machine got there: asked again).

    Parameters
    ----------
    machine : Machine
    ask : callable
        ``ask(prompt) -> str`` (``input`` in a terminal); EOFError means no operator.
    tell : callable
        ``tell(message)`` for explanations.
    source : MachinePositionSource, optional
        Where to read the position once the operator confirms.
    max_deviation_mm : float
        Largest accepted distance between the target and the typed position.
    """

    def __init__(
        self,
        machine: Machine,
        ask: Callable[[str], str] = input,
        tell: Callable[[str], None] = print,
        source: MachinePositionSource | None = None,
        max_deviation_mm: float = 5.0,
    ) -> None:
        self.machine = machine
        self.ask = ask
        self.tell = tell
        self.source = source
        self.max_deviation_mm = max_deviation_mm
        self._position_mm: Vec | None = None

    def position_mm(self) -> Vec:
        if self.source is not None:
            return np.asarray(self.source.position_mm(), dtype=float)
        if self._position_mm is None:
            self._position_mm = self._typed(None)
        return self._position_mm.copy()

    def is_standstill(self) -> bool:
        return True

    def move_to(self, position_mm: ArrayLike, feed_mm_min: float) -> None:
        target = np.asarray(position_mm, dtype=float)
        if not self.machine.within_travel(target):
            raise OutOfRangeError(f"{_format(target)} is outside the machine's travel")
        self.tell(f"Move the machine to {_format(target)} (tool point, CNC coordinates).")
        if self.source is None:
            self._position_mm = self._typed(target)
            return
        while True:  # Enter pressed before the machine got there: say where it is, ask again
            self._answer("Press Enter when the machine stands there: ")
            position = self.position_mm()
            miss = float(np.linalg.norm(position - target))
            if miss <= self.max_deviation_mm:
                return
            self.tell(
                f"the machine stands at {_format(position)}, {miss:.1f} mm from the target;"
                " move it there first"
            )

    def _answer(self, prompt: str) -> str:
        try:
            return self.ask(prompt)
        except EOFError as error:
            raise XmalignError("no answer from the operator (end of input)") from error

    def _typed(self, target: Vec | None) -> Vec:
        hint = "Enter accepts the target" if target is not None else "x y z"
        while True:
            text = self._answer(f"Position the CNC displays, mm ({hint}): ")
            try:
                return self._check(text, target)
            except InputError as error:
                self.tell(str(error))

    def _check(self, text: str, target: Vec | None) -> Vec:
        if not text.strip() and target is not None:
            return target.copy()
        position = parse_position(text)
        if position is None:
            raise InputError(f"'{text.strip()}' is not a position: type three numbers 'x y z'")
        if not self.machine.within_travel(position):
            raise InputError(f"{_format(position)} is outside the machine's travel")
        if target is not None and np.linalg.norm(position - target) > self.max_deviation_mm:
            raise InputError(
                f"{_format(position)} is more than {self.max_deviation_mm:g} mm from the target"
                f" {_format(target)}; move the machine there first"
            )
        return position
