"""HEIDENHAIN: nonlinear axis error compensation, ``.COM`` tables and the ``.CMA`` assignment.

Two layouts, by the control's series (the machine file's ``cnc.series``):

- **MANUALplus 620, TNC 620, TNC 640** (MANUALplus 620 Technical Manual,
  "Nonlinear axis error compensation", "Entering compensation values", p. 716):
  a ``*.COM`` table holds, in column ``AXISPOS``, the compensation points *with
  respect to the machine datum*, in the column of each compensated axis (names
  from ``CfgAxes/axisList``) the compensation values, and the values measured in
  the negative direction of traverse in column ``BACKLASH``; at most 256 entries.
  Every column is zero at the reference point but the axis's own column of the
  direction against its reference return, which holds the reversal there.
- **TNC 4xx** (TNC 407/415/425 Technical Manual, 01.98, pp. 4-28 to 4-31): the
  compensation points lie at a power-of-two spacing (2^n um) from a datum, the
  error curve starts at 0 at the datum, and the compensation acts only once MP730
  selects nonlinear compensation for the axis and a valid ``.CMA`` file exists.
  xmalign puts the datum at the start of the travel and, as that manual's example
  does, the largest spacing 2^n x 0.1 um not above the measured one (coarser if 256
  points would not span the travel); every column is zero at the datum but the
  axis's own column of the direction against its reference return (the reversal).
  Through the data interface the ``.CMA`` file travels as ``.S``, a ``.COM`` as ``.V``
  (p. 4-31). The ``BACKLASH`` column is not in that manual: said in the notes.

The ``*.CMA`` table assigns the ``*.COM`` tables: ``[axis column in .COM] =
F(axis column of .CMA in which the .COM is entered)``; a ``*`` in column
``ACTIVE`` activates the line (MANUALplus 620 manual, p. 718). The iTNC 530
uses another layout (numbered columns) that could not be confirmed from a
manual: it is refused. Tables are Heidenhain table files: ``BEGIN <name> MM``,
a header line of the column names, the rows, ``[END]``; ``HEIDENHAIN.TXT``
says which control the files are for and how to activate them.

One table per axis (``X.COM`` = everything that depends on X): the fitted
one-variable cross tables of that input axis (its own positioning, and the
straightness, squareness and mean Abbe effect it causes in the other two
axes), and with bidirectional data its own negative-direction values in
``BACKLASH``.

Values are the *errors* (mm, actual minus nominal), not corrections: the
technical manuals enter "only the compensation points of the error curve" in a
correction table (TNC 306/TNC 406 Technical Manual, 3/97, "Machine axes",
nonlinear axis-error compensation, p. 4-21: the example table holds the plotted
error curve's values) and give the linear axis error MP720 "with the correct
sign: positive if the table travel is too long" (TNC 407/415/425 Technical
Manual, 01.98, p. 4-26); the control takes them out.
"""

from __future__ import annotations

import math

import numpy as np

from xmalign.comp.common import (
    Comment,
    Grid,
    Loading,
    backlash_warnings,
    check_count,
    fitted,
    own_tables,
    reversal_statement,
    with_history,
)
from xmalign.comp.fit import CROSS, CompensationFit, CompModel
from xmalign.errors import MachineKeyError
from xmalign.geometry import Vec
from xmalign.machine import Machine
from xmalign.rigid_body import AXES

NAME = "heidenhain"
MODEL = CompModel(pairs=CROSS, directional=True)
MAX_ENTRIES = 256
CMA_NAME = "CONFIG.CMA"
README_NAME = "HEIDENHAIN.TXT"
#: Series whose tables sit at a power-of-two spacing from a datum.
POWER_OF_TWO_SERIES = ("TNC 4xx",)
#: Series whose .COM layout xmalign cannot write.
REFUSED_SERIES = ("iTNC 530",)
BACKLASH_PARAMETER = "the backlash machine parameter (MP710 on a TNC 4xx)"
_WIDTH = 12
FORMAT = "xmalign.comp.heidenhain/1"
#: Only the notes take comments; no comment syntax of .COM / .CMA tables was found in a
#: manual, so they get a NAME.history beside them.
COMMENTS = {README_NAME: Comment("# ")}


