"""The controller files xmalign writes against published examples (examples/README.md).

- ``linuxcnc_screwcompX.dat``: LinuxCNC 2.9's own ``COMP_FILE`` sample
  (``docs/examples/sample-configs/sim/screwcompX.dat``, Debian ``linuxcnc-uspace``),
  copied unchanged.
- ``sinumerik_k3_eec_example.ini``: the ``%_N_AX_EEC_INI`` example of the
  SINUMERIK 840D sl Function Manual Extended Functions, K3 "Compensations",
  4.4.2.3 "Example" (6FC5397-1BP40-3BA1, 03/2013, p. 242), points 3 .. 799 left out.
- the FANUC Series 0i-PB Parameter Manual's pitch compensation example, the ISG CSV
  format's programming example and the HEIDENHAIN TNC 306/406 technical manual's
  correction table (values in the tests below).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from tests.xmalign.comp.conftest import make_machine, make_tables, with_reversal
from xmalign.comp import compensate, fanuc
from xmalign.comp.fit import CompensationFit
from xmalign.formats.error_tables import Table
from xmalign.machine import parse_machine
from xmalign.rigid_body import ErrorTables

EXAMPLES = Path(__file__).parent / "examples"
NUMBER = r"[-+]?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?"


def _comp_file_rows(text: str) -> np.ndarray:
    """A type-0 COMP_FILE as LinuxCNC reads it: 'nominal forward reverse' per line, (N, 3)."""
    rows = []
    for line in text.splitlines():
        if line.strip():
            assert re.fullmatch(rf"\s*{NUMBER}\s+{NUMBER}\s+{NUMBER}\s*", line), line
            rows.append([float(v) for v in line.split()])
    return np.array(rows)


def test_our_comp_file_reads_like_linuxcncs_sample():
    sample = _comp_file_rows((EXAMPLES / "linuxcnc_screwcompX.dat").read_text())
    tables = with_reversal(make_tables({"EXX": [0, 5, -3, 2, 0]}), "EXX", 1.5)
    ours = _comp_file_rows(compensate(make_machine(), tables, "linuxcnc").files["x.comp"])
    for rows in (sample, ours):
        # nominal ascending; forward and reverse actual positions within a hair of it
        assert np.all(np.diff(rows[:, 0]) > 0)
        assert np.abs(rows[:, 1:] - rows[:, [0]]).max() < 0.25
    # the sample's reverse column lies above the forward one (backlash-like), as ours
    # does for a table whose '-' pass reads more than the '+' pass
    assert np.all(sample[:, 2] >= sample[:, 1]) and np.all(ours[:, 2] >= ours[:, 1])


def _statements(text: str) -> list[tuple[str, tuple[str, ...], str]]:
    """(variable, indices, value) of every ``$NAME[i,...]=value`` line."""
    found = []
    for line in text.splitlines():
        match = re.fullmatch(r"\$(\w+)\[([^\]]*)\]=(.*)", line.strip())
        if match:
            found.append((match[1], tuple(match[2].split(",")), match[3]))
    return found


def test_our_eec_init_program_has_the_manuals_structure():
    manual = (EXAMPLES / "sinumerik_k3_eec_example.ini").read_text()
    machine = make_machine(axis_names={"X": "X1", "Y": "Y1", "Z": "Z1"})
    tables = make_tables({"EXX": [3, 10, 12, 5, 0]})
    ours = compensate(machine, tables, "sinumerik").files["AX_EEC.INI"]
    for text in (manual, ours):
        lines = [line for line in text.splitlines() if line.strip() and not line.startswith(";")]
        assert lines[0] == "%_N_AX_EEC_INI" and lines[1] == "CHANDATA(1)" and lines[-1] == "M17"
    manual_statements = _statements(manual)
    ours_x1 = [s for s in _statements(ours) if s[1][-1] == "X1"]
    assert {name for name, *_ in manual_statements} == {name for name, *_ in ours_x1}
    for statements in (manual_statements, ours_x1):
        values = {name: float(value) for name, indices, value in statements if len(indices) == 2}
        points = [int(idx[1]) for name, idx, _ in statements if name == "AA_ENC_COMP"]
        assert all(idx[0] == "0" for _, idx, _ in statements)  # compensation table 0
        assert all(re.fullmatch(NUMBER, value) for *_, value in statements)
        # the last point sits at MAX: MIN + STEP x (points - 1)
        span = values["AA_ENC_COMP_MAX"] - values["AA_ENC_COMP_MIN"]
        assert max(points) * values["AA_ENC_COMP_STEP"] == np.float64(span)
        assert values["AA_ENC_COMP_IS_MODULO"] == 0


#: FANUC Series 0i-PB Parameter Manual (B-63980EN/01), parameters 3620-3624, p. 100,
#: "Example 1) For linear axis": reference position at 0 mm is compensation point No. 40,
#: points every 50 mm; the incremental compensation values of points No. 33 .. 49.
FANUC_EXAMPLE_FIRST = 33
FANUC_EXAMPLE_REFERENCE = 40
FANUC_EXAMPLE_VALUES = [2, 1, 1, -2, 0, -1, 0, -1, 2, 1, 0, -1, -1, -2, 0, 1, 2]


def test_our_fanuc_pitch_data_reproduce_the_parameter_manuals_example():
    # the absolute compensation the manual's figure plots, rebuilt from its increments:
    # point R + i carries the change over the section ending at i x 50 mm
    increments = np.array(FANUC_EXAMPLE_VALUES)
    i = np.arange(FANUC_EXAMPLE_FIRST - FANUC_EXAMPLE_REFERENCE - 1, 10)  # -8 .. 9
    steps = increments[i[1:] - i[0] - 1]
    correction = np.concatenate([[0], np.cumsum(steps)])
    correction -= correction[list(i).index(0)]  # zero at the reference position
    positions = i * 50.0
    error_mm = -correction * 1e-3  # 1 um detection unit; a correction is minus the error
    tables = ErrorTables(tables={"EXX": (positions, error_mm)})
    fit = CompensationFit(fanuc.MODEL, tables, tables, tables, 1.0, 0.0, 1, True)
    machine = make_machine(controller="fanuc", detection_unit_um=1.0)
    table = fanuc.pitch_table("X", fit, machine, next_free=FANUC_EXAMPLE_FIRST)
    assert table.first_number == FANUC_EXAMPLE_FIRST
    assert table.reference_number == FANUC_EXAMPLE_REFERENCE
    assert table.last_number == FANUC_EXAMPLE_FIRST + len(FANUC_EXAMPLE_VALUES) - 1
    assert (table.interval_units, table.magnification) == (50_000, 1)
    assert table.values.tolist() == FANUC_EXAMPLE_VALUES


#: The ISG CSV format's programming examples (Beckhoff Information System, TF5280
#: Volumetric Compensation, "ISG CSV format"), the elided values left out.
ISG_EXAMPLE = """// The header only contains position errors.
Y0A Z0A X0B
// Position errors are typically (but not necessarily)
// constant. Therefore, one data row is usually sufficient here.
0.1 0.2 0.11
#
// The header contains the argument "X" and component errors.
X EXX EYX EZX EAX EBX ECX
0.0 0.02 0.01 0.07 0.00 0.0042 0.003
10.0 0.00 -0.1 0.01 0.00 0.0011 0.002
"""
#: Names the same documentation lists as supported ("List of parameters supported").
ISG_POSITION_ERRORS = {f"{a}0{b}" for a in "XYZABC" for b in "XYZABC"}
ISG_COMPONENT_ERRORS = {f"E{a}{b}" for a in "XYZABC" for b in "XYZABC"}


def _isg_blocks(text: str) -> list[tuple[list[str], np.ndarray]]:
    """(header, records) of every block, read by the format's rules: ``//`` comments,
    ``#`` file breaks, a header naming arguments and parameters, numeric records."""
    blocks = []
    for part in text.split("\n#\n"):
        lines = [line.split() for line in part.splitlines() if line and not line.startswith("//")]
        header, rows = lines[0], lines[1:]
        assert rows and all(len(row) == len(header) for row in rows), part
        blocks.append((header, np.array(rows, dtype=float)))
    return blocks


