"""Laser-tracker points and laser-tracer lengths in the same fit as the interferometer lines.

One set of error tables and squareness (:mod:`xmalign.post.solve`'s layout and
basis) is fitted to every reading at once; each instrument brings its own setup
unknowns:

- a **tracker station**: its pose, ``t = R (p + dp) + c`` with ``t`` the SMR
  centre in the tracker's frame, ``p`` the commanded SMR point in the MCS and
  ``dp`` the machine's deviation there (seed 000); six unknowns;
- a **tracer place**: its pivot ``q`` (three unknowns) and one constant ``k``
  per run, ``L = |p + dp - q| + k`` (self-calibration, seed 004);
- with the machine file's priors, the instruments' systematic errors: a tracker
  station's angle errors (16 coefficients) and a scale per run of every station
  and place, each a pseudo-observation ``0 +- prior``;
- with several SMR positions, a constant correction of each but the first.

``p`` is the commanded point plus the row's SMR offset, expanded to 20 degC where
the row gives the material temperature.

The model is not linear in the poses and pivots, so it is solved by iterated
linearisation (Gauss-Newton): the table values stay the parameters (the
readings are linear in them), the poses and pivots are corrected by increments
about the current estimate. Starts come from the data alone: a tracker pose
from the commanded points by the closed-form rigid fit (Kabsch), a pivot and
its constants from the closed-form multilateration ``L**2 - |p|**2 =
-2 p.q + 2 L k + (|q|**2 - k**2)``, linear in ``q``, ``k`` and the bracket.

Each reading is weighted with its instrument's uncertainty model: a tracker
point with its 3 x 3 covariance (``sigma_radial`` along the beam,
``sigma_transverse`` across it, both growing with the distance), a tracer length
with ``sigma(L)``; the lines with the channel scatter the lines-only fit
estimates (:func:`xmalign.post.solve.fit_error_tables`). The covariance of the
tables is propagated as there (GUM).

A point only gives the position of the SMR. Without interferometer lines and
with one SMR position the angular errors whose lever arm never changes cannot be
seen (the rotations of the last axis of the tool side, and the rotation about
the only axis that moves a lever arm); the tables are then those of the SMR as
the functional point, and those rotations are written as 0 with no u95. SMR
positions that differ across a rotation's axis see it (docs/post.md).

Without lines the compensation points' spacing is chosen from the data by
generalised cross-validation (:func:`fit_joint`). Readings more than ten robust
standard deviations off are left out one by one and named; a fit that does not
settle, or tables beyond what a machine can have, are refused.

Points taken **on the fly** (seed 001) count only through their deviation across
the commanded path: the fit uses the two components perpendicular to it, at
the foot of the perpendicular from the measured point to the path. Their noise
may be correlated from sample to sample: the residuals' autocorrelation along
each path widens the station's uncertainty (:func:`correlation_samples`).

The rows are linearised in chunks of :data:`CHUNK_POINTS` points and only the
normal equations are accumulated, so a million rows fit in the memory of a few
chunks (docs/post.md); ``progress`` is told how far each pass is.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from functools import partial

import numpy as np
import scipy.linalg
import scipy.sparse
from scipy.spatial.transform import Rotation

from xmalign.environment import REFERENCE_TEMP_C, SENSOR_LIMITS, material_um
from xmalign.errors import GeometryError, InputError
from xmalign.formats.columns import tracer_columns, tracker_columns
from xmalign.formats.common import MAX_ERROR_MM, MAX_ERROR_RAD
from xmalign.formats.error_tables import ErrorTableSet, file_unit
from xmalign.formats.instruments import TracerFile, TrackerFile
from xmalign.geometry import Vec, skew
from xmalign.machine import TracerUncertainty, TrackerUncertainty
from xmalign.post.compare import rigid_motion_design
from xmalign.post.lines import LineData
from xmalign.post.setup_terms import N_CHANNELS, SetupLayout, Triplets
from xmalign.post.solve import (
    K_EXPANSION,
    MAX_OUTLIERS,
    OUTLIER_SIGMAS,
    ParameterLayout,
    TableFit,
    _inverse,
    _residual_rms,
    _tables,
    add_line_rows,
    bidirectional_axes,
    compensation_points,
    error_names,
    fit_error_tables,
    rms_curvature,
    spline_basis,
)
from xmalign.rigid_body import AXES, AXIS_INDEX, Chain, squareness_deviation

#: The chosen tables have at most this many values per reading component (docs/post.md).
MAX_COLUMNS_PER_READING = 0.25
#: The compensation-point spacings ``post`` tries or accepts where no line sets them, mm.
MIN_KNOT_SPACING_MM = 20.0
MAX_KNOT_SPACING_MM = 2000.0
#: Candidate spacings: the longest range the instruments measured over these (docs/post.md).
_CANDIDATE_INTERVALS = (2, 3, 4, 5, 6, 8, 10, 12, 14, 16, 20, 24, 28, 32, 40, 50, 64)
#: Above this many tracker points and tracer lengths the knot spacing is chosen on a
#: thinned copy of them (:func:`spacing_sample`), then all are fitted once at it.
SPACING_SAMPLE_POINTS = 50_000
#: Seed of the thinned copy's start within each run.
_SPACING_SAMPLE_SEED = 0
#: Spacing of the knots that continue the lines' tables where only instruments reach, mm.
EXTENSION_SPACING_MM = 400.0
#: Gauss-Newton stops when no pose or pivot moves more than this, mm.
_STEP_TOLERANCE_MM = 1e-7
_MAX_ITERATIONS = 20
_RANK_TOLERANCE = 1e-10
_NULL_TOLERANCE = 1e-9
_INVOLVED = 1e-4
#: A path whose direction has this much of an axis is parallel to it.
_PARALLEL = 1.0 - 1e-6
#: A tracker point this close to the tracker carries no direction.
_MIN_DISTANCE_MM = 1.0
#: Tracer places needed to place a point in space when no other instrument does.
MIN_TRACER_PLACES = 4
_TRACKER_SETUP = 6
#: Standard deviation of the pseudo-observations that continue a table linearly, rad.
_CONSTRAINT_SIGMA_RAD = 1e-9
#: The continuation prior is never taken as better than this (mm, rad).
_PRIOR_FLOOR_MM = 1e-5
_PRIOR_FLOOR_RAD = 1e-8
#: Points linearised at once: bounds the fit's memory (one chunk's sparse rows), not its result.
CHUNK_POINTS = 20_000
#: The longest lag of the residuals' autocorrelation that is looked at, points.
_MAX_LAG = 2000
#: ``progress(done, total, what)``: points linearised of all, in the pass named ``what``.
Progress = Callable[[int, int, str], None]
#: An instrument's scatter this much above its model re-weights the fit.
FACTOR_TOLERANCE = 0.05
#: Two SMR offsets this far apart across a rotation's axis let the points see it, mm.
_SMR_LEVER_MM = 1.0
#: The rotation tables about X, Y, Z by the start of their names.
_ROTATION_ABOUT = {"EA": 0, "EB": 1, "EC": 2}
#: Coefficients of a tracker station's systematic angle errors: 8 for each angle.
_ANGLE_COEFFICIENTS = 16


def _given(values: np.ndarray, rows: slice | np.ndarray) -> np.ndarray:
    """These rows of an optional per-row column (empty: none given, stays empty)."""
    return values[rows] if len(values) else values


@dataclass(frozen=True)
class TrackerStation:
    """The points of one tracker station (mm).

    ``to_mm`` is NaN for points at a standstill; ``u_radial_mm`` and
    ``u_transverse_mm`` are NaN where the machine file's model applies. Per row
    (empty: none given) ``index`` (-1 on the fly), ``smr`` (the SMR position's
    name, None: ``smr_offset_mm``; an object array) and ``material_c`` (NaN: 20 degC).
    """

    label: str
    source: str
    run: np.ndarray
    machine_mm: Vec
    tracker_mm: Vec
    to_mm: Vec
    u_radial_mm: Vec
    u_transverse_mm: Vec
    index: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    smr: np.ndarray = field(default_factory=lambda: np.zeros(0, object))
    material_c: Vec = field(default_factory=lambda: np.zeros(0))

    @property
    def on_the_fly(self) -> np.ndarray:
        return ~np.isnan(self.to_mm[:, 0])

    def rows(self, rows: slice | np.ndarray) -> TrackerStation:
        """The station with only these rows (a chunk of the fit)."""
        return dataclasses.replace(
            self,
            run=self.run[rows],
            machine_mm=self.machine_mm[rows],
            tracker_mm=self.tracker_mm[rows],
            to_mm=self.to_mm[rows],
            u_radial_mm=self.u_radial_mm[rows],
            u_transverse_mm=self.u_transverse_mm[rows],
            index=_given(self.index, rows),
            smr=_given(self.smr, rows),
            material_c=_given(self.material_c, rows),
        )

    def directions(self) -> Vec:
        """Each row's path direction in the MCS, unit (N, 3); 0 for points at a standstill."""
        direction = np.zeros_like(self.machine_mm)
        fly = self.on_the_fly
        path = self.to_mm[fly] - self.machine_mm[fly]
        direction[fly] = path / np.linalg.norm(path, axis=1)[:, None]
        return direction


@dataclass(frozen=True)
class TracerPlace:
    """The lengths of one tracer place (mm), with the file's coarse pivot guess if any.

    ``index``, ``smr`` and ``material_c`` per row as for :class:`TrackerStation`.
    """

    label: str
    source: str
    run: np.ndarray
    machine_mm: Vec
    length_mm: Vec
    guess_mm: Vec | None = None
    index: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    smr: np.ndarray = field(default_factory=lambda: np.zeros(0, object))
    material_c: Vec = field(default_factory=lambda: np.zeros(0))

    @property
    def runs(self) -> list[int]:
        return sorted({int(r) for r in self.run})

    def rows(self, rows: slice | np.ndarray) -> TracerPlace:
        """The place with only these lengths (a chunk of the fit)."""
        return dataclasses.replace(
            self,
            run=self.run[rows],
            machine_mm=self.machine_mm[rows],
            length_mm=self.length_mm[rows],
            index=_given(self.index, rows),
            smr=_given(self.smr, rows),
            material_c=_given(self.material_c, rows),
        )


def _labels(keys: list[tuple[str, str]]) -> list[str]:
    """Station names, with the file's name where two files use the same one."""
    names = [station for _, station in keys]
    return [
        station if names.count(station) == 1 else f"{station}@{source}" for source, station in keys
    ]


def _grouped(
    sources: list[tuple[str, dict[str, np.ndarray]]],
) -> list[tuple[str, str, str, np.ndarray, dict[str, np.ndarray]]]:
    """(source, station, label, rows, columns) of each (file, station), in the order first seen."""
    keys, found = [], []
    for source, columns in sources:
        stations = columns["station"].astype(str)
        _, first, group = np.unique(stations, return_index=True, return_inverse=True)
        for g in np.argsort(first):
            keys.append((source, str(stations[first[g]])))
            found.append((np.flatnonzero(np.ravel(group) == g), columns))
    return [
        (source, station, label, rows, columns)
        for (source, station), label, (rows, columns) in zip(
            keys, _labels(keys), found, strict=True
        )
    ]


def tracker_stations(files: list[TrackerFile]) -> list[TrackerStation]:
    """Group the points of tracker files by (file, station)."""
    groups = _grouped([(file.source, tracker_columns(file)) for file in files])
    return [
        TrackerStation(
            label=label,
            source=source,
            run=columns["run"][rows],
            machine_mm=columns["machine_mm"][rows],
            tracker_mm=columns["tracker_mm"][rows],
            to_mm=columns["to_mm"][rows],
            u_radial_mm=columns["u_radial_um"][rows] * 1e-3,
            u_transverse_mm=columns["u_transverse_um"][rows] * 1e-3,
            index=columns["index"][rows],
            smr=columns["smr"][rows],
            material_c=columns["material_c"][rows],
        )
        for source, _, label, rows, columns in groups
    ]


