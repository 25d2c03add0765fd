"""FANUC Series 0i / 16i / 30i: (bidirectional) pitch error compensation parameters and data.

From the parameter manuals (parameters 3620-3627, 3605#0) and FANUC's technical
report A-77810E "Bidirectional pitch error compensation":

- 3620 number of the compensation point of the reference position,
  3621 / 3622 the most distant point on the - / + side (travel in the
  positive direction), 3623 magnification, 3624 interval (detection units);
  with bidirectional compensation (3605#0 = 1) also 3626 the most distant
  point on the - side for travel in the negative direction (that table has as
  many points as the positive one) and 3627 the absolute compensation at the
  reference position when it is approached from the negative side;
- compensation points lie at multiples of the interval from the reference
  position; the value at point ``R + i`` is the *incremental* correction for
  the section from ``(i - 1)·interval`` to ``i·interval``, so the most distant
  point on the - side is ``R - stroke/interval + 1`` (the manual's example);
  values are detection units times the magnification, -127 .. 127 each;
- the point numbers 0 .. 1023 are shared by all axes;
- parameter tape format ``N<param>A<axis>P<value>...;`` and pitch data
  ``N1<point>P<value>;`` (``N10000`` is point 0), between ``%`` lines.

The correction is minus the fitted positioning error, zero at the reference
position (the machine file's ``cnc.reference_mm``, where the reference return
is taken to be made in the positive direction). The detection unit is the
machine file's ``cnc.detection_unit_um`` (1 um for IS-B, 0.1 um for IS-C).
Bit parameter 3605#0 and the power cycle are left to the operator
(``PITCH_README.TXT``): a tape would overwrite the other bits of 3605.

Straightness compensation is a Fanuc option with its own parameters, whose
numbers and layout differ between series and could not be checked against a
manual: xmalign writes no tape for it but ``STRAIGHTNESS.TXT``, the
corrections of each other axis at the moving axis's pitch points (detection
units, absolute, zero at the reference position) to enter by hand. They are
fitted to what the pitch tables leave, so the pitch tables are right with or
without the option.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from xmalign.comp.common import axis_number, check_count, has_reversal
from xmalign.comp.fit import PITCH, STRAIGHTNESS, CompensationFit, CompModel
from xmalign.errors import OutOfRangeError
from xmalign.geometry import Vec
from xmalign.machine import Machine
from xmalign.rigid_body import AXES

NAME = "fanuc"
MODEL = CompModel(pairs=PITCH, directional=True, optional=STRAIGHTNESS)
MAX_POINTS_PER_AXIS = 128
MAX_POINTS_TOTAL = 1024
MAX_VALUE = 127
MAX_MAGNIFICATION = 100


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
    negative_first_number: int | None = None
    negative_values: np.ndarray | None = None
    reference_negative: int = 0

    @property
    def count(self) -> int:
        return self.last_number - self.first_number + 1


def _sections(positions_mm: Vec, reference_mm: float, interval_mm: float) -> np.ndarray:
    """Section indices ``i`` (point ``R + i`` ends at ``reference + i·interval``), from i_min."""
    low = min(np.floor((positions_mm[0] - reference_mm) / interval_mm + 1e-9), 0)
    high = max(np.ceil((positions_mm[-1] - reference_mm) / interval_mm - 1e-9), 0)
    return np.arange(int(low), int(high) + 1)


def _interval_units(positions_mm: Vec, unit_mm: float) -> int:
    """The compensation point interval (parameter 3624): the table's mean spacing, units."""
    return max(int(round(np.mean(np.diff(positions_mm)) / unit_mm)), 1)


def _increments(correction: Vec, magnification: int) -> np.ndarray:
    """Incremental values for each section end (the first entry is the section start)."""
    return np.diff(np.round(correction / magnification)).astype(int)


def pitch_table(axis: str, fit: CompensationFit, machine: Machine, next_free: int) -> PitchTable:
    """Fanuc pitch data for one axis, numbered from the first free point ``next_free``.

    The reference point number must not be negative, so an axis whose reference
    lies at its negative end starts one number later.
    """
    unit_mm = machine.cnc.detection_unit_um * 1e-3
    reference = float(machine.cnc.reference[AXES.index(axis)])
    positions, forward = fit.table(axis, axis, "+")
    _, reverse = fit.table(axis, axis, "-")
    interval = _interval_units(positions, unit_mm)
    interval_mm = interval * unit_mm
    sections = _sections(positions, reference, interval_mm)
    at = reference + sections * interval_mm
    datum = np.interp(reference, positions, forward)
    correction = -(np.interp(at, positions, forward) - datum) / unit_mm
    correction_neg = -(np.interp(at, positions, reverse) - datum) / unit_mm
    bidirectional = has_reversal(fit, axis)
    count = len(sections) - 1
    first_number = max(next_free, int(sections[0]) + 1)
    check_count(count, MAX_POINTS_PER_AXIS, f"{axis} (per axis)", "Fanuc")
    for magnification in range(1, MAX_MAGNIFICATION + 1):
        values = _increments(correction, magnification)
        negative = _increments(correction_neg, magnification)
        if (
            max(np.max(np.abs(values)), np.max(np.abs(negative)) if bidirectional else 0)
            <= MAX_VALUE
        ):
            reference_number = first_number - int(sections[0]) - 1
            return PitchTable(
                axis=axis,
                reference_number=reference_number,
                first_number=first_number,
                last_number=first_number + count - 1,
                magnification=magnification,
                interval_units=interval,
                values=values,
                negative_first_number=first_number + count if bidirectional else None,
                negative_values=negative if bidirectional else None,
                reference_negative=int(
                    round(
                        -(np.interp(reference, positions, reverse) - datum)
                        / unit_mm
                        / magnification
                    )
                ),
            )
    raise OutOfRangeError(
        f"Fanuc: the {axis} correction changes by more than {MAX_VALUE} x {MAX_MAGNIFICATION}"
        " detection units between two points"
    )


