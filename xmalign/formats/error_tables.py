"""Error-table CSV of docs/formats.md: ``name,position_mm,value,unit,u95[,range]``.

Values are um (translations) or urad (rotations, squareness) in the file and
mm / rad in :class:`ErrorTableSet`. Directional tables carry ``+`` or ``-``
after the name. The optional last column ``range`` says ``measured`` or
``extrapolated`` (beyond the measured stroke); files without it (written
before it existed) are read as all measured (docs/post.md, "The range column").

Version 2 (:data:`ERROR_TABLES_FORMAT`) starts with the history preamble of
:mod:`xmalign.formats.provenance` and a ``# machine:`` line naming the machine
the tables were measured on (name, chain, travel), which ``comp`` checks;
version 1 (no preamble, written before 0.1.0 carried history) is read as
before, with no machine named.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections import defaultdict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Annotated, Any, Literal, Protocol

import numpy as np
from pydantic import Field, ValidationError, field_validator, model_validator

from xmalign.errors import FormatError, InputError
from xmalign.formats.common import (
    MAX_ERROR_MM,
    MAX_ERROR_RAD,
    FileModel,
    Finite,
    Length_mm,
    atomic_write_text,
    describe_problem,
    line_error,
    located,
    read_text,
)
from xmalign.formats.provenance import (
    FileSource,
    Provenance,
    csv_preamble,
    json_value,
    read_csv_preamble,
)
from xmalign.geometry import Vec
from xmalign.rigid_body import AXES, MOTION_NAMES, SQUARENESS_NAMES, ErrorTables

ERROR_TABLES_FORMAT = "xmalign.error-tables/2"
#: What a file without a preamble is: the CSV as written before files carried history.
FIRST_FORMAT = "xmalign.error-tables/1"
MACHINE_KEY = "machine"
#: Travel limits closer than this are the same machine, mm.
TRAVEL_TOLERANCE_MM = 1e-6
HEADER = ("name", "position_mm", "value", "unit", "u95")
RANGE_COLUMN = "range"
RANGES = ("measured", "extrapolated")
UM_PER_MM = 1000.0
URAD_PER_RAD = 1e6


def file_unit(name: str) -> str:
    """``um`` for translation errors, ``urad`` for rotations and squareness."""
    base = name.rstrip("+-")
    if base in SQUARENESS_NAMES or base[1] in "ABC":
        return "urad"
    return "um"


def _scale(unit: str) -> float:
    return UM_PER_MM if unit == "um" else URAD_PER_RAD


#: The largest value (and u95) a row may hold, in the file's units.
_LIMITS = {"um": MAX_ERROR_MM * UM_PER_MM, "urad": MAX_ERROR_RAD * URAD_PER_RAD}


@dataclass
class Table:
    """One error table: positions mm (M,), values and u95 in mm or rad (M,).

    ``measured`` (M,) bool is False at points extrapolated beyond the measured
    stroke (None: all measured).
    """

    positions_mm: Vec
    values: Vec
    u95: Vec
    measured: np.ndarray | None = None

    def measured_mask(self) -> np.ndarray:
        """Which points lie in the measured range, shape (M,) bool."""
        if self.measured is None:
            return np.ones(len(self.positions_mm), dtype=bool)
        return np.asarray(self.measured, dtype=bool)


class _MachineLike(Protocol):
    """What names a machine (:class:`xmalign.machine.Machine` has it)."""

    @property
    def name(self) -> str: ...

    @property
    def chain(self) -> str: ...

    @property
    def travel_mm(self) -> Mapping[Any, Sequence[float]]: ...


@dataclass(frozen=True)
class MachineIdentity:
    """The machine error tables were measured on: name, chain, travel (mm, ``[min, max]``)."""

    name: str
    chain: str
    travel_mm: dict[str, tuple[float, float]]

    @classmethod
    def of(cls, machine: _MachineLike) -> MachineIdentity:
        travel = {
            axis: (float(low), float(high)) for axis, (low, high) in machine.travel_mm.items()
        }
        return cls(machine.name, machine.chain, travel)

    def to_json(self) -> str:
        travel = {axis: list(limits) for axis, limits in sorted(self.travel_mm.items())}
        return json.dumps({"name": self.name, "chain": self.chain, "travel_mm": travel})

    def differs(self, machine: _MachineLike) -> str | None:
        """What makes ``machine`` another machine (chain or travel), or None."""
        other = MachineIdentity.of(machine)
        if other.chain != self.chain:
            return f"chain {self.chain}, not {other.chain}"
        for axis, limits in sorted(self.travel_mm.items()):
            given = other.travel_mm.get(axis)
            if given is None or max(abs(np.subtract(limits, given))) > TRAVEL_TOLERANCE_MM:
                return f"{axis} travel [{limits[0]:g}, {limits[1]:g}] mm, not {list(given or [])}"
        return None


@dataclass
class ErrorTableSet:
    """All tables of an error CSV, keyed by file name (``EXX``, ``EXX+``, ``EC0Y``).

    ``source`` names the file they were read from (for messages); ``machine``
    the machine they were measured on (None: a version 1 file does not say);
    ``history`` what the file says of its making (None: not read from a file).
    """

    tables: dict[str, Table] = field(default_factory=dict)
    squareness: dict[str, tuple[float, float]] = field(default_factory=dict)
    source: str = "the error tables"
    machine: MachineIdentity | None = None
    history: Provenance | None = None

    def check_machine(self, machine: _MachineLike) -> list[str]:
        """Refuse tables measured on another chain or travel; warnings to be shown.

        Raises
        ------
        InputError
            The file names a machine with another chain or travel than ``machine``.
        """
        if self.machine is None:
            return [f"{self.source} does not name the machine it was measured on (version 1)"]
        problem = self.machine.differs(machine)
        if problem is not None:
            raise InputError(
                f"{self.source}: measured on '{self.machine.name}' ({problem} of"
                f" '{machine.name}'): give the machine file it was measured on"
            )
        if self.machine.name != machine.name:
            return [f"{self.source} was measured on '{self.machine.name}', not '{machine.name}'"]
        return []

    def positioning_table(self, axis: str) -> Table:
        """The positioning table of ``axis`` (``EXX``, else ``EXX+``, else ``EXX-``).

        Raises
        ------
        InputError
            The file holds none (it was not posted from all six lines).
        """
        name = f"E{axis}{axis}"
        for candidate in (name, name + "+", name + "-"):
            if candidate in self.tables:
                return self.tables[candidate]
        raise InputError(f"{self.source}: no table {name} (run xmalign post on all six lines)")

    def check_within_travel(self, travel_min_mm: Vec, travel_max_mm: Vec, machine: str) -> None:
        """Refuse a table whose positions all lie outside its axis' travel (tables of
        another machine, or positions in another unit): nothing of it could be applied.

        Raises
        ------
        InputError
            Naming the file, the table, its axis and both ranges.
        """
        for name, table in self.tables.items():
            axis = name.rstrip("+-")[-1]
            low, high = travel_min_mm[AXES.index(axis)], travel_max_mm[AXES.index(axis)]
            first, last = table.positions_mm.min(), table.positions_mm.max()
            if last < low or first > high:
                raise InputError(
                    located(
                        self.source,
                        name,
                        f"positions {first:g}..{last:g} mm lie outside the {axis} travel"
                        f" {low:g}..{high:g} mm of machine '{machine}' (tables of another"
                        " machine?)",
                    )
                )

    def model(self, direction: str = "") -> ErrorTables:
        """The interpolating error model of one direction (``""``, ``"+"`` or ``"-"``).

        A name without that direction falls back to its unidirectional table.
        """
        chosen: dict[str, tuple[Vec, Vec]] = {}
        for name in MOTION_NAMES:
            table = self.tables.get(name + direction) or self.tables.get(name)
            if table is not None:
                chosen[name] = (table.positions_mm, table.values)
        return ErrorTables(
            tables=chosen, squareness={k: v for k, (v, _) in self.squareness.items()}
        )


class _RowModel(FileModel):
    """One row of the file, in the file's units (um or urad)."""

    name: str
    position_mm: Length_mm | None
    value: Finite
    unit: str
    u95: Annotated[float, Field(ge=0, allow_inf_nan=False)] | None
    range: Literal["measured", "extrapolated"] | None = None

    @field_validator("name")
    @classmethod
    def _known_name(cls, name: str) -> str:
        base = name.rstrip("+-")
        if base not in MOTION_NAMES and base not in SQUARENESS_NAMES or len(name) - len(base) > 1:
            raise ValueError(f"unknown error name '{name}'")
        return name

    @field_validator("position_mm", "u95", "range", mode="before")
    @classmethod
    def _empty_is_none(cls, text: str) -> str | None:
        return text or None

    @model_validator(mode="after")
    def _consistent(self) -> _RowModel:
        expected = file_unit(self.name)
        if self.unit != expected:
            raise ValueError(f"{self.name} is in {expected}, not '{self.unit}'")
        squareness = self.name.rstrip("+-") in SQUARENESS_NAMES
        if squareness != (self.position_mm is None):
            raise ValueError(
                f"{self.name}: position_mm must be "
                + ("empty for a squareness" if squareness else "given")
            )
        limit = _LIMITS[self.unit]
        for what, number in (("value", self.value), ("u95", self.u95)):
            if number is not None and abs(number) > limit:
                raise ValueError(
                    f"{what} {number:g} {self.unit} is more than a machine can have"
                    f" ({limit:g} {self.unit})"
                )
        return self