def tracer_places(files: list[TracerFile]) -> list[TracerPlace]:
    """Group the lengths of tracer files by (file, station), with the pivot guesses."""
    groups = _grouped([(file.source, tracer_columns(file)) for file in files])
    guesses = {(file.source, name): g for file in files for name, g in file.guesses_mm.items()}
    return [
        TracerPlace(
            label=label,
            source=source,
            run=columns["run"][rows],
            machine_mm=columns["machine_mm"][rows],
            length_mm=columns["length_mm"][rows],
            guess_mm=guesses.get((source, station)),
            index=columns["index"][rows],
            smr=columns["smr"][rows],
            material_c=columns["material_c"][rows],
        )
        for source, station, label, rows, columns in groups
    ]


@dataclass
class TrackerStationFit:
    """A tracker station's fitted pose and residuals.

    ``rotation_urad``: rotation vector of the tracker frame relative to the MCS;
    ``position_mm``: the tracker's origin in the MCS; u95 (k = 2) of both;
    ``residual_rms_um``: RMS length of the residual vectors (across the path for
    points on the fly); ``covered_mm``: the box of the commanded points (low, high);
    ``scatter_factor``: the residuals' scatter over the uncertainty model;
    ``correlation_samples``: over how many consecutive points on the fly the noise
    is correlated (:func:`correlation_samples`; the u95 is widened by its root).
    """

    label: str
    source: str
    n_points: int
    rotation_urad: Vec
    rotation_u95_urad: Vec
    position_mm: Vec
    position_u95_mm: Vec
    residual_rms_um: float
    covered_mm: tuple[Vec, Vec]
    scatter_factor: float = 1.0
    correlation_samples: float = 1.0
    angle_coefficients_urad: Vec = field(default_factory=lambda: np.zeros(0))
    angle_coefficients_u95_urad: Vec = field(default_factory=lambda: np.zeros(0))
    scale_ppm: dict[int, float] = field(default_factory=dict)
    scale_u95_ppm: dict[int, float] = field(default_factory=dict)


@dataclass
class TracerPlaceFit:
    """A tracer place's self-calibrated pivot (MCS) and constants per run, with u95 (k = 2).

    ``scatter_factor`` as for :class:`TrackerStationFit`.
    """

    label: str
    source: str
    n_lengths: int
    pivot_mm: Vec
    pivot_u95_mm: Vec
    constant_mm: dict[int, float]
    constant_u95_mm: dict[int, float]
    residual_rms_um: float
    covered_mm: tuple[Vec, Vec]
    scatter_factor: float = 1.0
    scale_ppm: dict[int, float] = field(default_factory=dict)
    scale_u95_ppm: dict[int, float] = field(default_factory=dict)


@dataclass(frozen=True)
class InstrumentOutlier:
    """A reading left out of the fit as a gross outlier: its name (file, instrument, run,
    index) and how many standard deviations off the fit it was."""

    name: str
    sigmas: float


@dataclass
class JointFit:
    """Result of the joint fit.

    ``fit`` holds the tables and the lines' setup and residuals as a lines-only
    fit would; ``undetermined`` names the rotation tables the point data cannot
    see (instrument-only fits: written as 0 with no u95); ``iterations`` the
    Gauss-Newton steps it took to settle; ``knot_spacing_mm`` the spacing of the
    compensation points where no line set them (None: the lines' default),
    ``spacing_scores`` each spacing tried with its generalised cross-validation
    score (empty when the spacing was given; above :data:`SPACING_SAMPLE_POINTS`
    rows, of :func:`spacing_sample`'s copy) and ``gcv`` this fit's (of all rows);
    ``outliers`` the readings left out.
    """

    fit: TableFit
    trackers: list[TrackerStationFit]
    tracers: list[TracerPlaceFit]
    undetermined: list[str]
    iterations: int
    functional_point: str = "tool point"
    knot_spacing_mm: float | None = None
    gcv: float = float("nan")
    spacing_scores: list[tuple[float, float]] = field(default_factory=list)
    outliers: list[InstrumentOutlier] = field(default_factory=list)
    layout: ParameterLayout | None = field(default=None, repr=False)
    covariance: Vec | None = field(default=None, repr=False)

    def volumetric_u_um(self, chain: Chain, points_mm: Vec, offset_mm: Vec | None = None) -> float:
        """RMS standard uncertainty of the fitted volumetric error at points, um.

        ``sqrt(mean(trace(J C J^T)))`` with ``J`` the points' sensitivity to the
        table values, less its rigid motion (as the comparison with a truth removes
        it, :func:`xmalign.post.compare.volumetric_rms_um`), and ``C`` their
        covariance; at the functional point, or ``offset_mm`` (3,) from it (a
        tool): what the readings' noise leaves in the tables (the information limit
        of the measurement), not the tables' model error.
        """
        assert self.layout is not None and self.covariance is not None
        n = self.layout.n_columns
        offset = np.zeros(3) if offset_mm is None else np.asarray(offset_mm, dtype=float)
        design = point_design(chain, self.layout, points_mm, offset).toarray()
        rigid = rigid_motion_design(points_mm)
        design -= rigid @ np.linalg.lstsq(rigid, design, rcond=None)[0]
        variance = np.sum((design @ self.covariance[:n, :n]) * design)
        return float(np.sqrt(variance / len(points_mm)) * 1e3)


# -- layout -----------------------------------------------------------------------


def _instrument_points(trackers: list[TrackerStation], tracers: list[TracerPlace]) -> Vec:
    parts = [s.machine_mm for s in trackers] + [s.to_mm[s.on_the_fly] for s in trackers]
    parts += [p.machine_mm for p in tracers]
    return np.concatenate([np.reshape(p, (-1, 3)) for p in parts])


def _beyond_lines(knots_mm: Vec, reached_mm: Vec, spacing_mm: float) -> Vec:
    """The lines' knots, continued out to the instruments' reach at about ``spacing_mm``.

    A stretch shorter than half the spacing gets no knot (the end segment's
    linear continuation covers it).
    """
    parts = [knots_mm]
    below, above = knots_mm[0] - reached_mm.min(), reached_mm.max() - knots_mm[-1]
    if below > spacing_mm / 2:
        n = int(np.ceil(below / spacing_mm))
        parts.insert(0, np.linspace(reached_mm.min(), knots_mm[0], n + 1)[:-1])
    if above > spacing_mm / 2:
        n = int(np.ceil(above / spacing_mm))
        parts.append(np.linspace(knots_mm[-1], reached_mm.max(), n + 1)[1:])
    return np.concatenate(parts).round(6)


def _standing_positions(trackers: list[TrackerStation], tracers: list[TracerPlace]) -> Vec:
    """Per axis, how many distinct coordinates (1 mm) it stood at while measured, shape (3,).

    A point at a standstill stands every axis; a path on the fly stands the axes
    it does not move. An axis's positioning error is seen only where it stands,
    or along a path oblique to it (then everywhere the path sweeps: no limit).
    """
    still = [s.machine_mm[~s.on_the_fly] for s in trackers] + [p.machine_mm for p in tracers]
    points = np.concatenate([np.reshape(p, (-1, 3)) for p in still])
    counts = np.zeros(3)
    for k in range(3):
        standing = [points[:, k]]
        oblique = False
        for s in trackers:
            fly = s.on_the_fly
            path = s.to_mm[fly] - s.machine_mm[fly]
            stands = path[:, k] == 0.0
            standing.append(s.machine_mm[fly][stands, k])
            length = np.linalg.norm(path, axis=1)
            oblique |= bool(np.any(~stands & (np.abs(path[:, k]) < _PARALLEL * length)))
        count = len(np.unique(np.round(np.concatenate(standing))))
        counts[k] = np.inf if oblique else count
    return counts


def instrument_knots(
    points_mm: Vec, spacing_mm: float, standing: Vec, sources: str = "the instruments"
) -> dict[str, Vec]:
    """Compensation points over the range the instruments measured, at about ``spacing_mm``.

    Never more points on an axis than the coordinates it stood at (``standing``,
    (3,)): paths on the fly along a regular grid put the points on the grid.

    Raises
    ------
    GeometryError
        An axis that did not move, or that stood at fewer than three coordinates.
    """
    knots = {}
    for k, axis in enumerate(AXES):
        low, high = points_mm[:, k].min(), points_mm[:, k].max()
        if high - low < 1.0:
            raise GeometryError(f"{sources}: the points do not move the {axis} axis")
        intervals = np.ceil(round((high - low) / spacing_mm, 6))  # range / n: n, not n + 1
        n = int(min(max(3, intervals + 1), standing[k]))
        if n < 3:
            raise GeometryError(
                f"{sources}: the {axis} axis stood at {int(standing[k])} coordinate(s) only;"
                f" its errors need at least 3 (measure more points, or paths at more {axis})"
            )
        knots[axis] = np.linspace(low, high, n).round(6)
    return knots


def unseen_rotations(chain: Chain) -> list[str]:
    """Rotation tables a point at the functional point cannot see (no lever arm changes).

    For an axis whose lever arm is moved by no other axis, all three; by one
    other axis J, the rotation about J.
    """
    names: list[str] = []
    for axis in AXES:
        moving = [other for other in chain.lever_arm_axes(axis) if other != axis]
        rotations = error_names(axis)[3:]
        if not moving:
            names.extend(rotations)
        elif len(moving) == 1:
            names.append(rotations[AXIS_INDEX[moving[0]]])
    return names


def _without_tables(layout: ParameterLayout, names: list[str]) -> ParameterLayout:
    """The layout with the named tables fixed at 0 (no columns), renumbered."""
    columns = {
        axis: {
            kind: np.where(np.isin(error_names(axis), names)[:, None], -1, c)
            for kind, c in kinds.items()
        }
        for axis, kinds in layout.column.items()
    }
    return _renumbered(layout, columns)


def _reversal_within(layout: ParameterLayout, line_knots: dict[str, Vec]) -> ParameterLayout:
    """The layout with the half reversals fixed at 0 beyond the lines' compensation points.

    Tracker points and tracer lengths have no direction of approach: the
    reversal is measured only where the lines measured it.
    """
    columns = {}
    for axis, kinds in layout.column.items():
        columns[axis] = dict(kinds)
        if "half" in kinds:
            knots = layout.knots[axis]
            outside = (knots < line_knots[axis][0] - 1e-6) | (knots > line_knots[axis][-1] + 1e-6)
            columns[axis]["half"] = np.where(outside[None, :], -1, kinds["half"])
    return _renumbered(layout, columns)


def _continuation_block(
    layout: ParameterLayout,
    line_knots: dict[str, Vec],
    line_tables: ErrorTableSet,
    unseen: list[str],
    n_columns: int,
) -> _Block | None:
    """Prior rows: beyond the lines' knots every table continues the lines' end segment.

    The lines-only fit extrapolates a table linearly from its last two knots, with
    the standard uncertainty ``kappa * d**2 / 2`` (``kappa`` the table's RMS
    curvature over the lines' knots, ``d`` the distance from the last one;
    docs/post.md). The same continuation, with that uncertainty, enters the joint
    fit as a pseudo-observation of each knot beyond the lines: where the
    instruments measure better than the extrapolation can be trusted they decide,
    where they are noisier it does. The rotations a point cannot see
    (:func:`unseen_rotations`) are held to the continuation outright.
    """
    rows = Triplets()
    sigma: list[float] = []
    for axis in AXES:
        knots, inner = layout.knots[axis], line_knots[axis]
        first = int(np.searchsorted(knots, inner[0] - 1e-6))
        last = int(np.searchsorted(knots, inner[-1] + 1e-6)) - 1
        beyond = [(j, first, first + 1) for j in range(first)]
        beyond += [(j, last, last - 1) for j in range(last + 1, len(knots))]
        for error, name in enumerate(error_names(axis)):
            table = line_tables.tables[name]
            kappa = rms_curvature(inner, table.positions_mm, table.values) if len(inner) > 2 else 0
            floor = _PRIOR_FLOOR_MM if error < 3 else _PRIOR_FLOOR_RAD
            columns = layout.column[axis]["mean"][error]
            for j, a, b in beyond:
                ratio = (knots[j] - knots[a]) / (knots[a] - knots[b])
                row = len(sigma)
                for column, value in (
                    (columns[j], 1.0),
                    (columns[a], -1.0 - ratio),
                    (columns[b], ratio),
                ):
                    if column >= 0:
                        rows.add(np.array([row]), int(column), value)
                spread = 0.5 * kappa * (knots[j] - knots[a]) ** 2
                sigma.append(_CONSTRAINT_SIGMA_RAD if name in unseen else max(spread, floor))
    if not sigma:
        return None
    r, c, v = rows.arrays()
    return _Block(
        design=scipy.sparse.csr_matrix((v, (r, c)), shape=(len(sigma), n_columns)),
        observed=np.zeros(len(sigma)),
        whitening=scipy.sparse.diags(1.0 / np.array(sigma)).tocsr(),
        ratio=np.array([0.0 if s == _CONSTRAINT_SIGMA_RAD else 1.0 for s in sigma]),
    )


