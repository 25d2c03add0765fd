import json
import re
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from cli_helpers import assert_one_line_error, run_cli, run_in_process

from xmalign import __version__
from xmalign.calibration import capture_sequence
from xmalign.formats.measurements import read_measurements
from xmalign.formats.plan import read_plan


def test_dry_run_then_run_sim_on_its_plan(tmp_path):
    out = tmp_path / "dry"
    result = run_cli("dry-run", "--out", str(out), "--seed", "3", "--in-process")
    assert result.returncode == 0, result.stderr
    assert "Dry run against the simulator's truth" in result.stdout
    assert "volumetric" in result.stdout and "on-machine time" in result.stdout
    for name in ("session.json", "pose.json", "plan.json", "measurements.csv", "errors.csv"):
        assert (out / name).exists()
    assert any((out / "comp").iterdir())
    csv_path = tmp_path / "m.csv"
    again = run_cli(
        "run", "--plan", str(out / "plan.json"), "--sim", "--seed", "3", "--out", str(csv_path),
        "--in-process",
    )  # fmt: skip
    assert again.returncode == 0, again.stderr
    assert len(read_measurements(csv_path)) == len(read_measurements(out / "measurements.csv"))


def test_run_refuses_bad_invocations(tmp_path):
    assert_one_line_error(run_cli("run", "--plan", "p.json", "--out", "m.csv"), "--sim")
    plan = tmp_path / "plan.json"
    plan.write_text('{"format": "xmalign.plan/7"}')
    assert_one_line_error(
        run_cli("run", "--plan", str(plan), "--sim", "--out", str(tmp_path / "m.csv")),
        "format xmalign.plan/7, this one reads up to /1",
    )


@pytest.fixture(scope="module")
def dry(dry_run_of_seed):
    """A dry run's folder: its plan, and its measurements as an uninterrupted run (seed 3)."""
    return dry_run_of_seed(3, "dry")[1]


def _run_sim(dry, out, *extra):
    """``run --sim --in-process`` on the dry run's plan (served: tests/sim/test_served_world.py)."""
    return run_in_process(
        "run", "--plan", str(dry / "plan.json"), "--sim", "--seed", "3", "--out", str(out),
        "--in-process", *extra,
    )  # fmt: skip


def _data_rows(path):
    lines = path.read_bytes().split(b"\n")
    return [line for line in lines if line and not line.startswith((b"#", b"line,"))]


def test_run_never_replaces_measurements(dry, tmp_path):
    existing = tmp_path / "m.csv"
    shutil.copy(dry / "measurements.csv", existing)
    before = existing.read_bytes()
    refusals = [
        _run_sim(dry, existing),
        run_in_process(
            "run",
            "--plan",
            str(dry / "plan.json"),
            "--config",
            "units.yaml",
            "--out",
            str(existing),
        ),
    ]
    for result in refusals:
        assert_one_line_error(result, str(existing), "never replaced", "--resume", "another --out")
    assert existing.read_bytes() == before
    assert_one_line_error(_run_sim(dry, tmp_path), str(tmp_path), "is a folder")
    assert_one_line_error(_run_sim(dry, tmp_path / "new.csv", "--resume"), "does not exist yet")
    assert_one_line_error(_run_sim(dry, tmp_path / "n.csv", "--seed", "-5"), "--seed: -5")
    assert not (tmp_path / "n.csv").exists()


def _first_row(change):
    """Apply ``change`` to the fields of the first data row (line 9: after the history
    preamble, the header, the run's start and the X setup)."""

    def damage(text):
        lines = text.split("\n")
        lines[8] = ",".join(change(lines[8].split(",")))
        return "\n".join(lines)

    return damage


BAD_RESUMES = [
    (
        "duplicate",
        lambda text: text + text.splitlines()[-1] + "\n",
        "line 404: line XZ run 0 direction + index 0 is recorded twice (first at line 403)",
    ),
    ("nan", _first_row(lambda f: [*f[:8], "nan", *f[9:]]), "line 9: linear_um is nan"),
    ("1e12 um", _first_row(lambda f: [*f[:9], "1e12", *f[10:]]), "line 9: straightness 1e+12"),
    ("latin-1", lambda text: text.replace("X,1,+,1,", "\u00c9,1,+,1,", 1), "line 10: not UTF-8"),
    (
        "another plan",
        lambda text: text.replace("plan_identity=", "plan_identity=0", 1),
        "another plan",
    ),
    (
        "not this plan",
        lambda text: _first_row(lambda f: [*f[:5], "5.0", *f[6:]])(
            text.replace("plan_identity", "x")
        ),
        "line X run 1 index 0 is not a point of this plan",
    ),
]


@pytest.mark.parametrize(
    "damage, message", [c[1:] for c in BAD_RESUMES], ids=[c[0] for c in BAD_RESUMES]
)
def test_a_resume_refuses_a_damaged_or_foreign_file_and_leaves_it_untouched(
    dry, tmp_path, damage, message
):
    path = tmp_path / "m.csv"
    text = damage((dry / "measurements.csv").read_text())
    path.write_bytes(text.encode("latin-1"))
    before = path.read_bytes()
    assert_one_line_error(_run_sim(dry, path, "--resume"), str(path), message)
    assert path.read_bytes() == before


