"""Each controller writer formats the shared fit as its manual says."""

from __future__ import annotations

import re

import numpy as np
import pytest

from tests.xmalign.comp.conftest import make_machine, make_tables, with_reversal
from xmalign.comp import compensate, fanuc, fit_for, heidenhain, isg, linuxcnc, sinumerik
from xmalign.errors import InputError, OutOfRangeError


def _files(controller, tables, machine=None):
    return compensate(machine or make_machine(controller=controller), tables, controller).files


def test_sinumerik_lec_is_the_error_zero_at_the_reference_with_named_axes():
    machine = make_machine(axis_names={"X": "X1", "Y": "Y1", "Z": "Z1"})
    text = _files("sinumerik", make_tables({"EXX": [3, 10, 12, 5, 0]}), machine)["AX_EEC.INI"]
    lines = text.splitlines()
    assert lines[0] == "%_N_AX_EEC_INI" and "CHANDATA(1)" in lines and lines[-1] == "M17"
    for expected in (
        "$AA_ENC_COMP[0,0,X1]=0.000000",  # zero at the reference point x = 0
        "$AA_ENC_COMP[0,1,X1]=0.007000",  # +7 um: the error itself (moves the axis negative)
        "$AA_ENC_COMP[0,2,X1]=0.009000",
        "$AA_ENC_COMP_STEP[0,X1]=100.000000",
        "$AA_ENC_COMP_MIN[0,X1]=0.000000",
        "$AA_ENC_COMP_MAX[0,X1]=400.000000",
        "$AA_ENC_COMP_MIN[0,Z1]=-200.000000",
        "$AA_ENC_COMP_IS_MODULO[0,X1]=0",
    ):
        assert expected in lines
    assert "MD32700" in text


def test_sinumerik_cec_cross_tables_reversal_and_activation():
    tables = with_reversal(make_tables({"EYX": [0, 10, 0, 0, 0]}, EC0Y=10.0), "EXX", 2.0)
    lines = _files("sinumerik", tables)["NC_CEC.INI"].splitlines()
    assert lines[0] == "%_N_NC_CEC_INI"
    index = next(i for i, line in enumerate(lines) if "EYX fitted" in line)
    table = lines[index].split()[2].rstrip(":")
    # correction = minus the error: -10 um at x = 100
    assert f"$AN_CEC[{table},1]=-0.010000" in lines
    assert f"$AN_CEC_INPUT_AXIS[{table}]=(AX1)" in lines
    assert f"$AN_CEC_OUTPUT_AXIS[{table}]=(AX2)" in lines
    # EXY carries EC0Y: error -y*EC0Y, correction +y*EC0Y = +3 um at y = 300
    index = next(i for i, line in enumerate(lines) if "EXY fitted" in line)
    table = lines[index].split()[2].rstrip(":")
    assert f"$AN_CEC[{table},4]=0.003000" in lines
    # reversal: X returns to its reference (x = 0, the lower end) moving '-', so the LEC is
    # the '-' table (zero there) and one CEC table on X itself, acting in '+' only, carries
    # the reversal: E+ - E- = -4 um, correction +4 um (6 cross tables come first)
    assert "$AN_CEC_DIRECTION[6]=1" in lines and "$AN_CEC[6,0]=0.004000" in lines
    assert not any(line.startswith("$AN_CEC[7,") for line in lines)
    # SD41300: every table is loaded switched off (they are switched on one at a time after
    # the sign check), SD41310 weight 1
    assert not any("=TRUE" in line for line in lines if not line.startswith(";"))
    for t in range(7):
        assert f"$SN_CEC_TABLE_ENABLE[{t}]=FALSE" in lines
        assert f"$SN_CEC_TABLE_WEIGHT[{t}]=1.0" in lines
    # the tables carry the reversal: the control's backlash goes to 0, said in the file
    assert any("set MD32450 $MA_BACKLASH to 0 on X" in line for line in lines)


