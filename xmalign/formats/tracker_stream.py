"""Laser-tracker streams (CSV, docs/formats.md): what a tracker logs while the machine runs.

First line ``# xmalign tracker-stream/1``, optional ``#`` comment lines, a header
``station,run,time_s,tx_mm,ty_mm,tz_mm`` (optional ``u_radial_um,u_transverse_um``;
columns in any order, unknown ones ignored) and one row per sample. A stream
holds hundreds of thousands of rows: it is read in chunks into column arrays
(no object per row); a row that cannot be used is refused with the file and
its line number.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from xmalign.errors import InputError
from xmalign.formats.common import atomic_write_text, line_error, read_text
from xmalign.formats.instruments import (
    MAX_COORDINATE_MM,
    PATH_END_COLUMNS,
    TIME_COLUMN,
    TRACKER_COLUMNS,
    TRACKER_FORMAT,
    UNCERTAINTY_COLUMNS,
    _provenance,
)
from xmalign.formats.provenance import FileSource
from xmalign.formats.spatial_analyzer import ListedPoint
from xmalign.geometry import Vec

STREAM_FORMAT = "# xmalign tracker-stream/1"
STREAM_COLUMNS = ("station", "run", "time_s", "tx_mm", "ty_mm", "tz_mm")
_NUMBERS = ("time_s", "tx_mm", "ty_mm", "tz_mm")
#: Rows converted at once (bounds the memory of the text fields being converted).
_CHUNK_ROWS = 100_000


@dataclass(frozen=True)
class StreamRun:
    """The samples of one (station, run) in the file's order.

    ``u_radial_um`` and ``u_transverse_um`` are NaN where the row gives none;
    ``line`` is each sample's line in the file (for messages).
    """

    station: str
    run: int
    time_s: Vec
    tracker_mm: Vec
    u_radial_um: Vec
    u_transverse_um: Vec
    line: np.ndarray


@dataclass
class TrackerStream:
    """A stream file as column arrays, one entry per row."""

    source: str
    station: np.ndarray
    run: np.ndarray
    time_s: Vec
    tracker_mm: Vec
    u_radial_um: Vec
    u_transverse_um: Vec
    line: np.ndarray
    comments: list[str] = field(default_factory=list)

    def runs(self) -> Iterator[StreamRun]:
        """Each (station, run) in the order it first appears."""
        keys = np.char.add(np.char.add(self.station.astype(str), "\x00"), self.run.astype(str))
        _, first, group = np.unique(keys, return_index=True, return_inverse=True)
        for g in np.argsort(first):
            rows = np.flatnonzero(np.ravel(group) == g)
            yield StreamRun(
                station=str(self.station[rows[0]]),
                run=int(self.run[rows[0]]),
                time_s=self.time_s[rows],
                tracker_mm=self.tracker_mm[rows],
                u_radial_um=self.u_radial_um[rows],
                u_transverse_um=self.u_transverse_um[rows],
                line=self.line[rows],
            )


def _header(lines: list[str], source: str) -> tuple[list[str], int, list[str]]:
    """The header's names, its index in ``lines`` and the comments before it."""
    if not lines or lines[0].strip() != STREAM_FORMAT:
        first = lines[0].strip()[:40] if lines else "an empty file"
        raise line_error(source, 1, f"expected '{STREAM_FORMAT}', found '{first}'")
    comments = []
    for number, line in enumerate(lines[1:], start=1):
        if not line.strip():
            continue
        if line.lstrip().startswith("#"):
            comments.append(line.strip())
            continue
        names = [name.strip() for name in next(csv.reader([line]))]
        missing = [name for name in STREAM_COLUMNS if name not in names]
        if missing:
            raise line_error(source, number + 1, f"header lacks column {', '.join(missing)}")
        return names, number, comments
    raise InputError(f"{source}: no header and no samples")


def _numbers(texts: np.ndarray, name: str, lines: np.ndarray, source: str) -> Vec:
    """Floats of a text column; the first one that is no finite number names its line."""
    try:
        values = np.char.strip(texts).astype(float)
    except ValueError:
        values = np.array([_float_or_nan(t) for t in texts])
    bad = ~np.isfinite(values)
    if np.any(bad):
        i = int(np.argmax(bad))
        raise line_error(source, int(lines[i]), f"{name} '{texts[i].strip()}' is not a number")
    return values


