"""Issue 22's careless-user cases that the bad-input table cannot express: what the
docs promise (a byte-order mark, the README's step-by-step chain, the error-table
columns, a program for other lines, the help texts)."""

from __future__ import annotations

import codecs
import re
import shlex
import shutil
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import run_in_process

from firmware_iface.weather_station import FileEnvironment
from xmalign.calibration import check_program_stop
from xmalign.errors import InputError
from xmalign.formats.error_tables import HEADER, RANGE_COLUMN, read_error_tables
from xmalign.formats.measurements import load_measurements, write_measurements
from xmalign.formats.plan import read_plan

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"


def _with_bom(source: Path, target: Path) -> Path:
    target.write_bytes(codecs.BOM_UTF8 + source.read_bytes())
    return target


def test_a_measurement_csv_with_a_byte_order_mark_is_read(tmp_path):
    """It was refused as "missing column 'line'"; docs/formats.md says a BOM is accepted."""
    from sim.machine import VirtualMachine
    from sim.synthetic import measure, six_line_plan
    from xmalign.machine import default_machine_path, load_machine
    from xmalign.rigid_body import Chain

    machine = load_machine(default_machine_path())
    plan = six_line_plan(machine, 5, runs=1, bidirectional=False)
    truth = VirtualMachine(machine, seed=1)
    rows = measure(plan, Chain.parse(machine.chain), truth, np.random.default_rng(1))
    plain = tmp_path / "m.csv"
    write_measurements(plain, rows)
    with_bom = load_measurements(_with_bom(plain, tmp_path / "bom.csv"))
    assert [r.key() for r in with_bom.rows] == [r.key() for r in load_measurements(plain).rows]


def test_every_example_file_with_a_byte_order_mark_is_read(tmp_path):
    """The error tables (a CSV), plan, pose, session and machine files with a BOM."""
    tables = read_error_tables(_with_bom(EXAMPLES / "errors.csv", tmp_path / "errors.csv"))
    assert set(tables.squareness) == {"EC0Y", "EA0Z", "EB0Z"}
    assert read_plan(_with_bom(EXAMPLES / "plan.json", tmp_path / "plan.json")).lines
    for name in ("pose.json", "session.json", "fyxz.yaml"):
        _with_bom(EXAMPLES / name, tmp_path / name)
    result = run_in_process(
        "program",
        "--pose",
        str(tmp_path / "pose.json"),
        "--machine",
        str(tmp_path / "fyxz.yaml"),
        "--out",
        str(tmp_path / "run.mpf"),
    )
    assert result.returncode == 0, result.stderr
    result = run_in_process("identify", "--input", str(tmp_path / "session.json"))
    assert result.returncode == 0, result.stderr


def test_an_environment_file_with_a_byte_order_mark_is_read(tmp_path):
    path = tmp_path / "air.csv"
    path.write_bytes(codecs.BOM_UTF8 + b"20.5,1013.2,45\n")
    assert FileEnvironment(path).read().air_temp_c == pytest.approx(20.5)


def _readme_chain() -> list[list[str]]:
    """The step-by-step commands of the README's virtual-machine chain."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    block = re.search(r"\n\n((?:    xmalign .*\n)+)", text[text.index("step by step") :])
    assert block is not None, "the README's step-by-step commands are gone"
    return [shlex.split(line)[1:] for line in block.group(1).splitlines()]


def test_the_readmes_step_by_step_identify_writes_the_pose_program_reads(tmp_path, monkeypatch):
    """``identify --sim --seed 4`` wrote no pose, so the next ``program`` failed."""
    identify, program, *_ = _readme_chain()
    assert identify[:1] == ["identify"] and program[:1] == ["program"]
    monkeypatch.chdir(tmp_path)
    result = run_in_process(*identify)
    assert result.returncode == 0, result.stderr
    result = run_in_process(*program)
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "plan.json").exists()


def test_identify_says_when_it_wrote_no_pose(tmp_path):
    shutil.copy(EXAMPLES / "session.json", tmp_path / "session.json")
    result = run_in_process("identify", "--input", str(tmp_path / "session.json"))
    assert result.returncode == 0, result.stderr
    assert "pose not written (give --out pose.json" in " ".join(result.stdout.split())


def test_the_docs_give_the_error_table_the_columns_post_writes():
    text = (ROOT / "docs" / "formats.md").read_text(encoding="utf-8")
    written = ",".join((*HEADER, RANGE_COLUMN))
    assert f"\n    {written}\n" in text
    assert "Six columns" in text


def test_dry_run_help_does_not_speak_of_sim():
    result = run_in_process("dry-run", "--help")
    shop = " ".join(result.stdout[result.stdout.index("--shop") :].split())[:200]
    assert "drifting" in shop and "--sim" not in shop


def test_a_programmed_stop_off_the_plans_line_is_refused():
    """docs/simulator.md: an in-process run refuses a program for other lines at once
    (a six-line program against a plan of line Z ended in "beam lost ... 0 points")."""
    plan = read_plan(EXAMPLES / "plan.json")
    x_line, z_line = (next(line for line in plan.lines if line.id == i) for i in ("X", "Z"))
    x_start = x_line.start_mm - 5.0 * x_line.frame[0]  # a pre-position of line X
    check_program_stop(x_line, x_start)
    with pytest.raises(InputError, match="off the plan's line Z: program and plan do not match"):
        check_program_stop(z_line, x_start)
