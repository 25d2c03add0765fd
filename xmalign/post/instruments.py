"""Laser-tracker points and laser-tracer lengths in the same fit as the interferometer lines.

One set of error tables and squareness (:mod:`xmalign.post.solve`'s layout and
basis) is fitted to every reading at once; each instrument brings its own setup
unknowns:

- a **tracker station**: its pose, ``t = R (p + dp) + c`` with ``t`` the SMR
  centre in the tracker's frame, ``p`` the commanded SMR point in the MCS and
  ``dp`` the machine's deviation there (seed 000); six unknowns;
- a **tracer place**: its pivot ``q`` (three unknowns) and one constant ``k``
  per run, ``L = |p + dp - q| + k`` (self-calibration, seed 004).

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

A point only gives the position of the SMR. Without interferometer lines the
angular errors whose lever arm never changes cannot be seen (the rotations of the
last axis of the tool side, and the rotation about the only axis that moves a
lever arm); the tables are then those of the SMR as the functional point, and
those rotations are written as 0 with no u95 (docs/post.md).

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
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from functools import partial

import numpy as np
import scipy.linalg
import scipy.sparse
from scipy.spatial.transform import Rotation

from xmalign.errors import GeometryError, InputError
from xmalign.formats.columns import LengthRows, PointRows
from xmalign.formats.error_tables import ErrorTableSet
from xmalign.formats.instruments import TracerFile, TrackerFile
from xmalign.geometry import Vec, skew
from xmalign.machine import TracerUncertainty, TrackerUncertainty
from xmalign.post.compare import rigid_motion_design
from xmalign.post.lines import LineData
from xmalign.post.setup_terms import N_CHANNELS, SetupLayout, Triplets
from xmalign.post.solve import (
    K_EXPANSION,
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

#: Spacing of the compensation points where only instruments measured, mm: tracer
#: lengths (sub-micrometre) resolve a finer table than tracker points (5-15 um), where
#: more points would only carry more noise (tests/benchmarks/bench_instruments.py).
TRACER_KNOT_SPACING_MM = 200.0
TRACKER_KNOT_SPACING_MM = 250.0
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
_FACTOR_TOLERANCE = 0.05


@dataclass(frozen=True)
class TrackerStation:
    """The points of one tracker station (mm).

    ``to_mm`` is NaN for points at a standstill; ``u_radial_mm`` and
    ``u_transverse_mm`` are NaN where the machine file's model applies.
    """

    label: str
    source: str
    run: np.ndarray
    machine_mm: Vec
    tracker_mm: Vec
    to_mm: Vec
    u_radial_mm: Vec
    u_transverse_mm: Vec

    @property
    def on_the_fly(self) -> np.ndarray:
        return ~np.isnan(self.to_mm[:, 0])

    def rows(self, rows: slice) -> TrackerStation:
        """The station with only these rows (a chunk of the fit)."""
        return dataclasses.replace(
            self,
            run=self.run[rows],
            machine_mm=self.machine_mm[rows],
            tracker_mm=self.tracker_mm[rows],
            to_mm=self.to_mm[rows],
            u_radial_mm=self.u_radial_mm[rows],
            u_transverse_mm=self.u_transverse_mm[rows],
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
    """The lengths of one tracer place (mm), with the file's coarse pivot guess if any."""

    label: str
    source: str
    run: np.ndarray
    machine_mm: Vec
    length_mm: Vec
    guess_mm: Vec | None = None

    @property
    def runs(self) -> list[int]:
        return sorted({int(r) for r in self.run})

    def rows(self, rows: slice) -> TracerPlace:
        """The place with only these lengths (a chunk of the fit)."""
        return dataclasses.replace(
            self,
            run=self.run[rows],
            machine_mm=self.machine_mm[rows],
            length_mm=self.length_mm[rows],
        )


def _labels(keys: list[tuple[str, str]]) -> list[str]:
    """Station names, with the file's name where two files use the same one."""
    names = [station for _, station in keys]
    return [
        station if names.count(station) == 1 else f"{station}@{source}" for source, station in keys
    ]


