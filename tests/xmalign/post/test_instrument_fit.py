"""The joint fit on machines and data nobody tuned it to (issue 30): knot spacing chosen from
the data, seed 004's gantry with its large squareness, several SMR positions for a tool,
the instruments' systematic errors, the material temperature, fits that must be refused.

Data from the simulator (sim.machine, sim.tracker, sim.tracer); the truth is the virtual
machine's own error model. Seed 004's machine and tracer places are the paper's (its
section 4 and Table 6).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import xmalign.post.instruments as fit_module
from sim.instrument_dry_run import simulate_instruments
from sim.machine import ErrorAmplitudes, VirtualMachine
from sim.tracer import VirtualTracer, measure_tracer
from sim.tracker import VirtualTracker, measure_tracker
from trajectories.instruments import grid_and_random_points, propose_tracer_places
from xmalign.errors import GeometryError
from xmalign.formats.instruments import TracerFile, TracerLength, TrackerFile, TrackerPoint
from xmalign.machine import (
    Machine,
    TracerUncertainty,
    TrackerUncertainty,
    default_machine_path,
    load_machine,
)
from xmalign.post.compare import grid_points, remove_rigid_motion, volumetric_rms_um
from xmalign.post.evaluate import Instruments, PostResult, post_stations
from xmalign.post.instruments import (
    TracerPlace,
    instrument_knots,
    spacing_sample,
    tracer_places,
    unseen_with_smr_positions,
)
from xmalign.rigid_body import Chain, deviation

SMR = [0.0, 0.0, -100.0]
#: Seed 004, Table 6: the four tracer pivots after calibration (machine coordinates, mm).
SEED_004_PIVOTS = np.array(
    [
        [158.8075, -1456.6824, -349.7023],
        [-113.1165, -1671.7155, -349.3517],
        [-468.6489, -1563.1627, -349.4140],
        [-769.8987, -1599.5469, -208.9567],
    ]
)


def _machine(**update: object) -> Machine:
    return load_machine(default_machine_path()).model_copy(update={"smr_offset_mm": SMR, **update})


def _tracer_rows(
    machine: Machine, truth: VirtualMachine, pivots: list[np.ndarray], n_random: int, **options
) -> list:
    rows = []
    for i, pivot in enumerate(pivots):
        points = grid_and_random_points(
            machine.travel_min_mm, machine.travel_max_mm, (5, 4, 3), n_random, i
        )
        tracer = VirtualTracer(np.asarray(pivot, float), seed=i)
        rows += measure_tracer(truth, tracer, points, 1, machine.smr_offset, f"P{i + 1}", **options)
    return rows


def _tracers(machine: Machine, rows: list, knot_spacing_mm: float | None = None) -> PostResult:
    instruments = Instruments(tracers=(TracerFile(rows, "r.csv"),), knot_spacing_mm=knot_spacing_mm)
    return post_stations(machine, [], instruments=instruments)


def _at_smr_um(machine: Machine, result: PostResult, truth: VirtualMachine) -> float:
    grid = grid_points(machine.travel_min_mm, machine.travel_max_mm, 6)
    chain = Chain.parse(machine.chain)
    return volumetric_rms_um(chain, grid, result.fit.tables.model(""), truth, machine.smr_offset)


def _limit_um(machine: Machine, result: PostResult, offset_mm=None) -> float:
    assert result.instruments is not None
    grid = grid_points(machine.travel_min_mm, machine.travel_max_mm, 6)
    return result.instruments.volumetric_u_um(Chain.parse(machine.chain), grid, offset_mm)


def test_the_knot_spacing_follows_a_small_machine() -> None:
    """YFXZ 800 x 600 x 450: 200 mm knots cannot follow its errors (issue 30: 3.05 um);
    cross-validation picks finer ones and reaches what the readings allow."""
    machine = _machine(chain="YFXZ", travel_mm={"X": [0, 800], "Y": [0, 600], "Z": [-450, 0]})
    truth = VirtualMachine(machine, seed=0)
    rows = _tracer_rows(machine, truth, propose_tracer_places(machine, 4), 200)
    chosen = _tracers(machine, rows)
    fixed = _tracers(machine, rows, knot_spacing_mm=200.0)
    assert chosen.instruments is not None and fixed.instruments is not None
    assert chosen.instruments.knot_spacing_mm is not None
    assert chosen.instruments.knot_spacing_mm < 120
    assert [s for s, _ in chosen.instruments.spacing_scores][0] > 200  # tried coarse first
    assert fixed.instruments.knot_spacing_mm == 200.0 and not fixed.instruments.spacing_scores
    residual = _at_smr_um(machine, chosen, truth)
    assert residual < 0.7 < _at_smr_um(machine, fixed, truth)
    assert residual < 1.5 * _limit_um(machine, chosen)


def test_a_score_that_rises_before_it_falls_does_not_end_the_search(tmp_path: Path) -> None:
    """The tracer dry run on the reference machine, seed 2 (issue 30): the score rises
    from 400 to 333 mm knots (7 % above the best so far) and falls twelvefold at 250 mm,
    where the tables first follow the errors' wavelength. The search that stopped 5 %
    above the best kept 400 mm: 3.56 um from the truth; over every candidate, 0.43 um."""
    machine = load_machine(default_machine_path())
    run = simulate_instruments(machine, tmp_path / "dry", "tracer", seed=2)
    joint = run.result.instruments
    assert joint is not None
    scores = [score for _, score in joint.spacing_scores]
    chosen = scores.index(min(scores))
    assert joint.gcv == scores[chosen]
    rises = [i for i in range(1, chosen) if scores[i] > 1.05 * min(scores[:i])]
    assert rises, scores  # the case's character: a rise before the least score
    assert run.volumetric_after_um < 1.0  # the target for tracers


def test_a_candidate_spacing_gives_the_intervals_it_was_divided_into() -> None:
    """600 / (600 / 7) is 7.000000000000001 in floating point: 7 intervals, not 8."""
    points = np.array([[0.0, 0, -450], [800, 600, 0]])
    knots = instrument_knots(points, 600 / 7, np.full(3, np.inf))
    assert [len(knots[a]) for a in "XYZ"] == [11, 8, 7]


def test_the_spacing_sample_spreads_over_every_run_the_same_every_time() -> None:
    """Thinned to about 1000 of 4550 rows: every 5th row of each run in capture order,
    every run kept (a run of 3 rows too), the same copy on every call."""
    runs = np.concatenate([np.repeat([1, 2, 3], [2000, 1000, 3]), np.repeat([1, 4], [500, 1047])])
    place = TracerPlace("P1", "t.csv", runs, np.zeros((len(runs), 3)), np.arange(len(runs)) * 1.0)
    (thinned,) = spacing_sample([], [place], 1000)[1]
    again = spacing_sample([], [place], 1000)[1][0]
    assert np.array_equal(thinned.length_mm, again.length_mm)
    kept = thinned.length_mm.astype(int)
    assert np.all(np.diff(kept) > 0)  # capture order
    assert set(thinned.run.tolist()) == {1, 2, 3, 4}
    for run in (1, 2, 4):  # every 5th row of the run
        rows = np.flatnonzero(runs == run)
        mine = kept[runs[kept] == run]
        assert np.all(np.diff(np.searchsorted(rows, mine)) == 5)
        assert len(mine) == pytest.approx(len(rows) / 5, abs=1)
    assert spacing_sample([], [place], len(runs))[1][0] is place  # not above: all rows


def test_a_spacing_chosen_on_a_thinned_copy_fits_all_rows_at_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Above SPACING_SAMPLE_POINTS the candidates are scored on a thinned copy whose knots
    are spread over all rows' reach; all rows are then fitted at the chosen spacing."""
    machine = _machine(chain="YFXZ", travel_mm={"X": [0, 800], "Y": [0, 600], "Z": [-450, 0]})
    truth = VirtualMachine(machine, seed=0)
    rows = _tracer_rows(machine, truth, propose_tracer_places(machine, 4), 200)
    everything = _tracers(machine, rows)
    monkeypatch.setattr(fit_module, "SPACING_SAMPLE_POINTS", 600)  # every 2nd of 1040
    thinned = _tracers(machine, rows)
    joint = thinned.instruments
    assert joint is not None and everything.instruments is not None
    assert joint.layout is not None and joint.knot_spacing_mm is not None
    assert thinned.fit.n_observations == everything.fit.n_observations
    assert joint.knot_spacing_mm in [s for s, _ in joint.spacing_scores]
    assert len(joint.spacing_scores) < len(everything.instruments.spacing_scores)
    places = tracer_places([TracerFile(rows, "r.csv")])
    reach = np.concatenate([p.machine_mm for p in places])
    knots = instrument_knots(reach, joint.knot_spacing_mm, np.full(3, np.inf))
    assert {a: len(k) for a, k in joint.layout.knots.items()} == {
        a: len(k) for a, k in knots.items()
    }


