"""The measurement CSV: round trips, the checks on reading, torn rows and damaged files."""

import os
import stat

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from xmalign.errors import InputError
from xmalign.formats.measurements import (
    NOMINAL_LIMITS,
    ChannelLimits,
    LineSetup,
    MeasurementRow,
    MeasurementWriter,
    load_measurements,
    read_measurements,
    write_measurements,
)

HEADER = (
    "line,run,direction,index,target_mm,x_mm,y_mm,z_mm,linear_um,straightness_v_um,"
    "straightness_w_um,angle_u_urad,angle_v_urad,angle_w_urad"
)
GOOD = "X,1,+,0,0.0,10,20,30,0.5,1.5,-2.5,3,4,-5"


def _rows(n: int) -> list[MeasurementRow]:
    return [
        MeasurementRow(
            "X", 1 + k // 10, "+", k % 10, 10.0 * k, np.array([10.0 * k, 2, 3]), np.arange(6.0) + k
        )
        for k in range(n)
    ]


def _file(tmp_path, *lines: str, end: str = "\n"):
    path = tmp_path / "m.csv"
    path.write_text("\n".join(lines) + end, encoding="utf-8")
    return path


def test_round_trip_keeps_the_plan_identity_setups_and_segments(tmp_path):
    path = tmp_path / "m.csv"
    setup = LineSetup("X", 1, np.array([0.5, -0.25]), np.array([3.0, 0.125, -1e-5]))
    with MeasurementWriter.create(path, "ab" * 32) as writer:
        writer.note_setup(setup)
        for row in _rows(3):
            writer.append(MeasurementRow(**{**row.__dict__, "segment": 1}))
    back = load_measurements(path)
    assert back.plan_sha256 == "ab" * 32
    # one meaning per name: the identity is plan_identity, the file's bytes '# input plan:'
    first = path.read_text().splitlines()[0]
    assert first == f"# xmalign measurements plan_identity={'ab' * 32}"
    # a file written under the old name (plan_sha256=, the same identity) reads alike
    path.write_text(path.read_text().replace("plan_identity=", "plan_sha256=", 1))
    assert load_measurements(path).plan_sha256 == "ab" * 32
    assert [r.key() for r in back.rows] == [r.key() for r in _rows(3)]
    assert {r.segment for r in back.rows} == {1}
    np.testing.assert_allclose(back.rows[2].channels, np.arange(6.0) + 2)
    (recorded,) = back.setups
    np.testing.assert_allclose(recorded.receiver_rad, setup.receiver_rad, rtol=1e-15)
    assert back.last_segments() == {"X": 1}


def test_environment_columns_in_any_order_are_parsed(tmp_path):
    path = _file(
        tmp_path,
        HEADER + ",material_temp_c,air_pressure_hpa,air_temp_c,air_humidity_percent",
        GOOD + ",20.5,1013.2,21.0,45",
    )
    (row,) = read_measurements(path)
    assert row.environment == {
        "air_temp_c": 21.0,
        "air_pressure_hpa": 1013.2,
        "air_humidity_percent": 45.0,
        "material_temp_c": 20.5,
    }
    assert row.segment == 0


def test_a_file_of_the_contract_without_xmalign_comments_is_read(tmp_path):
    rows = read_measurements(_file(tmp_path, HEADER, GOOD, GOOD.replace(",0,0.0,", ",1,100,")))
    assert [r.index for r in rows] == [0, 1]


BAD_FILES = [
    ("nan", [HEADER, GOOD.replace("0.5", "nan")], "line 2: linear_um is nan"),
    ("infinity", [HEADER, GOOD.replace("3,4,-5", "inf,4,-5")], "line 2: angle_u_urad is inf"),
    ("text", [HEADER, GOOD.replace("0.5", "0,5x")], "line 2: expected 14 fields"),
    ("not a number", [HEADER, GOOD.replace("0.5", "abc")], "line 2: linear_um 'abc'"),
    ("1e12 um", [HEADER, GOOD.replace("0.5", "1e12")], "line 2: linear_um 1e+12 um is beyond"),
    ("straightness", [HEADER, GOOD.replace("1.5,-2.5", "400,400")], "straightness 565.685"),
    ("angle", [HEADER, GOOD.replace("3,4,-5", "3,4,-1001")], "an angle 1001 urad"),
    ("1 km travel", [HEADER, GOOD.replace("10,20,30", "1e12,20,30")], "beyond 100 m"),
    ("duplicate", [HEADER, GOOD, GOOD], "line 3: line X run 1 direction + index 0 is recorded"),
    ("direction", [HEADER, GOOD.replace(",+,", ",up,")], "line 2: direction must be"),
    ("negative index", [HEADER, GOOD.replace(",+,0,", ",+,-1,")], "line 2: index -1 is neg"),
    ("fraction run", [HEADER, GOOD.replace("X,1,", "X,1.5,")], "line 2: run '1.5'"),
    ("empty line id", [HEADER, GOOD[1:]], "line 2: empty line id"),
    ("no header", [GOOD], "line 1: missing column 'line'"),
    ("unknown column", [HEADER + ",air_temp_k", GOOD + ",293"], "unknown column 'air_temp_k'"),
    ("column twice", [HEADER + ",segment,segment", GOOD + ",0,0"], "'segment' appears twice"),
    ("segment", [HEADER + ",segment", GOOD + ",-2"], "line 2: segment -2 is negative"),
    ("humidity", [HEADER + ",air_humidity_percent", GOOD + ",140"], "outside 0 to 100"),
    ("short row", [HEADER, "X,1,+,0"], "line 2: expected 14 fields, found 4"),
    ("setup", ["# setup line=X segment=0 launch_deg=1", HEADER], "line 1: damaged setup"),
    ("only comments", ["# nothing here"], "no header line"),
    ("huge field", [HEADER, GOOD.replace("X,", "X" * 200_000 + ",", 1)], "field larger"),
]