@pytest.mark.parametrize("series", ["840D sl", "828D"])
def test_sinumerik_files_say_the_load_order_of_k3_page_237(series):
    """K3 03/2013 p. 237: the tables load only while MD32700 = 0 and MD32710 = 0; MD38000 /
    MD18342 reformat the static user memory at the next start (archive first); an 828D
    has no MD18342. The sign check measures the axis, not a compensation display."""
    tables = with_reversal(make_tables({"EYX": [0, 10, 0, 0, 0]}), "EXX", 2.0)
    machine = make_machine(controller="sinumerik", series=series)
    files = compensate(machine, tables, "sinumerik").files
    for name in ("AX_EEC.INI", "NC_CEC.INI"):
        text = files[name]
        assert "MD32700 $MA_ENC_COMP_ENABLE[0]=0 AND MD32710 $MA_CEC_ENABLE=0" in text
        assert "p. 237" in text and "archive the NC" in text
        assert "reformats the static user memory at the next start" in text
        assert ("MD18342 $MN_MM_CEC_MAX_POINTS" in text) == (series != "828D"), name
        assert ("828D: no MD18342" in text) == (series == "828D"), name
    check = compensate(machine, tables, "sinumerik").loading.check
    assert "dial gauge" in check and "encoder actual value" in check
    assert "one at a time" in check


@pytest.mark.parametrize("reference_mm", [[0, 0, 0], [200, 150, -100], [400, 300, -200]])
def test_fanuc_no_axis_reference_number_is_another_axis_point(reference_mm):
    """Parameter 3620 of an axis never names a point number of another axis (Y's reference
    3620 = 150 once was X's last negative-direction point)."""
    tables = make_tables({"EXX": [0, -2, -3, -1, 1]})
    with_reversal(tables, "EXX", 1.0)
    with_reversal(tables, "EYY", 1.0)
    returns = {"X": "+", "Y": "-", "Z": "+"}
    machine = make_machine(controller="fanuc", reference_mm=reference_mm, reference_return=returns)
    pitch = fanuc.pitch_tables(fit_for(machine, tables, "fanuc"), machine)
    used = {}
    for table in pitch:
        used[table.axis] = set(range(table.first_number, table.last_number + 1))
        if table.negative_first_number is not None:
            negative = table.negative_first_number
            used[table.axis] |= set(range(negative, negative + table.count))
    for table in pitch:
        for other, numbers in used.items():
            if other != table.axis:
                assert table.reference_number not in numbers, (table.axis, other)
                assert not numbers & used[table.axis], (table.axis, other)


def test_sinumerik_refuses_more_points_than_md38000(monkeypatch):
    monkeypatch.setattr(sinumerik, "MAX_EEC_POINTS", 4)
    with pytest.raises(OutOfRangeError, match="limit of 4"):
        _files("sinumerik", make_tables(n=5))


def test_fanuc_incremental_values_and_parameters():
    tables = make_tables({"EXX": [0, -2, -3, -1, 1], "EZZ": [4, 3, 2, 1, 0]})
    lines = _files("fanuc", tables)["PITCH.TXT"].splitlines()
    assert lines[0] == "%" and lines[-1] == "%"
    # X: reference (x = 0) at its negative end: point R = 0, sections 1..4 are points 1..4
    # Y: reference 5, not X's last point 4 (a gap), points 6..9 (75 mm, 4 sections);
    # Z: -200..0, reference at its + end: points 10..13, reference 13
    assert "N03620A1P0A2P5A3P13;" in lines
    assert "N03621A1P1A2P6A3P10;" in lines
    assert "N03622A1P4A2P9A3P13;" in lines
    assert "N03623A1P1A2P1A3P1;" in lines
    assert "N03624A1P100000A2P75000A3P50000;" in lines
    assert not any(line.startswith("N03626") for line in lines)  # no direction data
    # X correction -(e - e_ref) = 0, 2, 3, 1, -1 -> increments 2, 1, -2, -2 at points 1..4
    assert [line for line in lines if line.startswith("N1000")][:4] == [
        "N10001P2;",
        "N10002P1;",
        "N10003P-2;",
        "N10004P-2;",
    ]
    # Z: corrections -4, -3, -2, -1, 0 (zero at z = 0) -> increments 1, 1, 1, 1
    assert [line for line in lines if line.startswith(("N10010", "N10013"))] == [
        "N10010P1;",
        "N10013P1;",
    ]


