"""Measurement CSV of docs/formats.md (output of ``run``, input of ``post``).

Rows are appended, flushed and synced one at a time, so an interrupted run
loses nothing; the reader names the line of any row it cannot use. Besides the
columns of docs/formats.md a file written by ``xmalign run`` carries (see
docs/measurement-files.md):

- a first comment line ``# xmalign measurements plan_identity=<hex>``, the
  identity of the plan the points were measured for (:func:`plan_sha256`, the
  SHA-256 of the plan's canonical content, not of the plan file's bytes: that one
  is the ``# input plan:`` line of the history; ``--resume`` refuses a file from
  another plan), followed by ``sim_seed=<n>`` for a run on the virtual machine
  (``--resume`` refuses another ``--seed``). Files written before the name was
  changed say ``plan_sha256=<hex>`` for the same identity: read alike;
- a ``segment`` column: 0 for a line's first setup, 1, 2, ... for the rows
  measured after the units had to be re-aligned on a resume (``post`` fits
  each segment with its own setup terms);
- one ``# setup`` comment line per alignment of a line, with the locked unit
  angles (a resume keeps the setup when the units still stand there).

Version 2 (:data:`MEASUREMENTS_FORMAT`) adds, after that first line, the
history preamble of :mod:`xmalign.formats.provenance` (format, software,
``created_utc``, the plan file's SHA-256), a ``time_s`` column (seconds on the
run's clock since the run, or its resumption, started: each start writes a
``# run started_utc=...`` line) and nothing else; version 1 files (no
``# format:`` line, no ``time_s``) are read as they are.

Lines starting with ``#`` are comments for every reader of the file.
"""

from __future__ import annotations

import csv
import errno
import fcntl
import hashlib
import io
import json
import logging
import math
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from xmalign.errors import FormatError, InputError
from xmalign.formats.common import os_problem, refuse_special, sync_folder
from xmalign.formats.plan import Plan, plan_to_dict
from xmalign.formats.provenance import (
    FileSource,
    Provenance,
    csv_preamble,
    now_utc,
    read_csv_preamble,
)
from xmalign.geometry import Vec
from xmalign.roles import CHANNELS

logger = logging.getLogger(__name__)

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
MEASUREMENTS_FORMAT = "xmalign.measurements/2"
#: What a file without a ``# format:`` line is (written before files carried history).
FIRST_FORMAT = "xmalign.measurements/1"
SEGMENT_COLUMN = "segment"
#: Seconds on the run's clock since the run (or its resumption) started.
TIME_COLUMN = "time_s"
#: Optional environment columns of docs/formats.md with the range a workshop can have.
ENVIRONMENT_LIMITS = {
    "air_temp_c": (-20.0, 60.0),
    "air_pressure_hpa": (500.0, 1200.0),
    "air_humidity_percent": (0.0, 100.0),
    "material_temp_c": (-20.0, 80.0),
}
#: xmalign's own: which environment values of the row were held at their last good
#: reading, and why (empty when all were fresh); written with the environment columns.
FLAGS_COLUMN = "environment_flags"
OPTIONAL_COLUMNS = (SEGMENT_COLUMN, TIME_COLUMN, *ENVIRONMENT_LIMITS, FLAGS_COLUMN)
#: What ``xmalign run`` writes.
WRITTEN_COLUMNS = (*HEADER, SEGMENT_COLUMN, TIME_COLUMN)
#: The largest travel a machine can have, mm (commanded points and targets).
MAX_COORDINATE_MM = 100_000.0
#: A recorded point farther than this from its plan target belongs to another plan, mm.
POINT_TOLERANCE_MM = 0.01
PLAN_KEY = "plan_identity"
#: The name :data:`PLAN_KEY` had before (the same identity), read alike.
OLD_PLAN_KEYS = ("plan_sha256",)
SEED_KEY = "sim_seed"
PREAMBLE = "# xmalign measurements"
SETUP_TAG = "# setup"
RUN_START_TAG = "# run started_utc="


@dataclass(frozen=True)
class ChannelLimits:
    """The largest channel values a file may hold: twice the instrument's ranges."""

    linear_um: float
    straightness_um: float
    angle_urad: float

    @classmethod
    def of_ranges(
        cls, max_range_mm: float, straightness_range_um: float, angle_range_urad: float
    ) -> ChannelLimits:
        return cls(2e3 * max_range_mm, 2 * straightness_range_um, 2 * angle_range_urad)


