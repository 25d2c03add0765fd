"""The commands' promises kept where a script calls the steps (issue 32, point 1).

Each misuse of the issue through :mod:`xmalign.api`: one line (an
:class:`~xmalign.errors.XmalignError`), nothing written over; the same cases
through the CLI are in tests/xmalign/bad_input_cases.py.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import warnings
from pathlib import Path

import pytest

from xmalign import api
from xmalign.errors import OutputError, XmalignError
from xmalign.formats.measurements import load_measurements

REFERENCE = Path(__file__).resolve().parents[2] / "examples" / "fyxz.yaml"


@pytest.fixture(scope="module")
def calibrated(dry_run_of_seed) -> Path:
    """A calibration's folder (session, pose, plan, measurements, errors) of the reference
    machine; each test works in a copy of it."""
    return dry_run_of_seed(3, "promises")[1]


@pytest.fixture
def folder(calibrated: Path, tmp_path: Path) -> Path:
    work = tmp_path / "work"
    shutil.copytree(calibrated, work)
    return work


def _hashes(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def _refused(call, *fragments: str) -> str:
    """``call()`` raises one line holding every fragment; the message."""
    with pytest.raises(XmalignError) as raised:
        call()
    message = str(raised.value)
    assert "\n" not in message, message
    for fragment in fragments:
        assert fragment in message, message
    return message


def _machine_file(tmp_path: Path, old: str, new: str) -> Path:
    text = REFERENCE.read_text()
    assert old in text
    path = tmp_path / "machine.yaml"
    path.write_text(text.replace(old, new))
    return path


def test_post_step_never_writes_over_its_data_plan_or_a_users_file(folder: Path) -> None:
    machine = api.load_machine(REFERENCE)
    plan = api.read_plan(folder / "plan.json")
    stations = [(plan, folder / "measurements.csv")]
    before = _hashes(folder)
    _refused(
        lambda: api.post_step(machine, stations, folder / "measurements.csv"),
        "measurements.csv",
        "errors_path",
        "measurements",
    )
    _refused(lambda: api.post_step(machine, stations, folder / "plan.json"), "plan")
    _refused(
        lambda: api.post_step(machine, stations, REFERENCE, replace=True), "is also the machine"
    )
    _refused(
        lambda: api.post_step(machine, stations, folder / "errors.csv"),
        "errors.csv",
        "already exists",
        "replace=True",
    )
    assert _hashes(folder) == before
    posted = api.post_step(machine, stations, folder / "errors.csv", replace=True)
    again = api.read_error_tables(folder / "errors.csv")
    assert again.history.input("measurements").sha256 == api.file_sha256(
        folder / "measurements.csv"
    )
    assert again.history.input("machine").sha256 == api.file_sha256(REFERENCE)
    assert posted.warnings == []


def test_post_step_refuses_a_station_given_twice_or_its_copy(folder: Path) -> None:
    machine = api.load_machine(REFERENCE)
    plan = api.read_plan(folder / "plan.json")
    shutil.copy(folder / "measurements.csv", folder / "copy.csv")
    for second in (folder / "measurements.csv", folder / "copy.csv"):
        stations = [(plan, folder / "measurements.csv"), (plan, second)]
        _refused(lambda s=stations: api.post_step(machine, s, folder / "e.csv"), "count twice")
    assert not (folder / "e.csv").exists()


def test_program_step_never_replaces_a_plan_nor_writes_over_the_pose(folder: Path) -> None:
    machine = api.load_machine(REFERENCE)
    pose = api.read_pose(folder / "pose.json")
    before = _hashes(folder)
    _refused(
        lambda: api.program_step(machine, pose, folder / "plan.json"),
        "plan.json",
        "plan_path",
        "replace=True",
    )
    _refused(
        lambda: api.program_step(
            machine, pose, folder / "pose.json", pose_path=folder / "pose.json", replace=True
        ),
        "pose.json",
        "is also the pose_path file",
    )
    _refused(
        lambda: api.program_step(machine, pose, folder / "p.json", folder / "p.json", replace=True),
        "p.json",
        "is also the plan_path file",
    )
    _refused(
        lambda: api.program_step(machine, pose, folder / "pose.json", replace=True),
        "is also the pose_path file",  # the file the pose was read from
    )
    assert _hashes(folder) == before
    programmed = api.program_step(
        machine, pose, folder / "plan.json", pose_path=folder / "pose.json", replace=True
    )
    assert programmed.files["plan"] == folder / "plan.json"


def test_comp_step_keeps_a_users_table_and_refuses_another_machines_tables(
    folder: Path, tmp_path: Path
) -> None:
    machine = api.load_machine(REFERENCE)
    tables = api.read_error_tables(folder / "errors.csv")
    out = tmp_path / "user"
    out.mkdir()
    (out / "AX_EEC.INI").write_text("; the user's own table\n")
    _refused(lambda: api.comp_step(machine, tables, out), "AX_EEC.INI", "replace=True")
    assert (out / "AX_EEC.INI").read_text() == "; the user's own table\n"
    xfyz = api.load_machine(_machine_file(tmp_path, "chain: FYXZ", "chain: XFYZ"))
    _refused(lambda: api.comp_step(xfyz, tables, tmp_path / "x"), "chain FYXZ, not XFYZ")
    assert not (tmp_path / "x").exists()
    compensation = api.comp_step(machine, tables, out, replace=True)
    assert "AX_EEC.INI" in compensation.files
    a_file = tmp_path / "a-file"
    a_file.write_text("kept\n")
    _refused(lambda: api.comp_step(machine, tables, a_file), "a-file: out_dir: is a file")
    _refused(
        lambda: api.volumetric_comp_step(machine, tables, a_file, "machine.ini"),
        "a-file: out_dir: is a file",
    )
    assert a_file.read_text() == "kept\n"


#: A LinuxCNC INI with the three joints' sections; joint 1 keeps a backlash compensation.
MILL_INI = "[KINS]\nJOINTS = 3\n\n[JOINT_0]\n\n[JOINT_1]\nBACKLASH = 0.01\n\n[JOINT_2]\n"


def test_comp_step_writes_the_merged_linuxcnc_ini_and_never_over_the_ini(
    folder: Path, tmp_path: Path
) -> None:
    """``comp --ini`` through the API: the joints, the merged copy with its history and the
    BACKLASH warning; the INI itself never written over, whatever the names or links."""
    machine = api.load_machine(REFERENCE)
    tables = api.read_error_tables(folder / "errors.csv")
    ini = tmp_path / "cfg" / "mill.ini"
    ini.parent.mkdir()
    ini.write_text(MILL_INI)
    out, told = tmp_path / "comp", []
    done = api.comp_step(machine, tables, out, "linuxcnc", ini=ini, on_warning=told.append)
    assert done.merged_ini == out / "mill-xmalign.ini" and done.joints == ("X", "Y", "Z")
    assert sorted(done.files) == sorted(path.name for path in out.iterdir())
    merged = done.merged_ini.read_text()
    assert f"COMP_FILE = {(out / 'y.comp').resolve()}" in merged
    assert any(line.startswith("# input ini: ") for line in merged.splitlines())
    assert len(told) == 1 and "[JOINT_1] BACKLASH" in told[0] and str(ini) in told[0]
    again = tmp_path / "again"
    again.mkdir()
    (again / "mill-xmalign.ini").symlink_to(ini)  # the merged copy's name is the INI itself
    _refused(
        lambda: api.comp_step(machine, tables, again, "linuxcnc", ini=ini, replace=True),
        "mill-xmalign.ini",
        "is also the ini file",
    )
    named_like_an_output = again / "joints.ini"
    named_like_an_output.write_text(MILL_INI)
    _refused(
        lambda: api.comp_step(
            machine, tables, again, "linuxcnc", ini=named_like_an_output, replace=True
        ),
        "joints.ini",
        "is also the ini file",
    )
    assert ini.read_text() == named_like_an_output.read_text() == MILL_INI
    assert sorted(path.name for path in again.iterdir()) == ["joints.ini", "mill-xmalign.ini"]
    _refused(
        lambda: api.comp_step(machine, tables, tmp_path / "s", "sinumerik", ini=ini),
        "ini is for the linuxcnc controller, not 'sinumerik'",
    )
    _refused(  # the machine file's controller (sinumerik) when none is given
        lambda: api.comp_step(machine, tables, tmp_path / "s", ini=ini), "not 'sinumerik'"
    )
    bare = tmp_path / "bare.ini"
    bare.write_text("[EMC]\nMACHINE = bare\n")
    _refused(
        lambda: api.comp_step(machine, tables, tmp_path / "b", "linuxcnc", ini=bare),
        "bare.ini",
        "no [JOINT_0] section",
    )
    _refused(lambda: api.comp_step(machine, tables, tmp_path / "b", "linuxcnc", ini=3), "ini")
    assert not (tmp_path / "s").exists() and not (tmp_path / "b").exists()


def test_another_file_of_the_same_machine_is_a_warning(folder: Path, tmp_path: Path) -> None:
    """Name, chain and travel the same, the file edited (feeds): a warning, not a refusal."""
    edited = api.load_machine(_machine_file(tmp_path, "rapid: ", "rapid: 1"))
    tables = api.read_error_tables(folder / "errors.csv")
    with pytest.warns(UserWarning, match="another file"):
        api.comp_step(edited, tables, tmp_path / "comp")
    told: list[str] = []
    api.comp_step(edited, tables, tmp_path / "comp2", on_warning=told.append)
    assert len(told) == 1 and "machine.yaml" in told[0]
    plan = api.read_plan(folder / "plan.json")
    posted = api.post_step(edited, [(plan, folder / "measurements.csv")], tmp_path / "e.csv")
    assert any("another file" in warning for warning in posted.warnings)


def test_a_plan_of_another_machine_is_refused_by_every_step(folder: Path, tmp_path: Path) -> None:
    other = api.load_machine(_machine_file(tmp_path, "X: [0, 2000]", "X: [0, 2100]"))
    plan = api.read_plan(folder / "plan.json")
    data = folder / "measurements.csv"
    fragments = ("plan.json was made for machine", str(tmp_path / "machine.yaml"))
    _refused(lambda: api.post_step(other, [(plan, data)], tmp_path / "e.csv"), *fragments)
    _refused(lambda: api.open_measurements_step(tmp_path / "m.csv", plan, other), *fragments)
    assert not (tmp_path / "e.csv").exists() and not (tmp_path / "m.csv").exists()


def test_a_pose_names_its_machine_and_program_step_checks_it(folder: Path, tmp_path: Path) -> None:
    """The pose written by the steps names the machine it was identified on (name and
    geometry, the machine file among its inputs); program_step refuses it for another
    machine, warns for another file of the same machine, and reads an older pose."""
    import json

    machine = api.load_machine(REFERENCE)
    pose = api.read_pose(folder / "pose.json")
    assert (pose.machine, pose.machine_sha256) == (machine.name, machine.geometry_sha256())
    assert pose.history.input("machine").sha256 == api.file_sha256(REFERENCE)
    other = api.load_machine(_machine_file(tmp_path, "X: [0, 2000]", "X: [0, 2100]"))
    _refused(
        lambda: api.program_step(other, pose, tmp_path / "plan.json"),
        "pose.json was made for machine",
        str(tmp_path / "machine.yaml"),
        "give the machine file the pose was made with",
    )
    renamed = api.load_machine(_machine_file(tmp_path, "name: ", "name: Other "))
    _refused(lambda: api.program_step(renamed, pose, tmp_path / "plan.json"), "made for machine")
    assert not (tmp_path / "plan.json").exists()
    edited = api.load_machine(_machine_file(tmp_path, "rapid: ", "rapid: 1"))
    programmed = api.program_step(edited, pose, tmp_path / "plan.json")
    assert any("another file" in warning for warning in programmed.warnings)
    document = json.loads((folder / "pose.json").read_text())
    for key in ("machine", "machine_sha256", "software", "created_utc", "inputs"):
        del document[key]
    (tmp_path / "old-pose.json").write_text(json.dumps(document))
    older = api.read_pose(tmp_path / "old-pose.json")
    assert older.machine is None
    assert api.program_step(other, older, None, write_program_file=False).checks == []


def test_a_plan_target_outside_the_travel_is_refused(folder: Path, tmp_path: Path) -> None:
    smaller = api.load_machine(_machine_file(tmp_path, "X: [0, 2000]", "X: [0, 1000]"))
    plan = api.read_plan(folder / "plan.json")
    plan.extra.pop("machine_sha256", None)
    _refused(
        lambda: api.open_measurements_step(tmp_path / "m.csv", plan, smaller),
        "lies outside the travel",
    )


def test_a_machine_remembers_its_file(tmp_path: Path) -> None:
    machine = api.load_machine(REFERENCE)
    assert machine.source is not None
    assert machine.source.path == str(REFERENCE)
    assert machine.source.sha256 == api.file_sha256(REFERENCE)
    assert machine.model_copy(update={"name": "other"}).source is None
    assert machine == api.load_machine(_machine_file(tmp_path, "\n", "\n"))  # content decides


def test_arguments_of_the_wrong_kind_are_one_line(folder: Path, tmp_path: Path) -> None:
    machine = api.load_machine(REFERENCE)
    plan = api.read_plan(folder / "plan.json")
    _refused(lambda: api.load_calibration("/nonexistent"), "/nonexistent", "no such folder")
    _refused(lambda: api.load_calibration(folder / "plan.json"), "plan.json", "not a folder")
    _refused(lambda: api.load_calibration(folder, "/nonexistent.yaml"), "/nonexistent.yaml")
    _refused(lambda: api.load_machine(3), "3", "machine file")
    _refused(lambda: api.post_step(machine, "plan.json", tmp_path / "e.csv"), "stations")
    _refused(lambda: api.post_step(machine, [("plan.json", "m.csv")], "e.csv"), "station 1")
    _refused(lambda: api.post_step(machine, [(plan, 3)], "e.csv"), "measurement file")
    _refused(lambda: api.post_step("fyxz.yaml", [(plan, "m.csv")], "e.csv"), "machine")
    _refused(lambda: api.program_step(machine, plan, tmp_path / "p.json"), "pose")
    _refused(lambda: api.comp_step(machine, "errors.csv", tmp_path), "tables")
    _refused(lambda: api.program_step(machine, None, 42), "plan_path", "42")
    _refused(lambda: api.identify("session.json", "joint"), "session", "Session")
    _refused(lambda: api.error_table_frames("errors.csv"), "tables", "ErrorTableSet")
    _refused(lambda: api.squareness_frame(3), "tables")
    _refused(lambda: api.iso230_2_frame("x"), "result", "PostResult")
    pose = api.read_pose(folder / "pose.json")
    for line_ids, shown in ((("X", "Q"), "'X,Q'"), (("X", "X"), "'X,X'"), ((), "''"), ("X", "'X'")):
        _refused(
            lambda ids=line_ids: api.program_step(machine, pose, tmp_path / "l.json", line_ids=ids),
            f"line_ids {shown}",
            "give distinct lines out of X, Y, Z",
        )
    assert not (tmp_path / "l.json").exists()
    for kind, options, fragments in (
        ("laser", {}, ("instrument 'laser' is not known",)),
        ("tracer", {"on_the_fly": True}, ("on_the_fly is for instrument tracker",)),
        ("tracker", {"places": 6}, ("places is for instrument tracer",)),
        ("tracer", {"places": 0}, ("places 0: give 4 to 12",)),  # was: fit_joint needs ...
        ("tracer", {"places": "4"}, ("places '4': give 4 to 12",)),  # was a TypeError
    ):
        _refused(lambda k=kind, o=options: api.instrument_program_step(machine, k, **o), *fragments)
    _refused(  # named as the script names it, not as the command's --dialect
        lambda: api.program_step(machine, pose, tmp_path / "d.json", dialect="fanucc"),
        "dialect 'fanucc' is not known",
    )
    _refused(lambda: api.instrument_program_step(machine, "tracer", dialect=3), "dialect '3'")


def test_a_link_is_followed_to_its_target_and_stays_a_link(folder: Path, tmp_path: Path) -> None:
    machine = api.load_machine(REFERENCE)
    plan = api.read_plan(folder / "plan.json")
    stations = [(plan, folder / "measurements.csv")]
    target = tmp_path / "tables" / "errors.csv"
    target.parent.mkdir()
    target.write_text("old\n")
    link = tmp_path / "link.csv"
    link.symlink_to(target)
    _refused(lambda: api.post_step(machine, stations, link), "link.csv", "already exists")
    api.post_step(machine, stations, link, replace=True)
    assert link.is_symlink() and os.readlink(link) == str(target)
    assert api.read_error_tables(target).history is not None
    dangling = tmp_path / "dangling.csv"
    dangling.symlink_to(tmp_path / "new.csv")
    api.post_step(machine, stations, dangling)
    assert dangling.is_symlink() and (tmp_path / "new.csv").is_file()


def test_loops_fifos_and_folders_are_refused_as_outputs(folder: Path, tmp_path: Path) -> None:
    machine = api.load_machine(REFERENCE)
    plan = api.read_plan(folder / "plan.json")
    stations = [(plan, folder / "measurements.csv")]
    loop = tmp_path / "loop"
    loop.symlink_to(loop)
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    for out, what in ((loop, "loops"), (fifo, "FIFO"), (tmp_path, "is a folder")):
        with pytest.raises(OutputError, match=what):
            api.post_step(machine, stations, out, replace=True)
    assert loop.is_symlink() and not loop.exists()


def test_a_newline_in_the_plans_name_is_escaped_as_sha256sum_does(
    folder: Path, tmp_path: Path
) -> None:
    """A name with a line feed does not split the ``# input`` line: the measurement file
    is read back (as post and --resume read it) and ``sha256sum -c`` checks the line."""
    machine = api.load_machine(REFERENCE)
    odd = tmp_path / "plan\nof the day\\.json"
    shutil.copy(folder / "plan.json", odd)
    plan = api.read_plan(odd)
    measurements = tmp_path / "m.csv"
    with api.open_measurements_step(measurements, plan, machine):
        pass
    recorded = load_measurements(measurements)
    assert recorded.history.input("plan").path == str(odd)
    line = next(x for x in measurements.read_text().splitlines() if x.startswith("# input plan"))
    checked = subprocess.run(
        ["sha256sum", "-c"],
        input=line.removeprefix("# input plan: ") + "\n",
        capture_output=True,
        text=True,
        check=False,
    )
    assert checked.returncode == 0, checked.stderr
    with api.open_measurements_step(measurements, plan, machine, resume=True) as output:
        assert output.warnings == []


def test_a_name_with_another_line_end_is_refused(folder: Path, tmp_path: Path) -> None:
    odd = tmp_path / "plan\u2028.json"
    shutil.copy(folder / "plan.json", odd)
    _refused(lambda: api.read_plan(odd), "ends a line", "rename the file")


def test_writing_steps_warn_nothing_when_all_is_well(folder: Path, tmp_path: Path) -> None:
    machine = api.load_machine(REFERENCE)
    tables = api.read_error_tables(folder / "errors.csv")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        api.comp_step(machine, tables, tmp_path / "comp")


# -- the same promises through the commands ------------------------------------------------


def test_run_and_resume_agree_on_a_plan_named_with_a_newline(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``run`` records a plan whose name holds a line feed; ``--resume`` goes on with the
    file, its ``# input`` line is one line that ``sha256sum -c`` checks."""
    from tests.cli_helpers import run_in_process
    from xmalign.formats.plan import write_plan

    monkeypatch.chdir(tmp_path)
    plan = api.read_plan(REFERENCE.parent / "plan.json")
    plan.lines = [line for line in plan.lines if line.id == "Z"]
    write_plan("pl\nan.json", plan)
    run = ("run", "--sim", "--in-process", "--plan", "pl\nan.json", "--out", "m.csv")
    assert run_in_process(*run).returncode == 0
    recorded = load_measurements(tmp_path / "m.csv")
    assert recorded.history.input("plan").path == "pl\nan.json" and recorded.rows
    resumed = run_in_process(*run, "--resume")
    assert resumed.returncode == 0, resumed.stderr
    line = next(x for x in Path("m.csv").read_text().splitlines() if x.startswith("# input"))
    checked = subprocess.run(
        ["sha256sum", "-c"], input=line.split(": ", 1)[1] + "\n", text=True, check=False
    )
    assert checked.returncode == 0


