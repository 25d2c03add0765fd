"""What every compensation-table writer needs: tables on a controller's grid, limits, signs.

Values inside are mm and rad (as :class:`~xmalign.formats.error_tables.ErrorTableSet`).
A *correction* is minus the error: what a controller adds to the set point so
the tool lands where it was commanded.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from xmalign.errors import InputError, OutOfRangeError
from xmalign.formats.error_tables import ErrorTableSet, Table
from xmalign.geometry import Vec
from xmalign.rigid_body import AXES, AXIS_INDEX, TRANSLATION_NAMES

#: Straightness tables that carry a squareness in the cross-axis tables, with the
#: squareness and its factor: ``EXY += -EC0Y·(y - y0)``, ``EYZ += -EA0Z·(z - z0)``,
#: ``EXZ += +EB0Z·(z - z0)`` (CONVENTIONS.md: a move y deviates by -y·EC0Y in X...).
SQUARENESS_IN_STRAIGHTNESS = {"EXY": ("EC0Y", -1.0), "EYZ": ("EA0Z", -1.0), "EXZ": ("EB0Z", 1.0)}
#: The three positioning errors, by axis.
POSITIONING = {axis: f"E{axis}{axis}" for axis in AXES}
#: The six straightness errors: name -> (input axis, output axis).
STRAIGHTNESS = {
    name: (axis, name[1]) for axis in AXES for name in TRANSLATION_NAMES[axis] if name[1] != axis
}


@dataclass(frozen=True)
class Grid:
    """Equidistant compensation points ``start + i·step``, i = 0 .. count - 1 (mm)."""

    start_mm: float
    step_mm: float
    count: int

    @property
    def positions_mm(self) -> Vec:
        return self.start_mm + self.step_mm * np.arange(self.count)

    @property
    def end_mm(self) -> float:
        return self.start_mm + self.step_mm * (self.count - 1)


def table(tables: ErrorTableSet, name: str) -> Table:
    """The table ``name``; InputError naming it when the error file lacks it."""
    if name not in tables.tables:
        raise InputError(f"{tables.source}: no table {name} (run xmalign post on all six lines)")
    return tables.tables[name]


def grid_of(positions_mm: Vec) -> Grid:
    """The equidistant grid spanning a table with as many points as it has."""
    count = len(positions_mm)
    step = (positions_mm[-1] - positions_mm[0]) / (count - 1)
    return Grid(float(positions_mm[0]), float(step), count)


def values_on(grid_positions_mm: Vec, source: Table) -> Vec:
    """Table values linearly interpolated at grid points (end values held outside)."""
    return np.interp(grid_positions_mm, source.positions_mm, source.values)


def straightness_with_squareness(tables: ErrorTableSet, name: str) -> Table:
    """A straightness table with its squareness folded in (zero at the first point).

    Controllers have no squareness entry of their own: a straightness
    compensation (cross-axis table) carries it as a slope.
    """
    base = table(tables, name)
    if name not in SQUARENESS_IN_STRAIGHTNESS:
        return base
    squareness, factor = SQUARENESS_IN_STRAIGHTNESS[name]
    value, _ = tables.squareness.get(squareness, (0.0, 0.0))
    slope = factor * value * (base.positions_mm - base.positions_mm[0])
    return Table(base.positions_mm, base.values + slope, base.u95)


def check_count(count: int, limit: int, what: str, controller: str) -> None:
    """Refuse a table longer than a controller allows, naming the limit."""
    if count > limit:
        raise OutOfRangeError(
            f"{controller}: {what} needs {count} compensation points, more than the limit of"
            f" {limit}; measure with a wider target spacing"
        )


def axis_number(axis: str) -> int:
    """1-based axis number (X = 1, Y = 2, Z = 3)."""
    return AXIS_INDEX[axis] + 1


def directional(tables: ErrorTableSet, name: str) -> tuple[Table, Table] | None:
    """Forward and reverse tables of ``name`` when the error file has them."""
    if name + "+" in tables.tables and name + "-" in tables.tables:
        return tables.tables[name + "+"], tables.tables[name + "-"]
    return None
