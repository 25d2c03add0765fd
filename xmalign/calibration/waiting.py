"""Waiting for the machine: at a point, gone from it, or any condition, with the units read."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from xmalign.calibration.capture import CalibrationRun, CapturePoint
from xmalign.errors import DeviceError
from xmalign.roles import MachinePositionSource

#: While a run waits for the machine, it reads the units this often (a lost link shows), s.
DEVICE_CHECK_S = 1.0


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
    run: CalibrationRun, done: Callable[[], bool], what: str, timeout_s: float, poll_s: float
) -> None:
    """Poll ``done`` until it holds; read the units every ``DEVICE_CHECK_S`` meanwhile."""
    clock = run.clock
    deadline = clock.now() + timeout_s
    checked_s = clock.now()
    while clock.now() < deadline:
        if done():
            return
        if clock.now() - checked_s >= DEVICE_CHECK_S:
            run.launch.angles_rad()
            run.receiver.angles_rad()
            checked_s = clock.now()
        clock.sleep(poll_s)
    # the controller answers all along: the machine is late, no connection is lost
    raise DeviceError(f"the machine did not {what} within {timeout_s:.0f} s (timeouts.machine_s)")