@pytest.mark.parametrize(
    "lines, message", [case[1:] for case in BAD_FILES], ids=[c[0] for c in BAD_FILES]
)
def test_a_damaged_file_is_refused_naming_file_and_line(tmp_path, lines, message):
    path = _file(tmp_path, *lines)
    with pytest.raises(InputError) as error:
        read_measurements(path)
    assert str(path) in str(error.value) and message in str(error.value)
    assert "\n" not in str(error.value)


def test_non_utf8_names_the_line(tmp_path):
    path = tmp_path / "m.csv"
    path.write_bytes((HEADER + "\n" + GOOD + "\n").encode() + b"X,1,+,1,\xff\n")
    with pytest.raises(InputError, match=r"m.csv: line 3: not UTF-8 text \(byte 0xff\)"):
        read_measurements(path)


def test_a_folder_or_a_missing_file_is_one_line(tmp_path):
    with pytest.raises(InputError, match="is a folder"):
        read_measurements(tmp_path)
    with pytest.raises(InputError, match="no such file"):
        read_measurements(tmp_path / "missing.csv")


def test_the_machine_ranges_set_the_limits(tmp_path):
    path = _file(tmp_path, HEADER, GOOD.replace("3,4,-5", "3,4,-900"))
    assert read_measurements(path)  # within twice the nominal 500 urad
    with pytest.raises(InputError, match="an angle 900 urad is beyond 800 urad"):
        read_measurements(path, ChannelLimits.of_ranges(4000, 250, 400))
    assert NOMINAL_LIMITS.angle_urad == 1000


def test_a_cut_last_row_is_refused_unless_resuming(tmp_path):
    path = _file(tmp_path, HEADER, GOOD, "X,1,+,1,100,1", end="")
    with pytest.raises(InputError, match="line 3: expected 14 .*cut short .*--resume"):
        read_measurements(path)
    resumed = load_measurements(path, torn_ok=True)
    assert len(resumed.rows) == 1 and resumed.torn.line_number == 3
    with MeasurementWriter.resume(resumed) as writer:
        writer.append(_rows(2)[1])
    assert [r.index for r in read_measurements(path)] == [0, 1]


def test_a_complete_last_row_without_line_end_is_accepted(tmp_path):
    assert len(read_measurements(_file(tmp_path, HEADER, GOOD, end=""))) == 1


def test_a_new_file_is_readable_by_the_controller_account(tmp_path):
    umask = os.umask(0o022)
    try:
        write_measurements(tmp_path / "m.csv", _rows(1))
    finally:
        os.umask(umask)
    assert stat.S_IMODE((tmp_path / "m.csv").stat().st_mode) == 0o644


def test_an_existing_file_is_never_replaced(tmp_path):
    path = _file(tmp_path, HEADER, GOOD)
    before = path.read_bytes()
    with pytest.raises(InputError, match="already exists; measurements are never replaced"):
        write_measurements(path, _rows(2))
    assert path.read_bytes() == before
    empty = tmp_path / "empty.csv"
    empty.touch()
    write_measurements(empty, _rows(2))  # an empty file holds nothing to lose
    assert len(read_measurements(empty)) == 2


@settings(max_examples=60, deadline=None)
@given(cut=st.integers(0, 10_000))
def test_a_file_cut_anywhere_resumes_with_every_complete_row(tmp_path_factory, cut):
    path = tmp_path_factory.mktemp("cut") / "m.csv"
    write_measurements(path, _rows(12), "cd" * 32)
    data = path.read_bytes()
    cut = cut % (len(data) + 1)
    header_end = data.index(b"\n", data.index(b"\nline,run,") + 1) + 1
    path.write_bytes(data[:cut])
    ended = data[:cut].split(b"\n")[:-1]
    complete = sum(1 for line in ended if not line.startswith(b"#")) - 1
    if cut < header_end:  # a cut header: refused, or (cut after a column) a file with no rows
        try:
            assert read_measurements(path) == []
        except InputError as error:
            assert str(path) in str(error)
        return
    resumed = load_measurements(path, torn_ok=True)
    assert [r.key() for r in resumed.rows] == [r.key() for r in _rows(12)[:complete]]
    assert (resumed.torn is None) == (cut == len(data) or data[cut - 1 : cut] == b"\n")


@settings(max_examples=80, deadline=None)
@given(position=st.integers(0, 10_000), byte=st.integers(0, 255))
def test_a_damaged_byte_gives_rows_or_one_line_error(tmp_path_factory, position, byte):
    path = tmp_path_factory.mktemp("flip") / "m.csv"
    write_measurements(path, _rows(6), "cd" * 32)
    data = bytearray(path.read_bytes())
    data[position % len(data)] = byte
    path.write_bytes(bytes(data))
    try:
        rows = read_measurements(path)
    except InputError as error:
        assert str(path) in str(error) and "\n" not in str(error)
    else:
        assert len(rows) <= 6
        assert all(np.all(np.isfinite(r.channels)) for r in rows)
