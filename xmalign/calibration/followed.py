"""The followed drive: the controller runs the program, xmalign waits for each stop."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from functools import partial

import numpy as np

from xmalign.calibration.capture import CalibrationRun, CapturePoint, capture_sequence
from xmalign.calibration.waiting import has_left, point_where, stands_at, wait_for
from xmalign.calibration.way import ProgramWay, check_stop_on_way
from xmalign.formats.plan import PlanLine
from xmalign.geometry import Vec
from xmalign.roles import MachinePositionSource, ReportsProgram

#: The end of what a run following the machine tells the operator once a line's units are set.
PRESS_CYCLE_START = "press cycle start"


def follow_machine(
    run: CalibrationRun,
    position: MachinePositionSource,
    lines: Iterable[PlanLine],
    tell: Callable[[str], None],
    way: ProgramWay,
    tolerance_mm: float = 0.005,
    timeout_s: float = 600.0,
    poll_s: float = 0.05,
    check_program: Callable[[], None] = lambda: None,
) -> None:
    """Capture while the controller runs the program: wait for standstill at each target.

    The units are set for a line once the machine stands at the line's
    pre-position (``way.overrun_mm`` before the first target, where the program
    stops for it): fine alignment needs a machine at rest where the plan
    aligned the beam. ``tell`` gets what the operator is to do: run the
    program while the machine is not there, press cycle start once the units
    are set. Where the program stops twice
    at one place (the last target of a run and the first back; the drift
    check), the machine has to leave it before it counts as there again: the
    program moves on to overrun and approach, and a capture while it does would
    average a moving machine. While waiting, the units are read every
    ``DEVICE_CHECK_S``; the machine not at its next stop within ``timeout_s``
    ends the run with one line. A controller that reports its program
    (:class:`~xmalign.roles.ReportsProgram`) is checked as a controlled run is:
    its program stopped with the machine at rest off the program's way to the
    next stop is a program that is not the plan's (one line); held on that way
    (a feed hold), it is waited for. ``check_program()`` raises when the controller
    runs another program than xmalign's (:class:`xmalign.program_check.ProgramGuard`):
    called first, and again before the units are set and before each capture.
    """
    check_program()
    last_stop_mm = position.position_mm()
    passed: list[PlanLine] = []  # lines done: the program still runs through them
    for line in lines:
        if run.line_is_done(line):
            passed.append(line)
            continue
        pre_mm = way.pre_position_mm(line)
        where = f"the pre-position of line {line.id} {np.round(pre_mm, 3).tolist()} mm"
        to_line = way.to_line(last_stop_mm, passed, line)
        there = _arrived(position, pre_mm, to_line, tolerance_mm, where)
        if not there():
            tell(
                f"line {line.id}: waiting for the machine to stop at {where}"
                " (start the program if it is not running)"
            )
            wait_for(run, there, f"stop at {where}", timeout_s, poll_s, tell)
        check_program()
        run.prepare_line(line)
        tell(f"line {line.id}: units aligned and locked; {PRESS_CYCLE_START}")
        on_line = way.on_line(line)
        previous: CapturePoint | None = None
        for point in capture_sequence(line):
            if previous is not None and np.allclose(previous.point_mm, point.point_mm):
                wait_for(
                    run,
                    partial(has_left, position, previous, tolerance_mm),
                    f"move on from {point_where(previous)}",
                    timeout_s,
                    poll_s,
                )
            arrived = _arrived(position, point.point_mm, on_line, tolerance_mm, point_where(point))
            wait_for(run, arrived, f"stop at {point_where(point)}", timeout_s, poll_s, tell)
            check_program()
            run.capture(point, line.dwell_s, lambda p: stands_at(position, p, tolerance_mm))
            previous = point
        last_stop_mm = line.target_points_mm()[0]  # the drift check
        passed = []


def _arrived(
    position: MachinePositionSource,
    target_mm: Vec,
    way: Callable[[Vec], float],
    tolerance_mm: float,
    what: str,
) -> Callable[[], bool]:
    """Whether a followed machine stands at ``target_mm``; a program it reports stopped at
    rest off ``way`` (distance from it, mm) is not the plan's (:func:`check_stop_on_way`)."""

    def there() -> bool:
        at_mm = position.position_mm()
        if not position.is_standstill():
            return False
        if float(np.linalg.norm(at_mm - target_mm)) <= tolerance_mm:
            return True
        if isinstance(position, ReportsProgram):
            report = position.program_report()
            if report is not None and report.state == "paused":
                check_stop_on_way(at_mm, target_mm, way, tolerance_mm, what)
        return False

    return there
