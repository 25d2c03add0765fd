"""What every compensation-table writer needs: fitted tables on a controller's grid, limits.

Values inside are mm. A fitted table is an *error* (what the controller takes
out); a *correction* is minus the error: what a controller adds to the set point
so the tool lands where it was commanded.
"""

from __future__ import annotations

import textwrap
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from fnmatch import fnmatchcase

import numpy as np

from xmalign.comp.fit import CompensationFit
from xmalign.errors import MachineKeyError, OutOfRangeError
from xmalign.formats.error_tables import ErrorTableSet
from xmalign.formats.provenance import FileSource, history_file, history_lines
from xmalign.geometry import Vec
from xmalign.machine import Machine
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


@dataclass(frozen=True)
class Reversal:
    """Who carries an axis's reversal: the tables (``bidirectional``) or the control.

    ``return_direction`` is the axis's reference-return direction; ``backlash_folded_um``
    the control's backlash compensation moved into the tables (see :func:`own_tables`).
    """

    axis: str
    bidirectional: bool
    return_direction: str
    backlash_folded_um: float


@dataclass(frozen=True)
class OwnTables:
    """An axis's own (positioning) table in each direction of travel, errors in mm.

    ``forward`` / ``reverse`` are for motion in ``+`` / ``-``, on ``grid``; the
    table of the reference-return direction (``return_direction``) is zero at the
    reference point, so nothing jumps when the control references the axis with the
    compensation on; the other carries the reversal there. ``backlash_folded_um``
    is the control's own backlash compensation (``cnc.backlash_um``) moved into the
    reversal, so that the control's backlash can be set to 0.
    """

    axis: str
    grid: Grid
    forward: Vec
    reverse: Vec
    return_direction: str
    bidirectional: bool
    backlash_folded_um: float

    def table(self, direction: str) -> Vec:
        return self.forward if direction == "+" else self.reverse

    @property
    def at_return(self) -> Vec:
        """The table of the reference-return direction (zero at the reference)."""
        return self.table(self.return_direction)

    @property
    def opposite_direction(self) -> str:
        return "-" if self.return_direction == "+" else "+"

    @property
    def reversal(self) -> Vec:
        """The opposite direction's table minus the return direction's, mm."""
        return self.table(self.opposite_direction) - self.at_return

    @property
    def carrier(self) -> Reversal:
        return Reversal(
            self.axis, self.bidirectional, self.return_direction, self.backlash_folded_um
        )


def own_tables(fit: CompensationFit, axis: str, machine: Machine, controller: str) -> OwnTables:
    """``axis``'s own tables per direction, zero at the reference in its return direction.

    A reversal measured with the control's backlash compensation ``B`` active is
    ``B`` short of the machine's own (a positive ``B`` takes out a play in which the
    ``-`` approach stops above the ``+`` approach), so ``B`` is added to the reverse
    table and the control's backlash goes to 0 (docs/controllers.md, "Reversal").
    Refused (InputError naming the key) when the data have a reversal and the
    return direction is unknown.
    """
    grid, forward = fitted(fit, axis, axis, "+")
    _, reverse = fitted(fit, axis, axis, "-")
    bidirectional = has_reversal(fit, axis)
    direction = machine.reference_return(axis)
    if direction is None:
        if bidirectional:
            raise MachineKeyError(
                f"cnc.reference_return.{axis}",
                f"needed for the {controller} tables: the reference point lies inside the"
                f" {axis} travel, so the direction of its reference return ('+' or '-')"
                " cannot be told, and the reversal table starts from it",
            )
        direction = "+"
    backlash_um = (machine.cnc.backlash(axis) or 0.0) if bidirectional else 0.0
    reverse = reverse + backlash_um * 1e-3
    reference = float(machine.cnc.reference[AXIS_INDEX[axis]])
    at_return = forward if direction == "+" else reverse
    datum = float(np.interp(reference, grid.positions_mm, at_return))
    return OwnTables(
        axis, grid, forward - datum, reverse - datum, direction, bidirectional, backlash_um
    )


#: The longest comment line a writer puts into a controller file (the notes are wrapped).
COMMENT_WIDTH = 100