#: Twice the nominal XM-60 ranges (4000 mm, 250 um, 500 urad).
NOMINAL_LIMITS = ChannelLimits.of_ranges(4000.0, 250.0, 500.0)


@dataclass(frozen=True)
class MeasurementRow:
    """One captured point: ``machine_mm`` (3,) commanded, ``channels`` (6,) um / urad.

    ``segment`` numbers the line's setup (0 unless the units were re-aligned on
    a resume); ``environment`` holds the optional environment columns present and
    ``environment_flags`` says which of them were held at their last good value;
    ``time_s`` when the point was captured, s since the run started (None: not recorded).
    """

    line: str
    run: int
    direction: str
    index: int
    target_mm: float
    machine_mm: Vec
    channels: Vec
    segment: int = 0
    environment: Mapping[str, float] = field(default_factory=dict)
    environment_flags: str = ""
    time_s: float | None = None
    #: Line of the file the row was read from (0: not read from a file), for messages.
    file_line: int = field(default=0, compare=False)

    def key(self) -> tuple[str, int, str, int]:
        """What identifies a point of a plan (for resuming)."""
        return (self.line, self.run, self.direction, self.index)

    def fields(self, columns: tuple[str, ...]) -> list[str]:
        """The row's fields under a file's ``columns``."""
        values = dict(
            zip(
                HEADER,
                [
                    self.line,
                    str(self.run),
                    self.direction,
                    str(self.index),
                    repr(float(self.target_mm)),
                    *(repr(float(v)) for v in self.machine_mm),
                    *(f"{float(v):.6g}" for v in self.channels),
                ],
                strict=True,
            )
        )
        values[SEGMENT_COLUMN] = str(self.segment)
        values[TIME_COLUMN] = "" if self.time_s is None else f"{self.time_s:.3f}"
        values.update({name: repr(float(v)) for name, v in self.environment.items()})
        values[FLAGS_COLUMN] = self.environment_flags
        missing = [name for name in columns if name not in values]
        if missing:
            raise InputError(f"row {self.key()} has no value for column {missing[0]}")
        return [values[name] for name in columns]


@dataclass(frozen=True)
class LineSetup:
    """One alignment of a line: the units' angles when they were locked, rad."""

    line: str
    segment: int
    launch_rad: Vec
    receiver_rad: Vec

    def comment(self) -> str:
        def degrees(angles: Vec) -> str:
            return ",".join(repr(float(v)) for v in np.degrees(angles))

        return (
            f"{SETUP_TAG} line={self.line} segment={self.segment}"
            f" launch_deg={degrees(self.launch_rad)} receiver_deg={degrees(self.receiver_rad)}"
        )


@dataclass(frozen=True)
class TornRow:
    """A last line without its line end: the run stopped while writing it."""

    line_number: int
    offset: int
    text: str


@dataclass
class MeasurementFile:
    """Everything a measurement CSV holds."""

    path: Path
    rows: list[MeasurementRow]
    columns: tuple[str, ...] = WRITTEN_COLUMNS
    plan_sha256: str | None = None
    setups: list[LineSetup] = field(default_factory=list)
    torn: TornRow | None = None
    #: The ``--seed`` of a run on the virtual machine (None: a live run, or not recorded).
    sim_seed: int | None = None
    history: Provenance | None = None

    @property
    def environment_columns(self) -> tuple[str, ...]:
        """The environment columns of the file, in its order."""
        return tuple(name for name in self.columns if name in ENVIRONMENT_LIMITS)

    def last_setups(self) -> dict[str, LineSetup]:
        """The latest setup of every line."""
        return {setup.line: setup for setup in self.setups}

    def last_segments(self) -> dict[str, int]:
        """The highest setup segment of every line with rows or a recorded setup."""
        last: dict[str, int] = {}
        for line, segment in [(r.line, r.segment) for r in self.rows] + [
            (s.line, s.segment) for s in self.setups
        ]:
            last[line] = max(segment, last.get(line, segment))
        return last