def _tracker_columns(file: TrackerFile) -> dict[str, np.ndarray]:
    """A file's points as columns (read as columns, or gathered from its points)."""
    if isinstance(file.points, PointRows):
        return file.points.columns
    points = file.points
    nan3 = np.full(3, np.nan)
    return {
        "station": np.array([p.station for p in points], dtype=object),
        "run": np.array([p.run for p in points], dtype=int),
        "machine_mm": np.reshape([p.machine_mm for p in points], (-1, 3)),
        "tracker_mm": np.reshape([p.tracker_mm for p in points], (-1, 3)),
        "to_mm": np.reshape([nan3 if p.to_mm is None else p.to_mm for p in points], (-1, 3)),
        "u_radial_um": np.array(
            [np.nan if p.u_radial_um is None else p.u_radial_um for p in points]
        ),
        "u_transverse_um": np.array(
            [np.nan if p.u_transverse_um is None else p.u_transverse_um for p in points]
        ),
    }


def _tracer_columns(file: TracerFile) -> dict[str, np.ndarray]:
    """A file's lengths as columns (read as columns, or gathered from its lengths)."""
    if isinstance(file.lengths, LengthRows):
        return file.lengths.columns
    lengths = file.lengths
    return {
        "station": np.array([r.station for r in lengths], dtype=object),
        "run": np.array([r.run for r in lengths], dtype=int),
        "machine_mm": np.reshape([r.machine_mm for r in lengths], (-1, 3)),
        "length_mm": np.array([r.length_mm for r in lengths], dtype=float),
    }


def _grouped(
    sources: list[tuple[str, dict[str, np.ndarray]]],
) -> list[tuple[str, str, str, np.ndarray, dict[str, np.ndarray]]]:
    """(source, station, label, rows) of each (file, station), in the order first seen."""
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
    groups = _grouped([(file.source, _tracker_columns(file)) for file in files])
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
        )
        for source, _, label, rows, columns in groups
    ]


