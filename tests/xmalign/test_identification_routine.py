"""The identification routine on the simulated setup: record as it goes, resume, refuse."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from sim.alignment_setup import point_by_truth
from sim.cnc import SimulatedCnc
from sim.dry_run import identify_virtually, virtual_setup
from sim.identification import spread_positions
from sim.units import SimPositioningUnit
from sim.world import World, build_world
from trajectories.identification_design import design_identification
from xmalign.alignment import FineAlignmentSettings
from xmalign.errors import BeamLostError, GeometryError, InputError, OutOfRangeError
from xmalign.formats.session import Session, read_session, write_session
from xmalign.geometry import wrap_angle
from xmalign.identification_routine import (
    PoseGuess,
    RoutineDevices,
    RoutineEvent,
    gamma_from_alignments,
    run_identification,
)
from xmalign.identify import identify
from xmalign.machine import Machine


def simulated(machine: Machine, seed: int = 3) -> tuple[World, RoutineDevices]:
    world = build_world(machine, seed=seed, gamma_rad=0.4)
    cnc = SimulatedCnc(machine, world.clock)
    world.interferometer.position = cnc  # the interferometer sees where the CNC is
    devices = RoutineDevices(
        cnc,
        SimPositioningUnit(world.launch),
        SimPositioningUnit(world.receiver),
        world.interferometer,
        world.clock,
    )
    return world, devices


def operator(world: World, machine: Machine, devices: RoutineDevices) -> list[int]:
    """A simulated operator who jogs the units into range; returns the list of calls."""
    calls: list[int] = []

    def manual_align() -> None:
        calls.append(1)
        point_by_truth(world, machine, devices.launch, devices.receiver)

    return calls, manual_align


def test_records_every_alignment_as_taken_and_identifies(reference_machine, tmp_path) -> None:  # noqa: ANN001
    world, devices = simulated(reference_machine)
    calls, manual_align = operator(world, reference_machine, devices)
    path = tmp_path / "session.json"
    positions = spread_positions(reference_machine, 5)
    recorded_counts = []

    def on_event(event: RoutineEvent) -> None:
        if event.stage == "recorded":
            recorded_counts.append(len(json.loads(path.read_text())["alignments"]))

    guess = PoseGuess(world.launch2mcs_mm + [0.02, -0.02, 0.01])  # gamma unknown
    session = run_identification(
        positions,
        reference_machine,
        devices,
        path,
        guess,
        manual_align=manual_align,
        on_event=on_event,
    )
    assert recorded_counts == [1, 2, 3, 4, 5]
    # the operator points the first one or two; then the learnt gamma and offsets suffice
    assert 1 <= len(calls) <= 2
    assert all(np.abs(a.straightness_um).max() <= 1.0 for a in session.alignments)
    assert all(axis.is_locked() for unit in (world.launch, world.receiver) for axis in unit.axes)
    result = identify(read_session(path), method="intersection")
    assert np.linalg.norm(result.position_mm - world.launch2mcs_mm) < 0.5
    assert abs(result.gamma_rad - world.gamma_rad) < 1e-3


def test_interrupted_routine_resumes_after_the_last_recorded(reference_machine, tmp_path) -> None:  # noqa: ANN001
    world, devices = simulated(reference_machine)
    _, manual_align = operator(world, reference_machine, devices)
    path = tmp_path / "session.json"
    positions = spread_positions(reference_machine, 4)
    guess = PoseGuess(world.launch2mcs_mm, world.gamma_rad)

    def stop_after_two(event: RoutineEvent) -> None:
        if event.stage == "recorded" and event.index == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_identification(
            positions,
            reference_machine,
            devices,
            path,
            guess,
            manual_align=manual_align,
            on_event=stop_after_two,
        )
    assert len(read_session(path).alignments) == 2
    assert all(axis.is_locked() for unit in (world.launch, world.receiver) for axis in unit.axes)
    stages: list[tuple[int, str]] = []
    session = run_identification(
        positions,
        reference_machine,
        devices,
        path,
        guess,
        manual_align=manual_align,
        on_event=lambda e: stages.append((e.index, e.stage)),
    )
    assert len(session.alignments) == 4
    assert (1, "skipped") in stages and (2, "skipped") in stages
    assert (3, "recorded") in stages and (4, "recorded") in stages
    recorded = np.array([a.machine_mm for a in read_session(path).alignments])
    np.testing.assert_allclose(recorded, positions, atol=1e-3)


def test_position_outside_travel_is_refused_before_moving(reference_machine, tmp_path) -> None:  # noqa: ANN001
    _, devices = simulated(reference_machine)
    positions = [[100.0, 100.0, -100.0], [2500.0, 100.0, -100.0]]
    with pytest.raises(OutOfRangeError, match=r"position 2 \[2500.0, 100.0, -100.0\] mm"):
        run_identification(positions, reference_machine, devices, tmp_path / "s.json")
    assert not (tmp_path / "s.json").exists()


def test_without_guess_or_operator_it_cannot_point(reference_machine, tmp_path) -> None:  # noqa: ANN001
    _, devices = simulated(reference_machine)
    with pytest.raises(GeometryError, match="no pose guess and no operator"):
        run_identification(
            [[500.0, 500.0, -100.0]], reference_machine, devices, tmp_path / "s.json"
        )


def test_session_of_another_setup_is_refused(reference_machine, tmp_path) -> None:  # noqa: ANN001
    _, devices = simulated(reference_machine)
    path = tmp_path / "s.json"
    write_session(path, Session(receiver_offset_mm=np.array([0.0, 0.0, -200.0])))
    with pytest.raises(InputError, match="s.json: key 'receiver_offset_mm'"):
        run_identification([[500.0, 500.0, -100.0]], reference_machine, devices, path)


def test_gamma_from_alignments(reference_machine, tmp_path: Path) -> None:  # noqa: ANN001
    world, devices = simulated(reference_machine)
    session = run_identification(
        spread_positions(reference_machine, 2),
        reference_machine,
        devices,
        tmp_path / "s.json",
        PoseGuess(world.launch2mcs_mm, world.gamma_rad),
    )
    assert gamma_from_alignments(world.launch2mcs_mm, session) == pytest.approx(
        world.gamma_rad, abs=2e-4
    )


def test_beam_missed_by_the_pointing_is_found_without_a_person(reference_machine, tmp_path) -> None:  # noqa: ANN001
    """A guess whose azimuth is 400 urad off points the beam out of range at every far
    position; fine alignment's search finds it there, so no operator is needed."""
    world, devices = simulated(reference_machine)
    guess = PoseGuess(world.launch2mcs_mm, world.gamma_rad + 400e-6)
    positions = spread_positions(reference_machine, 6)
    no_search = FineAlignmentSettings(search_radius_urad=0.0, search_radius_um=0.0)
    with pytest.raises(BeamLostError, match="not found again"):
        run_identification(
            positions, reference_machine, devices, tmp_path / "a.json", guess, no_search
        )
    world, devices = simulated(reference_machine)
    session = run_identification(positions, reference_machine, devices, tmp_path / "b.json", guess)
    assert len(session.alignments) == 6
    assert all(np.abs(a.straightness_um).max() <= 1.0 for a in session.alignments)