def plan_sha256(plan: Plan) -> str:
    """The identity of a plan: SHA-256 of its canonical JSON (sorted keys, no spaces)."""
    text = json.dumps(
        plan_to_dict(plan),
        sort_keys=True,
        separators=(",", ":"),
        default=lambda value: np.asarray(value).tolist(),
    )
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _read_bytes(path: Path) -> bytes:
    if path.is_dir():
        raise InputError(f"{path}: is a folder, not a measurement CSV")
    try:
        return path.read_bytes()
    except FileNotFoundError as error:
        raise InputError(f"{path}: no such file") from error
    except OSError as error:
        raise InputError(f"{path}: cannot read: {os_problem(error)}") from error


def _decode(data: bytes, path: Path) -> str:
    """UTF-8 text; a byte-order mark at the start (spreadsheet programs write one) is dropped."""
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as error:
        line = data[: error.start].count(b"\n") + 1
        raise InputError(
            f"{path}: line {line}: not UTF-8 text (byte 0x{data[error.start]:02x})"
        ) from error


class _Reader:
    """Parses the lines of one file, keeping what a row must be checked against."""

    def __init__(self, path: Path, limits: ChannelLimits) -> None:
        self.path = path
        self.limits = limits
        self.file = MeasurementFile(path, [], columns=())
        self.seen: dict[tuple[str, int, str, int], int] = {}
        self.preamble: list[str] = []

    def where(self, number: int) -> str:
        return f"{self.path}: line {number}"

    def comment(self, text: str, number: int) -> None:
        if text.startswith(PREAMBLE) and not self.file.columns:
            for item in text[len(PREAMBLE) :].split():
                key, _, value = item.partition("=")
                if key == PLAN_KEY or key in OLD_PLAN_KEYS:
                    self.file.plan_sha256 = value
                elif key == SEED_KEY:
                    self.file.sim_seed = self._seed(value, number)
        elif text.startswith(SETUP_TAG + " "):
            self.file.setups.append(self._setup(text, number))
        if not self.file.columns:
            self.preamble.append(text)

    def _seed(self, value: str, number: int) -> int:
        if not value.isdigit():
            raise InputError(f"{self.where(number)}: {SEED_KEY} '{value}' is not a seed")
        return int(value)

    def _setup(self, text: str, number: int) -> LineSetup:
        items = dict(item.partition("=")[::2] for item in text[len(SETUP_TAG) :].split())
        try:
            launch = np.radians([float(v) for v in items["launch_deg"].split(",")])
            receiver = np.radians([float(v) for v in items["receiver_deg"].split(",")])
            setup = LineSetup(items["line"], int(items["segment"]), launch, receiver)
        except (KeyError, ValueError) as error:
            raise InputError(f"{self.where(number)}: damaged setup comment") from error
        if launch.shape != (2,) or receiver.shape != (3,) or not np.all(np.isfinite(launch)):
            raise InputError(f"{self.where(number)}: damaged setup comment")
        return setup

    def header(self, fields: list[str], number: int) -> None:
        columns = tuple(f.strip() for f in fields)
        missing = [name for name in HEADER if name not in columns]
        unknown = [name for name in columns if name not in HEADER + OPTIONAL_COLUMNS]
        repeated = [name for name in columns if columns.count(name) > 1]
        if missing or unknown or repeated:
            what = (
                f"missing column '{missing[0]}'"
                if missing
                else f"unknown column '{unknown[0]}'"
                if unknown
                else f"column '{repeated[0]}' appears twice"
            )
            raise FormatError(
                f"{self.where(number)}: {what}; the header must be {','.join(HEADER)}"
                f" (optionally followed by {', '.join(OPTIONAL_COLUMNS)})"
            )
        self.file.history = read_csv_preamble(
            self.preamble, MEASUREMENTS_FORMAT, str(self.path), FIRST_FORMAT
        )
        self.file.columns = columns

    def row(self, fields: list[str], number: int) -> MeasurementRow:
        where = self.where(number)
        columns = self.file.columns
        if len(fields) != len(columns):
            raise InputError(f"{where}: expected {len(columns)} fields, found {len(fields)}")
        values = dict(zip(columns, (f.strip() for f in fields), strict=True))
        row = replace(_parse_row(values, where), file_line=number)
        _check_magnitudes(row, self.limits, where)
        first = self.seen.setdefault(row.key(), number)
        if first != number:
            raise InputError(
                f"{where}: line {row.line} run {row.run} direction {row.direction} index"
                f" {row.index} is recorded twice (first at line {first})"
            )
        return row

    def line(self, text: str, number: int) -> None:
        if not text.strip():
            return
        if text.startswith("#"):
            self.comment(text, number)
            return
        try:
            fields = next(csv.reader([text]))
        except csv.Error as error:  # e.g. a field beyond the csv module's size limit
            raise InputError(f"{self.where(number)}: {error}") from error
        if not self.file.columns:
            self.header(fields, number)
        else:
            self.file.rows.append(self.row(fields, number))