def tracer_places(files: list[TracerFile]) -> list[TracerPlace]:
    """Group the lengths of tracer files by (file, station), with the pivot guesses."""
    groups = _grouped([(file.source, _tracer_columns(file)) for file in files])
    guesses = {(file.source, name): g for file in files for name, g in file.guesses_mm.items()}
    return [
        TracerPlace(
            label=label,
            source=source,
            run=columns["run"][rows],
            machine_mm=columns["machine_mm"][rows],
            length_mm=columns["length_mm"][rows],
            guess_mm=guesses.get((source, station)),
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


@dataclass
class JointFit:
    """Result of the joint fit.

    ``fit`` holds the tables and the lines' setup and residuals as a lines-only
    fit would; ``undetermined`` names the rotation tables the point data cannot
    see (instrument-only fits: written as 0 with no u95); ``converged`` says
    whether the iteration settled within ``iterations``.
    """

    fit: TableFit
    trackers: list[TrackerStationFit]
    tracers: list[TracerPlaceFit]
    undetermined: list[str]
    iterations: int
    converged: bool
    functional_point: str = "tool point"
    layout: ParameterLayout | None = field(default=None, repr=False)
    covariance: Vec | None = field(default=None, repr=False)

    def volumetric_u_um(self, chain: Chain, points_mm: Vec) -> float:
        """RMS standard uncertainty of the fitted volumetric error at points, um.

        ``sqrt(mean(trace(J C J^T)))`` with ``J`` the points' sensitivity to the
        table values, less its rigid motion (as the comparison with a truth removes
        it, :func:`xmalign.post.compare.volumetric_rms_um`), and ``C`` their
        covariance: what the readings' noise leaves in the tables (the information
        limit of the measurement), not the tables' model error.
        """
        assert self.layout is not None and self.covariance is not None
        n = self.layout.n_columns
        design = point_design(chain, self.layout, points_mm, np.zeros(3)).toarray()
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
        n = int(min(max(3, np.ceil((high - low) / spacing_mm) + 1), standing[k]))
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
    """
    n = len(machine_mm)
    arms = chain.lever_arms(machine_mm, t_mm)
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
    """Rows of the linearised system: design, observations, whitening (all sparse/arrays)."""

    design: scipy.sparse.csr_matrix
    observed: Vec
    whitening: scipy.sparse.csr_matrix
    ratio: Vec  # (propagated / weighting variance) per whitened row


def _start_pairs(station: TrackerStation) -> tuple[Vec, Vec]:
    """Commanded and measured points that roughly correspond, for the closed-form start.

    Points at a standstill as they are. With fewer than three of them, each path
    on the fly also gives its ends: the first and the last of its rows (the file's
    order, which is the order of capture) stand at about its start and its end.
    Gauss-Newton takes it from there.
    """
    still = ~station.on_the_fly
    commanded, measured = [station.machine_mm[still]], [station.tracker_mm[still]]
    if still.sum() < 3:
        fly = np.flatnonzero(station.on_the_fly)
        paths = np.concatenate([station.machine_mm[fly], station.to_mm[fly]], axis=1)
        _, first, group = np.unique(paths, axis=0, return_index=True, return_inverse=True)
        for g, start in enumerate(first):
            rows = fly[np.ravel(group) == g]
            if len(rows) >= 2:
                commanded.append(
                    np.stack([station.machine_mm[fly[start]], station.to_mm[fly[start]]])
                )
                measured.append(station.tracker_mm[[rows[0], rows[-1]]])
    return np.concatenate(commanded), np.concatenate(measured)


class _TrackerState:
    def __init__(
        self, station: TrackerStation, smr_mm: Vec, arm_mm: Vec, first_column: int
    ) -> None:
        self.station = station
        self.noise_factor = 1.0
        self.smr_mm = smr_mm
        self.arm_mm = arm_mm
        self.column = first_column
        commanded, measured = _start_pairs(station)
        nominal = commanded + smr_mm
        if len(nominal) < 3 or np.linalg.matrix_rank(nominal - nominal.mean(axis=0), 1e-3) < 2:
            raise GeometryError(
                f"{station.source}: tracker station {station.label}: {len(station.run)} points"
                " cannot place the tracker (at least three not on one line, or paths on the fly"
                " that span a plane)"
            )
        self.rotation, self.offset = rigid_start(nominal, measured)

    def linearise(
        self,
        chain: Chain,
        layout: ParameterLayout,
        tables: Vec,
        n_columns: int,
        uncertainty: TrackerUncertainty,
        chunk: slice = slice(None),
    ) -> _Block:
        """The station's rows ``chunk`` about the current tables and pose."""
        s = self.station.rows(chunk)
        measured = (s.tracker_mm - self.offset) @ self.rotation  # R^T (t - c), (N, 3)
        commanded = s.machine_mm.copy()
        fly = s.on_the_fly
        direction = s.directions()
        if fly.any():
            along = np.sum((measured[fly] - self.smr_mm - s.machine_mm[fly]) * direction[fly], 1)
            commanded[fly] = s.machine_mm[fly] + along[:, None] * direction[fly]
        nominal = commanded + self.smr_mm
        design_dp = point_design(chain, layout, commanded, self.arm_mm)
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
        return _Block(
            design=(table_design + pose_design).tocsr(),
            observed=(measured - nominal).ravel(),
            whitening=scipy.sparse.csr_matrix(whitening),
            ratio=np.ones(whitening.shape[0]),
        )

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
    def __init__(self, place: TracerPlace, smr_mm: Vec, arm_mm: Vec, first_column: int) -> None:
        self.place = place
        self.noise_factor = 1.0
        self.smr_mm = smr_mm
        self.arm_mm = arm_mm
        self.column = first_column
        self.runs = place.runs
        self.run_index = np.searchsorted(self.runs, place.run)
        nominal = place.machine_mm + smr_mm
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
        return 3 + len(self.runs)

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
        p = self.place.rows(chunk)
        run_index = self.run_index[chunk]
        design_dp = point_design(chain, layout, p.machine_mm, self.arm_mm)
        dp0 = (design_dp @ tables[: layout.n_columns]).reshape(-1, 3)
        vector = p.machine_mm + self.smr_mm + dp0 - self.pivot
        distance = np.linalg.norm(vector, axis=1)
        beam = vector / distance[:, None]
        n = len(distance)
        project = scipy.sparse.csr_matrix(
            (beam.ravel(), (np.repeat(np.arange(n), 3), np.arange(3 * n))), shape=(n, 3 * n)
        )
        tables_part = scipy.sparse.hstack(
            [project @ design_dp, scipy.sparse.csr_matrix((n, n_columns - layout.n_columns))]
        )
        setup = Triplets()
        for c in range(3):
            setup.add(np.arange(n), self.column + c, -beam[:, c])
        setup.add(np.arange(n), self.column + 3 + run_index, 1.0)
        rows, cols, vals = setup.arrays()
        setup_part = scipy.sparse.csr_matrix((vals, (rows, cols)), shape=(n, n_columns))
        sigma = uncertainty.length_sigma_mm(distance)
        return _Block(
            design=(tables_part + setup_part).tocsr(),
            observed=p.length_mm - distance + np.sum(beam * dp0, axis=1),
            whitening=scipy.sparse.diags(1.0 / (sigma * self.noise_factor)).tocsr(),
            ratio=np.ones(n),
        )

    def update(self, solution: Vec) -> float:
        step = solution[self.column : self.column + 3]
        self.pivot = self.pivot + step
        self.constants = solution[self.column + 3 : self.column + self.n_columns].copy()
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
    """The solution, the inverse of the column-scaled normal matrix and the column norms."""

    solution: Vec
    inverse: Vec
    norms: Vec


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
    inverse = _inverse(factor)
    return _Solved(solution=inverse @ (equations.rhs / norms) / norms, inverse=inverse, norms=norms)


@dataclass
class _Evaluated:
    """The rows at the solution, per block: residuals (raw and whitened), the sum of the
    hat matrix's diagonal, and ``sum ratio a a^T`` of the column-scaled rows (GUM)."""

    raw: list[Vec]
    weighted: list[Vec]
    leverage: Vec
    middle: Vec

    @property
    def n_rows(self) -> int:
        return sum(len(w) for w in self.weighted)


def _evaluate(blocks: Iterable[tuple[int, _Block]], n_blocks: int, solved: _Solved) -> _Evaluated:
    """Residuals and what the covariance needs, one block (chunk) at a time."""
    raw: list[list[Vec]] = [[] for _ in range(n_blocks)]
    weighted: list[list[Vec]] = [[] for _ in range(n_blocks)]
    leverage = np.zeros(n_blocks)
    middle = np.zeros_like(solved.inverse)
    unscale = scipy.sparse.diags(1.0 / solved.norms)
    for number, block in blocks:
        design = _whitened(block)[0] @ unscale
        residual = block.observed - block.design @ solved.solution
        raw[number].append(residual)
        weighted[number].append(block.whitening @ residual)
        normal = (design.T @ design).toarray()
        leverage[number] += float(np.sum(normal * solved.inverse))
        if np.all(block.ratio == 1.0):
            middle += normal
        else:
            middle += (design.T @ scipy.sparse.diags(block.ratio) @ design).toarray()
    return _Evaluated(
        raw=[np.concatenate(r) if r else np.zeros(0) for r in raw],
        weighted=[np.concatenate(w) if w else np.zeros(0) for w in weighted],
        leverage=leverage,
        middle=middle,
    )


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
        SMR centre from the CNC tool point in the MCS, mm.
    tracker_uncertainty, tracer_uncertainty
        The machine file's models (a row's own tracker uncertainty wins).
    travel_mm : (ndarray, ndarray), optional
        Travel limits: the tables are written from end to end.
    knot_spacing_mm : float, optional
        Compensation-point spacing where no line sets it (default: 200 mm with tracer
        lengths, 250 mm with tracker points alone).
    progress : callable, optional
        ``progress(done, total, what)`` after each chunk of the instruments' rows:
        points done of all in the pass ``what`` (a Gauss-Newton iteration, or the
        residuals and uncertainty at the end).

    Raises
    ------
    GeometryError
        A station, place or table the data cannot determine (one line naming it).
    """
    if not trackers and not tracers:
        raise InputError("fit_joint needs tracker points or tracer lengths")
    sources = ", ".join(dict.fromkeys([s.source for s in trackers] + [p.source for p in tracers]))
    if not lines and not trackers and len(tracers) < MIN_TRACER_PLACES:
        raise GeometryError(
            f"{sources}: {len(tracers)} tracer place{'s' if len(tracers) != 1 else ''} cannot"
            f" place the points in space; measure from at least {MIN_TRACER_PLACES} places"
        )
    layout, line_knots, undetermined = _joint_layout(
        lines, trackers, tracers, chain, knot_spacing_mm, sources
    )
    smr_mm = np.asarray(smr_offset_mm, dtype=float)
    # without lines the tables are the SMR's: its offset is no lever arm (module docstring)
    arm_mm = smr_mm if lines else np.zeros(3)
    setup = SetupLayout(lines, layout.n_columns)
    states = _States(trackers, tracers, smr_mm, arm_mm, layout.n_columns + setup.n_columns)
    describe = _describer(layout, setup, states)
    line_block, alone, line_sigma = _line_block(
        lines, chain, layout, setup, channel_sigma, states.n_columns
    )
    fixed_blocks = [line_block] if line_block is not None else []
    if alone is not None:
        prior = _continuation_block(
            layout, line_knots, alone.tables, unseen_rotations(chain), states.n_columns
        )
        fixed_blocks += [prior] if prior is not None else []
    models = (tracker_uncertainty, tracer_uncertainty)

    total = states.n_points

    def numbered(current: _States, tables: Vec, what: str) -> Iterator[tuple[int, _Block]]:
        """Every block's rows (fixed blocks whole, instruments in chunks), telling progress."""
        yield from enumerate(fixed_blocks)
        done = 0
        for number, points, block in current.chunks(chain, layout, tables, models):
            yield len(fixed_blocks) + number, block
            done += points
            if progress is not None:
                progress(done, total, what)

    def iterate(tables: Vec, first: int) -> tuple[_Evaluated, _Solved, int, bool]:
        """Gauss-Newton until no pose, pivot or table value moves any more; then the rows
        at the solution (about the last linearisation)."""
        converged = False
        for iteration in range(first, first + _MAX_ITERATIONS):
            before = states.snapshot()
            rows = numbered(before, tables, f"iteration {iteration}")
            solved = _solve(_accumulate((b for _, b in rows), states.n_columns), describe)
            step = states.update(solved.solution)
            table_step = float(np.max(np.abs(solved.solution - tables)[: layout.n_columns]))
            linearised_at, tables = tables, solved.solution
            if step < _STEP_TOLERANCE_MM and table_step < _STEP_TOLERANCE_MM:
                converged = True
                break
        rows = numbered(before, linearised_at, "residuals and uncertainty")
        evaluated = _evaluate(rows, n_blocks, solved)
        return evaluated, solved, iteration - first + 1, converged

    n_blocks = len(fixed_blocks) + len(states.trackers) + len(states.tracers)
    evaluated, solved, iterations, converged = iterate(np.zeros(states.n_columns), 1)
    sigma0 = _sigma0(evaluated, states.n_columns)
    scatter = _noise_factors(evaluated, len(fixed_blocks))
    correlation = np.ones(len(scatter))
    for k, state in enumerate(states.trackers):
        correlation[k] = correlation_samples(
            state.station, evaluated.weighted[len(fixed_blocks) + k]
        )
    factors = scatter * np.sqrt(correlation)
    widened = 1.0
    if np.any(factors > 1.0 + _FACTOR_TOLERANCE):
        states.set_noise_factors(factors)
        if n_blocks == 1:  # one instrument alone: weighting it down moves no estimate
            widened = float(factors[0]) ** 2
        else:
            evaluated, solved, more, converged = iterate(solved.solution, iterations + 1)
            iterations += more
    covariance = (
        solved.inverse
        @ evaluated.middle
        @ solved.inverse
        / np.outer(solved.norms, solved.norms)
        * widened
    )
    raw = evaluated.raw
    table_set = _tables(layout, solved.solution, covariance, travel_mm)
    for name in undetermined:
        table_set.tables[name].u95[:] = np.nan
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
            _tracker_fit(s, r, covariance, c)
            for s, r, c in zip(states.trackers, instrument_raw, correlation, strict=False)
        ],
        tracers=[
            _tracer_fit(t, r, covariance)
            for t, r in zip(states.tracers, instrument_raw[n_trackers:], strict=True)
        ],
        undetermined=undetermined,
        iterations=iterations,
        converged=converged,
        functional_point="tool point" if lines else "SMR",
        layout=layout,
        covariance=covariance,
    )