def test_force_writes_a_links_target_and_keeps_the_link(
    calibrated: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``--plan-out`` a link with ``--force``, ``--out`` a dangling link: the file the link
    names is written, the link stays a link to it (it was replaced, the target left stale)."""
    from tests.cli_helpers import run_in_process

    monkeypatch.chdir(tmp_path)
    (tmp_path / "kept").mkdir()
    Path("kept/plan.json").write_text("{}\n")
    Path("plan.json").symlink_to("kept/plan.json")
    Path("pose.json").symlink_to("kept/pose.json")  # dangling
    identified = run_in_process(
        "identify", "--input", str(calibrated / "session.json"), "--out", "pose.json"
    )
    assert identified.returncode == 0, identified.stderr
    assert Path("pose.json").is_symlink() and api.read_pose("kept/pose.json")
    refused = run_in_process("program", "--plan-out", "plan.json", "--out", "run.mpf")
    assert refused.returncode == 2 and "--force" in refused.stderr
    forced = run_in_process("program", "--plan-out", "plan.json", "--out", "run.mpf", "--force")
    assert forced.returncode == 0, forced.stderr
    assert Path("plan.json").is_symlink() and os.readlink("plan.json") == "kept/plan.json"
    assert api.read_plan("kept/plan.json").history.input("pose").path == "pose.json"


@pytest.mark.parametrize(
    "reader",
    [
        "read_plan",
        "read_pose",
        "read_session",
        "read_error_tables",
        "load_measurements",
        "read_design",
        "read_study",
        "load_machine",
        "measurements_frame",
        "file_sha256",
    ],
)
def test_every_reader_refuses_what_is_not_a_path_in_one_line(reader: str) -> None:
    for value in (3, None, b"", ""):
        _refused(lambda v=value: getattr(api, reader)(v), "not a")


def test_identify_sim_force_writes_the_session_links_target(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from tests.cli_helpers import run_in_process

    monkeypatch.chdir(tmp_path)
    (tmp_path / "kept").mkdir()
    Path("kept/session.json").write_text("{}\n")
    Path("session.json").symlink_to("kept/session.json")
    done = run_in_process(
        "identify", "--sim", "--alignments", "4", "--session-out", "session.json", "--force"
    )
    assert done.returncode == 0, done.stderr
    assert (
        Path("session.json").is_symlink()
        and len(api.read_session("kept/session.json").alignments) == 4
    )


def test_instrument_programs_are_written_by_one_step(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``program --instrument`` (:func:`instrument_program_step`) and the instrument dry run
    write their G-code and point list through :func:`write_instrument_step`; its outputs
    keep the promises (an existing point list without replace=True)."""
    from sim import instrument_dry_run
    from xmalign import steps

    calls: list[object] = []

    def spy(*args, **kwargs):
        calls.append(args[2])
        return steps.write_instrument_step(*args, **kwargs)

    monkeypatch.setattr(instrument_dry_run, "write_instrument_step", spy)
    machine = api.load_machine(REFERENCE)
    instrument_dry_run.simulate_instruments(machine, tmp_path / "dry", "tracker", 1)
    assert calls == [tmp_path / "dry" / "tracker.nc"]
    planned = api.instrument_program_step(
        machine, "tracker", program_path=tmp_path / "t.nc", points_path=tmp_path / "p.csv"
    )
    assert planned.files == {"program": tmp_path / "t.nc", "points": tmp_path / "p.csv"}
    assert (tmp_path / "dry" / "points.csv").read_text() == (tmp_path / "p.csv").read_text()
    _refused(
        lambda: api.instrument_program_step(machine, "tracker", points_path=tmp_path / "p.csv"),
        "points_path",
        "replace=True",
    )
    (tmp_path / "q.csv.history").write_text("the user's notes\n")  # the list's history's place
    _refused(
        lambda: api.instrument_program_step(machine, "tracker", points_path=tmp_path / "q.csv"),
        "q.csv.history",
        "points_path",
        "replace=True",
    )
    assert (tmp_path / "q.csv.history").read_text() == "the user's notes\n"
    assert not (tmp_path / "q.csv").exists()
    _refused(lambda: api.instrument_program_step(machine, "tracker", simultaneous=True), "tracer")
    _refused(lambda: api.instrument_program_step(machine, "tracer", on_the_fly=True), "tracker")


def test_the_dry_runs_files_name_the_machine_file(calibrated: Path) -> None:
    """The dry run gets the machine's provenance from the steps: its pose, plan and error
    tables name the machine file (its SHA-256) the machine was read from."""
    import json

    machine_sha256 = api.file_sha256(REFERENCE)
    for name in ("pose.json", "plan.json"):
        inputs = json.loads((calibrated / name).read_text())["inputs"]
        assert {"role": "machine", "path": str(REFERENCE), "sha256": machine_sha256} in inputs
    tables = api.read_error_tables(calibrated / "errors.csv")
    assert tables.history.input("machine").sha256 == machine_sha256


def test_the_dry_runs_controller_files_name_the_error_tables(calibrated: Path) -> None:
    """comp_step is given the tables post_step wrote, read back: every controller file's
    history (in it, or in NAME.history beside it) names errors.csv by its SHA-256."""
    errors_sha256 = api.file_sha256(calibrated / "errors.csv")
    written = sorted((calibrated / "comp").iterdir())
    assert written
    for path in written:
        history = path.with_name(f"{path.name}.history")
        text = (history if history.exists() else path).read_text()
        named = [line for line in text.splitlines() if "input errors: " in line]
        assert len(named) == 1, path.name
        assert f"input errors: {errors_sha256}  " in named[0], named[0]
        assert named[0].endswith("errors.csv"), named[0]