def _parse_row(fields: list[str], header: tuple[str, ...], path: Path, line: int) -> _RowModel:
    if len(fields) != len(header):
        raise line_error(path, line, f"expected {len(header)} fields, found {len(fields)}")
    values = dict(zip(header, (f.strip() for f in fields), strict=True))
    try:
        return _RowModel.model_validate(values)
    except ValidationError as error:
        first = error.errors()[0]
        key = ".".join(str(part) for part in first["loc"])
        problem = describe_problem(first)
        raise line_error(path, line, f"{key}: {problem}" if key else problem) from error


def _split_preamble(text: str) -> tuple[list[str], str]:
    """The leading ``#`` lines and the rest, the rest keeping its line numbers."""
    lines = text.split("\n")
    count = next((n for n, line in enumerate(lines) if not line.startswith("#")), len(lines))
    return lines[:count], "\n" * count + "\n".join(lines[count:])


def _machine_of(history: Provenance, path: Path) -> MachineIdentity | None:
    data = json_value(history, MACHINE_KEY, str(path))
    if data is None:
        return None
    try:
        travel = {str(a): (float(lo), float(hi)) for a, (lo, hi) in data["travel_mm"].items()}
        return MachineIdentity(str(data["name"]), str(data["chain"]), travel)
    except (KeyError, TypeError, ValueError, AttributeError) as error:
        raise InputError(
            located(path, f"'# {MACHINE_KEY}' line", "needs name, chain and travel_mm")
        ) from error


