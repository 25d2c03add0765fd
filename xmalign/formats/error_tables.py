"""Error-table CSV of docs/formats.md: ``name,position_mm,value,unit,u95[,range]``.

Values are um (translations) or urad (rotations, squareness) in the file and
mm / rad in :class:`ErrorTableSet`. Directional tables carry ``+`` or ``-``
after the name. The optional last column ``range`` says ``measured`` or
``extrapolated`` (beyond the measured stroke); files without it (written
before it existed) are read as all measured (docs/post.md, "The range column").
"""

from __future__ import annotations

import csv
import io
import math
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

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
from xmalign.geometry import Vec
from xmalign.rigid_body import MOTION_NAMES, SQUARENESS_NAMES, ErrorTables

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


@dataclass
class ErrorTableSet:
    """All tables of an error CSV, keyed by file name (``EXX``, ``EXX+``, ``EC0Y``).

    ``source`` names the file they were read from (for messages).
    """

    tables: dict[str, Table] = field(default_factory=dict)
    squareness: dict[str, tuple[float, float]] = field(default_factory=dict)
    source: str = "the error tables"

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


def read_error_tables(path: str | Path) -> ErrorTableSet:
    """Read an error-table CSV; a bad or repeated row raises InputError with its line number."""
    path = Path(path)
    reader = csv.reader(io.StringIO(read_text(path), newline=""))
    try:
        header = tuple(h.strip() for h in next(reader, None) or ())
        if header not in (HEADER, (*HEADER, RANGE_COLUMN)):
            raise FormatError(
                located(path, "line 1", f"header must be {','.join(HEADER)}[,{RANGE_COLUMN}]")
            )
        rows: dict[str, list[tuple[float, float, float, bool]]] = defaultdict(list)
        first_line: dict[tuple[str, float | None], int] = {}
        result = ErrorTableSet(source=str(path))
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
    return result


def _number(value: float) -> str:
    return "" if not math.isfinite(value) else f"{value:.4f}"


def error_tables_to_csv(tables: ErrorTableSet) -> str:
    lines = [",".join((*HEADER, RANGE_COLUMN))]
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


def write_error_tables(path: str | Path, tables: ErrorTableSet) -> None:
    atomic_write_text(path, error_tables_to_csv(tables))