def test_fanuc_bidirectional_pitch_and_detection_unit():
    tables = with_reversal(make_tables({"EXX": [0, 5, 0, 0, 0]}), "EXX", 1.0)
    machine = make_machine(controller="fanuc", detection_unit_um=0.1)
    files = _files("fanuc", tables, machine)
    lines = files["PITCH.TXT"].splitlines()
    assert "N03624A1P1000000A2P750000A3P500000;" in lines  # 100 mm in 0.1 um units
    # negative-direction table follows the positive one. X returns to its reference (x = 0,
    # the lower end of its travel) moving '-' (A-77810E: 3627 is the value at the reference
    # approached against the return direction), so the '-' table is zero there and 3627
    # holds the '+' correction there: -(e+ - e-) = -(-1 - 1) um = +2 um = +20 units
    assert "N03626A1P5A2P0A3P0;" in lines
    assert "N03627A1P20A2P0A3P0;" in lines
    readme = files["PITCH_README.TXT"]
    assert "3605#0" in readme and "0.1 um" in readme and "X 0 (-)" in readme
    pitch = fanuc.pitch_tables(compensate(machine, tables, "fanuc").fit, machine)[0]
    assert pitch.negative_values is not None
    np.testing.assert_array_equal(pitch.values, [-50, 50, 0, 0])  # forward -(e+ - e+(0))
    # returning '+' instead, the '+' table is the zero one and 3627 the '-' correction
    returning_up = make_machine(
        controller="fanuc", detection_unit_um=0.1, reference_return={"X": "+"}
    )
    assert "N03627A1P-20A2P0A3P0;" in _files("fanuc", tables, returning_up)["PITCH.TXT"]


def test_fanuc_straightness_is_optional_and_leaves_the_pitch_tables_alone():
    pitch_only = make_tables({"EXX": [0, -2, -3, -1, 1]})
    bent = make_tables({"EXX": [0, -2, -3, -1, 1], "EYX": [0, 3, 4, 3, 0]})
    assert _files("fanuc", bent)["PITCH.TXT"] == _files("fanuc", pitch_only)["PITCH.TXT"]
    fit = compensate(make_machine(controller="fanuc"), bent, "fanuc").fit
    assert fit.after_optional_um == pytest.approx(0.0, abs=1e-9) and fit.after_um > 1.0
    text = _files("fanuc", bent)["STRAIGHTNESS.TXT"].splitlines()
    moving_x = text[text.index("moving axis X") + 1 :][:6]
    assert moving_x[0].split() == ["X", "mm", "Y", "Z"]
    # the Y correction is minus the straightness error at X's pitch points (um)
    assert [row.split()[1] for row in moving_x[1:]] == ["+0", "-3", "-4", "-3", "+0"]
    assert "moving axis Y" in text and "moving axis Z" in text


def test_fanuc_magnification_and_point_limit():
    big = make_tables({"EXX": [0, 300, 600, 900, 1200]})
    assert "N03623A1P3A2P1A3P1;" in _files("fanuc", big)["PITCH.TXT"]
    with pytest.raises(OutOfRangeError, match="limit of 128"):
        _files("fanuc", make_tables(n={"X": 200}))


def test_heidenhain_com_and_cma():
    tables = with_reversal(
        make_tables({"EXX": [0, 5, 0, 0, 0], "EZX": [0, 0, 4, 0, 0]}), "EXX", 1.0
    )
    files = _files("heidenhain", tables)
    com = files["X.COM"].splitlines()
    assert com[0] == "BEGIN X.COM MM" and com[-1] == "[END]"
    assert com[1].split() == ["NR", "AXISPOS", "X", "Y", "Z", "BACKLASH"]
    # the error itself (the manuals' error curve); forward in X, negative direction in BACKLASH;
    # X returns to its reference (x = 0) moving '-', so BACKLASH is zero there: e- - e-(0)
    assert com[2].split() == ["0", "+0.0000", "-0.00200", "+0.00000", "+0.00000", "+0.00000"]
    assert com[3].split() == ["1", "+100.0000", "+0.00300", "+0.00000", "+0.00000", "+0.00500"]
    assert com[4].split()[4] == "+0.00400"
    assert files["Y.COM"].splitlines()[1].split() == ["NR", "AXISPOS", "X", "Y", "Z"]
    cma = files["CONFIG.CMA"].splitlines()
    assert cma[1].split() == ["NR", "X", "Y", "Z", "ACTIVE"]
    assert cma[2].split() == ["0", "X.COM", "Y.COM", "Z.COM", "*"]
    assert heidenhain.MAX_ENTRIES == 256


