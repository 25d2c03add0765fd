"""Siemens SINUMERIK 840D sl: LEC (``$AA_ENC_COMP``) and CEC (``$AN_CEC``) init programs.

From the function manual K3 "Compensations", interpolatory compensation (its
``%_N_AX_EEC_INI`` example for machine axis X1 is kept in tests):

- Leadscrew / measuring-system error compensation (LEC, EEC), program
  ``%_N_AX_EEC_INI``: ``$AA_ENC_COMP[e,N,<axis>]`` the value at interpolation
  point N, ``$AA_ENC_COMP_STEP``, ``_MIN``, ``_MAX``, ``_IS_MODULO``. The value
  corrects the actual value: *a positive compensation value moves the axis
  negative*, so the value written is the positioning error itself. It acts
  once the axis is referenced (MD32700 ``$MA_ENC_COMP_ENABLE[0] = 1``); up to
  MD38000 ``$MA_MM_ENC_COMP_MAX_POINTS`` points.
- Sag / angularity compensation (CEC), program ``%_N_NC_CEC_INI``:
  ``$AN_CEC[t,N]`` added to the set point of ``$AN_CEC_OUTPUT_AXIS[t]`` as a
  function of ``$AN_CEC_INPUT_AXIS[t]``, with ``_STEP``, ``_MIN``, ``_MAX``,
  ``_DIRECTION`` (0 both, 1 / -1 one direction), ``_MULT_BY_TABLE``,
  ``_IS_MODULO``. The value is a set-point correction: minus the error. A
  table acts when MD32710 ``$MA_CEC_ENABLE`` is set on its output axis, setting
  data SD41300 ``$SN_CEC_TABLE_ENABLE[t]`` is TRUE and, weighted by SD41310
  ``$SN_CEC_TABLE_WEIGHT[t]``, once the axes are referenced. Up to MD18342
  ``$MN_MM_CEC_MAX_POINTS[t]`` points.

xmalign writes, per axis, the table of its reference-return direction as LEC
(zero at the reference point, so nothing jumps when the axis is referenced), the
fitted cross tables (straightness, squareness and the mean Abbe effect at the tool
point) as CEC, and with bidirectional data the reversal as one CEC table on the
axis itself that acts only in the other direction (``$AN_CEC_DIRECTION``, K3
4.4.4 "direction-dependent leadscrew error compensation"). The control's own
backlash compensation (MD32450 ``$MA_BACKLASH``) is then set to 0 on those axes.
``STEP``, ``MIN`` and ``MAX`` are written with six decimals such that ``MIN +
(points - 1)·STEP`` is ``MAX`` exactly. A SINUMERIK 828D has a fixed eight CEC
tables of 200 points (K3 03/2013 p. 264): the reversal of the axes that do not
fit goes into MD32450 as a constant. Machine axis names come from the machine
file's ``cnc.axis_names`` (default ``AX1`` .. ``AX3``).

Not settled from the manual: the sign of ``$AN_CEC`` (xmalign writes the
correction, minus the error, as a set-point correction; the LEC convention is
the opposite). ``xmalign comp`` prints the check that settles it on the machine.
"""

from __future__ import annotations

import numpy as np

from xmalign.comp.common import (
    Comment,
    Grid,
    Loading,
    OwnTables,
    backlash_warnings,
    check_count,
    fitted,
    own_tables,
    reversal_statement,
    with_history,
)
from xmalign.comp.fit import CROSS, CompensationFit, CompModel
from xmalign.geometry import Vec
from xmalign.machine import Machine
from xmalign.rigid_body import AXES

NAME = "sinumerik"
MODEL = CompModel(pairs=CROSS, directional=True)
#: Upper input limit of MD38000 $MA_MM_ENC_COMP_MAX_POINTS.
MAX_EEC_POINTS = 5000
#: Upper input limit of MD18342 $MN_MM_CEC_MAX_POINTS.
MAX_CEC_POINTS = 2000
#: SINUMERIK 828D: eight CEC tables of 200 points, fixed (K3 03/2013 p. 264).
MAX_828D_TABLES = 8
MAX_828D_POINTS = 200
BACKLASH_PARAMETER = "MD32450 $MA_BACKLASH"
FORMAT = "xmalign.comp.sinumerik/1"
#: The history as ``;`` comments after the program name (K3's own example has them).
COMMENTS = {"*.INI": Comment("; ", skip=1)}
_MICRO = 1_000_000


