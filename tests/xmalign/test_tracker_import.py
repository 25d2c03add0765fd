"""``xmalign import``: SpatialAnalyzer's ASCII export variants and plain Name,X,Y,Z lists.

The variants are those SpatialAnalyzer's user manual lists for its ASCII point
export ("Exporting ASCII Formatted Points": point names Collection Group Target,
Group Target or Target; spaces or commas; optional columns after the
coordinates; ``//`` header lines), made from examples/spatial-analyzer.txt,
which holds the readings of examples/tracker.csv.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import assert_one_line_error, run_in_process

from xmalign.formats.instruments import read_tracker_points
from xmalign.formats.spatial_analyzer import read_point_list, tracker_file_from_export
from xmalign.machine import default_machine_path, load_machine

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "spatial-analyzer.txt"
Fields = list[str]


@pytest.fixture(scope="module")
def machine_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The reference machine with the one SMR position the example export was measured with."""
    path = tmp_path_factory.mktemp("machine") / "one-smr.yaml"
    text = default_machine_path().read_text()
    path.write_text(text + "smr_offsets_mm: {A: [0, 0, 0]}\n")
    return path


@pytest.fixture(scope="module")
def point_list(tmp_path_factory: pytest.TempPathFactory, machine_file: Path) -> Path:
    """The point list ``program`` writes for that machine (one SMR: the example's points)."""
    folder = machine_file.parent
    result = run_in_process(
        "program", "--instrument", "tracker", "--points-out", str(folder / "points.csv"),
        "--out", str(folder / "t.mpf"), "--machine", str(machine_file),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    return folder / "points.csv"


def _variant(path: Path, line: Callable[[Fields], str], header: str = "") -> Path:
    rows = [x.split() for x in EXAMPLE.read_text().splitlines() if not x.startswith("//")]
    path.write_text(header + "".join(line(f) + "\n" for f in rows))
    return path


def _import(point_list: Path, out: Path, *options: str):
    machine = point_list.parent / "one-smr.yaml"
    return run_in_process(
        "import", *options, "--points", str(point_list), "--out", str(out),
        "--machine", str(machine),
    )  # fmt: skip


def _assert_like_the_example(out: Path, scale: float = 1.0) -> None:
    expected = read_tracker_points(ROOT / "examples" / "tracker.csv").points
    imported = read_tracker_points(out).points
    assert [(p.run, p.index) for p in imported] == [(p.run, p.index) for p in expected]
    np.testing.assert_allclose(
        [p.tracker_mm for p in imported], [p.tracker_mm for p in expected], atol=2e-4 * scale
    )


@pytest.mark.parametrize(
    ("name", "line", "options"),
    [
        ("tabs-extra-columns.txt", lambda f: "\t".join([*f, "0.012", "2026-11-27 10:00:01"]), ()),
        ("commas.csv", lambda f: ",".join(f), ()),
        ("group-target.txt", lambda f: " ".join(f[1:]), ("--naming", "group-target")),
        ("spaces-extra.txt", lambda f: "  ".join([*f, "0.01", "0.01", "0.02"]), ()),
    ],
)
def test_spatial_analyzer_variants_give_the_same_points(
    tmp_path: Path, point_list: Path, name: str, line: Callable[[Fields], str], options
) -> None:
    export = _variant(tmp_path / name, line, "// SA version 2023.1\n// Frame: Tracker\n")
    out = tmp_path / "t.csv"
    result = _import(point_list, out, "--spatial-analyzer", str(export), *options)
    assert result.returncode == 0, result.stderr
    _assert_like_the_example(out)


def test_target_naming_without_groups_counts_runs_by_repeats(tmp_path: Path, point_list) -> None:
    export = _variant(tmp_path / "t.txt", lambda f: " ".join(f[2:]))
    out = tmp_path / "t.csv"
    result = _import(point_list, out, "--spatial-analyzer", str(export), "--naming", "target")
    assert result.returncode == 0, result.stderr
    _assert_like_the_example(out)


def test_a_plain_name_xyz_export_in_inches_is_read_with_units_in(tmp_path, point_list) -> None:
    export = _variant(
        tmp_path / "plain.csv",
        lambda f: ",".join([f[2], *(f"{float(v) / 25.4:.7f}" for v in f[3:])]),
        "Name,X,Y,Z\n",
    )
    out = tmp_path / "t.csv"
    refused = _import(point_list, out, "--name-xyz", str(export))
    assert_one_line_error(refused, "plain.csv", "line 2", "in inches", "--units in")
    assert not out.exists()
    result = _import(point_list, out, "--name-xyz", str(export), "--units", "in")
    assert result.returncode == 0, result.stderr
    assert "read in in" in result.stderr
    _assert_like_the_example(out, scale=25.4)


def test_an_export_in_metres_named_mm_is_refused(tmp_path: Path, point_list: Path) -> None:
    export = _variant(
        tmp_path / "m.txt", lambda f: " ".join([*f[:3], *(str(float(v) / 1000) for v in f[3:])])
    )
    result = _import(point_list, tmp_path / "t.csv", "--spatial-analyzer", str(export))
    assert_one_line_error(result, "m.txt", "line 1", "in metres", "--units m")


@pytest.mark.parametrize(("shift", "line"), [(1, "line 1"), (-1, "line 2")])
def test_names_shifted_against_the_point_list_are_refused_at_the_first(
    tmp_path: Path, point_list: Path, shift: int, line: str
) -> None:
    def shifted(f: Fields) -> str:
        return " ".join([*f[:2], str(int(f[2]) + shift), *f[3:]])

    export = _variant(tmp_path / "s.txt", shifted)
    result = _import(point_list, tmp_path / "t.csv", "--spatial-analyzer", str(export))
    assert_one_line_error(result, "s.txt", line, "names shifted")


def test_the_import_through_the_api_checks_the_same(tmp_path: Path, point_list: Path) -> None:
    machine = load_machine(point_list.parent / "one-smr.yaml")
    listed = read_point_list(point_list)
    file = tracker_file_from_export(machine, EXAMPLE, listed, "T1")
    assert len(file.points) == 500 and file.lines[0] == 3
    export = _variant(
        tmp_path / "i.txt", lambda f: " ".join([*f[:3], *(str(float(v) / 25.4) for v in f[3:])])
    )
    file = tracker_file_from_export(machine, export, listed, "T1", units="in")
    assert file.points[0].tracker_mm[0] == pytest.approx(-1225.6882)


def test_a_program_with_three_smr_positions_imports_to_the_rows_measured(tmp_path: Path) -> None:
    """program (three SMR positions) -> virtual tracker -> SpatialAnalyzer export -> import:
    each row's commanded point and SMR come back from the point list."""
    from sim.instrument_examples import spatial_analyzer_text
    from sim.machine import VirtualMachine
    from sim.tracker import VirtualTracker, measure_tracker
    from trajectories.instruments import plan_instrument, tracker_place

    machine_file = tmp_path / "three.yaml"
    offsets = "{A: [0, 0, -100], B: [120, 0, -100], C: [0, 120, -60]}"
    machine_file.write_text(default_machine_path().read_text() + f"smr_offsets_mm: {offsets}\n")
    points = tmp_path / "points.csv"
    result = run_in_process(
        "program", "--instrument", "tracker", "--points-out", str(points),
        "--out", str(tmp_path / "t.mpf"), "--machine", str(machine_file),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    machine = load_machine(machine_file)
    program = plan_instrument(machine, "tracker").program
    tracker = VirtualTracker(tracker_place(machine), seed=4)
    rows = measure_tracker(
        VirtualMachine(machine, seed=4), tracker, program.points_mm, 1, machine.smr_offset,
        smr_offsets_mm=machine.smr_offsets(), smr_of_point=program.smr_names,
    )  # fmt: skip
    export = tmp_path / "sa.txt"
    export.write_text(spatial_analyzer_text(rows))
    out = tmp_path / "tracker.csv"
    imported = run_in_process(
        "import", "--spatial-analyzer", str(export), "--points", str(points), "--out", str(out),
        "--machine", str(machine_file),
    )  # fmt: skip
    assert imported.returncode == 0, imported.stderr
    back = read_tracker_points(out).points
    assert [(p.run, p.index, p.smr) for p in back] == [(p.run, p.index, p.smr) for p in rows]
    np.testing.assert_allclose(
        [p.machine_mm for p in back], [p.machine_mm for p in rows], atol=1e-3
    )