def test_linuxcnc_type0_triplets_are_actual_positions():
    tables = with_reversal(make_tables({"EXX": [0, 5, 0, 0, 0]}), "EXX", 2.0)
    files = _files("linuxcnc", tables)
    assert files["x.comp"].splitlines()[1] == "100.000000 100.003000 100.007000"
    assert files["z.comp"].splitlines()[0] == "-200.000000 -200.000000 -200.000000"
    assert "[JOINT_2]\nCOMP_FILE = z.comp\nCOMP_FILE_TYPE = 0" in files["joints.ini"]
    with pytest.raises(OutOfRangeError, match="limit of 256"):
        _files("linuxcnc", make_tables(n={"X": 257}))


def test_linuxcnc_gantry_gives_both_y_joints_the_y_table():
    machine = make_machine(joints=["X", "Y", "Y", "Z"])
    keys = _files("linuxcnc", make_tables(), machine)["joints.ini"]
    assert re.findall(r"\[JOINT_(\d)\]\nCOMP_FILE = (\w)", keys) == [
        ("0", "x"),
        ("1", "y"),
        ("2", "y"),
        ("3", "z"),
    ]


def test_isg_volumetric_csv():
    tables = make_tables({"EAX": [0, 7, 0, 0, 0], "EXY": [0, 3, 0, 0, 0]}, EC0Y=12.5)
    text = _files("isg", tables)[isg.FILE_NAME]
    lines = text.splitlines()
    start = lines.index("C0Y A0Z B0Z")
    assert lines[start : start + 2] == ["C0Y A0Z B0Z", "1.25e-05 0 0"]
    assert all(line.startswith("//") for line in lines[:start])  # notes are comments
    x_header = lines.index("X EXX EYX EZX EAX EBX ECX")
    assert lines[x_header + 2].split()[:5] == ["100", "0", "0", "0", "7e-06"]
    table_side = _files("isg", tables, make_machine("YFXZ", "isg"))[isg.FILE_NAME].splitlines()
    y_header = table_side.index("Y EXY EYY EZY EAY EBY ECY")
    assert table_side[y_header + 2].split()[1] == "-0.003"  # workpiece-side axis: physical sign


def test_machine_file_keys_are_checked():
    with pytest.raises(InputError, match="joints"):
        make_machine(joints=["X", "Y", "Y"])
    with pytest.raises(InputError, match="detection_unit_um"):
        make_machine(detection_unit_um=0)
    assert linuxcnc.MODEL.directional and fanuc.MODEL.directional


#: Each family's comment mark in the files that take comments (the rest get NAME.history).
COMMENT_MARKS = {
    "AX_EEC.INI": ";",
    "NC_CEC.INI": ";",
    "PITCH_README.TXT": "#",
    "STRAIGHTNESS.TXT": "#",
    "HEIDENHAIN.TXT": "#",
    "joints.ini": "#",
    "vol_comp.csv": "//",
}


@pytest.mark.parametrize("controller", ["sinumerik", "fanuc", "heidenhain", "linuxcnc", "isg"])
def test_every_controller_file_carries_its_history(controller, tmp_path):
    """Format, software, time and the error-table file's SHA-256: as comments where the
    format takes them, else in NAME.history, which ``sha256sum -c`` checks."""
    import hashlib
    import subprocess
    from pathlib import Path

    from tests.cli_helpers import run_in_process

    errors = Path(__file__).resolve().parents[3] / "examples" / "errors.csv"
    out = tmp_path / "comp"
    result = run_in_process(
        "comp", "--errors", str(errors), "--out", str(out), "--controller", controller
    )
    assert result.returncode == 0, result.stderr
    input_line = f"input errors: {hashlib.sha256(errors.read_bytes()).hexdigest()}  {errors}"
    written = sorted(path.name for path in out.iterdir())
    assert written
    for name in written:
        if name.endswith(".history"):
            continue
        text = (out / name).read_text()
        mark = COMMENT_MARKS.get(name)
        if mark is None:  # a format without comments: the history beside it, checkable
            history = (out / f"{name}.history").read_text()
            assert f"# format: xmalign.comp.{controller}/1\n" in history
            assert f"# {input_line}\n" in history and "# software: xmalign " in history
            check = subprocess.run(
                ["sha256sum", "-c", f"{name}.history"], cwd=out, capture_output=True, text=True
            )
            assert check.returncode == 0 and f"{name}: OK" in check.stdout, check.stderr
        else:
            assert f"{mark} format: xmalign.comp.{controller}/1\n" in text, name
            assert f"{mark} {input_line}\n" in text and f"{mark} created_utc: " in text, name
            assert not (out / f"{name}.history").exists()