def _mm(value: float) -> str:
    return f"{round(value, 6) + 0.0:.6f}"


def axis_name(machine: Machine, axis: str) -> str:
    """The machine axis identifier of ``axis`` (``AX1`` .. unless the machine file names it)."""
    return machine.cnc.axis_name(axis, f"AX{AXES.index(axis) + 1}")


def exact_grid(grid: Grid) -> Grid:
    """``grid`` with a six-decimal start and step (the step rounded up: it still spans it).

    The control checks ``(MAX - MIN) / STEP`` against the number of points; with six
    decimals for all three and ``MAX = MIN + (points - 1)·STEP`` that holds exactly.
    """
    start = round(grid.start_mm * _MICRO)
    step = int(np.ceil(round(grid.step_mm * _MICRO, 3)))
    return Grid(start / _MICRO, step / _MICRO, grid.count)


def _on(grid: Grid, source: Grid, values_mm: Vec) -> tuple[Grid, Vec]:
    exact = exact_grid(grid)
    return exact, np.interp(exact.positions_mm, source.positions_mm, values_mm)


def _eec_block(name: str, grid: Grid, values_mm: Vec) -> list[str]:
    lines = [f"$AA_ENC_COMP[0,{n},{name}]={_mm(v)}" for n, v in enumerate(values_mm)]
    return [
        *lines,
        f"$AA_ENC_COMP_STEP[0,{name}]={_mm(grid.step_mm)}",
        f"$AA_ENC_COMP_MIN[0,{name}]={_mm(grid.start_mm)}",
        f"$AA_ENC_COMP_MAX[0,{name}]={_mm(grid.end_mm)}",
        f"$AA_ENC_COMP_IS_MODULO[0,{name}]=0",
    ]


def _own(fit: CompensationFit, machine: Machine) -> list[OwnTables]:
    return [own_tables(fit, axis, machine, "Sinumerik") for axis in AXES]


def render_eec(fit: CompensationFit, machine: Machine) -> str:
    """``%_N_AX_EEC_INI``: each axis's reference-direction error as LEC (value = error, mm)."""
    out = [
        "%_N_AX_EEC_INI",
        f"; xmalign: SINUMERIK {machine.series} leadscrew error compensation; value ="
        " positioning error in mm",
        "; (a positive value moves the axis negative), zero at the reference point approached",
        "; in the axis's reference-return direction (the reversal is in NC_CEC.INI).",
        *load_order(machine),
        "CHANDATA(1)",
    ]
    for own in _own(fit, machine):
        grid, values = _on(own.grid, own.grid, own.at_return)
        name = axis_name(machine, own.axis)
        check_count(grid.count, MAX_EEC_POINTS, f"{own.axis} (MD38000)", "Sinumerik")
        out.append(
            f"; {own.axis} = {name}, reference return {own.return_direction}:"
            f" MD38000 $MA_MM_ENC_COMP_MAX_POINTS[0] >= {grid.count}"
        )
        out.extend(_eec_block(name, grid, values))
    out.append("M17")
    return "\n".join(out) + "\n"


CecTable = tuple[str, str, str, Grid, Vec, int]


def _reversal_tables(
    owns: list[OwnTables], room: int | None
) -> tuple[list[CecTable], dict[str, float]]:
    """The reversal CEC tables that fit in ``room`` (None: all), and the rest's MD32450, mm.

    Where tables are short, the axes whose reversal varies least along the travel
    give way: their mean play goes into MD32450 (:func:`backlash_mm`).
    """
    carried = sorted(
        (own for own in owns if own.bidirectional), key=lambda own: -float(np.std(own.reversal))
    )
    kept = carried if room is None else carried[: max(room, 0)]
    tables = []
    for own in kept:
        grid, correction = _on(own.grid, own.grid, -own.reversal)
        direction = 1 if own.opposite_direction == "+" else -1
        what = f"E{own.axis}{own.axis} reversal ({own.opposite_direction} only)"
        tables.append((what, own.axis, own.axis, grid, correction, direction))
    constant = {own.axis: backlash_mm(own) for own in carried if own not in kept}
    return tables, constant