def _number(values: Mapping[str, str], name: str, where: str) -> float:
    try:
        value = float(values[name])
    except ValueError as error:
        raise InputError(f"{where}: {name} '{values[name]}' is not a number") from error
    if not math.isfinite(value):
        raise InputError(f"{where}: {name} is {values[name]}, not a finite number")
    return value


def _integer(values: Mapping[str, str], name: str, where: str) -> int:
    try:
        value = int(values[name])
    except ValueError as error:
        raise InputError(f"{where}: {name} '{values[name]}' is not a whole number") from error
    if value < 0:
        raise InputError(f"{where}: {name} {value} is negative")
    return value


def _parse_row(values: Mapping[str, str], where: str) -> MeasurementRow:
    if not values["line"]:
        raise InputError(f"{where}: empty line id")
    if values["direction"] not in ("+", "-"):
        raise InputError(f"{where}: direction must be '+' or '-', not '{values['direction']}'")
    numbers = {name: _number(values, name, where) for name in HEADER[4:]}
    return MeasurementRow(
        line=values["line"],
        run=_integer(values, "run", where),
        direction=values["direction"],
        index=_integer(values, "index", where),
        target_mm=numbers["target_mm"],
        machine_mm=np.array([numbers[name] for name in ("x_mm", "y_mm", "z_mm")]),
        channels=np.array([numbers[name] for name in CHANNELS]),
        segment=_integer(values, SEGMENT_COLUMN, where) if SEGMENT_COLUMN in values else 0,
        environment={
            name: _number(values, name, where) for name in ENVIRONMENT_LIMITS if name in values
        },
        environment_flags=values.get(FLAGS_COLUMN, ""),
        time_s=_number(values, TIME_COLUMN, where) if values.get(TIME_COLUMN) else None,
    )


def _check_magnitudes(row: MeasurementRow, limits: ChannelLimits, where: str) -> None:
    """Refuse values no machine and no interferometer within its ranges can give."""
    coordinates = np.append(row.machine_mm, row.target_mm)
    if np.any(np.abs(coordinates) > MAX_COORDINATE_MM):
        raise InputError(f"{where}: a position beyond {MAX_COORDINATE_MM / 1e3:.0f} m")
    linear, sv, sw, *angles = row.channels
    checks = (
        (abs(linear), limits.linear_um, "linear_um", "um"),
        (math.hypot(sv, sw), limits.straightness_um, "straightness", "um"),
        (max(abs(a) for a in angles), limits.angle_urad, "an angle", "urad"),
    )
    for value, limit, name, unit in checks:
        if value > limit:
            raise InputError(
                f"{where}: {name} {value:.6g} {unit} is beyond {limit:g} {unit}, twice the"
                " interferometer's range"
            )
    for name, value in row.environment.items():
        low, high = ENVIRONMENT_LIMITS[name]
        if not low <= value <= high:
            raise InputError(f"{where}: {name} {value:g} is outside {low:g} to {high:g}")