def read_error_tables(path: str | Path) -> ErrorTableSet:
    """Read an error-table CSV (version 1 or 2); a bad or repeated row (with its line
    number), a table of one position or a missing squareness row (naming it) raises
    InputError, a newer version FormatError."""
    path = Path(path)
    comments, body = _split_preamble(read_text(path))
    history = read_csv_preamble(comments, ERROR_TABLES_FORMAT, str(path), FIRST_FORMAT)
    reader = csv.reader(io.StringIO(body, newline=""))
    try:
        while (first := next(reader, None)) == []:
            pass
        header = tuple(h.strip() for h in first or ())
        if header not in (HEADER, (*HEADER, RANGE_COLUMN)):
            raise FormatError(
                located(
                    path,
                    f"line {reader.line_num or 1}",
                    f"header must be {','.join(HEADER)}[,{RANGE_COLUMN}]",
                )
            )
        rows: dict[str, list[tuple[float, float, float, bool]]] = defaultdict(list)
        first_line: dict[tuple[str, float | None], int] = {}
        result = ErrorTableSet(
            source=str(path), machine=_machine_of(history, path), history=history
        )
        for fields in reader:
            if not fields:
                continue
            row = _parse_row(fields, header, path, reader.line_num)
            seen = first_line.setdefault((row.name, row.position_mm), reader.line_num)
            if seen != reader.line_num:
                at = "" if row.position_mm is None else f" at {row.position_mm:g} mm"
                raise line_error(path, reader.line_num, f"{row.name}{at} repeats line {seen}")
            scale = _scale(row.unit)
            value, u95 = row.value / scale, math.nan if row.u95 is None else row.u95 / scale
            if row.position_mm is None:
                result.squareness[row.name] = (value, u95)
            else:
                rows[row.name].append((row.position_mm, value, u95, row.range != "extrapolated"))
    except csv.Error as error:
        raise line_error(path, reader.line_num, f"not valid CSV ({error})") from error
    for name, entries in rows.items():
        if len(entries) < 2:
            raise InputError(located(path, name, "a table needs at least two positions"))
        data = np.array(sorted(entries))
        result.tables[name] = Table(data[:, 0], data[:, 1], data[:, 2], data[:, 3] > 0)
    missing = [name for name in SQUARENESS_NAMES if name not in result.squareness]
    if missing:
        raise InputError(
            located(
                path,
                "squareness",
                f"no row for {', '.join(missing)}; xmalign post writes all three (a machine"
                " taken as square needs them too, with value 0)",
            )
        )
    return result