def test_seed_004_gantry_with_its_squareness_and_one_sided_tracers() -> None:
    """Seed 004's machine (X [-800, 0], Y [-1000, 0], Z [-350, 0], E_C0Y 2900 urad) and its
    Table 6 pivots, all on one side: no pivot guess, the fit settles and reaches the limit."""
    machine = _machine(travel_mm={"X": [-800, 0], "Y": [-1000, 0], "Z": [-350, 0]})
    truth = VirtualMachine(machine, seed=1)
    truth._squareness[0] = 2900e-6  # the paper's E_C0Y (Table 7)
    rows = _tracer_rows(machine, truth, list(SEED_004_PIVOTS + [0, 0, -100]), 300)
    result = _tracers(machine, rows)
    assert result.instruments is not None
    true_ec0y = truth.truth_tables(100.0).squareness["EC0Y"][0]  # in the table conventions
    assert abs(true_ec0y) > 2800e-6
    np.testing.assert_allclose(result.fit.tables.squareness["EC0Y"][0], true_ec0y, atol=5e-6)
    residual = _at_smr_um(machine, result, truth)
    # seeds 0-4: 0.61-1.38 x the information limit (2.3-2.6 um: one-sided pivots), and
    # 6.8-12 um with the former fixed 200 mm knots; seed 1 is the worst of the five
    assert residual < 1.6 * _limit_um(machine, result), residual
    assert residual < 0.6 * _at_smr_um(machine, _tracers(machine, rows, 200.0), truth)
    for place, pivot in zip(result.instruments.tracers, SEED_004_PIVOTS, strict=True):
        np.testing.assert_allclose(place.pivot_mm, pivot + [0, 0, -100], atol=0.2)


