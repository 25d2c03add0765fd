"""FANUC Series 0i / 16i / 30i: (bidirectional) pitch error compensation parameters and data.

From the parameter manuals (parameters 3620-3627, 3605#0) and FANUC's technical
report A-77810E "Bidirectional pitch error compensation":

- 3620 number of the compensation point of the reference position,
  3621 / 3622 the most distant point on the - / + side (travel in the
  positive direction), 3623 magnification, 3624 interval (detection units);
  with bidirectional compensation (3605#0 = 1) also 3626 the most distant
  point on the - side for travel in the negative direction (that table has as
  many points as the positive one) and 3627 the compensation (absolute value)
  at the reference position when it is approached in the direction *opposite to
  the reference-return direction* (A-77810E, table (a));
- compensation points lie at multiples of the interval from the reference
  position; the value at point ``R + i`` is the *incremental* correction for
  the section from ``(i - 1)·interval`` to ``i·interval``, so the most distant
  point on the - side is ``R - stroke/interval + 1`` (the 0i-PB parameter
  manual's example, B-63980EN/01 p. 100);
- the point numbers 0 .. 1023 are shared by all axes; xmalign numbers the axes one
  after the other and never gives an axis's reference number (3620) to a point of
  another axis (a gap of one number where the reference lies at the negative end);
- parameter tape format ``N<param>A<axis>P<value>...;`` (Series 30i/31i/32i:
  ``N<param>Q1A<axis>P<value>...;``) and pitch data ``N1<point>P<value>;``
  (``N10000`` is point 0), between ``%`` lines.

The correction is minus the fitted positioning error. Each direction's table is
zero at the reference position (the machine file's ``cnc.reference_mm``) when
it is approached in that axis's reference-return direction (``cnc.reference_return``,
else inferred from where the reference lies in the travel: at the lower end the
return is made in ``-``), so 3627 is the reversal there, with its sign. The
detection unit is the machine file's ``cnc.detection_unit_um`` (1 um for IS-B,
0.1 um for IS-C). Bit parameter 3605#0 and the power cycle are left to the
operator (``PITCH_README.TXT``): a tape would overwrite the other bits of 3605.
Not settled from a manual (said in the README file and by ``xmalign comp``): the
unit of 3624 on a 30i, the range of one pitch value, the pitch-data tape syntax.

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

from xmalign.comp.common import (
    Comment,
    Loading,
    Reversal,
    axis_number,
    backlash_warnings,
    check_count,
    own_tables,
    reversal_statement,
    with_history,
)
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
#: Series whose parameter tape carries ``Q1`` in every parameter block.
SERIES_WITH_PATH = ("30i", "31i", "32i")
#: The control's own backlash compensation (cutting feed; 1852 for rapid traverse).
BACKLASH_PARAMETER = "parameters 1851 and 1852 (backlash compensation)"
FORMAT = "xmalign.comp.fanuc/1"
#: The notes take comments; the parameter tape gets PITCH.TXT.history (whether a parameter
#: tape takes ``( )`` comments was not found in a manual).
COMMENTS = {"PITCH_README.TXT": Comment("# "), "STRAIGHTNESS.TXT": Comment("# ")}


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
    reversal: Reversal
    negative_first_number: int | None = None
    negative_values: np.ndarray | None = None
    #: parameter 3627: the correction at the reference approached against the return
    reference_negative: int = 0

    @property
    def return_direction(self) -> str:
        return self.reversal.return_direction

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

    The reference point number is never a point of an axis numbered before (it is
    ``next_free`` or above: a gap when the reference lies at the axis's negative end,
    where it holds no section), nor negative. Corrections are zero at the
    reference approached in the reference-return direction; 3627 is the correction
    there approached the other way (A-77810E, table (a)).
    """
    unit_mm = machine.cnc.detection_unit_um * 1e-3
    reference = float(machine.cnc.reference[AXES.index(axis)])
    own = own_tables(fit, axis, machine, "Fanuc")
    positions = own.grid.positions_mm
    interval = _interval_units(positions, unit_mm)
    interval_mm = interval * unit_mm
    sections = _sections(positions, reference, interval_mm)
    at = reference + sections * interval_mm
    correction = -np.interp(at, positions, own.forward) / unit_mm
    correction_neg = -np.interp(at, positions, own.reverse) / unit_mm
    opposite = -np.interp(reference, positions, own.table(own.opposite_direction)) / unit_mm
    count = len(sections) - 1
    first_number = max(next_free, next_free + int(sections[0]) + 1)
    check_count(count, MAX_POINTS_PER_AXIS, f"{axis} (per axis)", "Fanuc")
    for magnification in range(1, MAX_MAGNIFICATION + 1):
        values = _increments(correction, magnification)
        negative = _increments(correction_neg, magnification)
        largest = max(np.max(np.abs(values)), np.max(np.abs(negative)) if own.bidirectional else 0)
        if largest <= MAX_VALUE:
            reference_number = first_number - int(sections[0]) - 1
            return PitchTable(
                axis=axis,
                reference_number=reference_number,
                first_number=first_number,
                last_number=first_number + count - 1,
                magnification=magnification,
                interval_units=interval,
                values=values,
                negative_first_number=first_number + count if own.bidirectional else None,
                negative_values=negative if own.bidirectional else None,
                reference_negative=int(round(opposite / magnification)),
                reversal=own.carrier,
            )
    raise OutOfRangeError(
        f"Fanuc: the {axis} correction changes by more than {MAX_VALUE} x {MAX_MAGNIFICATION}"
        " detection units between two points"
    )


