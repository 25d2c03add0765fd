"""The 18 error tables and 3 squareness errors from all lines in one weighted fit.

Follows seed 000 (Montavon et al.): every error motion is a linear B-spline
(triangular basis functions, its Eq. 8-10) over the compensation points, so the
channels are linear in the table values (its Eq. 12-14). The sensitivities come
from the rigid-body model of docs/conventions.md through
:meth:`xmalign.rigid_body.Chain.lever_arms` (``d(dp)/d(eps_K) = -[r_K]x``) and
:func:`xmalign.rigid_body.squareness_deviation`. The setup terms of
:mod:`xmalign.post.setup_terms` are nuisance columns of the same system. The
system is weighted with the channel standard uncertainties (its Eq. 19-21) and
the covariance of the table values propagated from them (its Eq. 22, GUM).

Table conventions (docs/conventions.md) are imposed by leaving columns out: the
positioning and angular tables have no value at their first compensation point,
the straightness tables none at their first and last; these are exactly the
directions the six lines cannot see (a rigid motion of the whole machine and
the angle offsets that trade with squareness).

With data in both directions every table gets a second set of columns, the
half reversal ``h``: an axis moving forward sees ``mean + h``, moving backward
``mean - h``, standing still ``mean``.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
import scipy.sparse
from scipy.interpolate import BSpline

from xmalign.errors import GeometryError, InputError
from xmalign.formats.error_tables import ErrorTableSet, Table
from xmalign.geometry import Vec
from xmalign.post.lines import LineData
from xmalign.post.setup_terms import N_CHANNELS, SetupLayout, SetupTerms, Triplets
from xmalign.rigid_body import (
    AXES,
    AXIS_INDEX,
    ROTATION_NAMES,
    SQUARENESS_NAMES,
    TRANSLATION_NAMES,
    Chain,
    squareness_deviation,
)

#: Expansion factor of the expanded uncertainty.
K_EXPANSION = 2.0
#: Cholesky pivots below this (columns scaled to unit norm) mean a parameter the lines
#: cannot determine.
_RANK_TOLERANCE = 1e-10
#: Eigenvalues of the scaled normal matrix below this fraction of the largest span its
#: null space.
_NULL_TOLERANCE = 1e-9
#: A column whose unit vector has more than this squared component in the null space is named.
_INVOLVED = 1e-4
_KNOT_DECIMALS = 6
#: The estimated channel scatter is kept above this fraction of the machine file's
#: channel uncertainty (noise-free data would otherwise get infinite weights).
_SIGMA_FLOOR = 1e-2
#: Re-weightings with the channels' estimated variance components (they settle in two).
_VARIANCE_ITERATIONS = 2
#: A reading whose residual exceeds this many standard deviations (the larger of the
#: channel's robust scatter, 1.4826 MAD, and the machine file's channel uncertainty) is a
#: gross outlier (a glitch, a bumped reflector), left out of the fit: ten is far beyond
#: any Gaussian tail of a few thousand readings, and far below a wrong reading of tens of um.
OUTLIER_SIGMAS = 10.0
#: More gross outliers than this and the measurement is refused, not patched.
MAX_OUTLIERS = 10
#: Knots whose polynomial gives the slope at a knot (fourth order).
_SLOPE_POINTS = 5
#: Table points per knot interval: a controller interpolates linearly between them,
#: which follows the cubic to well below its own model error (docs/post.md).
TABLE_SUBDIVISIONS = 4
#: A travel end closer than this to the outermost knot adds no extrapolated point.
_TRAVEL_TOLERANCE_MM = 1e-3


def error_names(axis: str) -> tuple[str, ...]:
    """The six error motion names of an axis in column order (EX, EY, EZ, EA, EB, EC)."""
    return (*TRANSLATION_NAMES[axis], *ROTATION_NAMES[axis])


def compensation_points(lines: list[LineData]) -> dict[str, Vec]:
    """Compensation points of each axis, wherever any line measured it.

    The targets of its axis lines, projected on it; where a diagonal reaches
    beyond them while its other axis stays on that axis's own line, more points
    over that stretch at the axis line's mean spacing (the diagonal sees the
    errors there, and the other axis's are known).

    Raises
    ------
    InputError
        An axis has no line parallel to it.
    """
    points: dict[str, list[float]] = {axis: [] for axis in AXES}
    for data in lines:
        axis = data.axis()
        if axis is not None:
            points[axis].extend(data.line.target_points_mm()[:, AXIS_INDEX[axis]])
    missing = [axis for axis in AXES if len(points[axis]) < 2]
    if missing:
        raise InputError(
            f"the measurement has no line along {', '.join(missing)}: post needs one line per"
            " axis (and the three face diagonals for the squareness)"
        )
    base = {axis: np.unique(np.round(p, _KNOT_DECIMALS)) for axis, p in points.items()}
    return {axis: _extended(base[axis], _determinable_reach(lines, axis, base)) for axis in AXES}


def _determinable_reach(lines: list[LineData], axis: str, base: dict[str, Vec]) -> Vec:
    """Positions of ``axis`` where a line measured while every other axis it moves was
    inside that axis's own line (else two unknown tables would share one line's channels)."""
    reached = []
    for data in lines:
        moving = data.moving_axes()
        if axis not in moving:
            continue
        inside = np.ones(len(data.run), dtype=bool)
        for other in moving:
            if other != axis:
                knots = base[other]
                margin = 0.5 * _mean_spacing(knots)
                position = data.machine_mm[:, AXIS_INDEX[other]]
                inside &= (position >= knots[0] - margin) & (position <= knots[-1] + margin)
        reached.append(data.machine_mm[inside, AXIS_INDEX[axis]])
    return np.concatenate(reached)


def _mean_spacing(knots_mm: Vec) -> float:
    return float(knots_mm[-1] - knots_mm[0]) / (len(knots_mm) - 1)


def _extended(knots_mm: Vec, reached_mm: Vec) -> Vec:
    """Knots, plus points at their mean spacing out to the farthest positions reached.

    A stretch shorter than half the spacing gets no point: the end segment's
    extrapolation covers it (a short segment would be poorly determined).
    """
    spacing = _mean_spacing(knots_mm)
    low, high = reached_mm.min(), reached_mm.max()
    below = knots_mm[0] - low
    above = high - knots_mm[-1]
    parts = [knots_mm]
    if below > spacing / 2:
        parts.insert(0, np.linspace(low, knots_mm[0], int(np.ceil(below / spacing)) + 1)[:-1])
    if above > spacing / 2:
        parts.append(np.linspace(knots_mm[-1], high, int(np.ceil(above / spacing)) + 1)[1:])
    return np.concatenate(parts).round(_KNOT_DECIMALS)


def spline_basis(knots_mm: Vec, position_mm: Vec) -> scipy.sparse.coo_array:
    """Local cubic (Hermite) basis at positions; beyond the end knots, linear continuation.

    The value at ``x`` is ``sum_m B[x, m] v_m``: between two knots the cubic
    that takes their values with the slopes of the polynomial through the
    neighbouring knots (:func:`_slope_matrix`). It interpolates (the value at a
    knot is its table value), reproduces polynomials up to the third degree
    exactly (so the table conventions still fix what the lines cannot see: a
    constant, a straight line), and each position depends on six knots only
    (the system stays sparse). A linear interpolation at 100 mm knots cost
    0.3-0.5 um of volumetric residual on seed 003's error shapes even with exact
    knot values (docs/post.md). Beyond the end knots the value continues with the end slope:
    a diagonal reaches parts of an axis's travel that its axis line does not
    measure, and holding the end value there would model a sloped table as a step.

    Returns
    -------
    scipy.sparse.coo_array, shape (N, M)
        ``B[i, m]`` weight of the value at knot ``m`` for position ``i``.
    """
    knots = np.asarray(knots_mm, dtype=float)
    x = np.asarray(position_mm, dtype=float)
    if len(knots) < 3:
        t = np.concatenate([[knots[0]], knots, [knots[-1]]])
        return BSpline.design_matrix(x, t, 1, extrapolate=True).tocoo()
    slopes = _slope_matrix(knots)
    segment = np.clip(np.searchsorted(knots, x, side="right") - 1, 0, len(knots) - 2)
    h = knots[segment + 1] - knots[segment]
    t = (np.clip(x, knots[0], knots[-1]) - knots[segment]) / h
    basis = np.zeros((len(x), len(knots)))
    rows = np.arange(len(x))
    basis[rows, segment] += 2 * t**3 - 3 * t**2 + 1
    basis[rows, segment + 1] += -2 * t**3 + 3 * t**2
    basis += ((t**3 - 2 * t**2 + t) * h)[:, None] * slopes[segment]
    basis += ((t**3 - t**2) * h)[:, None] * slopes[segment + 1]
    below, above = x < knots[0], x > knots[-1]
    basis[below] += np.outer(x[below] - knots[0], slopes[0])
    basis[above] += np.outer(x[above] - knots[-1], slopes[-1])
    basis[np.abs(basis) < 1e-12] = 0.0
    return scipy.sparse.coo_array(basis)


def _slope_matrix(knots_mm: Vec) -> Vec:
    """Slopes at the knots as a linear map of the knot values, shape (M, M), M >= 3.

    At each knot the derivative of the polynomial through the nearest
    :data:`_SLOPE_POINTS` knots (centred on it where the ends allow): fourth
    order, so the cubic between two knots follows the errors' curvature almost
    as well as a global spline while each position depends on six knots only.
    """
    m = len(knots_mm)
    n = min(_SLOPE_POINTS, m)
    slopes = np.zeros((m, m))
    for i in range(m):
        first = min(max(i - n // 2, 0), m - n)
        window = knots_mm[first : first + n]
        scale = float(window[-1] - window[0])
        powers = ((window - knots_mm[i]) / scale)[:, None] ** np.arange(n)
        slopes[i, first : first + n] = np.linalg.inv(powers)[1] / scale
    return slopes


def _gauge_free(axis: str, error: int, n_knots: int) -> np.ndarray:
    """Knots of one mean table that get a column (table conventions of docs/conventions.md)."""
    free = np.ones(n_knots, dtype=bool)
    free[0] = False
    if error < 3 and error != AXIS_INDEX[axis]:
        free[-1] = False
    return free


class ParameterLayout:
    """Column numbers of the table values: ``column[axis][kind][error, knot]`` (-1 if fixed).

    ``kind`` is ``"mean"`` or ``"half"`` (the half reversal, only with bidirectional
    data). Squareness columns come last.
    """

    def __init__(self, knots: dict[str, Vec], bidirectional_axes: set[str]) -> None:
        self.knots = knots
        self.column: dict[str, dict[str, np.ndarray]] = {}
        n = 0
        for axis in AXES:
            m = len(knots[axis])
            self.column[axis] = {}
            for kind in ("mean", "half") if axis in bidirectional_axes else ("mean",):
                columns = np.full((6, m), -1)
                for error in range(6):
                    free = _gauge_free(axis, error, m) if kind == "mean" else np.ones(m, bool)
                    columns[error, free] = n + np.arange(free.sum())
                    n += int(free.sum())
                self.column[axis][kind] = columns
        self.squareness_columns = n + np.arange(3)
        self.n_columns = n + 3

    def table_name(self, column: int) -> str | None:
        """The ISO 230-1 name of the table (or squareness) a column belongs to; None if none."""
        if column in self.squareness_columns:
            return SQUARENESS_NAMES[column - self.squareness_columns[0]]
        for axis, kinds in self.column.items():
            for kind, columns in kinds.items():
                hit = np.argwhere(columns == column)
                if len(hit):
                    return error_names(axis)[hit[0][0]] + ("" if kind == "mean" else " reversal")
        return None

    def describe(self, column: int) -> str:
        """A person's name for a column, with its knot (for error messages)."""
        for axis, kinds in self.column.items():
            for columns in kinds.values():
                hit = np.argwhere(columns == column)
                if len(hit):
                    return f"{self.table_name(column)} at {self.knots[axis][hit[0][1]]:g} mm"
        return self.table_name(column) or f"column {column}"