def _number(value: float) -> str:
    return "" if not math.isfinite(value) else f"{value:.4f}"


def error_tables_to_csv(tables: ErrorTableSet, inputs: Iterable[FileSource] = ()) -> str:
    """The CSV text: history preamble (with the machine when known), header, rows."""
    extra = {MACHINE_KEY: tables.machine.to_json()} if tables.machine else {}
    lines = [
        csv_preamble(ERROR_TABLES_FORMAT, inputs, extra).rstrip("\n"),
        ",".join((*HEADER, RANGE_COLUMN)),
    ]
    for name, table in tables.tables.items():
        unit = file_unit(name)
        scale = _scale(unit)
        for position, value, u95, measured in zip(
            table.positions_mm, table.values, table.u95, table.measured_mask(), strict=True
        ):
            lines.append(
                f"{name},{position:.3f},{_number(value * scale)},{unit},{_number(u95 * scale)},"
                + RANGES[0 if measured else 1]
            )
    for name, (value, u95) in tables.squareness.items():
        lines.append(f"{name},,{_number(value * URAD_PER_RAD)},urad,{_number(u95 * URAD_PER_RAD)},")
    return "\n".join(lines) + "\n"


def error_tables_text(
    tables: ErrorTableSet,
    inputs: Iterable[FileSource] = (),
    machine: _MachineLike | None = None,
) -> str:
    """The tables' file (format version 2), naming ``machine`` (else ``tables.machine``)
    and the files they were made from."""
    if machine is not None:
        tables = replace(tables, machine=MachineIdentity.of(machine))
    return error_tables_to_csv(tables, inputs)


def write_error_tables(
    path: str | Path,
    tables: ErrorTableSet,
    inputs: Iterable[FileSource] = (),
    machine: _MachineLike | None = None,
) -> None:
    """Write :func:`error_tables_text`."""
    atomic_write_text(path, error_tables_text(tables, inputs, machine))
