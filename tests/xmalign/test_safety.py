"""units_locked_on_exit: axes stopped and locked on success, error and Ctrl-C, one message."""

from __future__ import annotations

import os
import signal

import numpy as np
import pytest

from sim.clock import SimClock
from sim.units import SimPositioningUnit, SimUnit
from xmalign.errors import (
    DeviceError,
    DeviceTimeoutError,
    DriveFaultError,
    MachineKeyError,
    TransportError,
)
from xmalign.safety import (
    StopSignal,
    interrupted,
    like,
    lock_all,
    stop_signals_as_interrupts,
    units_locked_on_exit,
)


def moving_units() -> tuple[SimClock, SimPositioningUnit, SimPositioningUnit]:
    """Both simulated units with every axis in the middle of a long move."""
    clock = SimClock()
    launch = SimPositioningUnit(SimUnit("launch", clock, seed=1))
    receiver = SimPositioningUnit(SimUnit("receiver", clock, seed=2))
    for axis in (*launch.axes, *receiver.axes):
        axis.move_to(1.0)
    clock.sleep(0.5)
    return clock, launch, receiver


def all_locked(clock: SimClock, *units: SimPositioningUnit) -> bool:
    clock.sleep(1.0)  # braking from full speed takes a third of a second
    return all(axis.is_locked() for unit in units for axis in unit.axes)


def test_locks_after_success() -> None:
    clock, launch, receiver = moving_units()
    with units_locked_on_exit(launch, receiver):
        pass
    assert all_locked(clock, launch, receiver)
    assert all(abs(a) < 0.9 for a in np.concatenate([launch.angles_rad(), receiver.angles_rad()]))


@pytest.mark.parametrize(
    "error", [DriveFaultError("axis a1 reports fault 2"), RuntimeError("bug"), KeyboardInterrupt()]
)
def test_locks_and_propagates_on_error(error: BaseException) -> None:
    clock, launch, receiver = moving_units()
    with pytest.raises(type(error)) as caught, units_locked_on_exit(launch, receiver):
        raise error
    assert caught.value is error
    assert all_locked(clock, launch, receiver)


class UnreachableAxis:
    """An axis whose link is gone: every command fails."""

    name = "a2"
    label = "axis a2 of the launch unit at 10.0.0.5:502"

    def lock(self) -> None:
        raise TransportError("lost the connection to the launch unit at 10.0.0.5:502")


class HalfReachableUnit:
    kind = "launch"

    def __init__(self, reachable: SimPositioningUnit) -> None:
        self.axes = (reachable.axes[0], UnreachableAxis())


def test_one_unreachable_axis_does_not_stop_the_others() -> None:
    clock, launch, receiver = moving_units()
    unit = HalfReachableUnit(launch)
    with pytest.raises(DeviceError) as caught, units_locked_on_exit(unit, receiver):
        pass
    assert str(caught.value) == (
        "could not lock axis a2 of the launch unit at 10.0.0.5:502: lost the connection to the"
        " launch unit at 10.0.0.5:502"
    )
    assert all_locked(clock, receiver) and launch.axes[0].is_locked()


def test_locking_problems_join_the_original_message() -> None:
    _, launch, _ = moving_units()
    with pytest.raises(DriveFaultError) as caught, units_locked_on_exit(HalfReachableUnit(launch)):
        raise DriveFaultError("axis a1 reports fault 2: drive fault")
    assert str(caught.value).startswith("axis a1 reports fault 2: drive fault; could not lock")


def test_ctrl_c_becomes_one_line() -> None:
    _, launch, _ = moving_units()
    with pytest.raises(KeyboardInterrupt) as caught, units_locked_on_exit(launch):
        raise KeyboardInterrupt
    error = interrupted(caught.value)
    assert isinstance(error, KeyboardInterrupt)  # the CLI exits with 130
    assert str(error) == "interrupted by the operator; all axes were stopped and locked"


