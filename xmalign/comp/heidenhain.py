"""HEIDENHAIN TNC: nonlinear axis error compensation, ``.COM`` tables and the ``.CMA`` assignment.

From the technical manuals (TNC 407 ... TNC 640, MANUALplus 620, "Nonlinear axis
error compensation"):

- a ``*.COM`` table holds, in column ``AXISPOS``, the compensation points of the
  axis it depends on, and in the column of each compensated axis (names from
  ``CfgAxes/axisList``) the compensation values; the values measured in the
  negative direction of traverse go into column ``BACKLASH``; at most 256
  entries per table;
- the ``*.CMA`` table assigns the ``*.COM`` tables: ``[axis column in .COM] =
  F(axis column of .CMA in which the .COM is entered)``; a ``*`` in column
  ``ACTIVE`` activates the line;
- tables are Heidenhain table files: ``BEGIN <name> MM``, a header line of the
  column names, the rows, ``[END]``.

One table per axis (``X.COM`` = everything that depends on X): its own
positioning and the straightness it causes in the other two axes, the
squareness folded into the straightness as a slope. Values are corrections
(minus the error, mm). Angular errors are not written (no tool-length term).
"""

from __future__ import annotations

import numpy as np

from xmalign.comp.common import (
    POSITIONING,
    STRAIGHTNESS,
    check_count,
    directional,
    grid_of,
    straightness_with_squareness,
    table,
    values_on,
)
from xmalign.formats.error_tables import ErrorTableSet
from xmalign.rigid_body import AXES, Chain

NAME = "heidenhain"
MAX_ENTRIES = 256
CMA_NAME = "CONFIG.CMA"
COMPENSATES = frozenset({*POSITIONING.values(), *STRAIGHTNESS, "squareness"})
_WIDTH = 12


def _signed(value: float, decimals: int) -> str:
    """``+0.00123``; a value that rounds to zero is ``+0.00000``, never ``-0.00000``."""
    return f"{round(value, decimals) + 0.0:+.{decimals}f}"


def _row(cells: list[str]) -> str:
    return "".join(cell.ljust(_WIDTH) for cell in cells).rstrip()


def _com_columns(tables: ErrorTableSet, axis: str, positions: np.ndarray) -> dict[str, np.ndarray]:
    """Column name -> corrections (mm) of the table that depends on ``axis``."""
    columns: dict[str, np.ndarray] = {}
    pair = directional(tables, POSITIONING[axis])
    own = pair[0] if pair else table(tables, POSITIONING[axis])
    for output in AXES:
        if output == axis:
            columns[output] = -values_on(positions, own)
        else:
            name = f"E{output}{axis}"
            columns[output] = -values_on(positions, straightness_with_squareness(tables, name))
    if pair:
        columns["BACKLASH"] = -values_on(positions, pair[1])
    return columns


def render_com(tables: ErrorTableSet, axis: str) -> str:
    """The ``<axis>.COM`` table."""
    source = table(tables, POSITIONING[axis])
    grid = grid_of(source.positions_mm)
    check_count(grid.count, MAX_ENTRIES, f"{axis}.COM", "Heidenhain")
    positions = grid.positions_mm
    columns = _com_columns(tables, axis, positions)
    lines = [f"BEGIN {axis}.COM MM", _row(["NR", "AXISPOS", *columns])]
    for n, position in enumerate(positions):
        cells = [str(n), _signed(position, 4), *(_signed(c[n], 5) for c in columns.values())]
        lines.append(_row(cells))
    lines.append("[END]")
    return "\n".join(lines) + "\n"


def render_cma() -> str:
    """The ``.CMA`` assignment: X.COM in column X, ... , active."""
    lines = [
        f"BEGIN {CMA_NAME}",
        _row(["NR", *AXES, "ACTIVE"]),
        _row(["0", *(f"{axis}.COM" for axis in AXES), "*"]),
        "[END]",
    ]
    return "\n".join(lines) + "\n"


def render(tables: ErrorTableSet, chain: Chain) -> dict[str, str]:
    """File name -> text of the three ``.COM`` tables and the ``.CMA`` table."""
    files = {f"{axis}.COM": render_com(tables, axis) for axis in AXES}
    files[CMA_NAME] = render_cma()
    return files
