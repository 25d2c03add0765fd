"""Siemens SINUMERIK 840D sl: EEC (``$AA_ENC_COMP``) and CEC (``$AN_CEC``) init programs.

From the function manual K3 "Compensations" (interpolatory compensation):

- Leadscrew / measuring-system error compensation (LEC, EEC), program
  ``%_N_AX_EEC_INI``: ``$AA_ENC_COMP[e,N,AXi]`` the value at interpolation point
  N, ``$AA_ENC_COMP_STEP``, ``_MIN``, ``_MAX``, ``_IS_MODULO``. The value
  corrects the actual value: *a positive compensation value moves the axis
  negative*, so the value written is the measured positioning error itself.
  Up to MD38000 ``$MA_MM_ENC_COMP_MAX_POINTS`` points per axis.
- Sag / angularity compensation (CEC), program ``%_N_NC_CEC_INI``:
  ``$AN_CEC[t,N]`` added to the set point of ``$AN_CEC_OUTPUT_AXIS[t]`` as a
  function of ``$AN_CEC_INPUT_AXIS[t]``, with ``_STEP``, ``_MIN``, ``_MAX``,
  ``_DIRECTION`` (0 both, 1 / -1 one direction), ``_MULT_BY_TABLE``,
  ``_IS_MODULO``. The value is a set-point correction: minus the error. Up to
  MD18342 ``$MN_MM_CEC_MAX_POINTS`` points per table.

xmalign writes the positioning errors as EEC tables, the six straightness
errors (with the squareness folded in as a slope) as CEC tables and, with
bidirectional data, the reversal as one CEC table per direction on the axis
itself. Machine axes 1, 2, 3 are taken to be X, Y, Z (``AX1`` .. ``AX3``).
Angular errors cannot be entered here (their Abbe effect depends on the tool).
"""

from __future__ import annotations

from xmalign.comp.common import (
    POSITIONING,
    STRAIGHTNESS,
    Grid,
    axis_number,
    check_count,
    directional,
    grid_of,
    straightness_with_squareness,
    table,
    values_on,
)
from xmalign.formats.error_tables import ErrorTableSet, Table
from xmalign.geometry import Vec
from xmalign.rigid_body import AXES, Chain

NAME = "sinumerik"
#: Upper input limit of MD38000 $MA_MM_ENC_COMP_MAX_POINTS.
MAX_EEC_POINTS = 5000
#: Upper input limit of MD18342 $MN_MM_CEC_MAX_POINTS.
MAX_CEC_POINTS = 2000
#: What the tables written here compensate.
COMPENSATES = frozenset({*POSITIONING.values(), *STRAIGHTNESS, "squareness"})


def _mm(value: float) -> str:
    return f"{round(value, 6) + 0.0:.6f}"


def _eec_block(axis: str, grid: Grid, values_mm: Vec) -> list[str]:
    ax = f"AX{axis_number(axis)}"
    lines = [f"$AA_ENC_COMP[0,{n},{ax}]={_mm(v)}" for n, v in enumerate(values_mm)]
    return [
        *lines,
        f"$AA_ENC_COMP_STEP[0,{ax}]={_mm(grid.step_mm)}",
        f"$AA_ENC_COMP_MIN[0,{ax}]={_mm(grid.start_mm)}",
        f"$AA_ENC_COMP_MAX[0,{ax}]={_mm(grid.end_mm)}",
        f"$AA_ENC_COMP_IS_MODULO[0,{ax}]=0",
    ]


def _cec_block(
    index: int, input_axis: str, output_axis: str, grid: Grid, values_mm: Vec, direction: int
) -> list[str]:
    lines = [f"$AN_CEC[{index},{n}]={_mm(v)}" for n, v in enumerate(values_mm)]
    return [
        *lines,
        f"$AN_CEC_INPUT_AXIS[{index}]=(AX{axis_number(input_axis)})",
        f"$AN_CEC_OUTPUT_AXIS[{index}]=(AX{axis_number(output_axis)})",
        f"$AN_CEC_STEP[{index}]={_mm(grid.step_mm)}",
        f"$AN_CEC_MIN[{index}]={_mm(grid.start_mm)}",
        f"$AN_CEC_MAX[{index}]={_mm(grid.end_mm)}",
        f"$AN_CEC_DIRECTION[{index}]={direction}",
        f"$AN_CEC_MULT_BY_TABLE[{index}]=0",
        f"$AN_CEC_IS_MODULO[{index}]=0",
    ]


def _grid(source: Table, what: str, limit: int) -> Grid:
    grid = grid_of(source.positions_mm)
    check_count(grid.count, limit, what, "Sinumerik")
    return grid


def render_eec(tables: ErrorTableSet) -> str:
    """``%_N_AX_EEC_INI``: the positioning error of X, Y, Z as LEC tables."""
    out = [
        "%_N_AX_EEC_INI",
        "; xmalign: leadscrew error compensation; value = positioning error in mm",
        "; (a positive value moves the axis negative). Needs MD32700 $MA_ENC_COMP_ENABLE[0]=1",
        "CHANDATA(1)",
    ]
    for axis in AXES:
        source = table(tables, POSITIONING[axis])
        grid = _grid(source, f"{POSITIONING[axis]} (MD38000)", MAX_EEC_POINTS)
        out.append(f"; {axis}: MD38000 $MA_MM_ENC_COMP_MAX_POINTS >= {grid.count}")
        out.extend(_eec_block(axis, grid, values_on(grid.positions_mm, source)))
    out.append("M17")
    return "\n".join(out) + "\n"


def _cec_tables(tables: ErrorTableSet) -> list[tuple[str, str, str, Table, int]]:
    """(description, input, output, correction table, direction) of every CEC table."""
    entries = []
    for name, (input_axis, output_axis) in STRAIGHTNESS.items():
        source = straightness_with_squareness(tables, name)
        correction = Table(source.positions_mm, -source.values, source.u95)
        entries.append((f"{name} with squareness", input_axis, output_axis, correction, 0))
    for axis, name in POSITIONING.items():
        pair = directional(tables, name)
        if pair is None:
            continue
        mean = table(tables, name)
        for source, direction in zip(pair, (1, -1), strict=True):
            reversal = Table(mean.positions_mm, -(source.values - mean.values), source.u95)
            entries.append((f"{name} reversal", axis, axis, reversal, direction))
    return entries


def render_cec(tables: ErrorTableSet) -> str:
    """``%_N_NC_CEC_INI``: straightness, squareness and reversal as CEC tables (corrections)."""
    out = [
        "%_N_NC_CEC_INI",
        "; xmalign: sag/angularity compensation; value = correction (minus the error) in mm",
        "; Needs MD18342 $MN_MM_CEC_MAX_POINTS, MD32710 $MA_CEC_ENABLE=1 on the output axes",
        "CHANDATA(1)",
    ]
    for index, (what, input_axis, output_axis, source, direction) in enumerate(_cec_tables(tables)):
        grid = _grid(source, f"{what} (MD18342)", MAX_CEC_POINTS)
        out.append(f"; table {index}: {what}, {output_axis} = f({input_axis})")
        out.extend(
            _cec_block(
                index,
                input_axis,
                output_axis,
                grid,
                values_on(grid.positions_mm, source),
                direction,
            )
        )
    out.append("M17")
    return "\n".join(out) + "\n"


def render(tables: ErrorTableSet, chain: Chain) -> dict[str, str]:
    """File name -> text of the two init programs."""
    return {"AX_EEC.INI": render_eec(tables), "NC_CEC.INI": render_cec(tables)}