def _float_or_nan(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        return float("nan")


def _optional_numbers(texts: np.ndarray, name: str, lines: np.ndarray, source: str) -> Vec:
    """An optional column: NaN where empty, else a number > 0."""
    empty = np.char.str_len(np.char.strip(texts)) == 0
    values = np.full(len(texts), np.nan)
    if np.any(~empty):
        values[~empty] = _numbers(texts[~empty], name, lines[~empty], source)
        if np.any(values[~empty] <= 0):
            i = int(np.flatnonzero(~empty)[np.argmax(values[~empty] <= 0)])
            raise line_error(source, int(lines[i]), f"{name} {values[i]:g} must be > 0")
    return values


def _chunk(rows: list[list[str]], numbers: list[int], names: list[str], source: str) -> dict:
    """Column arrays of rows of fields (all of the header's length)."""
    table = np.array(rows, dtype=str)
    lines = np.array(numbers)
    column = {name: table[:, k] for k, name in enumerate(names)}
    station = np.char.strip(column["station"])
    if np.any(np.char.str_len(station) == 0):
        raise line_error(
            source, int(lines[np.argmax(np.char.str_len(station) == 0)]), "empty station"
        )
    runs = np.char.strip(column["run"])
    whole = np.char.isdigit(runs)
    if not np.all(whole):
        i = int(np.argmax(~whole))
        raise line_error(source, int(lines[i]), f"run '{runs[i]}' is not a whole number >= 0")
    values = {name: _numbers(column[name], name, lines, source) for name in _NUMBERS}
    tracker = np.stack([values["tx_mm"], values["ty_mm"], values["tz_mm"]], axis=1)
    far = np.any(np.abs(tracker) > MAX_COORDINATE_MM, axis=1)
    if np.any(far):
        raise line_error(source, int(lines[np.argmax(far)]), "tx_mm/ty_mm/tz_mm lies beyond 100 m")
    optional = {
        name: _optional_numbers(column[name], name, lines, source)
        if name in column
        else np.full(len(rows), np.nan)
        for name in UNCERTAINTY_COLUMNS
    }
    return {
        "station": station.astype(object),
        "run": runs.astype(int),
        "time_s": values["time_s"],
        "tracker_mm": tracker,
        "u_radial_um": optional["u_radial_um"],
        "u_transverse_um": optional["u_transverse_um"],
        "line": lines,
    }


def read_tracker_stream(path: str | Path) -> TrackerStream:
    """Read a tracker stream; InputError naming the file and line on bad input."""
    source = str(path)
    text = read_text(path)
    lines = text.splitlines()
    if lines and not text.endswith(("\n", "\r")) and not lines[-1].startswith("#"):
        raise line_error(
            source, len(lines), "the last row has no line end: the file was cut off while written"
        )
    names, header_at, comments = _header(lines, source)
    chunks = []
    rows: list[list[str]] = []
    numbers: list[int] = []
    for number, line in enumerate(lines[header_at + 1 :], start=header_at + 2):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        fields = line.split(",") if '"' not in line else next(csv.reader([line]))
        if len(fields) != len(names):
            raise line_error(source, number, f"{len(fields)} fields, the header has {len(names)}")
        rows.append(fields)
        numbers.append(number)
        if len(rows) == _CHUNK_ROWS:
            chunks.append(_chunk(rows, numbers, names, source))
            rows, numbers = [], []
    if rows:
        chunks.append(_chunk(rows, numbers, names, source))
    if not chunks:
        raise InputError(f"{source}: no samples")
    joined = {key: np.concatenate([c[key] for c in chunks]) for key in chunks[0]}
    return TrackerStream(source=source, comments=comments, **joined)


def tracker_stream_text(runs: list[StreamRun], inputs: Iterable[FileSource] = ()) -> str:
    """The CSV text of a stream (the uncertainty columns only where a sample has them)."""
    columns = list(STREAM_COLUMNS)
    with_u = any(np.any(np.isfinite(r.u_radial_um)) for r in runs)
    columns += list(UNCERTAINTY_COLUMNS) if with_u else []
    out = io.StringIO()
    out.write("\n".join([STREAM_FORMAT, *_provenance(STREAM_FORMAT, inputs), ",".join(columns)]))
    out.write("\n")
    for r in runs:
        table = np.column_stack([r.time_s, r.tracker_mm])
        out.write(_run_rows(r, table, "%.5f,%.5f,%.5f,%.5f", with_u))
    return out.getvalue()


def _run_rows(run: StreamRun | FlyRun, table: Vec, row_format: str, with_u: bool) -> str:
    """One (station, run)'s rows: ``station,run,`` then ``table`` (n, k) in ``row_format``,
    and the uncertainty columns where ``with_u`` (an empty field where a value is NaN)."""
    row = f"{run.station.replace('%', '%%')},{run.run},{row_format}"
    if with_u:
        table = np.column_stack([table, run.u_radial_um, run.u_transverse_um])
        row += ",%.4f,%.4f"
    text = io.StringIO()
    np.savetxt(text, table, fmt=row, comments="")
    return text.getvalue().replace(",nan", ",")


@dataclass(frozen=True)
class FlyRun:
    """On-the-fly rows of one (station, run): each sample with its path's commanded ends."""

    station: str
    run: int
    start_mm: Vec
    end_mm: Vec
    tracker_mm: Vec
    time_s: Vec
    u_radial_um: Vec
    u_transverse_um: Vec


def fly_rows_text(runs: list[FlyRun], inputs: Iterable[FileSource] = ()) -> str:
    """Tracker points (docs/formats.md) of on-the-fly rows: empty index, ``to_*``, ``time_s``."""
    columns = [*TRACKER_COLUMNS, *PATH_END_COLUMNS, TIME_COLUMN]
    with_u = any(np.any(np.isfinite(r.u_radial_um)) for r in runs)
    columns += list(UNCERTAINTY_COLUMNS) if with_u else []
    out = io.StringIO()
    out.write("\n".join([TRACKER_FORMAT, *_provenance(TRACKER_FORMAT, inputs), ",".join(columns)]))
    out.write("\n")
    # the index is empty on the fly: ``,`` before the commanded start
    row_format = "," + ",".join(["%.4f"] * 3 + ["%.5f"] * 3 + ["%.4f"] * 3) + ",%.5f"
    for r in runs:
        table = np.column_stack([r.start_mm, r.tracker_mm, r.end_mm, r.time_s])
        out.write(_run_rows(r, table, row_format, with_u))
    return out.getvalue()


def write_fly_rows(path: str | Path, runs: list[FlyRun], inputs: Iterable[FileSource] = ()) -> None:
    atomic_write_text(path, fly_rows_text(runs, inputs))


def program_paths(point_list: Mapping[str, ListedPoint], source: str) -> tuple[Vec, Vec]:
    """The measuring paths of a point list (``path N start``/``end``, SMR in the MCS), in order.

    Returns the starts and the ends, each (P, 3).

    Raises
    ------
    InputError
        A list without paths, or a path without its start or its end.
    """
    numbers = sorted({int(name.split()[1]) for name in point_list if _is_path_end(name)})
    if not numbers:
        raise InputError(
            f"{source}: names no paths ('path N start'/'path N end'); write it with"
            " xmalign program --instrument tracker --on-the-fly --points-out"
        )
    for number in numbers:
        for end in ("start", "end"):
            if f"path {number} {end}" not in point_list:
                raise InputError(f"{source}: path {number} has no '{end}' point")
    starts = np.array([point_list[f"path {n} start"].smr_mm for n in numbers])
    return starts, np.array([point_list[f"path {n} end"].smr_mm for n in numbers])


def _is_path_end(name: str) -> bool:
    parts = name.split()
    return (
        len(parts) == 3
        and parts[0] == "path"
        and parts[1].isdigit()
        and parts[2] in ("start", "end")
    )


def write_tracker_stream(
    path: str | Path, runs: list[StreamRun], inputs: Iterable[FileSource] = ()
) -> None:
    atomic_write_text(path, tracker_stream_text(runs, inputs))
