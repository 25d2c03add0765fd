"""The virtual laser tracker and tracer (sim.tracker, sim.tracer) measure the virtual machine."""

from __future__ import annotations

import numpy as np

from sim.instrument_errors import MaterialDrift
from sim.machine import ErrorAmplitudes, VirtualMachine
from sim.tracer import VirtualTracer, measure_tracer, measure_tracers_at_once
from sim.tracker import VirtualTracker, measure_tracker, measure_tracker_on_the_fly
from trajectories.instruments import axis_paths
from xmalign.machine import TracerUncertainty, TrackerUncertainty
from xmalign.rigid_body import Chain, deviation


def test_tracker_noise_follows_its_model_along_and_across_the_beam() -> None:
    model = TrackerUncertainty()
    tracker = VirtualTracker(np.zeros(3), np.array([0.0, 0.0, 90.0]), model, seed=1)
    point = np.array([[2000.0, 0.0, 0.0]])
    seen = tracker.observe(np.repeat(point, 20000, axis=0))
    # turned by 90 degrees about Z: the MCS +X lies along the tracker's -Y
    np.testing.assert_allclose(seen.mean(axis=0), [0.0, -2000.0, 0.0], atol=3e-4)
    along = seen[:, 1] + 2000.0
    expected_radial = (5.0 + 0.15 * 2.0) * 1e-3
    expected_transverse = (7.5 + 3.0 * 2.0) * 1e-3
    assert abs(along.std() / expected_radial - 1) < 0.03
    assert abs(seen[:, 0].std() / expected_transverse - 1) < 0.03
    assert abs(seen[:, 2].std() / expected_transverse - 1) < 0.03


def test_tracker_sees_the_same_truth_as_the_interferometer(reference_machine) -> None:
    machine = VirtualMachine(reference_machine, ErrorAmplitudes(repeatability_um=0.0), seed=5)
    quiet = TrackerUncertainty(radial_um=[0.0, 0.0], transverse_um=[0.0, 0.0])
    tracker = VirtualTracker(np.array([100.0, 200.0, -900.0]), np.zeros(3), quiet)
    cnc = np.array([[500.0, 400.0, -100.0], [1500.0, 1000.0, -300.0]])
    smr = np.array([0.0, 0.0, -100.0])
    rows = measure_tracker(machine, tracker, cnc, 1, smr)
    dp, _ = deviation(Chain.parse(reference_machine.chain), cnc, smr, machine)
    expected = cnc + smr + dp - [100.0, 200.0, -900.0]
    np.testing.assert_allclose([r.tracker_mm for r in rows], expected, atol=2e-6)


def test_tracer_lengths_carry_one_constant_per_run(reference_machine) -> None:
    machine = VirtualMachine(reference_machine, ErrorAmplitudes(scale=0.0, repeatability_um=0.0))
    quiet = TracerUncertainty(length_um=[0.0, 0.0])
    pivot = np.array([0.0, 0.0, -700.0])
    cnc = np.array([[0.0, 0.0, 0.0], [1000.0, 0.0, 0.0], [0.0, 1000.0, -200.0]])
    lengths = measure_tracer(machine, VirtualTracer(pivot, quiet, seed=3), cnc, 2, np.zeros(3))
    distance = np.linalg.norm(cnc - pivot, axis=1)
    constants = [
        np.array([r.length_mm for r in lengths if r.run == run]) - distance for run in (0, 1)
    ]
    for constant in constants:
        np.testing.assert_allclose(constant, constant[0], atol=1e-9)
    assert abs(constants[0][0] - constants[1][0]) > 1e-3


def test_on_the_fly_rows_name_their_path_and_no_index(reference_machine) -> None:
    machine = VirtualMachine(reference_machine, seed=2)
    paths = axis_paths(reference_machine.travel_min_mm, reference_machine.travel_max_mm, (2, 2, 2))
    tracker = VirtualTracker(np.array([1000.0, 750.0, -800.0]))
    rows = measure_tracker_on_the_fly(machine, tracker, paths, 100.0, np.zeros(3))
    assert all(r.index is None and r.to_mm is not None for r in rows)
    times = [r.time_s for r in rows]
    assert times == sorted(times)
    assert {tuple(r.machine_mm) for r in rows} == {tuple(start) for start, _ in paths}


def _quiet_machine(reference_machine) -> VirtualMachine:
    return VirtualMachine(reference_machine, ErrorAmplitudes(repeatability_um=0.0), seed=5)


