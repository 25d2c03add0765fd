"""Capture from a program's reported events (the simulated CNC's stops and dwells)."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from typing import Protocol

import numpy as np

from xmalign.calibration.capture import CalibrationRun, CapturePoint, capture_sequence
from xmalign.errors import InputError
from xmalign.formats.plan import PlanLine
from xmalign.geometry import Vec


def check_program_position(point: CapturePoint, position_mm: Vec, tolerance_mm: float) -> None:
    """Refuse a dwell that is not where the plan expects the next capture."""
    miss = float(np.linalg.norm(np.asarray(position_mm) - point.point_mm))
    if miss > tolerance_mm:
        raise InputError(
            f"the program dwells at {np.round(position_mm, 3).tolist()} mm but the plan expects "
            f"line {point.line.id} run {point.run} target {point.index + 1} at "
            f"{np.round(point.point_mm, 3).tolist()} mm: program and plan do not match"
        )


#: A programmed stop farther than this from its plan line's axis is for another line, mm.
STOP_OFF_LINE_MM = 1.0


def check_program_stop(line: PlanLine, position_mm: Vec) -> None:
    """Refuse a programmed stop that is not on the plan's next line (a program for other
    lines): setting the units for a line the machine is not on would only lose the beam.

    ``xmalign program`` stops each line at its pre-position, on the line's axis.
    """
    offset = np.asarray(position_mm, dtype=float) - line.start_mm
    u = line.frame[0]
    off_mm = float(np.linalg.norm(offset - (offset @ u) * u))
    if off_mm > STOP_OFF_LINE_MM:
        raise InputError(
            f"the program stops at {np.round(position_mm, 3).tolist()} mm, {off_mm:.0f} mm off"
            f" the plan's line {line.id}: program and plan do not match (a program for other"
            " lines?)"
        )


class ProgramEvent(Protocol):
    """What a controller running the program reports (the simulated CNC's events)."""

    @property
    def kind(self) -> str: ...

    @property
    def position_mm(self) -> Vec: ...

    @property
    def dwell_s(self) -> float: ...


def capture_program(
    run: CalibrationRun, events: Iterable[ProgramEvent], tolerance_mm: float = 1e-3
) -> None:
    """Capture while a program runs: set the units at each programmed stop, capture at each dwell.

    The program is the one ``xmalign program`` writes for ``run.plan``: one
    stop per line (before its first run) and one dwell per capture point, in
    the order of :func:`capture_sequence`.
    """
    lines = iter(run.plan.lines)
    points: Iterator[CapturePoint] = iter(())
    for event in events:
        if event.kind == "stop":
            line = next(lines, None)
            if line is None:
                raise InputError("the program stops for more lines than the plan has")
            check_program_stop(line, event.position_mm)
            if not run.line_is_done(line):
                run.prepare_line(line)
            points = capture_sequence(line)
        elif event.kind == "dwell":
            point = next(points, None)
            if point is None:
                raise InputError("the program dwells at more points than the plan has")
            check_program_position(point, event.position_mm, tolerance_mm)
            run.capture(point, event.dwell_s)