def _renumbered(
    layout: ParameterLayout, columns: dict[str, dict[str, np.ndarray]]
) -> ParameterLayout:
    """A copy of ``layout`` with these table columns (-1: fixed), numbered from 0 again."""
    kept = np.sort(
        np.concatenate(
            [c[c >= 0] for kinds in columns.values() for c in kinds.values()]
            + [layout.squareness_columns]
        )
    )
    renumber = np.full(layout.n_columns, -1)
    renumber[kept] = np.arange(len(kept))
    result = copy.copy(layout)
    result.column = {
        axis: {kind: np.where(c >= 0, renumber[np.maximum(c, 0)], -1) for kind, c in kinds.items()}
        for axis, kinds in columns.items()
    }
    result.squareness_columns = renumber[layout.squareness_columns]
    result.n_columns = len(kept)
    return result


def point_design(
    chain: Chain, layout: ParameterLayout, machine_mm: Vec, t_mm: Vec
) -> scipy.sparse.csr_matrix:
    """d(dp)/d(table values) at points: sparse, shape (3N, n_table_columns).

    Row ``3 i + c`` is component ``c`` (MCS) of the functional point's deviation at
    point ``i``; mean tables only (an instrument reading has no direction).
    ``t_mm``: the functional point from the tool point, (3,) or one per point (N, 3).
    """
    n = len(machine_mm)
    t = np.asarray(t_mm, dtype=float)
    arms = chain.lever_arms(machine_mm, np.zeros(3) if t.ndim == 2 else t)
    if t.ndim == 2:
        arms = {axis: arm + t for axis, arm in arms.items()}
    rows = 3 * np.arange(n)
    out = Triplets()
    for axis in AXES:
        basis = spline_basis(layout.knots[axis], machine_mm[:, AXIS_INDEX[axis]])
        columns = layout.column[axis]["mean"][:, basis.col]
        arm = arms[axis][basis.row]
        for error in range(6):
            keep = columns[error] >= 0
            point_rows = rows[basis.row[keep]]
            if error < 3:
                out.add(point_rows + error, columns[error][keep], basis.data[keep])
                continue
            effect = np.cross(np.eye(3)[error - 3], arm[keep])
            for c in range(3):
                out.add(point_rows + c, columns[error][keep], basis.data[keep] * effect[:, c])
    for s, column in enumerate(layout.squareness_columns):
        dp = squareness_deviation(machine_mm, np.eye(3)[s])
        for c in range(3):
            out.add(rows + c, int(column), dp[:, c])
    rows_all, cols_all, vals_all = out.arrays()
    return scipy.sparse.csr_matrix(
        (vals_all, (rows_all, cols_all)), shape=(3 * n, layout.n_columns)
    )


# -- starts -----------------------------------------------------------------------


def rigid_start(points_mcs_mm: Vec, points_tracker_mm: Vec) -> tuple[Vec, Vec]:
    """``R, c`` with ``tracker = R mcs + c`` by the closed-form least-squares fit (Kabsch)."""
    a_mean, b_mean = points_mcs_mm.mean(axis=0), points_tracker_mm.mean(axis=0)
    h = (points_mcs_mm - a_mean).T @ (points_tracker_mm - b_mean)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return r, b_mean - r @ a_mean


def multilateration_start(
    points_mm: Vec, length_mm: Vec, run_index: np.ndarray, n_runs: int
) -> tuple[Vec, Vec] | None:
    """Pivot and constants per run from lengths to known points, closed form; None if singular.

    ``L**2 - |p|**2 = -2 p.q + 2 L k_r + m_r`` with ``m_r = |q|**2 - k_r**2``:
    linear in ``q``, ``k_r`` and ``m_r``.
    """
    n = len(length_mm)
    design = np.zeros((n, 3 + 2 * n_runs))
    design[:, :3] = -2.0 * points_mm
    design[np.arange(n), 3 + run_index] = 2.0 * length_mm
    design[np.arange(n), 3 + n_runs + run_index] = 1.0
    scale = np.linalg.norm(design, axis=0)
    if np.any(scale == 0):
        return None
    observed = length_mm**2 - np.sum(points_mm**2, axis=1)
    solution, _, rank, singular = np.linalg.lstsq(design / scale, observed, rcond=None)
    if rank < design.shape[1] or singular[-1] < 1e-9 * singular[0]:
        return None
    solution = solution / scale
    return solution[:3], solution[3 : 3 + n_runs]


# -- the joint system -----------------------------------------------------------------


@dataclass
class _Block:
    """Rows of the linearised system: design, observations, whitening (all sparse/arrays).

    ``reading`` numbers each row's reading within its instrument (-1: no reading,
    e.g. a prior row); ``ratio`` is 0 for a row left out.
    """

    design: scipy.sparse.csr_matrix
    observed: Vec
    whitening: scipy.sparse.csr_matrix
    ratio: Vec  # (propagated / weighting variance) per whitened row
    reading: np.ndarray | None = None


@dataclass(frozen=True)
class _Setting:
    """What every instrument row needs beyond its own columns.

    ``smr_mm`` (3,) for rows without a name, ``smr_named_mm`` by name (MCS, mm);
    ``tool_tables``: the lever arm is the SMR offset (tables of the tool point),
    else 0 (tables of the SMR); the machine file's instrument models and scale
    expansion (ppm/K); ``smr_positions_mm`` (M, 3) the distinct SMR offsets the
    rows use: from the second one on, each gets a constant correction (three
    unknowns), since neither its nominal offset nor the tool's orientation
    (a constant rotation times the offsets' differences) is known to a micrometre.
    """

    smr_mm: Vec
    smr_named_mm: Mapping[str, Vec]
    tool_tables: bool
    tracker: TrackerUncertainty
    tracer: TracerUncertainty
    expansion_ppm_per_k: float = 0.0
    smr_positions_mm: Vec = field(default_factory=lambda: np.zeros((1, 3)))


def _row_reading(source: str, kind: str, label: str, run: int, index: int, row: int) -> str:
    """A person's name for one reading: file, instrument, run and index (or row on the fly)."""
    which = f"index {index}" if index >= 0 else f"row {row + 1} (on the fly)"
    return f"{source}: {kind} {label} run {run} {which}"


class _RowContext:
    """Per row of one instrument: the SMR offset, the lever arm and the thermal scale.

    Raises
    ------
    InputError
        A row naming an SMR position the machine file does not have, or a material
        temperature no machine hall has.
    """

    def __init__(
        self,
        setting: _Setting,
        kind: str,
        station: TrackerStation | TracerPlace,
        shift_column: int,
    ) -> None:
        n = len(station.run)
        names = station.smr if len(station.smr) else np.full(n, None, dtype=object)
        self.smr_mm = np.empty((n, 3))
        for name in dict.fromkeys(names):  # each name, its rows at once
            rows = names == name
            if name is None:
                self.smr_mm[rows] = setting.smr_mm
            elif name in setting.smr_named_mm:
                self.smr_mm[rows] = setting.smr_named_mm[name]
            else:
                raise InputError(
                    _row_reading(*self._where(kind, station, int(np.flatnonzero(rows)[0])))
                    + f": smr '{name}' is not in the machine file's smr_offsets_mm"
                    + f" ({', '.join(setting.smr_named_mm) or 'none given'})"
                )
        self.arm_mm = self.smr_mm if setting.tool_tables else np.zeros((n, 3))
        distance = np.linalg.norm(
            self.smr_mm[:, None, :] - setting.smr_positions_mm[None, :, :], axis=2
        )
        self.position = np.argmin(distance, axis=1)  # 0: no correction
        self.shift_column = shift_column
        material = station.material_c if len(station.material_c) else np.full(n, np.nan)
        low, high = SENSOR_LIMITS["material_temp_c"]
        bad = np.flatnonzero(~np.isnan(material) & ((material < low) | (material > high)))
        if len(bad):
            raise InputError(
                _row_reading(*self._where(kind, station, int(bad[0])))
                + f": material_c {material[bad[0]]:g} lies outside {low:g}..{high:g} degC"
            )
        self.material_c = np.where(np.isnan(material), REFERENCE_TEMP_C, material)
        self.expansion_ppm_per_k = setting.expansion_ppm_per_k

    @staticmethod
    def _where(
        kind: str, station: TrackerStation | TracerPlace, row: int
    ) -> tuple[str, str, str, int, int, int]:
        index = int(station.index[row]) if len(station.index) else row
        return station.source, kind, station.label, int(station.run[row]), index, row

    def part(self, rows: slice) -> _RowContext:
        """The context of only these rows (a chunk of the fit)."""
        part = copy.copy(self)
        part.smr_mm, part.arm_mm = self.smr_mm[rows], self.arm_mm[rows]
        part.position, part.material_c = self.position[rows], self.material_c[rows]
        return part

    def shift_design(self, n_columns: int) -> scipy.sparse.csr_matrix:
        """The rows' sensitivity to the SMR positions' corrections, (3N, n_columns)."""
        n = len(self.position)
        rows = np.flatnonzero(self.position > 0)
        columns = self.shift_column + 3 * (self.position[rows] - 1)
        return scipy.sparse.csr_matrix(
            (
                np.ones(3 * len(rows)),
                (
                    (3 * rows[:, None] + np.arange(3)).ravel(),
                    (columns[:, None] + np.arange(3)).ravel(),
                ),
            ),
            shape=(3 * n, n_columns),
        )

    def nominal_mm(self, commanded_mm: Vec) -> Vec:
        """The SMR's nominal place at 20 degC: the commanded point, the SMR offset and the
        scales' expansion at the row's material temperature, (N, 3)."""
        expansion = material_um(commanded_mm, self.material_c[:, None], self.expansion_ppm_per_k)
        return commanded_mm + self.smr_mm + expansion * 1e-3


def systematic_angle_basis(azimuth_rad: Vec, elevation_rad: Vec) -> Vec:
    """The eight functions of one angle reading's systematic error, shape (N, 8).

    ``cos k az, sin k az, cos k el, sin k el`` for k = 1, 2 (docs/formats.md
    "Systematic instrument errors"): an error is their sum with eight coefficients.
    """
    return np.stack(
        [
            f(k * angle)
            for k in (1, 2)
            for angle in (azimuth_rad, elevation_rad)
            for f in (np.cos, np.sin)
        ],
        axis=1,
    )


def beam_angles(tracker_mm: Vec) -> tuple[Vec, Vec]:
    """Azimuth and elevation of points in a tracker's frame (z up), rad, each (N,)."""
    horizontal = np.hypot(tracker_mm[:, 0], tracker_mm[:, 1])
    return np.arctan2(tracker_mm[:, 1], tracker_mm[:, 0]), np.arctan2(tracker_mm[:, 2], horizontal)


def _angle_partials(tracker_mm: Vec) -> tuple[Vec, Vec]:
    """d(point)/d(azimuth) and d(point)/d(elevation) in the tracker's frame, mm/rad, (N, 3)."""
    x, y, z = tracker_mm.T
    horizontal = np.maximum(np.hypot(x, y), _MIN_DISTANCE_MM)
    by_azimuth = np.stack([-y, x, np.zeros_like(x)], axis=1)
    by_elevation = np.stack([-z * x / horizontal, -z * y / horizontal, horizontal], axis=1)
    return by_azimuth, by_elevation