def _sensitivities(frame: Vec, arms_mm: Vec) -> Vec:
    """d(channels)/d(delta, eps) of one axis at N points, shape (N, 6, 6)."""
    n = len(arms_mm)
    g = np.zeros((n, 6, 6))
    g[:, 0:3, 0:3] = frame
    g[:, 3:6, 3:6] = frame
    for c in range(3):
        # f . (eps x r) = eps . (r x f)
        g[:, c, 3:6] = np.cross(arms_mm, frame[c])
    return g


def _add_axis_columns(
    data: LineData,
    first_row: int,
    axis: str,
    arms_mm: Vec,
    layout: ParameterLayout,
    out: Triplets,
) -> None:
    basis = spline_basis(layout.knots[axis], data.machine_mm[:, AXIS_INDEX[axis]])
    g = _sensitivities(data.frame, arms_mm)[basis.row]
    u_component = data.frame[0][AXIS_INDEX[axis]]
    moving = abs(u_component) > 1e-9
    factors = {"mean": np.ones(len(basis.row))}
    if moving and "half" in layout.column[axis]:
        factors["half"] = data.sign[basis.row] * np.sign(u_component)
    for kind, factor in factors.items():
        columns = layout.column[axis][kind][:, basis.col]
        for error in range(6):
            keep = columns[error] >= 0
            for channel in range(6 if error >= 3 else 3):
                out.add(
                    first_row + N_CHANNELS * basis.row[keep] + channel,
                    columns[error][keep],
                    (g[:, channel, error] * basis.data * factor)[keep],
                )


