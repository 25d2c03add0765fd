"""Each controller writer against small examples written from its manual."""

from __future__ import annotations

import numpy as np
import pytest

from xmalign.comp import fanuc, heidenhain, isg, linuxcnc, remaining_errors, sinumerik
from xmalign.errors import OutOfRangeError
from xmalign.formats.error_tables import ErrorTableSet, Table
from xmalign.rigid_body import MOTION_NAMES, SQUARENESS_NAMES, Chain

FYXZ = Chain.parse("FYXZ")
TRAVEL = {"X": (0.0, 400.0), "Y": (0.0, 300.0), "Z": (-200.0, 0.0)}


def _tables(values: dict[str, list[float]] | None = None, n: int = 5, **squareness: float):
    """Zero tables on 5 points per axis; ``values`` overrides (um or urad)."""
    values = values or {}
    result = ErrorTableSet()
    for name in MOTION_NAMES:
        low, high = TRAVEL[name[2]]
        positions = np.linspace(low, high, n)
        scale = 1e-3 if name[1] in "XYZ" else 1e-6
        v = np.asarray(values.get(name, np.zeros(n)), dtype=float) * scale
        result.tables[name] = Table(positions, v, np.zeros(n))
    result.squareness = {s: (squareness.get(s, 0.0) * 1e-6, 0.0) for s in SQUARENESS_NAMES}
    return result


def _with_reversal(tables: ErrorTableSet, name: str, half_um: float) -> ErrorTableSet:
    mean = tables.tables[name]
    tables.tables[name + "+"] = Table(mean.positions_mm, mean.values - half_um * 1e-3, mean.u95)
    tables.tables[name + "-"] = Table(mean.positions_mm, mean.values + half_um * 1e-3, mean.u95)
    return tables


def test_sinumerik_eec_like_the_manual_example():
    text = sinumerik.render(_tables({"EXX": [3, 10, 12, 5, 0]}), FYXZ)["AX_EEC.INI"]
    lines = text.splitlines()
    assert lines[0] == "%_N_AX_EEC_INI" and "CHANDATA(1)" in lines and lines[-1] == "M17"
    for expected in (
        "$AA_ENC_COMP[0,0,AX1]=0.003000",  # +3 um: the error itself (moves the axis negative)
        "$AA_ENC_COMP[0,2,AX1]=0.012000",
        "$AA_ENC_COMP_STEP[0,AX1]=100.000000",
        "$AA_ENC_COMP_MIN[0,AX1]=0.000000",
        "$AA_ENC_COMP_MAX[0,AX1]=400.000000",
        "$AA_ENC_COMP_MIN[0,AX3]=-200.000000",
        "$AA_ENC_COMP_IS_MODULO[0,AX1]=0",
    ):
        assert expected in lines


def test_sinumerik_cec_straightness_squareness_and_reversal():
    tables = _with_reversal(_tables({"EYX": [0, 10, 0, 0, 0]}, EC0Y=10.0), "EXX", 2.0)
    lines = sinumerik.render(tables, FYXZ)["NC_CEC.INI"].splitlines()
    assert lines[0] == "%_N_NC_CEC_INI"
    # table 0: EYX, Y = f(X), correction = minus the error
    assert "$AN_CEC[0,1]=-0.010000" in lines
    assert "$AN_CEC_INPUT_AXIS[0]=(AX1)" in lines and "$AN_CEC_OUTPUT_AXIS[0]=(AX2)" in lines
    # EXY carries EC0Y: error -y*EC0Y, correction +y*EC0Y = +3 um at y = 300
    index = next(i for i, line in enumerate(lines) if "EXY with squareness" in line)
    table = lines[index].split()[2].rstrip(":")
    assert f"$AN_CEC[{table},4]=0.003000" in lines
    # reversal: one table per direction on X itself
    assert "$AN_CEC_DIRECTION[6]=1" in lines and "$AN_CEC_DIRECTION[7]=-1" in lines
    assert "$AN_CEC[6,0]=0.002000" in lines and "$AN_CEC[7,0]=-0.002000" in lines


def test_sinumerik_refuses_more_points_than_md38000():
    with pytest.raises(OutOfRangeError, match="limit of 5000"):
        sinumerik.render(_tables(n=5001), FYXZ)