def _prior_rows(columns: np.ndarray, sigma: float, n_columns: int) -> _Block:
    """Pseudo-observations ``0 = x`` of these columns with standard deviation ``sigma``."""
    n = len(columns)
    return _Block(
        design=scipy.sparse.csr_matrix((np.ones(n), (np.arange(n), columns)), shape=(n, n_columns)),
        observed=np.zeros(n),
        whitening=scipy.sparse.diags(np.full(n, 1.0 / sigma)).tocsr(),
        ratio=np.ones(n),
    )


def _run_columns(
    rows: int, first_column: int, run_index: np.ndarray, values: Vec, n_columns: int
) -> scipy.sparse.csr_matrix:
    """One column per run: ``values`` (R, C) on the C rows of each reading of that run."""
    per_reading = values.shape[1]
    return scipy.sparse.csr_matrix(
        (
            values.ravel(),
            (np.arange(rows * per_reading), np.repeat(first_column + run_index, per_reading)),
        ),
        shape=(rows * per_reading, n_columns),
    )


def _start_pairs(station: TrackerStation, smr_mm: Vec) -> tuple[Vec, Vec]:
    """Nominal SMR places and measured points that roughly correspond, for the closed-form start.

    Points at a standstill as they are. With fewer than three of them, each path
    on the fly also gives its ends: the first and the last of its rows (the file's
    order, which is the order of capture) stand at about its start and its end.
    Gauss-Newton takes it from there. ``smr_mm``: each row's SMR offset, (N, 3).
    """
    still = ~station.on_the_fly
    nominal = [station.machine_mm[still] + smr_mm[still]]
    measured = [station.tracker_mm[still]]
    if still.sum() < 3:
        fly = np.flatnonzero(station.on_the_fly)
        paths = np.concatenate([station.machine_mm[fly], station.to_mm[fly]], axis=1)
        _, first, group = np.unique(paths, axis=0, return_index=True, return_inverse=True)
        for g, start in enumerate(first):
            rows = fly[np.ravel(group) == g]
            if len(rows) >= 2:
                ends = np.stack([station.machine_mm[fly[start]], station.to_mm[fly[start]]])
                nominal.append(ends + smr_mm[rows[[0, -1]]])
                measured.append(station.tracker_mm[[rows[0], rows[-1]]])
    return np.concatenate(nominal), np.concatenate(measured)


class _TrackerState:
    """A tracker station being fitted: its pose and, with the machine file's priors, its
    systematic angle errors (16 coefficients) and a scale per run (ppm)."""

    def __init__(
        self, station: TrackerStation, setting: _Setting, first_column: int, shift_column: int
    ) -> None:
        self.station = station
        self.noise_factor = 1.0
        self.rows = _RowContext(setting, "tracker station", station, shift_column)
        self.column = first_column
        self.kept = np.ones(len(station.run), dtype=bool)
        self.runs = sorted({int(r) for r in station.run})
        self.run_index = np.searchsorted(self.runs, station.run)
        angle_sigma = setting.tracker.angle_systematic_urad * 1e-6 / 2.0
        scale_sigma = setting.tracker.scale_ppm
        self.n_angle = _ANGLE_COEFFICIENTS if angle_sigma > 0 else 0
        self.n_scale = len(self.runs) if scale_sigma > 0 else 0
        self.priors = (angle_sigma, scale_sigma)
        nominal, measured = _start_pairs(station, self.rows.smr_mm)
        if len(nominal) < 3 or np.linalg.matrix_rank(nominal - nominal.mean(axis=0), 1e-3) < 2:
            raise GeometryError(
                f"{station.source}: tracker station {station.label}: {len(station.run)} points"
                " cannot place the tracker (at least three not on one line, or paths on the fly"
                " that span a plane)"
            )
        self.rotation, self.offset = rigid_start(nominal, measured)

    @property
    def n_columns(self) -> int:
        return _TRACKER_SETUP + self.n_angle + self.n_scale

    @property
    def scale_column(self) -> int:
        return self.column + _TRACKER_SETUP + self.n_angle

    def prior(self, n_columns: int) -> list[_Block]:
        """The systematic errors' prior rows (none where the machine file gives none)."""
        blocks = []
        if self.n_angle:
            columns = self.column + _TRACKER_SETUP + np.arange(self.n_angle)
            blocks.append(_prior_rows(columns, self.priors[0], n_columns))
        if self.n_scale:
            columns = self.scale_column + np.arange(self.n_scale)
            blocks.append(_prior_rows(columns, self.priors[1], n_columns))
        return blocks

    def describe(self, column: int) -> str:
        """A person's name for the station's ``column``-th unknown."""
        what = (
            "the pose"
            if column < _TRACKER_SETUP
            else "the angle errors"
            if column < _TRACKER_SETUP + self.n_angle
            else "a scale"
        )
        return f"{what} of tracker station {self.station.label} ({self.station.source})"

    def outlier(self, reading: int, sigmas: float) -> InstrumentOutlier:
        s = self.station
        index = int(s.index[reading]) if len(s.index) else reading
        return InstrumentOutlier(
            _row_reading(s.source, "tracker station", s.label, int(s.run[reading]), index, reading),
            sigmas,
        )

    def linearise(
        self,
        chain: Chain,
        layout: ParameterLayout,
        tables: Vec,
        n_columns: int,
        uncertainty: TrackerUncertainty,
        chunk: slice = slice(None),
    ) -> _Block:
        """The station's rows ``chunk`` about the current tables, pose and systematic errors."""
        s, context = self.station.rows(chunk), self.rows.part(chunk)
        measured = (s.tracker_mm - self.offset) @ self.rotation  # R^T (t - c), (N, 3)
        commanded = s.machine_mm.copy()
        fly = s.on_the_fly
        direction = s.directions()
        smr = context.smr_mm
        if fly.any():
            along = np.sum((measured[fly] - smr[fly] - s.machine_mm[fly]) * direction[fly], 1)
            commanded[fly] = s.machine_mm[fly] + along[:, None] * direction[fly]
        nominal = context.nominal_mm(commanded)
        design_dp = point_design(chain, layout, commanded, context.arm_mm)
        dp0 = (design_dp @ tables[: layout.n_columns]).reshape(-1, 3)
        n = len(nominal)
        pose = np.zeros((n, 3, 6))
        pose[:, :, :3] = -_skews(nominal + dp0)
        pose[:, :, 3:] = np.eye(3)
        pose_design = scipy.sparse.csr_matrix(
            (
                pose.reshape(3 * n, 6).ravel(),
                (np.repeat(np.arange(3 * n), 6), np.tile(self.column + np.arange(6), 3 * n)),
            ),
            shape=(3 * n, n_columns),
        )
        table_design = scipy.sparse.hstack(
            [design_dp, scipy.sparse.csr_matrix((3 * n, n_columns - layout.n_columns))]
        ).tocsr()
        whitening = self._whitening(s, uncertainty, direction, fly) / self.noise_factor
        reading = range(len(self.station.run))[chunk].start + np.repeat(
            np.arange(n), np.where(fly, 2, 3)
        )
        kept = self.kept[reading]
        systematic = self._systematic_design(s, self.run_index[chunk], n_columns)
        return _Block(
            design=(
                table_design + pose_design + systematic + context.shift_design(n_columns)
            ).tocsr(),
            observed=(measured - nominal).ravel(),
            whitening=(scipy.sparse.diags(kept.astype(float)) @ whitening).tocsr(),
            ratio=kept.astype(float),
            reading=reading,
        )

    def _systematic_design(
        self, s: TrackerStation, run_index: np.ndarray, n_columns: int
    ) -> scipy.sparse.csr_matrix:
        """The rows' sensitivity to the angle coefficients (mm/rad) and scales (mm/ppm)."""
        n = len(s.run)
        first = self.column + _TRACKER_SETUP
        design = scipy.sparse.csr_matrix((3 * n, n_columns))
        if self.n_angle:
            basis = systematic_angle_basis(*beam_angles(s.tracker_mm))  # (N, 8)
            partials = [p @ self.rotation for p in _angle_partials(s.tracker_mm)]  # MCS
            values = np.concatenate([p[:, :, None] * basis[:, None, :] for p in partials], axis=2)
            columns = np.broadcast_to(first + np.arange(self.n_angle), values.shape)
            rows = np.broadcast_to(np.arange(3 * n).reshape(n, 3, 1), values.shape)
            design = design + scipy.sparse.csr_matrix(
                (values.ravel(), (rows.ravel(), columns.ravel())), shape=(3 * n, n_columns)
            )
        if self.n_scale:
            scaled = (s.tracker_mm @ self.rotation) * 1e-6  # R^T t per ppm
            design = design + _run_columns(n, self.scale_column, run_index, scaled, n_columns)
        return design

    def _whitening(
        self, s: TrackerStation, uncertainty: TrackerUncertainty, direction: Vec, fly: np.ndarray
    ) -> scipy.sparse.csr_matrix:
        """Per point the inverse square root of its covariance (MCS); 2 x 3 across a path."""
        distance = np.maximum(np.linalg.norm(s.tracker_mm, axis=1), _MIN_DISTANCE_MM)
        beam = (s.tracker_mm / distance[:, None]) @ self.rotation  # in the MCS
        radial = np.where(
            np.isnan(s.u_radial_mm), uncertainty.radial_sigma_mm(distance), s.u_radial_mm
        )
        transverse = np.where(
            np.isnan(s.u_transverse_mm),
            uncertainty.transverse_sigma_mm(distance),
            s.u_transverse_mm,
        )
        along = beam[:, :, None] * beam[:, None, :]
        covariance = radial[:, None, None] ** 2 * along + transverse[:, None, None] ** 2 * (
            np.eye(3) - along
        )
        parts = []
        if (~fly).any():
            parts.append((np.flatnonzero(~fly), _inverse_sqrts(covariance[~fly])))  # (k, 3, 3)
        if fly.any():
            basis = _across(direction[fly])  # (k, 2, 3)
            across = basis @ covariance[fly] @ basis.transpose(0, 2, 1)
            parts.append((np.flatnonzero(fly), _inverse_sqrts(across) @ basis))  # (k, 2, 3)
        height = np.where(fly, 2, 3)
        first_row = np.concatenate([[0], np.cumsum(height)[:-1]])
        rows, cols, vals = [], [], []
        for points, blocks in parts:
            shape = blocks.shape
            r = first_row[points][:, None, None] + np.arange(shape[1])[None, :, None]
            c = 3 * points[:, None, None] + np.arange(3)[None, None, :]
            rows.append(np.broadcast_to(r, shape).ravel())
            cols.append(np.broadcast_to(c, shape).ravel())
            vals.append(blocks.ravel())
        return scipy.sparse.csr_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
            shape=(int(height.sum()), 3 * len(distance)),
        )

    def update(self, increment: Vec) -> float:
        rotation, shift = (
            increment[self.column : self.column + 3],
            increment[self.column + 3 : self.column + 6],
        )
        self.offset = self.offset + self.rotation @ shift
        self.rotation = self.rotation @ Rotation.from_rotvec(rotation).as_matrix()
        return float(max(np.linalg.norm(rotation) * 1e4, np.linalg.norm(shift)))


def _inverse_sqrts(covariance: Vec) -> Vec:
    """The symmetric inverse square roots of a stack of covariances (k, m, m)."""
    values, vectors = np.linalg.eigh(covariance)
    return (vectors / np.sqrt(values)[:, None, :]) @ vectors.transpose(0, 2, 1)


def _skews(vectors: Vec) -> Vec:
    """Cross-product matrices of a stack of vectors (k, 3) -> (k, 3, 3)."""
    x, y, z = vectors.T
    zero = np.zeros_like(x)
    return np.stack(
        [np.stack([zero, -z, y], 1), np.stack([z, zero, -x], 1), np.stack([-y, x, zero], 1)], 1
    )


