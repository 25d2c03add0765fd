from cli_helpers import assert_one_line_error, run_cli

from xmalign.formats.measurements import read_measurements


def test_dry_run_then_run_sim_on_its_plan(tmp_path):
    out = tmp_path / "dry"
    result = run_cli("dry-run", "--out", str(out), "--seed", "3")
    assert result.returncode == 0, result.stderr
    assert "Dry run against the simulator's truth" in result.stdout
    assert "volumetric" in result.stdout and "on-machine time" in result.stdout
    for name in ("session.json", "pose.json", "plan.json", "measurements.csv", "errors.csv"):
        assert (out / name).exists()
    assert any((out / "comp").iterdir())
    csv_path = tmp_path / "m.csv"
    again = run_cli(
        "run", "--plan", str(out / "plan.json"), "--sim", "--seed", "3", "--out", str(csv_path)
    )
    assert again.returncode == 0, again.stderr
    assert len(read_measurements(csv_path)) == len(read_measurements(out / "measurements.csv"))


def test_run_refuses_bad_invocations(tmp_path):
    assert_one_line_error(run_cli("run", "--plan", "p.json", "--out", "m.csv"), "--sim")
    plan = tmp_path / "plan.json"
    plan.write_text('{"format": "xmalign.plan/7"}')
    assert_one_line_error(
        run_cli("run", "--plan", str(plan), "--sim", "--out", str(tmp_path / "m.csv")),
        "version '7'",
    )
