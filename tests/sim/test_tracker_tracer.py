"""The virtual laser tracker and tracer (sim.tracker, sim.tracer) measure the virtual machine."""

from __future__ import annotations

import numpy as np

from sim.machine import ErrorAmplitudes, VirtualMachine
from sim.tracer import VirtualTracer, measure_tracer
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
