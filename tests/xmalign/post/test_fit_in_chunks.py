"""The joint fit in chunks, its progress, and its uncertainty with noise correlated in time.

The normal equations accumulated chunk by chunk must be those of the dense
Jacobian of all rows; the fit in small chunks the fit at once. The coverage
test streams on-the-fly paths of a perfect virtual machine (sim.tracker_stream:
AR(1) noise over about 50 mm of path) through the real assignment and the fit:
the tables' U95 must cover the truth (zero) as often as it says.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import xmalign.post.instruments as joint
from sim.instrument_errors import MaterialDrift
from sim.machine import ErrorAmplitudes, VirtualMachine
from sim.tracer import VirtualTracer, measure_tracer
from sim.tracker import VirtualTracker, measure_tracker, measure_tracker_on_the_fly
from sim.tracker_stream import StreamOptions, correlated_noise, record_stream
from trajectories.instruments import (
    InstrumentProgram,
    axis_paths,
    diagonal_paths,
    grid_and_random_points,
    tracker_place,
)
from xmalign.formats.instruments import TracerFile, TrackerFile
from xmalign.machine import Machine, default_machine_path
from xmalign.machine import load_machine as load
from xmalign.post.instruments import (
    TrackerStation,
    correlation_samples,
    fit_joint,
    tracer_places,
    tracker_stations,
)
from xmalign.post.stream_assign import assign_stream
from xmalign.rigid_body import Chain

SMR = np.array([0.0, 0.0, -100.0])


@pytest.fixture(scope="module")
def machine() -> Machine:
    return load(default_machine_path()).model_copy(update={"smr_offset_mm": list(SMR)})


@pytest.fixture(scope="module")
def small_data(machine: Machine) -> tuple[list[TrackerStation], list]:
    """Tracker points at a standstill and on the fly, and tracer lengths from two places."""
    truth = VirtualMachine(machine, ErrorAmplitudes(repeatability_um=0.0), seed=2)
    low, high = machine.travel_min_mm, machine.travel_max_mm
    tracker = VirtualTracker(tracker_place(machine), np.array([0.2, -0.4, 20.0]), seed=2)
    points = grid_and_random_points(low, high, (3, 3, 2), 10, seed=2)
    rows = measure_tracker(truth, tracker, points, 1, SMR)
    paths = axis_paths(low, high, (3, 3, 2)) + diagonal_paths(low, high, 6, seed=2)
    rows += measure_tracker_on_the_fly(truth, tracker, paths, 150.0, SMR)
    lengths = []
    for i, pivot in enumerate([np.array([300.0, 200.0, -700.0]), np.array([1700, 1300, -750.0])]):
        lengths += measure_tracer(truth, VirtualTracer(pivot, seed=i), points, 1, SMR, f"P{i}")
    return tracker_stations([TrackerFile(rows, "t.csv")]), tracer_places(
        [TracerFile(lengths, "l.csv")]
    )


def _fit(machine: Machine, trackers, tracers, **options):
    return fit_joint(
        [],
        trackers,
        tracers,
        Chain.parse(machine.chain),
        np.ones(6),
        SMR,
        machine.tracker,
        machine.tracer,
        (machine.travel_min_mm, machine.travel_max_mm),
        **options,
    )


def test_the_normal_equations_in_chunks_are_those_of_the_dense_jacobian(
    machine, small_data, monkeypatch
):
    trackers, tracers = small_data
    chain = Chain.parse(machine.chain)
    # with the systematic errors as unknowns: the angle terms and a scale per run
    models = (
        machine.tracker.model_copy(update={"angle_systematic_urad": 5.0, "scale_ppm": 1.0}),
        machine.tracer.model_copy(update={"scale_ppm": 0.5}),
    )
    setting = joint._Setting(SMR, {}, False, *models)
    inputs = joint._Inputs([], trackers, tracers, chain, np.ones(6), setting, None, "test", [])
    layout, _ = joint._joint_layout(inputs, 250.0)
    states = joint._States(trackers, tracers, setting, layout.n_columns)
    assert states.trackers[0].n_angle and states.tracers[0].n_scale
    tables = np.random.default_rng(0).normal(0, 1e-3, states.n_columns)
    whole = [
        s.linearise(chain, layout, tables, states.n_columns, models[0]) for s in states.trackers
    ]
    whole += [
        t.linearise(chain, layout, tables, states.n_columns, models[1]) for t in states.tracers
    ]
    dense = np.vstack([(b.whitening @ b.design).toarray() for b in whole])
    observed = np.concatenate([b.whitening @ b.observed for b in whole])
    monkeypatch.setattr(joint, "CHUNK_POINTS", 7)
    chunks = list(states.chunks(chain, layout, tables))
    assert len(chunks) > 20
    equations = joint._accumulate((b for _, _, b in chunks), states.n_columns)
    np.testing.assert_allclose(equations.normal, dense.T @ dense, rtol=1e-10, atol=1e-6)
    np.testing.assert_allclose(equations.rhs, dense.T @ observed, rtol=1e-10, atol=1e-6)


def test_a_fit_in_small_chunks_is_the_fit_at_once(machine, small_data, monkeypatch):
    trackers, tracers = small_data
    at_once = _fit(machine, trackers, tracers)
    monkeypatch.setattr(joint, "CHUNK_POINTS", 11)
    done: list[tuple[int, int, str]] = []
    chunked = _fit(machine, trackers, tracers, progress=lambda *a: done.append(a))
    for name, table in at_once.fit.tables.tables.items():
        other = chunked.fit.tables.tables[name]
        # the same fit, summed in another order: to within 1e-8 mm (the iteration's step limit)
        np.testing.assert_allclose(other.values, table.values, rtol=0, atol=1e-8)
        np.testing.assert_allclose(other.u95, table.u95, rtol=1e-6, atol=1e-10)
    assert chunked.fit.sigma0 == pytest.approx(at_once.fit.sigma0, rel=1e-9)
    assert chunked.trackers[0].residual_rms_um == pytest.approx(at_once.trackers[0].residual_rms_um)
    # the progress counts every point of each pass, the last pass being the uncertainty
    total = sum(len(s.run) for s in trackers) + sum(len(p.run) for p in tracers)
    assert all(d[1] == total for d in done)
    finished = [what for d, _, what in done if d == total]
    assert finished[0] == "iteration 1" and finished[-1] == "residuals and uncertainty"
    assert len(finished) >= chunked.iterations + 1
    assert len(done) > 3 * len(finished)  # and tells how far it is within each pass


def _station_with(residual_across: np.ndarray, n_paths: int) -> tuple[TrackerStation, np.ndarray]:
    """A station on the fly along ``n_paths`` paths and its whitened residuals (2 per point)."""
    n = len(residual_across)
    path = np.repeat(np.arange(n_paths), n // n_paths)
    start = np.stack([path * 100.0, np.zeros(n), np.zeros(n)], axis=1)
    station = TrackerStation(
        "T1", "t.csv", np.zeros(n, int), start, start, start + [0.0, 1000.0, 0.0],
        np.full(n, np.nan), np.full(n, np.nan),
    )  # fmt: skip
    return station, residual_across.ravel()


def test_the_correlation_is_estimated_from_the_residuals_in_the_order_of_capture():
    rng = np.random.default_rng(5)
    correlated = correlated_noise(20_000, 100.0, 0.05, rng)[:, :2]  # phi = exp(-1/5)
    phi = np.exp(-0.2)
    station, weighted = _station_with(correlated, 10)
    assert correlation_samples(station, weighted) == pytest.approx((1 + phi) / (1 - phi), rel=0.2)
    station, weighted = _station_with(rng.normal(size=(20_000, 2)), 10)
    assert correlation_samples(station, weighted) < 1.1


def _fly_fit(machine: Machine, seed: int):
    """A stream of a perfect machine with noise correlated over ~50 mm, imported and fitted."""
    truth = VirtualMachine(machine, ErrorAmplitudes(scale=0.0, repeatability_um=0.0), seed=seed)
    low, high = machine.travel_min_mm, machine.travel_max_mm
    paths = axis_paths(low, high, (3, 3, 2)) + diagonal_paths(low, high, 9, seed=seed)
    program = InstrumentProgram(paths_mm=paths)
    tracker = VirtualTracker(tracker_place(machine), np.array([0.4, 0.3, 10.0 * seed]), seed=seed)
    options = StreamOptions(rate_hz=20.0, correlation_s=0.6)  # 50 mm of path at 5000 mm/min
    run = record_stream(machine, truth, tracker, program, options)
    starts = np.array([s for s, _ in paths]) + SMR
    ends = np.array([e for _, e in paths]) + SMR
    a = assign_stream(run.time_s, run.tracker_mm, starts, ends, run.line, "stream")
    n = len(a.sample)
    station = TrackerStation(
        "T1", "stream", np.zeros(n, int), starts[a.path] - SMR, run.tracker_mm[a.sample],
        ends[a.path] - SMR, np.full(n, np.nan), np.full(n, np.nan),
    )  # fmt: skip
    return _fit(machine, [station], [])


def test_the_u95_covers_the_truth_with_noise_correlated_along_the_paths(machine):
    covered, naive = [], []
    for seed in range(4):
        fit = _fly_fit(machine, seed)
        widened = np.sqrt(fit.trackers[0].correlation_samples)
        assert widened > 3.0  # the fit noticed
        for name, table in fit.fit.tables.tables.items():
            if name in fit.undetermined:
                continue
            error = np.abs(table.values)  # the truth is a perfect machine
            covered += list(error <= table.u95)
            naive += list(error <= table.u95 / widened)
    assert np.mean(covered) >= 0.9
    assert np.mean(naive) < 0.75  # as the fit was before it looked at the correlation


def test_the_fit_in_chunks_carries_the_systematic_errors_smr_positions_material_and_outliers(
    machine, monkeypatch
):
    """Issue 30's unknowns through issue 31's chunks: a tracker with angle errors and a
    scale per run, three SMR positions, a drifting material temperature and one gross
    outlier, and tracers with a scale per run: the fit in chunks of 13 points is the fit
    at once (tables, u95, systematic terms, the outlier named)."""
    offsets = {"A": SMR, "B": SMR + [100.0, 0.0, 0.0], "C": SMR + [0.0, 100.0, 0.0]}
    priors = machine.model_copy(
        update={
            "tracker": machine.tracker.model_copy(
                update={"angle_systematic_urad": 5.0, "scale_ppm": 1.0}
            ),
            "tracer": machine.tracer.model_copy(update={"scale_ppm": 0.5}),
        }
    )
    truth = VirtualMachine(machine, ErrorAmplitudes(scale=0.3), seed=3)
    low, high = machine.travel_min_mm, machine.travel_max_mm
    points = grid_and_random_points(low, high, (3, 3, 2), 30, seed=3)
    names = [("A", "B", "C")[k % 3] for k in range(len(points))]
    drift = MaterialDrift(20.5, 21.5, machine.thermal.expansion_ppm_per_k)
    tracker = VirtualTracker(tracker_place(machine), np.array([0.2, -0.4, 20.0]), seed=3)
    options = {"smr_offsets_mm": offsets, "smr_of_point": names, "material": drift}
    rows = measure_tracker(
        truth, tracker, points, 2, SMR, angle_systematic_urad=5.0, scale_ppm=1.0, **options
    )
    rows[7] = dataclasses.replace(rows[7], tracker_mm=rows[7].tracker_mm + [0.3, 0.0, 0.0])
    lengths = []
    for i, pivot in enumerate([np.array([300.0, 200.0, -700.0]), np.array([1700, 1300, -750.0])]):
        tracer = VirtualTracer(pivot, seed=i)
        lengths += measure_tracer(truth, tracer, points, 1, SMR, f"P{i}", scale_ppm=0.5, **options)
    trackers = tracker_stations([TrackerFile(rows, "t.csv")])
    tracers = tracer_places([TracerFile(lengths, "l.csv")])
    extra = {
        "knot_spacing_mm": 400.0,
        "smr_offsets_mm": offsets,
        "expansion_ppm_per_k": machine.thermal.expansion_ppm_per_k,
    }
    at_once = _fit(priors, trackers, tracers, **extra)
    monkeypatch.setattr(joint, "CHUNK_POINTS", 13)
    chunked = _fit(priors, trackers, tracers, **extra)
    assert [o.name for o in at_once.outliers] == [o.name for o in chunked.outliers]
    assert len(at_once.outliers) == 1 and "index" in at_once.outliers[0].name
    for name, table in at_once.fit.tables.tables.items():
        other = chunked.fit.tables.tables[name]
        np.testing.assert_allclose(other.values, table.values, rtol=0, atol=1e-8)
        np.testing.assert_allclose(other.u95, table.u95, rtol=1e-6, atol=1e-10)
    for a, b in zip(at_once.trackers, chunked.trackers, strict=True):
        assert len(a.angle_coefficients_urad) == 16 and len(a.scale_ppm) == 6
        np.testing.assert_allclose(b.angle_coefficients_urad, a.angle_coefficients_urad, atol=1e-5)
        assert b.scale_ppm == pytest.approx(a.scale_ppm, abs=1e-5)
    for a, b in zip(at_once.tracers, chunked.tracers, strict=True):
        assert a.scale_ppm and b.scale_ppm == pytest.approx(a.scale_ppm, abs=1e-5)
