"""The identification routine: align the units at several machine positions and record them.

For each identification position the routine moves the machine (a
``MachineMover``: the simulated CNC, or an operator prompt that asks for the
move and the displayed position), coarse-points the units at the angles
predicted from a pose guess, fine-aligns them on the interferometer, locks
them, reads the encoders and appends the alignment to the session file at
once. Started again with the same session file it resumes after the last
recorded position. Solving the session is :func:`xmalign.identify.identify`'s
job. Only roles are used here (core code).
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
from xmalign.beam_search import BeamSearchSettings, search_first_beam
from xmalign.errors import BeamLostError, GeometryError, InputError, OutOfRangeError
from xmalign.formats.session import Alignment, Session, read_session, write_session
from xmalign.geometry import Vec, azimuth_elevation, circular_mean, wrap_angle
from xmalign.kinematics import EncoderOffsets, aligned_angles, receiver_cp
from xmalign.machine import Machine
from xmalign.roles import Clock, Interferometer, MachineMover, PositioningUnit, move_axes
from xmalign.safety import units_locked_on_exit

logger = logging.getLogger(__name__)

#: A recorded alignment this close to a position (CNC or operator readout) counts as done, mm.
SAME_POSITION_MM = 0.5
#: Distance assumed by the first fine alignment when no pose guess gives one, mm.
DEFAULT_DISTANCE_MM = 1000.0


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


def _usable_guess(guess: PoseGuess | None, session: Session) -> PoseGuess | None:
    """The guess completed from the recorded alignments (gamma, offsets, roll), if usable."""
    if guess is None or (guess.gamma_rad is None and not session.alignments):
        return guess if guess is None or guess.gamma_rad is not None else None
    gamma_rad = guess.gamma_rad
    if gamma_rad is None:
        gamma_rad = gamma_from_alignments(guess.launch2mcs_mm, session)
        guess = replace(guess, gamma_rad=gamma_rad)
    if not session.alignments:
        return guess
    offsets, roll = _pointing_bias(guess, gamma_rad, session)
    return replace(guess, offsets=offsets, receiver_roll_rad=roll)


def _point_units(
    guess: PoseGuess, cp_mm: Vec, session: Session, devices: RoutineDevices, timeout_s: float
) -> float:
    """Move both units at once to the angles predicted by the guess (``timeout_s`` for all
    axes together); returns the predicted distance."""
    assert guess.gamma_rad is not None, "_usable_guess completes gamma before any pointing"
    predicted = aligned_angles(
        guess.launch2mcs_mm, guess.gamma_rad, cp_mm, session.spindle_angle_rad, guess.offsets
    )
    receiver_target = np.array([*predicted.receiver_rad[:2], guess.receiver_roll_rad])
    axes = [*devices.launch.axes, *devices.receiver.axes]
    targets = np.concatenate([predicted.launch_rad, receiver_target])[: len(axes)]
    move_axes(axes, targets, timeout_s, "positioning units", devices.clock)
    return predicted.distance_mm


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
        the first position, ``manual_align``).

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
    refined = False
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
            usable = _usable_guess(guess, session)
            searched = usable is None and guess is not None and search is not None
            if usable is not None:
                event("pointing", machine_mm)
                distance_mm = _point_units(usable, cp_mm, session, devices, unit_timeout_s)
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
