"""The first alignment by itself: find the beam when the launch unit's azimuth is unknown.

The machine file gives the launch unit's rough place, the CNC where the
receiver is; only the launch unit's azimuth (gamma) is unknown, over the whole
circle. :func:`search_first_beam`

1. aims the receiver at the rough place (and the launch unit's elevation at the
   receiver);
2. turns the launch azimuth a1 once round at the unit's speed, reading the
   receiver's signal strength every few ms and the angle a1 has reached;
   wherever a1 moved more than the beam's capture aperture (its radius, as seen
   from the launch unit) between two readings, that stretch is stepped through again
   at rest, so the beam cannot pass the aperture unseen;
3. turns again for other places of the launch unit across the line to the
   receiver (a grid nearest first, out to the rough place's uncertainty), the
   receiver aimed at that place and the launch elevation at the receiver from it:
   the two move together, one turn per place;
4. once the receiver sees the beam, centres it: each of a1, a2, a3, a4 in turn
   finds the two angles where the signal ends and goes to their middle (the
   signal falls off symmetrically), again until the beam is in range (close to
   the launch unit a few passes), which leaves the channels in or near their
   ranges for fine alignment.

Bounded in angle (one turn per place, the places above) and in time
(``timeout_s``); when it finds nothing it raises a :class:`BeamLostError`
saying what to check.

Once an alignment is recorded the azimuth is known and the launch unit lies on
a line: :func:`search_along` points both units from places along it (no turn),
finds where along it the signal ends either side and points from the middle,
then centres as above. Pure control logic on roles (core code).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from xmalign.errors import BeamLostError, DeviceTimeoutError
from xmalign.geometry import Vec
from xmalign.kinematics import aligned_angles
from xmalign.machine import InterferometerRanges
from xmalign.roles import Clock, Interferometer, PositioningUnit, RotaryAxis, move_axes

logger = logging.getLogger(__name__)

#: What the operator checks when the search finds nothing (the one line's end).
WHAT_TO_CHECK = (
    "check that the beam shutter is open, the receiver faces the launch unit, the launch"
    " unit stands where launch_unit.position_mm in the machine file says (within the"
    " search's reach), and nothing blocks the beam between them"
)

#: At most this many passes of centring on a1..a4 (:func:`_centred`).
CENTRING_PASSES = 6
#: From the nearest place the search points from, the beam lands within the first
#: fraction of the capture radius, and the receiver faces the true place within the
#: second of its capture angle (the simulated signal there at least 18 %).
CAPTURE_FRACTION = (0.7, 0.8)
#: A turning a1 crosses the aperture, the beam at most ``CAPTURE_FRACTION[0]`` of the
#: capture radius above or below its centre, along a chord of ``2 sqrt(1 - 0.7^2)``
#: = 1.43 capture radii, 2.86 steps of half a radius: readings at most 0.9 of that
#: apart see the beam on it; only a longer stretch between two is stepped through again.
LATE_STEPS = 0.9 * 4.0 * math.sqrt(1.0 - CAPTURE_FRACTION[0] ** 2)


@dataclass(frozen=True)
class BeamSearchSettings:
    """Bounds and steps of :func:`search_first_beam`.

    Attributes
    ----------
    position_uncertainty_mm : float
        How far the launch unit may stand from the machine file's
        ``launch_unit.position_mm`` along each axis: sets how far the rows and
        the receiver's aims reach.
    timeout_s : float
        The whole search, clock time: enough for every place at 200 mm from the
        launch unit with 25 mm of uncertainty (121 turns of some 14 s).
    max_speed_rad_s : float
        The fastest a1 turns (the units' 30 °/s, docs/registers.md): while it
        turns, the signal is read every half capture aperture at this speed.
    min_signal_pct : float
        A signal at least this strong counts as the beam seen.
    edge_precision : float
        Centring ends when an edge is known within this fraction of the capture
        aperture (or angle).
    move_timeout_s : float
        Each unit move of the centring.
    settle_s : float
        Wait after a centring move before reading.
    """

    position_uncertainty_mm: float = 25.0
    timeout_s: float = 1800.0
    max_speed_rad_s: float = math.radians(30.0)
    min_signal_pct: float = 1.0
    edge_precision: float = 0.01
    move_timeout_s: float = 20.0
    settle_s: float = 0.02


@dataclass(frozen=True)
class BeamSearchResult:
    """Where the search found and centred the beam: unit angles (rad), time (s), rows swept."""

    launch_rad: Vec
    receiver_rad: Vec
    elapsed_s: float
    sweeps: int


@dataclass
class _Search:
    """The devices and limits of one search."""

    launch: PositioningUnit
    receiver: PositioningUnit
    interferometer: Interferometer
    clock: Clock
    settings: BeamSearchSettings
    started_s: float
    on_sweep: Callable[[int], None] | None = None
    sweeps: int = 0

    def sees(self) -> bool:
        return self.interferometer.read().sees_beam(self.settings.min_signal_pct)

    def check_time(self) -> None:
        if self.clock.now() >= self.started_s + self.settings.timeout_s:
            raise DeviceTimeoutError(
                f"no beam found within {self.settings.timeout_s:g} s of searching; {WHAT_TO_CHECK}"
            )

    def move(self, axes: list[RotaryAxis], angles_rad: Vec) -> None:
        move_axes(axes, angles_rad, self.settings.move_timeout_s, "positioning units", self.clock)


def _sweep(
    search: _Search, elevation_rad: float, start_rad: float, step_rad: float
) -> float | None:
    """Turn a1 once round from ``start_rad`` (in the direction of ``step_rad``) at
    ``elevation_rad``, reading the signal all the way; the a1 angle where the beam was
    seen (a1 then stops), or None.

    a1 runs at its own speed, read every ``step_rad`` at the units' top speed; where a
    reading came late (a slow host) and a1 moved farther since the one before than the
    beam's path across the receiver's aperture (:data:`LATE_STEPS`), that stretch is
    stepped through again.
    """
    azimuth, elevation = search.launch.axes[:2]
    search.move([azimuth, elevation], np.array([start_rad, elevation_rad]))
    search.sweeps += 1
    if search.on_sweep is not None:
        search.on_sweep(search.sweeps)
    end_rad = start_rad + math.copysign(2.0 * math.pi, step_rad)
    azimuth.move_to(end_rad)
    last_rad, gaps = start_rad, []
    while abs(last_rad - end_rad) > abs(step_rad) * 1e-3:
        search.check_time()
        search.clock.sleep(abs(step_rad) / search.settings.max_speed_rad_s)
        seen = search.sees()
        here_rad = azimuth.position_rad()
        if seen:
            azimuth.stop()
            return here_rad
        if abs(here_rad - last_rad) > LATE_STEPS * abs(step_rad):
            gaps.append((last_rad, here_rad))
        last_rad = here_rad
    for gap in gaps:
        found_rad = _step_through(search, *gap, step_rad)
        if found_rad is not None:
            return found_rad
    return None


def _step_through(search: _Search, from_rad: float, to_rad: float, step_rad: float) -> float | None:
    """Step a1 from ``from_rad`` to ``to_rad`` (``step_rad`` a step), reading at rest; the
    angle where the beam was seen, or None."""
    azimuth = search.launch.axes[0]
    for angle in np.arange(from_rad, to_rad, step_rad)[1:]:
        search.check_time()
        search.move([azimuth], np.array([angle]))
        if search.sees():
            return float(angle)
    return None


def _back_to_beam(search: _Search, seen_rad: float, step_rad: float) -> bool:
    """Put a1 back where the sweep saw the beam (the reading came before the angle, and
    the axis ran on while stopping); whether the receiver sees it there."""
    azimuth = search.launch.axes[0]
    for back in (0.0, 0.5, 1.0, 1.5):
        search.move([azimuth], np.array([seen_rad - back * step_rad]))
        search.clock.sleep(search.settings.settle_s)
        if search.sees():
            return True
    return False


def _edge(
    search: _Search,
    go: Callable[[float], None],
    inside: float,
    step: float,
    precision: float,
) -> float:
    """The value of what ``go`` sets (an axis angle, a place along a line) where the signal
    ends beyond ``inside`` in the direction of ``step`` (the beam is seen at
    ``inside``), within ``precision``."""
    outside = inside + step
    while True:
        search.check_time()
        go(outside)
        search.clock.sleep(search.settings.settle_s)
        if not search.sees():
            break
        inside, outside = outside, outside + step
    while abs(outside - inside) > precision:
        search.check_time()
        middle = 0.5 * (inside + outside)
        go(middle)
        search.clock.sleep(search.settings.settle_s)
        if search.sees():
            inside = middle
        else:
            outside = middle
    return 0.5 * (inside + outside)


def _middle(search: _Search, go: Callable[[float], None], here: float, half_width: float) -> float:
    """Set what ``go`` sets to the middle of the values where the beam is seen (seen at
    ``here``); that middle."""
    step, precision = 0.25 * half_width, search.settings.edge_precision * half_width
    middle = 0.5 * (
        _edge(search, go, here, step, precision) + _edge(search, go, here, -step, precision)
    )
    go(middle)
    search.clock.sleep(search.settings.settle_s)
    return middle


def _centre(search: _Search, axis: RotaryAxis, half_width_rad: float) -> None:
    """Move ``axis`` to the middle of the angles where the beam is seen (seen where it is)."""
    _middle(
        search,
        lambda angle: search.move([axis], np.array([angle])),
        axis.position_rad(),
        half_width_rad,
    )


def search_first_beam(
    launch: PositioningUnit,
    receiver: PositioningUnit,
    interferometer: Interferometer,
    clock: Clock,
    launch2mcs_mm: Vec,
    receiver_cp_mm: Vec,
    spindle_angle_rad: float,
    ranges: InterferometerRanges,
    settings: BeamSearchSettings | None = None,
    receiver_roll_rad: float = 0.0,
    on_sweep: Callable[[int], None] | None = None,
) -> BeamSearchResult:
    """Find the beam with the launch azimuth unknown, and centre it on the receiver.

    Parameters
    ----------
    launch, receiver : PositioningUnit
        Launch unit (a1, a2) and receiver unit (a3, a4[, a5]).
    interferometer : Interferometer
        Its ``signal_pct`` tells whether the receiver sees the beam (``beam_ok``
        where the instrument gives no signal strength).
    clock : Clock
    launch2mcs_mm : ndarray, shape (3,)
        The launch unit's rough place (the machine file's ``launch_unit``), MCS mm.
    receiver_cp_mm : ndarray, shape (3,)
        The receiver's control point where the machine stands, MCS mm.
    spindle_angle_rad : float
    ranges : InterferometerRanges
        Its ``capture_radius_mm`` and ``capture_angle_mrad`` size the steps, rows and aims.
    settings : BeamSearchSettings, optional
    receiver_roll_rad : float
        The a5 angle to hold.
    on_sweep : callable, optional
        Called with the turn's number as each turn of a1 starts (progress).

    Returns
    -------
    BeamSearchResult

    Raises
    ------
    BeamLostError
        The beam was not seen anywhere in the search's reach (the message says
        what to check).
    DeviceTimeoutError
        Not found within ``settings.timeout_s`` (the same advice).
    """
    settings = settings or BeamSearchSettings()
    started_s = clock.now()
    search = _Search(launch, receiver, interferometer, clock, settings, started_s, on_sweep)
    nominal = aligned_angles(launch2mcs_mm, 0.0, receiver_cp_mm, spindle_angle_rad)
    distance_mm = max(nominal.distance_mm - settings.position_uncertainty_mm * math.sqrt(3), 1.0)
    # the capture aperture as seen from the launch unit (at the nearest it may be), rad
    aperture_rad = ranges.capture_radius_mm / distance_mm
    capture_angle_rad = ranges.capture_angle_mrad * 1e-3
    places = _candidate_places_mm(
        launch2mcs_mm, receiver_cp_mm, settings.position_uncertainty_mm, distance_mm, ranges
    )
    step_rad = 0.5 * _across_azimuth(aperture_rad, nominal.launch_rad[1])
    logger.info(
        "searching the beam: up to %d turns of a1 (rough places), a1 read every %.2f mrad",
        len(places),
        step_rad * 1e3,
    )
    start = -math.pi
    for place_mm in places:
        aimed = aligned_angles(place_mm, 0.0, receiver_cp_mm, spindle_angle_rad)
        receiver_target = np.array([*aimed.receiver_rad[:2], receiver_roll_rad])
        search.move(list(receiver.axes), receiver_target[: len(receiver.axes)])
        direction = 1.0 if start < 0 else -1.0
        seen_rad = _sweep(search, aimed.launch_rad[1], start, direction * step_rad)
        start = -start
        if seen_rad is not None and _back_to_beam(search, seen_rad, step_rad):
            return _centred(search, aperture_rad, nominal.launch_rad[1], capture_angle_rad)
    raise BeamLostError(
        f"no beam found: the launch azimuth swept once round for {len(places)} place(s) of the"
        f" launch unit within {settings.position_uncertainty_mm:g} mm of the machine file's"
        f" ({clock.now() - started_s:.0f} s); {WHAT_TO_CHECK}"
    )


def search_along(
    launch: PositioningUnit,
    receiver: PositioningUnit,
    interferometer: Interferometer,
    clock: Clock,
    pointing: Callable[[float], Vec],
    offsets_mm: Vec,
    distance_mm: float,
    ranges: InterferometerRanges,
    settings: BeamSearchSettings | None = None,
) -> float | None:
    """Point both units from places of the launch unit along a line, each of
    ``offsets_mm`` in turn, until the receiver sees the beam; then point from the middle
    of the offsets where it is seen (edges found as the centring finds them) and centre
    as :func:`search_first_beam` does. The azimuth is known here: one pointing per
    place, no turn.

    Parameters
    ----------
    launch, receiver : PositioningUnit
    interferometer : Interferometer
    clock : Clock
    pointing : callable
        The launch then receiver angles, shape (n_axes,) rad, that point the units
        from the place ``offset_mm`` along the line.
    offsets_mm : ndarray, shape (N,)
        The places to point from, the likeliest first, evenly ``offsets_mm[1] -
        offsets_mm[0]`` apart or one.
    distance_mm : float
        About the distance to the receiver (sizes the centring's steps).
    ranges : InterferometerRanges
    settings : BeamSearchSettings, optional
        ``timeout_s`` bounds the whole; ``move_timeout_s``, ``settle_s`` each pointing.

    Returns
    -------
    float or None
        The offset where the beam is now centred; None when no place saw it, the units
        then pointed from the first.

    Raises
    ------
    DeviceTimeoutError
        Not found and centred within ``settings.timeout_s``.
    """
    settings = settings or BeamSearchSettings()
    search = _Search(launch, receiver, interferometer, clock, settings, clock.now())
    axes = [*launch.axes, *receiver.axes]

    def go(offset_mm: float) -> None:
        search.move(axes, pointing(offset_mm))

    spacing_mm = float(np.ptp(offsets_mm[:2])) if len(offsets_mm) > 1 else 1.0
    for offset_mm in offsets_mm:
        search.check_time()
        go(float(offset_mm))
        search.clock.sleep(settings.settle_s)
        if search.sees():
            middle_mm = _middle(search, go, float(offset_mm), spacing_mm)
            aperture_rad = ranges.capture_radius_mm / distance_mm
            elevation_rad = float(launch.angles_rad()[1])
            _centred(search, aperture_rad, elevation_rad, ranges.capture_angle_mrad * 1e-3)
            return middle_mm
    go(float(offsets_mm[0]))
    return None


def capture_reach_mm(ranges: InterferometerRanges, distance_mm: float) -> tuple[float, float]:
    """How far the launch unit may stand from a place the units point from and the
    receiver still see the beam: the beam lands within ``CAPTURE_FRACTION[0]`` of the
    capture radius (mm), and the receiver, ``distance_mm`` away, faces the true place
    within ``CAPTURE_FRACTION[1]`` of its capture angle (that angle's reach there, mm)."""
    of_radius, of_angle = CAPTURE_FRACTION
    return (
        of_radius * ranges.capture_radius_mm,
        of_angle * ranges.capture_angle_mrad * 1e-3 * distance_mm,
    )


def _candidate_places_mm(
    launch2mcs_mm: Vec,
    receiver_cp_mm: Vec,
    uncertainty_mm: float,
    nearest_mm: float,
    ranges: InterferometerRanges,
) -> Vec:
    """Where the launch unit may stand, nearest the rough place first, shape (N, 3), MCS mm.

    Only its offset across the line to the receiver matters (the turn of a1 covers the
    azimuth): a grid in that plane (``u`` level, ``v`` up the line's normal), fine enough
    that from the nearest node the beam the launch elevation sends lands within 0.7 of
    the capture radius of the receiver's centre (``v``) and the receiver aimed at the
    node faces the true place within 0.8 of its capture angle (``u`` and ``v``, at
    ``nearest_mm``), every place within the rough place's uncertainty
    (``uncertainty_mm`` per axis, ``sqrt(2)`` of it across) in some node's cell.
    Aiming the receiver and the launch elevation at the same place couples them: one
    turn per place, not one per elevation and receiver aim.
    """
    line = receiver_cp_mm - launch2mcs_mm
    line = line / np.linalg.norm(line)
    level = np.cross(line, [0.0, 0.0, 1.0])
    u = level / np.linalg.norm(level) if np.linalg.norm(level) > 1e-6 else np.array([1.0, 0, 0])
    v = np.cross(u, line)
    landing_mm, facing_mm = capture_reach_mm(ranges, nearest_mm)
    spacing_v = min(2.0 * landing_mm, math.sqrt(2.0) * facing_mm)
    spacing_u = 2.0 * math.sqrt(facing_mm**2 - (0.5 * spacing_v) ** 2)
    reach_mm = uncertainty_mm * math.sqrt(2.0)
    n_u, n_v = (math.ceil(reach_mm / spacing - 0.5) for spacing in (spacing_u, spacing_v))
    grid = np.array(
        [
            (i * spacing_u, j * spacing_v)
            for i in range(-n_u, n_u + 1)
            for j in range(-n_v, n_v + 1)
            # the node's cell (where it is the nearest node) reaches into the uncertainty
            if math.hypot(max(abs(i) - 0.5, 0.0) * spacing_u, max(abs(j) - 0.5, 0.0) * spacing_v)
            <= reach_mm
        ]
    )
    grid = grid[np.argsort(np.hypot(*grid.T), kind="stable")]
    return launch2mcs_mm + grid[:, :1] * u + grid[:, 1:] * v


def _across_azimuth(half_width_rad: float, elevation_rad: float) -> float:
    """The turn of an azimuth axis that moves the beam ``half_width_rad`` across at
    ``elevation_rad`` (by cos(elevation) of the turn; at most 20 times the width)."""
    return half_width_rad / max(abs(math.cos(elevation_rad)), 0.05)


def _centred(
    search: _Search, aperture_rad: float, launch_elevation_rad: float, capture_angle_rad: float
) -> BeamSearchResult:
    """Centre the seen beam on a1, a2, a3, a4 in turn, again until the beam is in range
    (at most ``CENTRING_PASSES`` times); the result. ``aperture_rad``: the receiver's
    capture radius seen from the launch unit, which stands at ``launch_elevation_rad``.

    Close to the launch unit, a turn of a1 or a2 also tilts the beam on the receiver, so
    the middle of where the beam is seen lies between centred and faced; each pass,
    the receiver facing the beam better, halves the distance to centred.
    """
    a1, a2 = search.launch.axes[:2]
    a3, a4 = search.receiver.axes[:2]
    for _ in range(CENTRING_PASSES):
        if search.interferometer.read().beam_ok:
            break
        azimuth_rad = _across_azimuth(aperture_rad, launch_elevation_rad)
        for axis, half_width in ((a1, azimuth_rad), (a2, aperture_rad)):
            _centre(search, axis, half_width)
        receiver_elevation_rad = float(search.receiver.angles_rad()[1])
        receiver_azimuth_rad = _across_azimuth(capture_angle_rad, receiver_elevation_rad)
        for axis, half_width in ((a3, receiver_azimuth_rad), (a4, capture_angle_rad)):
            _centre(search, axis, half_width)
    logger.info("beam found and centred after %d sweep(s)", search.sweeps)
    return BeamSearchResult(
        launch_rad=search.launch.angles_rad(),
        receiver_rad=search.receiver.angles_rad(),
        elapsed_s=search.clock.now() - search.started_s,
        sweeps=search.sweeps,
    )
