"""The measurement program: approach, runs over the targets with dwells, retract.

For each line of the plan:

1. a message naming the line and the unit angles to command (reported degrees);
2. a safe approach: rapid to the top of the Z travel, rapid across to the
   pre-position (first target minus the overrun), feed down to it;
3. a programmed stop, so the positioning units can be set before the run;
4. each run: the targets in order, each approached in ``+u`` and followed by a
   dwell, then the overrun past the last target; bidirectional runs come back
   over the targets in reverse (approached in ``-u``), unidirectional runs feed
   back to the pre-position;
5. a rapid retract to the top of the Z travel.

Points are machine coordinates of the CNC tool point; the dialect states the
coordinate system (machine coordinates, or a work offset it sets itself) and
retracts in machine coordinates.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from trajectories.gcode.base import Dialect
from xmalign.errors import OutOfRangeError
from xmalign.formats.plan import Plan, PlanLine
from xmalign.geometry import Vec
from xmalign.machine import AXES, Machine


def _axes(point_mm: Vec) -> dict[str, float]:
    return dict(zip(AXES, (float(v) for v in point_mm), strict=True))


def angles_message(line: PlanLine) -> str:
    """Operator message with the reported unit angles of a line, degrees."""
    launch = " ".join(f"{round(v, 4) + 0.0:.4f}" for v in np.degrees(line.launch_rad))
    receiver = " ".join(f"{round(v, 4) + 0.0:.4f}" for v in np.degrees(line.receiver_rad))
    return f"LINE {line.id}: LAUNCH DEG {launch} RECEIVER DEG {receiver}"


def _check_travel(line: PlanLine, label: str, point_mm: Vec, machine: Machine) -> None:
    if not machine.within_travel(point_mm):
        raise OutOfRangeError(
            f"line {line.id}: {label} at [{', '.join(f'{v:.3f}' for v in point_mm)}] mm is"
            f" outside the travel of '{machine.name}'; re-plan the line with xmalign program"
        )


def _run_blocks(
    dialect: Dialect, line: PlanLine, run: int, feed: float, overrun_mm: float
) -> Iterator[str]:
    points = line.target_points_mm()
    u = line.frame[0]
    count = len(points)
    passes = [("+", range(count))]
    if line.bidirectional:
        passes.append(("-", range(count - 1, -1, -1)))
    for direction, order in passes:
        for index in order:
            yield dialect.comment(
                f"{line.id} run {run} {direction} target {index + 1}/{count}"
                f" at {line.targets_mm[index]:.3f} mm"
            )
            yield dialect.feed(_axes(points[index]), feed)
            yield from dialect.dwell(line.dwell_s)
        past = points[-1] + overrun_mm * u if direction == "+" else points[0] - overrun_mm * u
        yield dialect.feed(_axes(past), feed)
    if not line.bidirectional:
        yield dialect.feed(_axes(points[0] - overrun_mm * u), feed)


def _line_blocks(
    dialect: Dialect, line: PlanLine, machine: Machine, overrun_mm: float
) -> Iterator[str]:
    feed = machine.feed_mm_min.measure
    safe_z = float(machine.travel_max_mm[2])
    points = line.target_points_mm()
    u = line.frame[0]
    before, after = points[0] - overrun_mm * u, points[-1] + overrun_mm * u
    for index, point in enumerate(points):
        _check_travel(line, f"target {index + 1}", point, machine)
    for label, point in (("pre-position", before), ("overrun end", after)):
        _check_travel(line, label, point, machine)
    yield dialect.message(angles_message(line))
    yield dialect.comment(f"line {line.id}: approach")
    yield dialect.retract({"Z": safe_z})
    yield dialect.rapid({"X": float(before[0]), "Y": float(before[1])})
    yield dialect.feed(_axes(before), feed)
    yield dialect.comment(f"line {line.id}: set the units, then cycle start")
    yield dialect.stop()
    for run in range(1, line.runs + 1):
        yield from _run_blocks(dialect, line, run, feed, overrun_mm)
    yield dialect.comment(f"line {line.id}: retract")
    yield dialect.retract({"Z": safe_z})


def write_program(plan: Plan, machine: Machine, dialect: Dialect) -> str:
    """The measurement program of ``plan`` in ``dialect``.

    Parameters
    ----------
    plan : Plan
        Lines with targets, runs, direction and dwell.
    machine : Machine
        Travel (every programmed point is checked), feeds and the overrun past
        the end targets before a reversal (``measurement.overrun_mm``).
    dialect : Dialect
        Controller spelling.

    Raises
    ------
    OutOfRangeError
        A target or an overrun point lies outside the travel.
    """
    blocks = [
        *dialect.begin(),
        dialect.comment(f"xmalign measurement program for {plan.machine}"),
        dialect.comment(f"{len(plan.lines)} lines: {' '.join(line.id for line in plan.lines)}"),
        dialect.retract({"Z": float(machine.travel_max_mm[2])}),
    ]
    for line in plan.lines:
        blocks.extend(_line_blocks(dialect, line, machine, machine.measurement.overrun_mm))
    blocks.extend(dialect.end({"Z": float(machine.travel_max_mm[2])}))
    return dialect.render(blocks)
