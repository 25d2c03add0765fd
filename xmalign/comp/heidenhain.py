"""HEIDENHAIN TNC: nonlinear axis error compensation, ``.COM`` tables and the ``.CMA`` assignment.

From the technical manuals (TNC 407 ... TNC 640, MANUALplus 620, "Nonlinear axis
error compensation"):

- a ``*.COM`` table holds, in column ``AXISPOS``, the compensation points of the
  axis it depends on, *with respect to the machine datum*, and in the column of
  each compensated axis (names from ``CfgAxes/axisList``) the compensation
  values; the values measured in the negative direction of traverse go into
  column ``BACKLASH``; at most 256 entries per table;
- the ``*.CMA`` table assigns the ``*.COM`` tables: ``[axis column in .COM] =
  F(axis column of .CMA in which the .COM is entered)``; a ``*`` in column
  ``ACTIVE`` activates the line;
- tables are Heidenhain table files: ``BEGIN <name> MM``, a header line of the
  column names, the rows, ``[END]``.

One table per axis (``X.COM`` = everything that depends on X): the fitted
one-variable cross tables of that input axis (its own positioning, and the
straightness, squareness and mean Abbe effect it causes in the other two
axes), zero at the reference point, and with bidirectional data its own
negative-direction values in ``BACKLASH``.

Values are the *errors* (mm, actual minus nominal), not corrections: the
technical manuals enter "only the compensation points of the error curve" in a
correction table (TNC 306/TNC 406 Technical Manual, 3/97, "Machine axes",
nonlinear axis-error compensation, p. 4-21: the example table holds the plotted
error curve's values) and give the linear axis error MP720 "with the correct
sign: positive if the table travel is too long" (TNC 407/415/425 Technical
Manual, 01.98, p. 4-26); the control takes them out.
"""

from __future__ import annotations

import numpy as np

from xmalign.comp.common import check_count, fitted, has_reversal
from xmalign.comp.fit import CROSS, CompensationFit, CompModel
from xmalign.machine import Machine
from xmalign.rigid_body import AXES

NAME = "heidenhain"
MODEL = CompModel(pairs=CROSS, directional=True)
MAX_ENTRIES = 256
CMA_NAME = "CONFIG.CMA"
_WIDTH = 12


def _signed(value: float, decimals: int) -> str:
    """``+0.00123``; a value that rounds to zero is ``+0.00000``, never ``-0.00000``."""
    return f"{round(value, decimals) + 0.0:+.{decimals}f}"


def _row(cells: list[str]) -> str:
    return "".join(cell.ljust(_WIDTH) for cell in cells).rstrip()


def _com_columns(fit: CompensationFit, axis: str) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Positions and column name -> errors (mm) of the table that depends on ``axis``."""
    grid, _ = fitted(fit, axis, axis)
    columns = {output: fitted(fit, output, axis)[1] for output in AXES}
    if has_reversal(fit, axis):
        columns[axis] = fitted(fit, axis, axis, "+")[1]
        columns["BACKLASH"] = fitted(fit, axis, axis, "-")[1]
    return grid.positions_mm, columns


def render_com(fit: CompensationFit, axis: str) -> str:
    """The ``<axis>.COM`` table."""
    positions, columns = _com_columns(fit, axis)
    check_count(len(positions), MAX_ENTRIES, f"{axis}.COM", "Heidenhain")
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


def render(fit: CompensationFit, machine: Machine) -> dict[str, str]:
    """File name -> text of the three ``.COM`` tables and the ``.CMA`` table."""
    files = {f"{axis}.COM": render_com(fit, axis) for axis in AXES}
    files[CMA_NAME] = render_cma()
    return files
