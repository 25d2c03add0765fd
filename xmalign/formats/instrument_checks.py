"""Gross checks on tracker points and tracer lengths against the machine (docs/formats.md).

What makes every table wrong is refused before the fit, with one line naming
the file and the row:

- dead or absurd values: an uncertainty column not in (0, 10 000] um (``1e30``),
  a tracer length of exactly 0, a material temperature outside [-20, 60] deg C;
- the same readings given twice (the same file, a link to it or a copy: by content);
- a commanded point outside the machine's travel (more than :data:`TRAVEL_MARGIN_MM`);
- an SMR position the machine file does not name;
- units: a tracker's distances between points are the commanded moves' (a rigid
  pose keeps distances), a tracer's lengths lie on a sphere about its pivot; a
  file in inches or metres, or rows in another unit than the rest, is named with
  its likely unit; a row that fits no unit is a wrong reading.

Outliers of a few times the noise are the fit's business (it names and leaves them out).
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from xmalign.errors import InputError
from xmalign.formats.common import line_error
from xmalign.formats.instruments import TracerFile, TrackerFile
from xmalign.geometry import Vec
from xmalign.machine import Machine

#: An uncertainty column beyond this is not a tracker's (the machine file's own bound), um.
MAX_UNCERTAINTY_UM = 10_000.0
#: A material temperature outside this is a sensor fault, deg C (as the weather station's).
MATERIAL_RANGE_C = (-20.0, 60.0)
#: A commanded point may lie this far outside the travel (rounding), mm.
TRAVEL_MARGIN_MM = 1.0
#: Length units a tracker's software may export, in mm, and their names.
UNITS_MM = {"mm": 1.0, "in": 25.4, "m": 1000.0}
UNIT_NAMES = {"mm": "mm", "in": "inches", "m": "metres"}
#: Only points at least this far apart compare distances, mm.
MIN_SEPARATION_MM = 100.0
#: Distances may differ from the commanded moves by this much (relative, median): the
#: machine's own errors are below 1e-2 (seed 004's squareness, 2900 urad, changes them 3e-3).
DISTANCE_TOLERANCE = 0.02
#: The points each row is compared with, per station.
REFERENCE_ROWS = 60
#: Rows compared at once (bounds the memory of a million rows' comparisons).
CHUNK_ROWS = 20_000
#: A tracer length farther than this from its station's sphere is a wrong reading, mm.
TRACER_GROSS_MM = 10.0
#: Spheres tried through random rows, the rows each is fitted to, and the rows that score
#: them (seeded RANSAC).
SPHERE_TRIALS, SPHERE_SAMPLE, SPHERE_SCORED = 200, 6, 2000


def _where(source: str, lines: list[int], row: int, problem: str) -> InputError:
    if lines:
        return line_error(source, lines[row], problem)
    return InputError(f"{source}: row {row + 1}: {problem}")


@dataclass(frozen=True)
class _Columns:
    """One file's rows as the columns the checks read (built in one pass)."""

    source: str
    lines: list[int]
    station: list[str]
    smr: list[str | None]
    run: npt.NDArray[np.int64]
    #: -1 for a tracker point on the fly
    index: npt.NDArray[np.int64]
    machine_mm: Vec
    #: the path's end of a point on the fly, else ``machine_mm``
    end_mm: Vec
    material_c: Vec
    #: tracker: ``tracker_mm`` (N, 3), ``u_radial_um``, ``u_transverse_um``; tracer: ``length_mm``
    readings: dict[str, Vec]


def _floats(values: list[float | None]) -> Vec:
    return np.array([np.nan if v is None else v for v in values], dtype=float)


def _tracker_columns(file: TrackerFile) -> _Columns:
    points = file.points
    machine = np.array([p.machine_mm for p in points], dtype=float).reshape(-1, 3)
    ends = [p.to_mm for p in points]
    return _Columns(
        file.source,
        file.lines,
        [p.station for p in points],
        [p.smr for p in points],
        np.array([p.run for p in points], dtype=np.int64),
        np.array([-1 if p.index is None else p.index for p in points], dtype=np.int64),
        machine,
        np.array([m if e is None else e for m, e in zip(machine, ends, strict=True)]).reshape(
            -1, 3
        ),
        _floats([p.material_c for p in points]),
        {
            "tracker_mm": np.array([p.tracker_mm for p in points], dtype=float).reshape(-1, 3),
            "u_radial_um": _floats([p.u_radial_um for p in points]),
            "u_transverse_um": _floats([p.u_transverse_um for p in points]),
        },
    )


