import json

from cli_helpers import assert_one_line_error, run_cli

from xmalign.formats.pose import read_pose


def test_simulated_identification_prints_pose_and_truth(tmp_path):
    pose_path, session_path = tmp_path / "pose.json", tmp_path / "session.json"
    result = run_cli(
        "identify", "--sim", "--out", str(pose_path), "--session-out", str(session_path)
    )
    assert result.returncode == 0, result.stderr
    assert "truth" in result.stdout and "gamma" in result.stdout
    pose = read_pose(pose_path)
    assert pose.method == "joint" and 3 <= pose.n_alignments <= 6
    again = run_cli("identify", "--input", str(session_path), "--method", "intersection")
    assert again.returncode == 0, again.stderr
    assert "intersection" in again.stdout


def test_simulated_identification_without_session_out_leaves_nothing_behind(tmp_path, monkeypatch):
    """Issue 32: the session went to a temporary folder left behind, and the pose named
    it; now the folder is removed and the pose names the machine file alone."""
    temporary = tmp_path / "tmp"
    temporary.mkdir()
    monkeypatch.setenv("TMPDIR", str(temporary))  # the command's temporary folder
    pose_path = tmp_path / "pose.json"
    result = run_cli("identify", "--sim", "--alignments", "4", "--out", str(pose_path))
    assert result.returncode == 0, result.stderr
    assert list(temporary.iterdir()) == []
    roles = [source["role"] for source in json.loads(pose_path.read_text())["inputs"]]
    assert roles == ["machine"]


def test_malformed_session_is_one_line(tmp_path):
    path = tmp_path / "session.json"
    path.write_text('{"format": "xmalign.identify-session/1", "alignments": [')
    assert_one_line_error(run_cli("identify", "--input", str(path)), str(path), "not valid JSON")


def test_unknown_version_is_one_line(tmp_path):
    path = tmp_path / "session.json"
    path.write_text(json.dumps({"format": "xmalign.identify-session/9", "alignments": []}))
    assert_one_line_error(run_cli("identify", "--input", str(path)), "newer xmalign")


def test_too_few_alignments_is_one_line(tmp_path):
    session = tmp_path / "session.json"
    run_cli("identify", "--sim", "--alignments", "3", "--session-out", str(session))
    data = json.loads(session.read_text())
    data["alignments"] = data["alignments"][:1]
    session.write_text(json.dumps(data))
    assert_one_line_error(run_cli("identify", "--input", str(session)), "at least 2 alignments")


def test_unknown_method_and_missing_input(tmp_path):
    assert_one_line_error(run_cli("identify", "--sim", "--method", "magic"), "magic")
    assert_one_line_error(run_cli("identify"), "--input")
    assert_one_line_error(
        run_cli("identify", "--input", str(tmp_path / "missing.json")), "missing.json"
    )


def test_live_and_uncertainty_options_are_checked_first(tmp_path):
    assert_one_line_error(
        run_cli("identify", "--live", "--config", str(tmp_path / "units.yaml")),
        "--live needs --config UNITS.yaml and --session SESSION.json",
    )
    assert_one_line_error(
        run_cli("identify", "--sim", "--encoder-urad", "-1"),
        "--encoder-urad",
        "the uncertainty must be positive",
    )
