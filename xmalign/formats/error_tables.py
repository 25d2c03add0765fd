"""Error-table CSV of FORMATS.md: ``name,position_mm,value,unit,u95[,range]``.

Values are um (translations) or urad (rotations, squareness) in the file and
mm / rad in :class:`ErrorTableSet`. Directional tables carry ``+`` or ``-``
after the name. The optional last column ``range`` says ``measured`` or
``extrapolated`` (beyond the measured stroke); files without it (written
before it existed) are read as all measured (docs/error-tables.md).
"""

from __future__ import annotations

import csv
import math
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from xmalign.errors import FormatError, InputError
from xmalign.formats.common import atomic_write_text
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
    """All tables of an error CSV, keyed by file name (``EXX``, ``EXX+``, ``EC0Y``)."""

    tables: dict[str, Table] = field(default_factory=dict)
    squareness: dict[str, tuple[float, float]] = field(default_factory=dict)

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


def _validate_name(name: str, where: str) -> str:
    base = name.rstrip("+-")
    if base not in MOTION_NAMES and base not in SQUARENESS_NAMES or len(name) - len(base) > 1:
        raise InputError(f"{where}: unknown error name '{name}'")
    return base


def _measured(text: str, where: str) -> bool:
    if text not in ("", *RANGES):
        raise InputError(f"{where}: range must be {' or '.join(RANGES)}, not '{text}'")
    return text != "extrapolated"


def read_error_tables(path: str | Path) -> ErrorTableSet:
    """Read an error-table CSV; a bad row raises InputError with its line number."""
    path = Path(path)
    try:
        handle = path.open(newline="", encoding="utf-8")
    except OSError as error:
        raise InputError(f"{path}: cannot read ({error.strerror})") from error
    rows: dict[str, list[tuple[float, float, float, bool]]] = defaultdict(list)
    result = ErrorTableSet()
    with handle:
        reader = csv.reader(handle)
        header = tuple(h.strip() for h in next(reader, None) or ())
        if header not in (HEADER, (*HEADER, RANGE_COLUMN)):
            raise FormatError(f"{path}: line 1: header must be {','.join(HEADER)}[,range]")
        for fields in reader:
            if not fields:
                continue
            where = f"{path}: line {reader.line_num}"
            if len(fields) != len(header):
                raise InputError(f"{where}: expected {len(header)} fields, found {len(fields)}")
            name, position, value, unit, u95 = (f.strip() for f in fields[:5])
            measured = _measured(fields[5].strip() if len(fields) > 5 else "", where)
            base = _validate_name(name, where)
            if unit != file_unit(name):
                raise InputError(f"{where}: {name} is in {file_unit(name)}, not '{unit}'")
            try:
                scale = _scale(unit)
                value_n = float(value) / scale
                u95_n = float(u95) / scale if u95 else math.nan
                if base in SQUARENESS_NAMES:
                    result.squareness[name] = (value_n, u95_n)
                else:
                    rows[name].append((float(position), value_n, u95_n, measured))
            except ValueError as error:
                raise InputError(f"{where}: {error}") from error
    for name, entries in rows.items():
        entries.sort()
        data = np.array(entries)
        if np.any(np.diff(data[:, 0]) <= 0):
            raise InputError(f"{path}: {name} has a repeated position")
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