def test_ctrl_c_keeps_every_saved_point_and_says_how_to_go_on(dry, tmp_path):
    out = tmp_path / "m.csv"
    process = _start(dry, out)
    _wait_for_rows(process, out, 30)
    process.send_signal(signal.SIGINT)
    _, stderr = process.communicate(timeout=60)
    saved = len(read_measurements(out))
    assert process.returncode == 130, stderr
    assert stderr.strip().splitlines() == [
        f"xmalign: stopped: {saved} points kept in {out}; go on with --resume"
    ]
    resumed = _run_sim(dry, out, "--resume")
    assert resumed.returncode == 0, resumed.stderr
    total = len(read_measurements(dry / "measurements.csv"))
    assert f"{total - saved} points captured; {total} points in {out}" in resumed.stdout


def _start(dry, out, *extra):
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "xmalign",
            "run",
            "--plan",
            str(dry / "plan.json"),
            "--sim",
            "--seed",
            "3",
            "--out",
            str(out),
            "--in-process",
            *extra,
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        stdin=subprocess.DEVNULL,
        text=True,
    )


def _wait_for_rows(process, out, count):
    """Poll the file until it holds ``count`` rows or the process ends."""
    while process.poll() is None:
        if out.exists() and len(_data_rows(out)) >= count:
            return
        time.sleep(0.002)


def test_killed_at_random_points_and_resumed_no_point_is_lost_or_repeated(dry, tmp_path):
    """SIGKILL (no clean-up at all) at seeded random points, half of them with a torn last row."""
    rng = np.random.default_rng(7)
    out = tmp_path / "m.csv"
    expected = sorted(row.key() for row in read_measurements(dry / "measurements.csv"))
    kills = torn = 0
    just_torn = False
    for _ in range(20):
        saved = len(_data_rows(out)) if out.exists() else 0
        process = _start(dry, out, *(["--resume"] if out.exists() else []))
        _wait_for_rows(process, out, saved + int(rng.integers(40, 150)))
        if process.poll() is None:
            process.kill()
            kills += 1
        _, stderr = process.communicate(timeout=60)
        assert not just_torn or "was cut short" in stderr, stderr
        just_torn = False
        if process.returncode == 0:
            break
        assert process.returncode == -signal.SIGKILL, stderr
        if rng.random() < 0.5:  # power loss in the middle of writing the last row
            data = out.read_bytes()
            last = data.rstrip(b"\n").rsplit(b"\n", 1)[1]
            if not last.startswith(b"#"):
                out.write_bytes(data[: len(data) - 1 - int(rng.integers(1, len(last)))])
                torn += 1
                just_torn = True
    assert process.returncode == 0, stderr
    assert kills >= 3 and torn >= 1
    rows = read_measurements(out)
    assert len(_data_rows(out)) == len(rows) == len(expected)
    assert sorted(row.key() for row in rows) == expected
    assert any(row.segment > 0 for row in rows)  # a new process re-aligned the units


def test_post_refuses_measurements_recorded_for_another_plan(dry, tmp_path):
    plan = json.loads((dry / "plan.json").read_text())
    plan["lines"][0]["dwell_s"] += 1.0
    other = tmp_path / "other-plan.json"
    other.write_text(json.dumps(plan))
    result = run_in_process(
        "post",
        "--plan",
        str(other),
        "--data",
        str(dry / "measurements.csv"),
        "--out",
        str(tmp_path / "e.csv"),
    )
    assert_one_line_error(result, "measurements.csv was recorded for another plan")
    assert not (tmp_path / "e.csv").exists()


def test_version_and_flags_in_help():
    assert run_in_process("--version").stdout.strip() == f"xmalign {__version__}"
    help_text = run_in_process("run", "--help").stdout
    assert "--sim " in help_text and "--resume " in help_text and "<bool>" not in help_text


def test_run_and_post_refuse_a_plan_made_for_another_machine(dry, tmp_path, reference_machine_path):
    other = tmp_path / "other.yaml"
    text = reference_machine_path.read_text()
    other.write_text(text.replace("X: [0, 2000]", "X: [0, 2100]"))
    plan = str(dry / "plan.json")
    for command in (
        ("run", "--plan", plan, "--sim", "--out", str(tmp_path / "m.csv")),
        (
            "post",
            "--plan",
            plan,
            "--data",
            str(dry / "measurements.csv"),
            "--out",
            str(tmp_path / "e.csv"),
        ),
    ):
        result = run_in_process(*command, "--machine", str(other))
        assert_one_line_error(
            result, "plan.json was made for machine 'Example FYXZ gantry mill'", str(other)
        )
    assert not (tmp_path / "m.csv").exists() and not (tmp_path / "e.csv").exists()
    renamed = tmp_path / "renamed.json"
    renamed.write_text((dry / "plan.json").read_text().replace("Example FYXZ", "Another"))
    assert_one_line_error(
        run_in_process(
            "post",
            "--plan",
            str(renamed),
            "--data",
            str(dry / "measurements.csv"),
            "--out",
            "e.csv",
        ),
        "made for machine 'Another gantry mill'",
        "not for the reference machine",
    )


