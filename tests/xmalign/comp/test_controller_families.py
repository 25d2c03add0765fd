"""Each family's files, read back as its manual says the control reads them (controls.py),
take out the measured errors, with the datum at the reference approached in its
reference-return direction; the family's limits; the loading notes."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from tests.xmalign.comp.conftest import TRAVEL, make_machine, make_tables
from tests.xmalign.comp.controls import taken_out
from xmalign.comp import compensate
from xmalign.comp.heidenhain import power_of_two_grid
from xmalign.errors import InputError, OutOfRangeError
from xmalign.formats.error_tables import ErrorTableSet, Table

#: reading resolution of each family's files, mm
RESOLUTION = {"sinumerik": 1e-6, "fanuc": 1e-3, "heidenhain": 1e-5, "linuxcnc": 1e-6}
#: which errors a family takes out: the own-axis tables, or the cross tables too
CROSS = {"sinumerik": True, "fanuc": False, "heidenhain": True, "linuxcnc": False}


def _errors(n: int = 5) -> tuple[ErrorTableSet, dict[str, dict[str, np.ndarray]]]:
    """Linear errors (so that any resampling is exact) and reversals on X and Z, mm.

    Returns the error tables and the truth by direction: name -> direction -> values.
    """
    tables = make_tables(n=n)
    truth: dict[str, dict[str, np.ndarray]] = {}
    slopes_um_per_m = {"EXX": 20.0, "EYX": -15.0, "EZZ": -30.0, "EXZ": 8.0}
    reversal_um = {"EXX": 3.0, "EZZ": -2.0}
    for name, slope in slopes_um_per_m.items():
        positions = tables.tables[name].positions_mm
        mean = slope * 1e-6 * positions
        tables.tables[name] = Table(positions, mean, np.zeros(n))
        half = reversal_um.get(name, 0.0) * 1e-3 / 2
        truth[name] = {"+": mean - half, "-": mean + half}
        if name in reversal_um:
            tables.tables[name + "+"] = Table(positions, mean - half, np.zeros(n))
            tables.tables[name + "-"] = Table(positions, mean + half, np.zeros(n))
    return tables, truth


CASES = [
    ("sinumerik", "840D sl", {}),
    ("sinumerik", "840D sl", {"reference_return": {"X": "+", "Z": "-"}}),
    ("sinumerik", "828D", {}),
    ("fanuc", "0i", {}),
    ("fanuc", "30i", {"reference_return": {"X": "+"}}),
    ("heidenhain", "TNC 640", {}),
    ("heidenhain", "TNC 4xx", {}),
    ("linuxcnc", "2.9", {}),
]


@pytest.mark.parametrize(("controller", "series", "cnc"), CASES)
def test_the_control_takes_out_the_errors_from_its_reference(controller, series, cnc):
    machine = make_machine(controller=controller, series=series, **cnc)
    tables, truth = _errors()
    files = compensate(machine, tables, controller).files
    for direction in "+-":
        applied = taken_out(controller, files, machine, direction)
        for name, by_direction in truth.items():
            own = name[1] == name[2]
            if not own and not CROSS[controller]:
                continue
            axis = name[2]
            reference = float(machine.cnc.reference["XYZ".index(axis)])
            if series == "TNC 4xx":  # the datum: the start of the travel
                reference = TRAVEL[axis][0]
            returns = machine.reference_return(axis)
            datum_table = by_direction[returns] if own else by_direction["+"]
            if controller == "linuxcnc":  # no reference-return rule: the mean is zero
                datum_table = (by_direction["+"] + by_direction["-"]) / 2
            positions = tables.tables[name].positions_mm
            datum = np.interp(reference, positions, datum_table)
            at, values = applied[name]
            expected = np.interp(at, positions, by_direction[direction]) - datum
            np.testing.assert_allclose(
                values, expected, atol=RESOLUTION[controller], err_msg=f"{name} {direction}"
            )


def test_sinumerik_step_min_max_agree_exactly_with_the_point_count():
    machine = make_machine(controller="sinumerik")
    tables, _ = _errors(n=7)  # 400 / 6 = 66.666... mm between points
    files = compensate(machine, tables, "sinumerik").files
    taken_out("sinumerik", files, machine, "+")  # asserts (MAX - MIN) / STEP == points - 1
    assert "$AA_ENC_COMP_STEP[0,AX1]=66.666667" in files["AX_EEC.INI"]
    assert "$AA_ENC_COMP_MAX[0,AX1]=400.000002" in files["AX_EEC.INI"]


def _three_reversals() -> tuple[ErrorTableSet, dict[str, dict[str, np.ndarray]]]:
    """:func:`_errors` with reversals that vary along X and Y too (Z's is a constant -2 um)."""
    tables, truth = _errors()
    for name in ("EXX", "EYY"):
        mean = tables.tables[name]
        half_mm = 1e-3 * (0.5 + mean.positions_mm / 200.0)
        tables.tables[name + "+"] = Table(mean.positions_mm, mean.values - half_mm, mean.u95)
        tables.tables[name + "-"] = Table(mean.positions_mm, mean.values + half_mm, mean.u95)
        truth[name] = {"+": mean.values - half_mm, "-": mean.values + half_mm}
    return tables, truth


def test_sinumerik_828d_keeps_eight_tables_and_moves_the_rest_of_the_reversal_to_md32450():
    tables, _ = _three_reversals()
    eight_and_more = make_machine(controller="sinumerik")
    cec = compensate(eight_and_more, tables, "sinumerik").files["NC_CEC.INI"]
    assert "$AN_CEC[8,0]" in cec  # 840D sl: 6 cross + 3 reversal tables
    small = make_machine(controller="sinumerik", series="828D")
    compensation = compensate(small, tables, "sinumerik")
    cec = compensation.files["NC_CEC.INI"]
    assert "$AN_CEC[7,0]" in cec and "$AN_CEC[8,0]" not in cec
    # the reversal that varies least along its axis (Z's) gives way: a constant in MD32450
    assert cec.count("MD32450 $MA_BACKLASH[0] =") == 1 and "; Z: no table left" in cec
    assert "MD32450 carries it as a constant" in compensation.loading.reversal


@pytest.mark.parametrize("returns", ["+", "-"])
def test_sinumerik_828d_backlash_is_the_machines_play_whatever_the_return_direction(returns):
    """MD32450 is positive when the encoder leads the machine part (the '-' approach stops
    above the '+' one): Z's play is e- - e+ = -2 um, so -0.002 mm whichever way Z is
    referenced (it once flipped with the direction, and doubled the play in one of them)."""
    tables, truth = _three_reversals()
    machine = make_machine(controller="sinumerik", series="828D", reference_return={"Z": returns})
    files = compensate(machine, tables, "sinumerik").files
    assert (
        "; Z: no table left for its reversal: MD32450 $MA_BACKLASH[0] = -0.002000 on AX3"
        in (files["NC_CEC.INI"])
    )
    positions = tables.tables["EZZ"].positions_mm
    datum = np.interp(0.0, positions, truth["EZZ"][returns])  # Z's reference: 0
    for direction in "+-":
        at, values = taken_out("sinumerik", files, machine, direction)["EZZ"]
        expected = np.interp(at, positions, truth["EZZ"][direction]) - datum
        np.testing.assert_allclose(values, expected, atol=1e-6, err_msg=direction)


def test_sinumerik_828d_refuses_more_than_200_points():
    machine = make_machine(controller="sinumerik", series="828D")
    with pytest.raises(OutOfRangeError, match="828D: 200 points"):
        compensate(machine, make_tables(n={"X": 201}), "sinumerik")


def test_heidenhain_tnc_4xx_tables_start_at_zero_at_the_datum_with_power_of_two_spacing():
    machine = make_machine(controller="heidenhain", series="TNC 4xx")
    tables, _ = _errors()  # 100 mm between the measured points on X
    files = compensate(machine, tables, "heidenhain").files
    rows = [line.split() for line in files["X.COM"].splitlines()[2:-1]]
    # 2^19 x 0.1 um = 52.4288 mm: the largest power of two not above 100 mm; 400 mm
    # of travel from the datum x = 0 in 8 spacings, 9 points
    assert [float(row[1]) for row in rows] == pytest.approx(52.4288 * np.arange(9))
    header = files["X.COM"].splitlines()[1].split()
    assert header == ["NR", "AXISPOS", "X", "Y", "Z", "BACKLASH"]
    # the curves start at 0; X returns '-': its BACKLASH column, X keeps the reversal there
    assert [float(value) for value in rows[0][2:]] == [-0.003, 0.0, 0.0, 0.0]
    readme = files["HEIDENHAIN.TXT"]
    assert "MP730" in readme and "TNC 4xx" in readme and "2^19 x 0.1 um" in readme


@pytest.mark.parametrize("series", ["TNC 640", "TNC 4xx"])
def test_heidenhain_txt_says_what_the_tables_hold_where_they_start(series):
    """HEIDENHAIN.TXT once said every table is zero at the reference point while X.COM's
    first row held the reversal: each of its statements is checked against the tables."""
    machine = make_machine(controller="heidenhain", series=series)
    files = compensate(machine, _errors()[0], "heidenhain").files
    readme = files["HEIDENHAIN.TXT"]
    assert "every table is zero" not in readme and "starts at 0" not in readme
    for axis in "XYZ":
        lines = files[f"{axis}.COM"].splitlines()
        header = lines[1].split()
        rows = np.array([[float(v) for v in line.split()] for line in lines[2:-1]])
        at = rows[0, 1] if series == "TNC 4xx" else float(machine.cnc.reference["XYZ".index(axis)])
        values = {
            name: np.interp(at, rows[:, 1], rows[:, header.index(name)]) for name in header[2:]
        }
        stated = re.search(
            rf"^{axis}\.COM at the \w+(?: \w+)? {axis} = (\S+) mm: (.*)$", readme, re.M
        )
        assert stated is not None, axis
        assert float(stated.group(1)) == pytest.approx(at)
        zero, _, held = stated.group(2).partition("; ")
        for name in zero.removesuffix(" zero").split(", "):
            assert values[name] == pytest.approx(0.0, abs=5e-6), (axis, name)
        for name, value in re.findall(r"(\w+) ([+-]\d\.\d{5}) mm", held):
            assert values[name] == pytest.approx(float(value), abs=5e-6), (axis, name)
        # X and Z have a reversal (3 and -2 um): it is stated, in the other direction's column
        assert ("the reversal there" in held) == (axis != "Y"), axis
    if series == "TNC 4xx":
        assert "CONFIG.CMA goes as CONFIG.S, each .COM as .V" in readme
        assert "p. 4-31" in readme
        assert "BACKLASH column on a TNC 4xx" in readme


def test_heidenhain_tnc_4xx_spacing_follows_the_manuals_example():
    """TNC 407/415/425 Technical Manual, 01.98, p. 4-28: a required distance of 7 mm gives
    2^16 = 6.5536 mm; 500 mm of Y travel (datum -90) then needs 77 spacings."""
    grid, exponent = power_of_two_grid(-90.0, 410.0, 7.0)
    assert exponent == 16 and grid.step_mm == pytest.approx(6.5536)
    assert grid.start_mm == -90.0 and grid.count - 1 == 77
    _, coarser = power_of_two_grid(0.0, 4000.0, 7.0)  # 256 points at most
    assert coarser == 18


def test_heidenhain_itnc_530_is_refused_in_one_line():
    machine = make_machine(controller="heidenhain", series="iTNC 530")
    with pytest.raises(InputError, match="cnc.series: Heidenhain iTNC 530: its .COM layout"):
        compensate(machine, make_tables(), "heidenhain")


def test_a_series_of_another_family_is_refused():
    with pytest.raises(InputError, match=r"cnc.series: '828D' is not a fanuc series"):
        make_machine(controller="fanuc", series="828D")


def test_a_reversal_with_the_reference_inside_the_travel_needs_the_return_direction():
    tables, _ = _errors()
    machine = make_machine(controller="fanuc", reference_mm=[200.0, 0.0, 0.0])
    with pytest.raises(InputError, match="cnc.reference_return.X: needed for the Fanuc"):
        compensate(machine, tables, "fanuc")
    told = make_machine(
        controller="fanuc", reference_mm=[200.0, 0.0, 0.0], reference_return={"X": "+"}
    )
    assert "PITCH.TXT" in compensate(told, tables, "fanuc").files


def test_the_controls_backlash_during_the_measurement_is_folded_into_the_reversal():
    tables, _ = _errors()
    machine = make_machine(controller="sinumerik", backlash_um={"X": 4.0})
    compensation = compensate(machine, tables, "sinumerik")
    loading = compensation.loading
    assert "X 4 um" in loading.reversal and "set MD32450 $MA_BACKLASH to 0 on X" in loading.reversal
    assert all("for X," not in warning for warning in loading.warnings)  # only Z is unknown
    forward = taken_out("sinumerik", compensation.files, machine, "+")["EXX"][1]
    reverse = taken_out("sinumerik", compensation.files, machine, "-")["EXX"][1]
    # measured reversal e- - e+ = 3 um, with the control's 4 um backlash active: 7 um
    np.testing.assert_allclose(reverse - forward, 7e-3, atol=1e-6)


@pytest.mark.parametrize("controller", ["sinumerik", "fanuc", "heidenhain", "linuxcnc", "isg"])
def test_every_writer_says_who_carries_the_reversal_and_the_check(controller):
    tables, _ = _errors()
    loading = compensate(make_machine(controller=controller), tables, controller).loading
    assert loading.reversal and loading.check
    lines = loading.lines()
    assert lines[0].startswith("Reversal: ") and lines[1].startswith("Check before use: ")


def test_comp_prints_who_carries_the_reversal_and_the_check(tmp_path):
    from tests.cli_helpers import run_in_process

    root = Path(__file__).resolve().parents[3] / "examples"
    result = run_in_process(
        "comp",
        "--errors",
        str(root / "errors.csv"),
        "--out",
        str(tmp_path / "comp"),
        "--controller",
        "fanuc",
    )
    assert result.returncode == 0, result.stderr
    assert "Reversal: the tables carry the reversal of X, Y, Z" in result.stdout
    assert "Check before use: read parameter 3624 back" in result.stdout
    assert "Not confirmed from a manual: the unit of 3624" in result.stdout
    readme = (tmp_path / "comp" / "PITCH_README.TXT").read_text()
    assert "Check before use:" in readme and "X 0 (-)" in readme


@pytest.mark.parametrize(
    ("series", "controller", "expected"),
    [
        (None, "fanuc", "FANUC Series 0i"),
        ("840D sl", "fanuc", "FANUC Series 0i"),
        ("828D", "heidenhain", "HEIDENHAIN MANUALplus 620"),
        ("828D", "sinumerik", "SINUMERIK 828D"),
    ],
)
def test_controller_option_chooses_the_familys_default_series(series, controller, expected):
    """``comp --controller fanuc`` on a Sinumerik machine file wrote "FANUC Series 840D sl"
    (or failed on cnc.series): another family gets its own default series."""
    cnc = {} if series is None else {"series": series}
    machine = make_machine(controller="sinumerik", **cnc)
    files = compensate(machine, _errors()[0], controller).files
    assert any(expected in text for text in files.values())
    assert not any(f"Series {series}" in text for text in files.values() if controller == "fanuc")


def test_comp_controller_fanuc_with_the_example_machine_file(tmp_path):
    from tests.cli_helpers import run_in_process

    root = Path(__file__).resolve().parents[3] / "examples"
    result = run_in_process(
        "comp",
        "--errors",
        str(root / "errors.csv"),
        "--machine",
        str(root / "fyxz.yaml"),
        "--out",
        str(tmp_path / "comp"),
        "--controller",
        "fanuc",
    )
    assert result.returncode == 0, result.stderr
    readme = (tmp_path / "comp" / "PITCH_README.TXT").read_text()
    assert "\nxmalign: FANUC Series 0i pitch error compensation (PITCH.TXT)\n" in readme


def _extrapolated_below(tables: ErrorTableSet, axis: str, u95_um: float) -> ErrorTableSet:
    """``axis``'s tables with their first point (the axis's lower travel end, where the
    comp test machine's reference lies) marked extrapolated, its u95 ``u95_um`` (urad)."""
    for name, table in list(tables.tables.items()):
        if name[2] != axis:
            continue
        measured = np.ones(len(table.positions_mm), dtype=bool)
        measured[0] = False
        u95 = np.array(table.u95, dtype=float)
        u95[0] = u95_um * (1e-3 if name[1] in "XYZ" else 1e-6)
        tables.tables[name] = Table(table.positions_mm, table.values, u95, measured)
    return tables


@pytest.mark.parametrize("controller", ["sinumerik", "fanuc", "heidenhain", "linuxcnc", "isg"])
def test_comp_names_the_tables_whose_reference_value_is_extrapolated(controller):
    """From one station the reference point may lie beyond the measured stroke: every
    writer names those tables with their U95 there, in its notes and its files."""
    tables = _extrapolated_below(_errors()[0], "X", 29.0)
    compensation = compensate(make_machine(controller=controller), tables, controller)
    [warning] = [w for w in compensation.loading.warnings if "outside the measured" in w]
    assert warning.startswith("the reference point X = 0 mm lies outside the measured range")
    assert "(100 to 400 mm)" in warning
    assert "EXX 29.0 um" in warning and "EAX 29.0 urad" in warning and "EYY" not in warning
    assert "A second station whose lines measure X across 0 mm removes it" in warning
    assert "EXX+" not in warning  # the directions' tables together: the largest U95
    if controller != "linuxcnc":  # LinuxCNC's comp files take no text (their notes: comp)
        # in a file the notes are comment lines wrapped at 100 characters
        unwrapped = [
            " ".join(line.lstrip(";#/ ") for line in text.splitlines())
            for text in compensation.files.values()
        ]
        assert any(warning in text for text in unwrapped)
        # a Sinumerik block has a length limit: no comment line there is longer than 100
        assert all(
            len(line) <= 100
            for name, text in compensation.files.items()
            for line in text.splitlines()
            if name.endswith(".INI")
        )


def test_no_warning_when_the_reference_was_measured():
    tables = _extrapolated_below(_errors()[0], "X", 29.0)
    machine = make_machine(
        controller="sinumerik", reference_mm=[100.0, 0.0, 0.0], reference_return={"X": "+"}
    )
    warnings = compensate(machine, tables, "sinumerik").loading.warnings
    assert not any("outside the measured" in warning for warning in warnings)