def test_smr_positions_on_one_line_leave_the_rotation_about_it() -> None:
    chain = Chain.parse("FYXZ")
    one = np.array([[0.0, 0, -100]])
    along_z = np.array([[0.0, 0, -100], [0, 0, -200]])
    three = np.array([[0.0, 0, -100], [100, 0, -60], [0, 100, -60]])
    assert unseen_with_smr_positions(chain, one) == ["ECX", "EAZ", "EBZ", "ECZ"]
    assert unseen_with_smr_positions(chain, along_z) == ["ECX", "ECZ"]
    assert unseen_with_smr_positions(chain, three) == []


def test_three_smr_positions_calibrate_a_tool() -> None:
    """Four tracer places, evaluated at a tool 250 mm long with an 80 mm lateral offset:
    one SMR position leaves the rotations it cannot see; three determine all 21 errors."""
    offsets = {"A": [0.0, 0, -100], "B": [100.0, 0, -60], "C": [0.0, 100, -60]}
    machine = _machine(smr_offsets_mm=offsets)
    truth = VirtualMachine(machine, seed=0)
    tool = np.array([80.0, 0, -250])
    grid = grid_points(machine.travel_min_mm, machine.travel_max_mm, 6)
    chain = Chain.parse(machine.chain)
    true, _ = deviation(chain, grid, tool, truth)
    pivots = propose_tracer_places(machine, 4)
    at_tool = {}
    for name, named in (("one", None), ("three", machine.smr_offsets())):
        result = _tracers(machine, _tracer_rows(machine, truth, pivots, 150, smr_offsets_mm=named))
        fitted, _ = deviation(chain, grid, tool, result.fit.tables.model(""))
        residual = remove_rigid_motion(grid, fitted - true)
        at_tool[name] = float(np.sqrt(np.mean(np.sum(residual**2, axis=1))) * 1e3)
        assert result.instruments is not None
        if name == "three":
            assert result.instruments.undetermined == []
            assert result.instruments.functional_point == "tool point"
            assert np.all(np.isfinite(result.fit.tables.tables["ECZ"].u95))
            assert at_tool[name] < 1.5 * _limit_um(machine, result, tool)
    assert at_tool["three"] < 0.5 * at_tool["one"], at_tool


def test_a_trackers_systematic_errors_are_unknowns_with_their_prior() -> None:
    """Angle errors common to a station's runs (30 urad RMS) and a scale per run (2 ppm):
    as noise they spoil the tables and the U95 claims too much; as unknowns with the machine
    file's prior the residual falls and the U95 covers it."""
    machine = _machine()
    truth = VirtualMachine(machine, ErrorAmplitudes(scale=0.3), seed=0)
    points = grid_and_random_points(machine.travel_min_mm, machine.travel_max_mm, (5, 4, 3), 190, 0)
    tracker = VirtualTracker(np.array([1000.0, 750, -800]), np.array([0.5, -1, 30]), seed=0)
    rows = measure_tracker(
        truth, tracker, points, 2, machine.smr_offset, angle_systematic_urad=30.0, scale_ppm=2.0
    )
    with_prior = machine.model_copy(
        update={"tracker": TrackerUncertainty(angle_systematic_urad=30.0, scale_ppm=2.0)}
    )
    figures = {}
    for name, model in (("as noise", machine), ("as unknowns", with_prior)):
        result = post_stations(
            model, [], instruments=Instruments(trackers=(TrackerFile(rows, "t.csv"),))
        )
        figures[name] = (_at_smr_um(model, result, truth), _limit_um(model, result))
        assert result.instruments is not None
    (station,) = result.instruments.trackers
    assert set(station.scale_ppm) == {0, 1} and len(station.angle_coefficients_urad) == 16
    residual, limit = figures["as unknowns"]
    assert residual < 0.4 * figures["as noise"][0], figures
    assert residual < 1.6 * limit
    assert figures["as noise"][0] > 2.5 * figures["as noise"][1]


