"""Every bad input and careless command: one line naming the file, exit 2, nothing lost.

The table lives in tests/xmalign/bad_input_cases.py (also tallied by
tests/benchmarks/bench_bad_input.py). Most cases run in-process; a few run
the real command in a fresh interpreter.
"""

from __future__ import annotations

import errno
import os
import shutil
from pathlib import Path

import pytest
from bad_input_cases import CASES, ROOT, Case, hashes, prepare, run_case, run_main, verdict
from cli_helpers import assert_one_line_error, run_cli


def test_there_are_at_least_a_hundred_cases() -> None:
    assert len(CASES) >= 100
    assert len({case.id for case in CASES}) == len(CASES)


@pytest.mark.parametrize("case", CASES, ids=lambda case: case.id)
def test_bad_input_is_one_line_and_loses_nothing(
    case: Case, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    outcome = run_case(case, tmp_path, monkeypatch)
    assert not outcome.traceback, outcome.traceback
    assert outcome.code == case.code, outcome.stderr_lines
    assert len(outcome.stderr_lines) == 1, outcome.stderr_lines
    line = outcome.stderr_lines[0]
    assert line.startswith("xmalign: "), line
    for fragment in case.fragments:
        assert fragment in line, line
    assert outcome.damaged == [], f"changed: {outcome.damaged}"
    assert outcome.leftovers == [], f"temporary files left: {outcome.leftovers}"
    assert verdict(case, outcome) == "clean"


@pytest.mark.parametrize(
    "argv",
    [
        ("comp", "--errors", "errors.csv", "--out", "comp", "--machine", "fyxz.yaml", "--force"),
        ("identify", "--input", "session.json", "--out", "pose-new.json"),
        ("program", "--pose", "pose.json", "--out", "run.mpf", "--plan-out", "plan-new.json"),
    ],
    ids=lambda argv: argv[0],
)
def test_the_undamaged_files_are_accepted(
    argv: tuple[str, ...], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The cases differ from a working command only by their damage."""
    prepare(tmp_path)
    monkeypatch.chdir(tmp_path)
    code, stderr, escaped = run_main(argv)
    assert (code, escaped) == (0, ""), stderr


def test_outputs_get_the_umask_mode_not_0600(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    prepare(tmp_path)
    monkeypatch.chdir(tmp_path)
    previous = os.umask(0o027)
    try:
        code, stderr, _ = run_main(("comp", "--errors", "errors.csv", "--out", "comp-new"))
        assert code == 0, stderr
        code, stderr, _ = run_main(("identify", "--input", "session.json", "--out", "p.json"))
        assert code == 0, stderr
    finally:
        os.umask(previous)
    for path in [tmp_path / "p.json", *(tmp_path / "comp-new").iterdir()]:
        assert path.stat().st_mode & 0o777 == 0o640, path


def test_comp_replaces_all_controller_files_or_none(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The disk fills up while the second of Sinumerik's two files is written."""
    prepare(tmp_path)
    monkeypatch.chdir(tmp_path)
    synced: list[int] = []
    real_fsync = os.fsync

    def fsync(fd: int) -> None:
        synced.append(fd)
        if len(synced) == 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    code, stderr, _ = run_main(("comp", "--errors", "errors.csv", "--out", "comp", "--force"))
    assert code == 2 and "disk full" in stderr
    assert [p.name for p in (tmp_path / "comp").iterdir()] == ["NC_CEC.INI"]
    assert (tmp_path / "comp" / "NC_CEC.INI").read_text() == "old table\n"


# -- the real command, in a fresh interpreter (a representative few) ------------------------


def _folder(tmp_path: Path) -> Path:
    prepare(tmp_path)
    return tmp_path


def test_cli_nan_in_error_tables_writes_no_controller_file(tmp_path: Path) -> None:
    folder = _folder(tmp_path)
    text = (folder / "errors.csv").read_text()
    (folder / "errors.csv").write_text(text.replace("EXX,352.220,-8.7083", "EXX,352.220,nan"))
    before = hashes(folder)
    result = run_cli("comp", "--errors", "errors.csv", "--out", "out", cwd=folder)
    assert_one_line_error(result, "errors.csv", "line 3", "not a finite number")
    assert not (folder / "out").exists() and hashes(folder) == before


def test_cli_post_refuses_to_replace_its_data(tmp_path: Path) -> None:
    folder = _folder(tmp_path)
    before = hashes(folder)
    result = run_cli("post", "--plan", "plan.json", "--data", "m.csv", "--out", "m.csv", cwd=folder)
    assert_one_line_error(result, "m.csv", "--data")
    assert hashes(folder) == before


def test_cli_infinity_in_the_pose(tmp_path: Path) -> None:
    folder = _folder(tmp_path)
    text = (folder / "pose.json").read_text()
    (folder / "pose.json").write_text(
        text.replace('"gamma_deg": -67', '"gamma_deg": Infinity,"x":-67')
    )
    result = run_cli("program", "--pose", "pose.json", "--out", "run.mpf", cwd=folder)
    assert_one_line_error(result, "pose.json", "gamma_deg", "not a finite number")
    assert not (folder / "run.mpf").exists()


def test_cli_dry_run_negative_seed() -> None:
    assert_one_line_error(run_cli("dry-run", "--seed", "-5"), "--seed")


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_cli_read_only_folder_keeps_the_old_file(tmp_path: Path) -> None:
    folder = _folder(tmp_path)
    out = folder / "locked"
    out.mkdir()
    shutil.copy(ROOT / "examples" / "pose.json", out / "pose.json")
    before = hashes(folder)
    out.chmod(0o555)
    try:
        result = run_cli(
            "identify", "--input", "session.json", "--out", "locked/pose.json", cwd=folder
        )
    finally:
        out.chmod(0o755)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "locked/pose.json" in result.stderr and "permission denied" in result.stderr
    assert hashes(folder) == before