def _tracer_columns(file: TracerFile) -> _Columns:
    lengths = file.lengths
    machine = np.array([r.machine_mm for r in lengths], dtype=float).reshape(-1, 3)
    return _Columns(
        file.source,
        file.lines,
        [r.station for r in lengths],
        [r.smr for r in lengths],
        np.array([r.run for r in lengths], dtype=np.int64),
        np.array([r.index for r in lengths], dtype=np.int64),
        machine,
        machine,
        _floats([r.material_c for r in lengths]),
        {"length_mm": np.array([r.length_mm for r in lengths], dtype=float)},
    )


def check_instrument_files(
    machine: Machine, trackers: Sequence[TrackerFile], tracers: Sequence[TracerFile]
) -> None:
    """Refuse instrument data that would make every table wrong (one line each).

    Raises
    ------
    InputError
        Naming the file and the row: see the module's list.
    """
    tracker_columns = [_tracker_columns(f) for f in trackers]
    tracer_columns = [_tracer_columns(f) for f in tracers]
    for columns in tracker_columns:
        _check_tracker_values(columns)
    for columns in tracer_columns:
        _check_tracer_values(columns)
    _check_not_twice([(c.source, _digest(c)) for c in tracker_columns])
    _check_not_twice([(c.source, _digest(c)) for c in tracer_columns])
    for columns in tracker_columns + tracer_columns:
        offsets = _smr_offsets(machine, columns)
        for points in (columns.machine_mm, columns.end_mm):
            _check_travel(machine, columns, points)
        if "tracker_mm" in columns.readings:
            _check_tracker_units(columns, offsets)
        else:
            _check_tracer_units(columns, offsets)


def _first_outside(
    columns: _Columns,
    name: str,
    values: Vec,
    inside: npt.NDArray[np.bool_],
    what: str,
) -> None:
    """Refuse the first row whose given value (not NaN) is not ``inside``."""
    bad = np.flatnonzero(~np.isnan(values) & ~inside)
    if len(bad):
        row = int(bad[0])
        raise _where(columns.source, columns.lines, row, f"{name} {values[row]:g} {what}")


def _check_material(columns: _Columns) -> None:
    low, high = MATERIAL_RANGE_C
    material_c = columns.material_c
    with np.errstate(invalid="ignore"):
        inside = (material_c >= low) & (material_c <= high)
    what = f"lies outside [{low:g}, {high:g}] deg C"
    _first_outside(columns, "material_c", material_c, inside, what)


def _check_tracker_values(columns: _Columns) -> None:
    """Dead or absurd uncertainties, impossible material temperatures."""
    for name in ("u_radial_um", "u_transverse_um"):
        values = columns.readings[name]
        with np.errstate(invalid="ignore"):
            inside = (values > 0) & (values <= MAX_UNCERTAINTY_UM)
        what = (
            f"is a dead or absurd uncertainty (a tracker's lies in (0, {MAX_UNCERTAINTY_UM:g}] um)"
        )
        _first_outside(columns, name, values, inside, what)
    _check_material(columns)


def _check_tracer_values(columns: _Columns) -> None:
    """Dead lengths (exactly 0: no tracer counts that by chance), impossible temperatures."""
    lengths = columns.readings["length_mm"]
    _first_outside(columns, "length_mm", lengths, lengths != 0.0, "is a dead reading")
    _check_material(columns)


def _digest(columns: _Columns) -> str:
    """The readings' content (station names aside): runs, indices, points, readings."""
    parts = [columns.run.astype(float), columns.index.astype(float), columns.machine_mm]
    parts += [columns.readings["tracker_mm" if "tracker_mm" in columns.readings else "length_mm"]]
    values = np.column_stack(parts)
    return hashlib.sha256(np.ascontiguousarray(values).tobytes()).hexdigest()


def _check_not_twice(files: list[tuple[str, str]]) -> None:
    """The same readings twice (the same file, a link or a copy): every point would count twice."""
    first: dict[str, str] = {}
    for source, digest in files:
        if digest in first:
            earlier = first[digest]
            same = Path(source).resolve() == Path(earlier).resolve()
            what = "is the same file as" if same else "holds the same readings as"
            raise InputError(
                f"{source}: {what} {earlier} (by content): every reading would count twice;"
                " give each file once"
            )
        first[digest] = source


def _smr_offsets(machine: Machine, columns: _Columns) -> Vec:
    """Each row's SMR offset, (N, 3); an unknown ``smr`` names the row."""
    known = {None: machine.smr_offset} | machine.smr_offsets()
    for row, name in enumerate(columns.smr):
        if name not in known:
            given = ", ".join(machine.smr_offsets_mm) or "none"
            raise _where(
                columns.source,
                columns.lines,
                row,
                f"smr '{name}' is not a key of the machine file's smr_offsets_mm ({given})",
            )
    names = list(known)
    which = np.array([names.index(name) for name in columns.smr], dtype=np.int64)
    return np.array([known[name] for name in names])[which].reshape(-1, 3)