def backlash_mm(own: OwnTables) -> float:
    """MD32450 ``$MA_BACKLASH`` for an axis's reversal, mm: the machine's play.

    The mean of the error moving ``-`` minus the error moving ``+``: positive when the
    encoder leads the machine part (the ``-`` approach stops above the ``+`` approach),
    MD32450's "normal case" (SINUMERIK 808D Parameter Manual, 08/2013, MD32450; MANUALplus
    620 Technical Manual, p. 707, defines positive backlash alike). A property of the
    machine: the reference-return direction does not change it (the control applies it
    at every reversal, whichever way the axis was referenced).
    """
    return float(np.mean(own.reverse - own.forward))


def _cross_tables(fit: CompensationFit) -> list[CecTable]:
    entries = []
    for output, axis in MODEL.pairs:
        if output == axis:
            continue
        grid, error = fitted(fit, output, axis)
        exact, correction = _on(grid, grid, -error)
        entries.append((f"E{output}{axis} fitted", axis, output, exact, correction, 0))
    return entries


def _cec_tables(fit: CompensationFit, machine: Machine) -> tuple[list[CecTable], dict[str, float]]:
    """Every CEC table (description, input, output, grid, correction mm, direction), and the
    reversals left to MD32450 (axis -> mean reversal, mm)."""
    cross = _cross_tables(fit)
    room = MAX_828D_TABLES - len(cross) if machine.series == "828D" else None
    reversal, constant = _reversal_tables(_own(fit, machine), room)
    return cross + reversal, constant


def _cec_block(
    index: int, names: tuple[str, str], grid: Grid, values_mm: Vec, direction: int
) -> list[str]:
    input_name, output_name = names
    lines = [f"$AN_CEC[{index},{n}]={_mm(v)}" for n, v in enumerate(values_mm)]
    return [
        *lines,
        f"$AN_CEC_INPUT_AXIS[{index}]=({input_name})",
        f"$AN_CEC_OUTPUT_AXIS[{index}]=({output_name})",
        f"$AN_CEC_STEP[{index}]={_mm(grid.step_mm)}",
        f"$AN_CEC_MIN[{index}]={_mm(grid.start_mm)}",
        f"$AN_CEC_MAX[{index}]={_mm(grid.end_mm)}",
        f"$AN_CEC_DIRECTION[{index}]={direction}",
        f"$AN_CEC_MULT_BY_TABLE[{index}]=0",
        f"$AN_CEC_IS_MODULO[{index}]=0",
    ]


def _point_limit(machine: Machine) -> tuple[int, str]:
    if machine.series == "828D":
        return MAX_828D_POINTS, "828D: 200 points per table"
    return MAX_CEC_POINTS, "MD18342"


def render_cec(fit: CompensationFit, machine: Machine) -> str:
    """``%_N_NC_CEC_INI``: cross tables and reversal as CEC tables (corrections), enabled."""
    tables, constant = _cec_tables(fit, machine)
    limit, limit_name = _point_limit(machine)
    out = [
        "%_N_NC_CEC_INI",
        f"; xmalign: SINUMERIK {machine.series} sag/angularity compensation;",
        "; value = correction (minus the error) in mm, cross tables zero at the reference point.",
        *load_order(machine),
        "; Every table is loaded switched off (SD41300 $SN_CEC_TABLE_ENABLE[t]=FALSE): switch",
        "; them on one at a time for the sign check below, then all (SD41310 weight 1.0).",
        *loading(fit, machine).lines("; "),
        "CHANDATA(1)",
    ]
    for axis, mean in constant.items():
        out.append(
            f"; {axis}: no table left for its reversal: MD32450 $MA_BACKLASH[0] ="
            f" {_mm(mean)} on {axis_name(machine, axis)}"
        )
    for index, (what, axis, output, grid, values, direction) in enumerate(tables):
        check_count(grid.count, limit, f"{what} ({limit_name})", "Sinumerik")
        names = (axis_name(machine, axis), axis_name(machine, output))
        size = "" if machine.series == "828D" else f"; MD18342[{index}] >= {grid.count}"
        out.append(f"; table {index}: {what}, {output} = f({axis}), {grid.count} points{size}")
        out.extend(_cec_block(index, names, grid, values, direction))
    for index in range(len(tables)):
        out += [f"$SN_CEC_TABLE_ENABLE[{index}]=FALSE", f"$SN_CEC_TABLE_WEIGHT[{index}]=1.0"]
    out.append("M17")
    return "\n".join(out) + "\n"


