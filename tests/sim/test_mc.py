"""Monte Carlo planning: strategies, trials, the study loop, Dask, and ``xmalign mc``."""

import json
import sys
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor

import numpy as np
import pytest
from cli_helpers import assert_one_line_error, run_cli, run_in_process

from sim.machine import ErrorAmplitudes
from sim.mc import (
    ENVELOPE_SAMPLES,
    Strategy,
    StudySettings,
    TrialSpec,
    calibration_trial,
    identification_trial,
    run_study,
    run_trial,
    strategies,
    trial_seed,
)
from xmalign.errors import InputError


def _spec(machine, seed=3, strategy=None, mode="identification"):
    strategy = strategy or Strategy()
    used = strategy.machine(machine)
    return TrialSpec(mode, used, strategy.identification_mm(used), seed)


def test_strategies_are_every_combination_of_the_varied_decisions(machine):
    chosen = strategies(machine, ["identification", "targets=100:50"])
    assert [s.name for s in chosen] == [
        "identification=designed, targets=100",
        "identification=designed, targets=50",
        "identification=spread, targets=100",
        "identification=spread, targets=50",
    ]
    assert chosen[1].machine(machine).measurement.target_spacing_mm == 50
    assert chosen[1].machine(machine).measurement.runs == machine.measurement.runs
    assert strategies(machine, [""]) == [Strategy()]


def test_launch_position_variants_move_the_guess(machine):
    guess = np.array(machine.launch_unit.position_mm)
    centre = 0.5 * (machine.travel_min_mm + machine.travel_max_mm)
    moved = {
        s.placement: np.array(s.machine(machine).launch_unit.position_mm)
        for s in strategies(machine, ["launch-position"])
    }
    assert np.allclose(moved["guess"], guess)
    assert np.allclose(moved["centre"], [centre[0], centre[1], guess[2]])
    assert np.allclose(moved["opposite"][:2], 2 * centre[:2] - guess[:2])


@pytest.mark.parametrize(
    ("vary", "fragment"),
    [
        (["speed"], "--vary 'speed': unknown"),
        (["alignments=1"], "--vary alignments: '1'"),
        (["targets=abc"], "--vary targets: 'abc'"),
        (["identification=random"], "expected one of designed, spread"),
    ],
)
def test_bad_variations_are_refused(machine, vary, fragment):
    with pytest.raises(InputError, match=fragment):
        strategies(machine, vary)


def test_moving_the_launch_unit_needs_its_position(machine):
    without = machine.model_copy(update={"launch_unit": None})
    with pytest.raises(InputError, match="launch_unit.position_mm"):
        strategies(without, ["launch-position"])


def test_designed_points_lie_inside_the_travel(machine):
    points = Strategy(alignments=6).identification_mm(machine)
    assert points.shape == (6, 3)
    assert np.all(machine.within_travel(points, tol_mm=0.0))


def test_trial_seeds_are_shared_by_strategies_and_differ_by_trial():
    assert trial_seed(0, 5) == trial_seed(0, 5)
    assert len({trial_seed(0, k) for k in range(100)}) == 100
    assert trial_seed(1, 5) != trial_seed(0, 5)


def test_identification_trial_is_reproducible_and_sensible(machine):
    first = identification_trial(_spec(machine))
    again = identification_trial(_spec(machine))
    assert first.values == again.values
    assert 0 < first.values["position_error_um"] < 300
    assert abs(first.values["gamma_error_urad"]) < 300
    assert set(first.envelope_um) == {"X", "Y", "Z", "XY", "YZ", "XZ"}
    assert all(curve.shape == (ENVELOPE_SAMPLES,) for curve in first.envelope_um.values())
    for line in first.envelope_um:
        # the curve's worst point is the planner's 95 % radius behind the margin
        margin = first.values[f"straightness_margin_um:{line}"]
        assert first.envelope_limit_um - first.envelope_um[line].max() == pytest.approx(margin)
    assert first.failure is None


def test_a_trial_identifies_and_plans_through_the_steps(machine, monkeypatch):
    """Issue 32: the trials ran identify and plan_measurement themselves."""
    import sim.dry_run as dry_run
    import sim.mc as mc
    from xmalign import steps

    calls: list[str] = []

    def spy(name):
        real = getattr(steps, name)

        def call(*args, **kwargs):
            calls.append(name)
            return real(*args, **kwargs)

        return call

    monkeypatch.setattr(mc, "plan_session_step", spy("plan_session_step"))
    monkeypatch.setattr(steps, "program_step", spy("program_step"))
    identification_trial(_spec(machine))
    assert calls == ["plan_session_step", "program_step"]
    calls.clear()
    monkeypatch.setattr(dry_run, "station_step", spy("station_step"))
    spec = _spec(machine, seed=5, mode="calibration")
    mc.calibration_trial(TrialSpec(**{**spec.__dict__, "amplitudes": ErrorAmplitudes(scale=0.5)}))
    assert calls == ["station_step", "program_step"]


def test_an_impossible_trial_is_recorded_as_a_failure(machine):
    spec = TrialSpec("identification", machine, np.array([[1000.0, 750.0, -250.0]]), 1)
    outcome = run_trial(spec)
    assert outcome.failure is not None and outcome.failure.startswith("InputError")
    assert outcome.values == {}