def _add_squareness_columns(
    data: LineData, first_row: int, layout: ParameterLayout, out: Triplets
) -> None:
    rows = first_row + N_CHANNELS * np.arange(len(data.run))
    for s, column in enumerate(layout.squareness_columns):
        dp = squareness_deviation(data.machine_mm, np.eye(3)[s]) @ data.frame.T
        for channel in range(3):
            out.add(rows + channel, int(column), dp[:, channel])


@dataclass(frozen=True)
class Outlier:
    """A reading left out of the fit as a gross outlier.

    ``line`` indexes the fitted lines, ``point`` the line's points, ``channel`` the six
    channels (linear, straightness v, w, angle u, v, w); ``sigmas`` is its residual in
    standard deviations when it was found.
    """

    line: int
    point: int
    channel: int
    sigmas: float


@dataclass
class TableFit:
    """Result of the fit.

    Attributes
    ----------
    tables : ErrorTableSet
        Values and u95 (k = 2) in mm / rad; mean tables always, ``+``/``-`` with
        bidirectional data.
    setup : list of SetupTerms
        The fitted setup terms of every line.
    residual_rms : dict of str to ndarray, shape (6,)
        RMS residual of each channel per line, um / urad.
    sigma0 : float
        Square root of the a-posteriori variance factor of the fit weighted with
        the machine file's channel uncertainties (1 when they describe the scatter).
    n_observations, n_parameters : int
    channel_scatter : ndarray, shape (6,)
        The channels' standard deviations estimated from the residuals (type A),
        with which the final fit is weighted, mm / rad.
    outliers : list of Outlier
        Readings left out as gross outliers (:data:`OUTLIER_SIGMAS`), in the order found.
    """

    tables: ErrorTableSet
    setup: list[SetupTerms]
    residual_rms: dict[str, Vec]
    sigma0: float
    n_observations: int
    n_parameters: int
    channel_scatter: Vec
    outliers: list[Outlier] = field(default_factory=list)