def _joint_layout(
    lines: list[LineData],
    trackers: list[TrackerStation],
    tracers: list[TracerPlace],
    chain: Chain,
    knot_spacing_mm: float | None,
    sources: str,
) -> tuple[ParameterLayout, dict[str, Vec], list[str]]:
    """The table columns, the lines' own knots and the tables no reading can see.

    With lines: their compensation points continued to the instruments' reach,
    the reversal only where the lines measured it. Without: points spread over
    the instruments' range, and the rotations a point cannot see left out.
    """
    reach = _instrument_points(trackers, tracers)
    if lines:
        line_knots = compensation_points(lines)
        knots = {
            a: _beyond_lines(k, reach[:, AXIS_INDEX[a]], EXTENSION_SPACING_MM)
            for a, k in line_knots.items()
        }
        layout = ParameterLayout(knots, bidirectional_axes(lines))
        return _reversal_within(layout, line_knots), line_knots, []
    undetermined = unseen_rotations(chain)
    if knot_spacing_mm is None:
        knot_spacing_mm = TRACER_KNOT_SPACING_MM if tracers else TRACKER_KNOT_SPACING_MM
    standing = _standing_positions(trackers, tracers)
    knots = instrument_knots(reach, knot_spacing_mm, standing, sources)
    return _without_tables(ParameterLayout(knots, set()), undetermined), knots, undetermined