def _check_travel(machine: Machine, columns: _Columns, points: Vec) -> None:
    low, high = machine.travel_min_mm, machine.travel_max_mm
    outside = np.max(np.maximum(low - points, points - high), axis=1, initial=-np.inf)
    bad = np.flatnonzero(outside > TRAVEL_MARGIN_MM)
    if len(bad):
        row = int(bad[0])
        travel = ", ".join(
            f"{a} [{lo:g}, {hi:g}]" for a, lo, hi in zip("XYZ", low, high, strict=True)
        )
        raise _where(
            columns.source,
            columns.lines,
            row,
            f"the commanded point {np.round(points[row], 3).tolist()} lies"
            f" {outside[row]:.0f} mm outside the machine's travel ({travel});"
            f" {len(bad)} of {len(points)} rows do",
        )


def _unit_text(factor_mm: float) -> str:
    return next(UNIT_NAMES[name] for name, mm in UNITS_MM.items() if mm == factor_mm)


def _unit_option(factor_mm: float) -> str:
    return next(name for name, mm in UNITS_MM.items() if mm == factor_mm)


def _check_tracker_units(columns: _Columns, offsets: Vec) -> None:
    """Distances between a station's points against the commanded moves, row by row."""
    stations = np.array(columns.station)
    standing = columns.index >= 0
    for station in dict.fromkeys(stations[standing].tolist()):
        rows = np.flatnonzero(standing & (stations == station))
        nominal = columns.machine_mm[rows] + offsets[rows]
        _check_distances(columns, station, rows, nominal, columns.readings["tracker_mm"][rows])


def _ratios(nominal: Vec, seen: Vec, ref_nominal: Vec, ref_seen: Vec) -> Vec:
    """Seen over commanded distance from each point to each reference, NaN if too close."""
    commanded = np.linalg.norm(nominal[:, None] - ref_nominal[None], axis=2)
    measured = np.linalg.norm(seen[:, None] - ref_seen[None], axis=2)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(commanded >= MIN_SEPARATION_MM, measured / commanded, np.nan)


def _consistent(ratios: Vec) -> Vec:
    """Per row: the median relative mismatch of its distances (NaN: no pair far enough)."""
    mismatch = np.abs(ratios - 1.0)
    with np.errstate(all="ignore"):
        return np.array([np.nanmedian(r) if np.any(np.isfinite(r)) else np.nan for r in mismatch])


def _mismatch(nominal: Vec, seen: Vec, base_nominal: Vec, base_seen: Vec) -> Vec:
    """:func:`_consistent` of every row against the base rows, a chunk of rows at a time."""
    return np.concatenate(
        [
            _consistent(_ratios(nominal[at : at + CHUNK_ROWS], seen[at : at + CHUNK_ROWS],
                                base_nominal, base_seen))
            for at in range(0, len(nominal), CHUNK_ROWS)
        ]
    )  # fmt: skip


def _check_distances(
    columns: _Columns, station: str, rows: npt.NDArray[np.intp], nominal: Vec, seen: Vec
) -> None:
    picks = np.unique(np.linspace(0, len(rows) - 1, min(REFERENCE_ROWS, len(rows))).astype(int))
    ref_nominal, ref_seen = nominal[picks], seen[picks]
    # the unit most reference pairs agree on (mm first on a tie), and the rows that agree
    counts = {
        mm: int(
            np.sum(
                np.abs(_ratios(ref_nominal, ref_seen * mm, ref_nominal, ref_seen * mm) - 1)
                < DISTANCE_TOLERANCE
            )
        )
        for mm in UNITS_MM.values()
    }
    unit = max(counts, key=lambda mm: (counts[mm], mm == 1.0))
    agree = _consistent(_ratios(ref_nominal, ref_seen * unit, ref_nominal, ref_seen * unit))
    good = agree < DISTANCE_TOLERANCE
    if np.sum(good) < 3:
        if np.sum(np.isfinite(agree)) < 4:
            return  # too few points far enough apart to judge
        raise _where(
            columns.source,
            columns.lines,
            int(rows[0]),
            "the distances between the points match the commanded moves in no unit:"
            " the points are not the commanded ones (names shifted or missing?) or not"
            " one tracker's readings",
        )
    if unit != 1.0:
        raise _where(
            columns.source,
            columns.lines,
            int(rows[picks[good][0]]),
            f"the tracker's distances between points are 1/{unit:g} of the commanded moves:"
            f" the file is in {_unit_text(unit)}, not mm (xmalign import --units"
            f" {_unit_option(unit)} converts an export)",
        )
    base_nominal, base_seen = ref_nominal[good], ref_seen[good]
    bad = np.flatnonzero(_mismatch(nominal, seen, base_nominal, base_seen) > DISTANCE_TOLERANCE)
    if len(bad):
        first = int(bad[0])
        one = nominal[first : first + 1]
        for name, mm in UNITS_MM.items():
            if (
                mm != 1.0
                and _consistent(
                    _ratios(one, seen[first : first + 1] * mm, base_nominal, base_seen)
                )[0]
                < DISTANCE_TOLERANCE
            ):
                what = f"in {UNIT_NAMES[name]}, not mm like the others"
                break
        else:
            off = np.nanmedian(
                np.abs(
                    np.linalg.norm(seen[first] - base_seen, axis=1)
                    - np.linalg.norm(nominal[first] - base_nominal, axis=1)
                )
            )
            what = f"{off:.0f} mm from where the commanded moves put it: a wrong reading"
        raise _where(
            columns.source,
            columns.lines,
            int(rows[first]),
            f"this point's distances to the others do not match the commanded moves: {what}"
            f" ({len(bad)} of {len(rows)} rows of station {station})",
        )


