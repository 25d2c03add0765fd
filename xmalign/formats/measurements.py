"""Measurement CSV of FORMATS.md (output of ``run``, input of ``post``).

Rows are appended and flushed one at a time, so an interrupted run loses
nothing; the reader names the line of any row it cannot parse.
"""

from __future__ import annotations

import csv
import math
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import numpy as np

from xmalign.errors import FormatError, InputError
from xmalign.geometry import Vec
from xmalign.roles import CHANNELS

HEADER = (
    "line",
    "run",
    "direction",
    "index",
    "target_mm",
    "x_mm",
    "y_mm",
    "z_mm",
    *CHANNELS,
)


@dataclass(frozen=True)
class MeasurementRow:
    """One captured point: ``machine_mm`` (3,) commanded, ``channels`` (6,) um / urad."""

    line: str
    run: int
    direction: str
    index: int
    target_mm: float
    machine_mm: Vec
    channels: Vec

    def key(self) -> tuple[str, int, str, int]:
        """What identifies a point of a plan (for resuming)."""
        return (self.line, self.run, self.direction, self.index)

    def as_fields(self) -> list[str]:
        return [
            self.line,
            str(self.run),
            self.direction,
            str(self.index),
            repr(float(self.target_mm)),
            *(repr(float(v)) for v in self.machine_mm),
            *(f"{float(v):.6g}" for v in self.channels),
        ]


def _parse_row(fields: list[str], where: str) -> MeasurementRow:
    if len(fields) != len(HEADER):
        raise InputError(f"{where}: expected {len(HEADER)} fields, found {len(fields)}")
    line, run, direction, index, *numbers = fields
    if direction not in ("+", "-"):
        raise InputError(f"{where}: direction must be '+' or '-', not '{direction}'")
    try:
        run_n, index_n = int(run), int(index)
        values = [float(v) for v in numbers]
    except ValueError as error:
        raise InputError(f"{where}: {error}") from error
    if not all(math.isfinite(v) for v in values):
        raise InputError(f"{where}: a value is not a finite number")
    if not line:
        raise InputError(f"{where}: empty line id")
    return MeasurementRow(
        line=line,
        run=run_n,
        direction=direction,
        index=index_n,
        target_mm=values[0],
        machine_mm=np.array(values[1:4]),
        channels=np.array(values[4:]),
    )


def read_measurements(path: str | Path) -> list[MeasurementRow]:
    """Every row of a measurement CSV; a bad row raises InputError with its line number."""
    path = Path(path)
    try:
        handle = path.open(newline="", encoding="utf-8")
    except OSError as error:
        raise InputError(f"{path}: cannot read ({error.strerror})") from error
    with handle:
        reader = csv.reader(handle)
        header = next(reader, None)
        if header is None or tuple(h.strip() for h in header) != HEADER:
            raise FormatError(f"{path}: line 1: header must be {','.join(HEADER)}")
        return [
            _parse_row([f.strip() for f in fields], f"{path}: line {reader.line_num}")
            for fields in reader
            if fields
        ]


class MeasurementWriter:
    """Appends rows to a measurement CSV, flushing and syncing each one.

    Opening an existing file keeps its rows (for ``--resume``); a new file gets
    the header.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fresh = not self.path.exists() or self.path.stat().st_size == 0
        self._handle: TextIO = self.path.open("a", newline="", encoding="utf-8")
        self._writer = csv.writer(self._handle, lineterminator="\n")
        if fresh:
            self._writer.writerow(HEADER)
            self._sync()

    def _sync(self) -> None:
        self._handle.flush()
        os.fsync(self._handle.fileno())

    def append(self, row: MeasurementRow) -> None:
        self._writer.writerow(row.as_fields())
        self._sync()

    def close(self) -> None:
        self._handle.close()

    def __enter__(self) -> MeasurementWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def write_measurements(path: str | Path, rows: Iterable[MeasurementRow]) -> None:
    """Write a whole measurement CSV (replacing any file there)."""
    Path(path).unlink(missing_ok=True)
    with MeasurementWriter(path) as writer:
        for row in rows:
            writer.append(row)


def rows_of_line(rows: Iterable[MeasurementRow], line_id: str) -> Iterator[MeasurementRow]:
    return (row for row in rows if row.line == line_id)