def _undetermined(normal: Vec, layout: ParameterLayout, setup: SetupLayout) -> GeometryError:
    """An error naming every error table and setup term in the null space of the system.

    A column takes part when its unit vector has a component in the null space;
    that component does not depend on which basis of the null space the
    eigensolver returns, so the message is the same on every machine and BLAS.
    """
    eigenvalues, vectors = np.linalg.eigh(normal)
    null = vectors[:, eigenvalues <= _NULL_TOLERANCE * eigenvalues[-1]]
    if null.shape[1] == 0:
        null = vectors[:, :1]
    involved = np.flatnonzero(np.sum(null**2, axis=1) > _INVOLVED)
    errors = _unique(layout.table_name(int(c)) for c in involved)
    if errors:
        lines = _unique(setup.line_of(int(c)) for c in involved)
        what = ", ".join(errors)
        if lines:
            plural = "s" if len(lines) > 1 else ""
            what += f" (they trade with the setup terms of line{plural} {', '.join(lines)})"
    else:
        lines = _unique(setup.line_of(int(c)) for c in involved)
        what = f"the setup terms of line{'s' if len(lines) > 1 else ''} {', '.join(lines)}"
    return GeometryError(
        f"the lines cannot determine {what}; measure the three axis lines"
        " and the three face diagonals"
    )


