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
#: A tracer length farther than this from its station's sphere is a wrong reading, mm.
TRACER_GROSS_MM = 10.0
#: Spheres tried through random rows, and the rows each is fitted to (seeded RANSAC).
SPHERE_TRIALS, SPHERE_SAMPLE = 200, 6


def _where(source: str, lines: list[int], row: int, problem: str) -> InputError:
    if lines:
        return line_error(source, lines[row], problem)
    return InputError(f"{source}: row {row + 1}: {problem}")


def check_instrument_files(
    machine: Machine, trackers: Sequence[TrackerFile], tracers: Sequence[TracerFile]
) -> None:
    """Refuse instrument data that would make every table wrong (one line each).

    Raises
    ------
    InputError
        Naming the file and the row: see the module's list.
    """
    for tracker in trackers:
        _check_tracker_values(tracker)
    for tracer in tracers:
        _check_tracer_values(tracer)
    _check_not_twice([(f.source, _tracker_digest(f)) for f in trackers])
    _check_not_twice([(f.source, _tracer_digest(f)) for f in tracers])
    for tracker in trackers:
        smr = [p.smr for p in tracker.points]
        for points in (
            [p.machine_mm for p in tracker.points],
            [p.machine_mm if p.to_mm is None else p.to_mm for p in tracker.points],
        ):
            _check_travel(machine, tracker.source, tracker.lines, points, smr)
        _check_tracker_units(machine, tracker)
    for tracer in tracers:
        commanded = [r.machine_mm for r in tracer.lengths]
        smr = [r.smr for r in tracer.lengths]
        _check_travel(machine, tracer.source, tracer.lines, commanded, smr)
        _check_tracer_units(machine, tracer)


def _column(values: Sequence[float | None]) -> Vec:
    return np.array([np.nan if v is None else v for v in values], dtype=float)


def _first_outside(
    file: TrackerFile | TracerFile,
    name: str,
    values: Vec,
    inside: npt.NDArray[np.bool_],
    what: str,
) -> None:
    """Refuse the first row whose given value (not NaN) is not ``inside``."""
    bad = np.flatnonzero(~np.isnan(values) & ~inside)
    if len(bad):
        row = int(bad[0])
        raise _where(file.source, file.lines, row, f"{name} {values[row]:g} {what}")


def _check_material(file: TrackerFile | TracerFile, material_c: Vec) -> None:
    low, high = MATERIAL_RANGE_C
    with np.errstate(invalid="ignore"):
        inside = (material_c >= low) & (material_c <= high)
    _first_outside(
        file, "material_c", material_c, inside, f"lies outside [{low:g}, {high:g}] deg C"
    )


def _check_tracker_values(file: TrackerFile) -> None:
    """Dead or absurd uncertainties, impossible material temperatures."""
    for name in ("u_radial_um", "u_transverse_um"):
        values = _column([getattr(p, name) for p in file.points])
        with np.errstate(invalid="ignore"):
            inside = (values > 0) & (values <= MAX_UNCERTAINTY_UM)
        what = (
            f"is a dead or absurd uncertainty (a tracker's lies in (0, {MAX_UNCERTAINTY_UM:g}] um)"
        )
        _first_outside(file, name, values, inside, what)
    _check_material(file, _column([p.material_c for p in file.points]))


def _check_tracer_values(file: TracerFile) -> None:
    """Dead lengths (exactly 0: no tracer counts that by chance), impossible temperatures."""
    lengths = np.array([r.length_mm for r in file.lengths])
    _first_outside(file, "length_mm", lengths, lengths != 0.0, "is a dead reading")
    _check_material(file, _column([r.material_c for r in file.lengths]))


def _tracker_digest(file: TrackerFile) -> str:
    values = np.array(
        [
            [p.run, -1 if p.index is None else p.index, *p.machine_mm, *p.tracker_mm]
            for p in file.points
        ]
    )
    return hashlib.sha256(np.ascontiguousarray(values).tobytes()).hexdigest()


def _tracer_digest(file: TracerFile) -> str:
    values = np.array([[r.run, r.index, *r.machine_mm, r.length_mm] for r in file.lengths])
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


def _smr_offsets(
    machine: Machine, source: str, lines: list[int], names: Sequence[str | None]
) -> Vec:
    """Each row's SMR offset, (N, 3); an unknown ``smr`` names the row."""
    known = {None: machine.smr_offset} | {
        name: np.asarray(offset, float) for name, offset in machine.smr_offsets_mm.items()
    }
    for row, name in enumerate(names):
        if name not in known:
            given = ", ".join(machine.smr_offsets_mm) or "none"
            raise _where(
                source,
                lines,
                row,
                f"smr '{name}' is not a key of the machine file's smr_offsets_mm ({given})",
            )
    return np.array([known[name] for name in names])


