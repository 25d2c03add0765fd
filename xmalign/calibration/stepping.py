"""The stepping drive: xmalign moves the machine to each target in turn."""

from __future__ import annotations

from collections.abc import Iterable

from xmalign.calibration.capture import CalibrationRun, capture_sequence
from xmalign.formats.plan import PlanLine
from xmalign.roles import MachineMover


def step_through(
    run: CalibrationRun,
    mover: MachineMover,
    lines: Iterable[PlanLine],
    feed_mm_min: float,
    overrun_mm: float,
) -> None:
    """Capture by moving the machine to each target in turn (an operator or a driven CNC).

    Each pass approaches its first target from beyond, by ``overrun_mm``, so
    every target of a pass is approached in the pass's direction.
    """
    for line in lines:
        if run.line_is_done(line):
            continue
        u = line.frame[0]
        points = line.target_points_mm()
        mover.move_to(points[0] - overrun_mm * u, feed_mm_min)
        run.prepare_line(line)
        for point in capture_sequence(line):
            if point.index == (0 if point.direction == "+" else len(points) - 1):
                beyond = -overrun_mm if point.direction == "+" else overrun_mm
                mover.move_to(point.point_mm + beyond * u, feed_mm_min)
            mover.move_to(point.point_mm, feed_mm_min)
            run.capture(point, line.dwell_s)
