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

xmalign writes the fitted per-axis tables as LEC, the fitted cross tables
(straightness, squareness and the mean Abbe effect at the tool point) as CEC
and, with bidirectional data, the reversal as one CEC table per direction on
the axis itself. Every table is zero at the reference point. Machine axis
names come from the machine file's ``cnc.axis_names`` (default ``AX1`` ..
``AX3``).
"""

from __future__ import annotations

from xmalign.comp.common import Grid, check_count, fitted, has_reversal
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


def _mm(value: float) -> str:
    return f"{round(value, 6) + 0.0:.6f}"


def axis_name(machine: Machine, axis: str) -> str:
    """The machine axis identifier of ``axis`` (``AX1`` .. unless the machine file names it)."""
    return machine.cnc.axis_name(axis, f"AX{AXES.index(axis) + 1}")


def _eec_block(name: str, grid: Grid, values_mm: Vec) -> list[str]:
    lines = [f"$AA_ENC_COMP[0,{n},{name}]={_mm(v)}" for n, v in enumerate(values_mm)]
    return [
        *lines,
        f"$AA_ENC_COMP_STEP[0,{name}]={_mm(grid.step_mm)}",
        f"$AA_ENC_COMP_MIN[0,{name}]={_mm(grid.start_mm)}",
        f"$AA_ENC_COMP_MAX[0,{name}]={_mm(grid.end_mm)}",
        f"$AA_ENC_COMP_IS_MODULO[0,{name}]=0",
    ]


def render_eec(fit: CompensationFit, machine: Machine) -> str:
    """``%_N_AX_EEC_INI``: the fitted per-axis error as LEC tables (value = error, mm)."""
    out = [
        "%_N_AX_EEC_INI",
        "; xmalign: leadscrew error compensation; value = positioning error in mm",
        "; (a positive value moves the axis negative), zero at the reference point.",
        "; Activation: MD32700 $MA_ENC_COMP_ENABLE[0]=0 while loading this program,",
        "; then 1 on each axis below, reset (NewConfig); acts after referencing.",
        "CHANDATA(1)",
    ]
    for axis in AXES:
        grid, values = fitted(fit, axis, axis)
        name = axis_name(machine, axis)
        check_count(grid.count, MAX_EEC_POINTS, f"{axis} (MD38000)", "Sinumerik")
        out.append(f"; {axis} = {name}: MD38000 $MA_MM_ENC_COMP_MAX_POINTS[0] >= {grid.count}")
        out.extend(_eec_block(name, grid, values))
    out.append("M17")
    return "\n".join(out) + "\n"


def _cec_tables(fit: CompensationFit) -> list[tuple[str, str, str, Grid, Vec, int]]:
    """(description, input, output, grid, correction mm, direction) of every CEC table."""
    entries = []
    for output, axis in MODEL.pairs:
        if output == axis:
            continue
        grid, error = fitted(fit, output, axis)
        entries.append((f"E{output}{axis} fitted", axis, output, grid, -error, 0))
    for axis in AXES:
        if not has_reversal(fit, axis):
            continue
        grid, mean = fitted(fit, axis, axis)
        for direction, sign in (("+", 1), ("-", -1)):
            _, own = fitted(fit, axis, axis, direction)
            entries.append((f"E{axis}{axis} reversal", axis, axis, grid, -(own - mean), sign))
    return entries


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


def render_cec(fit: CompensationFit, machine: Machine) -> str:
    """``%_N_NC_CEC_INI``: cross tables and reversal as CEC tables (corrections), enabled."""
    tables = _cec_tables(fit)
    out = [
        "%_N_NC_CEC_INI",
        "; xmalign: sag/angularity compensation; value = correction (minus the error) in mm,",
        "; zero at the reference point. Activation: MD18342 $MN_MM_CEC_MAX_POINTS[t] as below,",
        "; MD32710 $MA_CEC_ENABLE=1 on every output axis, reset (NewConfig); the tables are",
        "; switched on at the end (SD41300 $SN_CEC_TABLE_ENABLE, SD41310 $SN_CEC_TABLE_WEIGHT).",
        "CHANDATA(1)",
    ]
    for index, (what, axis, output, grid, values, direction) in enumerate(tables):
        check_count(grid.count, MAX_CEC_POINTS, f"{what} (MD18342)", "Sinumerik")
        names = (axis_name(machine, axis), axis_name(machine, output))
        out.append(
            f"; table {index}: {what}, {output} = f({axis}); MD18342[{index}] >= {grid.count}"
        )
        out.extend(_cec_block(index, names, grid, values, direction))
    for index in range(len(tables)):
        out += [f"$SN_CEC_TABLE_ENABLE[{index}]=TRUE", f"$SN_CEC_TABLE_WEIGHT[{index}]=1.0"]
    out.append("M17")
    return "\n".join(out) + "\n"


def render(fit: CompensationFit, machine: Machine) -> dict[str, str]:
    """File name -> text of the two init programs."""
    return {"AX_EEC.INI": render_eec(fit, machine), "NC_CEC.INI": render_cec(fit, machine)}
