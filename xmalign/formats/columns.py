"""Large instrument CSVs read as column arrays, in chunks (no object per row).

A tracker stream, or a million tracker points or tracer lengths, is read here:
the rows after the header are split into fields a chunk at a time, each chunk's
text columns converted to numbers at once (numpy), so memory and time grow with
the file, not with Python objects per row. :func:`fast_tracker_file` and
:func:`fast_tracer_file` take the common case (a file with nothing wrong in it)
and answer None at the first thing they would have to explain: the row reader
of :mod:`xmalign.formats.instruments` then reads the file and names the line,
with every check it makes.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import overload

import numpy as np

from xmalign.formats.instruments import (
    GUESS_TAG,
    MAX_COORDINATE_MM,
    PATH_END_COLUMNS,
    TIME_COLUMN,
    TRACER_COLUMNS,
    TRACER_FORMAT,
    TRACKER_COLUMNS,
    TRACKER_FORMAT,
    TracerFile,
    TracerLength,
    TrackerFile,
    TrackerPoint,
    _guess,
)
from xmalign.geometry import Vec

#: Rows converted at once (bounds the memory of the text fields being converted).
CHUNK_ROWS = 100_000
_XYZ = ("x_mm", "y_mm", "z_mm")
_TXYZ = ("tx_mm", "ty_mm", "tz_mm")

Chunk = dict[str, np.ndarray]


@dataclass(frozen=True)
class Table:
    """A CSV's header names, the comments before it (line, text) and the rows' chunks."""

    names: list[str]
    comments: list[tuple[int, str]]
    chunks: Iterator[tuple[np.ndarray, np.ndarray]]


def split_rows(lines: list[str], preamble: str) -> Table | None:
    """The header, the comments before it, and the rows as (text table, line numbers) chunks.

    None where the first line is not ``preamble``, there is no header, or a row
    has another number of fields or quotes (the row reader explains).
    """
    if not lines or lines[0].strip() != preamble:
        return None
    comments = []
    for at, line in enumerate(lines[1:], start=1):
        if not line.strip():
            continue
        if line.lstrip().startswith("#"):
            comments.append((at + 1, line.strip()))
            continue
        names = [name.strip() for name in line.split(",")]
        if '"' in line:
            return None
        return Table(names, comments, _chunks(lines, at + 1, len(names)))
    return None


class _IrregularRowError(Exception):
    """A row the column reader leaves to the row reader."""


def _chunks(lines: list[str], first: int, width: int) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    rows: list[list[str]] = []
    numbers: list[int] = []
    for number, line in enumerate(lines[first:], start=first + 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        fields = line.split(",")
        if len(fields) != width or '"' in line:
            raise _IrregularRowError
        rows.append(fields)
        numbers.append(number)
        if len(rows) == CHUNK_ROWS:
            yield np.array(rows, dtype=str), np.array(numbers)
            rows, numbers = [], []
    if rows:
        yield np.array(rows, dtype=str), np.array(numbers)


def numbers_or_nan(texts: np.ndarray) -> Vec:
    """Floats of a text column; NaN where a field is empty or no number."""
    stripped = np.char.strip(texts)
    try:
        return np.where(np.char.str_len(stripped) == 0, "nan", stripped).astype(float)
    except ValueError:
        return np.array([_float_or_nan(t) for t in stripped])


def _float_or_nan(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        return float("nan")


def whole_or_minus(texts: np.ndarray) -> np.ndarray:
    """Whole numbers >= 0 of a text column; -1 where empty, -2 where no whole number."""
    stripped = np.char.strip(texts)
    empty = np.char.str_len(stripped) == 0
    digits = np.char.isdigit(stripped)
    values = np.full(len(texts), -2, dtype=np.int64)
    values[empty] = -1
    values[digits] = stripped[digits].astype(np.int64)
    return values


def read_table(
    lines: list[str], preamble: str, required: tuple[str, ...], convert: Callable[..., Chunk | None]
) -> tuple[Table, Chunk] | None:
    """Every row converted chunk by chunk (``convert(columns, line_numbers)``), joined.

    None where a chunk cannot be converted, or anything else is irregular.
    """
    table = split_rows(lines, preamble)
    if table is None or any(name not in table.names for name in required):
        return None
    converted = []
    try:
        for texts, numbers in table.chunks:
            chunk = convert({n: texts[:, k] for k, n in enumerate(table.names)}, numbers)
            if chunk is None:
                return None
            converted.append(chunk)
    except _IrregularRowError:
        return None
    if not converted:
        return None
    return table, {key: np.concatenate([c[key] for c in converted]) for key in converted[0]}


def _points(columns: dict[str, np.ndarray], names: tuple[str, ...]) -> Vec | None:
    point = np.stack([numbers_or_nan(columns[n]) for n in names], axis=1)
    ok = np.all(np.isfinite(point)) and np.all(np.abs(point) <= MAX_COORDINATE_MM)
    return point if ok else None


def _common(columns: dict[str, np.ndarray], numbers: np.ndarray) -> Chunk | None:
    """Station, run, index and the commanded point of tracker or tracer rows."""
    station = np.char.strip(columns["station"])
    run = whole_or_minus(columns["run"])
    index = whole_or_minus(columns["index"])
    machine = _points(columns, _XYZ)
    if machine is None or np.any(np.char.str_len(station) == 0) or np.any(run < 0):
        return None
    if np.any(index == -2):
        return None
    time = _optional_column(columns, TIME_COLUMN, len(run))
    if time is None:
        return None
    return {
        "station": station.astype(object),
        "run": run,
        "index": index,
        "machine_mm": machine,
        "time_s": time,
        "line": numbers,
    }


def _optional_column(columns: dict[str, np.ndarray], name: str, n: int) -> Vec | None:
    """An optional number column: NaN where absent or empty; None where a field is no number."""
    if name not in columns:
        return np.full(n, np.nan)
    values = numbers_or_nan(columns[name])
    given = np.char.str_len(np.char.strip(columns[name])) > 0
    return None if np.any(given & ~np.isfinite(values)) else values


def _tracker_chunk(columns: dict[str, np.ndarray], numbers: np.ndarray) -> Chunk | None:
    common = _common(columns, numbers)
    tracker = _points(columns, _TXYZ)
    if common is None or tracker is None:
        return None
    fly = common["index"] == -1
    to = np.full((len(fly), 3), np.nan)
    if np.any(fly):
        if not all(n in columns for n in PATH_END_COLUMNS):
            return None
        ends = _points({n: columns[n][fly] for n in PATH_END_COLUMNS}, PATH_END_COLUMNS)
        if ends is None:
            return None
        to[fly] = ends
    radial = _optional_column(columns, "u_radial_um", len(fly))
    transverse = _optional_column(columns, "u_transverse_um", len(fly))
    if radial is None or transverse is None or np.any(radial <= 0) or np.any(transverse <= 0):
        return None
    return common | {
        "tracker_mm": tracker,
        "to_mm": to,
        "u_radial_um": radial,
        "u_transverse_um": transverse,
    }


def _tracer_chunk(columns: dict[str, np.ndarray], numbers: np.ndarray) -> Chunk | None:
    common = _common(columns, numbers)
    length = numbers_or_nan(columns["length_mm"])
    if common is None or np.any(common["index"] < 0):
        return None
    if not np.all(np.isfinite(length)) or np.any(np.abs(length) > MAX_COORDINATE_MM):
        return None
    return common | {"length_mm": length}


def _unique_keys(columns: Chunk) -> bool:
    """No (station, run, index) twice among the rows with an index."""
    indexed = columns["index"] >= 0
    if not np.any(indexed):
        return True
    keys = np.char.add(
        columns["station"][indexed].astype(str),
        np.char.add("\x00", np.char.add(columns["run"][indexed].astype(str), "\x00")),
    )
    keys = np.char.add(keys, columns["index"][indexed].astype(str))
    return len(np.unique(keys)) == len(keys)


def _cut_off(text: str, lines: list[str]) -> bool:
    return bool(lines) and not text.endswith(("\n", "\r")) and not lines[-1].startswith("#")


class PointRows(Sequence[TrackerPoint]):
    """Tracker points held as columns; a :class:`TrackerPoint` is made only when asked for."""

    def __init__(self, columns: Chunk) -> None:
        self.columns = columns

    def __len__(self) -> int:
        return len(self.columns["run"])

    def _point(self, i: int) -> TrackerPoint:
        c = self.columns
        index = int(c["index"][i])
        return TrackerPoint(
            station=str(c["station"][i]),
            run=int(c["run"][i]),
            index=None if index < 0 else index,
            machine_mm=c["machine_mm"][i].copy(),
            tracker_mm=c["tracker_mm"][i].copy(),
            to_mm=None if index >= 0 else c["to_mm"][i].copy(),
            time_s=_maybe(c["time_s"][i]),
            u_radial_um=_maybe(c["u_radial_um"][i]),
            u_transverse_um=_maybe(c["u_transverse_um"][i]),
        )

    @overload
    def __getitem__(self, i: int) -> TrackerPoint: ...
    @overload
    def __getitem__(self, i: slice) -> list[TrackerPoint]: ...
    def __getitem__(self, i: int | slice) -> TrackerPoint | list[TrackerPoint]:
        if isinstance(i, slice):
            return [self._point(k) for k in range(len(self))[i]]
        return self._point(range(len(self))[i])


class LengthRows(Sequence[TracerLength]):
    """Tracer lengths held as columns; a :class:`TracerLength` is made only when asked for."""

    def __init__(self, columns: Chunk) -> None:
        self.columns = columns

    def __len__(self) -> int:
        return len(self.columns["run"])

    def _length(self, i: int) -> TracerLength:
        c = self.columns
        return TracerLength(
            station=str(c["station"][i]),
            run=int(c["run"][i]),
            index=int(c["index"][i]),
            machine_mm=c["machine_mm"][i].copy(),
            length_mm=float(c["length_mm"][i]),
            time_s=_maybe(c["time_s"][i]),
        )

    @overload
    def __getitem__(self, i: int) -> TracerLength: ...
    @overload
    def __getitem__(self, i: slice) -> list[TracerLength]: ...
    def __getitem__(self, i: int | slice) -> TracerLength | list[TracerLength]:
        if isinstance(i, slice):
            return [self._length(k) for k in range(len(self))[i]]
        return self._length(range(len(self))[i])


def _maybe(value: float) -> float | None:
    return None if np.isnan(value) else float(value)


def fast_tracker_file(text: str, source: str) -> TrackerFile | None:
    """A tracker-points file as columns; None at anything the row reader must explain."""
    lines = text.splitlines()
    read = (
        None
        if _cut_off(text, lines)
        else read_table(lines, TRACKER_FORMAT, TRACKER_COLUMNS, _tracker_chunk)
    )
    if read is None or not _unique_keys(read[1]):
        return None
    table, columns = read
    return TrackerFile(PointRows(columns), source, [c for _, c in table.comments])  # type: ignore[arg-type]


def fast_tracer_file(text: str, source: str) -> TracerFile | None:
    """A tracer-lengths file as columns (with its pivot guesses); None as for the tracker."""
    lines = text.splitlines()
    read = (
        None
        if _cut_off(text, lines)
        else read_table(lines, TRACER_FORMAT, TRACER_COLUMNS, _tracer_chunk)
    )
    if read is None or not _unique_keys(read[1]):
        return None
    table, columns = read
    result = TracerFile(LengthRows(columns), source)  # type: ignore[arg-type]
    for number, comment in table.comments:
        if comment.startswith(GUESS_TAG.strip()) and "guess_mm=" in comment:
            name, guess = _guess(comment, source, number)
            result.guesses_mm[name] = guess
        else:
            result.comments.append(comment)
    return result
