"""Fine alignment on the simulated setup: the channel mapping, convergence, beam loss, jogging."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim.alignment_setup import simulated_setup
from xmalign.alignment import (
    AlignmentStep,
    FineAlignmentSettings,
    JogCommand,
    aligned_error,
    fine_align,
    jog,
    parse_jog,
    range_used,
    search_offsets_urad,
    sensitivity,
)
from xmalign.errors import BeamLostError, DeviceTimeoutError, InputError, OutOfRangeError
from xmalign.roles import InterferometerReading

#: CNC points giving beams from nearly level to steep (the launch unit stands below the table).
POSITIONS = [
    np.array(p, dtype=float) for p in ([1600, 1050, -100], [300, 1400, -400], [1900, 200, 0])
]


@pytest.mark.parametrize("position", POSITIONS)
def test_sensitivity_matches_the_simulated_instrument(reference_machine, position) -> None:  # noqa: ANN001
    world, devices = simulated_setup(reference_machine, position, seed=2, start_um=0, start_urad=0)
    step_rad = 20e-6
    base = world.interferometer.geometry()
    axes = [*devices.launch.axes, *devices.receiver.axes]
    motors = [*world.launch.axes, *world.receiver.axes]
    measured = []
    for axis, motor in zip(axes, motors, strict=True):
        start = motor.motor_rad()  # the encoder reading would add its noise
        axis.move_to(start + step_rad)
        axis.wait_in_position(1.0)
        after = world.interferometer.geometry()
        measured.append(aligned_error(_noise_free(after)) - aligned_error(_noise_free(base)))
        axis.move_to(start)
        axis.wait_in_position(1.0)
    elevation = devices.launch.angles_rad()[1]
    predicted = sensitivity(elevation, base.distance_mm) * (step_rad * 1e6)
    np.testing.assert_allclose(np.array(measured).T, predicted, rtol=0.02, atol=0.05)


def _noise_free(geometry) -> InterferometerReading:  # noqa: ANN001
    return InterferometerReading(0.0, geometry.channels, geometry.beam_ok)


@pytest.mark.parametrize("position", POSITIONS)
def test_converges_from_200um_300urad_within_5s(reference_machine, position) -> None:  # noqa: ANN001
    world, devices = simulated_setup(
        reference_machine, position, seed=7, start_um=200, start_urad=300
    )
    start = aligned_error(world.interferometer.read())
    assert np.hypot(*start[:2]) > 150 and np.all(np.abs(start[2:]) > 100)
    settings = FineAlignmentSettings()
    result = fine_align(
        devices.launch,
        devices.receiver,
        devices.interferometer,
        devices.clock,
        distance_mm=1000.0,
        settings=settings,
    )
    assert result.elapsed_s <= 5.0
    truth = aligned_error(_noise_free(world.interferometer.geometry()))
    assert np.all(np.abs(truth[:2]) <= 2 * settings.straightness_tol_um)
    assert np.all(np.abs(truth[2:]) <= 2 * settings.angle_tol_urad)
    assert result.distance_mm == pytest.approx(
        world.interferometer.geometry().distance_mm, rel=0.15
    )


def test_beam_out_of_range_at_the_start_is_found_by_the_search(reference_machine) -> None:  # noqa: ANN001
    world, devices = simulated_setup(
        reference_machine, POSITIONS[0], seed=1, start_um=600, start_urad=0
    )
    assert not world.interferometer.read().beam_ok
    settings = FineAlignmentSettings()
    result = fine_align(
        devices.launch, devices.receiver, devices.interferometer, devices.clock, 1000.0, settings
    )
    assert result.recoveries == 1 and result.search_s > 0
    truth = aligned_error(_noise_free(world.interferometer.geometry()))
    assert np.all(np.abs(truth[:2]) <= 2 * settings.straightness_tol_um)
    assert np.all(np.abs(truth[2:]) <= 2 * settings.angle_tol_urad)


def test_angle_out_of_range_is_found_by_turning_the_receiver(reference_machine) -> None:  # noqa: ANN001
    world, devices = simulated_setup(
        reference_machine, POSITIONS[0], seed=3, start_um=0, start_urad=0
    )
    a3 = devices.receiver.axes[0]
    elevation = devices.launch.angles_rad()[1]
    a3.move_to(a3.position_rad() + 700e-6 / math.cos(elevation))  # angle_w about 700 urad
    a3.wait_in_position(1.0)
    assert not world.interferometer.read().beam_ok
    settings = FineAlignmentSettings()
    result = fine_align(
        devices.launch, devices.receiver, devices.interferometer, devices.clock, 1000.0, settings
    )
    assert result.recoveries == 1
    truth = aligned_error(_noise_free(world.interferometer.geometry()))
    assert np.all(np.abs(truth[2:]) <= 2 * settings.angle_tol_urad)


def _knock_the_launch_unit(world, at_step: int, angle_urad: float):  # noqa: ANN001, ANN202
    """An on_step callback that turns the launch unit's base once (someone bumps it)."""
    steps = []

    def on_step(step: AlignmentStep) -> None:
        steps.append(step)
        if len(steps) == at_step:
            world.interferometer.gamma_rad += angle_urad * 1e-6

    return on_step


