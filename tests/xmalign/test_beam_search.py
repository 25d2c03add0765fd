"""The first alignment by itself (xmalign.beam_search): the launch azimuth unknown, full circle.

The simulated interferometer's signal strength is seen only while the launch unit's
azimuth and elevation put the beam on the receiver's aperture and the receiver faces
it (sim/interferometer.py); nothing in the search knows the true azimuth. One test runs
over the real protocols (Modbus TCP units, the interferometer's serial line on a pty)
as ``xmalign dry-run`` serves them, on the served world's virtual clock.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from sim.alignment_setup import point_by_truth
from sim.clock import LockstepClock
from sim.cnc import SimulatedCnc
from sim.dry_run import virtual_setup
from sim.units import SimPositioningUnit
from sim.world import FixedPosition, World, build_world
from xmalign.alignment import fine_align
from xmalign.beam_search import WHAT_TO_CHECK, BeamSearchSettings, search_first_beam
from xmalign.errors import BeamLostError, DeviceTimeoutError
from xmalign.formats.session import Alignment, Session, read_session
from xmalign.identification_routine import (
    PoseGuess,
    RoutineDevices,
    RoutineEvent,
    gamma_from_alignments,
    launch_place_from_alignments,
    run_identification,
)
from xmalign.identify import identify
from xmalign.kinematics import aligned_angles, receiver_cp
from xmalign.machine import Machine, load_machine
from xmalign.steps import design_step, refine_guess

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
#: The launch unit stands where the machine file says within this, per axis (tests).
NEAR_MM = 2.0


@pytest.fixture(scope="module")
def machine() -> Machine:
    return load_machine(EXAMPLES / "fyxz.yaml")


def _world(machine: Machine, seed: int, offset_mm: np.ndarray, clock=None) -> World:
    """A world whose launch unit stands ``offset_mm`` from the machine file's place, with a
    random azimuth over the full circle (the search's unknown)."""
    rng = np.random.default_rng(seed)
    assert machine.launch_unit is not None
    place = np.asarray(machine.launch_unit.position_mm, dtype=float) + offset_mm
    placed = machine.model_copy(
        update={"launch_unit": machine.launch_unit.model_copy(update={"position_mm": list(place)})}
    )
    position = FixedPosition(design_step(machine, 6).machine_mm[0])
    gamma_rad = float(rng.uniform(-math.pi, math.pi))
    return build_world(placed, position, seed=seed, gamma_rad=gamma_rad, clock=clock)


def _search(world: World, machine: Machine, launch, receiver, interferometer, clock, **settings):
    assert machine.launch_unit is not None
    cp = receiver_cp(
        world.interferometer.position.position_mm(),
        machine.receiver_offset,
        machine.spindle_angle_rad,
    )
    return search_first_beam(
        launch,
        receiver,
        interferometer,
        clock,
        np.asarray(machine.launch_unit.position_mm, dtype=float),
        cp,
        machine.spindle_angle_rad,
        machine.interferometer,
        BeamSearchSettings(**settings),
    )


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_finds_the_beam_from_an_unknown_azimuth(machine: Machine, seed: int) -> None:
    """The launch unit 2 mm off its place in the machine file, its azimuth anywhere: the
    search leaves the beam in range (or nearly: fine alignment converges from there)."""
    offset = np.random.default_rng(seed).uniform(-NEAR_MM, NEAR_MM, 3)
    world = _world(machine, seed, offset)
    launch, receiver = SimPositioningUnit(world.launch), SimPositioningUnit(world.receiver)
    assert not world.interferometer.read().sees_beam(1.0)
    result = _search(
        world, machine, launch, receiver, world.interferometer, world.clock,
        position_uncertainty_mm=NEAR_MM,
    )  # fmt: skip
    reading = world.interferometer.read()
    assert reading.signal_pct is not None and reading.signal_pct > 90.0
    assert result.sweeps <= 3 and result.elapsed_s < 3 * 15.0 + 30.0
    distance = float(np.linalg.norm(world.launch2mcs_mm - machine.launch_unit.position_mm)) + 1900
    aligned = fine_align(launch, receiver, world.interferometer, world.clock, distance)
    assert aligned.reading.beam_ok


def test_rows_and_receiver_aims_cover_a_rough_place(machine: Machine) -> None:
    """The launch unit 20 mm off in every axis (within the default 25 mm): found on a
    row above or below the first."""
    world = _world(machine, 5, np.array([20.0, -20.0, 20.0]))
    launch, receiver = SimPositioningUnit(world.launch), SimPositioningUnit(world.receiver)
    result = _search(world, machine, launch, receiver, world.interferometer, world.clock)
    assert result.sweeps > 1
    assert world.interferometer.read().signal_pct > 90.0


def test_a_blocked_beam_ends_in_one_line_saying_what_to_check(machine: Machine) -> None:
    world = _world(machine, 3, np.zeros(3))
    world.interferometer.interrupt(1e9)
    launch, receiver = SimPositioningUnit(world.launch), SimPositioningUnit(world.receiver)
    started_s = world.clock.now()
    with pytest.raises(BeamLostError) as error:
        _search(
            world, machine, launch, receiver, world.interferometer, world.clock,
            position_uncertainty_mm=NEAR_MM,
        )  # fmt: skip
    message = str(error.value)
    assert "\n" not in message and message.startswith("no beam found")
    assert WHAT_TO_CHECK in message and "beam shutter" in message
    assert world.clock.now() - started_s < 60.0  # one row: one turn of a1 and the moves


def test_the_search_is_bounded_in_time(machine: Machine) -> None:
    world = _world(machine, 4, np.zeros(3))
    world.interferometer.interrupt(1e9)
    launch, receiver = SimPositioningUnit(world.launch), SimPositioningUnit(world.receiver)
    started_s = world.clock.now()
    with pytest.raises(DeviceTimeoutError, match="no beam found within 5 s") as error:
        _search(world, machine, launch, receiver, world.interferometer, world.clock, timeout_s=5.0)
    assert WHAT_TO_CHECK in str(error.value)
    assert world.clock.now() - started_s < 5.0 + 2 * 15.0  # at most the turn back to the start


def test_the_routine_needs_no_one_for_the_first_alignment(machine: Machine, tmp_path) -> None:
    """No azimuth in the machine file, no operator: the routine searches, then points the
    next positions from the first alignment."""
    world = _world(machine, 21, np.zeros(3))
    cnc = SimulatedCnc(machine, world.clock, world.interferometer.position.position_mm())
    world.interferometer.position = cnc
    launch, receiver = SimPositioningUnit(world.launch), SimPositioningUnit(world.receiver)
    devices = RoutineDevices(cnc, launch, receiver, world.interferometer, world.clock)
    stages: list[str] = []
    assert machine.launch_unit is not None
    session = run_identification(
        design_step(machine, 6).machine_mm[:3],
        machine,
        devices,
        tmp_path / "session.json",
        guess=PoseGuess(np.asarray(machine.launch_unit.position_mm, dtype=float)),
        on_event=lambda event: stages.append(event.stage),
        search=BeamSearchSettings(position_uncertainty_mm=NEAR_MM),
    )
    assert len(session.alignments) == 3
    assert stages.count("searching") >= 1 and "manual" not in stages


def test_the_receiver_sees_the_beam_only_on_its_aperture_and_facing_it(machine: Machine) -> None:
    """What the search relies on in the simulated interferometer: the signal needs the
    beam within the capture radius of the receiver's centre and the receiver facing it
    within the capture angle; the channels' ranges are much narrower."""
    world = _world(machine, 41, np.zeros(3))
    launch, receiver = SimPositioningUnit(world.launch), SimPositioningUnit(world.receiver)
    point_by_truth(world, machine, launch, receiver)
    aligned = np.concatenate([launch.angles_rad(), receiver.angles_rad()])
    distance_mm = world.interferometer.geometry().distance_mm
    ranges = machine.interferometer
    aperture_rad = ranges.capture_radius_mm / distance_mm
    elevation = math.cos(aligned[1])

    def signal(offset_rad: np.ndarray) -> float:
        target = aligned + offset_rad
        launch.move_to(target[:2], 30.0)
        receiver.move_to(target[2:], 30.0)
        return world.interferometer.geometry().signal_pct

    assert signal(np.zeros(5)) > 99.0 and world.interferometer.geometry().beam_ok
    # the beam half the capture radius off: seen, but far out of the measuring range
    assert 50.0 < signal(np.array([0.5 * aperture_rad / elevation, 0, 0, 0, 0])) < 90.0
    assert not world.interferometer.geometry().beam_ok
    assert signal(np.array([1.1 * aperture_rad / elevation, 0, 0, 0, 0])) == 0.0
    assert signal(np.array([0, 1.1 * aperture_rad, 0, 0, 0])) == 0.0
    # the launch on target, the receiver facing away by more than its capture angle
    facing = ranges.capture_angle_mrad * 1e-3
    assert signal(np.array([0, 0, 0, 0.5 * facing, 0])) > 50.0
    assert signal(np.array([0, 0, 0, 1.1 * facing, 0])) == 0.0
    assert signal(np.array([0, 0, 1.1 * facing / math.cos(aligned[3]), 0, 0])) == 0.0


class _SlowHost:
    """The world's clock, but every wait of the host lasts 30 ms longer (a computer busy
    with other work): a1 turns some 16 mrad between two readings, farther than the
    beam's width at the receiver (some 6 mrad), so most of the turn is made up at rest."""

    def __init__(self, clock) -> None:
        self.clock = clock

    def now(self) -> float:
        return self.clock.now()

    def sleep(self, seconds: float) -> None:
        self.clock.sleep(seconds + 0.03)

    def await_stream(self) -> None:
        self.clock.await_stream()


def test_readings_that_come_late_are_made_up_at_rest(machine: Machine) -> None:
    world = _world(machine, 12, np.zeros(3))
    launch, receiver = SimPositioningUnit(world.launch), SimPositioningUnit(world.receiver)
    slow = _SlowHost(world.clock)
    result = _search(
        world, machine, launch, receiver, world.interferometer, slow,
        position_uncertainty_mm=NEAR_MM,
    )  # fmt: skip
    assert world.interferometer.read().signal_pct > 90.0
    assert result.sweeps <= 2


@pytest.mark.parametrize("seed", [31, 32])
def test_over_the_served_protocols(machine: Machine, seed: int) -> None:
    """The units over Modbus TCP and the interferometer's serial line (its S lines carry
    the signal strength), served as the dry run serves them, on its virtual clock."""
    from firmware_iface.config import open_devices
    from sim.servers.served_world import serve_world_with_linuxcnc

    world = _world(machine, seed, np.array([1.0, -1.5, 0.5]), clock=LockstepClock())
    cnc = SimulatedCnc(machine, world.clock, world.interferometer.position.position_mm())
    world.interferometer.position = cnc
    with (
        serve_world_with_linuxcnc(world, machine, cnc) as served,
        open_devices(served.config, machine, clock=served.clock) as devices,
    ):
        result = _search(
            world, machine, devices.launch, devices.receiver, devices.interferometer,
            served.clock, position_uncertainty_mm=NEAR_MM,
        )  # fmt: skip
        reading = devices.interferometer.read()
    assert reading.signal_pct is not None and reading.signal_pct > 90.0
    assert result.sweeps <= 3


def _session_at(machine: Machine, place_mm: np.ndarray, gamma_rad: float, count: int) -> Session:
    """A session of ``count`` exact alignments at the 3-alignment design's positions for a
    launch unit at ``place_mm`` with azimuth ``gamma_rad`` (no offsets)."""
    session = Session(machine.receiver_offset, machine.spindle_angle_rad)
    for position in design_step(machine, 3).machine_mm[:count]:
        cp = receiver_cp(position, machine.receiver_offset, machine.spindle_angle_rad)
        aligned = aligned_angles(place_mm, gamma_rad, cp, machine.spindle_angle_rad)
        session.alignments.append(
            Alignment(
                position, aligned.launch_rad, aligned.receiver_rad, straightness_um=np.zeros(2)
            )
        )
    return session


def test_one_alignment_puts_the_launch_unit_on_its_beam_line_two_fix_it(machine: Machine) -> None:
    """One alignment: the rough place moves onto the beam's line (the receiver's axis
    through its cp), what is left open is along that line, and the azimuth from there is
    the true one; two alignments at positions seen in other directions: the true place."""
    assert machine.launch_unit is not None
    rough = np.asarray(machine.launch_unit.position_mm, dtype=float)
    true_mm, gamma_rad = rough + np.array([-20.7, -13.2, 15.1]), 0.7
    one = _session_at(machine, true_mm, gamma_rad, 1)
    place, open_direction = launch_place_from_alignments(rough, one)
    line = true_mm - receiver_cp(one.alignments[0].machine_mm, machine.receiver_offset, 0.0)
    line /= np.linalg.norm(line)
    assert np.linalg.norm(np.cross(place - true_mm, line)) < 1e-3  # on the line
    assert abs(np.dot(place - rough, line)) < 1e-3  # the rough place moved across it only
    assert abs(abs(np.dot(open_direction, line)) - 1.0) < 1e-9
    assert abs(gamma_from_alignments(place, one) - gamma_rad) < 1e-6
    place, _ = launch_place_from_alignments(rough, _session_at(machine, true_mm, gamma_rad, 2))
    assert np.linalg.norm(place - true_mm) < 1e-3


class _InterruptedError(Exception):
    """Ctrl-C at the routine's second move (the session then holds one alignment)."""


def _seed3_routine(machine: Machine) -> tuple[World, RoutineDevices]:
    """The dry run's seed-3 setup (launch unit 28 mm off the machine file's place) with a
    simulated CNC, in-process."""
    world = virtual_setup(machine, 3).world
    cnc = SimulatedCnc(machine, world.clock, world.interferometer.position.position_mm())
    world.interferometer.position = cnc
    launch, receiver = SimPositioningUnit(world.launch), SimPositioningUnit(world.receiver)
    return world, RoutineDevices(cnc, launch, receiver, world.interferometer, world.clock)


def test_the_jog_is_the_last_resort_after_the_search_along_the_line(
    machine: Machine, tmp_path
) -> None:
    """One alignment recorded, then the beam blocked: the pointing from the beam line and
    the search along it find nothing, fine alignment neither; only then the operator is
    asked (once), and a beam still blocked ends in the one-line error."""
    world, devices = _seed3_routine(machine)
    positions = design_step(machine, 3).machine_mm
    assert machine.launch_unit is not None
    guess = PoseGuess(np.asarray(machine.launch_unit.position_mm, dtype=float))
    path, jogs, stages = tmp_path / "session.json", [], []

    def run(where: np.ndarray) -> Session:
        return run_identification(
            where, machine, devices, path, guess, manual_align=lambda: jogs.append(1),
            on_event=lambda e: stages.append(e.stage), search=BeamSearchSettings(),
        )  # fmt: skip

    run(positions[1:2])
    world.interferometer.interrupt(1e9)
    with pytest.raises(BeamLostError):
        run(positions)
    assert jogs == [1] and stages.count("searching") > 0 and stages[-1] == "manual"
    assert len(read_session(path).alignments) == 1  # nothing recorded is lost


@pytest.mark.parametrize("resumed", [False, True])
def test_no_jog_at_near_positions_after_the_search_straight_or_resumed(
    machine: Machine, tmp_path, resumed: bool
) -> None:
    """The launch unit 28 mm off its place in the machine file (the dry run's seed 3), the
    3-alignment design (its positions 201, 2412 and 150 mm away): the routine searches at
    the first, then points the others from that alignment's beam line (searching along
    it where it misses), straight through or resumed after a stop; no jog."""
    world, devices = _seed3_routine(machine)
    assert machine.launch_unit is not None
    positions = design_step(machine, 3).machine_mm
    stages: list[tuple[int, str]] = []
    jogs: list[int] = []

    def event(e: RoutineEvent) -> None:
        stages.append((e.index, e.stage))
        moves = sum(stage == "moving" for _, stage in stages)
        if resumed and e.stage == "moving" and moves == 2:
            raise _InterruptedError

    def run() -> Session:
        return run_identification(
            positions, machine, devices, tmp_path / "session.json",
            guess=PoseGuess(np.asarray(machine.launch_unit.position_mm, dtype=float)),
            manual_align=lambda: jogs.append(1), refine_guess=refine_guess,
            on_event=event, search=BeamSearchSettings(),
        )  # fmt: skip

    if resumed:
        with pytest.raises(_InterruptedError):
            run()
        assert len(read_session(tmp_path / "session.json").alignments) == 1
    session = run()
    assert len(session.alignments) == 3 and not jogs
    assert (1, "searching") in stages and not any(i != 1 and s == "searching" for i, s in stages)
    assert [i for i, s in stages if s == "recorded"] == [1, 2, 3]
    solved = identify(session, "intersection")
    assert np.linalg.norm(solved.position_mm - world.launch2mcs_mm) < 0.5