def test_a_tracer_scale_per_run_enters_the_u95() -> None:
    """Issue 30: 1 ppm of scale took tracers from 0.41 to 0.91 um with the same residuals.

    The simulated scale is drawn per place and run (sim.instrument_errors): with a
    standard deviation of 2 ppm the four places' draws (-1.7 to +1.8 ppm) show it
    as clearly as the issue's 1 ppm did; with 1 ppm these draws leave 1.3 x the limit.
    """
    machine = _machine()
    truth = VirtualMachine(machine, ErrorAmplitudes(scale=0.3), seed=1)
    rows = _tracer_rows(machine, truth, propose_tracer_places(machine, 4), 150, scale_ppm=2.0)
    with_prior = machine.model_copy(update={"tracer": TracerUncertainty(scale_ppm=2.0)})
    as_noise = _tracers(machine, rows)
    as_unknowns = _tracers(with_prior, rows)
    assert _at_smr_um(machine, as_noise, truth) > 1.5 * _limit_um(machine, as_noise)
    residual = _at_smr_um(with_prior, as_unknowns, truth)
    assert residual < 1.3 * _limit_um(with_prior, as_unknowns)
    assert as_unknowns.instruments is not None
    assert all(place.scale_u95_ppm[0] > 1.0 for place in as_unknowns.instruments.tracers)


def test_the_material_temperature_normalises_to_20_c() -> None:
    """A machine 5 K warm: its scales (11.5 ppm/K) put every point 57 ppm farther from the
    machine's zero; with material_c the tables are the machine's at 20 degC."""
    machine = _machine()
    truth = VirtualMachine(machine, ErrorAmplitudes(scale=0.3), seed=2)
    pivots = propose_tracer_places(machine, 4)
    rows = []
    for i, pivot in enumerate(pivots):
        points = grid_and_random_points(
            machine.travel_min_mm, machine.travel_max_mm, (5, 4, 3), 150, i
        )
        actual, _ = truth.actual_functional_point(points, np.ones_like(points), machine.smr_offset)
        warm = actual + 11.5e-6 * 5.0 * points
        lengths = VirtualTracer(pivot, seed=i).observe(warm, 10.0)
        rows += [
            TracerLength(f"P{i + 1}", 0, k, points[k], float(lengths[k]), material_c=25.0)
            for k in range(len(points))
        ]
    without = [TracerLength(r.station, r.run, r.index, r.machine_mm, r.length_mm) for r in rows]
    normalised = _tracers(machine, rows)
    as_measured = _tracers(machine, without)
    assert (
        _at_smr_um(machine, normalised, truth) < 1.0 < 5.0 < _at_smr_um(machine, as_measured, truth)
    )


def test_a_fit_that_does_not_settle_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    machine = _machine()
    truth = VirtualMachine(machine, seed=0)
    rows = _tracer_rows(machine, truth, propose_tracer_places(machine, 4), 50)
    monkeypatch.setattr(fit_module, "_MAX_ITERATIONS", 1)
    with pytest.raises(GeometryError, match=r"r\.csv: the fit did not settle in 1 iterations"):
        _tracers(machine, rows, knot_spacing_mm=250.0)


def test_tables_beyond_what_a_machine_can_have_are_refused() -> None:
    """A tracker whose lengths are 0.2 % long (a wrong unit factor, a wrong wavelength):
    the tables would hold millimetres; nothing is written."""
    machine = _machine()
    truth = VirtualMachine(machine, seed=0)
    points = grid_and_random_points(machine.travel_min_mm, machine.travel_max_mm, (5, 4, 3), 100, 0)
    tracker = VirtualTracker(np.array([1000.0, 750, -800]), seed=0)
    rows = measure_tracker(truth, tracker, points, 1, machine.smr_offset)
    long = [
        TrackerPoint(r.station, r.run, r.index, r.machine_mm, r.tracker_mm * 1.002) for r in rows
    ]
    with pytest.raises(GeometryError, match="more than a machine can have"):
        post_stations(machine, [], instruments=Instruments(trackers=(TrackerFile(long, "t.csv"),)))