def load_order(machine: Machine) -> list[str]:
    """The order of loading, as comment lines (K3 03/2013 p. 237; docs/controllers.md).

    The tables are written only while both compensations are off (MD32700 = 0 and
    MD32710 = 0); a change of MD38000 or MD18342 reformats the static user memory at
    the next start, so the NC is archived first; an 828D has no MD18342 (eight fixed
    tables of 200 points, K3 p. 264).
    """
    sizes = "MD38000" if machine.series == "828D" else "MD38000 or MD18342"
    lines = [
        "; Load order (SINUMERIK K3 Compensations, 03/2013, p. 237):",
        f"; 1. archive the NC (a series start-up archive) before changing {sizes}:",
        ";    a change reformats the static user memory at the next start, the archive",
        ";    restores what was there;",
        "; 2. set MD38000 $MA_MM_ENC_COMP_MAX_POINTS[0]"
        + ("" if machine.series == "828D" else " and MD18342 $MN_MM_CEC_MAX_POINTS[t]"),
        ";    to at least the counts below, NewConfig / power on;",
        "; 3. MD32700 $MA_ENC_COMP_ENABLE[0]=0 AND MD32710 $MA_CEC_ENABLE=0 on every axis:",
        ";    the tables are written only while both compensations are off;",
        "; 4. run AX_EEC.INI and NC_CEC.INI; then MD32700=1 and MD32710=1 on the axes",
        ";    named below, reset (NewConfig), reference every axis.",
    ]
    if machine.series == "828D":
        lines.append(
            "; 828D: no MD18342 (eight CEC tables of 200 points, fixed: K3 03/2013 p. 264)."
        )
    return lines


def loading(fit: CompensationFit, machine: Machine) -> Loading:
    """Reversal, the check on the machine and what the manual left open."""
    owns = _own(fit, machine)
    _, constant = _cec_tables(fit, machine)
    carriers = [own.carrier for own in owns if own.axis not in constant]
    reversal = reversal_statement(carriers, BACKLASH_PARAMETER)
    if constant:
        reversal += (
            f"; {machine.series} has no CEC table left for the reversal of"
            f" {', '.join(constant)}: MD32450 carries it as a constant (values in NC_CEC.INI)"
        )
    return Loading(
        reversal=reversal,
        check=(
            "the sign of one cross table, on the machine itself: with every table off, set a"
            " dial gauge (or read the output axis's encoder actual value, not a compensation"
            " display, which shows the table's value whichever way it is applied) on the output"
            " axis, move the input axis to where the table's correction is largest, note the"
            " reading, then switch on that one table (SD41300 $SN_CEC_TABLE_ENABLE[t]=TRUE) and"
            " let the axes settle: the output axis must move by the table's value there (a"
            " correction: minus the error); if it moves the other way, switch the table off"
            " and do not use NC_CEC.INI. Then switch the tables on one at a time"
        ),
        unconfirmed=(
            "the sign of $AN_CEC: written as a set-point correction (minus the error), the"
            " opposite of the LEC values in AX_EEC.INI (K3: a positive LEC value moves the"
            " axis negative)",
        ),
        warnings=backlash_warnings(carriers, BACKLASH_PARAMETER) + fit.warnings,
    )


def render(fit: CompensationFit, machine: Machine) -> dict[str, str]:
    """File name -> text of the two init programs."""
    files = {"AX_EEC.INI": render_eec(fit, machine), "NC_CEC.INI": render_cec(fit, machine)}
    return with_history(files, FORMAT, fit.sources, COMMENTS)
