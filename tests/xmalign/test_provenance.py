"""Files carry their history; older versions are read, newer ones refused (issue 23, item 2).

tests/data/v1/ holds files as xmalign wrote them before they carried history (a dry
run of seed 0 and ``plan-identify`` / ``mc`` of the reference machine): the version 1
samples every reader must keep reading.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from tests.cli_helpers import assert_one_line_error, run_cli
from xmalign.errors import FormatError, InputError
from xmalign.formats.error_tables import read_error_tables, write_error_tables
from xmalign.formats.measurements import (
    MeasurementRow,
    load_measurements,
    plan_sha256,
    write_measurements,
)
from xmalign.formats.plan import read_plan
from xmalign.formats.pose import read_pose
from xmalign.formats.provenance import FileSource, csv_preamble, read_csv_preamble
from xmalign.formats.session import read_session
from xmalign.formats.studies import read_design, read_study
from xmalign.machine import load_machine, parse_machine
from xmalign.steps import post_step

V1 = Path(__file__).resolve().parents[1] / "data" / "v1"
ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def dry_run(dry_run_of_seed) -> Path:
    return dry_run_of_seed(3, "provenance")[1]


def test_version_1_files_are_read_as_they_are():
    tables = read_error_tables(V1 / "errors.csv")
    assert tables.history is not None and tables.history.version == 1 and tables.machine is None
    assert len(tables.tables) >= 18
    recorded = load_measurements(V1 / "measurements.csv")
    assert recorded.history is not None and recorded.history.version == 1
    assert recorded.rows and all(row.time_s is None for row in recorded.rows)
    plan = read_plan(V1 / "plan.json")
    assert recorded.plan_sha256 == plan_sha256(plan)  # the identity did not change
    assert plan.history is not None and plan.history.software is None
    assert read_pose(V1 / "pose.json").n_alignments > 0
    assert read_session(V1 / "session.json").alignments
    assert read_design(V1 / "design.json").machine_mm.shape == (6, 3)
    study = read_study(V1 / "mc.json")
    assert study.strategies[0].quantities["position_error_um"].count > 0


def test_version_1_measurements_post_to_version_2_tables(tmp_path, reference_machine):
    plan = read_plan(V1 / "plan.json")
    errors = tmp_path / "errors.csv"
    post_step(reference_machine, [(plan, V1 / "measurements.csv")], errors)
    tables = read_error_tables(errors)
    assert tables.history is not None and tables.history.format == "xmalign.error-tables/2"
    assert tables.machine is not None and tables.machine.chain == reference_machine.chain
    old = read_error_tables(V1 / "errors.csv").tables["EXX"]
    new = tables.tables["EXX"]
    np.testing.assert_allclose(new.values, old.values, atol=1e-7)  # the file rounds to 0.1 nm


def _inputs_checked_by_sha256sum(lines: list[str], cwd: Path) -> None:
    """``sha256sum -c`` (GNU coreutils, not ours) on the ``# input`` lines of a preamble."""
    listing = "".join(line.split(": ", 1)[1] + "\n" for line in lines if line.startswith("# input"))
    assert listing
    check = subprocess.run(
        ["sha256sum", "-c", "-"], input=listing, text=True, capture_output=True, cwd=cwd
    )
    assert check.returncode == 0, check.stdout + check.stderr


@pytest.mark.skipif(shutil.which("sha256sum") is None, reason="needs sha256sum")
def test_error_tables_lead_back_to_measurements_plan_and_pose(dry_run):
    tables_text = (dry_run / "errors.csv").read_text().splitlines()
    assert tables_text[0] == "# format: xmalign.error-tables/2"
    assert tables_text[1].startswith("# software: xmalign ")
    assert tables_text[2].startswith("# created_utc: 20") and tables_text[2].endswith("Z")
    # the dry run's folder was copied: the recorded paths are the original's, the bytes the same
    tables = read_error_tables(dry_run / "errors.csv")
    assert tables.history is not None
    measurements = tables.history.input("measurements")
    plan_source = tables.history.input("plan")
    assert measurements is not None and plan_source is not None
    for source, name in ((measurements, "measurements.csv"), (plan_source, "plan.json")):
        assert source.sha256 == hashlib.sha256((dry_run / name).read_bytes()).hexdigest()
    plan = read_plan(dry_run / "plan.json")
    assert plan.history is not None
    pose = plan.history.input("pose")
    assert pose is not None
    assert pose.sha256 == hashlib.sha256((dry_run / "pose.json").read_bytes()).hexdigest()
    recorded = load_measurements(dry_run / "measurements.csv")
    assert recorded.history is not None and recorded.history.input("plan") == FileSource(
        "plan", plan_source.path, plan_source.sha256
    )
    times = [row.time_s for row in recorded.rows]
    assert all(t is not None for t in times) and times == sorted(times)  # type: ignore[type-var]
    copied = [
        line.replace(str(Path(plan_source.path).parent), ".")
        for line in tables_text
        if line.startswith("# input")
    ]
    _inputs_checked_by_sha256sum(copied, dry_run)


