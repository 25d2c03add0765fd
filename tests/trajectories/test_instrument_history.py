"""The history of the instrument programs and of the point list (docs/formats.md)."""

from __future__ import annotations

import subprocess

import pytest

from trajectories.gcode import DIALECTS
from trajectories.instruments import (
    InstrumentProgram,
    point_list_csv,
    tracker_points,
    write_instrument_program,
)
from xmalign.formats.spatial_analyzer import read_point_list
from xmalign.steps import write_instrument_step


def test_the_point_list_gets_a_history_beside_it_that_sha256sum_checks(tmp_path, machine):
    """A tracker's own software reads the list: it takes no comment, its history lies in
    points.csv.history, whose last line is the list's own sha256sum line."""
    program = InstrumentProgram(points_mm=tracker_points(machine)[:5])
    path = tmp_path / "points.csv"
    write_instrument_step(machine, program, points_path=path)
    assert path.read_text() == point_list_csv(program, machine.smr_offset)
    assert len(read_point_list(path)) == 5
    history = (tmp_path / "points.csv.history").read_text().splitlines()
    assert history[0] == "# format: xmalign.point-list/1"
    assert history[1].startswith("# software: xmalign ") and "# file: points.csv" in history
    check = subprocess.run(
        ["sha256sum", "-c", "points.csv.history"], cwd=tmp_path, capture_output=True, text=True
    )
    assert check.returncode == 0 and "points.csv: OK" in check.stdout, check.stderr
    path.write_text(path.read_text() + "9,0,0,0\n")  # a changed list no longer checks
    check = subprocess.run(
        ["sha256sum", "-c", "points.csv.history"], cwd=tmp_path, capture_output=True, text=True
    )
    assert check.returncode != 0


@pytest.mark.parametrize("dialect", sorted(DIALECTS))
def test_instrument_programs_carry_their_history(dialect, machine):
    program = InstrumentProgram(points_mm=tracker_points(machine)[:3])
    text, _ = write_instrument_program(program, machine, DIALECTS[dialect](), "xmalign tracker")
    assert "format: xmalign.instrument-program/1" in text
    assert "created_utc: 20" in text and f"dialect: {dialect}" in text