def _describe(column: int, layout: ParameterLayout, setup: SetupLayout) -> str:
    line = setup.line_of(column)
    return f"the setup terms of line {line}" if line else layout.describe(column)


def _unique(names: Iterable[str | None]) -> list[str]:
    return list(dict.fromkeys(name for name in names if name is not None))


def _inverse(factor: tuple[Vec, bool]) -> Vec:
    """The inverse of a matrix from its upper Cholesky factor (``_factorise``)."""
    inverse, info = scipy.linalg.lapack.dpotri(factor[0], lower=False)
    if info != 0:
        raise np.linalg.LinAlgError(f"dpotri failed ({info})")
    return np.triu(inverse) + np.triu(inverse, 1).T


def _factorise(normal: Vec, layout: ParameterLayout, setup: SetupLayout) -> tuple[Vec, bool]:
    """Cholesky factor of the (column-scaled) normal matrix; GeometryError when singular."""
    try:
        factor = scipy.linalg.cho_factor(normal, lower=False, check_finite=False)
    except np.linalg.LinAlgError as error:
        raise _undetermined(normal, layout, setup) from error
    pivots = np.diag(factor[0]) ** 2
    if pivots.min() < _RANK_TOLERANCE * pivots.max():
        raise _undetermined(normal, layout, setup)
    return factor