def _parameter(number: int, values: list[int], path: str) -> str:
    axes = "".join(f"A{i}P{v}" for i, v in enumerate(values, start=1))
    return f"N{number:05d}{path}{axes};"


def _path_word(machine: Machine) -> str:
    """``Q1`` in every parameter block of a Series 30i/31i/32i tape, nothing before."""
    return "Q1" if machine.series in SERIES_WITH_PATH else ""


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


def render_tape(tables: list[PitchTable], machine: Machine) -> str:
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
    path = _path_word(machine)
    lines = ["%"]
    lines += [_parameter(number, [get(t) for t in ordered], path) for number, get in fields]
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


def loading(fit: CompensationFit, machine: Machine) -> Loading:
    """Reversal, the check on the machine and what the manuals left open."""
    return _loading(pitch_tables(fit, machine), machine, fit.warnings)


def _loading(tables: list[PitchTable], machine: Machine, fit_warnings: tuple[str, ...]) -> Loading:
    own = [t.reversal for t in tables]
    interval = ", ".join(
        f"{t.axis} {t.interval_units * machine.cnc.detection_unit_um * 1e-3:g} mm" for t in tables
    )
    return Loading(
        reversal=reversal_statement(own, BACKLASH_PARAMETER),
        check=(
            f"read parameter 3624 back on the parameter screen: the pitch points must lie"
            f" {interval} apart; then move each axis to a table point away from the reference"
            " and compare the position with the verification run (xmalign post --verify-data)"
        ),
        unconfirmed=(
            "the unit of 3624 (written in detection units, as on the 0i/16i parameter"
            " manuals; a 30i may take it in mm)",
            "the range of one pitch value (written within -127..127 x 3623)",
            "the tape syntax of the pitch data lines (N1xxxxP...;)"
            + (" and the Q1 of a 30i tape in them" if machine.series in SERIES_WITH_PATH else ""),
        ),
        warnings=backlash_warnings(own, BACKLASH_PARAMETER) + fit_warnings,
    )


def render_readme(tables: list[PitchTable], machine: Machine, fit_warnings: tuple[str, ...]) -> str:
    """What to set by hand before and after loading the tape (and the fit's warnings)."""
    unit = machine.cnc.detection_unit_um
    lines = [
        f"xmalign: FANUC Series {machine.series} pitch error compensation (PITCH.TXT)",
        f"Detection unit assumed: {unit:g} um (machine file cnc.detection_unit_um);"
        " parameter 3624 is in detection units.",
        "Reference positions (machine coordinates, mm) and reference-return directions: "
        + ", ".join(
            f"{t.axis} {machine.cnc.reference[AXES.index(t.axis)]:g} ({t.return_direction})"
            for t in tables
        ),
        "Each table is zero at the reference position approached in its reference-return"
        " direction (parameter 1006#5 ZMI: 0 = +, 1 = -); 3627 holds the value there"
        " approached the other way. If the machine returns the other way, change"
        " cnc.reference_return and run xmalign comp again.",
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
        *_loading(tables, machine, fit_warnings).lines(),
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
    files = {
        "PITCH.TXT": render_tape(tables, machine),
        "PITCH_README.TXT": render_readme(tables, machine, fit.warnings),
        "STRAIGHTNESS.TXT": render_straightness(fit, machine),
    }
    return with_history(files, FORMAT, fit.sources, COMMENTS)