def test_lock_all_reports_each_axis_that_cannot_be_locked() -> None:
    clock, launch, receiver = moving_units()
    assert lock_all((launch, receiver)) == []
    assert all_locked(clock, launch, receiver)
    problems = lock_all((HalfReachableUnit(launch),))
    assert problems == [
        "could not lock axis a2 of the launch unit at 10.0.0.5:502: lost the"
        " connection to the launch unit at 10.0.0.5:502"
    ]


class UnreachableUnit:
    """A unit whose link is lost: every axis fails to lock for the same reason."""

    kind = "receiver"

    def __init__(self) -> None:
        self.axes = (UnreachableAxis(), UnreachableAxis(), UnreachableAxis())
        for axis, name in zip(self.axes, ("a3", "a4", "a5"), strict=True):
            axis.name = name


def test_a_lost_unit_is_one_sentence_not_one_per_axis() -> None:
    assert lock_all((UnreachableUnit(),)) == [
        "could not lock axes a3, a4, a5 of the receiver unit: lost the connection to the"
        " launch unit at 10.0.0.5:502"
    ]


class SignalledWhileLocking:
    """An axis whose lock command is interrupted by a signal (a shutdown while locking)."""

    name = "a1"

    def __init__(self, axis, signum: int) -> None:
        self.axis, self.signum = axis, signum

    def lock(self) -> None:
        signal.raise_signal(self.signum)
        self.axis.lock()


def test_a_sigterm_while_locking_waits_until_every_axis_is_locked() -> None:
    clock, launch, receiver = moving_units()

    class Unit:
        kind = "launch"
        axes = (SignalledWhileLocking(launch.axes[0], signal.SIGTERM), *launch.axes[1:])

    with (
        stop_signals_as_interrupts(),
        pytest.raises(StopSignal) as caught,
        units_locked_on_exit(Unit(), receiver),
    ):
        pass
    assert caught.value.signum == signal.SIGTERM
    assert all_locked(clock, launch, receiver)


def test_sigterm_becomes_one_line_naming_it() -> None:
    _, launch, _ = moving_units()
    with (
        stop_signals_as_interrupts(),
        pytest.raises(StopSignal) as caught,
        units_locked_on_exit(launch),
    ):
        signal.raise_signal(signal.SIGHUP)
    error = interrupted(caught.value)
    assert isinstance(error, StopSignal) and error.signum == signal.SIGHUP
    assert str(error) == "stopped by SIGHUP; all axes were stopped and locked"


def test_a_forked_worker_ends_on_sigterm_as_by_default() -> None:
    """``mc``'s process pool forks workers that inherit the handler: a SIGTERM ends a worker
    as it would without xmalign (no StopSignal, no traceback in a worker)."""
    ready, tell = os.pipe()
    with stop_signals_as_interrupts():
        child = os.fork()
        if child == 0:  # pragma: no cover - the worker; a StopSignal here exits with 3
            try:
                os.write(tell, b"r")
                signal.pause()
            finally:
                os._exit(3)
        os.read(ready, 1)  # the worker runs Python code: the signal is not lost in the fork
        os.kill(child, signal.SIGTERM)
        _, status = os.waitpid(child, 0)
    os.close(ready)
    os.close(tell)
    assert os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGTERM


@pytest.mark.parametrize(
    "error",
    [
        StopSignal(signal.SIGTERM),
        KeyboardInterrupt(),
        MachineKeyError("cnc.work_offset", "not a G54..G59 offset"),
        DeviceTimeoutError("no answer"),
    ],
    ids=["sigterm", "ctrl-c", "machine-key", "timeout"],
)
def test_like_keeps_the_kind_and_the_attributes_with_the_new_message(error) -> None:
    """Made by calling the class, a StopSignal would take the message for its signal."""
    same = like(error, "stopped: 3 points kept")
    assert type(same) is type(error) and str(same) == "stopped: 3 points kept"
    assert vars(same) == vars(error)  # a StopSignal's signum, a MachineKeyError's key