def test_beam_lost_midway_is_found_again(reference_machine) -> None:  # noqa: ANN001
    world, devices = simulated_setup(
        reference_machine, POSITIONS[0], seed=1, start_um=200, start_urad=300
    )
    settings = FineAlignmentSettings()
    result = fine_align(
        devices.launch,
        devices.receiver,
        devices.interferometer,
        devices.clock,
        1000.0,
        settings,
        on_step=_knock_the_launch_unit(world, at_step=2, angle_urad=400.0),
    )
    assert result.recoveries == 1
    truth = aligned_error(_noise_free(world.interferometer.geometry()))
    assert np.all(np.abs(truth[:2]) <= 2 * settings.straightness_tol_um)
    assert np.all(np.abs(truth[2:]) <= 2 * settings.angle_tol_urad)


def test_a_brief_interruption_goes_back_to_the_last_in_range_angles(reference_machine) -> None:  # noqa: ANN001
    world, devices = simulated_setup(
        reference_machine, POSITIONS[1], seed=2, start_um=100, start_urad=100
    )

    class Interrupted:
        """The interferometer with the beam blocked for its second reading."""

        def __init__(self) -> None:
            self.readings = 0

        def average(self, duration_s: float) -> InterferometerReading:
            self.readings += 1
            reading = world.interferometer.average(duration_s)
            if self.readings == 2:
                return InterferometerReading(reading.time_s, reading.channels, beam_ok=False)
            return reading

    result = fine_align(devices.launch, devices.receiver, Interrupted(), devices.clock, 1000.0)
    assert result.recoveries == 1
    # found at the first candidate, the last in-range angles: one move, no spiral
    assert result.search_s < 0.5


def test_beam_not_found_by_the_search_asks_for_a_person(reference_machine) -> None:  # noqa: ANN001
    _, devices = simulated_setup(
        reference_machine, POSITIONS[0], seed=1, start_um=600, start_urad=0
    )
    settings = FineAlignmentSettings(search_radius_urad=100.0, search_radius_um=0.0)
    with pytest.raises(BeamLostError, match="not found again.*spiral searches.*align --manual"):
        fine_align(
            devices.launch,
            devices.receiver,
            devices.interferometer,
            devices.clock,
            1000.0,
            settings,
        )


@pytest.mark.parametrize(("step", "radius"), [(1.0, 0.5), (1.0, 1.0), (1.0, 3.7), (120.0, 1400.0)])
def test_search_spiral_covers_the_disc_once_in_unit_steps(step: float, radius: float) -> None:
    offsets = search_offsets_urad(step, radius)
    grid = np.round(offsets / step).astype(int)
    assert len({tuple(p) for p in grid}) == len(grid)  # no point twice
    assert np.all(np.hypot(*offsets.T) <= radius + 1e-9)
    n = int(radius // step)
    expected = {
        (i, j)
        for i in range(-n, n + 1)
        for j in range(-n, n + 1)
        if (i, j) != (0, 0) and np.hypot(i, j) * step <= radius + 1e-9
    }
    assert {tuple(p) for p in grid} == expected
    # nearest first: rings never move inwards
    rings = np.max(np.abs(grid), axis=1) if len(grid) else grid
    assert np.all(np.diff(rings) >= 0)


def test_timeout_names_the_residuals(reference_machine) -> None:  # noqa: ANN001
    _, devices = simulated_setup(
        reference_machine, POSITIONS[0], seed=1, start_um=200, start_urad=300
    )
    settings = FineAlignmentSettings(timeout_s=0.1)
    with pytest.raises(DeviceTimeoutError, match=r"did not converge in 0.1 s \(straightness_v"):
        fine_align(
            devices.launch,
            devices.receiver,
            devices.interferometer,
            devices.clock,
            1000.0,
            settings,
        )


@pytest.mark.parametrize(
    ("text", "axis", "step_deg"), [("a2 -0.01", 2, -0.01), ("A5 +.5", 5, 0.5), (" a1 3 ", 1, 3.0)]
)
def test_parse_jog(text: str, axis: int, step_deg: float) -> None:
    assert parse_jog(text) == JogCommand(axis, math.radians(step_deg))


@pytest.mark.parametrize("text", ["a6 0.1", "a1", "x 1", "a1 0.1 0.2", "a1 1e"])
def test_parse_jog_refuses_nonsense(text: str) -> None:
    with pytest.raises(InputError, match="expected an axis a1..a5"):
        parse_jog(text)


def test_jog_moves_one_axis(reference_machine) -> None:  # noqa: ANN001
    _, devices = simulated_setup(reference_machine, POSITIONS[0], seed=1, start_um=0, start_urad=0)
    before = np.concatenate([devices.launch.angles_rad(), devices.receiver.angles_rad()])
    jog(devices.launch, devices.receiver, JogCommand(4, math.radians(0.01)), 1.0)
    after = np.concatenate([devices.launch.angles_rad(), devices.receiver.angles_rad()])
    moved = after - before
    assert moved[3] == pytest.approx(math.radians(0.01), abs=5e-5)
    assert np.all(np.abs(np.delete(moved, 3)) < 5e-5)
    with pytest.raises(OutOfRangeError, match="no axis a6"):
        jog(devices.launch, devices.receiver, JogCommand(6, 0.0), 1.0)


def test_range_used() -> None:
    reading = InterferometerReading(0.0, np.array([5.0, 125.0, -250.0, 50.0, -500.0, 0.0]))
    np.testing.assert_allclose(range_used(reading, 250.0, 500.0), [0.5, 1.0, 0.0, 1.0, 0.1])