def _across(direction: Vec) -> Vec:
    """Two unit vectors across each unit direction (k, 3), orthogonal: (k, 2, 3)."""
    helper = np.eye(3)[np.argmin(np.abs(direction), axis=1)]
    first = np.cross(direction, helper)
    first /= np.linalg.norm(first, axis=1)[:, None]
    return np.stack([first, np.cross(direction, first)], axis=1)


class _TracerState:
    """A tracer place being fitted: its pivot, a constant per run and, with the machine
    file's prior, a scale per run (ppm)."""

    def __init__(
        self, place: TracerPlace, setting: _Setting, first_column: int, shift_column: int
    ) -> None:
        self.place = place
        self.noise_factor = 1.0
        self.rows = _RowContext(setting, "tracer place", place, shift_column)
        self.column = first_column
        self.kept = np.ones(len(place.run), dtype=bool)
        self.runs = place.runs
        self.run_index = np.searchsorted(self.runs, place.run)
        self.scale_sigma = setting.tracer.scale_ppm
        #: The place's point design by layout, kept where the place is one chunk (it is the
        #: same in every step); a dict, so that a snapshot of the state shares it.
        self._designs: dict[int, tuple[ParameterLayout, scipy.sparse.csr_matrix]] = {}
        self.n_scale = len(self.runs) if self.scale_sigma > 0 else 0
        nominal = self.rows.nominal_mm(place.machine_mm)
        start = multilateration_start(nominal, place.length_mm, self.run_index, len(self.runs))
        if start is None:
            if place.guess_mm is None:
                raise GeometryError(
                    f"{place.source}: tracer place {place.label}: its {len(nominal)} lengths cannot"
                    " place the pivot (points on one plane or line; give"
                    " '# station NAME guess_mm=x,y,z' or measure more points)"
                )
            pivot = np.asarray(place.guess_mm, dtype=float)
            distance = np.linalg.norm(nominal - pivot, axis=1)
            constants = np.array(
                [
                    np.mean((place.length_mm - distance)[self.run_index == r])
                    for r in range(len(self.runs))
                ]
            )
            start = (pivot, constants)
        self.pivot, self.constants = start

    @property
    def n_columns(self) -> int:
        return 3 + len(self.runs) + self.n_scale

    @property
    def scale_column(self) -> int:
        return self.column + 3 + len(self.runs)

    def prior(self, n_columns: int) -> list[_Block]:
        if not self.n_scale:
            return []
        columns = self.scale_column + np.arange(self.n_scale)
        return [_prior_rows(columns, self.scale_sigma, n_columns)]

    def describe(self, column: int) -> str:
        """A person's name for the place's ``column``-th unknown."""
        what = (
            "the pivot"
            if column < 3
            else "a constant"
            if column < 3 + len(self.runs)
            else "a scale"
        )
        return f"{what} of tracer place {self.place.label} ({self.place.source})"

    def outlier(self, reading: int, sigmas: float) -> InstrumentOutlier:
        p = self.place
        index = int(p.index[reading]) if len(p.index) else reading
        return InstrumentOutlier(
            _row_reading(p.source, "tracer place", p.label, int(p.run[reading]), index, reading),
            sigmas,
        )

    def linearise(
        self,
        chain: Chain,
        layout: ParameterLayout,
        tables: Vec,
        n_columns: int,
        uncertainty: TracerUncertainty,
        chunk: slice = slice(None),
    ) -> _Block:
        """The place's lengths ``chunk`` about the current tables, pivot and constants."""
        p, context = self.place.rows(chunk), self.rows.part(chunk)
        run_index = self.run_index[chunk]
        design_dp = self._point_design(chain, layout, p, context)
        dp0 = (design_dp @ tables[: layout.n_columns]).reshape(-1, 3)
        vector = context.nominal_mm(p.machine_mm) + dp0 - self.pivot
        distance = np.linalg.norm(vector, axis=1)
        beam = vector / distance[:, None]
        n = len(distance)
        project = scipy.sparse.csr_matrix(
            (beam.ravel(), (np.repeat(np.arange(n), 3), np.arange(3 * n))), shape=(n, 3 * n)
        )
        tables_part = scipy.sparse.hstack(
            [project @ design_dp, scipy.sparse.csr_matrix((n, n_columns - layout.n_columns))]
        ) + project @ context.shift_design(n_columns)
        setup = Triplets()
        for c in range(3):
            setup.add(np.arange(n), self.column + c, -beam[:, c])
        setup.add(np.arange(n), self.column + 3 + run_index, 1.0)
        if self.n_scale:  # mm per ppm
            setup.add(np.arange(n), self.scale_column + run_index, distance * 1e-6)
        rows, cols, vals = setup.arrays()
        setup_part = scipy.sparse.csr_matrix((vals, (rows, cols)), shape=(n, n_columns))
        sigma = uncertainty.length_sigma_mm(distance)
        reading = np.arange(len(self.place.run))[chunk]
        kept = self.kept[reading].astype(float)
        return _Block(
            design=(tables_part + setup_part).tocsr(),
            observed=p.length_mm - distance + np.sum(beam * dp0, axis=1),
            whitening=scipy.sparse.diags(kept / (sigma * self.noise_factor)).tocsr(),
            ratio=kept,
            reading=reading,
        )

    def _point_design(
        self, chain: Chain, layout: ParameterLayout, p: TracerPlace, context: _RowContext
    ) -> scipy.sparse.csr_matrix:
        """:func:`point_design` of the rows ``p``; kept for the next step where the place
        is one chunk (a larger place would hold all its chunks' designs in memory)."""
        whole = len(p.run) == len(self.place.run)
        cached = self._designs.get(0)
        if whole and cached is not None and cached[0] is layout:
            return cached[1]
        design = point_design(chain, layout, p.machine_mm, context.arm_mm)
        if whole:
            self._designs[0] = (layout, design)
        return design

    def update(self, solution: Vec) -> float:
        step = solution[self.column : self.column + 3]
        self.pivot = self.pivot + step
        self.constants = solution[self.column + 3 : self.column + 3 + len(self.runs)].copy()
        return float(np.linalg.norm(step))


@dataclass
class _Normal:
    """The normal equations of whitened rows, accumulated chunk by chunk: ``A^T A``, ``A^T y``."""

    normal: Vec
    rhs: Vec


def _whitened(block: _Block) -> tuple[scipy.sparse.csr_matrix, Vec]:
    return (block.whitening @ block.design).tocsr(), block.whitening @ block.observed


def _accumulate(blocks: Iterable[_Block], n_columns: int) -> _Normal:
    """The normal equations of all the blocks' rows, one block (chunk) at a time."""
    normal = np.zeros((n_columns, n_columns))
    rhs = np.zeros(n_columns)
    for block in blocks:
        design, observed = _whitened(block)
        normal += (design.T @ design).toarray()
        rhs += design.T @ observed
    return _Normal(normal, rhs)


@dataclass
class _Solved:
    """The solution, the Cholesky factor of the column-scaled normal matrix, the column norms."""

    solution: Vec
    factor: tuple[Vec, bool]
    norms: Vec

    @functools.cached_property
    def inverse(self) -> Vec:
        """The scaled normal matrix's inverse."""
        return _inverse(self.factor)


def _solve(equations: _Normal, describe: Callable[..., str]) -> _Solved:
    norms = np.sqrt(np.diag(equations.normal))
    if np.any(norms == 0):
        raise GeometryError(f"no reading sees {describe(int(np.argmin(norms)))}")
    normal = equations.normal / np.outer(norms, norms)
    try:
        factor = scipy.linalg.cho_factor(normal, lower=False, check_finite=False)
        pivots = np.diag(factor[0]) ** 2
        singular = pivots.min() < _RANK_TOLERANCE * pivots.max()
    except np.linalg.LinAlgError:
        singular = True
    if singular:
        raise _undetermined(normal, describe)
    scaled = scipy.linalg.cho_solve(factor, equations.rhs / norms, check_finite=False)
    return _Solved(solution=scaled / norms, factor=factor, norms=norms)


@dataclass
class _Evaluated:
    """The rows at the solution, per block: residuals (raw and whitened), each whitened
    row's reading (-1: none) and whether it is kept, the sum of the hat matrix's diagonal
    over the block, and ``sum ratio a a^T`` of the column-scaled rows (GUM)."""

    raw: list[Vec]
    weighted: list[Vec]
    reading: list[np.ndarray]
    kept: list[np.ndarray]
    leverage: Vec
    middle: Vec

    @property
    def n_rows(self) -> int:
        return sum(len(w) for w in self.weighted)


def _evaluate(blocks: Iterable[tuple[int, _Block]], n_blocks: int, solved: _Solved) -> _Evaluated:
    """Residuals and what the covariance needs, one block (chunk) at a time."""
    parts: list[list[tuple[Vec, Vec, np.ndarray, np.ndarray]]] = [[] for _ in range(n_blocks)]
    leverage = np.zeros(n_blocks)
    middle = np.zeros_like(solved.inverse)
    unscale = scipy.sparse.diags(1.0 / solved.norms)
    for number, block in blocks:
        design = _whitened(block)[0] @ unscale
        residual = block.observed - block.design @ solved.solution
        rows = block.reading if block.reading is not None else np.full(len(block.ratio), -1)
        parts[number].append((residual, block.whitening @ residual, rows, block.ratio > 0))
        normal = (design.T @ design).toarray()
        leverage[number] += float(np.sum(normal * solved.inverse))
        if np.all(block.ratio == 1.0):
            middle += normal
        else:
            middle += (design.T @ scipy.sparse.diags(block.ratio) @ design).toarray()
    joined = [[np.concatenate(column) for column in zip(*part, strict=True)] for part in parts]
    raw, weighted, reading, kept = (list(column) for column in zip(*joined, strict=True))
    return _Evaluated(raw, weighted, reading, kept, leverage, middle)


def _undetermined(normal: Vec, describe: Callable[..., str]) -> GeometryError:
    """Names every table and instrument setup with a component in the null space."""
    values, vectors = np.linalg.eigh(normal)
    null = vectors[:, values <= _NULL_TOLERANCE * values[-1]]
    if null.shape[1] == 0:
        null = vectors[:, :1]
    involved = np.flatnonzero(np.sum(null**2, axis=1) > _INVOLVED)
    names = list(dict.fromkeys(describe(int(c), knot=False) for c in involved))
    tables = [name for name in names if not name.startswith(("the ", "a "))]
    setups = [name for name in names if name.startswith(("the ", "a "))]
    what = ", ".join(tables or setups)
    if tables and setups:
        what += f" (they trade with {', '.join(setups)})"
    return GeometryError(
        f"the data cannot determine {what}; measure more points, or from more places"
        " (tracer pivots not on one line)"
    )


def _covered(points_mm: Vec) -> tuple[Vec, Vec]:
    return points_mm.min(axis=0), points_mm.max(axis=0)