def _check_travel(
    machine: Machine,
    source: str,
    lines: list[int],
    commanded_mm: Sequence[Vec],
    smr: Sequence[str | None],
) -> None:
    points = np.array(commanded_mm, dtype=float).reshape(-1, 3)
    low, high = machine.travel_min_mm, machine.travel_max_mm
    outside = np.max(np.maximum(low - points, points - high), axis=1)
    bad = np.flatnonzero(outside > TRAVEL_MARGIN_MM)
    if len(bad):
        row = int(bad[0])
        travel = ", ".join(
            f"{a} [{lo:g}, {hi:g}]" for a, lo, hi in zip("XYZ", low, high, strict=True)
        )
        raise _where(
            source,
            lines,
            row,
            f"the commanded point {np.round(points[row], 3).tolist()} lies"
            f" {outside[row]:.0f} mm outside the machine's travel ({travel});"
            f" {len(bad)} of {len(points)} rows do",
        )
    _smr_offsets(machine, source, lines, smr)


def _unit_text(factor_mm: float) -> str:
    return next(UNIT_NAMES[name] for name, mm in UNITS_MM.items() if mm == factor_mm)


def _unit_option(factor_mm: float) -> str:
    return next(name for name, mm in UNITS_MM.items() if mm == factor_mm)


def _check_tracker_units(machine: Machine, file: TrackerFile) -> None:
    """Distances between a station's points against the commanded moves, row by row."""
    standing = [i for i, p in enumerate(file.points) if p.index is not None]
    for station in dict.fromkeys(file.points[i].station for i in standing):
        rows = np.array([i for i in standing if file.points[i].station == station])
        offsets = _smr_offsets(machine, file.source, file.lines, [file.points[i].smr for i in rows])
        nominal = np.array([file.points[i].machine_mm for i in rows]) + offsets
        seen = np.array([file.points[i].tracker_mm for i in rows])
        _check_distances(file, rows, nominal, seen)


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


def _check_distances(file: TrackerFile, rows: Vec, nominal: Vec, seen: Vec) -> None:
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
            file.source,
            file.lines,
            int(rows[0]),
            "the distances between the points match the commanded moves in no unit:"
            " the points are not the commanded ones (names shifted or missing?) or not"
            " one tracker's readings",
        )
    if unit != 1.0:
        raise _where(
            file.source,
            file.lines,
            int(rows[picks[good][0]]),
            f"the tracker's distances between points are 1/{unit:g} of the commanded moves:"
            f" the file is in {_unit_text(unit)}, not mm (xmalign import --units"
            f" {_unit_option(unit)} converts an export)",
        )
    base_nominal, base_seen = ref_nominal[good], ref_seen[good]
    mismatch = _consistent(_ratios(nominal, seen, base_nominal, base_seen))
    bad = np.flatnonzero(mismatch > DISTANCE_TOLERANCE)
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
            file.source,
            file.lines,
            int(rows[first]),
            f"this point's distances to the others do not match the commanded moves: {what}"
            f" ({len(bad)} of {len(rows)} rows of station {file.points[int(rows[first])].station})",
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
    """:func:`_sphere_misfit_mm` through the largest set of rows that agree (seeded RANSAC)."""
    rng = np.random.default_rng(0)
    best = np.zeros(len(lengths_mm), bool)
    for _ in range(SPHERE_TRIALS):
        pick = np.zeros(len(lengths_mm), bool)
        pick[rng.choice(len(lengths_mm), SPHERE_SAMPLE, replace=False)] = True
        inliers = np.abs(_sphere_misfit_mm(nominal, lengths_mm, pick)) <= TRACER_GROSS_MM
        if inliers.sum() > best.sum():
            best = inliers
    return _sphere_misfit_mm(nominal, lengths_mm, best if best.sum() >= SPHERE_SAMPLE else ~best)


def _check_tracer_units(machine: Machine, file: TracerFile) -> None:
    """Each station's lengths of a run on a sphere about its pivot, in mm, row by row."""
    groups = dict.fromkeys((r.station, r.run) for r in file.lengths)
    for station, run in groups:
        rows = np.array(
            [i for i, r in enumerate(file.lengths) if (r.station, r.run) == (station, run)]
        )
        if len(rows) < 2 * SPHERE_SAMPLE:
            continue  # the fit says what too few lengths cannot do
        smr = [file.lengths[i].smr for i in rows]
        nominal = np.array([file.lengths[i].machine_mm for i in rows])
        nominal = nominal + _smr_offsets(machine, file.source, file.lines, smr)
        lengths = np.array([file.lengths[i].length_mm for i in rows])
        misfit = {mm: _robust_misfit_mm(nominal, lengths * mm) for mm in UNITS_MM.values()}
        fits = {mm: int(np.sum(np.abs(m) <= TRACER_GROSS_MM)) for mm, m in misfit.items()}
        unit = max(fits, key=lambda mm: (fits[mm], mm == 1.0))
        where = f"station {station}, run {run}"
        if unit != 1.0:
            raise _where(
                file.source,
                file.lines,
                int(rows[0]),
                f"the lengths of {where} lie on a sphere about one pivot in {_unit_text(unit)},"
                f" not in mm ({fits[unit]} of {len(rows)} rows; {fits[1.0]} in mm):"
                " convert the file to mm",
            )
        bad = np.flatnonzero(np.abs(misfit[1.0]) > TRACER_GROSS_MM)
        if len(bad):
            first = int(bad[0])
            raise _where(
                file.source,
                file.lines,
                int(rows[first]),
                f"this length lies {abs(misfit[1.0][first]):.0f} mm off the sphere through the"
                f" other lengths of {where} (the commanded moves): a wrong reading or another"
                f" unit ({len(bad)} of {len(rows)} rows)",
            )