def test_calibration_trial_maps_the_residual_the_dry_run_reports(machine):
    spec = _spec(machine, seed=5, mode="calibration")
    spec = TrialSpec(**{**spec.__dict__, "amplitudes": ErrorAmplitudes(scale=0.5)})
    outcome = calibration_trial(spec)
    assert outcome.failure is None
    values = outcome.values
    rms = float(np.sqrt(np.mean(outcome.volumetric_um**2)))
    assert rms == pytest.approx(values["volumetric_after_um"], rel=1e-3)
    assert values["volumetric_after_um"] < values["volumetric_before_um"]
    assert outcome.grid_mm.shape == (outcome.volumetric_um.size, 3)
    assert values["on_machine_min"] > 1.0
    assert {f"measured_margin_um:{line}" for line in outcome.envelope_um} <= set(values)


def test_study_runs_batches_to_the_cap_with_common_seeds(machine):
    same = [Strategy(name="a"), Strategy(name="b")]
    settings = StudySettings(mode="identification", max_trials=5, batch=2)
    seen = []
    with ProcessPoolExecutor(2) as pool:
        results = run_study(machine, same, settings, pool, lambda: seen.append(1))
    assert [r.trials for r in results] == [5, 5]
    assert len(seen) == 10
    assert [len(b["position_error_um"]) for b in results[0].study.batches] == [2, 2, 1]
    first, second = (np.sort(r.study.values("position_error_um")) for r in results)
    assert np.array_equal(first, second)


def test_study_stops_a_strategy_once_it_is_stable(machine, monkeypatch):
    # one alignment-free quantity that never varies is stable after two batches
    from sim import mc

    def constant_trial(spec):
        return mc.TrialOutcome(spec.strategy_index, {"constant": 1.0})

    monkeypatch.setattr(mc, "run_trial", constant_trial)
    settings = StudySettings(mode="identification", max_trials=100, batch=3)
    with ThreadPoolExecutor(1) as pool:
        (result,) = run_study(machine, [Strategy()], settings, pool)
    assert result.stable
    assert result.trials == 6


def test_study_settings_are_checked():
    with pytest.raises(InputError, match="--mode"):
        StudySettings(mode="fast")
    with pytest.raises(InputError, match="--batch"):
        StudySettings(batch=1)


def test_trials_run_on_a_dask_cluster(machine):
    distributed = pytest.importorskip("dask.distributed")
    settings = StudySettings(mode="identification", max_trials=4, batch=2, seed=7)
    with (
        distributed.LocalCluster(
            n_workers=1,
            processes=False,
            protocol="tcp://",
            host="127.0.0.1",
            scheduler_port=0,
            dashboard_address=None,
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        (on_dask,) = run_study(machine, [Strategy()], settings, client.get_executor(pure=False))
    with ThreadPoolExecutor(2) as pool:
        (local,) = run_study(machine, [Strategy()], settings, pool)
    assert on_dask.trials == 4
    assert np.array_equal(
        np.sort(on_dask.study.values("position_error_um")),
        np.sort(local.study.values("position_error_um")),
    )


def test_cli_compares_strategies_and_writes_results_and_plots(tmp_path):
    result = run_cli(
        "mc",
        "--mode",
        "identification",
        "--trials",
        "6",
        "--batch",
        "3",
        "--vary",
        "identification",
        "--workers",
        "2",
        "--tolerance-um",
        "100",
        "--out",
        str(tmp_path),
    )
    assert result.returncode == 0, result.stderr
    assert "identification=spread" in result.stdout
    assert "P(launch position error" in result.stdout
    document = json.loads((tmp_path / "mc.json").read_text())
    assert document["format"] == "xmalign-mc/1"
    assert [s["trials"] for s in document["strategies"]] == [6, 6]
    quantities = document["strategies"][0]["quantities"]
    assert quantities["position_error_um"]["count"] == 6
    for plot in ("histograms.png", "envelopes.png"):
        assert (tmp_path / plot).stat().st_size > 1000
    assert not (tmp_path / "volumetric.png").exists()


def test_cli_runs_on_a_dask_scheduler(tmp_path):
    distributed = pytest.importorskip("dask.distributed")
    with distributed.LocalCluster(
        n_workers=1,
        processes=False,
        protocol="tcp://",
        host="127.0.0.1",
        scheduler_port=0,
        dashboard_address=None,
    ) as cluster:
        result = run_cli(
            "mc",
            "--mode",
            "identification",
            "--trials",
            "4",
            "--batch",
            "2",
            "--scheduler",
            cluster.scheduler_address,
            "--out",
            str(tmp_path),
        )
    assert result.returncode == 0, result.stderr
    document = json.loads((tmp_path / "mc.json").read_text())
    assert document["strategies"][0]["trials"] == 4


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (("--vary", "speed"), "--vary 'speed'"),
        (("--mode", "fast"), "--mode 'fast'"),
        (("--scheduler", "tcp://127.0.0.1:9"), "--scheduler tcp://127.0.0.1:9"),
    ],
)
def test_cli_bad_options_are_one_line(tmp_path, args, fragment):
    result = run_cli("mc", "--trials", "2", "--out", str(tmp_path), *args)
    assert_one_line_error(result, fragment)


@pytest.mark.parametrize(
    ("scheduler", "fragment"),
    [("tcp://127.0.0.1:9", "cannot connect"), ("no-dask", "needs dask.distributed")],
)
def test_a_scheduler_that_cannot_be_used_leaves_no_folder(
    tmp_path, monkeypatch, scheduler, fragment
):
    """Issue 32: ``mc --scheduler`` without dask made --out and left it empty."""
    if scheduler == "no-dask":
        monkeypatch.setitem(sys.modules, "dask.distributed", None)  # import fails as if absent
        scheduler = "tcp://127.0.0.1:9"
    out = tmp_path / "study"
    result = run_in_process("mc", "--trials", "2", "--out", str(out), "--scheduler", scheduler)
    assert_one_line_error(result, "--scheduler", fragment)
    assert not out.exists()