def fit_joint(
    lines: list[LineData],
    trackers: list[TrackerStation],
    tracers: list[TracerPlace],
    chain: Chain,
    channel_sigma: Vec,
    smr_offset_mm: Vec,
    tracker_uncertainty: TrackerUncertainty,
    tracer_uncertainty: TracerUncertainty,
    travel_mm: tuple[Vec, Vec] | None = None,
    knot_spacing_mm: float | None = None,
    smr_offsets_mm: Mapping[str, Vec] | None = None,
    expansion_ppm_per_k: float = 0.0,
    progress: Progress | None = None,
) -> JointFit:
    """One fit of the error tables to interferometer lines, tracker points and tracer lengths.

    Parameters
    ----------
    lines : list of LineData
        May be empty.
    trackers, tracers
        Tracker stations and tracer places (each may be empty, not both with no lines).
    chain : Chain
    channel_sigma : ndarray, shape (6,)
        The machine file's channel uncertainties, mm / rad.
    smr_offset_mm : ndarray, shape (3,)
        SMR centre from the CNC tool point in the MCS, mm (rows without an ``smr`` name).
    tracker_uncertainty, tracer_uncertainty
        The machine file's models (a row's own tracker uncertainty wins), with their
        systematic errors (``angle_systematic_urad``, ``scale_ppm``: unknowns with
        that prior).
    travel_mm : (ndarray, ndarray), optional
        Travel limits: the tables are written from end to end.
    knot_spacing_mm : float, optional
        Compensation-point spacing where no line sets it (default: chosen by
        generalised cross-validation, :func:`knot_spacing_candidates`); with lines,
        the spacing of the points that continue their tables (default 400 mm).
    smr_offsets_mm : mapping of str to ndarray (3,), optional
        The named SMR positions (MCS, mm) rows may name in their ``smr`` column.
    expansion_ppm_per_k : float
        The scales' expansion: rows with a material temperature are normalised to 20 degC.
    progress : callable, optional
        ``progress(done, total, what)`` after each chunk of the instruments' rows:
        points done of all in the pass ``what`` (a Gauss-Newton iteration, or the
        residuals and uncertainty at the end).

    Raises
    ------
    GeometryError
        A station, place or table the data cannot determine, a fit that does not
        settle or tables beyond what a machine can have (one line naming it).
    InputError
        An unknown SMR name, an absurd material temperature, a spacing out of
        range, or more than :data:`MAX_OUTLIERS` gross outliers.
    """
    if not trackers and not tracers:
        raise InputError("fit_joint needs tracker points or tracer lengths")
    sources = ", ".join(dict.fromkeys([s.source for s in trackers] + [p.source for p in tracers]))
    if not lines and not trackers and len(tracers) < MIN_TRACER_PLACES:
        raise GeometryError(
            f"{sources}: {len(tracers)} tracer place{'s' if len(tracers) != 1 else ''} cannot"
            f" place the points in space; measure from at least {MIN_TRACER_PLACES} places"
        )
    if knot_spacing_mm is not None and not (
        MIN_KNOT_SPACING_MM <= knot_spacing_mm <= MAX_KNOT_SPACING_MM
    ):
        raise InputError(
            f"knot spacing {knot_spacing_mm:g} mm: give {MIN_KNOT_SPACING_MM:g} to"
            f" {MAX_KNOT_SPACING_MM:g} mm"
        )
    smr_mm = np.asarray(smr_offset_mm, dtype=float)
    named = {name: np.asarray(v, dtype=float) for name, v in (smr_offsets_mm or {}).items()}
    used = _smr_positions([*trackers, *tracers], smr_mm, named)
    undetermined = [] if lines else unseen_with_smr_positions(chain, used)
    inputs = _Inputs(
        lines=lines,
        trackers=trackers,
        tracers=tracers,
        chain=chain,
        channel_sigma=np.asarray(channel_sigma, dtype=float),
        # without lines and with one SMR position the tables are the SMR's: its offset is
        # no lever arm (module docstring)
        setting=_Setting(
            smr_mm,
            named,
            bool(lines) or len(used) > 1,
            tracker_uncertainty,
            tracer_uncertainty,
            expansion_ppm_per_k,
            used,
        ),
        travel_mm=travel_mm,
        sources=sources,
        undetermined=undetermined,
        progress=progress,
    )
    if lines or knot_spacing_mm is not None:
        return _fit(inputs, knot_spacing_mm)
    return _fit_chosen_spacing(inputs)


@dataclass(frozen=True)
class _Inputs:
    """Everything one fit at one knot spacing needs."""

    lines: list[LineData]
    trackers: list[TrackerStation]
    tracers: list[TracerPlace]
    chain: Chain
    channel_sigma: Vec
    setting: _Setting
    travel_mm: tuple[Vec, Vec] | None
    sources: str
    undetermined: list[str]
    progress: Progress | None = None
    #: The reach (each axis's least and greatest coordinate, (2, 3)) and standing counts
    #: the knots are spread by, where not these rows' own (a thinned copy's: all rows').
    knot_basis: tuple[Vec, Vec] | None = None


def _smr_positions(
    instruments: list[TrackerStation | TracerPlace], default_mm: Vec, named_mm: Mapping[str, Vec]
) -> Vec:
    """The distinct SMR offsets the rows use, (M, 3) (unknown names are refused later)."""
    offsets = [
        default_mm if name is None else named_mm.get(name)
        for instrument in instruments
        for name in (set(instrument.smr) if len(instrument.smr) else {None})
    ]
    found = np.array([o for o in offsets if o is not None])
    return np.unique(found.round(6), axis=0)


def unseen_with_smr_positions(chain: Chain, offsets_mm: Vec) -> list[str]:
    """The rotations a point cannot see (:func:`unseen_rotations`) that these SMR offsets
    (M, 3) do not see either: a rotation about ``e`` is seen where two offsets differ
    across ``e`` (``|e x d| > 1 mm``)."""
    differences = offsets_mm[1:] - offsets_mm[0]
    names = []
    for name in unseen_rotations(chain):
        axis = np.eye(3)[_ROTATION_ABOUT[name[:2]]]
        lever = np.linalg.norm(np.cross(axis, differences), axis=1) if len(differences) else []
        if not np.any(np.asarray(lever) > _SMR_LEVER_MM):
            names.append(name)
    return names


def knot_spacing_candidates(reach_mm: Vec) -> list[float]:
    """Spacings tried, coarse to fine: the longest range measured over 2, 3, 4 ... 64, mm.

    Within :data:`MIN_KNOT_SPACING_MM` .. :data:`MAX_KNOT_SPACING_MM` (at least one).
    """
    longest = float(np.ptp(reach_mm, axis=0).max())
    spacings = [
        longest / n
        for n in _CANDIDATE_INTERVALS
        if MIN_KNOT_SPACING_MM <= longest / n <= MAX_KNOT_SPACING_MM
    ]
    return spacings or [float(np.clip(longest / 2, MIN_KNOT_SPACING_MM, MAX_KNOT_SPACING_MM))]


