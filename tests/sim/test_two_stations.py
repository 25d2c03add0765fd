"""Two launch-unit stations end to end on the virtual machine (issue 13, item 2)."""

from __future__ import annotations

import pytest

from sim.dry_run import DryRunOptions
from sim.two_stations import simulate_two_stations
from trajectories.stations import TARGET_COVERAGE
from xmalign.errors import InputError
from xmalign.formats.error_tables import read_error_tables


def test_two_stations_cover_the_travel(reference_machine, tmp_path):
    report = simulate_two_stations(reference_machine, tmp_path, DryRunOptions(seed=2))
    assert min(report.proposal.coverage.values()) >= TARGET_COVERAGE
    second = report.stations[1].plan.plan
    assert [line.id for line in second.lines] == list(report.proposal.line_ids)
    labels = set(report.post.fit.residual_rms)
    assert {"X", "Z", "Z@2"} <= labels
    tables = read_error_tables(tmp_path / "errors.csv")
    assert tables.tables["EZZ"].positions_mm[0] == reference_machine.travel_min_mm[2]
    # issue 13: <= 1.0 um over the whole travel with two stations
    assert report.travel_um <= 1.0


def test_two_stations_call_the_steps_in_the_shop_and_mode_asked_for(
    reference_machine, tmp_path, monkeypatch
):
    """``dry-run --stations 2`` measures each station through the one station step of the
    dry run (identify, program, open, run), posts through the step layer, in the shop
    given, and served as the one-station dry run is: xmalign running its program on a
    LinuxCNC (issue 32: two stations served went through the position file)."""
    import sim.dry_run as dry
    import sim.two_stations as two
    from xmalign import steps
    from xmalign.formats.measurements import load_measurements

    calls: dict[str, list] = {}

    def spy(name, real):
        calls[name] = []

        def call(*args, **kwargs):
            calls[name].append(args)
            return real(*args, **kwargs)

        return call

    for name in ("identify_step", "program_step", "open_measurements_step"):
        monkeypatch.setattr(steps, name, spy(name, getattr(steps, name)))
    monkeypatch.setattr(dry, "station_step", spy("station_step", steps.station_step))
    monkeypatch.setattr(two, "post_step", spy("post_step", steps.post_step))

    def served_here(setup, machine, plan, output):
        _, program = steps.program_gcode(plan, machine, "linuxcnc", "XMALIGN")
        return dry.measure_virtually(setup, plan, program, "linuxcnc", output)

    # served: measure_controlled is called (measured in-process here, the served path has its
    # own tests in tests/sim/test_served_world.py and the CLI's served dry run)
    monkeypatch.setattr(dry, "measure_controlled", spy("measure_controlled", served_here))
    monkeypatch.setattr(dry, "measure_served", spy("measure_served", None))
    options = DryRunOptions(seed=2, shop="reference", served=True)
    simulate_two_stations(reference_machine, tmp_path, options)
    assert {name: len(made) for name, made in calls.items()} == {
        "identify_step": 2,
        "program_step": 2,
        "open_measurements_step": 2,
        "station_step": 2,
        "post_step": 1,
        "measure_controlled": 2,
        "measure_served": 0,
    }
    recorded = load_measurements(tmp_path / "station2-measurements.csv")
    air = [row.environment["air_temp_c"] for row in recorded.rows]
    assert recorded.environment_columns and max(abs(t - 20.0) for t in air) < 0.5  # drifting: 22-25


def test_a_folder_with_an_earlier_stations_file_is_refused_before_anything(
    reference_machine, tmp_path
):
    """An interrupted run's session was deleted without a word (and a later one resumed
    by nobody); now any of the two stations' files refuses the folder, naming it."""
    (tmp_path / "station1-session.json").write_text("the earlier run's alignments\n")
    with pytest.raises(InputError, match="station1-session.json"):
        simulate_two_stations(reference_machine, tmp_path, DryRunOptions(seed=2))
    assert [p.name for p in tmp_path.iterdir()] == ["station1-session.json"]
    assert (tmp_path / "station1-session.json").read_text() == "the earlier run's alignments\n"


def test_a_verification_is_refused_for_two_stations(reference_machine, tmp_path):
    """verify was refused by the command alone: the simulation ignored it."""
    options = DryRunOptions(seed=2, verify=True)
    with pytest.raises(InputError, match="--verify is for one station"):
        simulate_two_stations(reference_machine, tmp_path / "two", options)
    assert not (tmp_path / "two").exists()
