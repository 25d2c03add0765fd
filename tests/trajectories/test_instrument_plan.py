"""Instrument plans with several SMR positions, and tracers at once (trajectories.instruments)."""

from __future__ import annotations

import numpy as np
import pytest

from trajectories.gcode import make_dialect
from trajectories.instruments import (
    SMR_CHANGE_S,
    TRACER_RANDOM,
    TRACKER_GRID,
    InstrumentProgram,
    plan_instrument,
    plan_smr_positions,
    point_list_csv,
    shared_points_program,
    tracer_points,
    write_instrument_program,
)
from xmalign.formats.spatial_analyzer import read_point_list


def test_the_machine_files_smr_positions_are_used(reference_machine) -> None:
    named = {"T": [0.0, 0.0, -250.0], "S": [80.0, 0.0, -200.0]}
    machine = reference_machine.model_copy(update={"smr_offsets_mm": named})
    offsets, proposed = plan_smr_positions(machine)
    assert not proposed and list(offsets) == ["T", "S"]
    np.testing.assert_array_equal(offsets["S"], [80.0, 0.0, -200.0])


def test_proposed_smr_positions_are_not_on_one_line_through_the_tool_point(
    reference_machine,
) -> None:
    for base in ([0.0, 0.0, 0.0], [0.0, 0.0, -100.0], [30.0, -20.0, -150.0]):
        machine = reference_machine.model_copy(update={"smr_offset_mm": base})
        offsets, proposed = plan_smr_positions(machine)
        assert proposed and len(offsets) == 3
        np.testing.assert_array_equal(offsets["A"], base)
        assert np.linalg.matrix_rank(np.array(list(offsets.values())), tol=1.0) >= 2


def test_shared_points_cover_the_grid_with_every_smr_and_each_random_point_once(
    reference_machine,
) -> None:
    offsets, _ = plan_smr_positions(reference_machine)
    program = shared_points_program(reference_machine, TRACER_RANDOM, offsets)
    single = tracer_points(reference_machine)
    grid = int(np.prod(TRACKER_GRID))
    assert len(program.points_mm) == 3 * grid + TRACER_RANDOM
    assert program.smr_order == ["A", "B", "C"]
    names = np.array(program.smr_names)
    assert list(names) == sorted(names)  # one SMR after the other: two changes
    everything = {tuple(p) for p in single}
    for name in "ABC":
        block = {tuple(p) for p in program.points_mm[names == name]}
        assert block <= everything
        assert len(block & {tuple(p) for p in single}) >= grid
    assert {tuple(p) for p in program.points_mm} == everything
    assert [program.run_of(i, 1) for i in (0, len(names) - 1)] == [3, 5]


def test_the_program_stops_for_each_smr_and_counts_the_change(reference_machine) -> None:
    offsets, _ = plan_smr_positions(reference_machine)
    program = shared_points_program(reference_machine, 12, offsets)
    dialect = make_dialect("linuxcnc", reference_machine, "t")
    text, time = write_instrument_program(program, reference_machine, dialect, "t")
    lines = text.splitlines()
    stops = [i for i, line in enumerate(lines) if line.strip() == "M0"]
    assert len(stops) == 3
    assert "(MSG,mount SMR B at 100, 0, 0 mm" in lines[stops[1] - 1]
    first_b = program.smr_names.index("B")
    assert lines[stops[1] + 1] == f"(point {first_b})"
    single = InstrumentProgram(points_mm=program.points_mm)
    one_smr, plain = write_instrument_program(single, reference_machine, dialect, "t")
    assert "M0" not in one_smr and time.total_s > plain.total_s + 3 * SMR_CHANGE_S - 1


def test_the_point_list_names_each_points_smr_and_offsets_it(reference_machine, tmp_path) -> None:
    offsets, _ = plan_smr_positions(reference_machine)
    program = shared_points_program(reference_machine, 12, offsets)
    path = tmp_path / "points.csv"
    path.write_text(point_list_csv(program, reference_machine.smr_offset))
    listed = read_point_list(path)
    index = program.smr_names.index("C")
    assert listed[str(index)].smr == "C"
    np.testing.assert_allclose(listed[str(index)].smr_mm, program.points_mm[index] + [0, 100, 0])


@pytest.mark.parametrize("places", [4, 6])
def test_tracers_at_once_take_one_run_instead_of_one_per_place(reference_machine, places) -> None:
    apart = plan_instrument(reference_machine, "tracer", places=places)
    together = plan_instrument(reference_machine, "tracer", places=places, simultaneous=True)
    assert (apart.runs, together.runs) == (places, 1)
    assert together.limit_um == pytest.approx(apart.limit_um)
    assert "tracers at once" in together.notes[0]
    assert any("SMR B (100, 0, 0 mm) before point" in note for note in together.notes)