def spacing_sample(
    trackers: list[TrackerStation],
    tracers: list[TracerPlace],
    points: int = SPACING_SAMPLE_POINTS,
) -> tuple[list[TrackerStation], list[TracerPlace]]:
    """The rows the knot spacing is chosen on: all, or about ``points`` spread over all.

    Above ``points`` tracker points and tracer lengths in all, every station and
    place keeps every ``k``-th row of each of its runs in capture order
    (``k = ceil(total / points)``, the same for all), from a start drawn within
    the run's first ``k`` rows (seeded: the same copy every time; a run that
    repeats the last one's points keeps other ones). Every run keeps a row.
    """
    total = sum(len(s.run) for s in trackers) + sum(len(p.run) for p in tracers)
    if total <= points:
        return trackers, tracers
    stride = -(-total // points)
    rng = np.random.default_rng(_SPACING_SAMPLE_SEED)
    return (
        [s.rows(_every(s.run, stride, rng)) for s in trackers],
        [p.rows(_every(p.run, stride, rng)) for p in tracers],
    )


def _every(run: np.ndarray, stride: int, rng: np.random.Generator) -> np.ndarray:
    """Every ``stride``-th row of each run, from a random start within its first ``stride``."""
    _, group, sizes = np.unique(run, return_inverse=True, return_counts=True)
    order = np.argsort(group, kind="stable")  # each run's rows in capture order
    first = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    start = rng.integers(0, np.minimum(stride, sizes))
    within = np.arange(len(run)) - np.repeat(first, sizes)
    offset = within - np.repeat(start, sizes)
    return np.sort(order[(offset >= 0) & (offset % stride == 0)])


def _knot_basis(inputs: _Inputs) -> tuple[Vec, Vec]:
    """The reach ((N, 3) points, or their least and greatest) and standing counts (3,)."""
    if inputs.knot_basis is not None:
        return inputs.knot_basis
    reach = _instrument_points(inputs.trackers, inputs.tracers)
    return reach, _standing_positions(inputs.trackers, inputs.tracers)


def _fit_chosen_spacing(inputs: _Inputs) -> JointFit:
    """The fit at the knot spacing with the least generalised cross-validation score.

    Candidates from coarse to fine (:func:`knot_spacing_candidates`), every one
    scored (a score can stay flat or rise over several spacings and fall again,
    tenfold and more, where the tables first follow an error's wavelength:
    the least score so far is no minimum of the curve); the search stops where
    the data cannot determine a finer table, or where the tables would have more
    than a :data:`MAX_COLUMNS_PER_READING` share of the readings' components
    (noise-free or sparse data would otherwise go on to ever finer tables that
    interpolate the readings and swing between them). Above
    :data:`SPACING_SAMPLE_POINTS` rows the candidates are scored on
    :func:`spacing_sample` (knots spread over all rows' reach), and all rows are
    then fitted once at the chosen spacing.
    """
    reach = _instrument_points(inputs.trackers, inputs.tracers)
    standing = _standing_positions(inputs.trackers, inputs.tracers)
    trackers, tracers = spacing_sample(inputs.trackers, inputs.tracers, SPACING_SAMPLE_POINTS)
    thinned = trackers is not inputs.trackers or tracers is not inputs.tracers
    scored = inputs
    if thinned:
        bounds = np.stack([reach.min(axis=0), reach.max(axis=0)])
        scored = dataclasses.replace(
            inputs, trackers=trackers, tracers=tracers, knot_basis=(bounds, standing)
        )
    components = sum(2 * int(s.on_the_fly.sum()) + 3 * int((~s.on_the_fly).sum()) for s in trackers)
    components += sum(len(p.run) for p in tracers)
    best: tuple[float, _System] | None = None
    previous: _System | None = None
    scores: list[tuple[float, float]] = []
    knots_tried: set[tuple[int, ...]] = set()
    for spacing in knot_spacing_candidates(reach):
        knots = instrument_knots(reach, spacing, standing, inputs.sources)
        counts = tuple(len(k) for k in knots.values())
        if counts in knots_tried:
            continue
        knots_tried.add(counts)
        layout, _ = _joint_layout(scored, spacing)
        if best is not None and layout.n_columns > MAX_COLUMNS_PER_READING * components:
            break
        try:
            system = _System(scored, spacing, start=previous)
        except GeometryError:
            if best is None:
                raise
            break  # finer than the data can determine
        previous = system
        scores.append((spacing, system.gcv))
        if best is None or system.gcv < best[1].gcv:
            best = (spacing, system)
    assert best is not None  # the coarsest candidate either fitted or raised
    chosen = _System(inputs, best[0], start=best[1]) if thinned else best[1]
    joint = _fit(inputs, best[0], chosen)
    joint.spacing_scores = scores
    return joint


class _System:
    """The joint system at one knot spacing, settled with the instruments' own models.

    ``start``: a fit at another spacing whose poses, pivots and constants to start
    from (their closed-form starts otherwise).
    """

    def __init__(
        self, inputs: _Inputs, knot_spacing_mm: float | None, start: _System | None = None
    ) -> None:
        lines, chain = inputs.lines, inputs.chain
        self.layout, line_knots = _joint_layout(inputs, knot_spacing_mm)
        self.setup = SetupLayout(lines, self.layout.n_columns)
        states = _States(
            inputs.trackers,
            inputs.tracers,
            inputs.setting,
            self.layout.n_columns + self.setup.n_columns,
        )
        if start is not None:
            states.start_from(start.states)
        self.states: _States = states
        describe = _describer(self.layout, self.setup, states)
        self.line_block, self.alone, self.line_sigma = _line_block(
            lines, chain, self.layout, self.setup, inputs.channel_sigma, states.n_columns
        )
        fixed_blocks = [self.line_block] if self.line_block is not None else []
        if self.alone is not None:
            prior = _continuation_block(
                self.layout, line_knots, self.alone.tables, unseen_rotations(chain),
                states.n_columns,
            )  # fmt: skip
            fixed_blocks += [prior] if prior is not None else []
        self.fixed_blocks = fixed_blocks + states.priors()
        self.settle = _Settler(
            states, chain, self.layout, self.fixed_blocks, describe, inputs.sources,
            inputs.progress,
        )  # fmt: skip
        self.evaluated, self.solved = self.settle(np.zeros(states.n_columns))
        self.outliers, self.evaluated, self.solved = _leave_out_outliers(
            states, self.settle, self.evaluated, self.solved
        )
        self.correlation = _correlations(states, self.evaluated, len(self.fixed_blocks))
        self.gcv = _gcv(self.evaluated, len(self.fixed_blocks), self.correlation)


def _fit(inputs: _Inputs, knot_spacing_mm: float | None, system: _System | None = None) -> JointFit:
    """The joint fit at one knot spacing (with lines: of the points beyond them).

    ``system``: that spacing's system, already settled.
    """
    lines = inputs.lines
    system = system or _System(inputs, knot_spacing_mm)
    layout, setup, states, settle = system.layout, system.setup, system.states, system.settle
    line_block, alone, line_sigma = system.line_block, system.alone, system.line_sigma
    fixed_blocks, outliers, solved = system.fixed_blocks, system.outliers, system.solved
    evaluated, first = system.evaluated, len(system.fixed_blocks)
    sigma0 = _sigma0(evaluated, states.n_columns)
    correlation = system.correlation
    factors = _noise_factors(evaluated, first) * np.sqrt(correlation)
    widened = 1.0
    if np.any(factors > 1.0 + FACTOR_TOLERANCE):
        states.set_noise_factors(factors)
        if len(evaluated.weighted) == 1:  # one instrument alone: weighting it down moves nothing
            widened = float(factors[0]) ** 2
        else:
            evaluated, solved = settle(solved.solution)
    covariance = (
        solved.inverse
        @ evaluated.middle
        @ solved.inverse
        / np.outer(solved.norms, solved.norms)
        * widened
    )
    raw = evaluated.raw
    table_set = _tables(layout, solved.solution, covariance, inputs.travel_mm)
    for name in inputs.undetermined:
        table_set.tables[name].u95[:] = np.nan
    _refuse_beyond_bounds(table_set, inputs.sources)
    sizes = [N_CHANNELS * len(d.run) for d in lines]
    fit = TableFit(
        tables=table_set,
        setup=setup.unpack(solved.solution),
        residual_rms=_residual_rms(
            lines,
            [int(r) for r in np.cumsum([0, *sizes])[: len(lines)]],
            _line_residual(line_block, raw),
        ),
        sigma0=sigma0,
        n_observations=evaluated.n_rows,
        n_parameters=states.n_columns,
        channel_scatter=line_sigma,
        outliers=alone.outliers if alone is not None else [],
    )
    instrument_raw = raw[len(fixed_blocks) :]
    n_trackers = len(states.trackers)
    return JointFit(
        fit=fit,
        trackers=[
            _tracker_fit(s, r, solved.solution, covariance, c)
            for s, r, c in zip(states.trackers, instrument_raw, correlation, strict=False)
        ],
        tracers=[
            _tracer_fit(t, r, solved.solution, covariance)
            for t, r in zip(states.tracers, instrument_raw[n_trackers:], strict=True)
        ],
        undetermined=inputs.undetermined,
        iterations=settle.iterations,
        functional_point="SMR" if inputs.undetermined else "tool point",
        knot_spacing_mm=knot_spacing_mm,
        gcv=system.gcv,
        outliers=outliers,
        layout=layout,
        covariance=covariance,
    )


class _Settler:
    """Gauss-Newton until no pose, pivot or table value moves any more.

    Raises
    ------
    GeometryError
        When it has not settled after :data:`_MAX_ITERATIONS` (one line naming the files).
    """

    def __init__(
        self,
        states: _States,
        chain: Chain,
        layout: ParameterLayout,
        fixed_blocks: list[_Block],
        describe: Callable[..., str],
        sources: str,
        progress: Progress | None = None,
    ) -> None:
        self.states, self.chain, self.layout = states, chain, layout
        self.fixed_blocks, self.describe, self.sources = fixed_blocks, describe, sources
        self.progress = progress
        self.iterations = 0

    def rows(self, states: _States, tables: Vec, what: str) -> Iterator[tuple[int, _Block]]:
        """Every block's rows, numbered (fixed blocks whole, the instruments in chunks),
        telling ``progress`` how far the pass ``what`` is."""
        yield from enumerate(self.fixed_blocks)
        done = 0
        for number, points, block in states.chunks(self.chain, self.layout, tables):
            yield len(self.fixed_blocks) + number, block
            done += points
            if self.progress is not None:
                self.progress(done, states.n_points, what)

    def __call__(self, tables: Vec) -> tuple[_Evaluated, _Solved]:
        """Settle from ``tables``; the rows at the solution (about the last linearisation)."""
        step = table_step = np.inf
        n_blocks = len(self.fixed_blocks) + len(self.states.all)
        for _ in range(_MAX_ITERATIONS):
            self.iterations += 1
            before = self.states.snapshot()
            rows = self.rows(before, tables, f"iteration {self.iterations}")
            solved = _solve(_accumulate((b for _, b in rows), self.states.n_columns), self.describe)
            step = self.states.update(solved.solution)
            table_step = float(np.max(np.abs(solved.solution - tables)[: self.layout.n_columns]))
            if step < _STEP_TOLERANCE_MM and table_step < _STEP_TOLERANCE_MM:
                rows = self.rows(before, tables, "residuals and uncertainty")
                return _evaluate(rows, n_blocks, solved), solved
            tables = solved.solution
        raise GeometryError(
            f"{self.sources}: the fit did not settle in {_MAX_ITERATIONS} iterations (a pose or"
            f" pivot still moved {step:.2g} mm, a table value {table_step:.2g}); check the"
            " instruments' units and setups and that the points are the commanded ones"
        )


def _leave_out_outliers(
    states: _States, settle: _Settler, evaluated: _Evaluated, solved: _Solved
) -> tuple[list[InstrumentOutlier], _Evaluated, _Solved]:
    """Leave out gross outliers one at a time, the worst first, refitting after each; the
    outliers and the last fit.

    A reading is one where a whitened residual is more than :data:`OUTLIER_SIGMAS`
    times the larger of 1 (its uncertainty model) and its instrument's robust scatter
    (1.4826 x the median absolute whitened residual), as for the lines.

    Raises
    ------
    InputError
        More than :data:`MAX_OUTLIERS` of them: the measurement, not a reading, is wrong.
    """
    outliers: list[InstrumentOutlier] = []
    first = len(evaluated.weighted) - len(states.all)
    while (worst := _worst_reading(states, evaluated, first)) is not None:
        state, reading, sigmas = worst
        outliers.append(state.outlier(reading, sigmas))
        if len(outliers) > MAX_OUTLIERS:
            raise InputError(
                f"{settle.sources}: more than {MAX_OUTLIERS} readings are gross outliers (over"
                f" {OUTLIER_SIGMAS:g} standard deviations off the fit, e.g. {outliers[0].name}):"
                " the measurement is not usable; check units, setups and points"
            )
        state.kept[reading] = False
        evaluated, solved = settle(solved.solution)
    return outliers, evaluated, solved


def _worst_reading(
    states: _States, evaluated: _Evaluated, first: int
) -> tuple[_TrackerState | _TracerState, int, float] | None:
    worst: tuple[_TrackerState | _TracerState, int, float] | None = None
    for number, state in enumerate(states.all, start=first):
        whitened, kept = np.abs(evaluated.weighted[number]), evaluated.kept[number]
        scale = max(1.0, 1.4826 * float(np.median(whitened[kept])))
        sigmas = np.zeros(len(state.kept))
        np.maximum.at(sigmas, evaluated.reading[number][kept], whitened[kept] / scale)
        reading = int(np.argmax(sigmas))
        if sigmas[reading] > OUTLIER_SIGMAS and (worst is None or sigmas[reading] > worst[2]):
            worst = (state, reading, float(sigmas[reading]))
    return worst


def _refuse_beyond_bounds(tables: ErrorTableSet, sources: str) -> None:
    """Tables beyond what a machine can have (the error-table format's bound) are refused.

    Raises
    ------
    GeometryError
        Naming the worst table: the data do not fit the model (units, wrong points).
    """
    values = [(name, t.values, t.u95) for name, t in tables.tables.items()]
    values += [(name, np.array([v]), np.array([u])) for name, (v, u) in tables.squareness.items()]
    for name, value, u95 in values:
        limit = MAX_ERROR_MM if file_unit(name) == "um" else MAX_ERROR_RAD
        worst = float(np.nanmax(np.abs(np.concatenate([value, u95, [0.0]]))))
        if worst > limit:
            unit, scale = ("um", 1e3) if limit == MAX_ERROR_MM else ("urad", 1e6)
            raise GeometryError(
                f"{sources}: the fit gives {name} {worst * scale:.3g} {unit} (value or u95),"
                f" more than a machine can have ({limit * scale:g} {unit}); the readings do"
                " not fit the commanded points (units? points of another program?)"
            )


def _joint_layout(
    inputs: _Inputs, knot_spacing_mm: float | None
) -> tuple[ParameterLayout, dict[str, Vec]]:
    """The table columns and the lines' own knots (or the instruments').

    With lines: their compensation points continued to the instruments' reach at
    ``knot_spacing_mm`` (default :data:`EXTENSION_SPACING_MM`), the reversal only
    where the lines measured it. Without: points spread over the instruments'
    range at ``knot_spacing_mm``, and the rotations no reading can see left out.
    """
    reach, standing = _knot_basis(inputs)
    if inputs.lines:
        line_knots = compensation_points(inputs.lines)
        spacing = EXTENSION_SPACING_MM if knot_spacing_mm is None else knot_spacing_mm
        knots = {
            a: _beyond_lines(k, reach[:, AXIS_INDEX[a]], spacing) for a, k in line_knots.items()
        }
        layout = ParameterLayout(knots, bidirectional_axes(inputs.lines))
        return _reversal_within(layout, line_knots), line_knots
    assert knot_spacing_mm is not None  # chosen by _fit_chosen_spacing
    knots = instrument_knots(reach, knot_spacing_mm, standing, inputs.sources)
    return _without_tables(ParameterLayout(knots, set()), inputs.undetermined), knots


class _States:
    """The tracker stations and tracer places being fitted, their columns after ``first``."""

    def __init__(
        self,
        trackers: list[TrackerStation],
        tracers: list[TracerPlace],
        setting: _Setting,
        first: int,
    ) -> None:
        self.setting = setting
        self.shift_column = first  # the SMR positions' corrections, then each instrument
        column = first + 3 * (len(setting.smr_positions_mm) - 1)
        self.first_instrument_column = column
        self.trackers: list[_TrackerState] = []
        for station in trackers:
            self.trackers.append(_TrackerState(station, setting, column, first))
            column += self.trackers[-1].n_columns
        self.tracers: list[_TracerState] = []
        for place in tracers:
            self.tracers.append(_TracerState(place, setting, column, first))
            column += self.tracers[-1].n_columns
        self.n_columns = column

    @property
    def all(self) -> list[_TrackerState | _TracerState]:
        return [*self.trackers, *self.tracers]

    def priors(self) -> list[_Block]:
        """The prior rows of the instruments' systematic errors."""
        return [block for state in self.all for block in state.prior(self.n_columns)]

    @property
    def n_points(self) -> int:
        """Tracker points and tracer lengths, all stations and places."""
        return sum(len(s.station.run) for s in self.trackers) + sum(
            len(t.place.run) for t in self.tracers
        )

    def chunks(
        self, chain: Chain, layout: ParameterLayout, tables: Vec
    ) -> Iterator[tuple[int, int, _Block]]:
        """Each instrument's rows about the current tables, poses and pivots, in chunks.

        Yields the instrument's number (trackers, then tracers), the chunk's points
        and its rows: at most :data:`CHUNK_POINTS` points at once, so a million rows
        never stand in memory as one design matrix.
        """
        linearisers: list[tuple[int, Callable[[slice], _Block]]] = [
            (
                len(s.station.run),
                partial(s.linearise, chain, layout, tables, self.n_columns, self.setting.tracker),
            )
            for s in self.trackers
        ]
        linearisers += [
            (
                len(t.place.run),
                partial(t.linearise, chain, layout, tables, self.n_columns, self.setting.tracer),
            )
            for t in self.tracers
        ]
        for number, (n, linearise) in enumerate(linearisers):
            for first in range(0, n, CHUNK_POINTS):
                chunk = slice(first, min(first + CHUNK_POINTS, n))
                yield number, chunk.stop - chunk.start, linearise(chunk)

    def snapshot(self) -> _States:
        """A copy whose poses and pivots later updates leave as they are now."""
        copied = copy.copy(self)
        copied.trackers = [copy.copy(s) for s in self.trackers]
        copied.tracers = [copy.copy(t) for t in self.tracers]
        return copied

    def update(self, solution: Vec) -> float:
        """Apply a solution's increments; the largest move of a pose or pivot, mm."""
        return max([state.update(solution) for state in self.all] + [0.0])

    def set_noise_factors(self, factors: Vec) -> None:
        for state, factor in zip(self.all, factors, strict=True):
            state.noise_factor = float(factor)

    def start_from(self, other: _States) -> None:
        """Start from another fit's poses, pivots and constants (the same instruments)."""
        for state, settled in zip(self.trackers, other.trackers, strict=True):
            state.rotation, state.offset = settled.rotation, settled.offset
        for tracer, done in zip(self.tracers, other.tracers, strict=True):
            tracer.pivot, tracer.constants = done.pivot, done.constants


def _describer(layout: ParameterLayout, setup: SetupLayout, states: _States) -> Callable[..., str]:
    """A person's name for a column of the joint system (``knot``: with the table's knot)."""

    def describe(c: int, knot: bool = True) -> str:
        if c < layout.n_columns:
            return layout.describe(c) if knot else str(layout.table_name(c))
        line = setup.line_of(c)
        if line is not None:
            return f"the setup terms of line {line}"
        if c < states.first_instrument_column:
            return "the correction of an SMR position"
        for state in states.all:
            if 0 <= c - state.column < state.n_columns:
                return state.describe(c - state.column)
        return f"column {c}"

    return describe


def _sigma0(evaluated: _Evaluated, n_columns: int) -> float:
    """Square root of the a-posteriori variance factor of a solved system."""
    squares = sum(float(w @ w) for w in evaluated.weighted)
    return float(np.sqrt(squares / max(evaluated.n_rows - n_columns, 1)))


def _line_block(
    lines: list[LineData],
    chain: Chain,
    layout: ParameterLayout,
    setup: SetupLayout,
    channel_sigma: Vec,
    n_columns: int,
) -> tuple[_Block | None, TableFit | None, Vec]:
    """The lines' rows, weighted with the scatter a lines-only fit estimates (its sigma floor).

    The covariance is propagated with the larger of that scatter and the machine
    file's uncertainty, as :func:`xmalign.post.solve.fit_error_tables` does; the
    readings that fit left out as gross outliers get no weight here either. Also
    returns the lines-only fit (None when the lines alone are undetermined) and
    the channels' standard deviations the rows are weighted with (mm / rad).
    """
    prior = np.asarray(channel_sigma, dtype=float)
    if not lines:
        return None, None, prior
    alone: TableFit | None
    try:
        alone = fit_error_tables(lines, chain, prior)
        sigma = alone.channel_scatter
    except (GeometryError, InputError):  # the lines need the instruments to determine them
        alone, sigma = None, prior
    triplets = Triplets()
    first_rows = add_line_rows(lines, chain, layout, setup, triplets)
    rows, cols, vals = triplets.arrays()
    n_rows = N_CHANNELS * sum(len(d.run) for d in lines)
    design = scipy.sparse.csr_matrix((vals, (rows, cols)), shape=(n_rows, n_columns))
    repeats = n_rows // N_CHANNELS
    weights = np.tile(1.0 / sigma, repeats)
    for outlier in alone.outliers if alone is not None else []:
        weights[first_rows[outlier.line] + N_CHANNELS * outlier.point + outlier.channel] = 0.0
    block = _Block(
        design=design,
        observed=np.concatenate([d.channels.ravel() for d in lines]),
        whitening=scipy.sparse.diags(weights).tocsr(),
        ratio=np.tile((np.maximum(prior, sigma) / sigma) ** 2, repeats),
    )
    return block, alone, sigma


def _line_residual(line_block: _Block | None, raw: list[Vec]) -> Vec:
    """The lines' residuals (mm / rad), NaN for the readings left out as outliers."""
    if line_block is None:
        return np.zeros(0)
    return np.where(line_block.whitening.diagonal() > 0, raw[0], np.nan)


def _noise_factors(evaluated: _Evaluated, first: int) -> Vec:
    """Per instrument block, its scatter over its uncertainty model (type A), at least 1.

    Each block's weighted residuals over its redundancy (the sum of ``1 - h_ii``
    of its kept rows, ``h`` the hat matrix), as the lines' channels get in
    :func:`xmalign.post.solve.fit_error_tables`; kept at 1 or above, so the u95
    never claims better than the instrument's own uncertainty (the machine's
    repeatability, for one, adds to every reading). ``first``: the first
    instrument block (the lines and the priors come before).
    """
    factors = []
    for number in range(first, len(evaluated.weighted)):
        weighted = evaluated.weighted[number]
        redundancy = max(float(np.sum(evaluated.kept[number])) - evaluated.leverage[number], 1.0)
        factors.append(max(1.0, np.sqrt(float(weighted @ weighted) / redundancy)))
    return np.array(factors)


def _gcv(evaluated: _Evaluated, first: int, correlation: Vec) -> float:
    """Generalised cross-validation score of the instruments' readings (Craven & Wahba).

    ``N * RSS / (N - tau tr H)**2`` over the instruments' kept rows (the blocks from
    ``first`` on), weighted with their uncertainty models: an estimate of the mean
    squared error with which the fit predicts a reading it was not given, without
    refitting. ``tr H`` over those rows is the sum of their blocks' leverage;
    ``tau`` the rows' mean ``correlation`` (per instrument block,
    :func:`correlation_samples`): with noise correlated along a tracker's paths
    only ``N / tau`` rows are independent, so each degree of freedom of the tables
    costs ``tau`` rows (Altman 1990); without it the score keeps falling as ever
    finer tables follow the correlated noise. 1 for independent readings.
    """
    counts = np.array([float(np.sum(kept)) for kept in evaluated.kept[first:]])
    rows = float(counts.sum())
    tau = float(counts @ correlation) / max(rows, 1.0)
    freedom = rows - tau * float(np.sum(evaluated.leverage[first:]))
    squares = sum(float(w @ w) for w in evaluated.weighted[first:])
    return rows * squares / max(freedom, 1.0) ** 2


def _correlations(states: _States, evaluated: _Evaluated, first: int) -> Vec:
    """Per instrument block (trackers, then tracers): :func:`correlation_samples` of its
    whitened residuals; 1 for tracer places (lengths seconds apart)."""
    correlation = np.ones(len(states.all))
    for k, state in enumerate(states.trackers):
        correlation[k] = correlation_samples(state.station, evaluated.weighted[first + k])
    return correlation


def correlation_samples(station: TrackerStation, weighted: Vec) -> float:
    """How many consecutive points on the fly one point's noise is worth, at least 1.

    The integrated autocorrelation time ``tau = 1 + 2 sum_k rho_k`` of the
    whitened residuals across the path, taken per path in the file's order (the
    order of capture), pooled over the paths and both components; the sum runs
    over the lags while ``rho_k`` is significant (above ``2 / sqrt(pairs)``).
    Correlated noise averages out ``tau`` times slower than white noise: the
    station's weights are divided by ``tau`` (its u95 widened by ``sqrt(tau)``).
    Points at a standstill (seconds apart) are taken as independent.
    """
    fly = station.on_the_fly
    if fly.sum() < 3:
        return 1.0
    height = np.where(fly, 2, 3)
    first_row = np.concatenate([[0], np.cumsum(height)[:-1]])
    across = np.stack([weighted[first_row[fly]], weighted[first_row[fly] + 1]], axis=1)
    paths = np.concatenate([station.machine_mm[fly], station.to_mm[fly]], axis=1)
    group = np.ravel(np.unique(paths, axis=0, return_inverse=True)[1])
    order = np.argsort(group, kind="stable")
    sequence, group = across[order], group[order]
    variance = float(np.mean(np.sum(sequence**2, axis=1)))
    if variance == 0.0:
        return 1.0
    tau = 1.0
    for lag in range(1, min(_MAX_LAG, len(sequence) // 4) + 1):
        same = group[lag:] == group[:-lag]
        pairs = int(same.sum())
        if pairs < 2:
            break
        products = np.sum(sequence[lag:][same] * sequence[:-lag][same], axis=1)
        rho = float(np.mean(products)) / variance
        if rho <= 2.0 / np.sqrt(pairs):
            break
        tau += 2.0 * rho
    return tau


def _u95(covariance: Vec) -> Vec:
    return K_EXPANSION * np.sqrt(np.maximum(np.diag(covariance), 0.0))


def _scales(
    state: _TrackerState | _TracerState, first: int, solution: Vec, covariance: Vec
) -> tuple[dict[int, float], dict[int, float]]:
    """The fitted scale per run and its u95 (ppm), empty without a scale prior."""
    columns = first + np.arange(state.n_scale)
    u95 = _u95(covariance[np.ix_(columns, columns)]) if state.n_scale else np.zeros(0)
    return (
        {r: float(solution[c]) for r, c in zip(state.runs, columns, strict=False)},
        {r: float(u) for r, u in zip(state.runs, u95, strict=False)},
    )


def _tracker_fit(
    state: _TrackerState, residual: Vec, solution: Vec, covariance: Vec, correlation: float
) -> TrackerStationFit:
    s = state.station
    direction = s.directions()
    columns = state.column + np.arange(6)
    block = covariance[np.ix_(columns, columns)]
    origin = -state.rotation.T @ state.offset  # the tracker's origin in the MCS
    jacobian = np.hstack([skew(origin), -np.eye(3)])
    still = ~s.on_the_fly
    vectors = residual.reshape(-1, 3)
    along = np.sum(vectors * direction, axis=1)  # 0 at a standstill
    squares = np.sum((vectors - along[:, None] * direction) ** 2, axis=1)[state.kept]
    angles = state.column + _TRACKER_SETUP + np.arange(state.n_angle)
    scale, scale_u95 = _scales(state, state.scale_column, solution, covariance)
    return TrackerStationFit(
        label=s.label,
        source=s.source,
        n_points=len(s.run),
        rotation_urad=Rotation.from_matrix(state.rotation.T).as_rotvec() * 1e6,
        rotation_u95_urad=_u95(block[:3, :3]) * 1e6,
        position_mm=origin,
        position_u95_mm=_u95(jacobian @ block @ jacobian.T),
        residual_rms_um=float(np.sqrt(np.mean(squares)) * 1e3),
        covered_mm=_covered(np.concatenate([s.machine_mm, s.to_mm[~still]])),
        scatter_factor=state.noise_factor / np.sqrt(correlation),
        correlation_samples=correlation,
        angle_coefficients_urad=solution[angles] * 1e6,
        angle_coefficients_u95_urad=_u95(covariance[np.ix_(angles, angles)]) * 1e6,
        scale_ppm=scale,
        scale_u95_ppm=scale_u95,
    )


def _tracer_fit(
    state: _TracerState, residual: Vec, solution: Vec, covariance: Vec
) -> TracerPlaceFit:
    p = state.place
    columns = state.column + np.arange(3 + len(state.runs))
    u95 = _u95(covariance[np.ix_(columns, columns)])
    scale, scale_u95 = _scales(state, state.scale_column, solution, covariance)
    return TracerPlaceFit(
        label=p.label,
        source=p.source,
        n_lengths=len(p.run),
        pivot_mm=state.pivot.copy(),
        pivot_u95_mm=u95[:3],
        constant_mm={r: float(k) for r, k in zip(state.runs, state.constants, strict=True)},
        constant_u95_mm={r: float(u) for r, u in zip(state.runs, u95[3:], strict=True)},
        residual_rms_um=float(np.sqrt(np.mean(residual[state.kept] ** 2)) * 1e3),
        covered_mm=_covered(p.machine_mm),
        scatter_factor=state.noise_factor,
        scale_ppm=scale,
        scale_u95_ppm=scale_u95,
    )
