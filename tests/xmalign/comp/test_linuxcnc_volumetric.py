"""The volumetric component's table file and the INI/HAL merge (no LinuxCNC needed).

The component itself is tested in a real LinuxCNC in tests/linuxcnc/.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import assert_one_line_error, run_cli, run_in_process
from hypothesis import given, settings
from hypothesis import strategies as st

from xmalign.comp.linuxcnc_volumetric import (
    INSTANCE,
    TABLE_FILE,
    WIRING_FILE,
    correction_mm,
    joint_coordinates,
    mean_model,
    merge_config,
    parse_table,
    read_ini,
    render_table,
)
from xmalign.errors import FormatError, InputError
from xmalign.formats.error_tables import ErrorTableSet, Table, write_error_tables
from xmalign.machine import parse_machine
from xmalign.rigid_body import MOTION_NAMES, SQUARENESS_NAMES, Chain, deviation

TRAVEL = {"X": (0.0, 400.0), "Y": (0.0, 300.0), "Z": (-200.0, 0.0)}
OFFSET = [5.0, -3.0, -80.0]

INI = """[EMC]
MACHINE = test
[DISPLAY]
DISPLAY = axis
PROGRAM_PREFIX = nc_files
[RS274NGC]
PARAMETER_FILE = sim.var
[HAL]
HALFILE = machine.hal
HALUI = halui
[KINS]
KINEMATICS = trivkins coordinates={coordinates} kinstype=BOTH
JOINTS = {joints}
[EMCIO]
TOOL_TABLE = sim.tbl
[JOINT_0]
MIN_LIMIT = {x_min}
MAX_LIMIT = 400
"""

HAL = """loadrt [KINS]KINEMATICS
loadrt [EMCMOT]EMCMOT servo_period_nsec=[EMCMOT]SERVO_PERIOD num_joints=[KINS]JOINTS
addf motion-command-handler servo-thread
addf motion-controller servo-thread
net estop-loop iocontrol.0.user-enable-out iocontrol.0.emc-enable-in
"""


def _tables(rng: np.random.Generator, n: int = 9) -> ErrorTableSet:
    result = ErrorTableSet()
    for name in MOTION_NAMES:
        low, high = TRAVEL[name[2]]
        scale = 1e-3 if name[1] in "XYZ" else 1e-6
        values = rng.uniform(-20, 20, n) * scale
        result.tables[name] = Table(np.linspace(low, high, n), values, np.zeros(n))
    result.squareness = {s: (float(rng.uniform(-30, 30)) * 1e-6, 0.0) for s in SQUARENESS_NAMES}
    return result


def _machine(chain: str = "FYXZ", **cnc):
    return parse_machine(
        {
            "name": "test",
            "chain": chain,
            "travel_mm": {axis: list(limits) for axis, limits in TRAVEL.items()},
            "feed_mm_min": {"rapid": 8000, "measure": 2000},
            "controller": "linuxcnc",
            "receiver_offset_mm": [0, 0, -100],
            "cnc": {"tool_offset_mm": OFFSET, "max_correction_um": 60.0, **cnc},
        }
    )


def _config(folder: Path, coordinates: str = "XYYZ", x_min: float = 0.0, hal: str | None = None):
    joints = len(coordinates)
    loops = "".join(
        f"net j{j} joint.{j}.motor-pos-cmd => joint.{j}.motor-pos-fb\n" for j in range(joints)
    )
    (folder / "machine.hal").write_text(hal if hal is not None else HAL + loops)
    (folder / "sim.tbl").write_text("T1 P1 ;\n")
    (folder / "nc_files").mkdir(exist_ok=True)
    ini = folder / "machine.ini"
    ini.write_text(INI.format(coordinates=coordinates, joints=joints, x_min=x_min))
    return ini


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), chain=st.sampled_from(["FYXZ", "XFYZ", "YXFZ", "ZFXY"]))
def test_table_file_round_trip_gives_the_same_corrections(seed, chain):
    rng = np.random.default_rng(seed)
    tables = _tables(rng)
    text = render_table(tables, Chain.parse(chain), "XYYZ", OFFSET, 80.0)
    read = parse_table(text)
    assert (read.coordinates, str(read.chain), read.max_correction_um) == ("XYYZ", chain, 80.0)
    points = rng.uniform([0, 0, -200], [400, 300, 0], (20, 3))
    expected = correction_mm(Chain.parse(chain), mean_model(tables), OFFSET, points)
    got = correction_mm(read.chain, read.model, read.tool_offset_mm, points)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_any_changed_or_truncated_table_file_is_refused(data):
    text = render_table(
        _tables(np.random.default_rng(1), n=3), Chain.parse("FYXZ"), "XYZ", OFFSET, 50
    )
    index = data.draw(st.integers(0, len(text) - 2))
    if data.draw(st.booleans()):
        damaged = text[:index]
    else:
        replacement = data.draw(st.sampled_from("0123456789. -e\nxX"))
        damaged = text[:index] + replacement + text[index + 1 :]
    if damaged == text:
        return
    with pytest.raises(FormatError):
        parse_table(damaged)


def test_the_correction_puts_the_model_tool_point_on_the_commanded_point():
    tables = mean_model(_tables(np.random.default_rng(4)))
    chain = Chain.parse("FYXZ")
    points = np.random.default_rng(5).uniform([0, 0, -200], [400, 300, 0], (50, 3))
    c = correction_mm(chain, tables, OFFSET, points)
    dp, _ = deviation(chain, points + c, OFFSET, tables)
    np.testing.assert_allclose(c + dp, 0.0, atol=1e-9)  # 1 pm after three steps
    assert np.abs(c).max() > 0.01


def test_a_bidirectional_table_enters_as_the_mean_of_both_directions():
    tables = _tables(np.random.default_rng(2))
    mean = tables.tables.pop("EXX")
    tables.tables["EXX+"] = Table(mean.positions_mm, mean.values - 0.002, mean.u95)
    tables.tables["EXX-"] = Table(mean.positions_mm, mean.values + 0.002, mean.u95)
    np.testing.assert_allclose(mean_model(tables).tables["EXX"][1], mean.values, atol=1e-15)


def test_merge_rewires_the_drives_through_the_component(tmp_path):
    ini = _config(tmp_path)
    merged = merge_config(ini, _tables(np.random.default_rng(3)), _machine(), tmp_path / "out")
    hal = merged.files["machine_volcomp.hal"].splitlines()
    assert hal[0] == "# format: xmalign.comp.linuxcnc-volumetric/1"  # the copy's history
    # loaded before its pins are named; feedback in before motion reads it, command after
    hal = [line for line in hal if not line.startswith("#")]
    assert hal[0] == f"loadrt xmalign_volcomp table={(tmp_path / 'out').resolve()}/{TABLE_FILE}"
    motion = hal.index("addf motion-controller servo-thread")
    assert hal[motion - 1] == f"addf {INSTANCE}.feedback servo-thread"
    assert hal[motion + 1] == f"addf {INSTANCE}.command servo-thread"
    assert f"net j3 {INSTANCE}.motor-pos-out-3 => {INSTANCE}.motor-pos-fb-in-3" in hal
    assert f"net estop-loop iocontrol.0.user-enable-out {INSTANCE}.enable-in" in hal
    wiring = merged.files[WIRING_FILE].splitlines()
    assert (
        f"net xmalign-motor-pos-cmd-2 joint.2.motor-pos-cmd => {INSTANCE}.motor-pos-cmd-2" in wiring
    )
    assert f"net xmalign-fb-2 {INSTANCE}.motor-pos-fb-out-2 => joint.2.motor-pos-fb" in wiring
    assert f"net xmalign-enable {INSTANCE}.enable-out => iocontrol.0.emc-enable-in" in wiring
    for pin, component_pin in [
        ("joint.3.homed", "joint-homed-3"),
        ("motion.is-all-homed", "all-homed"),
        ("motion.motion-enabled", "motion-enabled"),
    ]:
        own = f"xmalign-{component_pin}"
        assert f"net {own} {pin} => {INSTANCE}.{component_pin}" in wiring
    lines = merged.files["machine_volcomp.ini"].splitlines()
    halfiles = [line for line in lines if line.startswith("HALFILE")]
    assert halfiles == ["HALFILE = machine_volcomp.hal", f"HALFILE = {WIRING_FILE}"]
    assert f"TOOL_TABLE = {tmp_path.resolve() / 'sim.tbl'}" in lines
    assert f"PROGRAM_PREFIX = {tmp_path.resolve() / 'nc_files'}" in lines
    assert "PARAMETER_FILE = sim.var" in lines  # not there yet: LinuxCNC makes it
    assert parse_table(merged.files[TABLE_FILE]).coordinates == "XYYZ"
    assert merged.warnings == []


def test_merge_joins_a_signal_the_user_already_has(tmp_path):
    loops = "".join(
        f"net j{j} joint.{j}.motor-pos-cmd => joint.{j}.motor-pos-fb\n" for j in range(3)
    )
    extra = "net x-commanded joint.0.pos-cmd => some.display\n"
    ini = _config(tmp_path, "XYZ", hal=HAL + loops + extra)
    merged = merge_config(ini, _tables(np.random.default_rng(3)), _machine(), tmp_path)
    assert f"net x-commanded => {INSTANCE}.joint-pos-cmd-0" in merged.files[WIRING_FILE]


def test_merge_leaves_pitch_tables_out_of_the_copy(tmp_path):
    ini = _config(tmp_path)
    ini.write_text(ini.read_text() + "COMP_FILE = joint0.comp\nCOMP_FILE_TYPE = 0\n")
    merged = merge_config(ini, _tables(np.random.default_rng(3)), _machine(), tmp_path)
    text = merged.files["machine_volcomp.ini"]
    assert "\nCOMP_FILE" not in text and "replaces: COMP_FILE = joint0.comp" in text
    assert any("[JOINT_0] COMP_FILE = joint0.comp left out" in w for w in merged.warnings)


def test_merge_warns_where_the_joint_limits_pass_the_tables(tmp_path):
    ini = _config(tmp_path, x_min=-10.0)
    merged = merge_config(ini, _tables(np.random.default_rng(3)), _machine(), tmp_path)
    assert len(merged.warnings) == 1 and "[JOINT_0] limits -10 .. 400 mm" in merged.warnings[0]


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (
            lambda ini, hal: (ini.replace("trivkins coordinates=XYYZ", "corexykins"), hal),
            "trivkins",
        ),
        (lambda ini, hal: (ini.replace("coordinates=XYYZ", "coordinates=XYZA"), hal), "XYZA"),
        (lambda ini, hal: (ini.replace("machine.hal", "LIB:basic_sim.tcl"), hal), "LIB:basic_sim"),
        (
            lambda ini, hal: (ini, hal.replace("addf motion-controller", "addf other")),
            "motion-controller",
        ),
        (lambda ini, hal: (ini, hal.replace("joint.3.motor-pos-fb", "x")), "joint.3.motor-pos-fb"),
        (lambda ini, hal: (ini, hal + "loadrt xmalign_volcomp table=x\n"), "already"),
        (lambda ini, hal: (ini, hal + "linkps motion.is-all-homed s\n"), "line 10: motion.is-all"),
        (
            lambda ini, hal: (ini + "[TRAJ]\nLINEAR_UNITS = inch\n", hal),
            "[TRAJ] LINEAR_UNITS is not mm",
        ),
    ],
)
def test_merge_refuses_what_it_cannot_wire(tmp_path, edit, message):
    ini = _config(tmp_path)
    ini_text, hal_text = edit(ini.read_text(), (tmp_path / "machine.hal").read_text())
    ini.write_text(ini_text)
    (tmp_path / "machine.hal").write_text(hal_text)
    with pytest.raises(InputError, match=message.replace("[", r"\[")):
        merge_config(ini, _tables(np.random.default_rng(3)), _machine(), tmp_path)


def test_joint_coordinates_default_to_trivkins_identity(tmp_path):
    ini = _config(tmp_path, "XYZ")
    ini.write_text(ini.read_text().replace(" coordinates=XYZ kinstype=BOTH", ""))
    assert joint_coordinates(read_ini(ini), ini, _machine()) == "XYZ"


def test_joints_from_the_machine_file_when_the_ini_has_none(tmp_path):
    ini = _config(tmp_path, "XYYZ")
    ini.write_text(ini.read_text().replace(" coordinates=XYYZ kinstype=BOTH", ""))
    assert joint_coordinates(read_ini(ini), ini, _machine(joints=list("XYYZ"))) == "XYYZ"
    with pytest.raises(InputError, match="JOINTS = 4 but 3 joints"):
        joint_coordinates(read_ini(ini), ini, _machine())


def test_cli_writes_the_merged_configuration(tmp_path):
    ini = _config(tmp_path)
    write_error_tables(tmp_path / "errors.csv", _tables(np.random.default_rng(6)))
    result = run_cli(
        "comp",
        *("--errors", str(tmp_path / "errors.csv"), "--out", str(tmp_path / "out")),
        *("--controller", "linuxcnc-volumetric", "--ini", str(ini)),
    )
    assert result.returncode == 0, result.stderr
    written = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert written == sorted(
        ["machine_volcomp.hal", "machine_volcomp.ini", TABLE_FILE, WIRING_FILE]
        + [f"{TABLE_FILE}.history"]  # the table file's lines are the component's: no comment
    )
    check = subprocess.run(
        ["sha256sum", "-c", f"{TABLE_FILE}.history"],
        cwd=tmp_path / "out",
        capture_output=True,
        text=True,
        check=False,
    )
    assert check.returncode == 0 and f"{TABLE_FILE}: OK" in check.stdout, check.stderr


def test_cli_writes_through_the_comp_step(tmp_path, monkeypatch):
    """``comp --controller linuxcnc-volumetric`` writes through the step layer's
    volumetric_comp_step (a spy in its place sees the call), with --force checked there."""
    import xmalign.cli.linuxcnc_volumetric as command
    from xmalign import steps

    calls = []

    def spy(*args, **kwargs):
        calls.append(args[2])
        return steps.volumetric_comp_step(*args, **kwargs)

    monkeypatch.setattr(command, "volumetric_comp_step", spy)
    ini = _config(tmp_path)
    write_error_tables(tmp_path / "errors.csv", _tables(np.random.default_rng(6)))
    args = ("comp", "--errors", str(tmp_path / "errors.csv"), "--out", str(tmp_path / "out"))
    result = run_in_process(*args, "--controller", "linuxcnc-volumetric", "--ini", str(ini))
    assert result.returncode == 0, result.stderr
    assert calls == [tmp_path / "out"]
    again = run_in_process(*args, "--controller", "linuxcnc-volumetric", "--ini", str(ini))
    assert again.returncode == 2 and "--force" in again.stderr


def test_cli_without_ini_is_one_line_error(tmp_path):
    write_error_tables(tmp_path / "errors.csv", _tables(np.random.default_rng(6)))
    result = run_cli(
        "comp",
        *("--errors", str(tmp_path / "errors.csv"), "--out", str(tmp_path / "out")),
        *("--controller", "linuxcnc-volumetric"),
    )
    assert_one_line_error(result, "--ini")


def test_machine_file_bound_of_the_correction(reference_machine):
    data = reference_machine.model_dump()
    assert data["cnc"]["max_correction_um"] == 100.0
    data["cnc"]["max_correction_um"] = 0
    with pytest.raises(InputError, match="cnc.max_correction_um"):
        parse_machine(data, "m.yaml")