class _WeightedSystem:
    """The least-squares system weighted with channel standard deviations ``sigma`` (6,)."""

    def __init__(
        self,
        design: scipy.sparse.csr_matrix,
        observed: Vec,
        sigma: Vec,
        layout: ParameterLayout,
        setup: SetupLayout,
        kept: np.ndarray,
    ) -> None:
        n_rows, n_columns = design.shape
        self.sigma = sigma
        self.kept = kept
        self.weights = np.tile(1.0 / sigma, n_rows // N_CHANNELS) * kept
        weighted = scipy.sparse.diags(self.weights) @ design
        self.norms = np.sqrt(np.asarray(weighted.multiply(weighted).sum(axis=0))).ravel()
        if np.any(self.norms == 0):
            unseen = _describe(int(np.argmin(self.norms)), layout, setup)
            raise GeometryError(
                f"no measurement sees {unseen}; measure the three axis lines and the three face"
                " diagonals"
            )
        self.scaled = (weighted @ scipy.sparse.diags(1.0 / self.norms)).tocsr()
        factor = _factorise((self.scaled.T @ self.scaled).toarray(), layout, setup)
        self.inverse = _inverse(factor)
        solution_scaled = self.inverse @ (self.scaled.T @ (observed * self.weights))
        self.residual = observed * self.weights - self.scaled @ solution_scaled
        self.solution = solution_scaled / self.norms
        dof = max(int(np.count_nonzero(kept)) - n_columns, 1)
        self.sigma0 = float(np.sqrt(self.residual @ self.residual / dof))

    def channel_factors(self) -> Vec:
        """Per channel, the ratio of the scatter to ``sigma`` (variance components), (6,).

        Each channel's weighted residuals over its redundancy (the sum of
        ``1 - h_ii`` of its rows, ``h`` the hat matrix): a type A evaluation of
        the channel's standard deviation.
        """
        redundancy = ((1.0 - self._leverage()) * self.kept).reshape(-1, N_CHANNELS).sum(axis=0)
        squares = (self.residual**2).reshape(-1, N_CHANNELS).sum(axis=0)
        return np.sqrt(squares / np.maximum(redundancy, 1.0))

    def _leverage(self) -> Vec:
        """Diagonal of the hat matrix, ``a_i N^-1 a_i^T`` per row (rows are sparse), (N,)."""
        coo = self.scaled.tocoo()
        order = np.argsort(coo.row, kind="stable")
        rows, cols, vals = coo.row[order], coo.col[order], coo.data[order]
        counts = np.bincount(rows, minlength=self.scaled.shape[0])
        starts = np.repeat(np.cumsum(counts) - counts, counts)
        leverage = np.zeros(self.scaled.shape[0])
        # every pair (j, k) of one row's entries: entry j with its row's entry at offset k
        for offset in range(int(counts.max(initial=0))):
            partner = starts + offset
            valid = offset < counts[rows]
            partner = np.where(valid, partner, 0)
            terms = vals * vals[partner] * self.inverse[cols, cols[partner]]
            leverage += np.bincount(rows, np.where(valid, terms, 0.0), len(leverage))
        return leverage

    def covariance(self, sigma: Vec) -> Vec:
        """Covariance of the solution when the channels scatter with ``sigma`` (6,).

        ``N^-1 A^T W Sigma W A N^-1``: the estimate weighted with ``self.sigma``,
        propagated with the channel variances ``sigma**2`` (GUM).
        """
        ratio = np.tile((sigma / self.sigma) ** 2, len(self.weights) // N_CHANNELS)
        middle = (self.scaled.T @ scipy.sparse.diags(ratio) @ self.scaled).toarray()
        return self.inverse @ middle @ self.inverse / np.outer(self.norms, self.norms)


def bidirectional_axes(lines: list[LineData]) -> set[str]:
    """The axes some line measured in both directions (they get reversal tables)."""
    return {axis for data in lines if data.bidirectional for axis in data.moving_axes()}


def add_line_rows(
    lines: list[LineData],
    chain: Chain,
    layout: ParameterLayout,
    setup: SetupLayout,
    out: Triplets,
) -> list[int]:
    """Add the six channel rows of every line's points (tables, squareness, setup).

    Returns the first row of each line; the rows are numbered from 0.
    """
    sizes = [N_CHANNELS * len(d.run) for d in lines]
    first_rows = [int(r) for r in np.cumsum([0, *sizes])[: len(lines)]]
    for data, first_row in zip(lines, first_rows, strict=True):
        arms = chain.lever_arms(data.machine_mm, data.tool_offset_mm)
        for axis in AXES:
            _add_axis_columns(data, first_row, axis, arms[axis], layout, out)
        _add_squareness_columns(data, first_row, layout, out)
    setup.add_columns(lines, first_rows, out)
    return first_rows


def fit_error_tables(
    lines: list[LineData],
    chain: Chain,
    channel_sigma: Vec,
    travel_mm: tuple[Vec, Vec] | None = None,
) -> TableFit:
    """Weighted least-squares fit of the error tables, squareness and setup terms.

    Parameters
    ----------
    lines : list of LineData
        Channels in mm / rad, from one or more launch-unit stations; every line
        has its own setup terms. The lever arms include each line's receiver
        offset (``LineData.tool_offset_mm``), which removes the Abbe offsets; the
        tables are for ``t = 0``.
    chain : Chain
    channel_sigma : ndarray, shape (6,)
        Standard uncertainty of each channel, mm / rad.
    travel_mm : (ndarray, ndarray), each shape (3,), optional
        Travel minimum and maximum: the tables get a point at each travel end
        beyond the measured stroke, linearly extrapolated (``Table.measured``
        False), with the u95 the extrapolation propagates.
    """
    knots = compensation_points(lines)
    layout = ParameterLayout(knots, bidirectional_axes(lines))
    setup = SetupLayout(lines, layout.n_columns)
    triplets = Triplets()
    first_rows = add_line_rows(lines, chain, layout, setup, triplets)
    n_rows = N_CHANNELS * sum(len(d.run) for d in lines)

    n_columns = layout.n_columns + setup.n_columns
    rows, cols, vals = triplets.arrays()
    design = scipy.sparse.csr_matrix((vals, (rows, cols)), shape=(n_rows, n_columns))
    observed = np.concatenate([d.channels.ravel() for d in lines])
    prior = np.asarray(channel_sigma, dtype=float)
    kept = np.ones(n_rows, dtype=bool)
    system = _WeightedSystem(design, observed, prior, layout, setup, kept)
    outliers: list[Outlier] = []
    while (worst := _worst_outlier(system.residual, kept)) is not None:
        row, sigmas = worst
        line = int(np.searchsorted(first_rows, row, side="right")) - 1
        point, channel = divmod(row - int(first_rows[line]), N_CHANNELS)
        outliers.append(Outlier(line, point, channel, sigmas))
        if len(outliers) > MAX_OUTLIERS:
            raise InputError(
                f"more than {MAX_OUTLIERS} readings are gross outliers (over"
                f" {OUTLIER_SIGMAS:g} standard deviations off the fit): the measurement is not"
                " usable; check the setup and measure again"
            )
        kept[row] = False
        system = _WeightedSystem(design, observed, prior, layout, setup, kept)
    sigma0 = system.sigma0
    sigma = prior
    for _ in range(_VARIANCE_ITERATIONS):
        sigma = np.maximum(sigma * system.channel_factors(), prior * _SIGMA_FLOOR)
        system = _WeightedSystem(design, observed, sigma, layout, setup, kept)
    solution = system.solution
    covariance = system.covariance(np.maximum(prior, sigma))
    residual = system.residual
    weights = system.weights
    return TableFit(
        tables=_tables(layout, solution, covariance, travel_mm),
        setup=setup.unpack(solution),
        residual_rms=_residual_rms(
            lines, first_rows, np.divide(residual, weights, out=np.full(n_rows, np.nan), where=kept)
        ),
        sigma0=sigma0,
        n_observations=n_rows,
        n_parameters=n_columns,
        channel_scatter=sigma,
        outliers=outliers,
    )


def _worst_outlier(residual: Vec, kept: np.ndarray) -> tuple[int, float] | None:
    """The row of the largest gross outlier among the kept readings and its size in
    standard deviations, or None (``residual`` weighted with the channel uncertainties)."""
    by_channel = np.where(kept, np.abs(residual), np.nan).reshape(-1, N_CHANNELS)
    scatter = np.maximum(1.4826 * np.nanmedian(by_channel, axis=0), 1.0)
    sigmas = np.nan_to_num(by_channel / scatter, nan=0.0).ravel()
    row = int(np.argmax(sigmas))
    return (row, float(sigmas[row])) if sigmas[row] > OUTLIER_SIGMAS else None


def _output_positions(knots_mm: Vec, low_mm: float, high_mm: float) -> tuple[Vec, np.ndarray]:
    """Table positions and which are measured.

    The knots with :data:`TABLE_SUBDIVISIONS` equal steps between neighbours (a
    controller interpolates its tables linearly, so the table samples the
    spline finely enough), extended to the travel ends.
    """
    steps = np.linspace(0.0, 1.0, TABLE_SUBDIVISIONS + 1)[:-1]
    inner = (knots_mm[:-1, None] + np.outer(np.diff(knots_mm), steps)).ravel()
    inner = np.round(np.append(inner, knots_mm[-1]), _KNOT_DECIMALS)
    before = [low_mm] if low_mm < knots_mm[0] - _TRAVEL_TOLERANCE_MM else []
    after = [high_mm] if high_mm > knots_mm[-1] + _TRAVEL_TOLERANCE_MM else []
    positions = np.concatenate([before, inner, after])
    measured = np.concatenate(
        [np.zeros(len(before), bool), np.ones(len(inner), bool), np.zeros(len(after), bool)]
    )
    return positions, measured


def _evaluate(
    parts: list[tuple[np.ndarray, Vec]], solution: Vec, covariance: Vec
) -> tuple[Vec, Vec]:
    """Values and u95 of ``sum(weights @ solution[columns])`` over parts (fixed knots: -1)."""
    columns = np.concatenate([c for c, _ in parts])
    weights = np.hstack([w for _, w in parts])
    free = columns >= 0
    columns, weights = columns[free], weights[:, free]
    values = weights @ solution[columns]
    variance = np.einsum("ij,jk,ik->i", weights, covariance[np.ix_(columns, columns)], weights)
    return values, K_EXPANSION * np.sqrt(np.maximum(variance, 0.0))


def rms_curvature(knots_mm: Vec, positions_mm: Vec, values: Vec) -> float:
    """RMS second difference of a table over its knots (M >= 3), value per mm squared."""
    at_knots = np.interp(knots_mm, positions_mm, values)
    slopes = np.diff(at_knots) / np.diff(knots_mm)
    curvature = np.diff(slopes) / (0.5 * (knots_mm[2:] - knots_mm[:-2]))
    return float(np.sqrt(np.mean(curvature**2)))


def _extrapolation_u(knots_mm: Vec, positions_mm: Vec, values: Vec) -> Vec:
    """Standard uncertainty of the linear continuation beyond the knots, shape (P,).

    The table's RMS curvature over the knots, kept up over the distance ``d``
    from the nearest knot: ``kappa * d**2 / 2`` (0 between the knots).
    """
    if len(knots_mm) < 3:
        return np.zeros(len(positions_mm))
    kappa = rms_curvature(knots_mm, positions_mm, values)
    distance = np.maximum(knots_mm[0] - positions_mm, 0) + np.maximum(
        positions_mm - knots_mm[-1], 0
    )
    return 0.5 * kappa * distance**2


def _tables(
    layout: ParameterLayout, solution: Vec, covariance: Vec, travel_mm: tuple[Vec, Vec] | None
) -> ErrorTableSet:
    """The tables at the knots and, linearly extrapolated, at the travel ends (if given)."""
    result = ErrorTableSet()
    for axis in AXES:
        knots = layout.knots[axis]
        i = AXIS_INDEX[axis]
        low, high = (
            (knots[0], knots[-1]) if travel_mm is None else (travel_mm[0][i], travel_mm[1][i])
        )
        positions, measured = _output_positions(knots, low, high)
        basis = spline_basis(knots, positions).toarray()
        kinds = layout.column[axis]
        for error, name in enumerate(error_names(axis)):
            mean = (kinds["mean"][error], basis)
            variants = {"": [mean]}
            if "half" in kinds:
                half = kinds["half"][error]
                variants["+"] = [mean, (half, basis)]
                variants["-"] = [mean, (half, -basis)]
            for suffix, parts in variants.items():
                values, u95 = _evaluate(parts, solution, covariance)
                u95 = np.hypot(u95, K_EXPANSION * _extrapolation_u(knots, positions, values))
                result.tables[name + suffix] = Table(positions, values, u95, measured)
    for name, column in zip(SQUARENESS_NAMES, layout.squareness_columns, strict=True):
        result.squareness[name] = (
            float(solution[column]),
            float(K_EXPANSION * np.sqrt(covariance[column, column])),
        )
    return result


def _residual_rms(lines: list[LineData], first_rows: list[int], residual: Vec) -> dict[str, Vec]:
    scale = np.array([1e3, 1e3, 1e3, 1e6, 1e6, 1e6])
    out = {}
    for data, first_row in zip(lines, first_rows, strict=True):
        part = residual[first_row : first_row + N_CHANNELS * len(data.run)].reshape(-1, 6)
        out[data.label] = np.sqrt(np.nanmean(part**2, axis=0)) * scale  # outliers: NaN
    return out
