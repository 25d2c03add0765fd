"""The environment recorded on every row by a run, and compensated by post."""

import subprocess
import sys

import numpy as np
import pytest

from sim.dry_run import measure_virtually, virtual_setup
from sim.environment import ShopClimate, attach_shop
from trajectories.gcode import DIALECTS
from trajectories.gcode.program import write_program
from xmalign.calibration import open_run_output
from xmalign.environment import DRIFT_RUN, EnvironmentMonitor
from xmalign.errors import InputError
from xmalign.formats.measurements import (
    FLAGS_COLUMN,
    load_measurements,
    read_measurements,
    write_measurements,
)
from xmalign.formats.plan import read_plan
from xmalign.post.evaluate import post_process

AIR = ("air_temp_c", "air_pressure_hpa", "air_humidity_percent", "material_temp_c")


@pytest.fixture(scope="module")
def drifting(dry_run_of_seed):
    return dry_run_of_seed(3, "drifting")


def test_every_row_records_the_drifting_shop(drifting):
    _, workdir = drifting
    recorded = load_measurements(workdir / "measurements.csv")
    assert set(AIR) | {FLAGS_COLUMN} <= set(recorded.columns)
    air = np.array([row.environment["air_temp_c"] for row in recorded.rows])
    assert air[0] < 23.0 and air[-1] > air[0] + 0.5  # the shop warms during the run
    assert all(row.environment_flags == "" for row in recorded.rows)


def test_post_compensates_the_air_and_the_material(drifting, reference_machine):
    report, workdir = drifting
    # fails when post ignores the environment columns: the uncompensated fit is far off
    assert report.volumetric_after_um < 1.0
    assert report.volumetric_uncompensated_um > 10 * report.volumetric_after_um
    plan = read_plan(workdir / "plan.json")
    rows = read_measurements(workdir / "measurements.csv")
    result = post_process(reference_machine, plan, rows, "measurements.csv")
    assert result.compensation[0] is not None
    assert "air compensated" in result.notes[0]
    assert set(result.compensation[0].environment) == {line.id for line in plan.lines}


def _short_plan(workdir, machine):
    plan = read_plan(workdir / "plan.json")
    plan.lines = plan.lines[:1]
    return plan, write_program(plan, machine, DIALECTS["linuxcnc"]())


class _FailingAfter:
    """A station that stops answering after ``reads`` readings."""

    def __init__(self, station, reads):
        self.station = station
        self.reads = reads

    def read(self):
        self.reads -= 1
        if self.reads < 0:
            self.station.answering = False
        return self.station.read()


def test_a_station_that_stops_answering_never_loses_a_point(drifting, reference_machine, tmp_path):
    _, workdir = drifting
    plan, program = _short_plan(workdir, reference_machine)
    setup = virtual_setup(reference_machine, 3)
    station = _FailingAfter(attach_shop(setup.world, ShopClimate.drifting(), 3), reads=5)
    path = tmp_path / "m.csv"
    with open_run_output(path, plan, False, environment=EnvironmentMonitor(station)) as output:
        run = measure_virtually(setup, plan, program, "linuxcnc", output)
    rows = read_measurements(path)
    assert len(rows) == run.statistics.points > 5
    held = [row for row in rows if row.environment_flags]
    assert len(held) == len(rows) - 4  # prime + 4 fresh samples, then held
    assert "not answering" in held[0].environment_flags
    assert all(row.environment == held[0].environment for row in held)


def test_a_sensor_out_of_range_keeps_the_last_good_value(drifting, reference_machine, tmp_path):
    _, workdir = drifting
    plan, program = _short_plan(workdir, reference_machine)
    setup = virtual_setup(reference_machine, 3)
    station = attach_shop(setup.world, ShopClimate.drifting(), 3)
    monitor = EnvironmentMonitor(station)
    path = tmp_path / "m.csv"
    with open_run_output(path, plan, False, environment=monitor) as output:
        station.failed.add("air_humidity_percent")
        measure_virtually(setup, plan, program, "linuxcnc", output)
    rows = read_measurements(path)
    assert all("air_humidity_percent held" in row.environment_flags for row in rows)
    assert len({row.environment["air_humidity_percent"] for row in rows}) == 1
    assert len({row.environment["air_temp_c"] for row in rows}) > 1