def test_fanuc_incremental_values_and_parameters():
    tables = _tables({"EXX": [0, -2, -3, -1, 1], "EZZ": [4, 3, 2, 1, 0]})
    lines = fanuc.render(tables, FYXZ)["PITCH.TXT"].splitlines()
    assert lines[0] == "%" and lines[-1] == "%"
    # X: reference (machine zero) at the first point 0; Y: points 5..9; Z: -200..0 -> 10..14
    assert "N03620A1P0A2P5A3P14;" in lines
    assert "N03621A1P0A2P5A3P10;" in lines
    assert "N03622A1P4A2P9A3P14;" in lines
    assert "N03623A1P1A2P1A3P1;" in lines
    assert "N03624A1P100000A2P75000A3P50000;" in lines
    # correction -(e - e_ref) = 0, 2, 3, 1, -1 -> increments 0, 2, 1, -2, -2
    assert [line for line in lines if line.startswith("N1000")][:5] == [
        "N10000P0;",
        "N10001P2;",
        "N10002P1;",
        "N10003P-2;",
        "N10004P-2;",
    ]
    # Z: reference at z = 0 (e = 0); corrections -4, -3, -2, -1, 0 -> increments 0, 1, 1, 1, 1
    assert lines[lines.index("N10010P0;") + 1] == "N10011P1;"


def test_fanuc_magnification_and_point_limit():
    big = _tables({"EXX": [0, 300, 600, 900, 1200]})
    assert "N03623A1P3A2P1A3P1;" in fanuc.render(big, FYXZ)["PITCH.TXT"]
    with pytest.raises(OutOfRangeError, match="limit of 128"):
        fanuc.render(_tables(n=200), FYXZ)


def test_heidenhain_com_and_cma():
    tables = _with_reversal(_tables({"EXX": [0, 5, 0, 0, 0], "EZX": [0, 0, 4, 0, 0]}), "EXX", 1.0)
    files = heidenhain.render(tables, FYXZ)
    com = files["X.COM"].splitlines()
    assert com[0] == "BEGIN X.COM MM" and com[-1] == "[END]"
    assert com[1].split() == ["NR", "AXISPOS", "X", "Y", "Z", "BACKLASH"]
    assert com[3].split() == ["1", "+100.0000", "-0.00400", "+0.00000", "+0.00000", "-0.00600"]
    assert com[4].split()[4] == "-0.00400"
    assert files["Y.COM"].splitlines()[1].split() == ["NR", "AXISPOS", "X", "Y", "Z"]
    cma = files["CONFIG.CMA"].splitlines()
    assert cma[1].split() == ["NR", "X", "Y", "Z", "ACTIVE"]
    assert cma[2].split() == ["0", "X.COM", "Y.COM", "Z.COM", "*"]
    with pytest.raises(OutOfRangeError, match="limit of 256"):
        heidenhain.render(_tables(n=300), FYXZ)


def test_linuxcnc_type0_triplets_are_actual_positions():
    tables = _with_reversal(_tables({"EXX": [0, 5, 0, 0, 0]}), "EXX", 2.0)
    files = linuxcnc.render(tables, FYXZ)
    assert files["joint0.comp"].splitlines()[1] == "100.000000 100.003000 100.007000"
    assert files["joint2.comp"].splitlines()[0] == "-200.000000 -200.000000 -200.000000"
    ini = files["joints.ini"]
    assert "[JOINT_2]\nCOMP_FILE = joint2.comp\nCOMP_FILE_TYPE = 0" in ini
    with pytest.raises(OutOfRangeError, match="limit of 256"):
        linuxcnc.render(_tables(n=257), FYXZ)


def test_isg_volumetric_csv():
    tables = _tables({"EAX": [0, 7, 0, 0, 0], "EXY": [0, 3, 0, 0, 0]}, EC0Y=12.5)
    text = isg.render(tables, FYXZ)[isg.FILE_NAME]
    lines = text.splitlines()
    assert lines[3:5] == ["C0Y A0Z B0Z", "1.25e-05 0 0"]
    x_header = lines.index("X EXX EYX EZX EAX EBX ECX")
    assert lines[x_header + 2].split()[:5] == ["100", "0", "0", "0", "7e-06"]
    table_side = isg.render(tables, Chain.parse("YFXZ"))[isg.FILE_NAME].splitlines()
    y_header = table_side.index("Y EXY EYY EZY EAY EBY ECY")
    assert table_side[y_header + 2].split()[1] == "-0.003"  # workpiece-side axis: physical sign


@pytest.mark.parametrize(
    ("module", "kept"),
    [(isg, set()), (fanuc, {"EYX", "EAX"}), (sinumerik, {"EAX"}), (linuxcnc, {"EYX"})],
)
def test_remaining_errors_after_each_controller(module, kept):
    tables = _tables({name: [0, 1, 2, 1, 0] for name in MOTION_NAMES}, EC0Y=5.0)
    remaining = remaining_errors(tables, module.NAME)
    assert kept <= set(remaining.tables)
    assert not ({"EXX", "EYY", "EZZ"} & set(remaining.tables))
    assert ("EC0Y" in remaining.squareness) == (module in (fanuc, linuxcnc))