def test_our_isg_file_follows_the_isg_csv_format_and_its_parameter_names():
    for header, _ in _isg_blocks(ISG_EXAMPLE):  # the reader reads the published example
        assert set(header) <= ISG_POSITION_ERRORS | ISG_COMPONENT_ERRORS | set("XYZ")
    rng = np.random.default_rng(8)
    tables = make_tables({name: rng.normal(0, 3, 5) for name in ("EXX", "EYX", "EBY")}, EC0Y=4)
    ours = _isg_blocks(compensate(make_machine(), tables, "isg").files["vol_comp.csv"])
    example_x_header = _isg_blocks(ISG_EXAMPLE)[1][0]
    assert [header for header, _ in ours] == [
        ["C0Y", "A0Z", "B0Z"],
        example_x_header,
        ["Y", "EXY", "EYY", "EZY", "EAY", "EBY", "ECY"],
        ["Z", "EXZ", "EYZ", "EZZ", "EAZ", "EBZ", "ECZ"],
    ]
    for header, records in ours:
        assert set(header) <= ISG_POSITION_ERRORS | ISG_COMPONENT_ERRORS | set("XYZ")
        if header[0] in "XYZ":
            assert np.all(np.diff(records[:, 0]) > 0)  # records ordered by their argument


#: HEIDENHAIN TNC 306/TNC 406 Technical Manual (3/97), "Machine axes", nonlinear
#: axis-error compensation, p. 4-21: "Only the compensation points of the error curve
#: should be entered. [...] the correction table is thus: Y = F(Z), DATUM POINT -990,
#: SETUP 14" (2^14 um = 16.384 mm between points) with Y values 0, -0.06, -0.09, (no
#: entry), (no entry), -0.12, -0.12, -0.1, -0.09 mm; the control interpolates linearly,
#: so the two empty lines are -0.10 and -0.11 here.
HEIDENHAIN_DATUM_MM = -990.0
HEIDENHAIN_SPACING_MM = 16.384
HEIDENHAIN_Y_OF_Z_MM = [0.0, -0.06, -0.09, -0.10, -0.11, -0.12, -0.12, -0.10, -0.09]


