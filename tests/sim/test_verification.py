"""A verification run after compensation (as left), simulated and posted."""

import numpy as np
import pytest
from cli_helpers import assert_one_line_error, run_cli

from sim.dry_run import DryRunOptions, measured_strokes, simulate_calibration
from xmalign.comp import fit_for
from xmalign.formats.error_tables import read_error_tables
from xmalign.formats.measurements import read_measurements
from xmalign.formats.plan import read_plan
from xmalign.post.compare import grid_points, volumetric_rms_um
from xmalign.post.evaluate import Station, post_stations
from xmalign.rigid_body import Chain, slopes_as_squareness_rad


@pytest.fixture(scope="module")
def verified(tmp_path_factory, reference_machine):
    workdir = tmp_path_factory.mktemp("verified")
    report = simulate_calibration(reference_machine, workdir, DryRunOptions(seed=3, verify=True))
    return report, workdir


def test_the_verification_run_measures_what_the_tables_left(verified, reference_machine):
    report, workdir = verified
    left = report.as_left
    assert left is not None and left.controller == reference_machine.controller
    assert left.volumetric_true_um < 0.9 * report.volumetric_before_um  # the tables did work
    assert left.measurement_error_um < 1.0
    # posted as if nothing had been loaded, the compensated machine is no rigid-body
    # chain any more (its axes still tilt, the tool point does not follow): far off
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


def test_the_verification_confirms_the_squareness_the_tables_were_fitted_to_leave(
    verified, reference_machine
):
    report, workdir = verified
    found_tables = read_error_tables(workdir / "errors.csv")
    found = found_tables.model("").squareness_rad()
    applied = fit_for(reference_machine, found_tables, reference_machine.controller).mean
    predicted = found - slopes_as_squareness_rad(applied.tables)
    left = report.as_left.post.tool_point_squareness_rad()
    largest = int(np.argmax(np.abs(found)))
    assert abs(found[largest]) > 10e-6, found  # a squareness worth taking out
    assert abs(left[largest]) < abs(found[largest])  # the cross tables take out some
    assert np.abs(left - predicted).max() < 3e-6  # what the as-found errors predicted
    # the machine's own squareness, compensation added back, is unchanged
    own = report.as_left.post.fit.tables.model("").squareness_rad()
    assert np.abs(own - found).max() < 3e-6
