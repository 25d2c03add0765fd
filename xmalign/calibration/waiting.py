"""Waiting for the machine: at a point, gone from it, or any condition, with the units read."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from xmalign.calibration.capture import CalibrationRun, CapturePoint
from xmalign.errors import DeviceError
from xmalign.roles import MachinePositionSource

#: While a run waits for the machine, it reads the units this often (a lost link shows), s.
DEVICE_CHECK_S = 1.0
#: A wait for the machine longer than this is told, and again every WAIT_RETOLD_S, s.
WAIT_TOLD_S = 10.0
WAIT_RETOLD_S = 60.0


def stands_at(position: MachinePositionSource, point: CapturePoint, tolerance_mm: float) -> bool:
    """The machine stands still at the point (it has not gone on with the program)."""
    miss = float(np.linalg.norm(position.position_mm() - point.point_mm))
    return position.is_standstill() and miss <= tolerance_mm


def has_left(position: MachinePositionSource, point: CapturePoint, tolerance_mm: float) -> bool:
    return not stands_at(position, point, tolerance_mm)


def point_where(point: CapturePoint) -> str:
    return (
        f"line {point.line.id} run {point.run} target {point.index + 1}"
        f" {np.round(point.point_mm, 3).tolist()} mm"
    )


def wait_for(
    run: CalibrationRun,
    done: Callable[[], bool],
    what: str,
    timeout_s: float,
    poll_s: float,
    tell: Callable[[str], None] = lambda text: None,
) -> None:
    """Poll ``done`` until it holds; read the units every ``DEVICE_CHECK_S`` meanwhile.

    A wait longer than ``WAIT_TOLD_S`` is told (``tell``: what it waits for, how
    long so far, the longest it waits), and again every ``WAIT_RETOLD_S``.
    """
    clock = run.clock
    started_s = clock.now()
    deadline = started_s + timeout_s
    checked_s = told_s = started_s
    next_tell_s = started_s + WAIT_TOLD_S
    while clock.now() < deadline:
        if done():
            return
        if clock.now() - checked_s >= DEVICE_CHECK_S:
            run.launch.angles_rad()
            run.receiver.angles_rad()
            checked_s = clock.now()
        if clock.now() >= next_tell_s:
            told_s = clock.now()
            next_tell_s = told_s + WAIT_RETOLD_S
            tell(
                f"still waiting for the machine to {what} ({told_s - started_s:.0f} s so far;"
                f" at most {timeout_s:.0f} s, timeouts.machine_s)"
            )
        clock.sleep(poll_s)
    # the controller answers all along: the machine is late, no connection is lost
    raise DeviceError(f"the machine did not {what} within {timeout_s:.0f} s (timeouts.machine_s)")
