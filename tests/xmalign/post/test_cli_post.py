"""``xmalign post`` and ``comp`` end to end on synthetic files, and their bad-input messages."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from sim.machine import VirtualMachine
from sim.synthetic import SetupDisturbance, measure, six_line_plan
from xmalign.cli import app
from xmalign.comp import WRITERS
from xmalign.errors import InputError
from xmalign.formats.error_tables import read_error_tables
from xmalign.formats.measurements import write_measurements
from xmalign.formats.plan import write_plan
from xmalign.rigid_body import Chain


@pytest.fixture(scope="module")
def files(tmp_path_factory, reference_machine) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("post")
    plan = six_line_plan(reference_machine, 12, runs=2, bidirectional=True)
    rows = measure(
        plan,
        Chain.parse(reference_machine.chain),
        VirtualMachine(reference_machine, seed=4),
        np.random.default_rng(9),
        backlash_mm=[0.003, 0.002, 0.001],
    )
    paths = {"plan": folder / "plan.json", "data": folder / "m.csv", "dir": folder}
    write_plan(paths["plan"], plan)
    write_measurements(paths["data"], rows)
    return paths


def _post(files, *extra: str):
    return CliRunner().invoke(
        app,
        [
            "post",
            "--plan",
            str(files["plan"]),
            "--data",
            str(files["data"]),
            "--out",
            str(files["dir"] / "errors.csv"),
            "--force",  # the tests of this module post to one errors.csv in turn
            *extra,
        ],
    )


def test_post_writes_tables_and_report(files, reference_machine_path):
    result = _post(
        files,
        "--machine",
        str(reference_machine_path),
        "--report",
        str(files["dir"] / "report.html"),
    )
    assert result.exit_code == 0, result.output
    tables = read_error_tables(files["dir"] / "errors.csv")
    assert {"EXX", "EXX+", "EXX-", "ECZ"} <= set(tables.tables)
    assert set(tables.squareness) == {"EC0Y", "EA0Z", "EB0Z"}
    html = (files["dir"] / "report.html").read_text()
    assert html.count("data:image/png;base64") == 4 and "EC0Y" in html


@pytest.mark.parametrize("controller", sorted(WRITERS))
def test_comp_writes_each_controller(files, controller):
    _post(files)
    out = files["dir"] / controller
    result = CliRunner().invoke(
        app,
        [
            "comp",
            "--errors",
            str(files["dir"] / "errors.csv"),
            "--controller",
            controller,
            "--out",
            str(out),
        ],
    )
    assert result.exit_code == 0, result.output
    assert any(out.iterdir())


def test_a_bad_row_is_named_by_its_line(files):
    lines = files["data"].read_text().splitlines()
    lines[7] = lines[7].replace(",+,", ",?,", 1)
    bad = files["dir"] / "bad.csv"
    bad.write_text("\n".join(lines) + "\n")
    result = CliRunner().invoke(
        app,
        [
            "post",
            "--plan",
            str(files["plan"]),
            "--data",
            str(bad),
            "--out",
            str(files["dir"] / "e.csv"),
        ],
    )
    assert isinstance(result.exception, InputError)
    assert "bad.csv: line 8" in str(result.exception)


def test_a_row_of_an_unknown_line_is_refused_with_exit_2(files):
    lines = files["data"].read_text().splitlines()
    first = next(n for n, line in enumerate(lines) if line.startswith("X,"))
    lines[first] = "Q" + lines[first][lines[first].index(",") :]
    bad = files["dir"] / "unknown.csv"
    bad.write_text("\n".join(lines) + "\n")
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "xmalign",
            "post",
            "--plan",
            str(files["plan"]),
            "--data",
            str(bad),
            "--out",
            str(files["dir"] / "e.csv"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2
    assert "line 'Q'" in done.stderr and "Traceback" not in done.stderr


def test_unknown_controller(files):
    _post(files)
    result = CliRunner().invoke(
        app,
        [
            "comp",
            "--errors",
            str(files["dir"] / "errors.csv"),
            "--controller",
            "mazak",
            "--out",
            str(files["dir"] / "x"),
        ],
    )
    assert isinstance(result.exception, InputError) and "mazak" in str(result.exception)


def test_two_stations_are_fitted_together(files, reference_machine):
    """A second --plan/--data pair is used (not silently dropped), with its own setup terms."""
    plan = six_line_plan(reference_machine, 12, runs=1, bidirectional=False)
    plan.lines = [line for line in plan.lines if line.id in ("Z", "YZ", "XZ")]
    rows = measure(
        plan,
        Chain.parse(reference_machine.chain),
        VirtualMachine(reference_machine, seed=4),
        np.random.default_rng(10),
    )
    write_plan(files["dir"] / "plan2.json", plan)
    write_measurements(files["dir"] / "m2.csv", rows)
    result = _post(
        files, "--plan", str(files["dir"] / "plan2.json"), "--data", str(files["dir"] / "m2.csv")
    )
    assert result.exit_code == 0, result.output
    assert "line Z@2" in result.output and "line X@2" not in result.output


def test_unpaired_plan_and_data_are_refused(files):
    result = _post(files, "--plan", str(files["plan"]))
    assert isinstance(result.exception, InputError)
    assert "2 --plan but 1 --data" in str(result.exception)


def test_a_rezeroed_minus_pass_is_reported(files, reference_machine):
    plan = six_line_plan(reference_machine, 10, runs=1, bidirectional=True)
    rows = measure(
        plan,
        Chain.parse(reference_machine.chain),
        VirtualMachine(reference_machine, seed=4),
        np.random.default_rng(11),
        setup=SetupDisturbance(rezero_each_pass=True),
    )
    write_plan(files["dir"] / "plan-rz.json", plan)
    write_measurements(files["dir"] / "m-rz.csv", rows)
    result = CliRunner().invoke(
        app,
        [
            "post",
            "--plan",
            str(files["dir"] / "plan-rz.json"),
            "--data",
            str(files["dir"] / "m-rz.csv"),
            "--out",
            str(files["dir"] / "e-rz.csv"),
        ],
    )
    assert result.exit_code == 0, result.output
    assert "warning:" in result.output and "re-zeroed" in result.output.replace("\n", " ")


def test_verify_plan_alone_is_refused(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "xmalign", "post", "--plan", "p.json", "--data", "m.csv"]
        + ["--out", str(tmp_path / "e.csv"), "--verify-plan", "p.json"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert result.stderr.strip() == (
        "xmalign: error: --verify-plan needs --verify-data (the verification measurement)"
    )
