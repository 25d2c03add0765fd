"""The joint fit of tracker points and tracer lengths (xmalign.post.instruments).

The data come from the simulator's virtual machine (sim.machine), tracker
(sim.tracker) and tracer (sim.tracer); the truth is the virtual machine's own
error model.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from sim.machine import ErrorAmplitudes, VirtualMachine
from sim.tracer import VirtualTracer, measure_tracer
from sim.tracker import VirtualTracker, measure_tracker, measure_tracker_on_the_fly
from trajectories.instruments import axis_paths, diagonal_paths, grid_and_random_points
from xmalign.errors import GeometryError
from xmalign.formats.instruments import TracerFile, TrackerFile
from xmalign.machine import Machine, TracerUncertainty, TrackerUncertainty, default_machine_path
from xmalign.machine import load_machine as load
from xmalign.post.compare import grid_points, remove_rigid_motion
from xmalign.post.instruments import (
    fit_joint,
    multilateration_start,
    rigid_start,
    tracer_places,
    tracker_stations,
    unseen_rotations,
)
from xmalign.rigid_body import Chain, deviation

SMR = np.array([0.0, 0.0, -100.0])
PIVOTS = [
    np.array([200.0, 150.0, -650.0]),
    np.array([1800.0, 150.0, -750.0]),
    np.array([1800.0, 1350.0, -650.0]),
    np.array([200.0, 1350.0, -750.0]),
]


@pytest.fixture(scope="module")
def machine() -> Machine:
    return load(default_machine_path()).model_copy(update={"smr_offset_mm": list(SMR)})


def _truth(machine: Machine, seed: int = 3) -> VirtualMachine:
    return VirtualMachine(machine, ErrorAmplitudes(repeatability_um=0.0), seed=seed)


def _points(machine: Machine, n_random: int, seed: int = 0) -> np.ndarray:
    return grid_and_random_points(
        machine.travel_min_mm, machine.travel_max_mm, (4, 4, 3), n_random, seed
    )


def _residual_at_smr_um(machine: Machine, model, truth) -> float:
    chain = Chain.parse(machine.chain)
    points = grid_points(machine.travel_min_mm, machine.travel_max_mm, 6)
    fitted, _ = deviation(chain, points, np.zeros(3), model)
    true, _ = deviation(chain, points, SMR, truth)
    residual = remove_rigid_motion(points, fitted - true)
    return float(np.sqrt(np.mean(np.sum(residual**2, axis=1))) * 1e3)


def _fit(machine: Machine, trackers=(), tracers=(), lines=()):
    return fit_joint(
        list(lines),
        tracker_stations(list(trackers)),
        tracer_places(list(tracers)),
        Chain.parse(machine.chain),
        np.ones(6) * 1e-3,
        SMR,
        machine.tracker,
        machine.tracer,
        (machine.travel_min_mm, machine.travel_max_mm),
    )


def _quiet_tracker(position, rotation_deg, seed=0) -> VirtualTracker:
    """A tracker without noise (its model's sigmas at 1 nm, the floor)."""
    quiet = TrackerUncertainty(radial_um=[0.0, 0.0], transverse_um=[0.0, 0.0])
    return VirtualTracker(np.asarray(position, float), np.asarray(rotation_deg, float), quiet, seed)


def test_rigid_and_multilateration_starts_are_exact_on_exact_data() -> None:
    rng = np.random.default_rng(1)
    points = rng.uniform(-1000, 1000, (30, 3))
    rotation = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    rotation *= np.sign(np.linalg.det(rotation))
    r, c = rigid_start(points, points @ rotation.T + [5, 6, 7])
    np.testing.assert_allclose(r, rotation, atol=1e-12)
    np.testing.assert_allclose(c, [5, 6, 7], atol=1e-9)
    pivot = np.array([100.0, -200.0, -700.0])
    runs = np.arange(30) % 2
    lengths = np.linalg.norm(points - pivot, axis=1) + np.where(runs == 0, 12.5, -40.0)
    q, k = multilateration_start(points, lengths, runs, 2)
    np.testing.assert_allclose(q, pivot, atol=1e-6)
    np.testing.assert_allclose(k, [12.5, -40.0], atol=1e-6)
    assert multilateration_start(points[:, :1] * [1, 0, 0], lengths, runs, 2) is None


def test_unseen_rotations_follow_the_chain() -> None:
    assert unseen_rotations(Chain.parse("FYXZ")) == ["ECX", "EAZ", "EBZ", "ECZ"]
    assert unseen_rotations(Chain.parse("XFYZ")) == ["ECY", "EAZ", "EBZ", "ECZ"]


def test_tracker_alone_without_noise_recovers_the_volumetric_errors(machine: Machine) -> None:
    truth = _truth(machine)
    # turned far from any coarse guess: the closed-form start needs none
    tracker = _quiet_tracker([1000, 750, -800], [10, -20, 170])
    rows = measure_tracker(truth, tracker, _points(machine, 150), 1, machine.smr_offset)
    joint = _fit(machine, trackers=[TrackerFile(rows, "t.csv")])
    assert joint.functional_point == "SMR"
    # the table model at 250 mm knots, not noise, limits this (noisy: ~4 um)
    assert _residual_at_smr_um(machine, joint.fit.tables.model(""), truth) < 1.0
    (station,) = joint.trackers
    # the pose up to the gauge of the table conventions (a rigid motion of micrometres)
    np.testing.assert_allclose(station.position_mm, [1000, 750, -800], atol=0.05)
    np.testing.assert_allclose(station.rotation_urad, np.radians([10, -20, 170]) * 1e6, atol=100)
    assert station.residual_rms_um < 1.0
    assert np.all(np.isnan(joint.fit.tables.tables["ECZ"].u95))
    assert np.all(np.isfinite(joint.fit.tables.tables["EAY"].u95))


def test_tracers_alone_self_calibrate_their_pivots(machine: Machine) -> None:
    truth = _truth(machine)
    quiet = TracerUncertainty(length_um=[0.0, 0.0])
    lengths = []
    for i, pivot in enumerate(PIVOTS):
        tracer = VirtualTracer(pivot, quiet, seed=i)
        points = _points(machine, 150, seed=i)
        lengths += measure_tracer(truth, tracer, points, 2, machine.smr_offset, f"P{i}")
    joint = _fit(machine, tracers=[TracerFile(lengths, "r.csv")])
    assert joint.iterations < 20
    assert _residual_at_smr_um(machine, joint.fit.tables.model(""), truth) < 0.3
    for place, pivot in zip(joint.tracers, PIVOTS, strict=True):
        np.testing.assert_allclose(place.pivot_mm, pivot, atol=0.05)
        assert set(place.constant_mm) == {0, 1}
        # no noise: what remains is the cubic tables' model error at 200 mm knots (~0.1 um)
        assert place.residual_rms_um < 0.2


def test_noise_is_weighted_by_the_uncertainty_model(machine: Machine) -> None:
    """With the simulator's noise drawn from the machine file's model, sigma0 is about 1."""
    truth = _truth(machine)
    tracker = VirtualTracker(np.array([1000.0, 750, -800]), np.array([0.0, 0.0, 30.0]), seed=4)
    rows = measure_tracker(truth, tracker, _points(machine, 200), 2, machine.smr_offset)
    joint = _fit(machine, trackers=[TrackerFile(rows, "t.csv")])
    assert 0.85 < joint.fit.sigma0 < 1.15
    u95 = joint.fit.tables.tables["EXX"].u95
    assert np.all(np.isfinite(u95)) and np.nanmax(u95) > 0


def test_a_tracker_station_with_too_few_points_is_named(machine: Machine) -> None:
    truth = _truth(machine)
    tracker = _quiet_tracker([1000, 750, -800], [0, 0, 0])
    good = measure_tracker(truth, tracker, _points(machine, 100), 1, machine.smr_offset)
    few = measure_tracker(truth, tracker, _points(machine, 0)[:2], 1, machine.smr_offset, "T9")
    with pytest.raises(GeometryError, match=r"few\.csv: tracker station T9: 2 points"):
        _fit(machine, trackers=[TrackerFile(good, "t.csv"), TrackerFile(few, "few.csv")])


def test_too_few_tracer_places_alone_are_refused(machine: Machine) -> None:
    truth = _truth(machine)
    lengths = []
    for i, pivot in enumerate(PIVOTS[:3]):
        lengths += measure_tracer(
            truth, VirtualTracer(pivot, seed=i), _points(machine, 50), 1, SMR, f"P{i}"
        )
    with pytest.raises(GeometryError, match="3 tracer places cannot place the points"):
        _fit(machine, tracers=[TracerFile(lengths, "r.csv")])


def test_a_tracer_place_whose_points_lie_on_a_line_is_named(machine: Machine) -> None:
    truth = _truth(machine)
    lengths = []
    for i, pivot in enumerate(PIVOTS):
        points = _points(machine, 50)
        if i == 2:
            points = np.linspace([100.0, 100, -100], [1900.0, 100, -100], 20)
        lengths += measure_tracer(truth, VirtualTracer(pivot, seed=i), points, 1, SMR, f"P{i}")
    with pytest.raises(GeometryError, match=r"r\.csv: tracer place P2: its 20 lengths cannot"):
        _fit(machine, tracers=[TracerFile(lengths, "r.csv")])


def test_points_that_do_not_move_an_axis_are_refused(machine: Machine) -> None:
    truth = _truth(machine)
    points = _points(machine, 100)
    points[:, 2] = -200.0
    rows = measure_tracker(truth, _quiet_tracker([1000, 750, -800], [0, 0, 0]), points, 1, SMR)
    with pytest.raises(GeometryError, match=r"t\.csv: the points do not move the Z axis"):
        _fit(machine, trackers=[TrackerFile(rows, "t.csv")])


def test_a_tracker_only_on_the_fly_needs_no_synchronisation(machine: Machine) -> None:
    """Seed 001: rows without index, no standstill point; only the deviation across counts."""
    truth = _truth(machine)
    low, high = machine.travel_min_mm, machine.travel_max_mm
    paths = axis_paths(low, high, (5, 4, 3)) + diagonal_paths(low, high, 24, seed=1)
    tracker = _quiet_tracker([1000, 750, -800], [0, 0, 120])
    rows = measure_tracker_on_the_fly(truth, tracker, paths, 40.0, SMR, feed_mm_min=5000.0)
    joint = _fit(machine, trackers=[TrackerFile(rows, "fly.csv")])
    assert joint.iterations < 20
    # no noise: the tables' model error over sparse paths (standstill points: < 1 um)
    assert _residual_at_smr_um(machine, joint.fit.tables.model(""), truth) < 2.0
    # the along-path component is not a residual: only the deviation across counts
    assert joint.trackers[0].residual_rms_um < 1.0
    np.testing.assert_allclose(joint.trackers[0].position_mm, [1000, 750, -800], atol=0.05)


def test_axis_paths_alone_put_the_knots_where_the_axes_stood(machine: Machine) -> None:
    truth = _truth(machine)
    paths = axis_paths(machine.travel_min_mm, machine.travel_max_mm, (5, 4, 3))
    rows = measure_tracker_on_the_fly(
        truth, _quiet_tracker([1000, 750, -800], [0, 0, 0]), paths, 100.0, SMR
    )
    joint = _fit(machine, trackers=[TrackerFile(rows, "fly.csv")])
    measured = joint.fit.tables.tables["EXX"]
    knots = measured.positions_mm[::4]
    np.testing.assert_allclose(knots, [0, 500, 1000, 1500, 2000])


def test_the_propagated_uncertainty_matches_the_scatter_of_the_result(machine: Machine) -> None:
    """GUM check: on a smooth machine (no model error) the residual over the travel is what
    the covariance predicts (the information limit), within the spread of a few seeds."""
    chain = Chain.parse(machine.chain)
    grid = grid_points(machine.travel_min_mm, machine.travel_max_mm, 6)
    ratios = []
    for seed in range(3):
        truth = VirtualMachine(machine, ErrorAmplitudes(scale=0.05, repeatability_um=0.0), seed)
        tracker = VirtualTracker(np.array([1000.0, 750, -800]), np.array([0.0, 0, 30]), seed=seed)
        rows = measure_tracker(truth, tracker, _points(machine, 200, seed), 2, SMR)
        joint = _fit(machine, trackers=[TrackerFile(rows, "t.csv")])
        actual = _residual_at_smr_um(machine, joint.fit.tables.model(""), truth)
        ratios.append(actual / joint.volumetric_u_um(chain, grid))
    assert 0.6 < np.mean(ratios) < 1.4, ratios


def test_a_rows_own_uncertainty_weights_it_and_a_gross_outlier_is_named(machine: Machine) -> None:
    """A point 5 mm off with its own u of 10 mm counts for nothing; without it, it is a gross
    outlier: named (file, station, run, index) and left out, also from the residual."""
    truth = _truth(machine)
    rows = measure_tracker(
        truth, _quiet_tracker([1000, 750, -800], [0, 0, 0]), _points(machine, 100), 1, SMR
    )
    bad = rows[7]
    moved = replace(bad, tracker_mm=bad.tracker_mm + 5.0)
    flagged = replace(moved, u_radial_um=1e4, u_transverse_um=1e4)
    fits = {}
    for name, row in (("flagged", flagged), ("unflagged", moved)):
        fits[name] = _fit(machine, trackers=[TrackerFile(rows[:7] + [row] + rows[8:], "t.csv")])
        model = fits[name].fit.tables.model("")
        assert _residual_at_smr_um(machine, model, truth) < 1.0
    assert fits["flagged"].outliers == []
    (outlier,) = fits["unflagged"].outliers
    assert outlier.name == f"t.csv: tracker station T1 run 0 index {bad.index}"
    assert outlier.sigmas > 10
    assert fits["unflagged"].trackers[0].residual_rms_um < 1.0


def test_two_files_with_the_same_station_name_are_two_stations(machine: Machine) -> None:
    truth = _truth(machine)
    files = []
    for i, place in enumerate(([1000, 750, -800], [300, 200, -700])):
        tracker = _quiet_tracker(place, [0, 0, 20 * i])
        rows = measure_tracker(truth, tracker, _points(machine, 60, seed=i), 1, SMR)
        files.append(TrackerFile(rows, f"day{i}.csv"))
    joint = _fit(machine, trackers=files)
    assert [s.label for s in joint.trackers] == ["T1@day0.csv", "T1@day1.csv"]
    np.testing.assert_allclose(joint.trackers[1].position_mm, [300, 200, -700], atol=0.05)
