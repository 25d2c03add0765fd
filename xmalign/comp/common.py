"""What every compensation-table writer needs: fitted tables on a controller's grid, limits.

Values inside are mm. A fitted table is an *error* (what the controller takes
out); a *correction* is minus the error: what a controller adds to the set point
so the tool lands where it was commanded.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from xmalign.comp.fit import CompensationFit
from xmalign.errors import OutOfRangeError
from xmalign.geometry import Vec
from xmalign.rigid_body import AXIS_INDEX


@dataclass(frozen=True)
class Grid:
    """Equidistant compensation points ``start + i·step``, i = 0 .. count - 1 (mm)."""

    start_mm: float
    step_mm: float
    count: int

    @property
    def positions_mm(self) -> Vec:
        return self.start_mm + self.step_mm * np.arange(self.count, dtype=np.float64)

    @property
    def end_mm(self) -> float:
        return self.start_mm + self.step_mm * (self.count - 1)


def grid_of(positions_mm: Vec) -> Grid:
    """The equidistant grid spanning a table with as many points as it has."""
    count = len(positions_mm)
    step = (positions_mm[-1] - positions_mm[0]) / (count - 1)
    return Grid(float(positions_mm[0]), float(step), count)


def fitted(fit: CompensationFit, output: str, axis: str, direction: str = "") -> tuple[Grid, Vec]:
    """The fitted error of ``output`` as a function of ``axis`` on its equidistant grid, mm."""
    positions, values = fit.table(output, axis, direction)
    grid = grid_of(positions)
    return grid, np.interp(grid.positions_mm, positions, values)


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


def has_reversal(fit: CompensationFit, axis: str) -> bool:
    """True when the forward and reverse tables of ``axis`` differ."""
    name = f"E{axis}{axis}"
    forward, reverse = fit.forward.tables.get(name), fit.reverse.tables.get(name)
    return forward is not None and reverse is not None and not np.allclose(forward[1], reverse[1])