def test_newer_versions_are_refused_with_one_line(tmp_path):
    errors = tmp_path / "errors.csv"
    errors.write_text("# format: xmalign.error-tables/3\n" + (V1 / "errors.csv").read_text())
    expected = "written by a newer xmalign: format xmalign.error-tables/3, this one reads up to /2"
    with pytest.raises(FormatError, match=expected):
        read_error_tables(errors)
    measurements = tmp_path / "m.csv"
    lines = (V1 / "measurements.csv").read_text().splitlines(keepends=True)
    measurements.write_text(lines[0] + "# format: xmalign.measurements/3\n" + "".join(lines[1:]))
    with pytest.raises(FormatError, match="format xmalign.measurements/3, this one reads up to /2"):
        load_measurements(measurements)
    plan = json.loads((V1 / "plan.json").read_text()) | {"format": "xmalign.plan/2"}
    (tmp_path / "plan.json").write_text(json.dumps(plan))
    with pytest.raises(FormatError, match="format xmalign.plan/2, this one reads up to /1"):
        read_plan(tmp_path / "plan.json")


def test_the_machine_file_may_name_its_format(reference_machine):
    data = reference_machine.model_dump(mode="json", exclude_none=True, exclude={"format"})
    named = parse_machine(data | {"format": "xmalign.machine/1"})
    assert named.format == "xmalign.machine/1"
    assert named.model_copy(update={"format": None}) == parse_machine(data)
    with pytest.raises(InputError, match="key 'format': written by a newer xmalign"):
        parse_machine(data | {"format": "xmalign.machine/2"}, "m.yaml")
    with pytest.raises(InputError, match="key 'format': 'xmalign.plan/1' is not a"):
        parse_machine(data | {"format": "xmalign.plan/1"}, "m.yaml")


def test_a_preamble_round_trips():
    source = FileSource("plan", "a dir/plan.json", "ab" * 32)
    text = csv_preamble("xmalign.x/2", [source], {"machine": '{"chain": "FYXZ"}'})
    history = read_csv_preamble(text.splitlines(), "xmalign.x/2", "f.csv", "xmalign.x/1")
    assert history.inputs == (source,) and history.extra == {"machine": '{"chain": "FYXZ"}'}
    assert history.version == 2 and history.software and history.created_utc


def test_rows_keep_their_time(tmp_path):
    rows = [
        MeasurementRow("X", 1, "+", i, 10.0 * i, np.array([i, 0.0, 0]), np.zeros(6), time_s=t)
        for i, t in enumerate((1.5, 2.25))
    ]
    write_measurements(tmp_path / "m.csv", rows)
    assert [row.time_s for row in load_measurements(tmp_path / "m.csv").rows] == [1.5, 2.25]


def _machine_yaml(tmp_path: Path, old: str, new: str) -> Path:
    text = (ROOT / "examples" / "fyxz.yaml").read_text()
    assert old in text
    path = tmp_path / "other.yaml"
    path.write_text(text.replace(old, new))
    load_machine(path)
    return path


@pytest.mark.parametrize(
    ("old", "new", "fragment"),
    [
        ("chain: FYXZ", "chain: XFYZ", "chain FYXZ, not XFYZ"),
        ("X: [0, 2000]", "X: [0, 4000]", "X travel [0, 2000] mm"),
    ],
)
def test_comp_refuses_tables_of_another_machine(tmp_path, dry_run, old, new, fragment):
    other = _machine_yaml(tmp_path, old, new)
    result = run_cli(
        "comp", "--errors", str(dry_run / "errors.csv"), "--machine", str(other),
        "--out", str(tmp_path / "comp"),
    )  # fmt: skip
    assert_one_line_error(result, "errors.csv", "measured on", fragment)
    assert not (tmp_path / "comp").exists()


def test_tables_name_the_machine_they_were_measured_on(tmp_path, reference_machine):
    tables = read_error_tables(V1 / "errors.csv")
    assert tables.check_machine(reference_machine) == [
        f"{V1 / 'errors.csv'} does not name the machine it was measured on (version 1)"
    ]
    write_error_tables(tmp_path / "e.csv", tables, machine=reference_machine)
    again = read_error_tables(tmp_path / "e.csv")
    assert again.check_machine(reference_machine) == []
    renamed = reference_machine.model_copy(update={"name": "another name"})
    assert "not 'another name'" in again.check_machine(renamed)[0]


def test_each_command_records_what_it_read(tmp_path):
    """identify --input, program and plan-identify: each file names its inputs' SHA-256."""
    session = ROOT / "examples" / "session.json"
    machine = ROOT / "examples" / "fyxz.yaml"
    pose = tmp_path / "pose.json"
    done = run_cli(
        "identify", "--input", str(session), "--machine", str(machine), "--out", str(pose)
    )
    assert done.returncode == 0, done.stderr
    written = json.loads(pose.read_text())
    assert written["software"].startswith("xmalign ") and written["created_utc"].endswith("Z")
    assert {(i["role"], i["sha256"]) for i in written["inputs"]} == {
        ("session", hashlib.sha256(session.read_bytes()).hexdigest()),
        ("machine", hashlib.sha256(machine.read_bytes()).hexdigest()),
    }
    plan = tmp_path / "plan.json"
    done = run_cli("program", "--pose", str(pose), "--plan-out", str(plan), "--out",
                   str(tmp_path / "run.mpf"))  # fmt: skip
    assert done.returncode == 0, done.stderr
    history = read_plan(plan).history
    assert history is not None and history.input("pose") == FileSource.of("pose", pose)
    design = tmp_path / "design.json"
    done = run_cli("plan-identify", "--machine", str(machine), "--out", str(design))
    assert done.returncode == 0, done.stderr
    read = read_design(design)
    assert read.history is not None and read.history.input("machine") == FileSource.of(
        "machine", machine
    )
