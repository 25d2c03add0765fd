"""Aligning the launch and receiver units to each other (pure control logic on roles).

Two modes, as in the positioning-unit design (seed 002, section 2.2):

* **manual**: the operator jogs single axes from the terminal until every beam
  is in range (:func:`parse_jog`, :func:`jog`, :func:`range_used`);
* **automatic fine alignment** (:func:`fine_align`): each unit axis gets a
  position loop fed by one interferometer channel, and the loops drive the
  five non-linear channels to zero.

Channel-to-axis mapping (derived in docs/conventions-notes.md, "Alignment")::

    a1 (launch azimuth)     -> straightness_v   sv = -l·cos(e)·dphi1
    a2 (launch elevation)   -> straightness_w   sw = -l·dphi2
    a3 (receiver azimuth)   -> angle_w          aw = cos(e)·(dphi3 - dphi1)
    a4 (receiver elevation) -> angle_v          av = dphi4 + dphi2
    a5 (receiver roll)      -> angle_u          au = sin(e)·(dphi3 - dphi1) - dphi5

with ``l`` the cp-to-cp distance and ``e`` the beam elevation. The launch axes
also turn the launch frame, so they move the angle channels as well; the loops
are decoupled by solving this (triangular) sensitivity matrix for the step,
and the distance ``l``, which scales the straightness loops, is re-estimated
from every step's response (at most halved or doubled per step: a noisy
response must not multiply the loop gain).

**Beam recovery.** When the beam leaves its range (before or during fine
alignment), the units go back to the last angles at which the beam was in
range (or the present ones, if it was never seen); if it is not there, the
receiver alone searches a square spiral of angles (an angle channel out of
range), then both units search a square spiral (:func:`search_offsets_urad`):
the launch unit sweeps the beam across the receiver's position while the
receiver turns with it so the angle channels stay as they were. The steps let
the capture regions overlap; the spirals reach ``search_radius_urad`` plus
``search_radius_um`` over the beam's length (the units' pointing uncertainty).
Only if the search fails is a person asked to jog the units.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from xmalign.errors import BeamLostError, DeviceTimeoutError, InputError, OutOfRangeError
from xmalign.geometry import Vec
from xmalign.roles import (
    CHANNELS,
    Clock,
    Interferometer,
    InterferometerReading,
    PositioningUnit,
    RotaryAxis,
    move_axes,
)

logger = logging.getLogger(__name__)

#: The five channels fine alignment drives to zero, in the order of the unit axes a1..a5.
ALIGNED_CHANNELS = (
    "straightness_v_um",
    "straightness_w_um",
    "angle_w_urad",
    "angle_v_urad",
    "angle_u_urad",
)
_CHANNEL_INDEX = [CHANNELS.index(name) for name in ALIGNED_CHANNELS]
#: Accepted range of the running distance estimate, mm (an XM-60 reaches 4 m).
DISTANCE_LIMITS_MM = (20.0, 10000.0)
#: Smallest predicted beam motion of a launch step that re-estimates the distance, um.
_MIN_PROBE_UM = 20.0
#: Largest factor by which one step's response may change the distance estimate.
_MAX_DISTANCE_FACTOR = 2.0
#: cos(elevation) below which the azimuth search steps stop growing (near-vertical beams).
_MIN_COS_ELEVATION = 0.2


def sensitivity(elevation_rad: float, distance_mm: float, n_axes: int = 5) -> Vec:
    """Response of the aligned channels to small axis moves.

    Parameters
    ----------
    elevation_rad : float
        Elevation of the beam (launch axis a2 angle).
    distance_mm : float
        cp-to-cp distance ``l``.
    n_axes : int
        5 with the receiver roll a5, 4 without it (then ``angle_u`` is not aligned).

    Returns
    -------
    ndarray, shape (n_axes, n_axes)
        Rows :data:`ALIGNED_CHANNELS` (um or urad), columns axes a1..a5, per urad.
    """
    c, s = math.cos(elevation_rad), math.sin(elevation_rad)
    l_um_per_urad = distance_mm * 1e-3
    matrix = np.array(
        [
            [-l_um_per_urad * c, 0.0, 0.0, 0.0, 0.0],
            [0.0, -l_um_per_urad, 0.0, 0.0, 0.0],
            [-c, 0.0, c, 0.0, 0.0],
            [0.0, 1.0, 0.0, 1.0, 0.0],
            [-s, 0.0, s, 0.0, -1.0],
        ]
    )
    return matrix[:n_axes, :n_axes]


def aligned_error(reading: InterferometerReading, n_axes: int = 5) -> Vec:
    """The channels fine alignment drives to zero, in :data:`ALIGNED_CHANNELS` order, (n_axes,)."""
    return np.asarray(reading.channels, dtype=float)[_CHANNEL_INDEX[:n_axes]]


@dataclass(frozen=True)
class FineAlignmentSettings:
    """Convergence criteria and loop parameters of :func:`fine_align`.

    Attributes
    ----------
    straightness_tol_um, angle_tol_urad : float
        Converged when every straightness and angle channel is within these.
    timeout_s : float
        Give up after this long (clock time) with a DeviceTimeoutError.
    gain : float
        Fraction of the computed correction applied per step (0 < gain <= 1).
    average_s : float
        Interferometer averaging per step.
    settle_s : float
        Wait after a move before reading (vibration of the units).
    max_step_urad : float
        Largest correction of one axis in one step.
    move_timeout_s : float
        Timeout of each unit move.
    align_roll : bool
        Also drive ``angle_u`` to zero with the receiver roll a5.
    search_radius_urad, search_radius_um : float
        How far from the last in-range angles the beam search goes: the units'
        pointing uncertainty as an angle, plus a lateral uncertainty of where the
        receiver is (seen over the beam's length, which dominates on short
        beams). Both 0 disable the search.
    beam_capture_um, angle_capture_urad : float
        How far off the receiver's centre a beam is still seen, and how far off
        facing the receiver may turn (a little inside the interferometer's
        straightness and angle ranges); they set the search steps.
    max_recoveries : int
        How often one fine alignment may recover a lost beam before giving up.
    steer_launch : bool
        Also steer the launch axes (straightness). Off at a measuring line's
        start: there the receiver is close to the launch unit, so zeroing a
        few µm of straightness would tilt the beam by (offset / distance) and
        lose it at the line's far end; the beam direction comes from the
        identified pose and only the receiver turns to face it.
    """

    straightness_tol_um: float = 1.0
    angle_tol_urad: float = 3.0
    timeout_s: float = 5.0
    gain: float = 0.9
    average_s: float = 0.05
    settle_s: float = 0.02
    max_step_urad: float = 5000.0
    move_timeout_s: float = 2.0
    align_roll: bool = True
    steer_launch: bool = True
    search_radius_urad: float = 1000.0
    search_radius_um: float = 500.0
    beam_capture_um: float = 200.0
    angle_capture_urad: float = 400.0
    max_recoveries: int = 3


@dataclass(frozen=True)
class AlignmentStep:
    """One iteration: reading time, the aligned channels (um, urad) and the distance estimate."""

    time_s: float
    error: Vec
    distance_mm: float


@dataclass
class FineAlignmentResult:
    """Outcome of :func:`fine_align`: the last reading, unit angles (rad) and the history.

    ``recoveries`` counts the times the beam was lost and found again (back at
    the last in-range angles or by the search), ``search_s`` the time spent
    searching.
    """

    reading: InterferometerReading
    launch_rad: Vec
    receiver_rad: Vec
    distance_mm: float
    elapsed_s: float
    steps: list[AlignmentStep] = field(default_factory=list)
    recoveries: int = 0
    search_s: float = 0.0

    @property
    def straightness_um(self) -> Vec:
        """Residual ``[sv, sw]``, shape (2,)."""
        return aligned_error(self.reading)[:2]


#: Singular values of the tolerance-scaled sensitivity below this fraction of the
#: largest are directions the axes cannot steer (gimbal lock of a vertical beam).
_CONTROLLABLE_RATIO = 1e-3


def _tolerances(settings: FineAlignmentSettings, n_axes: int) -> Vec:
    tolerances = [settings.straightness_tol_um] * 2 + [settings.angle_tol_urad] * 3
    return np.array(tolerances[:n_axes])


@dataclass(frozen=True)
class _Loop:
    """The loop's linear model in tolerance units, split into what the axes can steer.

    Near a vertical beam the azimuth axes turn the beam about itself (gimbal
    lock): the lateral error across the elevation plane cannot be steered by
    small moves. Such directions are left alone and do not count against
    convergence; their residual is what the coarse pointing left, which the
    beam ranges absorb.
    """

    scale: Vec  # tolerance of each channel, (n,)
    u_steerable: Vec  # (n, k) left singular vectors of the steerable directions
    solve: Vec  # (n_axes, n) pseudo-inverse on the steerable directions

    @classmethod
    def of(cls, matrix: Vec, scale: Vec) -> _Loop:
        u, s, vt = np.linalg.svd(matrix / scale[:, None])
        keep = s > _CONTROLLABLE_RATIO * s[0]
        solve = vt[keep].T @ np.diag(1.0 / s[keep]) @ u[:, keep].T @ np.diag(1.0 / scale)
        return cls(scale, u[:, keep], solve)

    def steerable_error(self, error: Vec) -> Vec:
        """The part of the error the axes can remove, in tolerance units."""
        scaled = error / self.scale
        return self.u_steerable @ (self.u_steerable.T @ scaled)


def _describe(error: Vec) -> str:
    names = [n.removesuffix("_um").removesuffix("_urad") for n in ALIGNED_CHANNELS]
    units = ["um", "um", "urad", "urad", "urad"]
    return ", ".join(f"{n} {v:+.1f} {u}" for n, v, u in zip(names, error, units, strict=False))


def _check_distance(distance_mm: float) -> None:
    """A cp-to-cp distance the search and the loops can work with (a NaN, an infinity or
    a micrometre would make the spiral search endless)."""
    low, high = DISTANCE_LIMITS_MM
    if not low <= distance_mm <= high:
        raise OutOfRangeError(
            f"cp-to-cp distance {distance_mm:g} mm is outside {low:g}..{high:g} mm"
            " (the instrument's reach)"
        )


def search_offsets_urad(step_urad: float, radius_urad: float) -> Vec:
    """Offsets of a square spiral around the centre, nearest first, (N, 2) urad.

    Grid points ``step_urad`` apart out to ``radius_urad`` (the centre itself excluded),
    walked ring by ring so that the units move only one step between readings.
    """
    if step_urad <= 0 or radius_urad < step_urad:
        return np.zeros((0, 2))
    points: list[tuple[int, int]] = []
    for r in range(1, int(radius_urad // step_urad) + 1):
        points += [(r, k) for k in range(-r + 1, r + 1)]  # right side, upwards
        points += [(k, r) for k in range(r - 1, -r - 1, -1)]  # top, leftwards
        points += [(-r, k) for k in range(r - 1, -r - 1, -1)]  # left side, downwards
        points += [(k, -r) for k in range(-r + 1, r + 1)]  # bottom, rightwards
    grid = np.array(points, dtype=float) * step_urad
    return grid[np.hypot(grid[:, 0], grid[:, 1]) <= radius_urad + 1e-9]


def _search_targets(
    centre_rad: Vec, offsets_urad: Vec, elevation_rad: float, receiver_only: bool = False
) -> Vec:
    """Unit setpoints (N, n_axes) for a search pattern of offsets (N, 2), urad.

    Beam search (``receiver_only`` False): the launch unit moves the beam across the
    receiver, the azimuth step scaled by 1/cos(elevation) so that the beam moves the
    same lateral distance in both directions; the receiver turns with the beam (a3
    with a1, a4 against a2) so that the angle channels stay as they were. Angle
    search (``receiver_only``): the receiver alone turns (a3, a4), which changes the
    angle channels ``angle_w``, ``angle_v`` by the offsets and not the straightness.
    """
    cos_e = max(abs(math.cos(elevation_rad)), _MIN_COS_ELEVATION)
    d1 = offsets_urad[:, 0] * 1e-6 / cos_e
    d2 = offsets_urad[:, 1] * 1e-6
    steps = np.zeros((len(offsets_urad), len(centre_rad)))
    if receiver_only:
        steps[:, 2], steps[:, 3] = d1, d2
        return centre_rad + steps
    steps[:, 0], steps[:, 1] = d1, d2
    if len(centre_rad) >= 4:
        steps[:, 2], steps[:, 3] = d1, -d2
    return centre_rad + steps


@dataclass
class _Recovery:
    """State of beam recovery within one fine alignment."""

    last_in_range_rad: Vec | None = None
    count: int = 0
    search_s: float = 0.0


def _recover(
    launch: PositioningUnit,
    receiver: PositioningUnit,
    interferometer: Interferometer,
    clock: Clock,
    setpoint: Vec,
    distance_mm: float,
    recovery: _Recovery,
    settings: FineAlignmentSettings,
) -> tuple[Vec, InterferometerReading]:
    """Find the lost beam: back to the last in-range angles, then a spiral search.

    Returns the setpoint where the beam is in range and the reading there.
    Raises BeamLostError when neither finds it (or after ``max_recoveries``).
    """
    started = clock.now()
    recovery.count += 1
    if recovery.count > settings.max_recoveries:
        raise BeamLostError(
            f"the beam was lost {recovery.count} times during fine alignment; jog the units"
            " until every beam is in range (xmalign align --manual) and start again"
        )
    centre = setpoint if recovery.last_in_range_rad is None else recovery.last_in_range_rad
    step_urad = math.sqrt(2.0) * settings.beam_capture_um / distance_mm * 1e3
    radius_urad = settings.search_radius_urad + settings.search_radius_um / distance_mm * 1e3
    offsets = search_offsets_urad(step_urad, radius_urad)
    angle_offsets = search_offsets_urad(math.sqrt(2.0) * settings.angle_capture_urad, radius_urad)
    elevation = float(centre[1])
    candidates = np.vstack(
        ([centre[None, :]] if recovery.last_in_range_rad is not None else [])
        + ([] if len(centre) < 4 else [_search_targets(centre, angle_offsets, elevation, True)])
        + [_search_targets(centre, offsets, elevation)]
    )
    logger.info(
        "beam lost (%s in range before); searching %d points, step %.0f urad",
        "was" if recovery.last_in_range_rad is not None else "never",
        len(candidates),
        step_urad,
    )
    try:
        for target in candidates:
            _move_units(launch, receiver, target, settings.move_timeout_s, clock)
            clock.sleep(settings.settle_s)
            reading = interferometer.average(settings.average_s)
            if reading.beam_ok:
                logger.info(
                    "beam found again %.1f urad from the last in-range angles",
                    float(np.linalg.norm(target - centre) * 1e6),
                )
                return target, reading
    finally:
        recovery.search_s += clock.now() - started
    raise BeamLostError(
        "the beam was lost during fine alignment and not found again (back to the last"
        f" in-range angles, then spiral searches of {len(candidates)} points out to"
        f" {radius_urad:.0f} urad); jog the units until every beam is in range"
        " (xmalign align --manual) and start again"
    )


def find_beam(
    launch: PositioningUnit,
    receiver: PositioningUnit,
    interferometer: Interferometer,
    clock: Clock,
    last_in_range_rad: Vec,
    distance_mm: float,
    settings: FineAlignmentSettings,
) -> tuple[Vec, InterferometerReading]:
    """Find a lost beam: back to ``last_in_range_rad``, then the spiral searches.

    The recovery of fine alignment (module docstring, "Beam recovery") for a
    beam lost elsewhere, e.g. while capturing a line's points. Returns the unit
    setpoint (launch then receiver angles, rad) where the beam is in range and
    the reading there; raises BeamLostError when the search does not find it.
    """
    _check_distance(distance_mm)
    centre = np.asarray(last_in_range_rad, dtype=float)
    recovery = _Recovery(last_in_range_rad=centre.copy())
    return _recover(
        launch, receiver, interferometer, clock, centre, distance_mm, recovery, settings
    )


def _updated_distance(
    distance_mm: float, elevation_rad: float, step_urad: Vec, straightness_change_um: Vec
) -> float:
    """Least-squares distance from one launch step (commanded, urad) and the straightness response.

    Only steps that should move the beam by at least :data:`_MIN_PROBE_UM` are
    used, so that noise and the small cross-talk of the receiver's optical-centre
    offset do not corrupt the estimate; one step changes the estimate by at most
    a factor :data:`_MAX_DISTANCE_FACTOR` (a unit's positioning noise on a small
    step must not multiply the loop gain and throw the beam out of range).
    """
    lever = np.array([math.cos(elevation_rad) * step_urad[0], step_urad[1]])
    if np.linalg.norm(lever) * distance_mm * 1e-3 < _MIN_PROBE_UM:
        return distance_mm
    estimate = -1e3 * float(straightness_change_um @ lever) / float(lever @ lever)
    low, high = DISTANCE_LIMITS_MM
    if not low <= estimate <= high:
        return distance_mm
    return float(
        np.clip(estimate, distance_mm / _MAX_DISTANCE_FACTOR, distance_mm * _MAX_DISTANCE_FACTOR)
    )


def fine_align(
    launch: PositioningUnit,
    receiver: PositioningUnit,
    interferometer: Interferometer,
    clock: Clock,
    distance_mm: float,
    settings: FineAlignmentSettings | None = None,
    on_step: Callable[[AlignmentStep], None] | None = None,
) -> FineAlignmentResult:
    """Drive straightness and angles to zero with position loops on the unit axes.

    Each step reads the interferometer (averaged), computes the correction of
    every axis from the decoupled channel loops, and moves the units by it.
    The axes are left unlocked where they stopped; the caller locks them
    (:func:`xmalign.safety.units_locked_on_exit`).

    Parameters
    ----------
    launch, receiver : PositioningUnit
        Launch unit (a1, a2) and receiver unit (a3, a4[, a5]).
    interferometer : Interferometer
        Reads in the beam's frame.
    clock : Clock
        Time of the timeout (simulated time in the simulator).
    distance_mm : float
        First guess of the cp-to-cp distance; refined from the responses.
    settings : FineAlignmentSettings, optional
    on_step : callable, optional
        Called with each :class:`AlignmentStep` (progress display).

    Raises
    ------
    BeamLostError
        A beam left its range and neither going back to the last in-range angles
        nor the spiral search found it (see the module's "Beam recovery").
    OutOfRangeError
        ``distance_mm`` is outside :data:`DISTANCE_LIMITS_MM`.
    DeviceTimeoutError
        Not converged within ``settings.timeout_s`` (search time not counted); the
        message gives the residuals.
    """
    _check_distance(distance_mm)
    settings = settings or FineAlignmentSettings()
    n_axes = 5 if settings.align_roll and len(receiver.axes) >= 3 else 4
    start_s = clock.now()
    setpoint = np.concatenate([launch.angles_rad(), receiver.angles_rad()[: n_axes - 2]])
    steps: list[AlignmentStep] = []
    last_step: tuple[Vec, Vec] | None = None  # (commanded launch step urad, error before it)
    recovery = _Recovery()
    prior_distance_mm = distance_mm
    while True:
        reading = interferometer.average(settings.average_s)
        if not reading.beam_ok:
            setpoint, reading = _recover(
                launch,
                receiver,
                interferometer,
                clock,
                setpoint,
                prior_distance_mm,
                recovery,
                settings,
            )
            distance_mm, last_step = prior_distance_mm, None
        recovery.last_in_range_rad = setpoint.copy()
        error = aligned_error(reading, n_axes)
        elevation = float(setpoint[1])
        if last_step is not None:
            distance_mm = _updated_distance(
                distance_mm, elevation, last_step[0], error[:2] - last_step[1][:2]
            )
        step = AlignmentStep(time_s=reading.time_s, error=error, distance_mm=distance_mm)
        steps.append(step)
        if on_step is not None:
            on_step(step)
        matrix = sensitivity(elevation, distance_mm, n_axes)
        if not settings.steer_launch:
            matrix[:, :2] = 0.0
        loop = _Loop.of(matrix, _tolerances(settings, n_axes))
        if np.all(np.abs(loop.steerable_error(error)) <= 1.0):
            return FineAlignmentResult(
                reading=reading,
                launch_rad=launch.angles_rad(),
                receiver_rad=receiver.angles_rad(),
                distance_mm=distance_mm,
                elapsed_s=clock.now() - start_s,
                steps=steps,
                recoveries=recovery.count,
                search_s=recovery.search_s,
            )
        if clock.now() - start_s - recovery.search_s >= settings.timeout_s:
            raise DeviceTimeoutError(
                f"fine alignment did not converge in {settings.timeout_s:g} s ({_describe(error)})"
            )
        correction_urad = loop.solve @ -error
        correction_urad = np.clip(
            settings.gain * correction_urad, -settings.max_step_urad, settings.max_step_urad
        )
        last_step = (correction_urad[:2], error)
        setpoint = setpoint + correction_urad * 1e-6
        _move_units(launch, receiver, setpoint, settings.move_timeout_s, clock)
        clock.sleep(settings.settle_s)


def _move_units(
    launch: PositioningUnit,
    receiver: PositioningUnit,
    setpoint_rad: Vec,
    timeout_s: float,
    clock: Clock,
) -> None:
    axes: list[RotaryAxis] = [*launch.axes, *receiver.axes][: len(setpoint_rad)]
    move_axes(axes, setpoint_rad, timeout_s, "positioning units", clock)


# --- manual mode ----------------------------------------------------------------------------

_JOG_PATTERN = re.compile(r"^\s*a([1-5])\s+([+-]?\d+(?:\.\d*)?|[+-]?\.\d+)\s*$", re.IGNORECASE)


@dataclass(frozen=True)
class JogCommand:
    """Move axis ``axis`` (1..5, docs/conventions.md numbering) by ``step_rad``."""

    axis: int
    step_rad: float


def parse_jog(text: str) -> JogCommand:
    """Parse ``"a<n> <step_deg>"`` as typed by the operator, e.g. ``"a2 -0.01"``."""
    match = _JOG_PATTERN.match(text)
    if match is None:
        raise InputError(
            f"jog command {text.strip()!r}: expected an axis a1..a5 and a step in degrees,"
            " e.g. 'a2 -0.01'"
        )
    return JogCommand(axis=int(match.group(1)), step_rad=math.radians(float(match.group(2))))


def unit_axis(launch: PositioningUnit, receiver: PositioningUnit, axis: int) -> RotaryAxis:
    """Axis ``a<axis>``: a1, a2 on the launch unit, a3, a4, a5 on the receiver."""
    axes = [*launch.axes, *receiver.axes]
    if not 1 <= axis <= len(axes):
        raise OutOfRangeError(f"there is no axis a{axis} (these units have a1..a{len(axes)})")
    return axes[axis - 1]


def jog(
    launch: PositioningUnit, receiver: PositioningUnit, command: JogCommand, timeout_s: float
) -> float:
    """Move one axis by the command's step and wait; returns its new reported angle, rad."""
    axis = unit_axis(launch, receiver, command.axis)
    axis.move_to(axis.position_rad() + command.step_rad)
    axis.wait_in_position(timeout_s)
    return axis.position_rad()


def range_used(
    reading: InterferometerReading, straightness_range_um: float, angle_range_urad: float
) -> Vec:
    """Fraction of its range each aligned channel uses (1 = at the edge), shape (5,)."""
    ranges = np.array([straightness_range_um] * 2 + [angle_range_urad] * 3)
    return np.abs(aligned_error(reading)) / ranges


@dataclass
class AlignmentDevices:
    """The units, the interferometer and the clock one alignment runs on."""

    launch: PositioningUnit
    receiver: PositioningUnit
    interferometer: Interferometer
    clock: Clock
    distance_mm: float
