"""The measurement program: approach, runs over the targets with dwells, retract.

For each line of the plan:

1. a message naming the line and the unit angles to command (reported degrees);
2. a safe approach: rapid to the top of the Z travel, rapid across to the
   pre-position (first target minus the overrun), feed down to it;
3. a programmed stop, so the positioning units can be set before the run;
4. each run: the targets in order, each approached in ``+u`` and followed by a
   dwell (or, for a controller xmalign runs the program on, a programmed stop
   that xmalign resumes once the point is captured), then the overrun past
   the last target; bidirectional runs come back
   over the targets in reverse (approached in ``-u``), unidirectional runs feed
   back to the pre-position. Between targets the tool moves at the transit
   feed (the rapid feed, or the interferometer's ``max_speed_mm_min`` if
   lower) as a straight G1 move, and only the last ``measurement.approach_mm``
   before each target at the measuring feed (docs/machine-time.md);
5. the drift check: the first target once more, approached in ``+u``, with a dwell;
6. a rapid retract to the top of the Z travel.

Points are machine coordinates of the CNC tool point; the dialect states the
coordinate system (machine coordinates, or a work offset it sets itself) and
retracts in machine coordinates.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from trajectories.gcode.base import Dialect
from trajectories.gcode.linuxcnc import LinuxCncDialect
from trajectories.gcode.machine_time import MachineTime, MachineTimer
from xmalign.errors import OutOfRangeError
from xmalign.formats.plan import Plan, PlanLine
from xmalign.geometry import Vec
from xmalign.machine import AXES, Machine

#: The comment near the top of every program xmalign writes (how it knows its own files).
PROGRAM_MARK = "xmalign measurement program"
#: The format of the measurement program, in its history comments.
PROGRAM_FORMAT = "xmalign.program/1"


@dataclass(frozen=True)
class _Feeds:
    """Measuring feed (last approach, overrun) and transit feed (between targets), mm/min."""

    measure: float
    transit: float


def _with(point_mm: Vec, **axes_mm: float) -> Vec:
    """``point_mm`` with the named axes replaced, shape (3,)."""
    moved = np.array(point_mm, dtype=float)
    for axis, value in axes_mm.items():
        moved[AXES.index(axis)] = value
    return moved


def _start_mm(machine: Machine) -> Vec:
    """Where the program is assumed to start: top of Z above the X and Y minimum (as sim/cnc.py)."""
    low, high = machine.travel_min_mm, machine.travel_max_mm
    return np.array([low[0], low[1], high[2]])


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


def _approach_blocks(
    dialect: Dialect,
    from_mm: Vec,
    target_mm: Vec,
    feeds: _Feeds,
    approach_mm: float,
    timer: MachineTimer,
) -> Iterator[str]:
    """Transit to ``approach_mm`` before the target, then the measuring feed onto it.

    Transit is a feed move (G1), not a rapid: a rapid need not be straight, and
    the receiver must stay on the beam.
    """
    step = target_mm - from_mm
    distance = float(np.linalg.norm(step))
    if distance > approach_mm and feeds.transit > feeds.measure:
        slow_from = target_mm - approach_mm * step / distance
        yield dialect.feed(_axes(slow_from), feeds.transit)
        timer.move(slow_from, feeds.transit)
    yield dialect.feed(_axes(target_mm), feeds.measure)
    timer.move(target_mm, feeds.measure)


def _run_blocks(
    dialect: Dialect,
    line: PlanLine,
    run: int,
    feeds: _Feeds,
    machine: Machine,
    timer: MachineTimer,
) -> Iterator[str]:
    points = line.target_points_mm()
    u = line.frame[0]
    overrun_mm = machine.measurement.overrun_mm
    approach_mm = machine.measurement.approach_mm
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
            yield from _approach_blocks(
                dialect, timer.position_mm, points[index], feeds, approach_mm, timer
            )
            yield from dialect.capture_wait(line.dwell_s)
            timer.dwell(line.dwell_s)
        past = points[-1] + overrun_mm * u if direction == "+" else points[0] - overrun_mm * u
        yield dialect.feed(_axes(past), feeds.measure)
        timer.move(past, feeds.measure)
    if not line.bidirectional:
        before = points[0] - overrun_mm * u
        yield dialect.feed(_axes(before), feeds.transit)
        timer.move(before, feeds.transit)


def _line_blocks(
    dialect: Dialect, line: PlanLine, machine: Machine, timer: MachineTimer
) -> Iterator[str]:
    feeds = _Feeds(machine.feed_mm_min.measure, machine.transit_feed_mm_min)
    overrun_mm = machine.measurement.overrun_mm
    rapid = machine.feed_mm_min.rapid
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
    timer.move(_with(timer.position_mm, Z=safe_z), rapid)
    yield dialect.rapid({"X": float(before[0]), "Y": float(before[1])})
    timer.move(_with(timer.position_mm, X=before[0], Y=before[1]), rapid)
    yield dialect.feed(_axes(before), feeds.measure)
    timer.move(before, feeds.measure)
    yield dialect.comment(f"line {line.id}: set the units, then cycle start")
    yield dialect.stop()
    for run in range(1, line.runs + 1):
        yield from _run_blocks(dialect, line, run, feeds, machine, timer)
    yield dialect.comment(f"line {line.id}: drift check, target 1 again")
    yield from _approach_blocks(
        dialect, timer.position_mm, points[0], feeds, machine.measurement.approach_mm, timer
    )
    yield from dialect.capture_wait(line.dwell_s)
    timer.dwell(line.dwell_s)
    yield dialect.comment(f"line {line.id}: retract")
    yield dialect.retract({"Z": safe_z})
    timer.move(_with(timer.position_mm, Z=safe_z), rapid)


def _program_blocks(
    plan: Plan, machine: Machine, dialect: Dialect, timer: MachineTimer
) -> list[str]:
    safe_z = float(machine.travel_max_mm[2])
    blocks = [
        *dialect.begin(),
        dialect.comment(f"{PROGRAM_MARK} for {plan.machine}"),
        *dialect.history(PROGRAM_FORMAT, [plan.source] if plan.source is not None else []),
        dialect.comment(f"{len(plan.lines)} lines: {' '.join(line.id for line in plan.lines)}"),
        dialect.retract({"Z": safe_z}),
    ]
    timer.move(_with(timer.position_mm, Z=safe_z), machine.feed_mm_min.rapid)
    for line in plan.lines:
        blocks.extend(_line_blocks(dialect, line, machine, timer))
    blocks.extend(dialect.end({"Z": safe_z}))
    return blocks


def write_program(plan: Plan, machine: Machine, dialect: Dialect) -> str:
    """The measurement program of ``plan`` in ``dialect``, with its history in comments
    (the plan file's SHA-256 when the plan was read from one).

    Parameters
    ----------
    plan : Plan
        Lines with targets, runs, direction and dwell.
    machine : Machine
        Travel (every programmed point is checked), the measuring feed (over
        the last ``measurement.approach_mm`` before each target and the
        overrun), the transit feed between targets (``transit_feed_mm_min``)
        and the overrun past the end targets (``measurement.overrun_mm``).
    dialect : Dialect
        Controller spelling.

    Raises
    ------
    OutOfRangeError
        A target or an overrun point lies outside the travel.
    """
    timer = MachineTimer(_start_mm(machine), machine.cnc.acceleration_mm_s2)
    return dialect.render(_program_blocks(plan, machine, dialect, timer))


def estimate_machine_time(plan: Plan, machine: Machine) -> MachineTime:
    """Machine time of the program :func:`write_program` writes for ``plan``.

    Every programmed move starts and ends at rest (exact stop) with a
    trapezoidal speed profile at its programmed feed and the machine file's
    ``cnc.acceleration_mm_s2`` (none given: feeds reached at once); dwells
    count in full. Programmed stops (setting the units) are not counted.
    The program starts at the top of Z above the X and Y minimum.
    """
    timer = MachineTimer(_start_mm(machine), machine.cnc.acceleration_mm_s2)
    _program_blocks(plan, machine, LinuxCncDialect(), timer)
    return timer.result()