def test_program_finds_pose_json_in_the_working_folder(dry, tmp_path):
    missing = run_cli("program", cwd=tmp_path)
    assert_one_line_error(
        missing, "pose.json: cannot read: no such file", "xmalign identify", "--pose"
    )
    shutil.copy(dry / "pose.json", tmp_path / "pose.json")
    result = run_cli("program", "--plan-out", "plan.json", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert result.stdout.count("\n") > 100 and (tmp_path / "plan.json").exists()


def test_ctrl_c_in_a_dry_run_says_how_to_finish_the_run(tmp_path):
    folder = tmp_path / "dry"
    process = subprocess.Popen(
        [sys.executable, "-m", "xmalign", "dry-run", "--seed", "3", "--out", str(folder)]
        + ["--in-process"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        stdin=subprocess.DEVNULL,
        text=True,
    )
    _wait_for_rows(process, folder / "measurements.csv", 20)
    process.send_signal(signal.SIGINT)
    _, stderr = process.communicate(timeout=60)
    assert process.returncode == 130, stderr
    (line,) = stderr.strip().splitlines()
    csv_path = folder / "measurements.csv"
    saved = len(read_measurements(csv_path))
    assert line.startswith(
        f"xmalign: stopped: {saved} points kept in {csv_path}; go on with --resume ("
    )
    command = line[line.index("(xmalign ") + len("(xmalign ") : -1].split()
    finished = run_in_process(*command)
    assert finished.returncode == 0, finished.stderr
    plan = read_plan(folder / "plan.json")
    assert len(read_measurements(csv_path)) == sum(
        1 for line in plan.lines for _ in capture_sequence(line)
    )
    assert_one_line_error(
        run_in_process("dry-run", "--out", str(folder)), "already holds a dry run"
    )
    assert_one_line_error(
        run_in_process("dry-run", "--seed", "-5", "--out", str(tmp_path / "x")), "--seed: -5"
    )


BAD_OPTIONS = [
    (["--program", "missing.nc"], "missing.nc: cannot read G-code program"),
    (["--program", "bad.nc"], "bad.nc: G-code program is not UTF-8 text"),
    (["--program", "."], "cannot read G-code program (Is a directory)"),
    (["--dialect", "klingon"], "--dialect 'klingon' is not known"),
    (["--config", "units.yaml"], "give either --sim or --config"),
    (["--seed", "-5"], "option --seed: -5 must be 0 or more"),
]


@pytest.mark.parametrize("options, message", BAD_OPTIONS, ids=[o[0][0] for o in BAD_OPTIONS])
def test_bad_run_options_are_one_line_and_create_no_file(
    dry, tmp_path, monkeypatch, options, message
):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "bad.nc").write_bytes(b"G1 X\xff\n")
    assert_one_line_error(_run_sim(dry, tmp_path / "m.csv", *options), message)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.nc"]


def test_dry_run_with_two_stations_reports_both_stations_and_the_residuals(tmp_path):
    out = tmp_path / "two"
    result = run_cli("dry-run", "--stations", "2", "--in-process", "--out", str(out), "--seed", "2")
    assert result.returncode == 0, result.stderr
    text = " ".join(result.stdout.split())
    assert "second station: launch cp at [" in text
    assert re.search(r"station 1: on-machine time \d+\.\d min \(lines X Y Z XY YZ XZ\)", text)
    assert re.search(r"station 2: on-machine time \d+\.\d min \(lines Z YZ XZ\)", text)
    strokes, travel = (
        float(v)
        for v in re.search(r"([\d.]+) um over the measured strokes, ([\d.]+) um", text).groups()
    )
    assert 0 < strokes < 1.0 and 0 < travel < 1.5
    for name in ("station1-plan.json", "station2-measurements.csv", "errors.csv"):
        assert (out / name).exists()
    again = run_cli("dry-run", "--stations", "2", "--out", str(out), "--seed", "2")
    assert_one_line_error(again, str(out))


def test_run_writes_a_timestamped_log_file(dry, tmp_path):
    log = tmp_path / "wire.log"
    result = _run_sim(dry, tmp_path / "m.csv", "--log-file", str(log))
    assert result.returncode == 0, result.stderr
    lines = log.read_text().splitlines()
    assert lines, "the log file is empty"
    assert all(re.match(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z ", line) for line in lines)


def test_run_sim_refuses_an_unknown_shop_before_creating_the_file(dry, tmp_path):
    out = tmp_path / "m.csv"
    assert_one_line_error(_run_sim(dry, out, "--shop", "cellar"), "--shop: 'cellar' is not one")
    assert not out.exists()
