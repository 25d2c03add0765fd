"""Measuring lines through the launch unit: where they run, how long, which targets.

Every line is a straight tool path whose receiver cp runs along the beam
through the launch cp: the 3 axis lines ``X``, ``Y``, ``Z`` and the 3 face
diagonals ``XY``, ``YZ``, ``XZ`` (the diagonals of the travel rectangle of that
face, as in ISO 230-6). The tool point is the receiver cp minus the receiver
offset. Along the beam, the receiver cp stays at least the stand-off and at most
the interferometer's range from the launch cp, and the tool point, overrun
included, stays inside the travel.

The line starts at the end nearest the launch unit, so ``u`` points away from
it, along the beam. Targets are distances from the start along ``u``.

When the launch cp lies outside what the receiver cp can reach across a line
(e.g. below the lowest receiver position for the X and Y lines), the line is
moved to the closest reachable parallel line (``shift_mm``); the beam is then
aimed at the middle target and runs slightly oblique to the line.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from xmalign.errors import GeometryError
from xmalign.geometry import Vec, rot_z, unit
from xmalign.machine import AXES, Machine

AXIS_LINES = ("X", "Y", "Z")
DIAGONAL_LINES = ("XY", "YZ", "XZ")
LINE_IDS = AXIS_LINES + DIAGONAL_LINES

#: Inner targets of an irregular layout move by up to this fraction of the spacing.
IRREGULAR_FRACTION = 0.25
#: Seed of the irregular layout, so that the same setup gives the same plan.
IRREGULAR_SEED = 2302
#: Components of a line direction below this count as zero (line parallel to that axis plane).
_ZERO_COMPONENT = 1e-12
#: Resolution of the G-code coordinates (3 decimals in mm): every target lies on this grid.
PROGRAM_RESOLUTION_MM = 1e-3
#: The grid step along a line is chosen among this many resolution units at most.
_MAX_GRID_STEPS = 10_000
#: A grid step whose direction is within this of the wanted one (rad) is taken at once.
_GRID_ANGLE_RAD = 1e-7


@dataclass(frozen=True)
class LineLayout:
    """Where one measuring line runs (CNC tool point coordinates, mm).

    Attributes
    ----------
    id : str
        ``X``, ``Y``, ``Z``, ``XY``, ``YZ`` or ``XZ``.
    start_mm : ndarray, shape (3,)
        Tool point at the first target.
    u : ndarray, shape (3,)
        Unit direction from start to end (away from the launch unit).
    targets_mm : ndarray, shape (M,)
        Distances of the targets from the start along ``u``; first 0, last the length.
    aim_receiver_cp_mm : ndarray, shape (3,)
        Receiver cp the beam is aimed at (the middle target).
    shift_mm : ndarray, shape (3,)
        Offset of the line from the beam line through the launch cp (zero unless the
        cp lies outside the receiver's reach across the line).
    beam_distance_mm : tuple of float
        Launch-cp-to-receiver-cp distance at the first and last target.
    coverage : float
        Length as a fraction of the stroke (axis lines) or of the face diagonal.
    """

    id: str
    start_mm: Vec
    u: Vec
    targets_mm: Vec
    aim_receiver_cp_mm: Vec
    shift_mm: Vec
    beam_distance_mm: tuple[float, float]
    coverage: float

    @property
    def length_mm(self) -> float:
        return float(self.targets_mm[-1])

    @property
    def end_mm(self) -> Vec:
        return self.start_mm + self.length_mm * self.u

    def target_points_mm(self) -> Vec:
        """Tool points of the targets, shape (M, 3)."""
        return self.start_mm + np.outer(self.targets_mm, self.u)


def receiver_offset_mcs(machine: Machine) -> Vec:
    """Receiver offset turned by the spindle angle: receiver cp = tool point + this, (3,)."""
    return rot_z(machine.spindle_angle_rad) @ machine.receiver_offset


def line_directions(line_id: str, machine: Machine) -> list[Vec]:
    """Candidate unit directions of a line, each shape (3,); the sense is chosen later.

    An axis line has its axis; a face diagonal has both diagonals of the face's
    travel rectangle.
    """
    stroke = machine.travel_max_mm - machine.travel_min_mm
    indices = [AXES.index(letter) for letter in line_id]
    if len(indices) == 1:
        return [np.eye(3)[indices[0]]]
    first, second = indices
    directions = []
    for sign in (1.0, -1.0):
        d = np.zeros(3)
        d[first], d[second] = stroke[first], sign * stroke[second]
        directions.append(unit(d))
    return directions


def _travel_interval(point_mm: Vec, e: Vec, machine: Machine) -> tuple[float, float]:
    """Parameter range ``s`` with ``point + s·e`` inside the travel (slab intersection)."""
    low, high = -math.inf, math.inf
    for k in range(3):
        if abs(e[k]) < _ZERO_COMPONENT:
            continue
        a = (machine.travel_min_mm[k] - point_mm[k]) / e[k]
        b = (machine.travel_max_mm[k] - point_mm[k]) / e[k]
        low, high = max(low, min(a, b)), min(high, max(a, b))
    return low, high


@dataclass(frozen=True)
class _Stretch:
    e: Vec
    sense: float
    near: float
    far: float
    shift: Vec

    @property
    def length(self) -> float:
        return self.far - self.near


def _stretches(launch_cp_mm: Vec, e: Vec, machine: Machine, overrun_mm: float) -> list[_Stretch]:
    """Usable target stretches on both senses of direction ``e`` through the launch cp.

    ``near``/``far`` are beam parameters (distance along ``sense·e`` from the cp
    to the receiver cp) of the first and last target, overrun already left out.
    """
    tool_on_beam = launch_cp_mm - receiver_offset_mcs(machine)
    fixed = np.abs(e) < _ZERO_COMPONENT
    clamped = np.clip(tool_on_beam, machine.travel_min_mm, machine.travel_max_mm)
    shift = np.where(fixed, clamped - tool_on_beam, 0.0)
    low, high = _travel_interval(tool_on_beam + shift, e, machine)
    measurement = machine.measurement
    reach = math.sqrt(max(machine.interferometer.max_range_mm**2 - float(shift @ shift), 0.0))
    stretches = []
    for sense in (1.0, -1.0):
        lo_s, hi_s = (low, high) if sense > 0 else (-high, -low)
        near = max(lo_s, measurement.standoff_mm) + overrun_mm
        far = min(hi_s, reach) - overrun_mm
        stretches.append(_Stretch(e=e, sense=sense, near=near, far=far, shift=shift))
    return stretches


def target_distances(length_mm: float, spacing_mm: float, irregular: bool) -> Vec:
    """Target distances from 0 to ``length_mm`` no more than ``spacing_mm`` apart, (M,).

    With ``irregular`` the inner targets move by a reproducible pseudo-random
    amount of up to ±25 % of the spacing (ISO 230-2: uneven intervals reveal
    periodic errors).
    """
    count = max(2, math.ceil(length_mm / spacing_mm - 1e-9) + 1)
    targets = np.linspace(0.0, length_mm, count)
    if irregular and count > 2:
        step = length_mm / (count - 1)
        rng = np.random.default_rng(IRREGULAR_SEED)
        targets[1:-1] += rng.uniform(-IRREGULAR_FRACTION, IRREGULAR_FRACTION, count - 2) * step
    return targets


def _grid_start(start_mm: Vec, step_mm: Vec, overrun_mm: float, machine: Machine) -> Vec:
    """The grid point nearest the start, moved on by grid steps until the overrun fits."""
    u = step_mm / np.linalg.norm(step_mm)
    start = np.round(start_mm / PROGRAM_RESOLUTION_MM) * PROGRAM_RESOLUTION_MM
    for _ in range(_MAX_GRID_STEPS):
        if machine.within_travel(start - overrun_mm * u, tol_mm=0.0):
            return start
        start = start + step_mm
    raise GeometryError(
        f"no point of the program's {PROGRAM_RESOLUTION_MM * 1000:g} um grid near"
        f" {np.round(start_mm, 4).tolist()} mm leaves the overrun inside the travel"
    )


def grid_step(u: Vec) -> Vec:
    """The shortest step on the program's grid along ``u`` (within 0.1 urad), mm, shape (3,).

    From a start on the grid, every whole multiple of it is on the grid too,
    so the plan's targets are exactly the coordinates the G-code commands. An
    axis line gets one resolution unit; a face diagonal of a 2000 x 1500 mm
    face (4:3) gets (4, 3) units; a direction with no short grid step gets the
    closest one within :data:`_MAX_GRID_STEPS` units.
    """
    u = np.asarray(u, dtype=float)
    lengths = np.arange(1, _MAX_GRID_STEPS + 1)[:, None]
    candidates = np.round(lengths * u)
    norms = np.linalg.norm(candidates, axis=1)
    norms[norms == 0] = np.inf
    angle = np.linalg.norm(candidates / norms[:, None] - u, axis=1)
    close = np.flatnonzero(angle < _GRID_ANGLE_RAD)
    best = int(close[0]) if len(close) else int(np.argmin(angle))
    return candidates[best] * PROGRAM_RESOLUTION_MM


def snap_targets(targets_mm: Vec, step_mm: float) -> Vec:
    """Target distances moved to whole grid steps; the last one never beyond its place."""
    steps = np.round(np.asarray(targets_mm) / step_mm)
    steps[-1] = np.floor(targets_mm[-1] / step_mm + 1e-9)
    return np.unique(steps) * step_mm


def _coverage(line_id: str, length_mm: float, machine: Machine) -> float:
    stroke = machine.travel_max_mm - machine.travel_min_mm
    indices = [AXES.index(letter) for letter in line_id]
    return length_mm / float(np.linalg.norm(stroke[indices]))


def plan_line(
    line_id: str, launch_cp_mm: Vec, machine: Machine, max_length_mm: float | None = None
) -> LineLayout:
    """Longest usable measuring line ``line_id`` through the launch cp.

    ``max_length_mm`` cuts it to at most that length from its end nearest the
    launch unit (a try-out before the real run: ``xmalign program --max-length-mm``).

    Raises
    ------
    GeometryError
        The longest stretch is shorter than ``measurement.min_line_mm``; the message
        says why and what to change.
    """
    launch_cp = np.asarray(launch_cp_mm, dtype=float)
    measurement = machine.measurement
    candidates = [
        stretch
        for e in line_directions(line_id, machine)
        for stretch in _stretches(launch_cp, e, machine, measurement.overrun_mm)
    ]
    best = max(candidates, key=lambda s: s.length)
    if best.length < measurement.min_line_mm:
        raise GeometryError(_too_short_message(line_id, best, machine))
    step = grid_step(best.sense * best.e)
    u = step / np.linalg.norm(step)
    exact_start = launch_cp + best.shift + best.near * u - receiver_offset_mcs(machine)
    start = _grid_start(exact_start, step, measurement.overrun_mm, machine)
    inside = min(
        best.length - float((start - exact_start) @ u),
        _travel_interval(start, u, machine)[1] - measurement.overrun_mm,
        math.inf if max_length_mm is None else max_length_mm,
    )
    targets = snap_targets(
        target_distances(inside, measurement.target_spacing_mm, measurement.irregular_spacing),
        float(np.linalg.norm(step)),
    )
    middle = 0.5 * (best.near + best.far)
    return LineLayout(
        id=line_id,
        start_mm=start,
        u=u,
        targets_mm=targets,
        aim_receiver_cp_mm=launch_cp + best.shift + middle * u,
        shift_mm=best.shift,
        beam_distance_mm=(
            float(math.hypot(best.near, np.linalg.norm(best.shift))),
            float(math.hypot(best.far, np.linalg.norm(best.shift))),
        ),
        coverage=_coverage(line_id, best.length, machine),
    )


def _too_short_message(line_id: str, best: _Stretch, machine: Machine) -> str:
    measurement = machine.measurement
    usable = max(best.length, 0.0)
    return (
        f"line {line_id}: only {usable:.0f} mm usable (minimum measurement.min_line_mm ="
        f" {measurement.min_line_mm:.0f} mm) between the stand-off of"
        f" {measurement.standoff_mm:.0f} mm from the launch unit, the"
        f" {machine.interferometer.max_range_mm:.0f} mm beam range and the travel"
        f" (overrun {measurement.overrun_mm:.0f} mm at both ends). Fix: place the launch unit"
        f" near one end of the {line_id} travel, or reduce measurement.standoff_mm"
    )


def shift_reason(layout: LineLayout, launch_cp_mm: Vec, machine: Machine) -> str:
    """Why the line could not pass through the launch cp and how to fix it (one sentence)."""
    offset = receiver_offset_mcs(machine)
    parts = []
    for k, axis in enumerate(AXES):
        delta = float(layout.shift_mm[k])
        if abs(delta) < 1e-9:
            continue
        low = machine.travel_min_mm[k] + offset[k]
        high = machine.travel_max_mm[k] + offset[k]
        coordinate = float(launch_cp_mm[k])
        if delta > 0:
            parts.append(
                f"the launch cp ({axis.lower()} = {coordinate:.1f} mm) is {delta:.1f} mm below"
                f" the lowest receiver cp {axis.lower()} = {low:.1f} mm ({axis} travel"
                f" min + receiver offset); raise the launch unit along {axis} by at least"
                f" {delta:.1f} mm"
            )
        else:
            parts.append(
                f"the launch cp ({axis.lower()} = {coordinate:.1f} mm) is {-delta:.1f} mm above"
                f" the highest receiver cp {axis.lower()} = {high:.1f} mm ({axis} travel"
                f" max + receiver offset); lower the launch unit along {axis} by at least"
                f" {-delta:.1f} mm"
            )
    return "; ".join(parts)
