"""FANUC Series 0i / 16i / 30i: pitch error compensation parameters and values.

From the parameter manuals (parameters 3620-3624) and the pitch error
compensation descriptions:

- 3620 number of the compensation point at the reference position,
  3621 / 3622 the most negative / most positive point number,
  3623 magnification, 3624 interval between points (detection units);
- the machine coordinate origin is the reference position, compensation
  points lie at multiples of the interval from it;
- the value at point ``n`` is the *incremental* correction for the move from
  point ``n - 1`` to point ``n`` (so the value at the most negative point is 0),
  in detection units times the magnification, within -127 .. 127 per point;
- the point numbers 0 .. 1023 are shared by all axes, at most 128 per axis;
- parameter tape format ``N<param>A<axis>P<value>...;`` and pitch data
  ``N1<point>P<value>;`` (``N10000`` is point 0), between ``%`` lines.

The correction is minus the positioning error, referred to the reference
position. The detection unit is taken as 1 um (IS-B). Only the positioning
error is written (mean of both directions); straightness and squareness need
Fanuc's separate straightness / inclination compensation options.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from xmalign.comp.common import POSITIONING, axis_number, check_count, grid_of, table
from xmalign.errors import OutOfRangeError
from xmalign.formats.error_tables import ErrorTableSet, Table
from xmalign.rigid_body import AXES, Chain

NAME = "fanuc"
DETECTION_UNIT_UM = 1.0
MAX_POINTS_PER_AXIS = 128
MAX_POINTS_TOTAL = 1024
MAX_VALUE = 127
MAX_MAGNIFICATION = 100
COMPENSATES = frozenset(POSITIONING.values())


@dataclass(frozen=True)
class PitchTable:
    """The pitch error compensation of one axis (Fanuc numbering and units)."""

    axis: str
    reference_number: int
    first_number: int
    last_number: int
    magnification: int
    interval_units: int
    values: np.ndarray


def pitch_table(axis: str, source: Table, first_number: int) -> PitchTable:
    """Fanuc pitch data for one axis, its points numbered from ``first_number``."""
    interval = max(int(round(grid_of(source.positions_mm).step_mm * 1e3 / DETECTION_UNIT_UM)), 1)
    interval_mm = interval * DETECTION_UNIT_UM * 1e-3
    low = min(np.floor(source.positions_mm[0] / interval_mm + 1e-9), 0)
    high = max(np.ceil(source.positions_mm[-1] / interval_mm - 1e-9), 0)
    steps = np.arange(int(low), int(high) + 1)
    check_count(len(steps), MAX_POINTS_PER_AXIS, f"{POSITIONING[axis]} (per axis)", "Fanuc")
    error_um = np.interp(steps * interval_mm, source.positions_mm, source.values) * 1e3
    reference = int(np.flatnonzero(steps == 0)[0])
    correction = -(error_um - error_um[reference]) / DETECTION_UNIT_UM
    for magnification in range(1, MAX_MAGNIFICATION + 1):
        increments = np.diff(np.round(correction / magnification), prepend=np.nan)
        increments[0] = 0
        if np.max(np.abs(increments)) <= MAX_VALUE:
            return PitchTable(
                axis=axis,
                reference_number=first_number + reference,
                first_number=first_number,
                last_number=first_number + len(steps) - 1,
                magnification=magnification,
                interval_units=interval,
                values=increments.astype(int),
            )
    raise OutOfRangeError(
        f"Fanuc: {POSITIONING[axis]} changes by more than {MAX_VALUE} x {MAX_MAGNIFICATION}"
        " detection units between two points"
    )


def _parameter(number: int, values: list[int]) -> str:
    axes = "".join(f"A{i}P{v}" for i, v in enumerate(values, start=1))
    return f"N{number:05d}{axes};"


def render(tables: ErrorTableSet, chain: Chain) -> dict[str, str]:
    """File name -> text of the parameter tape."""
    pitch = []
    first = 0
    for axis in AXES:
        pitch.append(pitch_table(axis, table(tables, POSITIONING[axis]), first))
        first = pitch[-1].last_number + 1
    check_count(first, MAX_POINTS_TOTAL, "X, Y and Z together", "Fanuc")
    lines = ["%"]
    for number, field in (
        (3620, "reference_number"),
        (3621, "first_number"),
        (3622, "last_number"),
        (3623, "magnification"),
        (3624, "interval_units"),
    ):
        by_axis = {p.axis: getattr(p, field) for p in pitch}
        lines.append(_parameter(number, [by_axis[a] for a in sorted(by_axis, key=axis_number)]))
    for p in pitch:
        lines.extend(f"N{10000 + p.first_number + i:05d}P{int(v)};" for i, v in enumerate(p.values))
    lines.append("%")
    return {"PITCH.TXT": "\n".join(lines) + "\n"}