def load_measurements(
    path: str | Path, limits: ChannelLimits = NOMINAL_LIMITS, torn_ok: bool = False
) -> MeasurementFile:
    """Read and check a measurement CSV; any refusal is one InputError naming file and line.

    A last line without its line end is a row the run was writing when it
    stopped. With ``torn_ok`` (resuming) it is returned as ``torn`` and not
    parsed; otherwise it is accepted only if it is a complete row.
    """
    path = Path(path)
    data = _read_bytes(path)
    cut = data.rfind(b"\n") + 1
    body, tail = data[:cut], data[cut:]
    reader = _Reader(path, limits)
    lines = _decode(body, path).split("\n")[:-1]
    for number, text in enumerate(lines, start=1):
        reader.line(text.rstrip("\r"), number)
    tail_number = len(lines) + 1
    if tail and torn_ok:
        reader.file.torn = TornRow(tail_number, cut, tail.decode("utf-8", "replace"))
    elif tail:
        try:
            reader.line(_decode(tail, path), tail_number)
        except InputError as error:
            raise InputError(
                f"{error}; the line is cut short (the run stopped while writing it): go on"
                " with `xmalign run --resume`, which drops it and measures the point again"
            ) from error
    if not reader.file.columns and reader.file.torn is None:
        raise FormatError(f"{path}: no header line; expected {','.join(HEADER)}")
    return reader.file


def read_measurements(
    path: str | Path, limits: ChannelLimits = NOMINAL_LIMITS
) -> list[MeasurementRow]:
    """Every row of a measurement CSV; a bad row raises InputError with its line number."""
    return load_measurements(path, limits).rows


def _write_error(path: Path, error: OSError) -> InputError:
    return InputError(f"{path}: cannot write ({os_problem(error)})")


class RunLock:
    """An exclusive lock on a measurement file for the whole of one run.

    Two runs appending to one file (two ``run --resume`` at once) would record
    points twice; the second is refused while the first holds the lock. The
    lock is ``fcntl.flock`` on the file itself: it ends with the process, even
    a killed one. Opening it creates a missing file and its folders (an empty
    file counts as new).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._fd: int | None = os.open(self.path, os.O_RDONLY | os.O_CREAT, 0o666)
        except OSError as error:
            raise _write_error(self.path, error) from error
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as error:
            self.release()
            if error.errno not in (errno.EWOULDBLOCK, errno.EAGAIN):
                raise _write_error(self.path, error) from error
            raise InputError(
                f"{self.path}: in use by another run (another xmalign run is writing it);"
                " wait until it ends, or give another --out"
            ) from error

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


class MeasurementWriter:
    """Appends rows and setup comments to a measurement CSV, syncing each one to disk.

    Use :meth:`create` for a new file and :meth:`resume` to go on with one.
    ``saved`` counts the rows in the file. Writes are unbuffered (``os.write``):
    after a failed write (disk full) nothing is left pending, and the file ends
    in at most one row cut short, which ``--resume`` drops.
    """

    def __init__(self, path: Path, fd: int, columns: tuple[str, ...], saved: int) -> None:
        self.path = path
        self.columns = columns
        self.saved = saved
        self._fd: int | None = fd

    @classmethod
    def create(
        cls,
        path: str | Path,
        plan_sha256: str | None = None,
        environment_columns: tuple[str, ...] = (),
        *,
        sim_seed: int | None = None,
        inputs: Iterable[FileSource] = (),
    ) -> MeasurementWriter:
        """Start a new file (an existing empty file counts as new, nothing else does).

        ``environment_columns`` (names of :data:`ENVIRONMENT_LIMITS`) are written
        after the channels, with the flags column, when the run samples the environment;
        ``sim_seed`` is the virtual machine's seed of a simulated run.
        ``inputs`` (the plan file) go into the history preamble.
        """
        path = Path(path)
        unknown = [name for name in environment_columns if name not in ENVIRONMENT_LIMITS]
        if unknown:
            raise InputError(f"{path}: no environment column '{unknown[0]}'")
        columns = WRITTEN_COLUMNS + (
            (*environment_columns, FLAGS_COLUMN) if environment_columns else ()
        )
        if path.is_dir():
            raise InputError(f"{path}: is a folder; give a file name for the measurements")
        refuse_special(path, "cannot write")  # a FIFO would block, a device lose the rows
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            flags = os.O_WRONLY | os.O_APPEND | os.O_CREAT
            empty = path.is_file() and path.stat().st_size == 0
            fd = os.open(path, flags | (0 if empty else os.O_EXCL), 0o666)
        except FileExistsError as error:
            raise InputError(f"{path}: already exists; measurements are never replaced") from error
        except OSError as error:
            raise _write_error(path, error) from error
        writer = cls(path, fd, columns, 0)
        preamble = PREAMBLE + (f" {PLAN_KEY}={plan_sha256}" if plan_sha256 else "")
        preamble += f" {SEED_KEY}={sim_seed}" if sim_seed is not None else ""
        history = csv_preamble(MEASUREMENTS_FORMAT, inputs)
        writer._put(preamble + "\n" + history + ",".join(columns) + "\n")
        writer.note_start()
        sync_folder(path.parent)
        return writer

    @classmethod
    def resume(cls, recorded: MeasurementFile) -> MeasurementWriter:
        """Go on appending to a file read with ``torn_ok``; a torn last row is cut off first."""
        path = recorded.path
        try:
            fd = os.open(path, os.O_WRONLY | os.O_APPEND)
        except OSError as error:
            raise _write_error(path, error) from error
        writer = cls(path, fd, recorded.columns, len(recorded.rows))
        if recorded.torn is not None:
            try:
                os.ftruncate(fd, recorded.torn.offset)
                os.fsync(fd)
            except OSError as error:
                writer.close()
                raise _write_error(path, error) from error
        writer.note_start()
        return writer

    def _put(self, text: str) -> None:
        if self._fd is None:
            raise InputError(f"{self.path}: closed; measurements can no longer be written")
        data = memoryview(text.encode("utf-8"))
        try:
            while data:
                data = data[os.write(self._fd, data) :]
            os.fsync(self._fd)
        except OSError as error:
            raise _write_error(self.path, error) from error
        for line in text.splitlines():
            logger.debug("%s < %s", self.path, line)

    def append(self, row: MeasurementRow) -> None:
        """Write one row and sync it to disk before returning."""
        if row.segment and SEGMENT_COLUMN not in self.columns:
            raise InputError(
                f"{self.path}: has no '{SEGMENT_COLUMN}' column for the rows of a re-aligned"
                " line; go on with another --out"
            )
        self._put(_csv_line(row.fields(self.columns)))
        self.saved += 1

    def note_start(self) -> None:
        """Mark where a run (or its resumption) starts: ``time_s`` counts from here."""
        self._put(f"{RUN_START_TAG}{now_utc()}\n")

    def note_setup(self, setup: LineSetup) -> None:
        """Record a line's alignment (the locked unit angles) before its rows."""
        self._put(setup.comment() + "\n")

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> MeasurementWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _csv_line(fields: list[str]) -> str:
    text = io.StringIO()
    csv.writer(text, lineterminator="\n").writerow(fields)
    return text.getvalue()


