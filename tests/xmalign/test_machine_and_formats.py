import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from xmalign.errors import FormatError, InputError
from xmalign.formats.error_tables import ErrorTableSet, Table, read_error_tables, write_error_tables
from xmalign.formats.measurements import (
    MeasurementRow,
    MeasurementWriter,
    load_measurements,
    read_measurements,
)
from xmalign.formats.plan import Plan, PlanLine, read_plan, write_plan
from xmalign.formats.pose import LaunchPose, read_pose, write_pose
from xmalign.formats.session import Alignment, Session, read_session, write_session
from xmalign.machine import default_machine_path, load_machine


def test_reference_machine_loads(reference_machine):
    assert reference_machine.chain == "FYXZ"
    np.testing.assert_allclose(reference_machine.travel_max_mm, [2000, 1500, 0])
    assert reference_machine.interferometer.max_range_mm == 4000
    assert load_machine(default_machine_path()) == reference_machine


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda d: d.pop("chain"), "key 'chain': missing"),
        (lambda d: d.update(spindel_angle_deg=0), "key 'spindel_angle_deg': not a known key"),
        (lambda d: d["travel_mm"].update(X=[10, 5]), "key 'travel_mm'"),
        (lambda d: d["feed_mm_min"].update(measure=0), "key 'feed_mm_min.measure'"),
        (lambda d: d.update(receiver_offset_mm=[0, 0]), "key 'receiver_offset_mm'"),
    ],
)
def test_machine_errors_name_the_file_and_key(tmp_path, reference_machine_path, change, message):
    data = yaml.safe_load(reference_machine_path.read_text())
    change(data)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(InputError, match=message) as info:
        load_machine(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_machine_yaml_syntax_error_names_the_line(tmp_path):
    path = tmp_path / "m.yaml"
    path.write_text("name: a\nchain: [FYXZ\n")
    with pytest.raises(InputError, match="line"):
        load_machine(path)


def _session() -> Session:
    return Session(
        receiver_offset_mm=np.array([0.0, 0.0, -180.0]),
        spindle_angle_rad=math.radians(30),
        alignments=[
            Alignment(np.array([1.0, 2, 3]), np.radians([10.0, 5]), np.radians([190.0, -5, 0])),
            Alignment(
                np.array([4.0, 5, 6]),
                np.radians([11.0, 6]),
                np.radians([191.0, -6, 0]),
                distance_mm=1234.5,
                straightness_um=np.array([3.0, -4.0]),
            ),
        ],
    )


def test_session_round_trip(tmp_path):
    path = tmp_path / "s.json"
    write_session(path, _session())
    back = read_session(path)
    assert back.spindle_angle_rad == pytest.approx(math.radians(30))
    assert back.alignments[1].distance_mm == 1234.5
    np.testing.assert_allclose(back.alignments[1].straightness_um, [3, -4])
    np.testing.assert_allclose(back.alignments[0].launch_rad, np.radians([10.0, 5]))


@pytest.mark.parametrize(
    ("text", "error", "message"),
    [
        ("{not json", InputError, "line 1: not valid JSON at column 2"),
        (
            '{"format": "xmalign.identify-session/2"}',
            FormatError,
            "newer xmalign: format xmalign.identify-session/2, this one reads up to /1",
        ),
        ('{"format": "xmalign.plan/1"}', FormatError, "not a xmalign.identify-session"),
        ('{"alignments": []}', FormatError, "key 'format': missing"),
        (
            '{"format": "xmalign.identify-session/1", "alignments": []}',
            InputError,
            "key 'receiver_offset_mm': missing",
        ),
    ],
)
def test_session_reader_refuses_bad_files(tmp_path, text, error, message):
    path = tmp_path / "s.json"
    path.write_text(text)
    with pytest.raises(error, match=message):
        read_session(path)


def test_pose_round_trip_and_checks(tmp_path):
    pose = LaunchPose(
        position_mm=np.array([1.0, 2, 3]),
        gamma_rad=0.5,
        covariance=np.diag([1e-3, 2e-3, 3e-3, 1e-10]),
        encoder_offsets_rad={"c3": 1e-4},
        method="joint",
        residual_rms_um=3.0,
        n_alignments=8,
    )
    path = tmp_path / "p.json"
    write_pose(path, pose)
    back = read_pose(path)
    assert back.gamma_rad == pytest.approx(0.5)
    assert back.offsets.c3 == pytest.approx(1e-4) and back.offsets.c2 == 0
    data = json.loads(path.read_text())
    data["encoder_offsets_deg"] = {"c9": 1}
    path.write_text(json.dumps(data))
    with pytest.raises(InputError, match="c9"):
        read_pose(path)


def test_plan_round_trip_keeps_extra_keys(tmp_path):
    line = PlanLine(
        id="X",
        start_mm=np.zeros(3),
        end_mm=np.array([100.0, 0, 0]),
        frame=np.eye(3),
        launch_rad=np.array([0.1, 0.0]),
        receiver_rad=np.array([3.0, 0.0, 0.0]),
        targets_mm=np.array([0.0, 50, 100]),
        runs=2,
        bidirectional=True,
        dwell_s=1.5,
        extra={"margin_um": 120.0},
    )
    plan = Plan("m", np.array([0, 0, -180.0]), 0.0, [line])
    write_plan(tmp_path / "plan.json", plan)
    back = read_plan(tmp_path / "plan.json")
    assert back.lines[0].extra == {"margin_um": 120.0}
    np.testing.assert_allclose(back.lines[0].target_points_mm()[-1], [100, 0, 0])
    assert back.line("X").runs == 2


def test_measurements_append_and_bad_row_line_number(tmp_path):
    path = tmp_path / "m.csv"
    row = MeasurementRow("X", 1, "+", 0, 0.0, np.array([1.0, 2, 3]), np.arange(6.0))
    with MeasurementWriter.create(path) as writer:
        writer.append(row)
    with MeasurementWriter.resume(load_measurements(path, torn_ok=True)) as writer:
        writer.append(MeasurementRow("X", 1, "+", 1, 100.0, np.array([101.0, 2, 3]), np.ones(6)))
    rows = read_measurements(path)
    assert [r.index for r in rows] == [0, 1]
    np.testing.assert_allclose(rows[0].channels, np.arange(6.0))
    with path.open("a") as handle:
        handle.write("X,1,?,2,200,1,2,3,0,0,0,0,0,0,0,7.5\n")
    bad_line = len(path.read_text().splitlines())
    with pytest.raises(InputError, match=rf"line {bad_line}: direction"):
        read_measurements(path)


def test_error_tables_round_trip(tmp_path):
    tables = ErrorTableSet(
        tables={
            "EXX": Table(np.array([0.0, 100, 200]), np.array([0.0, 1e-3, 2e-3]), np.full(3, 1e-4)),
            "EBY+": Table(np.array([0.0, 100]), np.array([0.0, 5e-6]), np.array([np.nan, 1e-6])),
        },
        squareness={"EC0Y": (12.5e-6, 1.1e-6), "EA0Z": (0.0, 1e-6), "EB0Z": (-3e-6, 1e-6)},
    )
    path = tmp_path / "errors.csv"
    write_error_tables(path, tables)
    text = Path(path).read_text()
    assert "EXX,100.000,1.0000,um,0.1000" in text and "EC0Y,,12.5000,urad,1.1000" in text
    back = read_error_tables(path)
    np.testing.assert_allclose(back.tables["EXX"].values, [0, 1e-3, 2e-3])
    assert math.isnan(back.tables["EBY+"].u95[0])
    model = back.model("+")
    assert model.value("EBY", 50.0) == pytest.approx(2.5e-6)
    assert model.squareness_rad()[0] == pytest.approx(12.5e-6)
    path.write_text("name,position_mm,value,unit,u95\nEXX,0,1,urad,\n")
    with pytest.raises(InputError, match="line 2: EXX is in um"):
        read_error_tables(path)


def test_channel_limits_are_twice_the_ranges(reference_machine):
    limits = reference_machine.interferometer.channel_limits()
    np.testing.assert_allclose(limits, [8e6, 500, 500, 1000, 1000, 1000])


def test_an_interrupted_write_leaves_the_old_file_and_no_temporary(tmp_path, monkeypatch):
    import xmalign.formats.common as common

    path = tmp_path / "pose.json"
    path.write_text("old\n")

    def interrupted(fd):
        raise KeyboardInterrupt

    monkeypatch.setattr(common.os, "fsync", interrupted)
    with pytest.raises(KeyboardInterrupt):
        common.atomic_write_text(path, "new\n")
    assert path.read_text() == "old\n"
    assert [p.name for p in tmp_path.iterdir()] == ["pose.json"]


def test_yaml_duplicate_keys_and_bom(tmp_path):
    from xmalign.formats.common import read_yaml

    path = tmp_path / "a.yaml"
    path.write_bytes(b"\xef\xbb\xbfa: 1\nb: {c: 2}\n")
    assert read_yaml(path) == {"a": 1, "b": {"c": 2}}
    path.write_text("a: 1\nb:\n  c: 2\n  c: 3\n")
    with pytest.raises(
        InputError, match=r"a.yaml: line 4: key 'c' given twice \(first on line 3\)"
    ):
        read_yaml(path)
    path.write_text("a: {b: 1, b: 2}\n")
    with pytest.raises(InputError, match="a.yaml: line 1: key 'b' given twice"):
        read_yaml(path)


def test_json_with_nan_is_not_written(tmp_path):
    from xmalign.errors import OutputError
    from xmalign.formats.common import write_json

    with pytest.raises(OutputError, match="p.json: cannot write: a value is not a finite"):
        write_json(tmp_path / "p.json", {"x": float("nan")})
    assert not (tmp_path / "p.json").exists()
