"""A verification run after compensation (as left), simulated and posted."""

import numpy as np
import pytest
from cli_helpers import assert_one_line_error, run_cli, run_in_process

from sim.dry_run import DryRunOptions, measured_strokes, simulate_calibration
from xmalign.formats.error_tables import read_error_tables
from xmalign.formats.measurements import read_measurements
from xmalign.formats.plan import read_plan
from xmalign.post.compare import (
    grid_points,
    measured_box_mm,
    tool_point_squareness_rad,
    volumetric_rms_um,
)
from xmalign.post.evaluate import Station, post_stations
from xmalign.rigid_body import Chain


@pytest.fixture(scope="module")
def verified(tmp_path_factory, reference_machine):
    workdir = tmp_path_factory.mktemp("verified")
    report = simulate_calibration(reference_machine, workdir, DryRunOptions(seed=3, verify=True))
    return report, workdir


def test_the_verification_run_measures_what_the_tables_left(verified, reference_machine):
    report, _ = verified
    left = report.as_left
    assert left is not None and left.controller == reference_machine.controller
    assert left.volumetric_true_um < 0.5 * report.volumetric_before_um  # the tables did work
    assert left.measurement_error_um < 1.0


@pytest.fixture(scope="module")
def verified_isg(tmp_path_factory, reference_machine):
    workdir = tmp_path_factory.mktemp("verified-isg")
    machine = reference_machine.model_copy(update={"controller": "isg"})
    options = DryRunOptions(seed=3, verify=True, dialect="iso")  # ISG kernels read DIN 66025
    return simulate_calibration(machine, workdir, options), workdir


def test_a_volumetric_compensation_is_posted_with_what_it_applied(verified_isg, reference_machine):
    report, workdir = verified_isg
    left = report.as_left
    assert left.volumetric_true_um < 0.1 * report.volumetric_before_um
    assert left.measurement_error_um < 1.0
    # ISG shifts the tool point by the full model, tilts times lever arms included: the
    # machine as left is no rigid-body chain, so posted as if nothing had been loaded the
    # fit is far off
    plan = read_plan(workdir / "plan.json")
    rows = read_measurements(workdir / "verification.csv")
    naive = post_stations(reference_machine, [Station(plan, rows, "verification.csv")])
    chain = Chain.parse(reference_machine.chain)
    points = grid_points(*measured_strokes(report.plan))
    off = volumetric_rms_um(chain, points, naive.fit.tables.model(), left.post.tool_point_errors())
    assert off > 3 * left.measurement_error_um


def test_post_compares_as_found_and_as_left(verified, tmp_path):
    _, workdir = verified
    result = run_cli(
        "post",
        *("--plan", str(workdir / "plan.json"), "--data", str(workdir / "measurements.csv")),
        *("--verify-data", str(workdir / "verification.csv")),
        *("--out", str(tmp_path / "errors.csv"), "--report", str(tmp_path / "record.html")),
        timeout=300,
    )
    assert result.returncode == 0, result.stderr
    assert "As found / as left" in result.stdout
    record = (tmp_path / "record.html").read_text()
    assert "As found / as left" in record and "as left" in record


def test_verify_options_need_the_verification_data(verified, tmp_path):
    _, workdir = verified
    for option, value in (("--verify-plan", "plan.json"), ("--verify-controller", "fanuc")):
        result = run_cli(
            "post",
            *("--plan", str(workdir / "plan.json"), "--data", str(workdir / "measurements.csv")),
            *(option, str(workdir / value) if value.endswith(".json") else value),
            "--out",
            str(tmp_path / "errors.csv"),
        )
        assert_one_line_error(result, option, "--verify-data")
        assert not (tmp_path / "errors.csv").exists()


def test_the_cross_tables_square_the_tool_point_and_the_machine_stays_as_it_was(
    verified, reference_machine
):
    report, workdir = verified
    chain = Chain.parse(reference_machine.chain)
    found_tables = read_error_tables(workdir / "errors.csv")
    points = grid_points(*measured_box_mm(found_tables))
    found = tool_point_squareness_rad(chain, points, found_tables.model(""))
    left = tool_point_squareness_rad(chain, points, report.as_left.post.tool_point_errors())
    assert np.abs(found).max() > 10e-6, found  # a squareness worth taking out
    # Sinumerik's cross tables are linear in each axis: no shear is left at the tool point
    assert np.abs(left).max() < 0.15 * np.abs(found).max(), (found, left)
    # the machine's own squareness, compensation added back, is what it was
    own = report.as_left.post.fit.tables.model("").squareness_rad()
    assert np.abs(own - found_tables.model("").squareness_rad()).max() < 3e-6


def test_tool_point_squareness_of_a_pure_squareness_is_that_squareness(reference_machine):
    from xmalign.rigid_body import ErrorTables

    chain = Chain.parse(reference_machine.chain)
    points = grid_points(reference_machine.travel_min_mm, reference_machine.travel_max_mm)
    squareness = {"EC0Y": 12e-6, "EA0Z": -5e-6, "EB0Z": 30e-6}
    model = ErrorTables(squareness=squareness)
    np.testing.assert_allclose(
        tool_point_squareness_rad(chain, points, model), list(squareness.values()), atol=1e-12
    )


def test_post_and_the_dry_run_take_as_left_from_the_one_step(
    verified, reference_machine, tmp_path, monkeypatch
):
    """`post --verify-data` calls the step layer's as_left_step (a spy in its place sees
    the call), and the dry run's as left is what that step gives for its files."""
    import xmalign.cli.post as post_command
    from xmalign import steps
    from xmalign.comp import fit_for

    report, workdir = verified
    calls = []

    def spy(*args, **kwargs):
        calls.append(args[2])
        return steps.as_left_step(*args, **kwargs)

    monkeypatch.setattr(post_command, "as_left_step", spy)
    result = run_in_process(
        "post",
        *("--plan", str(workdir / "plan.json"), "--data", str(workdir / "measurements.csv")),
        *("--verify-data", str(workdir / "verification.csv")),
        *("--out", str(tmp_path / "errors.csv")),
    )
    assert result.returncode == 0, result.stderr
    assert calls == [workdir / "verification.csv"]
    tables = read_error_tables(workdir / "errors.csv")
    applied = fit_for(reference_machine, tables, reference_machine.controller).mean
    plan = read_plan(workdir / "plan.json")
    again = steps.as_left_step(reference_machine, plan, workdir / "verification.csv", applied)
    for name, table in again.fit.tables.tables.items():
        np.testing.assert_allclose(
            report.as_left.post.fit.tables.tables[name].values, table.values, atol=1e-6
        )  # 1 nm: the tables applied here are read back from errors.csv (0.1 nm digits)
