"""Laser-tracker points and laser-tracer lengths (CSV, docs/formats.md).

Both files start with a format line (``# xmalign tracker-points/1``,
``# xmalign tracer-lengths/1``), then optional ``#`` comment lines (xmalign
writes its provenance there; a tracer file may name a coarse pivot guess with
``# station NAME guess_mm=x,y,z``), a header line and one row per reading.
Columns may come in any order; columns the reader does not know are ignored.
A row that cannot be used is refused with the file and its line number.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import TypeVar

import numpy as np

import xmalign
from xmalign.errors import InputError
from xmalign.formats.common import atomic_write_text, line_error, os_problem
from xmalign.geometry import Vec

TRACKER_FORMAT = "# xmalign tracker-points/1"
TRACER_FORMAT = "# xmalign tracer-lengths/1"
TRACKER_COLUMNS = ("station", "run", "index", "x_mm", "y_mm", "z_mm", "tx_mm", "ty_mm", "tz_mm")
TRACER_COLUMNS = ("station", "run", "index", "x_mm", "y_mm", "z_mm", "length_mm")
PATH_END_COLUMNS = ("to_x_mm", "to_y_mm", "to_z_mm")
UNCERTAINTY_COLUMNS = ("u_radial_um", "u_transverse_um")
TIME_COLUMN = "time_s"
#: Optional columns of both files: the SMR position's name, the scale temperature.
SMR_COLUMN = "smr"
MATERIAL_COLUMN = "material_c"
GUESS_TAG = "# station "
#: No machine or tracker reaches farther, mm.
MAX_COORDINATE_MM = 100_000.0


@dataclass(frozen=True)
class TrackerPoint:
    """One SMR position as a laser tracker reports it.

    Attributes
    ----------
    station, run, index
        The tracker's place, the repeat and the commanded point (None: on the fly).
    machine_mm : ndarray, shape (3,)
        Commanded CNC tool point (the start of the path for a point on the fly).
    tracker_mm : ndarray, shape (3,)
        SMR centre in the tracker's frame, mm.
    to_mm : ndarray, shape (3,), optional
        End of the commanded straight path (points on the fly only).
    time_s : float, optional
    u_radial_um, u_transverse_um : float, optional
        The row's own standard uncertainty along and across the beam.
    smr : str, optional
        The SMR position (a key of the machine file's ``smr_offsets_mm``).
    material_c : float, optional
        The machine's scale temperature, degC.
    """

    station: str
    run: int
    index: int | None
    machine_mm: Vec
    tracker_mm: Vec
    to_mm: Vec | None = None
    time_s: float | None = None
    u_radial_um: float | None = None
    u_transverse_um: float | None = None
    smr: str | None = None
    material_c: float | None = None

    @property
    def on_the_fly(self) -> bool:
        return self.index is None


@dataclass(frozen=True)
class TracerLength:
    """One laser-tracer reading: pivot-to-SMR distance plus the (station, run) constant, mm.

    ``smr`` and ``material_c`` as for :class:`TrackerPoint`.
    """

    station: str
    run: int
    index: int
    machine_mm: Vec
    length_mm: float
    time_s: float | None = None
    smr: str | None = None
    material_c: float | None = None


@dataclass
class TrackerFile:
    """Tracker points and where they came from (``lines``: each point's line, when read)."""

    points: list[TrackerPoint]
    source: str
    comments: list[str] = field(default_factory=list)
    lines: list[int] = field(default_factory=list)


@dataclass
class TracerFile:
    """Tracer lengths and where they came from (``lines``: each length's line, when read)."""

    lengths: list[TracerLength]
    source: str
    guesses_mm: dict[str, Vec] = field(default_factory=dict)
    comments: list[str] = field(default_factory=list)
    lines: list[int] = field(default_factory=list)


Row = TypeVar("Row")


def _number(values: Mapping[str, str], name: str, problem: Callable[[str], InputError]) -> float:
    text = values.get(name, "").strip()
    try:
        value = float(text)
    except ValueError as error:
        raise problem(f"{name} '{text}' is not a number") from error
    if not math.isfinite(value):
        raise problem(f"{name} is {text}, not a finite number")
    return value


def _optional(
    values: Mapping[str, str], name: str, problem: Callable[[str], InputError]
) -> float | None:
    return None if not values.get(name, "").strip() else _number(values, name, problem)


def _whole(values: Mapping[str, str], name: str, problem: Callable[[str], InputError]) -> int:
    text = values.get(name, "").strip()
    if not text.isdigit():
        raise problem(f"{name} '{text}' is not a whole number >= 0")
    return int(text)


def _point(
    values: Mapping[str, str], names: tuple[str, ...], problem: Callable[[str], InputError]
) -> Vec:
    point = np.array([_number(values, name, problem) for name in names])
    if np.any(np.abs(point) > MAX_COORDINATE_MM):
        raise problem(f"{'/'.join(names)} {point.tolist()} lies beyond 100 m")
    return point


def _station(values: Mapping[str, str], problem: Callable[[str], InputError]) -> str:
    station = values.get("station", "").strip()
    if not station:
        raise problem("empty station")
    return station


def _read_text(path: Path) -> str:
    try:
        data = path.read_bytes()
    except OSError as error:
        raise InputError(f"{path}: {os_problem(error)}") from error
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as error:
        line = data[: error.start].count(b"\n") + 1
        raise line_error(path, line, "not UTF-8 text") from error


def _parse(
    text: str,
    source: str,
    preamble: str,
    columns: tuple[str, ...],
    parse_row: Callable[[Mapping[str, str], Callable[[str], InputError]], Row],
    on_comment: Callable[[str, int], None],
) -> list[int]:
    """Rows of a CSV with a format line, comments and a header; checks every line.

    Returns the line number of each row, in order.
    """
    lines = text.splitlines()
    if lines and text and not text.endswith(("\n", "\r")) and not lines[-1].startswith("#"):
        raise line_error(
            source, len(lines), "the last row has no line end: the file was cut off while written"
        )
    if not lines or lines[0].strip() != preamble:
        first = lines[0].strip()[:40] if lines else "an empty file"
        raise line_error(source, 1, f"expected '{preamble}', found '{first}'")
    header: list[str] | None = None
    seen: dict[tuple[object, ...], int] = {}
    numbers: list[int] = []
    for number, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        if line.lstrip().startswith("#"):
            if header is None:
                on_comment(line.strip(), number)
            continue
        fields = next(csv.reader([line]))
        if header is None:
            header = [name.strip() for name in fields]
            missing = [name for name in columns if name not in header]
            if missing:
                raise line_error(source, number, f"header lacks column {', '.join(missing)}")
            continue

        def problem(text: str, number: int = number) -> InputError:
            return line_error(source, number, text)

        if len(fields) != len(header):
            raise problem(f"{len(fields)} fields, the header has {len(header)}")
        row = parse_row(dict(zip(header, fields, strict=True)), problem)
        key = _key(row)
        if key in seen:
            raise problem(f"repeats the reading of line {seen[key]} (station, run, smr, index)")
        seen[key] = number
        numbers.append(number)
    if not numbers:
        raise InputError(f"{source}: no readings")
    return numbers


def _key(row: object) -> tuple[object, ...]:
    index = getattr(row, "index", None)
    if index is None:  # points on the fly are told apart by their path and order
        return (id(row),)
    fields = ("station", "run", "smr")  # one index may be measured with each SMR position
    return (*(getattr(row, name, None) for name in fields), index)


def _tracker_row(values: Mapping[str, str], problem: Callable[[str], InputError]) -> TrackerPoint:
    station = _station(values, problem)
    run = _whole(values, "run", problem)
    index = None if not values["index"].strip() else _whole(values, "index", problem)
    to_mm = None
    if index is None:
        if any(not values.get(name, "").strip() for name in PATH_END_COLUMNS):
            raise problem("a point on the fly (empty index) needs to_x_mm, to_y_mm, to_z_mm")
        to_mm = _point(values, PATH_END_COLUMNS, problem)
    radial = _optional(values, "u_radial_um", problem)
    transverse = _optional(values, "u_transverse_um", problem)
    for name, value in (("u_radial_um", radial), ("u_transverse_um", transverse)):
        if value is not None and value <= 0:
            raise problem(f"{name} {value:g} must be > 0")
    return TrackerPoint(
        station=station,
        run=run,
        index=index,
        machine_mm=_point(values, ("x_mm", "y_mm", "z_mm"), problem),
        tracker_mm=_point(values, ("tx_mm", "ty_mm", "tz_mm"), problem),
        to_mm=to_mm,
        time_s=_optional(values, TIME_COLUMN, problem),
        u_radial_um=radial,
        u_transverse_um=transverse,
        smr=values.get(SMR_COLUMN, "").strip() or None,
        material_c=_optional(values, MATERIAL_COLUMN, problem),
    )


def _tracer_row(values: Mapping[str, str], problem: Callable[[str], InputError]) -> TracerLength:
    station = _station(values, problem)
    run = _whole(values, "run", problem)
    if not values["index"].strip():
        raise problem("a tracer length needs an index (on the fly is for tracker points)")
    length = _number(values, "length_mm", problem)
    if abs(length) > MAX_COORDINATE_MM:
        raise problem(f"length_mm {length:g} lies beyond 100 m")
    return TracerLength(
        station=station,
        run=run,
        index=_whole(values, "index", problem),
        machine_mm=_point(values, ("x_mm", "y_mm", "z_mm"), problem),
        length_mm=length,
        time_s=_optional(values, TIME_COLUMN, problem),
        smr=values.get(SMR_COLUMN, "").strip() or None,
        material_c=_optional(values, MATERIAL_COLUMN, problem),
    )


def _collect(rows: list[Row], parse_row: Callable[..., Row]) -> Callable[..., Row]:
    def parse_and_keep(values: Mapping[str, str], problem: Callable[[str], InputError]) -> Row:
        row = parse_row(values, problem)
        rows.append(row)
        return row

    return parse_and_keep


def read_tracker_points(path: str | Path) -> TrackerFile:
    """Read a tracker-points file; InputError naming the file and line on bad input."""
    path = Path(path)
    comments: list[str] = []
    points: list[TrackerPoint] = []
    lines = _parse(
        _read_text(path),
        str(path),
        TRACKER_FORMAT,
        TRACKER_COLUMNS,
        _collect(points, _tracker_row),
        lambda text, number: comments.append(text),
    )
    return TrackerFile(points, str(path), comments, lines)


def read_tracer_lengths(path: str | Path) -> TracerFile:
    """Read a tracer-lengths file; InputError naming the file and line on bad input."""
    path = Path(path)
    result = TracerFile([], str(path))

    def comment(text: str, number: int) -> None:
        if text.startswith(GUESS_TAG.strip()) and "guess_mm=" in text:
            name, guess = _guess(text, str(path), number)
            result.guesses_mm[name] = guess
        else:
            result.comments.append(text)

    result.lines = _parse(
        _read_text(path),
        str(path),
        TRACER_FORMAT,
        TRACER_COLUMNS,
        _collect(result.lengths, _tracer_row),
        comment,
    )
    return result


def _guess(text: str, source: str, number: int) -> tuple[str, Vec]:
    """``# station NAME guess_mm=x,y,z`` -> (NAME, guess)."""
    parts = text[len(GUESS_TAG.strip()) :].split()
    if len(parts) != 2 or not parts[1].startswith("guess_mm="):
        raise line_error(source, number, "expected '# station NAME guess_mm=x,y,z'")
    values = parts[1][len("guess_mm=") :].split(",")
    try:
        guess = np.array([float(v) for v in values])
    except ValueError as error:
        raise line_error(source, number, f"guess_mm '{parts[1][9:]}' is not x,y,z") from error
    if len(guess) != 3 or not np.all(np.isfinite(guess)):
        raise line_error(source, number, f"guess_mm '{parts[1][9:]}' is not three numbers")
    return parts[0], guess


def _provenance(inputs: Mapping[str, str]) -> list[str]:
    time = datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    lines = [f"# software xmalign {xmalign.__version__} written {time}"]
    lines += [f"# input {name} sha256={digest}" for name, digest in inputs.items()]
    return lines


def _number_text(value: float) -> str:
    return repr(float(value))


def tracker_points_text(points: list[TrackerPoint], inputs: Mapping[str, str] | None = None) -> str:
    """The CSV text of tracker points (extra columns only where a point uses them)."""
    columns = list(TRACKER_COLUMNS)
    if any(p.to_mm is not None for p in points):
        columns += PATH_END_COLUMNS
    if any(p.time_s is not None for p in points):
        columns.append(TIME_COLUMN)
    if any(p.u_radial_um is not None or p.u_transverse_um is not None for p in points):
        columns += UNCERTAINTY_COLUMNS
    columns += _optional_columns(points)
    out = io.StringIO()
    out.write("\n".join([TRACKER_FORMAT, *_provenance(inputs or {}), ",".join(columns)]) + "\n")
    writer = csv.writer(out, lineterminator="\n")
    for p in points:
        values = {
            "station": p.station,
            "run": str(p.run),
            "index": "" if p.index is None else str(p.index),
            **dict(zip(("x_mm", "y_mm", "z_mm"), map(_number_text, p.machine_mm), strict=True)),
            **dict(zip(("tx_mm", "ty_mm", "tz_mm"), map(_number_text, p.tracker_mm), strict=True)),
        }
        if p.to_mm is not None:
            values.update(zip(PATH_END_COLUMNS, map(_number_text, p.to_mm), strict=True))
        for name, value in (
            (TIME_COLUMN, p.time_s),
            ("u_radial_um", p.u_radial_um),
            ("u_transverse_um", p.u_transverse_um),
        ):
            if value is not None:
                values[name] = _number_text(value)
        values.update(_optional_values(p))
        writer.writerow([values.get(name, "") for name in columns])
    return out.getvalue()


def tracer_lengths_text(
    lengths: list[TracerLength],
    guesses_mm: Mapping[str, Vec] | None = None,
    inputs: Mapping[str, str] | None = None,
) -> str:
    """The CSV text of tracer lengths, with the pivot guesses as ``# station`` lines."""
    columns = list(TRACER_COLUMNS)
    if any(length.time_s is not None for length in lengths):
        columns.append(TIME_COLUMN)
    columns += _optional_columns(lengths)
    guesses = [
        f"{GUESS_TAG}{name} guess_mm={','.join(_number_text(v) for v in guess)}"
        for name, guess in (guesses_mm or {}).items()
    ]
    out = io.StringIO()
    out.write(
        "\n".join([TRACER_FORMAT, *_provenance(inputs or {}), *guesses, ",".join(columns)]) + "\n"
    )
    writer = csv.writer(out, lineterminator="\n")
    for r in lengths:
        row = [r.station, str(r.run), str(r.index), *map(_number_text, r.machine_mm)]
        row.append(_number_text(r.length_mm))
        if TIME_COLUMN in columns:
            row.append("" if r.time_s is None else _number_text(r.time_s))
        extra = _optional_values(r)
        row += [extra.get(name, "") for name in columns[len(row) :]]
        writer.writerow(row)
    return out.getvalue()


def _optional_columns(rows: list[TrackerPoint] | list[TracerLength]) -> list[str]:
    """The SMR and material columns, where a row uses them."""
    return [
        name
        for name, used in (
            (SMR_COLUMN, any(r.smr is not None for r in rows)),
            (MATERIAL_COLUMN, any(r.material_c is not None for r in rows)),
        )
        if used
    ]


def _optional_values(row: TrackerPoint | TracerLength) -> dict[str, str]:
    values = {} if row.smr is None else {SMR_COLUMN: row.smr}
    if row.material_c is not None:
        values[MATERIAL_COLUMN] = _number_text(row.material_c)
    return values


def write_tracker_points(
    path: str | Path, points: list[TrackerPoint], inputs: Mapping[str, str] | None = None
) -> None:
    atomic_write_text(path, tracker_points_text(points, inputs))


def write_tracer_lengths(
    path: str | Path,
    lengths: list[TracerLength],
    guesses_mm: Mapping[str, Vec] | None = None,
    inputs: Mapping[str, str] | None = None,
) -> None:
    atomic_write_text(path, tracer_lengths_text(lengths, guesses_mm, inputs))