def write_measurements(
    path: str | Path,
    rows: Iterable[MeasurementRow],
    plan_sha256: str | None = None,
    inputs: Iterable[FileSource] = (),
) -> None:
    """Write a new measurement CSV (refused where a non-empty file exists).

    The environment columns are those of the first row.
    """
    rows = list(rows)
    present = rows[0].environment if rows else {}
    columns = tuple(name for name in ENVIRONMENT_LIMITS if name in present)
    with MeasurementWriter.create(path, plan_sha256, columns, inputs=inputs) as writer:
        for row in rows:
            writer.append(row)


def check_recorded_plan(
    recorded: MeasurementFile, plan: Plan, check_points: bool = True
) -> list[str]:
    """Refuse a file recorded for another plan; a warning when the file does not say.

    The identity recorded in the file decides; every row must also be a point of
    the plan (``check_points``: ``post`` checks them itself, naming more).
    """
    path = recorded.path
    expected = plan_sha256(plan)
    if recorded.plan_sha256 is not None and recorded.plan_sha256 != expected:
        raise InputError(
            f"{path} was recorded for another plan ({PLAN_KEY} {recorded.plan_sha256[:12]}...,"
            f" this plan is {expected[:12]}...): give the plan it was recorded with"
        )
    points = {line.id: line.target_points_mm() for line in plan.lines}
    for row in recorded.rows if check_points else []:
        targets = points.get(row.line)
        if (
            targets is None
            or row.index >= len(targets)
            or np.linalg.norm(targets[row.index] - row.machine_mm) > POINT_TOLERANCE_MM
        ):
            raise InputError(
                f"{path}: line {row.line} run {row.run} index {row.index} is not a point of"
                " this plan: the file was recorded for another plan"
            )
    if recorded.plan_sha256 is None:
        return [f"{path} does not record its plan; its points match this plan's targets"]
    return []