def _parameter(number: int, values: list[int]) -> str:
    axes = "".join(f"A{i}P{v}" for i, v in enumerate(values, start=1))
    return f"N{number:05d}{axes};"


def pitch_tables(fit: CompensationFit, machine: Machine) -> list[PitchTable]:
    """The three axes' tables, numbered one after the other from point 0."""
    tables = []
    first = 0
    for axis in AXES:
        table = pitch_table(axis, fit, machine, first)
        tables.append(table)
        first = table.last_number + 1 + (table.count if table.negative_values is not None else 0)
    check_count(first, MAX_POINTS_TOTAL, "X, Y and Z together", "Fanuc")
    return tables


def render_tape(tables: list[PitchTable]) -> str:
    """The parameter and pitch-data tape."""
    bidirectional = any(t.negative_values is not None for t in tables)
    fields = [
        (3620, lambda t: t.reference_number),
        (3621, lambda t: t.first_number),
        (3622, lambda t: t.last_number),
        (3623, lambda t: t.magnification),
        (3624, lambda t: t.interval_units),
    ]
    if bidirectional:
        fields += [
            (3626, lambda t: t.negative_first_number or 0),
            (3627, lambda t: t.reference_negative),
        ]
    ordered = sorted(tables, key=lambda t: axis_number(t.axis))
    lines = ["%", *(_parameter(number, [get(t) for t in ordered]) for number, get in fields)]
    for table in tables:
        lines += [
            f"N{10000 + table.first_number + i:05d}P{int(v)};" for i, v in enumerate(table.values)
        ]
        if table.negative_values is not None and table.negative_first_number is not None:
            lines += [
                f"N{10000 + table.negative_first_number + i:05d}P{int(v)};"
                for i, v in enumerate(table.negative_values)
            ]
    lines.append("%")
    return "\n".join(lines) + "\n"


def render_readme(tables: list[PitchTable], machine: Machine) -> str:
    """What to set by hand before and after loading the tape."""
    unit = machine.cnc.detection_unit_um
    lines = [
        "xmalign: FANUC pitch error compensation (PITCH.TXT)",
        f"Detection unit assumed: {unit:g} um (machine file cnc.detection_unit_um);"
        " parameter 3624 is in detection units.",
        "Reference positions (machine coordinates, mm): "
        + ", ".join(f"{t.axis} {machine.cnc.reference[AXES.index(t.axis)]:g}" for t in tables),
    ]
    bidirectional = [t.axis for t in tables if t.negative_values is not None]
    if bidirectional:
        lines.append(
            f"Bidirectional pitch error compensation for {', '.join(bidirectional)}: set bit"
            " parameter 3605#0 (BDPx) = 1 on those axes by hand (option required)."
        )
    else:
        lines.append("Unidirectional (no direction data): keep 3605#0 = 0.")
    lines += [
        "Load PITCH.TXT (parameters and pitch data) with parameter write enabled,",
        "switch the CNC off and on, then make a reference position return on every axis.",
        "STRAIGHTNESS.TXT: for the straightness compensation option (if the machine has it),",
        "corrections to enter by hand; set up the option by the CNC's own manual.",
    ]
    return "\n".join(lines) + "\n"


def _pitch_points_mm(positions_mm: Vec, reference_mm: float, unit_mm: float) -> Vec:
    """The pitch compensation points over a table's positions (as :func:`pitch_table`)."""
    interval_mm = _interval_units(positions_mm, unit_mm) * unit_mm
    return reference_mm + _sections(positions_mm, reference_mm, interval_mm) * interval_mm


def render_straightness(fit: CompensationFit, machine: Machine) -> str:
    """The optional straightness corrections, a table per moving axis (detection units)."""
    assert fit.optional is not None
    unit_mm = machine.cnc.detection_unit_um * 1e-3
    lines = [
        "xmalign: FANUC straightness compensation (optional, enter by hand)",
        f"Corrections in detection units ({machine.cnc.detection_unit_um:g} um), absolute,"
        " zero at the reference position, at the moving axis's pitch compensation points.",
    ]
    for moving in AXES:
        reference = float(machine.cnc.reference[AXES.index(moving)])
        others = [axis for axis in AXES if axis != moving]
        positions, _ = fit.optional.tables[f"E{others[0]}{moving}"]
        at = _pitch_points_mm(positions, reference, unit_mm)
        lines += ["", f"moving axis {moving}", "  ".join([f"{moving} mm", *others])]
        columns = []
        for axis in others:
            table = fit.optional.tables[f"E{axis}{moving}"]
            error = np.interp(at, *table) - np.interp(reference, *table)
            columns.append(np.round(-error / unit_mm).astype(int))
        for k, position in enumerate(at):
            lines.append("  ".join([f"{position:.3f}", *(f"{c[k]:+d}" for c in columns)]))
    return "\n".join(lines) + "\n"


def render(fit: CompensationFit, machine: Machine) -> dict[str, str]:
    """File name -> text of the parameter tape and its instructions."""
    tables = pitch_tables(fit, machine)
    return {
        "PITCH.TXT": render_tape(tables),
        "PITCH_README.TXT": render_readme(tables, machine),
        "STRAIGHTNESS.TXT": render_straightness(fit, machine),
    }
