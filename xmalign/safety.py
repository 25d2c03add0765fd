"""Leave the positioning units stopped and locked, whatever happens.

:func:`units_locked_on_exit` is a context manager around any work with the
units. On the way out, on success, on an error and on Ctrl-C alike, it stops
and locks every axis of every unit, axis by axis, so one unreachable axis does
not leave the others free. A second Ctrl-C while locking is deferred until the
locking is done. Only roles are used here: the same code secures Modbus units,
CiA 402 axes and simulated units.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

from xmalign.errors import DeviceError, XmalignError
from xmalign.roles import PositioningUnit, RotaryAxis


def _label(axis: RotaryAxis, unit: PositioningUnit) -> str:
    return getattr(axis, "label", f"axis {axis.name} of the {unit.kind} unit")


def lock_all(units: tuple[PositioningUnit, ...]) -> list[str]:
    """Command every axis to stop and lock; one sentence per axis that refused or did not answer.

    An axis locks once it has braked to rest, so ``is_locked`` may still be
    False right after the command.
    """
    problems = []
    for unit in units:
        failed: dict[str, list[RotaryAxis]] = {}  # reason -> the axes it left unlocked
        for axis in unit.axes:
            try:
                axis.lock()
            except Exception as error:  # noqa: BLE001 - every axis must get its chance
                failed.setdefault(str(error), []).append(axis)
        for reason, axes in failed.items():
            if len(axes) == 1:
                problems.append(f"could not lock {_label(axes[0], unit)}: {reason}")
            else:  # a lost link: one sentence for the unit, not the same one per axis
                names = ", ".join(axis.name for axis in axes)
                problems.append(f"could not lock axes {names} of the {unit.kind} unit: {reason}")
    return problems


@contextmanager
def _sigint_deferred() -> Iterator[None]:
    """Hold back Ctrl-C (main thread only) and re-deliver it when the block ends."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list[bool] = []
    previous = signal.signal(signal.SIGINT, lambda *_: pending.append(True))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if pending:
        raise KeyboardInterrupt


@contextmanager
def units_locked_on_exit(*units: PositioningUnit) -> Iterator[None]:
    """Run a block with the units, then stop and lock all their axes.

    If the block raised an xmalign error and an axis could not be locked, the
    error is re-raised with the same type and the locking problems appended to
    its message (one line for the operator). Other exceptions (Ctrl-C, bugs)
    propagate unchanged with the problems as notes. If the block succeeded and
    an axis could not be locked, a :class:`~xmalign.errors.DeviceError` names it.
    """
    try:
        yield
    except BaseException as error:
        with _sigint_deferred():
            problems = lock_all(units)
        if problems and isinstance(error, XmalignError):
            raise type(error)("; ".join([str(error), *problems])) from error
        for problem in problems:
            error.add_note(problem)
        raise
    with _sigint_deferred():
        problems = lock_all(units)
    if problems:
        raise DeviceError("; ".join(problems))


def interrupted(error: KeyboardInterrupt) -> KeyboardInterrupt:
    """The one line a command reports for Ctrl-C inside :func:`units_locked_on_exit`.

    Still a KeyboardInterrupt: the CLI prints it and exits with 130, as for any Ctrl-C.
    """
    notes = getattr(error, "__notes__", [])
    if notes:
        return KeyboardInterrupt("interrupted by the operator; " + "; ".join(notes))
    return KeyboardInterrupt("interrupted by the operator; all axes were stopped and locked")