def _sphere_misfit_mm(nominal: Vec, lengths_mm: Vec, fit: Vec) -> Vec:
    """Each length's distance from the sphere through the rows ``fit`` selects, mm.

    Pivot ``c`` and the run's constant ``b`` from the equations, linear in the unknowns,
    ``|P|^2 - L^2 = 2 P.c - 2 L b + (b^2 - |c|^2)``; the misfit is ``|P - c| - |L - b|``.
    """
    design = np.column_stack([2 * nominal, -2 * lengths_mm, np.ones(len(lengths_mm))])
    target = np.sum(nominal**2, axis=1) - lengths_mm**2
    solution, *_ = np.linalg.lstsq(design[fit], target[fit], rcond=None)
    distance = np.linalg.norm(nominal - solution[:3], axis=1)
    return np.asarray(distance - np.abs(lengths_mm - solution[3]))


def _robust_misfit_mm(nominal: Vec, lengths_mm: Vec) -> Vec:
    """:func:`_sphere_misfit_mm` through the largest set of rows that agree (seeded RANSAC,
    the trial spheres scored on at most :data:`SPHERE_SCORED` rows spread over the run)."""
    rng = np.random.default_rng(0)
    n = len(lengths_mm)
    scored = np.unique(np.linspace(0, n - 1, min(n, SPHERE_SCORED)).astype(int))
    best = np.zeros(len(scored), bool)
    for _ in range(SPHERE_TRIALS):
        pick = np.zeros(len(scored), bool)
        pick[rng.choice(len(scored), SPHERE_SAMPLE, replace=False)] = True
        misfit = _sphere_misfit_mm(nominal[scored], lengths_mm[scored], pick)
        inliers = np.abs(misfit) <= TRACER_GROSS_MM
        if inliers.sum() > best.sum():
            best = inliers
    fit = np.zeros(n, bool)
    fit[scored[best if best.sum() >= SPHERE_SAMPLE else ~best]] = True
    return _sphere_misfit_mm(nominal, lengths_mm, fit)


def _check_tracer_units(columns: _Columns, offsets: Vec) -> None:
    """Each station's lengths of a run on a sphere about its pivot, in mm, row by row."""
    stations = np.array(columns.station)
    for station, run in dict.fromkeys(zip(columns.station, columns.run.tolist(), strict=True)):
        rows = np.flatnonzero((stations == station) & (columns.run == run))
        if len(rows) < 2 * SPHERE_SAMPLE:
            continue  # the fit says what too few lengths cannot do
        nominal = columns.machine_mm[rows] + offsets[rows]
        lengths = columns.readings["length_mm"][rows]
        misfit = {mm: _robust_misfit_mm(nominal, lengths * mm) for mm in UNITS_MM.values()}
        fits = {mm: int(np.sum(np.abs(m) <= TRACER_GROSS_MM)) for mm, m in misfit.items()}
        unit = max(fits, key=lambda mm: (fits[mm], mm == 1.0))
        where = f"station {station}, run {run}"
        if unit != 1.0:
            raise _where(
                columns.source,
                columns.lines,
                int(rows[0]),
                f"the lengths of {where} lie on a sphere about one pivot in {_unit_text(unit)},"
                f" not in mm ({fits[unit]} of {len(rows)} rows; {fits[1.0]} in mm):"
                " convert the file to mm",
            )
        bad = np.flatnonzero(np.abs(misfit[1.0]) > TRACER_GROSS_MM)
        if len(bad):
            first = int(bad[0])
            raise _where(
                columns.source,
                columns.lines,
                int(rows[first]),
                f"this length lies {abs(misfit[1.0][first]):.0f} mm off the sphere through the"
                f" other lengths of {where} (the commanded moves): a wrong reading or another"
                f" unit ({len(bad)} of {len(rows)} rows)",
            )