def _signed(value: float, decimals: int) -> str:
    """``+0.00123``; a value that rounds to zero is ``+0.00000``, never ``-0.00000``."""
    return f"{round(value, decimals) + 0.0:+.{decimals}f}"


def _row(cells: list[str]) -> str:
    return "".join(cell.ljust(_WIDTH) for cell in cells).rstrip()


def power_of_two_grid(start_mm: float, end_mm: float, wanted_mm: float) -> tuple[Grid, int]:
    """Points from ``start`` at 2^n x 0.1 um: the largest such spacing not above ``wanted``.

    The TNC 407/415/425 Technical Manual's rule and unit (01.98, p. 4-28: "required
    distance of compensation points = 7 mm, possible power of two = 2^16 = 6.5536 mm");
    coarser where 256 points would not span the travel. Returns the grid and ``n``.
    """
    length_mm = end_mm - start_mm
    exponent = max(0, math.floor(math.log2(wanted_mm * 1e4)))
    while math.ceil(length_mm / (2.0**exponent * 1e-4) - 1e-9) + 1 > MAX_ENTRIES:
        exponent += 1
    step_mm = 2.0**exponent * 1e-4
    return Grid(start_mm, step_mm, math.ceil(length_mm / step_mm - 1e-9) + 1), exponent


def _com_columns(fit: CompensationFit, machine: Machine, axis: str) -> tuple[Vec, dict[str, Vec]]:
    """Positions and column name -> errors (mm) of the table that depends on ``axis``."""
    own = own_tables(fit, axis, machine, "Heidenhain")
    grid = own.grid
    columns = {output: fitted(fit, output, axis)[1] for output in AXES if output != axis}
    columns[axis] = own.forward if own.bidirectional else own.at_return
    if own.bidirectional:
        columns["BACKLASH"] = own.reverse
    ordered = {name: columns[name] for name in (*AXES, "BACKLASH") if name in columns}
    if machine.series not in POWER_OF_TWO_SERIES:
        return grid.positions_mm, ordered
    low, high = next(limits for a, limits in machine.travel_mm.items() if a == axis)
    datum_grid, _ = power_of_two_grid(low, high, grid.step_mm)
    at = datum_grid.positions_mm
    moved = {name: np.interp(at, grid.positions_mm, values) for name, values in ordered.items()}
    own_name = "BACKLASH" if own.bidirectional and own.return_direction == "-" else axis
    datum = {name: values[0] for name, values in moved.items()}
    datum[axis] = datum["BACKLASH"] = datum[own_name]  # the reversal at the datum stays
    return at, {name: values - datum[name] for name, values in moved.items()}


def render_positions(fit: CompensationFit, machine: Machine, axis: str) -> Vec:
    """The compensation points of ``<axis>.COM``, mm."""
    return _com_columns(fit, machine, axis)[0]


def render_com(fit: CompensationFit, machine: Machine, axis: str) -> str:
    """The ``<axis>.COM`` table."""
    positions, columns = _com_columns(fit, machine, axis)
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


def loading(fit: CompensationFit, machine: Machine) -> Loading:
    """Reversal, the check on the machine and what the manuals left open."""
    carriers = [own_tables(fit, axis, machine, "Heidenhain").carrier for axis in AXES]
    unconfirmed = [
        "the table file framing (BEGIN <name> MM, header line, [END]): not checked against a"
        " published file",
    ]
    if machine.series in POWER_OF_TWO_SERIES:
        unconfirmed += [
            "the TNC 4xx .COM layout (AXISPOS column at the 2^n spacing)",
            "the BACKLASH column on a TNC 4xx: the MANUALplus 620 Technical Manual (p. 716)"
            " describes it, the TNC 407/415/425 Technical Manual (01.98) does not; if the"
            " control does not accept the column, do not load these tables",
        ]
    return Loading(
        reversal=reversal_statement(carriers, BACKLASH_PARAMETER)
        + " (Heidenhain adds its backlash parameter at every reversal, tables or not)",
        check=(
            "with the CONFIG.CMA line active, move each axis to a compensation point away from"
            " the reference, in both directions, and compare the position with the verification"
            " run (xmalign post --verify-data): it must move by minus the table's value"
        ),
        unconfirmed=tuple(unconfirmed),
        warnings=backlash_warnings(carriers, BACKLASH_PARAMETER) + fit.warnings,
    )


