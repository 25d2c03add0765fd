"""Leave the positioning units stopped and locked, whatever happens.

:func:`units_locked_on_exit` is a context manager around any work with the
units. On the way out, on success, on an error and on Ctrl-C alike, it stops
and locks every axis of every unit, axis by axis, so one unreachable axis does
not leave the others free. A second Ctrl-C (or a SIGTERM, SIGHUP) while
locking is deferred until the locking is done. :func:`stop_signals_as_interrupts`
makes SIGTERM and SIGHUP stop a command as Ctrl-C does (:class:`StopSignal`).
Only roles are used here: the same code secures Modbus units,
CiA 402 axes and simulated units.
"""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TypeVar

from xmalign.errors import DeviceError, XmalignError
from xmalign.roles import PositioningUnit, RotaryAxis

#: Any exception: :func:`like` gives back the kind it is given.
E = TypeVar("E", bound=BaseException)


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


#: Signals that stop a command as Ctrl-C does: a shutdown, a closed terminal or ssh session.
STOP_SIGNALS = (signal.SIGTERM, signal.SIGHUP)


class StopSignal(KeyboardInterrupt):
    """SIGTERM or SIGHUP taken as a Ctrl-C; ``signum`` says which (exit code 128 + signum)."""

    def __init__(self, signum: int, *args: object) -> None:
        super().__init__(*args)
        self.signum = signum

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name


def like(error: E, message: str) -> E:
    """The same error saying ``message``: its class and attributes (a StopSignal's signal).

    Not made by calling the class with the message: a class whose constructor
    takes more than one message (:class:`StopSignal`,
    :class:`~xmalign.errors.MachineKeyError`) would take it for another argument.
    """
    kind = type(error)
    same = kind.__new__(kind)
    same.__dict__.update(error.__dict__)
    same.args = (message,)
    return same


def _stop_handler(owner_pid: int) -> Callable[[int, object], None]:
    """Raise StopSignal in the process that installed it; a forked worker (``mc``'s
    process pool) that inherited it ends as the signal's default would end it."""

    def handler(signum: int, frame: object) -> None:
        if os.getpid() != owner_pid:
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)
            return
        raise StopSignal(signum)

    return handler


@contextmanager
def stop_signals_as_interrupts() -> Iterator[None]:
    """Within the block, SIGTERM and SIGHUP raise :class:`StopSignal` (main thread only).

    Whatever handles Ctrl-C then handles them too: the units are locked, every
    point kept, and the command ends with one line.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    stop = _stop_handler(os.getpid())
    previous = {signum: signal.signal(signum, stop) for signum in STOP_SIGNALS}
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


@contextmanager
def _sigint_deferred() -> Iterator[None]:
    """Hold back Ctrl-C, SIGTERM and SIGHUP (main thread only); re-deliver the first after."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list[int] = []
    deferred = (signal.SIGINT, *STOP_SIGNALS)
    previous = {
        signum: signal.signal(signum, lambda signum, _: pending.append(signum))
        for signum in deferred
    }
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    if pending and pending[0] == signal.SIGINT:
        raise KeyboardInterrupt
    if pending:
        signal.raise_signal(pending[0])


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
            raise like(error, "; ".join([str(error), *problems])) from error
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
    cause = (
        f"stopped by {error.name}"
        if isinstance(error, StopSignal)
        else "interrupted by the operator"
    )
    notes = getattr(error, "__notes__", []) or ["all axes were stopped and locked"]
    return like(error, "; ".join([cause, *notes]))
