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
    MATERIAL_COLUMN,
    MAX_COORDINATE_MM,
    PATH_END_COLUMNS,
    SMR_COLUMN,
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
    """Station, run, index, the commanded point, time, SMR position (None: the machine
    file's ``smr_offset_mm``) and material temperature of tracker or tracer rows."""
    station = np.char.strip(columns["station"])
    run = whole_or_minus(columns["run"])
    index = whole_or_minus(columns["index"])
    machine = _points(columns, _XYZ)
    if machine is None or np.any(np.char.str_len(station) == 0) or np.any(run < 0):
        return None
    if np.any(index == -2):
        return None
    time = _optional_column(columns, TIME_COLUMN, len(run))
    material = _optional_column(columns, MATERIAL_COLUMN, len(run))
    if time is None or material is None:
        return None
    smr = np.full(len(run), None, dtype=object)
    if SMR_COLUMN in columns:
        names = np.char.strip(columns[SMR_COLUMN])
        given = np.char.str_len(names) > 0
        smr[given] = names[given].astype(object)
    return {
        "station": station.astype(object),
        "run": run,
        "index": index,
        "machine_mm": machine,
        "time_s": time,
        "smr": smr,
        "material_c": material,
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
    """No (station, run, smr, index) twice among the rows with an index."""
    indexed = columns["index"] >= 0
    if not np.any(indexed):
        return True
    smr = np.where(columns["smr"][indexed] == None, "", columns["smr"][indexed])  # noqa: E711
    keys = columns["station"][indexed].astype(str)
    for part in (columns["run"][indexed], smr, columns["index"][indexed]):
        keys = np.char.add(np.char.add(keys, "\x00"), part.astype(str))
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
            smr=c["smr"][i],
            material_c=_maybe(c["material_c"][i]),
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
            smr=c["smr"][i],
            material_c=_maybe(c["material_c"][i]),
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
    comments = [c for _, c in table.comments]
    lines = columns["line"].tolist()
    return TrackerFile(PointRows(columns), source, comments, lines)  # type: ignore[arg-type]


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
    result = TracerFile(LengthRows(columns), source, lines=columns["line"].tolist())  # type: ignore[arg-type]
    for number, comment in table.comments:
        if comment.startswith(GUESS_TAG.strip()) and "guess_mm=" in comment:
            name, guess = _guess(comment, source, number)
            result.guesses_mm[name] = guess
        else:
            result.comments.append(comment)
    return result


def tracker_columns(file: TrackerFile) -> Chunk:
    """A file's points as columns (read as columns, or gathered from its points): station,
    run, index (-1 on the fly), machine_mm, tracker_mm, to_mm (NaN at a standstill),
    u_radial_um, u_transverse_um, material_c (NaN: not given) and smr (None: not given)."""
    if isinstance(file.points, PointRows):
        return file.points.columns
    points = file.points
    nan3 = np.full(3, np.nan)
    return {
        "station": np.array([p.station for p in points], dtype=object),
        "run": np.array([p.run for p in points], dtype=int),
        "index": np.array([-1 if p.index is None else p.index for p in points], dtype=int),
        "machine_mm": np.reshape([p.machine_mm for p in points], (-1, 3)),
        "tracker_mm": np.reshape([p.tracker_mm for p in points], (-1, 3)),
        "to_mm": np.reshape([nan3 if p.to_mm is None else p.to_mm for p in points], (-1, 3)),
        "u_radial_um": _floats([p.u_radial_um for p in points]),
        "u_transverse_um": _floats([p.u_transverse_um for p in points]),
        "material_c": _floats([p.material_c for p in points]),
        "smr": _names([p.smr for p in points]),
    }


def tracer_columns(file: TracerFile) -> Chunk:
    """A file's lengths as columns (as :func:`tracker_columns`): station, run, index,
    machine_mm, length_mm, material_c and smr."""
    if isinstance(file.lengths, LengthRows):
        return file.lengths.columns
    lengths = file.lengths
    return {
        "station": np.array([r.station for r in lengths], dtype=object),
        "run": np.array([r.run for r in lengths], dtype=int),
        "index": np.array([r.index for r in lengths], dtype=int),
        "machine_mm": np.reshape([r.machine_mm for r in lengths], (-1, 3)),
        "length_mm": np.array([r.length_mm for r in lengths], dtype=float),
        "material_c": _floats([r.material_c for r in lengths]),
        "smr": _names([r.smr for r in lengths]),
    }


def _floats(values: Sequence[float | None]) -> Vec:
    return np.array([np.nan if v is None else v for v in values], dtype=float)


def _names(values: Sequence[str | None]) -> np.ndarray:
    names = np.empty(len(values), dtype=object)
    names[:] = values
    return names