def test_a_resume_keeps_the_environment_columns(drifting, reference_machine, tmp_path):
    _, workdir = drifting
    plan, program = _short_plan(workdir, reference_machine)
    rows = read_measurements(workdir / "measurements.csv")
    partial = tmp_path / "partial.csv"
    write_measurements(partial, [row for row in rows if row.line == plan.lines[0].id][:7])
    with pytest.raises(InputError, match="recorded with the environment"):
        open_run_output(partial, plan, True)
    setup = virtual_setup(reference_machine, 3)
    monitor = EnvironmentMonitor(attach_shop(setup.world, ShopClimate.drifting(), 3))
    with open_run_output(partial, plan, True, environment=monitor) as output:
        measure_virtually(setup, plan, program, "linuxcnc", output)
    resumed = read_measurements(partial)
    assert len(resumed) == len([row for row in rows if row.line == plan.lines[0].id])
    assert all(set(AIR) <= set(row.environment) for row in resumed)


def test_a_first_reading_that_is_incomplete_creates_no_file(reference_machine, tmp_path, drifting):
    _, workdir = drifting
    plan, _ = _short_plan(workdir, reference_machine)
    setup = virtual_setup(reference_machine, 3)
    station = attach_shop(setup.world, ShopClimate.drifting(), 3)
    station.failed.add("air_temp_c")
    with pytest.raises(InputError, match="air_temp_c"):
        open_run_output(tmp_path / "m.csv", plan, False, environment=EnvironmentMonitor(station))
    assert not (tmp_path / "m.csv").exists()


def test_flags_with_commas_round_trip(tmp_path, drifting):
    _, workdir = drifting
    rows = read_measurements(workdir / "measurements.csv")[:3]
    from dataclasses import replace

    flagged = [replace(rows[0], environment_flags='air_temp_c held: station "A", no answer')]
    write_measurements(tmp_path / "m.csv", flagged + rows[1:])
    again = read_measurements(tmp_path / "m.csv")
    assert again[0].environment_flags == flagged[0].environment_flags
    assert again[1].environment == rows[1].environment


def test_post_prints_the_compensation_and_writes_the_record(drifting, tmp_path):
    _, workdir = drifting
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "xmalign",
            "post",
            *("--plan", str(workdir / "plan.json"), "--data", str(workdir / "measurements.csv")),
            *("--out", str(tmp_path / "errors.csv"), "--report", str(tmp_path / "record.html")),
            *("--operator", "A. Tester", "--vdi3441"),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    assert "air compensated (modified Edlén), dead path included" in done.stdout
    record = (tmp_path / "record.html").read_text()
    assert "A. Tester" in record and "VDI/DGQ 3441" in record
    assert "No environment was recorded" not in record


def test_each_line_ends_with_its_drift_check_and_post_reports_it(drifting, reference_machine):
    _, workdir = drifting
    plan = read_plan(workdir / "plan.json")
    rows = read_measurements(workdir / "measurements.csv")
    for line in plan.lines:
        own = [row for row in rows if row.line == line.id]
        checks = [row for row in own if row.run == DRIFT_RUN]
        assert len(checks) == 1 and own[-1] is checks[0]  # once, after the last run
        assert (checks[0].direction, checks[0].index) == ("+", 0)
    result = post_process(reference_machine, plan, rows, "measurements.csv")
    drift = {check.line_id: check.drift_um for check in result.compensation[0].drift}
    assert set(drift) == {line.id for line in plan.lines}
    # compensated, the shop's 1.5 K warming leaves about a micrometre at the first target
    assert max(abs(value) for value in drift.values()) < 3.0
    assert not result.warnings or all("drift" not in w for w in result.warnings)
    thermal = reference_machine.thermal.model_copy(update={"drift_limit_um": 0.01})
    strict = reference_machine.model_copy(update={"thermal": thermal})
    warned = post_process(strict, plan, rows, "measurements.csv")
    assert sum("drift" in w for w in warned.warnings) == len(plan.lines)
