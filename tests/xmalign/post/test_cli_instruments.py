"""``xmalign post --tracker/--tracer`` end to end, and what it refuses (one line, nothing written).

examples/tracker.csv and examples/tracer.csv were written by the simulator
(sim.tracker, sim.tracer) measuring the reference machine.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from sim.machine import VirtualMachine
from sim.synthetic import measure, six_line_plan
from sim.tracker import VirtualTracker, measure_tracker
from tests.cli_helpers import assert_one_line_error, run_in_process
from trajectories.instruments import (
    InstrumentProgram,
    grid_and_random_points,
    point_list_csv,
    tracker_points,
)
from xmalign.formats.error_tables import read_error_tables
from xmalign.formats.instruments import (
    read_tracer_lengths,
    read_tracker_points,
    write_tracer_lengths,
    write_tracker_points,
)
from xmalign.formats.measurements import write_measurements
from xmalign.formats.plan import write_plan
from xmalign.machine import default_machine_path, load_machine
from xmalign.rigid_body import Chain

EXAMPLES = Path(__file__).resolve().parents[3] / "examples"


def test_post_with_a_tracker_alone_writes_tables_and_shows_the_station(tmp_path: Path) -> None:
    out = tmp_path / "errors.csv"
    result = run_in_process("post", "--tracker", str(EXAMPLES / "tracker.csv"), "--out", str(out))
    assert result.returncode == 0, result.stderr
    tables = read_error_tables(out)
    assert {"EXX", "EYY", "EZZ", "ECZ"} <= set(tables.tables)
    assert np.all(np.isnan(tables.tables["ECZ"].u95))
    assert "tracker T1 (500 points" in result.stdout
    assert "the tables are those of the SMR" in result.stdout


def test_post_with_tracers_alone_self_calibrates_four_places(tmp_path: Path) -> None:
    out, report = tmp_path / "errors.csv", tmp_path / "report.html"
    result = run_in_process(
        "post", "--tracer", str(EXAMPLES / "tracer.csv"), "--out", str(out), "--report", str(report)
    )
    assert result.returncode == 0, result.stderr
    for place in ("P1", "P2", "P3", "P4"):
        assert f"tracer {place}" in result.stdout
        assert f"tracer {place} (" in report.read_text()
    assert out.exists()


def test_post_knot_spacing_is_chosen_or_given_and_an_outlier_is_named(tmp_path: Path) -> None:
    """Without the option the console says which spacing cross-validation chose; with it,
    the tables' compensation points are that far apart. A tracker point 3 mm off is named
    as a gross outlier and left out."""
    points = read_tracker_points(EXAMPLES / "tracker.csv").points
    bumped = points[:10] + [replace(points[10], tracker_mm=points[10].tracker_mm + 3.0)]
    damaged = tmp_path / "tracker.csv"
    write_tracker_points(damaged, bumped + points[11:])
    chosen = run_in_process("post", "--tracker", str(damaged), "--out", str(tmp_path / "a.csv"))
    assert chosen.returncode == 0, chosen.stderr
    assert "apart: the least generalised cross-validation score of" in chosen.stdout
    run, index = points[10].run, points[10].index
    assert f"tracker station T1 run {run} index {index}:" in chosen.stdout
    assert "a gross outlier: left out of the fit" in chosen.stdout
    out = tmp_path / "b.csv"
    given = run_in_process(
        "post", "--tracker", str(damaged), "--out", str(out), "--knot-spacing-mm", "500"
    )
    assert given.returncode == 0, given.stderr
    assert "cross-validation" not in given.stdout
    table = read_error_tables(out).tables["EXX"]
    np.testing.assert_allclose(np.diff(table.positions_mm[table.measured_mask()][::4]), 500.0)


def test_post_fits_lines_and_tracker_points_together(
    tmp_path: Path, reference_machine, reference_machine_path
) -> None:
    chain = Chain.parse(reference_machine.chain)
    truth = VirtualMachine(reference_machine, seed=2)
    plan = six_line_plan(reference_machine, 10, runs=1, bidirectional=False)
    write_plan(tmp_path / "plan.json", plan)
    write_measurements(tmp_path / "m.csv", measure(plan, chain, truth, np.random.default_rng(2)))
    points = grid_and_random_points(
        reference_machine.travel_min_mm, reference_machine.travel_max_mm, (4, 4, 3), 60, 2
    )
    tracker = VirtualTracker(np.array([1000.0, 750, -800]), np.array([0.0, 0, 45]), seed=2)
    write_tracker_points(
        tmp_path / "t.csv", measure_tracker(truth, tracker, points, 1, reference_machine.smr_offset)
    )
    out = tmp_path / "errors.csv"
    result = run_in_process(
        "post",
        "--machine", str(reference_machine_path),
        "--plan", str(tmp_path / "plan.json"),
        "--data", str(tmp_path / "m.csv"),
        "--tracker", str(tmp_path / "t.csv"),
        "--out", str(out),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    tables = read_error_tables(out)
    assert np.all(np.isfinite(tables.tables["ECZ"].u95))  # the lines see every rotation
    assert "tracker T1 (108 points" in result.stdout


def test_a_damaged_tracker_file_is_one_line_and_nothing_is_written(tmp_path: Path) -> None:
    bad = tmp_path / "t.csv"
    lines = (EXAMPLES / "tracker.csv").read_text().splitlines()
    lines[10] = lines[10].replace(",", ",x", 1)
    bad.write_text("\n".join(lines) + "\n")
    out = tmp_path / "errors.csv"
    result = run_in_process("post", "--tracker", str(bad), "--out", str(out))
    assert_one_line_error(result, str(bad), "line 11", "run")
    assert not out.exists()


def test_too_few_tracer_places_are_one_line_and_nothing_is_written(tmp_path: Path) -> None:
    tracer = read_tracer_lengths(EXAMPLES / "tracer.csv")
    three = tmp_path / "three.csv"
    write_tracer_lengths(three, [r for r in tracer.lengths if r.station != "P4"])
    out = tmp_path / "errors.csv"
    result = run_in_process("post", "--tracer", str(three), "--out", str(out))
    assert_one_line_error(result, "3 tracer places cannot place the points")
    assert not out.exists()


@pytest.mark.parametrize(
    ("argv", "fragment"),
    [
        ((), "post: nothing to fit"),
        (("--verify-data", "v.csv", "--tracker", "t.csv"), "--verify-data needs --verify-plan"),
    ],
)
def test_post_without_anything_to_fit_says_so(tmp_path: Path, argv, fragment: str) -> None:
    result = run_in_process("post", "--out", str(tmp_path / "e.csv"), *argv)
    assert_one_line_error(result, fragment)


@pytest.mark.parametrize("dialect", ["iso", "sinumerik", "heidenhain", "linuxcnc"])
def test_program_for_a_tracker_writes_every_point_and_the_point_list(
    tmp_path: Path, dialect: str
) -> None:
    out, points = tmp_path / "t.nc", tmp_path / "points.csv"
    result = run_in_process(
        "program", "--instrument", "tracker", "--dialect", dialect,
        "--out", str(out), "--points-out", str(points),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    text = out.read_text()
    rows = points.read_text().splitlines()
    count = len(rows) - 1
    assert f"point {count - 1}" in text and f"point {count}" not in text
    # the reference machine names no SMR positions: three proposed, each measuring the
    # 5 x 4 x 3 grid and a third of the 190 random points, mounted at a programmed stop
    assert count == 3 * 60 + 190
    assert rows[0] == "name,x_mm,y_mm,z_mm,smr" and rows[1].startswith("0,")
    assert [row.split(",")[-1] for row in rows[1:]] == ["A"] * 124 + ["B"] * 123 + ["C"] * 123
    assert text.count("mount SMR") == 2 * 3  # a comment and a message at each
    assert "machine time:" in result.stderr and "run it twice" in result.stderr
    assert "SMR B (100, 0, 0 mm) before point 124" in result.stderr


def test_program_for_tracers_proposes_places_and_says_how_good(tmp_path: Path) -> None:
    result = run_in_process(
        "program", "--instrument", "tracer", "--places", "5", "--out", str(tmp_path / "p.mpf")
    )
    assert result.returncode == 0, result.stderr
    assert "tracer place P5" in result.stderr
    assert "the volumetric error over the whole travel to about" in result.stderr


def test_program_on_the_fly_writes_paths(tmp_path: Path) -> None:
    out = tmp_path / "fly.ngc"
    result = run_in_process(
        "program", "--instrument", "tracker", "--on-the-fly", "--dialect", "linuxcnc",
        "--out", str(out),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert "(path 70)" in out.read_text() and "F5000.0" in out.read_text()


@pytest.mark.parametrize(
    ("argv", "fragment"),
    [
        (("--places", "4"), "--places needs --instrument"),
        (("--instrument", "laser"), "--instrument 'laser' is not known"),
        (("--instrument", "tracer", "--on-the-fly"), "--on-the-fly is for --instrument tracker"),
        (("--instrument", "tracer", "--places", "3"), "--places 3: give 4 to 12"),
    ],
)
def test_program_instrument_options_that_do_not_fit(argv, fragment: str) -> None:
    assert_one_line_error(run_in_process("program", *argv), fragment)


def _point_list(tmp_path: Path) -> Path:
    """The point list of a tracker program with the one SMR of examples/spatial-analyzer.txt
    (``program`` itself plans several where the machine file names none)."""
    machine = load_machine(default_machine_path())
    points = tmp_path / "points.csv"
    program = InstrumentProgram(points_mm=tracker_points(machine))
    points.write_text(point_list_csv(program, machine.smr_offset))
    return points


def test_import_of_a_spatial_analyzer_export_gives_the_tracker_points(tmp_path: Path) -> None:
    """examples/spatial-analyzer.txt holds the readings of examples/tracker.csv."""
    out = tmp_path / "tracker.csv"
    result = run_in_process(
        "import", "--spatial-analyzer", str(EXAMPLES / "spatial-analyzer.txt"),
        "--points", str(_point_list(tmp_path)), "--out", str(out),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    imported = read_tracker_points(out).points
    expected = read_tracker_points(EXAMPLES / "tracker.csv").points
    assert [(p.run, p.index) for p in imported] == [(p.run, p.index) for p in expected]
    np.testing.assert_array_equal(
        [p.tracker_mm for p in imported], [p.tracker_mm for p in expected]
    )
    np.testing.assert_allclose([p.machine_mm for p in imported], [p.machine_mm for p in expected])


def test_import_reads_commas_and_header_lines(tmp_path: Path) -> None:
    export = tmp_path / "sa.csv"
    export.write_text("// header\n// Collection,Group,Target,X,Y,Z\nA,g1,0,1,2,3\nA,g2,0,1,2,4\n")
    out = tmp_path / "t.csv"
    result = run_in_process(
        "import", "--spatial-analyzer", str(export), "--points", str(_point_list(tmp_path)),
        "--out", str(out),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert [(p.run, p.index) for p in read_tracker_points(out).points] == [(0, 0), (1, 0)]


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("A g 0 1 2\n", "line 1: 5 fields"),
        ("// x\nA g 0 1 2 abc\n", "line 2: '1 2 abc' is not X Y Z"),
        ("A g 9999 1 2 3\n", "line 1: target '9999' is not in the point list"),
        ("A g 0 1 2 3\nA g 0 1 2 3\n", "line 2: target '0' twice in group 'g'"),
        ("// only a header\n", "no points"),
    ],
)
def test_a_damaged_export_is_one_line_and_nothing_is_written(
    tmp_path: Path, text: str, fragment: str
) -> None:
    export = tmp_path / "sa.txt"
    export.write_text(text)
    out = tmp_path / "t.csv"
    result = run_in_process(
        "import", "--spatial-analyzer", str(export), "--points", str(_point_list(tmp_path)),
        "--out", str(out),
    )  # fmt: skip
    assert_one_line_error(result, str(export), fragment)
    assert not out.exists()


@pytest.mark.parametrize("instrument", ["tracker", "tracer"])
def test_dry_run_of_an_instrument_runs_the_chain_against_the_truth(
    tmp_path: Path, instrument: str
) -> None:
    out = tmp_path / "dry"
    result = run_in_process("dry-run", "--instrument", instrument, "--out", str(out), "--seed", "3")
    assert result.returncode == 0, result.stderr
    assert "volumetric error over the whole travel" in result.stdout
    after = float(result.stdout.split(" after ")[1].split(" um")[0])
    assert after < (5.0 if instrument == "tracker" else 1.0)
    assert (out / f"{instrument}.csv").exists() and (out / "errors-instruments.csv").exists()
    again = run_in_process("dry-run", "--instrument", instrument, "--out", str(out))
    assert_one_line_error(again, "already holds")


def test_dry_run_of_an_xm60_station_with_a_tracker(tmp_path: Path) -> None:
    out = tmp_path / "dry"
    result = run_in_process("dry-run", "--instrument", "xm60+tracker", "--out", str(out))
    assert result.returncode == 0, result.stderr
    after = float(result.stdout.split(" after ")[1].split(" um")[0])
    alone = float(result.stdout.split("station alone: ")[1].split(" um")[0])
    assert after < 0.8 * alone
    assert (out / "measurements.csv").exists() and (out / "tracker.csv").exists()


def test_mc_compares_the_instruments_on_the_same_machines(tmp_path: Path) -> None:
    out = tmp_path / "mc"
    result = run_in_process("mc", "--mode", "instruments", "--trials", "1", "--out", str(out))
    assert result.returncode == 0, result.stderr
    document = json.loads((out / "mc-instruments.json").read_text())
    names = [s["name"] for s in document["strategies"]]
    assert names == ["tracker", "tracker on the fly", "tracers", "xm60", "xm60+tracker"]
    residual = {s["name"]: s["residual_um"][0] for s in document["strategies"]}
    assert residual["tracers"] < residual["tracker"]
    assert residual["xm60+tracker"] < residual["xm60"]
    assert "xm60+tracker" in result.stdout
