"""Tracker-point and tracer-length files: round trips and damaged files (docs/formats.md)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from xmalign.errors import InputError
from xmalign.formats.instruments import (
    TRACER_FORMAT,
    TRACKER_FORMAT,
    TracerLength,
    TrackerPoint,
    read_tracer_lengths,
    read_tracker_points,
    tracer_lengths_text,
    tracker_points_text,
    write_tracer_lengths,
    write_tracker_points,
)
from xmalign.formats.provenance import FileSource

coordinate = st.floats(-5000, 5000, allow_nan=False)
point = st.tuples(coordinate, coordinate, coordinate).map(np.array)
name = st.text("ABCxyz019_-", min_size=1, max_size=6)


@st.composite
def tracker_points(draw: st.DrawFn) -> list[TrackerPoint]:
    n = draw(st.integers(1, 8))
    points = []
    for i in range(n):
        fly = draw(st.booleans())
        points.append(
            TrackerPoint(
                station=draw(name),
                run=draw(st.integers(0, 3)),
                index=None if fly else i,
                machine_mm=draw(point),
                tracker_mm=draw(point),
                to_mm=draw(point) if fly else None,
                time_s=draw(st.none() | st.floats(0, 1e4)),
                u_radial_um=draw(st.none() | st.floats(0.1, 50)),
            )
        )
    return points


def _same_tracker(a: TrackerPoint, b: TrackerPoint) -> None:
    assert (a.station, a.run, a.index, a.time_s, a.u_radial_um, a.u_transverse_um) == (
        b.station,
        b.run,
        b.index,
        b.time_s,
        b.u_radial_um,
        b.u_transverse_um,
    )
    np.testing.assert_array_equal(a.machine_mm, b.machine_mm)
    np.testing.assert_array_equal(a.tracker_mm, b.tracker_mm)
    assert (a.to_mm is None) == (b.to_mm is None)
    if a.to_mm is not None:
        np.testing.assert_array_equal(a.to_mm, b.to_mm)


@settings(max_examples=40, deadline=None)
@given(tracker_points())
def test_tracker_points_round_trip(tmp_path_factory: pytest.TempPathFactory, points) -> None:
    path = tmp_path_factory.mktemp("t") / "tracker.csv"
    write_tracker_points(path, points, [FileSource("plan", "plan.json", "ab" * 32)])
    read = read_tracker_points(path)
    assert len(read.points) == len(points)
    for a, b in zip(points, read.points, strict=True):
        _same_tracker(a, b)
    assert f"# input plan: {'ab' * 32}  plan.json" in read.comments


@settings(max_examples=40, deadline=None)
@given(
    st.lists(st.tuples(name, st.integers(0, 3), point, st.floats(-1e4, 1e4)), min_size=1),
    st.dictionaries(name, point, max_size=3),
)
def test_tracer_lengths_round_trip(tmp_path_factory: pytest.TempPathFactory, rows, guesses) -> None:
    lengths = [
        TracerLength(station, run, i, machine, length)
        for i, (station, run, machine, length) in enumerate(rows)
    ]
    path = tmp_path_factory.mktemp("t") / "tracer.csv"
    write_tracer_lengths(path, lengths, guesses)
    read = read_tracer_lengths(path)
    assert [(r.station, r.run, r.index, r.length_mm) for r in read.lengths] == [
        (r.station, r.run, r.index, r.length_mm) for r in lengths
    ]
    assert set(read.guesses_mm) == set(guesses)
    for key, guess in guesses.items():
        np.testing.assert_array_equal(read.guesses_mm[key], guess)


TRACKER_GOOD = (
    f"{TRACKER_FORMAT}\nstation,run,index,x_mm,y_mm,z_mm,tx_mm,ty_mm,tz_mm\n"
    "T1,0,0,0,0,0,1000,0,0\nT1,0,1,100,0,0,1100,0,0\n"
)
TRACER_GOOD = (
    f"{TRACER_FORMAT}\n# station P1 guess_mm=0,0,-600\nstation,run,index,x_mm,y_mm,z_mm,length_mm\n"
    "P1,0,0,0,0,0,600.5\n"
)


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("station,run\n", "line 1: expected '# xmalign tracker-points/1'"),
        ("", "line 1: expected"),
        (TRACKER_GOOD.replace("tz_mm\n", "\n").replace(",0\nT1", "\nT1"), "lacks column tz_mm"),
        (TRACKER_GOOD + "T1,0,2,1e3,0,0,abc,0,0\n", "line 5: tx_mm 'abc' is not a number"),
        (TRACKER_GOOD + "T1,0,2,1e3,0,0,nan,0,0\n", "line 5: tx_mm is nan"),
        (TRACKER_GOOD + "T1,-1,2,0,0,0,0,0,0\n", "line 5: run '-1'"),
        (TRACKER_GOOD + ",0,2,0,0,0,0,0,0\n", "line 5: empty station"),
        (TRACKER_GOOD + "T1,0,1,0,0,0,0,0,0\n", "line 5: repeats the reading of line 4"),
        (TRACKER_GOOD + "T1,0,,0,0,0,0,0,0\n", "line 5: a point on the fly"),
        (TRACKER_GOOD + "T1,0,3,0,0\n", "line 5: 5 fields"),
        (TRACKER_GOOD + "T1,0,3,2e5,0,0,0,0,0\n", "line 5: x_mm/y_mm/z_mm"),
        (TRACKER_GOOD.split("T1")[0], "no readings"),
        (TRACKER_GOOD.rstrip("\n"), "line 4: the last row has no line end"),
    ],
)
def test_damaged_tracker_file_names_file_and_line(tmp_path: Path, text: str, fragment: str) -> None:
    path = tmp_path / "tracker.csv"
    path.write_text(text)
    with pytest.raises(InputError) as caught:
        read_tracker_points(path)
    message = str(caught.value)
    assert message.startswith(str(path)) and fragment in message
    assert "\n" not in message


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        (TRACKER_GOOD, "line 1: expected '# xmalign tracer-lengths/1'"),
        (TRACER_GOOD.replace("guess_mm=0,0,-600", "guess_mm=0,0"), "line 2: guess_mm '0,0'"),
        (TRACER_GOOD.replace("guess_mm=0,0,-600", "guess_mm=a,0,0"), "line 2: guess_mm"),
        (TRACER_GOOD + "P1,0,,0,0,0,1\n", "line 5: a tracer length needs an index"),
        (TRACER_GOOD + "P1,0,1,0,0,0,inf\n", "line 5: length_mm is inf"),
        (TRACER_GOOD + "P1,0,0,0,0,0,1\n", "line 5: repeats the reading of line 4"),
    ],
)
def test_damaged_tracer_file_names_file_and_line(tmp_path: Path, text: str, fragment: str) -> None:
    path = tmp_path / "tracer.csv"
    path.write_text(text)
    with pytest.raises(InputError) as caught:
        read_tracer_lengths(path)
    assert str(caught.value).startswith(str(path)) and fragment in str(caught.value)


def test_unknown_columns_are_ignored_and_order_is_free(tmp_path: Path) -> None:
    path = tmp_path / "tracker.csv"
    path.write_text(
        f"{TRACKER_FORMAT}\nindex,station,note,run,tz_mm,ty_mm,tx_mm,z_mm,y_mm,x_mm\n"
        "4,T2,hello,1,3,2,1,-30,20,10\n"
    )
    (p,) = read_tracker_points(path).points
    assert (p.station, p.run, p.index) == ("T2", 1, 4)
    np.testing.assert_array_equal(p.machine_mm, [10, 20, -30])
    np.testing.assert_array_equal(p.tracker_mm, [1, 2, 3])


def test_text_of_points_without_optional_columns_has_the_contract_header() -> None:
    text = tracker_points_text([TrackerPoint("T1", 0, 0, np.zeros(3), np.ones(3))])
    assert text.splitlines()[0] == TRACKER_FORMAT
    assert "station,run,index,x_mm,y_mm,z_mm,tx_mm,ty_mm,tz_mm" in text.splitlines()
    text = tracer_lengths_text([TracerLength("P1", 0, 0, np.zeros(3), 1.0)], {"P1": np.zeros(3)})
    assert "# station P1 guess_mm=0.0,0.0,0.0" in text.splitlines()


def test_machine_keys_for_tracker_and_tracer(tmp_path: Path) -> None:
    from xmalign.machine import default_machine_path, load_machine

    text = default_machine_path().read_text()
    good = tmp_path / "m.yaml"
    good.write_text(
        text + "smr_offset_mm: [0, 0, -100]\ntracker:\n  radial_um: [4, 0.2]\n"
        "tracer:\n  length_um: [0.1, 0.15]\n"
    )
    machine = load_machine(good)
    np.testing.assert_array_equal(machine.smr_offset, [0, 0, -100])
    np.testing.assert_allclose(machine.tracker.radial_sigma_mm(np.array([2000.0])), [4.4e-3])
    np.testing.assert_allclose(machine.tracker.transverse_sigma_mm(np.array([1000.0])), [10.5e-3])
    np.testing.assert_allclose(machine.tracer.length_sigma_mm(np.array([1000.0])), [0.25e-3])
    bad = tmp_path / "bad.yaml"
    bad.write_text(text + "tracer:\n  length_um: [0.1]\n")
    with pytest.raises(InputError) as caught:
        load_machine(bad)
    assert str(bad) in str(caught.value) and "tracer" in str(caught.value)
    assert "\n" not in str(caught.value)


def test_tracker_and_tracer_files_carry_the_common_history_sha256sum_checks(tmp_path) -> None:
    """The history form of every CSV xmalign writes: format, software, created_utc, and
    ``# input ROLE: SHA-256  PATH`` lines that ``sha256sum -c`` checks once the prefix is
    taken off."""
    import subprocess

    export = tmp_path / "export.txt"
    export.write_text("any bytes\n")
    tracker = tmp_path / "tracker.csv"
    point = TrackerPoint("T1", 0, 0, np.zeros(3), np.ones(3))
    write_tracker_points(tracker, [point], [FileSource.of("spatial_analyzer", export)])
    tracer = tmp_path / "tracer.csv"
    write_tracer_lengths(tracer, [], inputs=[FileSource.of("plan", export)])
    for path, name in ((tracker, "tracker-points"), (tracer, "tracer-lengths")):
        lines = path.read_text().splitlines()
        assert lines[1:3] == [f"# format: xmalign.{name}/1", lines[2]]
        assert lines[2].startswith("# software: xmalign ") and lines[3].startswith(
            "# created_utc: "
        )
        checks = [line.split(": ", 1)[1] for line in lines if line.startswith("# input ")]
        result = subprocess.run(
            ["sha256sum", "-c"], input="\n".join(checks) + "\n", capture_output=True, text=True
        )
        assert result.returncode == 0 and f"{export}: OK" in result.stdout, result.stderr
