"""The virtual machine tool: seedable rigid-body errors (docs/conventions.md), ``ErrorModel``.

Each of the 18 error motions is, as in the Monte Carlo study of seed 003
(its Eq. 3 and Table 1), a polynomial of order 0 and 1 plus two Fourier terms
of the normalised axis position ``x = (k - k_min) / (k_max - k_min)``::

    E(x) = a0 + a1·x + b1·sin(n1·π·x) + c1·cos(n1·π·x) + b2·sin(n2·π·x) + c2·cos(n2·π·x)

with every coefficient drawn uniformly in ±(its amplitude). The truth of the
deviation is :func:`xmalign.rigid_body.deviation`, not re-implemented here.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from xmalign.errors import OutOfRangeError
from xmalign.formats.error_tables import ErrorTableSet, Table, write_error_tables
from xmalign.geometry import Vec
from xmalign.machine import AXES, Machine
from xmalign.rigid_body import (
    AXIS_INDEX,
    MOTION_NAMES,
    ROTATION_NAMES,
    SLOPE_TO_SQUARENESS,
    SQUARENESS_NAMES,
    TRANSLATION_NAMES,
    Chain,
    ErrorModel,
    deviation,
)

UM = 1e-3
URAD = 1e-6

#: Seed 003 Table 1: (a0, a1, n1, b1, c1, n2, b2, c2), µm or µrad.
SEED_003_TABLE_1: dict[str, tuple[float, ...]] = {
    "EXX": (0, 70, 0.5, 20, 20, 5, 10, 10),
    "EYX": (0, 0, 0.5, 30, 0, 5, 3, 3),
    "EZX": (0, 0, 0.5, 15, 0, 5, 3, 3),
    "EAX": (10, 20, 0.5, 10, 10, 5, 5, 5),
    "EBX": (10, 20, 0.5, 10, 10, 5, 5, 5),
    "ECX": (10, 20, 0.5, 10, 10, 5, 5, 5),
    "EXY": (0, 0, 0.5, 15, 0, 2, 5, 5),
    "EYY": (0, 30, 0.5, 5, 5, 2, 3, 3),
    "EZY": (0, 0, 0.5, 15, 0, 2, 5, 5),
    "EAY": (10, 30, 0.5, 10, 10, 2, 5, 5),
    "EBY": (10, 30, 0.5, 10, 10, 2, 5, 5),
    "ECY": (10, 30, 0.5, 10, 10, 2, 5, 5),
    "EXZ": (0, 0, 0.5, 15, 0, 1, 5, 5),
    "EYZ": (0, 0, 0.5, 15, 0, 1, 5, 5),
    "EZZ": (0, 30, 0.5, 30, 30, 1, 3, 3),
    "EAZ": (10, 30, 0.5, 10, 10, 1, 3, 3),
    "EBZ": (10, 30, 0.5, 10, 10, 1, 3, 3),
    "ECZ": (10, 30, 0.5, 10, 10, 1, 3, 3),
}

_POSITIONING = ("EXX", "EYY", "EZZ")


@dataclass(frozen=True)
class ErrorAmplitudes:
    """How large the virtual machine's errors are drawn (half-widths of uniform ranges).

    Attributes
    ----------
    motions : dict of str to tuple
        Per ISO 230-1 motion name ``(a0, a1, n1, b1, c1, n2, b2, c2)`` in µm or µrad
        (``n1``, ``n2`` are the Fourier orders); default seed 003 Table 1.
    squareness_urad : float
        Half-width of EC0Y, EA0Z, EB0Z.
    scale : float
        Factor on every amplitude (0 gives a perfect machine).
    repeatability_um : float
        Standard deviation of the tool point per approach, each axis.
    backlash_um : tuple of float
        Lost motion of X, Y, Z on reversal: a forward approach lands half of it
        short, a reverse approach half of it long.
    """

    motions: dict[str, tuple[float, ...]] = field(default_factory=lambda: dict(SEED_003_TABLE_1))
    squareness_urad: float = 20.0
    scale: float = 1.0
    repeatability_um: float = 0.5
    backlash_um: tuple[float, float, float] = (0.0, 0.0, 0.0)


class VirtualMachine:
    """A machine tool with known geometric errors (implements ``ErrorModel``).

    Parameters
    ----------
    machine : Machine
        Chain, travel and receiver offset.
    amplitudes : ErrorAmplitudes, optional
    seed : int, optional
        Seeds the error draw and the repeatability noise.
    """

    def __init__(
        self, machine: Machine, amplitudes: ErrorAmplitudes | None = None, seed: int | None = None
    ) -> None:
        self.machine = machine
        self.chain = Chain.parse(machine.chain)
        self.amplitudes = amplitudes or ErrorAmplitudes()
        rng = np.random.default_rng(seed)
        self._noise_rng = np.random.default_rng(rng.integers(2**63))
        scale = self.amplitudes.scale
        self._coefficients: dict[str, Vec] = {}
        for name in MOTION_NAMES:
            a0, a1, n1, b1, c1, n2, b2, c2 = self.amplitudes.motions[name]
            unit = UM if name in _translation_names() else URAD
            half_widths = np.array([a0, a1, b1, c1, b2, c2]) * unit * scale
            self._coefficients[name] = np.concatenate(
                [rng.uniform(-half_widths, half_widths), [n1, n2]]
            )
        self._squareness = (
            rng.uniform(-1.0, 1.0, 3) * self.amplitudes.squareness_urad * URAD * scale
        )
        self._last_cnc_mm: Vec | None = None
        self._approach = np.ones(3)
        self._noise_mm = np.zeros(3)
        self._applied: ErrorModel | None = None

    def load_compensation(self, applied: ErrorModel | None) -> None:
        """Let the CNC apply compensation tables (None: none).

        The controller shifts every commanded position by the error ``applied``
        predicts at its tool point (``cnc.tool_offset``); the tool's rotation
        stays what the machine's geometry makes it. First order in the error
        gradient, i.e. exact to nanometres for micrometre errors.
        """
        self._applied = applied

    # ErrorModel -------------------------------------------------------------
    def motions(self, axis: str, position_mm: Vec) -> tuple[Vec, Vec]:
        """``(delta mm (N, 3), eps rad (N, 3))`` of ``axis`` at its coordinates (N,)."""
        x = self._normalised(axis, position_mm)
        delta = np.stack([self._error(name, x) for name in TRANSLATION_NAMES[axis]], axis=-1)
        eps = np.stack([self._error(name, x) for name in ROTATION_NAMES[axis]], axis=-1)
        return delta, eps

    def squareness_rad(self) -> Vec:
        """``[EC0Y, EA0Z, EB0Z]`` in rad, shape (3,)."""
        return self._squareness.copy()

    # the physical machine -----------------------------------------------------
    def check_travel(self, cnc_mm: ArrayLike) -> Vec:
        """CNC points (..., 3) as an array; OutOfRangeError if one lies outside the travel."""
        points = np.asarray(cnc_mm, dtype=float)
        inside = self.machine.within_travel(points)
        if not np.all(inside):
            bad = np.atleast_2d(points)[~np.atleast_1d(inside)][0]
            raise OutOfRangeError(
                f"machine position {np.round(bad, 3).tolist()} mm is outside the travel "
                f"{self.machine.travel_mm}"
            )
        return points

    def actual_functional_point(
        self, cnc_mm: ArrayLike, approach_sign: ArrayLike, t_mm: ArrayLike
    ) -> tuple[Vec, Vec]:
        """Where the functional point really is, with backlash and a fresh repeatability draw.

        Parameters
        ----------
        cnc_mm : array_like, shape (3,) or (N, 3)
            Commanded CNC tool point.
        approach_sign : array_like, shape (3,) or (N, 3)
            Direction of the last motion of each axis (+1 forward, -1 reverse).
        t_mm : array_like, shape (3,)
            Functional point offset from the tool point, MCS, mm.

        Returns
        -------
        point_mm : ndarray, shape like ``cnc_mm``
            Actual functional point (nominal ``cnc + t`` plus the deviation).
        rotation_rad : ndarray, shape like ``cnc_mm``
            Rotation of the tool relative to the workpiece.
        """
        cnc = self.check_travel(cnc_mm)
        noise = self._noise_rng.normal(0.0, self.amplitudes.repeatability_um * UM, cnc.shape)
        return self._pose(cnc, approach_sign, t_mm, noise)

    def tool_pose(self, cnc_mm: ArrayLike, t_mm: ArrayLike) -> tuple[Vec, Vec]:
        """Actual functional point and rotation of the physical tool standing at ``cnc_mm``.

        Stateful: the approach direction of each axis follows the sequence of
        positions asked for, and each axis draws its repeatability noise anew
        when it moves to a new coordinate, so repeated readings at a standstill
        see the same tool pose. An axis that does not move keeps its draw: its
        servo holds the position it reached (ISO 230-2's repeatability is that
        of an axis positioning, not of one standing still).
        """
        cnc = self.check_travel(np.asarray(cnc_mm, dtype=float).reshape(3))
        if self._last_cnc_mm is None or not np.array_equal(cnc, self._last_cnc_mm):
            moved = np.ones(3, dtype=bool)
            if self._last_cnc_mm is not None:
                step = np.sign(cnc - self._last_cnc_mm)
                self._approach = np.where(step != 0.0, step, self._approach)
                moved = step != 0.0
            fresh = self._noise_rng.normal(0.0, self.amplitudes.repeatability_um * UM, 3)
            self._noise_mm = np.where(moved, fresh, self._noise_mm)
            self._last_cnc_mm = cnc.copy()
        return self._pose(cnc, self._approach, t_mm, self._noise_mm)

    def _pose(
        self, cnc: Vec, approach_sign: ArrayLike, t_mm: ArrayLike, noise_mm: Vec
    ) -> tuple[Vec, Vec]:
        dp, rotation = deviation(self.chain, cnc, t_mm, self)
        dp = dp.reshape(cnc.shape)
        if self._applied is not None:
            applied_mm, _ = deviation(self.chain, cnc, self.machine.cnc.tool_offset, self._applied)
            dp = dp - applied_mm.reshape(cnc.shape)
        lost = -0.5 * np.asarray(approach_sign, dtype=float) * self.backlash_mm
        point = cnc + np.asarray(t_mm, dtype=float) + dp + lost + noise_mm
        return point, rotation.reshape(cnc.shape)

    @property
    def backlash_mm(self) -> Vec:
        """Backlash of X, Y, Z, mm, shape (3,)."""
        return np.asarray(self.amplitudes.backlash_um, dtype=float) * UM

    # truth tables ---------------------------------------------------------------
    def compensation_points(self, axis: str, spacing_mm: float) -> Vec:
        """Points from the first to the last travel limit at ``spacing_mm`` (last one added)."""
        low, high = self._travel_mm(axis)
        points = np.arange(low, high, spacing_mm)
        return np.append(points, high) if high - points[-1] > 1e-9 else points

    def truth_tables(self, spacing_mm: float) -> ErrorTableSet:
        """The true errors as compensation tables, in the table conventions of docs/conventions.md.

        Positioning and angular errors are zero at the first point; straightness
        is zero at the first and last point, its end-point slope moved into the
        squareness (documented in docs/conventions-notes.md). With backlash the
        positioning errors get ``+``/``-`` tables, both offset by the mean of
        the two directions at the first point.
        """
        result = ErrorTableSet()
        squareness = self.squareness_rad()
        for axis in AXES:
            points = self.compensation_points(axis, spacing_mm)
            nan = np.full(len(points), np.nan)
            delta, eps = self.motions(axis, points)
            values = dict(zip(TRANSLATION_NAMES[axis], delta.T, strict=True))
            values.update(zip(ROTATION_NAMES[axis], eps.T, strict=True))
            for name, value in values.items():
                if name in SLOPE_TO_SQUARENESS:
                    slope = (value[-1] - value[0]) / (points[-1] - points[0])
                    target, sign = SLOPE_TO_SQUARENESS[name]
                    squareness[SQUARENESS_NAMES.index(target)] += sign * slope
                    value = value - value[0] - slope * (points - points[0])
                else:
                    value = value - value[0]
                if name in _POSITIONING and self.backlash_mm[AXIS_INDEX[axis]] > 0.0:
                    half = 0.5 * self.backlash_mm[AXIS_INDEX[axis]]
                    result.tables[name + "+"] = Table(points, value - half, nan)
                    result.tables[name + "-"] = Table(points, value + half, nan)
                else:
                    result.tables[name] = Table(points, value, nan)
        result.squareness = {
            name: (float(v), float("nan"))
            for name, v in zip(SQUARENESS_NAMES, squareness, strict=True)
        }
        return result

    def write_truth_tables(self, path: str, spacing_mm: float) -> None:
        """Write :meth:`truth_tables` as an error-table CSV (docs/formats.md)."""
        write_error_tables(path, self.truth_tables(spacing_mm))

    # helpers --------------------------------------------------------------------
    def _travel_mm(self, axis: str) -> tuple[float, float]:
        k = AXES.index(axis)
        return float(self.machine.travel_min_mm[k]), float(self.machine.travel_max_mm[k])

    def _normalised(self, axis: str, position_mm: ArrayLike) -> Vec:
        low, high = self._travel_mm(axis)
        return (np.asarray(position_mm, dtype=float) - low) / (high - low)

    def _error(self, name: str, x: Vec) -> Vec:
        a0, a1, b1, c1, b2, c2, n1, n2 = self._coefficients[name]
        return (
            a0
            + a1 * x
            + b1 * np.sin(n1 * np.pi * x)
            + c1 * np.cos(n1 * np.pi * x)
            + b2 * np.sin(n2 * np.pi * x)
            + c2 * np.cos(n2 * np.pi * x)
        )


def _translation_names() -> set[str]:
    return {name for axis in AXES for name in TRANSLATION_NAMES[axis]}
