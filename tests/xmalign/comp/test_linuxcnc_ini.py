"""LinuxCNC pitch tables: joints from the machine file or the INI, and the merged INI."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import assert_one_line_error, run_cli

from tests.xmalign.comp.conftest import make_machine, make_tables
from xmalign.comp import compensate
from xmalign.comp.linuxcnc import (
    backlash_warnings,
    ini_files,
    ini_value,
    merge_ini,
    read_machine_ini,
    resolve_joints,
    units_per_mm,
)
from xmalign.errors import InputError
from xmalign.formats.error_tables import write_error_tables

OUT = Path("/cfg/out")


def _ini(coordinates: str = "XYZ", joint_keys: dict[int, list[str]] | None = None) -> str:
    """A LinuxCNC INI with one [JOINT_n] section per letter (extra lines per joint)."""
    lines = [
        "[KINS]",
        f"KINEMATICS = trivkins coordinates={coordinates}",
        f"JOINTS = {len(coordinates)}",
        "",
        "[TRAJ]",
        f"COORDINATES = {' '.join(coordinates)}",
        "",
    ]
    for number in range(len(coordinates)):
        extra = (joint_keys or {}).get(number, [])
        lines += [f"[JOINT_{number}]", "TYPE = LINEAR", "MAX_VELOCITY = 50", *extra, ""]
    return "\n".join(lines) + "\n"


def _section(text: str, name: str) -> list[str]:
    lines = text.splitlines()
    start = lines.index(f"[{name}]")
    end = next((i for i in range(start + 1, len(lines)) if lines[i].startswith("[")), len(lines))
    return [line for line in lines[start + 1 : end] if line.strip()]


def test_keys_go_inside_the_existing_sections_and_the_other_keys_stay():
    text = _ini(joint_keys={1: ["BACKLASH = 0.01", "# a comment", "HOME = 0"]})
    merged = merge_ini(text, ["X", "Y", "Z"], OUT, "mill.ini")
    assert _section(merged, "JOINT_1") == [
        "TYPE = LINEAR",
        "MAX_VELOCITY = 50",
        "BACKLASH = 0.01",
        "# a comment",
        "HOME = 0",
        "COMP_FILE = /cfg/out/y.comp",
        "COMP_FILE_TYPE = 0",
    ]
    assert merged.count("[JOINT_1]") == 1  # never a second section LinuxCNC would ignore
    assert _section(merged, "KINS") == _section(text, "KINS")


def test_existing_comp_keys_are_replaced_in_place_not_duplicated():
    old = ["COMP_FILE = old.comp", "COMP_FILE_TYPE = 1", "FERROR = 1"]
    merged = merge_ini(_ini(joint_keys={0: old}), ["X", "Y", "Z"], OUT, "mill.ini")
    section = _section(merged, "JOINT_0")
    assert "old.comp" not in merged and "COMP_FILE_TYPE = 1" not in section
    assert section[-3:] == ["FERROR = 1", "COMP_FILE = /cfg/out/x.comp", "COMP_FILE_TYPE = 0"]
    assert ini_value(merged.splitlines(), "JOINT_0", "COMP_FILE_TYPE") == "0"


def test_gantry_gives_both_y_joints_the_y_table_and_z_the_z_table():
    merged = merge_ini(_ini("XYYZ"), ["X", "Y", "Y", "Z"], OUT, "gantry.ini")
    lines = merged.splitlines()
    files = [Path(ini_value(lines, f"JOINT_{n}", "COMP_FILE")).name for n in range(4)]
    assert files == ["x.comp", "y.comp", "y.comp", "z.comp"]


def test_a_missing_joint_section_is_one_clear_error():
    text = _ini("XYZ").replace("[JOINT_2]", "[JOINT_7]")
    with pytest.raises(InputError, match=r"mill.ini: no \[JOINT_2\] section"):
        merge_ini(text, ["X", "Y", "Z"], OUT, "mill.ini")
    with pytest.raises(InputError, match=r"mill.ini: \[KINS\] JOINTS = 3 but 4 joints"):
        merge_ini(_ini("XYZ"), ["X", "Y", "Y", "Z"], OUT, "mill.ini")


def test_relative_paths_of_the_ini_folder_become_absolute(tmp_path):
    (tmp_path / "mill.hal").write_text("")
    text = "[HAL]\nHALFILE = mill.hal\nHALFILE = LIB:basic_sim.tcl\nPOSTGUI = missing.hal\n"
    merged = merge_ini(text + _ini(), ["X", "Y", "Z"], OUT, "mill.ini", tmp_path)
    assert f"HALFILE = {tmp_path.resolve() / 'mill.hal'}" in merged
    assert "HALFILE = LIB:basic_sim.tcl" in merged and "POSTGUI = missing.hal" in merged


def test_joints_from_the_machine_file_else_the_ini_else_xyz():
    gantry = make_machine(joints=["X", "Y", "Y", "Z"])
    assert resolve_joints(gantry, None, "m.ini") == ["X", "Y", "Y", "Z"]
    assert resolve_joints(make_machine(), _ini("XYYZ").splitlines(), "m.ini") == list("XYYZ")
    traj_only = _ini("YXZ").replace("KINEMATICS = trivkins coordinates=YXZ", "KINEMATICS = x")
    assert resolve_joints(make_machine(), traj_only.splitlines(), "m.ini") == list("YXZ")
    assert resolve_joints(make_machine(), ["[EMC]"], "m.ini") == ["X", "Y", "Z"]
    assert resolve_joints(gantry, _ini("XYYZ").splitlines(), "m.ini") == list("XYYZ")


def test_machine_file_and_ini_that_disagree_or_name_other_axes_are_refused():
    gantry = make_machine(joints=["X", "Y", "Y", "Z"])
    with pytest.raises(InputError, match="m.ini: the INI's joints XYZ differ .* XYYZ"):
        resolve_joints(gantry, _ini("XYZ").splitlines(), "m.ini")
    with pytest.raises(InputError, match="m.ini: joints XYZA must give X, Y and Z"):
        resolve_joints(make_machine(), _ini("XYZA").splitlines(), "m.ini")
    with pytest.raises(InputError, match="joints"):
        make_machine(joints=["X", "Y", "A"])  # the machine file knows X, Y and Z only


def test_comp_with_an_ini_that_lacks_a_joint_section_exits_with_one_line(tmp_path):
    write_error_tables(tmp_path / "errors.csv", make_tables())
    ini = tmp_path / "mill.ini"
    ini.write_text(_ini("XYYZ").replace("[JOINT_3]", "[JOINT_9]"))
    result = run_cli(
        "comp",
        *("--errors", str(tmp_path / "errors.csv"), "--controller", "linuxcnc"),
        *("--ini", str(ini), "--out", str(tmp_path / "out")),
    )
    assert_one_line_error(result, str(ini), "[JOINT_3]")
    assert not (tmp_path / "out" / "x.comp").exists()  # nothing half written


def test_the_merged_ini_starts_with_its_history(tmp_path):
    from xmalign.formats.provenance import FileSource

    ini = tmp_path / "mill.ini"
    ini.write_text(_ini())
    merged = merge_ini(_ini(), ["X", "Y", "Z"], OUT, str(ini), inputs=(FileSource.of("ini", ini),))
    lines = merged.splitlines()
    assert lines[0] == "# format: xmalign.comp.linuxcnc/1"
    assert any(line.startswith("# input ini: ") and line.endswith(f"  {ini}") for line in lines)
    assert merged.endswith(merge_ini(_ini(), ["X", "Y", "Z"], OUT, str(ini)).split("\n", 3)[3])


def test_linear_units_as_linuxcnc_reads_them():
    """Names and numbers (units per mm) of src/emc/ini/emcIniFile.cc; mm when not given."""
    with_units = lambda value: _ini().replace("[TRAJ]\n", f"[TRAJ]\nLINEAR_UNITS = {value}\n")  # noqa: E731
    assert units_per_mm(_ini().splitlines(), "m.ini") == 1.0
    for value, expected in [("mm", 1.0), ("metric", 1.0), ("inch", 1 / 25.4), ("IN", 1 / 25.4)]:
        assert units_per_mm(with_units(value).splitlines(), "m.ini") == expected
    assert units_per_mm(with_units("0.5").splitlines(), "m.ini") == 0.5
    for bad in ("furlong", "-1", "0", "nan", "inf"):
        with pytest.raises(InputError, match=r"m\.ini: \[TRAJ\] LINEAR_UNITS"):
            units_per_mm(with_units(bad).splitlines(), "m.ini")


def test_an_inch_ini_gets_its_comp_files_in_inches_and_the_backlash_folded_in(tmp_path):
    """X's table in inches for an inch INI; cnc.backlash_um as LinuxCNC's BACKLASH applied
    it: +B/2 added to the correction moving + (actual - B/2), -B/2 moving -."""
    tables = make_tables({"EXX": [4.0, -2.0, 0.0, 6.0, 1.0]})
    plain = compensate(make_machine(), tables, "linuxcnc")
    folded = compensate(make_machine(backlash_um={"X": 8.0}), tables, "linuxcnc")
    rows = np.loadtxt(io.StringIO(plain.files["x.comp"]))
    # the error as measured, up to the constant the fit leaves free
    np.testing.assert_allclose(
        np.diff(rows[:, 1] - rows[:, 0]), [-6e-3, 2e-3, 6e-3, -5e-3], atol=1e-9
    )
    shifted = np.loadtxt(io.StringIO(folded.files["x.comp"])) - rows
    np.testing.assert_allclose(shifted[:, 1:], np.tile([-4e-3, 4e-3], (len(rows), 1)), atol=2e-9)
    assert "cnc.backlash_um X 8 um" in folded.loading.reversal
    ini = tmp_path / "mill.ini"
    ini.write_text(_ini().replace("[TRAJ]\n", "[TRAJ]\nLINEAR_UNITS = inch\n"))
    machine_ini = read_machine_ini(make_machine(), ini)
    inch = ini_files(plain.fit, make_machine(), machine_ini, tmp_path / "out")
    np.testing.assert_allclose(np.loadtxt(io.StringIO(inch["x.comp"])) * 25.4, rows, atol=2e-7)


def test_a_backlash_in_the_ini_is_told_unless_the_tables_carry_that_one(tmp_path):
    ini = tmp_path / "mill.ini"
    ini.write_text(_ini(joint_keys={0: ["BACKLASH = 0.008"], 2: ["BACKLASH = 0"]}))
    machine_ini = read_machine_ini(make_machine(), ini)
    (told,) = backlash_warnings(machine_ini, make_machine())
    assert "[JOINT_0] BACKLASH = 0.008 (8 um)" in told and "cnc.backlash_um {X: 8}" in told
    assert backlash_warnings(machine_ini, make_machine(backlash_um={"X": 8.0})) == []
    (other,) = backlash_warnings(machine_ini, make_machine(backlash_um={"X": 5.0}))
    assert "is not cnc.backlash_um X 5 um" in other