def test_tracker_angle_errors_are_fixed_per_station_with_the_spec_rms(reference_machine) -> None:
    quiet = TrackerUncertainty(radial_um=[0.0, 0.0], transverse_um=[0.0, 0.0])
    rng = np.random.default_rng(0)
    directions = rng.normal(size=(4000, 3))
    points = 2000.0 * directions / np.linalg.norm(directions, axis=1)[:, None]
    rms = []
    for seed in range(40):
        tracker = VirtualTracker(np.zeros(3), np.zeros(3), quiet, seed=seed)
        first = tracker.observe(points, 0, angle_systematic_urad=20.0)
        again = tracker.observe(points, 1, angle_systematic_urad=20.0)
        np.testing.assert_allclose(first, again, atol=1e-5)  # the same in every run
        np.testing.assert_allclose(np.linalg.norm(first, axis=1), 2000.0, atol=1e-5)
        rms.append(np.sqrt(np.mean(np.sum((first - points) ** 2, axis=1))) / 2000.0 * 1e6)
    # two angle readings of RMS s each; the elevation's is along a full radius, the
    # azimuth's along cos(el): sqrt(s^2 + s^2 * E[cos^2 el] = 2/3) = s * sqrt(5/3)
    assert abs(np.sqrt(np.mean(np.square(rms))) / (20.0 * np.sqrt(5 / 3)) - 1) < 0.15


def test_scale_error_differs_per_run_and_station(reference_machine) -> None:
    quiet = TrackerUncertainty(radial_um=[0.0, 0.0], transverse_um=[0.0, 0.0])
    point = np.array([[3000.0, 0.0, 0.0]])
    factors = {
        (seed, run): VirtualTracker(np.zeros(3), np.zeros(3), quiet, seed).observe(
            point, run, scale_ppm=2.0
        )[0, 0]
        / 3000.0
        for seed in range(30)
        for run in range(2)
    }
    deviations_ppm = (np.array(list(factors.values())) - 1) * 1e6
    assert len(set(np.round(deviations_ppm, 9))) == 60
    assert 1.4 < deviations_ppm.std() < 2.6
    tracer = VirtualTracer(np.zeros(3), TracerUncertainty(length_um=[0.0, 0.0]), seed=1)
    assert abs(tracer.observe(point, 0.0, 0, 0.0)[0] - 3000.0) < 1e-5
    assert tracer.observe(point, 0.0, 0, 5.0)[0] != tracer.observe(point, 0.0, 1, 5.0)[0]


def test_several_smr_positions_are_runs_of_their_own(reference_machine) -> None:
    machine = _quiet_machine(reference_machine)
    quiet = TrackerUncertainty(radial_um=[0.0, 0.0], transverse_um=[0.0, 0.0])
    cnc = np.array([[500.0, 400.0, -100.0], [1500.0, 1000.0, -300.0], [900.0, 700.0, -200.0]])
    offsets = {"A": np.array([0.0, 0.0, -100.0]), "B": np.array([80.0, 0.0, -60.0])}
    tracker = VirtualTracker(np.array([100.0, 200.0, -900.0]), np.zeros(3), quiet)
    rows = measure_tracker(
        machine, tracker, cnc, 2, np.zeros(3), smr_offsets_mm=offsets, smr_of_point=list("ABA")
    )
    assert [(r.run, r.smr, r.index) for r in rows[:3]] == [(0, "A", 0), (0, "A", 2), (1, "B", 1)]
    assert {r.run for r in rows} == {0, 1, 2, 3}
    for row in rows:
        dp, _ = deviation(
            Chain.parse(reference_machine.chain), row.machine_mm, offsets[row.smr], machine
        )
        expected = row.machine_mm + offsets[row.smr] + dp - [100.0, 200.0, -900.0]
        np.testing.assert_allclose(row.tracker_mm, expected.ravel(), atol=2e-6)


def test_tracers_at_once_read_the_same_points_and_the_material_drifts(reference_machine) -> None:
    machine = VirtualMachine(reference_machine, ErrorAmplitudes(repeatability_um=2.0), seed=5)
    quiet = TracerUncertainty(length_um=[0.0, 0.0])
    pivots = {"P1": np.array([0.0, 0.0, -700.0]), "P2": np.array([2000.0, 1500.0, -700.0])}
    tracers = {
        name: VirtualTracer(pivot, quiet, seed=i) for i, (name, pivot) in enumerate(pivots.items())
    }
    cnc = np.array([[100.0, 100.0, -50.0], [1900.0, 1400.0, -400.0], [1000.0, 700.0, -200.0]])
    drift = MaterialDrift(21.0, 23.0, 11.5)
    rows = measure_tracers_at_once(machine, tracers, cnc, 1, np.zeros(3), material=drift)
    assert [r.material_c for r in rows if r.station == "P1"] == [21.0, 22.0, 23.0]
    # both tracers see one actual point: it lies on both spheres (constant removed by pairs)
    lengths = {name: np.array([r.length_mm for r in rows if r.station == name]) for name in pivots}
    actual_2_minus_0 = {name: lengths[name][2] - lengths[name][0] for name in pivots}
    grown = cnc * (1 + 11.5e-6 * (np.array([21.0, 22.0, 23.0]) - 20.0))[:, None]
    for name, pivot in pivots.items():
        nominal = np.linalg.norm(grown - pivot, axis=1)
        assert abs(actual_2_minus_0[name] - (nominal[2] - nominal[0])) < 0.05