def _zero_point(fit: CompensationFit, machine: Machine, axis: str) -> str:
    """What ``<axis>.COM`` holds where it starts from (reference point or TNC 4xx datum),
    read from the table itself: the columns that are zero there, and the one that holds
    the reversal (the own axis's column of the direction against the reference return)."""
    own = own_tables(fit, axis, machine, "Heidenhain")
    positions, columns = _com_columns(fit, machine, axis)
    if machine.series in POWER_OF_TWO_SERIES:
        where, at_mm = "at the datum", float(positions[0])
    else:
        at_mm = float(machine.cnc.reference[AXES.index(axis)])
        where = "at the reference point"
    values = {name: float(np.interp(at_mm, positions, column)) for name, column in columns.items()}
    zero = [name for name, value in values.items() if round(value, 5) == 0.0]
    held = [f"{name} {_signed(value, 5)} mm" for name, value in values.items() if name not in zero]
    text = f"{axis}.COM {where} {axis} = {at_mm:g} mm: {', '.join(zero)} zero"
    if held:
        reversal = "BACKLASH" if own.return_direction == "+" else axis
        text += (
            f"; {', '.join(held)} (the reversal there: {axis} returns to its reference in"
            f" '{own.return_direction}', the {reversal} column is the other direction's)"
        )
    return text


def render_readme(fit: CompensationFit, machine: Machine) -> str:
    """Which control the tables are for, what each holds at its start and how they are
    activated (every statement read from the tables themselves)."""
    lines = [f"xmalign: HEIDENHAIN {machine.series} nonlinear axis error compensation"]
    if machine.series in POWER_OF_TWO_SERIES:
        for axis in AXES:
            positions = render_positions(fit, machine, axis)
            exponent = round(math.log2((positions[1] - positions[0]) * 1e4))
            lines.append(
                f"{axis}.COM: datum {positions[0]:g} mm (the start of the travel), spacing"
                f" 2^{exponent} x 0.1 um = {positions[1] - positions[0]:g} mm,"
                f" {len(positions)} points"
            )
        lines.append(
            "Activation: MP730 bit per axis = 1 (nonlinear axis error compensation) and"
            " CONFIG.CMA with its line selected (TNC 407/415/425 Technical Manual, p. 4-28)."
        )
        lines.append(
            "Transfer through the data interface (PLC Programming mode): CONFIG.CMA goes as"
            " CONFIG.S, each .COM as .V (X.COM as X.V; TNC 407/415/425 Technical Manual,"
            " 01.98, p. 4-31)."
        )
    else:
        lines.append(
            "AXISPOS is the position from the machine datum. Activation: CONFIG.CMA with '*'"
            " in ACTIVE (MANUALplus 620 Technical Manual, p. 718)."
        )
    lines += [_zero_point(fit, machine, axis) for axis in AXES]
    lines += loading(fit, machine).lines()
    return "\n".join(lines) + "\n"


def render(fit: CompensationFit, machine: Machine) -> dict[str, str]:
    """File name -> text of the three ``.COM`` tables, the ``.CMA`` table and the notes."""
    if machine.series in REFUSED_SERIES:
        raise MachineKeyError(
            "cnc.series",
            f"Heidenhain {machine.series}: its .COM layout could not be confirmed from a"
            " manual; xmalign writes MANUALplus 620 / TNC 620 / TNC 640 and TNC 4xx tables",
        )
    files = {f"{axis}.COM": render_com(fit, machine, axis) for axis in AXES}
    files[CMA_NAME] = render_cma()
    files[README_NAME] = render_readme(fit, machine)
    return with_history(files, FORMAT, fit.sources, COMMENTS)