def test_virtual_sessions_with_machine_errors_agree_with_the_stated_uncertainty(
    reference_machine, tmp_path
) -> None:  # noqa: ANN001
    """The whole routine on the dry run's virtual machine (its errors turn the receiver):
    no false outlier, no 'residuals larger than stated' warning, the truth inside 95 %."""
    positions = design_identification(reference_machine, 6).machine_mm
    limit = stats.chi2.ppf(0.95, 4)
    for seed in range(1, 9):
        setup = virtual_setup(reference_machine, seed)
        result = identify_virtually(
            setup, reference_machine, positions, tmp_path / f"{seed}.json", seed=seed
        )
        assert result.outlier is None and result.converged
        assert not any("larger than the stated" in w for w in result.warnings), result.warnings
        delta = np.append(
            result.position_mm - setup.world.launch2mcs_mm,
            wrap_angle(result.gamma_rad - setup.world.gamma_rad),
        )
        assert delta @ np.linalg.solve(result.covariance, delta) <= limit


def test_coarse_pointing_starts_every_axis_of_both_units_before_waiting(
    reference_machine: Machine, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Both units turn together: pointing takes the longest axis move, not the sum of
    the launch unit's and the receiver's."""
    world, devices = simulated(reference_machine)
    axis_type = type(devices.launch.axes[0])
    calls: list[str] = []
    pointing = False

    def recorded(verb: str) -> object:
        original = getattr(axis_type, verb)

        def call(axis: object, *args: object) -> None:
            if pointing:
                calls.append(f"{verb} {axis.name}")  # type: ignore[attr-defined]
            original(axis, *args)

        return call

    for verb in ("move_to", "wait_in_position"):
        monkeypatch.setattr(axis_type, verb, recorded(verb))

    def on_event(event: RoutineEvent) -> None:
        nonlocal pointing
        pointing = event.stage == "pointing"

    guess = PoseGuess(world.launch2mcs_mm, world.gamma_rad)
    run_identification(
        spread_positions(reference_machine, 1),
        reference_machine,
        devices,
        tmp_path / "session.json",
        guess,
        on_event=on_event,
    )
    names = [axis.name for unit in (devices.launch, devices.receiver) for axis in unit.axes]
    assert calls == [f"move_to {n}" for n in names] + [f"wait_in_position {n}" for n in names]
