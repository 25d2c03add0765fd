from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
from typer.testing import CliRunner

from tests.trajectories.conftest import make_pose
from trajectories.identification_design import (
    _start_points,
    design_identification,
    predicted_pose_covariance,
)
from xmalign.cli import app
from xmalign.formats.plan import read_plan
from xmalign.formats.pose import write_pose

runner = CliRunner()


def test_program_writes_clean_gcode_to_stdout_and_the_plan(tmp_path):
    pose_path, plan_path = tmp_path / "pose.json", tmp_path / "plan.json"
    write_pose(pose_path, make_pose())
    result = runner.invoke(
        app,
        [
            "program",
            "--pose",
            str(pose_path),
            "--plan-out",
            str(plan_path),
            "--dialect",
            "linuxcnc",
        ],
    )
    assert result.exit_code == 0, result.output
    plan = read_plan(plan_path)
    assert [line.id for line in plan.lines] == ["X", "Y", "Z", "XY", "YZ", "XZ"]
    assert plan.line("X").extra["envelope"]["within"] is True
    assert 0 < plan.line("Z").extra["coverage_percent"] <= 100


def test_bad_pose_file_is_one_line_and_exit_2(tmp_path):
    bad = tmp_path / "pose.json"
    bad.write_text(json.dumps({"format": "xmalign.launch-pose/9"}))
    result = subprocess.run(
        [sys.executable, "-m", "xmalign", "program", "--pose", str(bad)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2
    assert result.stdout == ""
    assert result.stderr.strip().count("\n") == 0 and "reads up to /1" in result.stderr


def test_strict_refuses_a_pose_whose_envelope_leaves_the_range(tmp_path):
    pose_path = tmp_path / "pose.json"
    write_pose(pose_path, make_pose(offsets_deg={}))
    lenient = runner.invoke(
        app, ["program", "--pose", str(pose_path), "--out", str(tmp_path / "a.mpf")]
    )
    assert lenient.exit_code == 0 and (tmp_path / "a.mpf").read_text().endswith("M30\n")
    strict = runner.invoke(app, ["program", "--pose", str(pose_path), "--strict"])
    assert strict.exit_code != 0 and "margin" in str(strict.exception)


def test_isg_controller_needs_a_dialect(tmp_path, machine):
    data = machine.model_dump()
    data["controller"] = "isg"
    machine_path = tmp_path / "m.json"
    machine_path.write_text(json.dumps(data))
    pose_path = tmp_path / "pose.json"
    write_pose(pose_path, make_pose())
    result = runner.invoke(
        app, ["program", "--machine", str(machine_path), "--pose", str(pose_path)]
    )
    assert "--dialect" in str(result.exception)


def test_identification_design_beats_its_start_and_stays_feasible(machine):
    design = design_identification(machine, 4)
    assert np.all(machine.within_travel(design.machine_mm, 1e-3))
    start = predicted_pose_covariance(machine, _start_points(machine, 4))
    assert np.linalg.det(design.pose_covariance[:3, :3]) < np.linalg.det(start[:3, :3])
    assert np.all(design.std[:3] < 0.05) and design.std[3] < 50e-6


def test_plan_identify_command_writes_the_positions(tmp_path):
    result = runner.invoke(
        app, ["plan-identify", "--count", "3", "--out", str(tmp_path / "d.json")]
    )
    assert result.exit_code == 0, result.output
    written = json.loads((tmp_path / "d.json").read_text())
    assert written["format"] == "xmalign.identify-design/1"
    assert np.array(written["machine_mm"]).shape == (3, 3)


def test_program_proposes_a_second_station_and_plans_only_the_lines_asked(tmp_path):
    pose_path, plan_path = tmp_path / "pose.json", tmp_path / "plan.json"
    write_pose(pose_path, make_pose())
    first = runner.invoke(app, ["program", "--pose", str(pose_path), "--out", str(tmp_path / "a")])
    assert first.exit_code == 0, first.output
    assert "second station" in first.output and "--lines Z,YZ,XZ" in first.output
    second = runner.invoke(
        app,
        ["program", "--pose", str(pose_path), "--lines", "z, yz", "--plan-out", str(plan_path)],
    )
    assert second.exit_code == 0, second.output
    assert [line.id for line in read_plan(plan_path).lines] == ["Z", "YZ"]
    assert "second station" not in second.output


def test_unknown_lines_are_refused(tmp_path):
    pose_path = tmp_path / "pose.json"
    write_pose(pose_path, make_pose())
    result = runner.invoke(app, ["program", "--pose", str(pose_path), "--lines", "X,Q"])
    assert result.exit_code != 0 and "--lines 'X,Q'" in str(result.exception)


def test_max_length_cuts_every_line_for_a_try_out_and_the_plan_records_it(tmp_path):
    """``--max-length-mm 20``: every line from its end nearest the launch unit, 20 mm
    long; the plan says so (``max_length_mm``), and its program is as short."""
    pose_path, full_path, cut_path = (tmp_path / n for n in ("pose.json", "a.json", "b.json"))
    write_pose(pose_path, make_pose())
    for plan_path, extra in ((full_path, []), (cut_path, ["--max-length-mm", "20"])):
        result = runner.invoke(
            app,
            ["program", "--pose", str(pose_path), "--plan-out", str(plan_path), "--out"]
            + [str(plan_path.with_suffix(".ngc")), "--dialect", "linuxcnc", *extra],
        )
        assert result.exit_code == 0, result.output
    full, cut = read_plan(full_path), read_plan(cut_path)
    assert json.loads(cut_path.read_text())["max_length_mm"] == 20.0
    assert "max_length_mm" not in json.loads(full_path.read_text())
    for long, short in zip(full.lines, cut.lines, strict=True):
        assert long.id == short.id and long.targets_mm[-1] > 100.0
        assert 0.0 < short.targets_mm[-1] <= 20.0 and short.targets_mm[0] == 0.0
        np.testing.assert_allclose(short.start_mm, long.start_mm)
        assert np.linalg.norm(short.end_mm - short.start_mm) <= 20.0 + 1e-9


def test_max_length_must_be_positive(tmp_path):
    pose_path = tmp_path / "pose.json"
    write_pose(pose_path, make_pose())
    result = subprocess.run(
        [sys.executable, "-m", "xmalign", "program", "--pose", str(pose_path)]
        + ["--max-length-mm", "0"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2 and result.stdout == ""
    assert result.stderr.strip().count("\n") == 0 and "--max-length-mm" in result.stderr