def test_our_heidenhain_table_holds_the_manuals_error_curve():
    z = HEIDENHAIN_DATUM_MM + HEIDENHAIN_SPACING_MM * np.arange(len(HEIDENHAIN_Y_OF_Z_MM))
    machine = parse_machine(
        {
            "name": "TNC example",
            "chain": "FYXZ",
            "travel_mm": {"X": [0, 400], "Y": [0, 300], "Z": [float(z[0]), float(z[-1])]},
            "feed_mm_min": {"rapid": 6000, "measure": 1000},
            "controller": "heidenhain",
            "receiver_offset_mm": [0, 0, -100],
            "cnc": {"reference_mm": [0.0, 0.0, HEIDENHAIN_DATUM_MM]},
        },
        "test",
    )
    tables = make_tables()
    for name in ("EXZ", "EYZ", "EZZ", "EAZ", "EBZ", "ECZ"):
        values = HEIDENHAIN_Y_OF_Z_MM if name == "EYZ" else np.zeros(len(z))
        tables.tables[name] = Table(z, np.asarray(values, dtype=float), np.zeros(len(z)))
    com = compensate(machine, tables, "heidenhain").files["Z.COM"].splitlines()
    header = com[1].split()
    rows = [line.split() for line in com[2:-1]]
    positions = [float(row[header.index("AXISPOS")]) for row in rows]
    np.testing.assert_allclose(positions, z, atol=1e-4)
    y = [float(row[header.index("Y")]) for row in rows]
    np.testing.assert_allclose(y, HEIDENHAIN_Y_OF_Z_MM, atol=1e-5)  # the error, not minus it


#: SINUMERIK 840D sl Function Manual K3 "Compensations" (6FC5397-1BP40-3BA1, 03/2013),
#: 4.4.4.3 "Example", p. 264: the direction-dependent compensation of axis X in two CEC
#: tables of 11 interpolation points at X = -585, -527, ..., -5 (MD18342[0] = MD18342[1]
#: = 11), one table for each traversing direction.
K3_DIRECTION_POSITIONS_MM = np.arange(-585.0, -4.0, 58.0)


def test_our_direction_table_sits_on_the_k3_examples_interpolation_points():
    machine = parse_machine(
        {
            "name": "K3 example",
            "chain": "FYXZ",
            "travel_mm": {"X": [-585, -5], "Y": [0, 300], "Z": [-200, 0]},
            "feed_mm_min": {"rapid": 6000, "measure": 1000},
            "controller": "sinumerik",
            "receiver_offset_mm": [0, 0, -100],
            "cnc": {"reference_mm": [-5.0, 0.0, 0.0]},
        },
        "test",
    )
    tables = make_tables()
    for name in ("EXX", "EYX", "EZX", "EAX", "EBX", "ECX"):
        n = len(K3_DIRECTION_POSITIONS_MM)
        tables.tables[name] = Table(K3_DIRECTION_POSITIONS_MM, np.zeros(n), np.zeros(n))
    tables = with_reversal(tables, "EXX", 2.0)
    cec = compensate(machine, tables, "sinumerik").files["NC_CEC.INI"]
    statements = {(v, i): value for v, i, value in _statements(cec)}
    directional = [
        index
        for (name, index), value in statements.items()
        if name == "AN_CEC_DIRECTION" and value != "0"
    ]
    assert len(directional) == 1  # one table carries the reversal
    (table,) = directional[0]
    assert statements[("AN_CEC_MIN", (table,))] == "-585.000000"
    assert statements[("AN_CEC_STEP", (table,))] == "58.000000"
    assert statements[("AN_CEC_MAX", (table,))] == "-5.000000"
    assert sum(1 for v, i in statements if v == "AN_CEC" and i[0] == table) == 11
    # X references at its upper end (-5) moving '+': the table acts in '-' only
    assert statements[("AN_CEC_DIRECTION", (table,))] == "-1"
