"""Fit a controller's own compensation model to the error field over the whole travel.

``post`` gives a rigid-body error model (18 tables, 3 squareness). A controller
applies something simpler: one table per axis of its own position (pitch), or
one-variable cross tables (output axis corrected as a function of one input
axis), or the full model (volumetric). :func:`fit_compensation` predicts the
volumetric error of the tool point (``t``, the machine file's tool offset) on a
grid over the whole travel with :func:`xmalign.rigid_body.deviation` and fits
the controller's tables to it by least squares. Writers only format the result.

Fitted tables are *errors* (what the controller takes out; a correction is
minus them), named ISO 230-1 style ``E<output><input>`` (``EYX``: Y error as a
function of X), on the measured positions of the input axis, shifted so they are
zero at the reference point (no jump when the compensation is switched on). A
constant offset of the whole volume is not an error a table must remove (the
six lines do not see it and the work offset takes it up), so residuals are
RMS lengths after the mean is removed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse

from xmalign.formats.error_tables import ErrorTableSet
from xmalign.formats.provenance import FileSource
from xmalign.geometry import Vec
from xmalign.rigid_body import (
    AXES,
    AXIS_INDEX,
    Chain,
    ErrorModel,
    ErrorTables,
    RemainingErrors,
    deviation,
)

#: Per-axis pitch: each axis corrected as a function of its own position.
PITCH = tuple((axis, axis) for axis in AXES)
#: One-variable cross tables: every axis corrected as a function of every axis.
CROSS = tuple((output, axis) for axis in AXES for output in AXES)
#: Straightness: every axis corrected as a function of each other axis.
STRAIGHTNESS = tuple(pair for pair in CROSS if pair[0] != pair[1])
#: Above this many grid points the midpoints between table nodes are left out, then the
#: full grid gives way to one slab per axis.
MAX_GRID_POINTS = 400_000
#: Points across each other axis in a slab.
SLAB_POINTS = 15
#: Fewer than this share of the error removed is worth a warning.
WARN_REMOVED_SHARE = 0.5


@dataclass(frozen=True)
class CompModel:
    """What a controller's tables can apply.

    ``pairs`` lists ``(output axis, input axis)`` of the one-variable tables;
    ``directional`` says whether an axis's own table can differ by direction
    of travel; ``volumetric`` means the controller applies the full rigid-body
    model itself (the fitted tables are then ``post``'s own). ``optional``
    lists tables of a controller option (e.g. Fanuc's straightness
    compensation): fitted to what ``pairs`` leave, so ``pairs`` stay right
    without the option.
    """

    pairs: tuple[tuple[str, str], ...]
    directional: bool
    volumetric: bool = False
    optional: tuple[tuple[str, str], ...] = ()


@dataclass(frozen=True)
class CompensationFit:
    """The tables a controller gets, and the error they leave over the whole travel.

    ``forward`` / ``reverse`` hold the fitted tables for motion in the positive /
    negative direction (equal when the model or the data has no direction);
    ``mean`` is the direction-free fit. Residuals are RMS vector lengths over
    the grid and both directions, um, after removing the mean offset.
    ``optional`` holds the tables of the model's option (none without one) and
    ``after_optional_um`` the residual with them loaded too.
    """

    model: CompModel
    mean: ErrorTables
    forward: ErrorTables
    reverse: ErrorTables
    before_um: float
    after_um: float
    grid_points: int
    converged: bool
    optional: ErrorTables | None = None
    after_optional_um: float | None = None
    #: what the fit cannot vouch for (:func:`extrapolated_references`), said by every writer
    warnings: tuple[str, ...] = ()
    #: the files the tables were made from (their hashes go into every controller file)
    sources: tuple[FileSource, ...] = ()

    @property
    def removed_share(self) -> float:
        """Share of the RMS error the tables remove (1 = all, 0 = none)."""
        return 1.0 - self.after_um / self.before_um if self.before_um > 0 else 1.0

    @property
    def removes_enough(self) -> bool:
        """False when the tables remove less than half of the error."""
        return self.removed_share >= WARN_REMOVED_SHARE

    def table(self, output: str, axis: str, direction: str = "") -> tuple[Vec, Vec]:
        """``(positions mm, error mm)`` of one fitted table (``direction`` ``""``, ``+``, ``-``)."""
        source = {"": self.mean, "+": self.forward, "-": self.reverse}[direction]
        return source.tables[f"E{output}{axis}"]


def travel_grid(nodes_mm: dict[str, Vec], low_mm: Vec, high_mm: Vec) -> Vec:
    """Points over the whole travel at which the field is fitted, shape (N, 3).

    The grid of every axis's table nodes and travel ends, with the midpoints
    between them while that stays under :data:`MAX_GRID_POINTS`. Tables too
    long even for that (a fine spacing on every axis) get one slab per axis
    instead: all of its nodes and midpoints times :data:`SLAB_POINTS` points
    across each other axis. Either way every node is a grid coordinate of its
    axis, so every table value is pinned by the fit.
    """
    per_axis = []
    for axis in AXES:
        k = AXIS_INDEX[axis]
        values = np.union1d(nodes_mm[axis], [low_mm[k], high_mm[k]])
        per_axis.append(values[(values >= low_mm[k]) & (values <= high_mm[k])])
    with_midpoints = [np.union1d(v, 0.5 * (v[1:] + v[:-1])) for v in per_axis]
    for candidate in (with_midpoints, per_axis):
        if np.prod([len(v) for v in candidate]) <= MAX_GRID_POINTS:
            return _tensor(candidate)
    across = [np.linspace(low_mm[k], high_mm[k], SLAB_POINTS) for k in range(3)]
    slabs = [
        _tensor([with_midpoints[k] if k == along else across[k] for k in range(3)])
        for along in range(3)
    ]
    return np.concatenate(slabs)


def _tensor(coordinates: list[Vec]) -> Vec:
    return np.stack(np.meshgrid(*coordinates, indexing="ij"), axis=-1).reshape(-1, 3)


def hat_basis(nodes_mm: Vec, x_mm: Vec) -> scipy.sparse.csr_array:
    """Linear-interpolation weights of ``x`` on ``nodes`` (end values held), sparse (N, M)."""
    count = len(nodes_mm)
    x = np.clip(x_mm, nodes_mm[0], nodes_mm[-1])
    right = np.clip(np.searchsorted(nodes_mm, x, side="right"), 1, max(count - 1, 1))
    left = right - 1
    span = nodes_mm[np.minimum(right, count - 1)] - nodes_mm[left]
    weight = np.divide(x - nodes_mm[left], span, out=np.zeros_like(x), where=span > 0)
    rows = np.arange(len(x))
    return scipy.sparse.csr_array(
        (
            np.concatenate([1.0 - weight, weight]),
            (np.concatenate([rows, rows]), np.concatenate([left, np.minimum(right, count - 1)])),
        ),
        shape=(len(x), count),
    )


def _rms_um(residual_mm: Vec) -> float:
    """RMS length after removing one mean offset (shared by both directions), um."""
    centred = residual_mm - residual_mm.mean(axis=0)
    return float(np.sqrt(np.mean(np.sum(centred**2, axis=1))) * 1e3)


def _fit_field(
    model: CompModel, nodes: dict[str, Vec], points_mm: Vec, field_mm: Vec
) -> tuple[dict[str, tuple[Vec, Vec]], bool]:
    """Least-squares one-variable tables for a field (N, 3); each output component apart."""
    fitted: dict[str, tuple[Vec, Vec]] = {}
    converged = True
    for output in AXES:
        inputs = [axis for out, axis in model.pairs if out == output]
        if not inputs:
            continue
        blocks = [hat_basis(nodes[a], points_mm[:, AXIS_INDEX[a]]) for a in inputs]
        constant = scipy.sparse.csr_array(np.ones((len(points_mm), 1)))
        design = scipy.sparse.hstack([*blocks, constant], format="csr")
        target = field_mm[:, AXIS_INDEX[output]]
        # the normal equations are small (one unknown per table node) and well conditioned
        normal = (design.T @ design).toarray()
        solution, _, rank, _ = np.linalg.lstsq(normal, design.T @ target, rcond=1e-12)
        converged &= bool(np.all(np.isfinite(solution)))
        # rank deficiency is only the shared constants (one per extra input)
        converged &= rank >= design.shape[1] - len(inputs)
        start = 0
        for axis, block in zip(inputs, blocks, strict=True):
            values = solution[start : start + block.shape[1]]
            fitted[f"E{output}{axis}"] = (nodes[axis], values)
            start += block.shape[1]
    return fitted, converged


def _zero_at(tables: dict[str, tuple[Vec, Vec]], reference_mm: Vec) -> dict[str, tuple[Vec, Vec]]:
    """Each table shifted by its value at the reference point of its input axis."""
    shifted = {}
    for name, (positions, values) in tables.items():
        at_reference = np.interp(reference_mm[AXIS_INDEX[name[2]]], positions, values)
        shifted[name] = (positions, values - at_reference)
    return shifted


def _reversal(tables: ErrorTableSet, axis: str, direction: str) -> tuple[Vec, Vec] | None:
    """``E<axis><axis><direction>`` minus the direction-free table, on its positions."""
    name = f"E{axis}{axis}"
    if name + direction not in tables.tables or name not in tables.tables:
        return None
    own, mean = tables.tables[name + direction], tables.tables[name]
    return own.positions_mm, own.values - np.interp(
        own.positions_mm, mean.positions_mm, mean.values
    )


def _with_reversal(
    model: CompModel, tables: ErrorTableSet, mean: dict[str, tuple[Vec, Vec]], direction: str
) -> dict[str, tuple[Vec, Vec]]:
    if not model.directional:
        return dict(mean)
    result = dict(mean)
    for axis in AXES:
        name = f"E{axis}{axis}"
        reversal = _reversal(tables, axis, direction)
        if name in mean and reversal is not None:
            positions, values = mean[name]
            result[name] = (positions, values + np.interp(positions, *reversal))
    return result


def _field(chain: Chain, points_mm: Vec, tool_offset_mm: Vec, model: ErrorModel) -> Vec:
    return deviation(chain, points_mm, tool_offset_mm, model)[0]


def fit_compensation(
    model: CompModel,
    tables: ErrorTableSet,
    chain: Chain,
    travel_mm: tuple[Vec, Vec],
    tool_offset_mm: Vec,
    reference_mm: Vec,
) -> CompensationFit:
    """Fit a controller's compensation model to the error ``post`` predicts.

    Parameters
    ----------
    model : CompModel
        The tables the controller has.
    tables : ErrorTableSet
        ``post``'s error tables (mm, rad), directional positioning tables optional.
    chain : Chain
        Kinematic chain (lever arms of the angular errors).
    travel_mm : (ndarray (3,), ndarray (3,))
        Lower and upper travel limits: the grid spans the whole travel.
    tool_offset_mm : ndarray, shape (3,)
        Tool point ``t`` whose error is compensated.
    reference_mm : ndarray, shape (3,)
        Reference point of each axis; one-variable tables are zero there.
    """
    low, high = (np.asarray(v, dtype=float) for v in travel_mm)
    nodes = {axis: tables.positioning_table(axis).positions_mm for axis in AXES}
    points = travel_grid(nodes, low, high)
    t = np.asarray(tool_offset_mm, dtype=float)
    directions = ("+", "-") if _has_directions(tables) else ("",)
    fields = {d: _field(chain, points, t, tables.model(d)) for d in directions}
    if model.volumetric:
        mean = forward = reverse = tables.model("")
        if directions != ("",):
            forward, reverse = tables.model("+"), tables.model("-")
        converged = True
    else:
        mean, converged = fit_tables(model, nodes, chain, points, t, reference_mm, tables.model(""))
        forward = ErrorTables(tables=_with_reversal(model, tables, mean.tables, "+"))
        reverse = ErrorTables(tables=_with_reversal(model, tables, mean.tables, "-"))
    applied = {"": mean, "+": forward, "-": reverse}
    before = np.concatenate([fields[d] for d in directions])
    after = np.concatenate([fields[d] - _field(chain, points, t, applied[d]) for d in directions])
    optional, after_optional_um = None, None
    if model.optional:
        left = RemainingErrors(tables.model(""), mean)
        option = CompModel(model.optional, directional=False)
        optional, optional_converged = fit_tables(
            option, nodes, chain, points, t, reference_mm, left
        )
        converged &= optional_converged
        after_optional_um = _rms_um(
            after - np.tile(_field(chain, points, t, optional), (len(directions), 1))
        )
    return CompensationFit(
        model=model,
        mean=mean,
        forward=forward,
        reverse=reverse,
        before_um=_rms_um(before),
        after_um=_rms_um(after),
        grid_points=len(points),
        converged=converged,
        optional=optional,
        after_optional_um=after_optional_um,
        warnings=extrapolated_references(tables, np.asarray(reference_mm, dtype=float)),
    )


def _u95_text(name: str, u95: float) -> str:
    """``EXX 29.4 um`` (linear errors, stored in mm) or ``EAX 3.1 urad`` (angular, rad)."""
    return f"{name} {u95 * 1e3:.1f} um" if name[1] in AXES else f"{name} {u95 * 1e6:.1f} urad"


def extrapolated_references(tables: ErrorTableSet, reference_mm: Vec) -> tuple[str, ...]:
    """One warning per axis whose reference point lies outside the measured range of its
    tables (the error-table file's ``range`` column), naming those tables and their U95
    at the reference.

    Every controller table is zero at the reference point, so the value ``post``'s tables
    have there shifts them all: from an extrapolated stretch it is only as good as that
    U95. A second station whose lines measure across the reference removes it.
    """
    warnings = []
    for axis in AXES:
        reference = float(reference_mm[AXIS_INDEX[axis]])
        worst: dict[str, float] = {}  # table name (directions together) -> largest U95
        ranges = []
        for name, table in sorted(tables.tables.items()):
            measured = table.positions_mm[table.measured_mask()]
            if name[2] != axis or not measured.size:
                continue
            low, high = float(measured[0]), float(measured[-1])
            ranges.append((low, high))
            if not low - 1e-6 <= reference <= high + 1e-6:
                u95 = float(np.interp(reference, table.positions_mm, table.u95))
                worst[name[:3]] = max(u95, worst.get(name[:3], 0.0))
        named = [_u95_text(name, u95) for name, u95 in worst.items()]
        if named:
            low = max(r[0] for r in ranges)
            high = min(r[1] for r in ranges)
            warnings.append(
                f"the reference point {axis} = {reference:g} mm lies outside the measured"
                f" range of {axis} ({low:g} to {high:g} mm): the reference values of these"
                f" tables come from their extrapolated stretch, U95 there: {', '.join(named)};"
                f" every {axis} table the control gets is shifted by that value. A second"
                f" station whose lines measure {axis} across {reference:g} mm removes it"
            )
    return tuple(warnings)


def fit_tables(
    model: CompModel,
    nodes_mm: dict[str, Vec],
    chain: Chain,
    points_mm: Vec,
    tool_offset_mm: Vec,
    reference_mm: Vec,
    errors: ErrorModel,
) -> tuple[ErrorTables, bool]:
    """A controller's one-variable tables fitted to the field of ``errors`` (direction-free).

    Parameters
    ----------
    nodes_mm : dict of str to ndarray
        Table positions per input axis, mm.
    points_mm : ndarray, shape (N, 3)
        Where the field is fitted (:func:`travel_grid`).
    tool_offset_mm : ndarray, shape (3,)
    reference_mm : ndarray, shape (3,)
        The tables are zero there.
    errors : ErrorModel
        The errors to compensate: ``post``'s tables, or a simulator's truth.

    Returns
    -------
    tables : ErrorTables
    converged : bool
        False when the grid left a table value undetermined.
    """
    field_mm = _field(chain, points_mm, tool_offset_mm, errors)
    fitted, converged = _fit_field(model, nodes_mm, points_mm, field_mm)
    fitted = _zero_at(fitted, np.asarray(reference_mm, dtype=float))
    return ErrorTables(tables=fitted), converged


def _has_directions(tables: ErrorTableSet) -> bool:
    return any(name.endswith(("+", "-")) for name in tables.tables)