@dataclass(frozen=True)
class Loading:
    """What a technician must know to load a writer's files (printed by ``xmalign comp``).

    ``reversal``: which of the tables and the control's backlash compensation carries
    the reversal, and what to set the other to; ``check``: the one check to make on
    the machine before trusting the tables; ``unconfirmed``: facts of the file that
    could not be settled from the maker's manual; ``warnings``: this calibration's.
    """

    reversal: str
    check: str
    unconfirmed: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()

    def lines(self, comment: str = "") -> list[str]:
        """The loading notes as text lines, each prefixed by ``comment``; in a file (a
        ``comment`` mark given) wrapped to :data:`COMMENT_WIDTH` characters, for a control
        whose blocks have a length limit."""
        notes = [f"Reversal: {self.reversal}", f"Check before use: {self.check}"]
        notes += [f"Not confirmed from a manual: {fact}" for fact in self.unconfirmed]
        notes += [f"Warning: {warning}" for warning in self.warnings]
        if not comment:
            return notes
        width = COMMENT_WIDTH - len(comment)
        return [
            comment + line
            for note in notes
            for line in textwrap.wrap(note, width, subsequent_indent="  ", break_long_words=False)
        ]


def backlash_warnings(tables: Sequence[Reversal], parameter: str) -> tuple[str, ...]:
    """Warnings for axes whose reversal the tables carry but whose backlash was not given."""
    unknown = [t.axis for t in tables if t.bidirectional and t.backlash_folded_um == 0.0]
    if not unknown:
        return ()
    return (
        f"cnc.backlash_um not given for {', '.join(unknown)}: the tables carry the reversal"
        f" as measured, so {parameter} must have been 0 during the measurement and must"
        " stay 0 (else give cnc.backlash_um and run comp again)",
    )


def reversal_statement(tables: Sequence[Reversal], parameter: str) -> str:
    """Who carries the reversal of each axis, and what the control's backlash is set to."""
    carried = [t.axis for t in tables if t.bidirectional]
    kept = [t.axis for t in tables if not t.bidirectional]
    parts = []
    if carried:
        folded = [f"{t.axis} {t.backlash_folded_um:g} um" for t in tables if t.backlash_folded_um]
        included = f" (its value during the measurement is included: {', '.join(folded)})"
        parts.append(
            f"the tables carry the reversal of {', '.join(carried)}: set {parameter} to 0 on"
            f" {', '.join(carried)}" + (included if folded else "")
        )
    if kept:
        parts.append(
            f"no direction data for {', '.join(kept)}: the tables are the mean of both"
            f" directions; keep {parameter} on {', '.join(kept)} as it was during the measurement"
        )
    return "; ".join(parts)


@dataclass(frozen=True)
class Comment:
    """How a file takes comment lines: ``prefix`` before each, after its first ``skip``
    lines (a Sinumerik init program starts with its ``%_N_`` name)."""

    prefix: str
    skip: int = 0


def table_sources(tables: ErrorTableSet) -> tuple[FileSource, ...]:
    """The error-table file the tables were read from (none when they were not)."""
    return () if tables.history is None else (FileSource.of("errors", tables.source),)


def with_history(
    files: Mapping[str, str],
    format_name: str,
    inputs: Sequence[FileSource],
    comments: Mapping[str, Comment],
) -> dict[str, str]:
    """``files`` with their history (format, software, time, the inputs' SHA-256).

    A file whose name matches a pattern of ``comments`` carries it as comment lines in
    that syntax; any other file (a format that takes no comment, or none confirmed from
    its manual) gets ``NAME.history`` beside it (:func:`history_file`).
    """
    out: dict[str, str] = {}
    for name, text in files.items():
        comment = next((c for pattern, c in comments.items() if fnmatchcase(name, pattern)), None)
        if comment is None:
            out[name] = text
            out[f"{name}.history"] = history_file(format_name, name, text.encode(), inputs)
            continue
        lines = text.splitlines(keepends=True)
        block = [f"{comment.prefix}{line}\n" for line in history_lines(format_name, inputs)]
        out[name] = "".join(lines[: comment.skip] + block + lines[comment.skip :])
    return out