class _States:
    """The tracker stations and tracer places being fitted, their columns after ``first``."""

    def __init__(
        self,
        trackers: list[TrackerStation],
        tracers: list[TracerPlace],
        smr_mm: Vec,
        arm_mm: Vec,
        first: int,
    ) -> None:
        column = first
        self.trackers: list[_TrackerState] = []
        for station in trackers:
            self.trackers.append(_TrackerState(station, smr_mm, arm_mm, column))
            column += _TRACKER_SETUP
        self.tracers: list[_TracerState] = []
        for place in tracers:
            self.tracers.append(_TracerState(place, smr_mm, arm_mm, column))
            column += self.tracers[-1].n_columns
        self.n_columns = column

    @property
    def n_points(self) -> int:
        """Tracker points and tracer lengths, all stations and places."""
        return sum(len(s.station.run) for s in self.trackers) + sum(
            len(t.place.run) for t in self.tracers
        )

    def chunks(
        self,
        chain: Chain,
        layout: ParameterLayout,
        tables: Vec,
        models: tuple[TrackerUncertainty, TracerUncertainty],
    ) -> Iterator[tuple[int, int, _Block]]:
        """Each instrument's rows about the current tables, poses and pivots, in chunks.

        Yields the instrument's number (trackers, then tracers), the chunk's points
        and its rows: at most :data:`CHUNK_POINTS` points at once, so a million rows
        never stand in memory as one design matrix.
        """
        linearisers: list[tuple[int, Callable[[slice], _Block]]] = [
            (
                len(s.station.run),
                partial(s.linearise, chain, layout, tables, self.n_columns, models[0]),
            )
            for s in self.trackers
        ]
        linearisers += [
            (
                len(t.place.run),
                partial(t.linearise, chain, layout, tables, self.n_columns, models[1]),
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
        moves = [s.update(solution) for s in self.trackers]
        return max(moves + [t.update(solution) for t in self.tracers] + [0.0])

    def set_noise_factors(self, factors: Vec) -> None:
        states: list[_TrackerState | _TracerState] = [*self.trackers, *self.tracers]
        for state, factor in zip(states, factors, strict=True):
            state.noise_factor = float(factor)


def _describer(layout: ParameterLayout, setup: SetupLayout, states: _States) -> Callable[..., str]:
    """A person's name for a column of the joint system (``knot``: with the table's knot)."""

    def describe(c: int, knot: bool = True) -> str:
        if c < layout.n_columns:
            return layout.describe(c) if knot else str(layout.table_name(c))
        line = setup.line_of(c)
        if line is not None:
            return f"the setup terms of line {line}"
        for s in states.trackers:
            if 0 <= c - s.column < _TRACKER_SETUP:
                return f"the pose of tracker station {s.station.label} ({s.station.source})"
        for t in states.tracers:
            if 0 <= c - t.column < 3:
                return f"the pivot of tracer place {t.place.label} ({t.place.source})"
            if 0 <= c - t.column < t.n_columns:
                return f"a constant of tracer place {t.place.label} ({t.place.source})"
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
    of its rows, ``h`` the hat matrix), as the lines' channels get in
    :func:`xmalign.post.solve.fit_error_tables`; kept at 1 or above, so the u95
    never claims better than the instrument's own uncertainty (the machine's
    repeatability, for one, adds to every reading). ``first``: the first
    instrument block (the lines and the prior come before).
    """
    factors = []
    for weighted, leverage in zip(
        evaluated.weighted[first:], evaluated.leverage[first:], strict=True
    ):
        redundancy = max(len(weighted) - float(leverage), 1.0)
        factors.append(max(1.0, np.sqrt(float(weighted @ weighted) / redundancy)))
    return np.array(factors)


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


def _tracker_fit(
    state: _TrackerState, residual: Vec, covariance: Vec, correlation: float
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
    squares = np.sum((vectors - along[:, None] * direction) ** 2, axis=1)
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
    )


def _tracer_fit(state: _TracerState, residual: Vec, covariance: Vec) -> TracerPlaceFit:
    p = state.place
    columns = state.column + np.arange(state.n_columns)
    u95 = _u95(covariance[np.ix_(columns, columns)])
    return TracerPlaceFit(
        label=p.label,
        source=p.source,
        n_lengths=len(p.run),
        pivot_mm=state.pivot.copy(),
        pivot_u95_mm=u95[:3],
        constant_mm={r: float(k) for r, k in zip(state.runs, state.constants, strict=True)},
        constant_u95_mm={r: float(u) for r, u in zip(state.runs, u95[3:], strict=True)},
        residual_rms_um=float(np.sqrt(np.mean(residual**2)) * 1e3),
        covered_mm=_covered(p.machine_mm),
        scatter_factor=state.noise_factor,
    )


def describe_undetermined(names: Iterable[str]) -> str:
    """One line for the report: which rotations the points could not see."""
    listed = ", ".join(names)
    return (
        f"{listed}: a point cannot see these rotations (no lever arm changes); written as 0"
        " without u95, the tables are those of the SMR as the functional point"
    )


def _triple(values: Vec, digits: int = 3) -> str:
    return ", ".join(f"{v:.{digits}f}" for v in values)


def _covered_text(covered_mm: tuple[Vec, Vec]) -> str:
    spans = (f"{a} {lo:.0f}..{hi:.0f}" for a, lo, hi in zip("XYZ", *covered_mm, strict=True))
    return "covered " + ", ".join(spans) + " mm"


def instrument_lines(joint: JointFit) -> list[str]:
    """One line per tracker station (pose) and tracer place (pivot, constants), with U95."""
    lines = []
    for s in joint.trackers:
        lines.append(
            f"tracker {s.label} ({s.n_points} points, {s.source}): origin"
            f" {_triple(s.position_mm)} mm (U95 {_triple(s.position_u95_mm)}), rotation"
            f" {_triple(s.rotation_urad, 0)} urad (U95 {_triple(s.rotation_u95_urad, 1)});"
            f" residual {s.residual_rms_um:.2f} um RMS (scatter / model {s.scatter_factor:.2f})"
            + _correlation_text(s.correlation_samples)
            + f"; {_covered_text(s.covered_mm)}"
        )
    for p in joint.tracers:
        constants = ", ".join(
            f"run {run} {k:.4f} (U95 {p.constant_u95_mm[run]:.4f})"
            for run, k in p.constant_mm.items()
        )
        lines.append(
            f"tracer {p.label} ({p.n_lengths} lengths, {p.source}): pivot"
            f" {_triple(p.pivot_mm, 4)} mm (U95 {_triple(p.pivot_u95_mm, 4)}), constant"
            f" {constants} mm; residual {p.residual_rms_um:.3f} um RMS (scatter / model"
            f" {p.scatter_factor:.2f}); {_covered_text(p.covered_mm)}"
        )
    return lines


def _correlation_text(samples: float) -> str:
    if samples <= 1.0 + _FACTOR_TOLERANCE:
        return ""
    return (
        f"; noise correlated over {samples:.1f} points on the fly (U95 widened"
        f" {np.sqrt(samples):.2f}x)"
    )


def instrument_notes(joint: JointFit) -> list[str]:
    """What the user should know about the joint fit (one line each)."""
    notes = []
    if joint.undetermined:
        notes.append(describe_undetermined(joint.undetermined))
    if not joint.converged:
        notes.append(
            f"the fit did not settle in {joint.iterations} iterations; check the instruments'"
            " setups and the points"
        )
    return notes
