"""The identification routine: align the units at several machine positions and record them.

For each identification position the routine moves the machine (a
``MachineMover``: the simulated CNC, or an operator prompt that asks for the
move and the displayed position), coarse-points the units at the angles
predicted from a pose guess, fine-aligns them on the interferometer, locks
them, reads the encoders and appends the alignment to the session file at
once. Started again with the same session file it resumes after the last
recorded position. With no one at the machine the first alignment searches the
beam (:mod:`xmalign.beam_search`), and until a quick identification can point, the
next ones are pointed from the recorded beam lines, searching along the line they
leave open where that misses. Solving the session is
:func:`xmalign.identify.identify`'s job. Only roles are used here (core code).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike

from xmalign.alignment import FineAlignmentResult, FineAlignmentSettings, fine_align
from xmalign.beam_search import (
    BeamSearchSettings,
    capture_reach_mm,
    search_along,
    search_first_beam,
)
from xmalign.errors import BeamLostError, GeometryError, InputError, OutOfRangeError
from xmalign.formats.session import Alignment, Session, read_session, write_session
from xmalign.geometry import Vec, azimuth_elevation, circular_mean, wrap_angle
from xmalign.kinematics import EncoderOffsets, aligned_angles, receiver_axis, receiver_cp
from xmalign.machine import Machine
from xmalign.roles import Clock, Interferometer, MachineMover, PositioningUnit, move_axes
from xmalign.safety import units_locked_on_exit

logger = logging.getLogger(__name__)

#: A recorded alignment this close to a position (CNC or operator readout) counts as done, mm.
SAME_POSITION_MM = 0.5
#: Distance assumed by the first fine alignment when no pose guess gives one, mm.
DEFAULT_DISTANCE_MM = 1000.0
#: How weakly the rough place holds the launch place where the beam lines leave it open
#: (:func:`launch_place_from_alignments`; against 1 per line), 1.
ROUGH_PLACE_WEIGHT = 1e-6


@dataclass(frozen=True)
class PoseGuess:
    """What is known of the launch pose before identification.

    ``gamma_rad`` may be unknown (None): the machine file only guesses the
    position; the routine then estimates gamma from the first alignment.
    ``offsets`` and ``receiver_roll_rad`` (reported a5 angle of zero roll)
    are learnt from the recorded alignments as they come in.
    """

    launch2mcs_mm: Vec
    gamma_rad: float | None = None
    offsets: EncoderOffsets = field(default_factory=EncoderOffsets)
    receiver_roll_rad: float = 0.0


Stage = Literal["skipped", "moving", "pointing", "searching", "manual", "aligning", "recorded"]


@dataclass(frozen=True)
class RoutineEvent:
    """Progress of the routine: position ``index`` of ``total`` reached ``stage``
    (``searching``: once per turn of the first alignment's search)."""

    index: int
    total: int
    stage: Stage
    machine_mm: Vec


@dataclass
class RoutineDevices:
    """The roles the routine drives."""

    mover: MachineMover
    launch: PositioningUnit
    receiver: PositioningUnit
    interferometer: Interferometer
    clock: Clock


def open_session(path: Path, machine: Machine) -> Session:
    """The session recorded so far in ``path``, or a new empty one for the machine.

    Raises InputError when an existing file was taken with another receiver
    offset or spindle angle (its alignments would not fit this setup).
    """
    if not path.exists():
        return Session(
            receiver_offset_mm=machine.receiver_offset.copy(),
            spindle_angle_rad=machine.spindle_angle_rad,
        )
    session = read_session(path)
    if not np.allclose(session.receiver_offset_mm, machine.receiver_offset, atol=1e-6):
        raise InputError(
            f"{path}: key 'receiver_offset_mm' {list(session.receiver_offset_mm)} differs from the"
            f" machine file's {machine.receiver_offset_mm}; start a new session file"
        )
    if not math.isclose(session.spindle_angle_rad, machine.spindle_angle_rad, abs_tol=1e-9):
        raise InputError(
            f"{path}: key 'spindle_angle_deg' differs from the machine file's"
            f" {machine.spindle_angle_deg}; start a new session file"
        )
    return session


def is_recorded(session: Session, machine_mm: Vec) -> bool:
    """Whether the session already holds an alignment at this machine position."""
    return any(
        np.linalg.norm(a.machine_mm - machine_mm) <= SAME_POSITION_MM for a in session.alignments
    )


def gamma_from_alignments(launch2mcs_mm: Vec, session: Session) -> float:
    """Launch azimuth from recorded alignments and a launch position (circular mean), rad."""
    gammas = []
    for a in session.alignments:
        cp = receiver_cp(a.machine_mm, session.receiver_offset_mm, session.spindle_angle_rad)
        azimuth, _ = azimuth_elevation(cp - launch2mcs_mm)
        gammas.append(float(azimuth) - a.launch_rad[0])
    return circular_mean(gammas)


def _pointing_bias(
    guess: PoseGuess, gamma_rad: float, session: Session
) -> tuple[EncoderOffsets, float]:
    """Encoder offsets and receiver roll that the recorded alignments show for this guess.

    The angles the guess predicts at each recorded position minus the angles
    recorded there (mean): the zero offsets plus whatever the guess gets wrong
    nearby, so that coarse pointing at the next position lands in range.
    """
    biases = []
    for a in session.alignments:
        cp = receiver_cp(a.machine_mm, session.receiver_offset_mm, session.spindle_angle_rad)
        predicted = aligned_angles(guess.launch2mcs_mm, gamma_rad, cp, session.spindle_angle_rad)
        biases.append(
            [
                predicted.launch_rad[1] - a.launch_rad[1],
                float(wrap_angle(predicted.receiver_rad[0] - a.receiver_rad[0])),
                predicted.receiver_rad[1] - a.receiver_rad[1],
            ]
        )
    c2, c3, c4 = np.mean(biases, axis=0)
    roll = float(np.mean([a.receiver_rad[2] for a in session.alignments]))
    return EncoderOffsets(float(c2), float(c3), float(c4)), roll


def launch_place_from_alignments(rough_mm: Vec, session: Session) -> tuple[Vec, Vec]:
    """Where the recorded alignments put the launch unit, and the direction they leave open.

    Each alignment puts the launch unit on the beam's line through the receiver cp,
    along the receiver's reported axis (a3, a4 and the spindle angle; their zero
    offsets, tens of microradians, neglected). The place is the point nearest all
    the lines (least squares), held weakly at the rough place where they leave it
    open: one alignment moves the rough place onto its line, two lines that cross
    give their crossing.

    Parameters
    ----------
    rough_mm : ndarray, shape (3,)
        The machine file's place of the launch unit, MCS mm.
    session : Session
        At least one recorded alignment.

    Returns
    -------
    place_mm : ndarray, shape (3,)
        MCS mm.
    open_direction : ndarray, shape (3,)
        Unit vector along which the lines fix the place least (the line itself
        after one alignment).
    """
    normal, rhs = np.zeros((3, 3)), np.zeros(3)
    for a in session.alignments:
        cp = receiver_cp(a.machine_mm, session.receiver_offset_mm, session.spindle_angle_rad)
        axis = receiver_axis(session.spindle_angle_rad, a.receiver_rad[0], a.receiver_rad[1])
        across = np.eye(3) - np.outer(axis, axis)
        normal, rhs = normal + across, rhs + across @ cp
    held = normal + ROUGH_PLACE_WEIGHT * np.eye(3)
    pulled = rhs + ROUGH_PLACE_WEIGHT * np.asarray(rough_mm, dtype=float)
    place = np.asarray(np.linalg.solve(held, pulled), dtype=float)
    open_direction: Vec = np.linalg.eigh(normal)[1][:, 0]
    return place, open_direction


def _guess_at(guess: PoseGuess, place_mm: Vec, session: Session) -> PoseGuess:
    """The guess with the launch unit at ``place_mm`` and the azimuth the recorded
    alignments give from there, with the offsets and roll they show."""
    gamma_rad = gamma_from_alignments(place_mm, session)
    guess = replace(guess, launch2mcs_mm=place_mm, gamma_rad=gamma_rad)
    offsets, roll = _pointing_bias(guess, gamma_rad, session)
    return replace(guess, offsets=offsets, receiver_roll_rad=roll)


def _usable_guess(guess: PoseGuess | None, session: Session, onto_lines: bool) -> PoseGuess | None:
    """The guess completed from the recorded alignments (azimuth, offsets, roll), if
    usable; ``onto_lines``: its place first moved to :func:`launch_place_from_alignments`
    (a coarse guess with no one at the machine: the rough place may be centimetres off,
    the lines hold to tenths of a millimetre; with an operator the guess stays, the jog
    corrects it)."""
    if guess is None or not session.alignments:
        return guess if guess is not None and guess.gamma_rad is not None else None
    if onto_lines:
        place_mm, _ = launch_place_from_alignments(guess.launch2mcs_mm, session)
        return _guess_at(guess, place_mm, session)
    if guess.gamma_rad is None:
        return _guess_at(guess, guess.launch2mcs_mm, session)
    offsets, roll = _pointing_bias(guess, guess.gamma_rad, session)
    return replace(guess, offsets=offsets, receiver_roll_rad=roll)


def _pointing(guess: PoseGuess, cp_mm: Vec, session: Session, n_axes: int) -> tuple[Vec, float]:
    """The launch and receiver angles the guess predicts, shape (``n_axes``,) rad, and the
    predicted distance, mm."""
    assert guess.gamma_rad is not None, "_usable_guess completes gamma before any pointing"
    predicted = aligned_angles(
        guess.launch2mcs_mm, guess.gamma_rad, cp_mm, session.spindle_angle_rad, guess.offsets
    )
    receiver_target = np.array([*predicted.receiver_rad[:2], guess.receiver_roll_rad])
    targets = np.concatenate([predicted.launch_rad, receiver_target])[:n_axes]
    return targets, predicted.distance_mm


def _point_units(
    guess: PoseGuess, cp_mm: Vec, session: Session, devices: RoutineDevices, timeout_s: float
) -> float:
    """Move both units at once to the angles predicted by the guess (``timeout_s`` for all
    axes together); returns the predicted distance."""
    axes = [*devices.launch.axes, *devices.receiver.axes]
    targets, distance_mm = _pointing(guess, cp_mm, session, len(axes))
    move_axes(axes, targets, timeout_s, "positioning units", devices.clock)
    return distance_mm


def _offsets_along(
    place_mm: Vec, open_direction: Vec, cp_mm: Vec, machine: Machine, reach_mm: float
) -> Vec:
    """Offsets of the launch unit's place along ``open_direction`` out to ``reach_mm``
    either side, nearest first, shape (N,), mm: close enough that from the nearest the
    beam lands on the receiver and the receiver faces the true place, each within
    its capture (:func:`~xmalign.beam_search.capture_reach_mm`)."""
    line = cp_mm - place_mm
    distance_mm = float(np.linalg.norm(line))
    across = float(np.linalg.norm(np.cross(open_direction, line / distance_mm)))
    nearest_mm = max(distance_mm - reach_mm, 1.0)
    miss_mm = min(capture_reach_mm(machine.interferometer, nearest_mm))
    spacing_mm = min(2.0 * miss_mm / max(across, 1e-3), reach_mm)
    count = math.ceil(reach_mm / spacing_mm)
    steps = np.array(sorted(range(-count, count + 1), key=lambda k: (abs(k), k)), dtype=float)
    return steps * spacing_mm


def _search_place(
    guess: PoseGuess,
    cp_mm: Vec,
    session: Session,
    machine: Machine,
    devices: RoutineDevices,
    settings: BeamSearchSettings,
) -> float | None:
    """Pointing from the recorded alignments missed: point again from other places of the
    launch unit along the direction they leave open (each with the azimuth they give
    from there), nearest first, out to the rough place's uncertainty
    (:func:`~xmalign.beam_search.search_along`); the distance to the place where the
    beam was found and centred, or None (the units back at the first pointing)."""
    place_mm, open_direction = launch_place_from_alignments(guess.launch2mcs_mm, session)
    reach_mm = settings.position_uncertainty_mm * math.sqrt(3.0)
    offsets_mm = _offsets_along(place_mm, open_direction, cp_mm, machine, reach_mm)
    n_axes = len(devices.launch.axes) + len(devices.receiver.axes)

    def pointing(offset_mm: float) -> Vec:
        place = place_mm + offset_mm * open_direction
        return _pointing(_guess_at(guess, place, session), cp_mm, session, n_axes)[0]

    logger.info(
        "the beam missed: pointing again from up to %d places of the launch unit along the"
        " line the recorded alignments leave open",
        len(offsets_mm),
    )
    distance_mm = float(np.linalg.norm(cp_mm - place_mm))
    found_mm = search_along(
        devices.launch,
        devices.receiver,
        devices.interferometer,
        devices.clock,
        pointing,
        offsets_mm,
        distance_mm,
        machine.interferometer,
        settings,
    )
    if found_mm is None:
        return None
    return float(np.linalg.norm(cp_mm - place_mm - found_mm * open_direction))


def _pointed(
    usable: PoseGuess,
    coarse: PoseGuess | None,
    cp_mm: Vec,
    session: Session,
    machine: Machine,
    devices: RoutineDevices,
    timeout_s: float,
    search: BeamSearchSettings | None,
) -> float:
    """Point the units from ``usable`` (:func:`_point_units`); the distance. Where that
    comes from a ``coarse`` guess moved onto the recorded beam lines, which may leave the
    place open, and misses with no one there (``search``), point again from along them
    (:func:`_search_place`)."""
    distance_mm = _point_units(usable, cp_mm, session, devices, timeout_s)
    if coarse is None or search is None or not session.alignments:
        return distance_mm
    if devices.interferometer.read().beam_ok:
        return distance_mm
    found_mm = _search_place(coarse, cp_mm, session, machine, devices, search)
    return distance_mm if found_mm is None else found_mm


def _search(
    guess: PoseGuess,
    cp_mm: Vec,
    machine: Machine,
    devices: RoutineDevices,
    settings: BeamSearchSettings,
    on_sweep: Callable[[], None],
) -> float:
    """The first alignment with the launch azimuth unknown: find the beam from the launch
    unit's rough place (:func:`~xmalign.beam_search.search_first_beam`); returns the
    distance to the rough place, mm."""
    search_first_beam(
        devices.launch,
        devices.receiver,
        devices.interferometer,
        devices.clock,
        guess.launch2mcs_mm,
        cp_mm,
        machine.spindle_angle_rad,
        machine.interferometer,
        settings,
        guess.receiver_roll_rad,
        lambda _: on_sweep(),
    )
    return float(np.linalg.norm(cp_mm - guess.launch2mcs_mm))


def _record(session: Session, machine_mm: Vec, devices: RoutineDevices, residual_um: Vec) -> None:
    devices.launch.lock()
    devices.receiver.lock()
    receiver = devices.receiver.angles_rad()
    session.alignments.append(
        Alignment(
            machine_mm=machine_mm,
            launch_rad=devices.launch.angles_rad(),
            receiver_rad=np.concatenate([receiver, np.zeros(3 - len(receiver))]),
            straightness_um=residual_um,
        )
    )


def _align(
    devices: RoutineDevices,
    distance_mm: float,
    settings: FineAlignmentSettings | None,
    manual_align: Callable[[], None] | None,
    on_manual: Callable[[Vec], None],
) -> FineAlignmentResult:
    """Fine alignment (which finds a lost beam itself); a person only if its search fails."""

    def align() -> FineAlignmentResult:
        return fine_align(
            devices.launch,
            devices.receiver,
            devices.interferometer,
            devices.clock,
            distance_mm,
            settings,
        )

    try:
        return align()
    except BeamLostError:
        if manual_align is None:
            raise
        logger.warning("fine alignment could not find the beam; asking the operator")
    on_manual(np.asarray(devices.mover.position_mm(), dtype=float))
    manual_align()
    return align()


def run_identification(
    positions_mm: ArrayLike,
    machine: Machine,
    devices: RoutineDevices,
    session_path: str | Path,
    guess: PoseGuess | None = None,
    settings: FineAlignmentSettings | None = None,
    manual_align: Callable[[], None] | None = None,
    refine_guess: Callable[[Session], PoseGuess | None] | None = None,
    on_event: Callable[[RoutineEvent], None] | None = None,
    unit_timeout_s: float = 30.0,
    search: BeamSearchSettings | None = None,
) -> Session:
    """Align the units at each position and record every alignment as it is taken.

    Parameters
    ----------
    positions_mm : array_like, shape (N, 3)
        CNC tool points to align at, in order.
    machine : Machine
        Travel, feeds, receiver offset and spindle angle.
    devices : RoutineDevices
        Machine mover, launch and receiver units, interferometer and clock.
    session_path : str or Path
        Session file; written after every alignment, resumed from if it exists.
    guess : PoseGuess, optional
        Prior launch pose for coarse pointing (e.g. the machine file's ``launch_unit``).
        With its position but no azimuth and ``search`` given, the first alignment
        searches the beam itself (:func:`~xmalign.beam_search.search_first_beam`);
        no one is asked.
    settings : FineAlignmentSettings, optional
    manual_align : callable, optional
        Lets the operator jog the units into range; used where no guess can point
        them (no launch position at all), where the coarse guess misses, and where
        fine alignment's own beam search (back to the last in-range angles, then a
        spiral) does not find the beam.
    refine_guess : callable, optional
        Given the session so far, a better guess (e.g. a quick identification).
    on_event : callable, optional
        Progress callback.
    unit_timeout_s : float
        Timeout of each coarse unit move.
    search : BeamSearchSettings, optional
        Bounds of the first alignment's search; None: no search (an operator aligns
        the first position, ``manual_align``). Given, no one is assumed at the
        machine: after the first alignment the units are pointed from the recorded
        beam lines (:func:`launch_place_from_alignments`) until a refined guess
        exists, and where such a pointing misses, from places along the line they
        leave open; ``manual_align`` only when fine alignment then fails.

    Returns
    -------
    Session
        All alignments, the earlier recorded ones first.

    Raises
    ------
    OutOfRangeError
        A position outside the machine's travel (checked before anything moves).
    GeometryError
        Neither a guess nor an operator can point the units.
    BeamLostError, DeviceTimeoutError
        The first alignment's search did not find the beam (the message says what
        to check).
    """
    positions = np.atleast_2d(np.asarray(positions_mm, dtype=float))
    outside = np.flatnonzero(~machine.within_travel(positions))
    if outside.size:
        raise OutOfRangeError(
            f"identification position {outside[0] + 1} {positions[outside[0]].tolist()} mm is"
            " outside the machine's travel"
        )
    path = Path(session_path)
    session = open_session(path, machine)
    distance_mm = DEFAULT_DISTANCE_MM
    # resumed: the recorded alignments refine the guess as they did before the stop
    better = refine_guess(session) if refine_guess is not None and session.alignments else None
    guess, refined = (better, True) if better is not None else (guess, False)
    with units_locked_on_exit(devices.launch, devices.receiver):
        for index, target in enumerate(positions, start=1):

            def event(stage: Stage, where: Vec, index: int = index) -> None:
                if on_event is not None:
                    on_event(RoutineEvent(index, len(positions), stage, where))

            if is_recorded(session, target):
                event("skipped", target)
                continue
            event("moving", target)
            devices.mover.move_to(target, machine.feed_mm_min.rapid)
            machine_mm = np.asarray(devices.mover.position_mm(), dtype=float)
            cp_mm = receiver_cp(machine_mm, session.receiver_offset_mm, session.spindle_angle_rad)
            usable = _usable_guess(guess, session, search is not None and not refined)
            searched = usable is None and guess is not None and search is not None
            if usable is not None:
                event("pointing", machine_mm)
                coarse = None if refined else guess
                distance_mm = _pointed(
                    usable, coarse, cp_mm, session, machine, devices, unit_timeout_s, search
                )
            elif searched:
                assert guess is not None and search is not None  # see searched
                distance_mm = _search(
                    guess, cp_mm, machine, devices, search, partial(event, "searching", machine_mm)
                )
            # Pointed from the coarse guess alone, a beam out of range may be centimetres
            # off: beyond fine alignment's search, so a person aligns. From a refined guess,
            # or with no one there (``search`` given), fine alignment searches.
            coarse_miss = (
                usable is not None
                and not refined
                and search is None
                and manual_align is not None
                and not devices.interferometer.read().beam_ok
            )
            if (usable is None and not searched) or coarse_miss:
                if manual_align is None:
                    raise GeometryError(
                        f"cannot point the units at identification position {index}: no pose"
                        " guess and no operator to align them (give launch_unit in the machine"
                        " file or align manually)"
                    )
                event("manual", machine_mm)
                manual_align()
            event("aligning", machine_mm)
            result = _align(devices, distance_mm, settings, manual_align, partial(event, "manual"))
            distance_mm = result.distance_mm
            _record(session, machine_mm, devices, result.straightness_um)
            write_session(path, session)
            event("recorded", machine_mm)
            better = refine_guess(session) if refine_guess is not None else None
            if better is not None:
                guess, refined = better, True
    return session
