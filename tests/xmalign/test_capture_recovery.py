"""A beam lost while capturing: found again by the search, the point captured again."""

from __future__ import annotations

import numpy as np
import pytest

from sim.dry_run import measure_virtually, virtual_setup
from trajectories.gcode import DIALECTS
from trajectories.gcode.program import write_program
from xmalign.calibration import capture_sequence, open_run_output
from xmalign.errors import BeamLostError
from xmalign.formats.measurements import read_measurements
from xmalign.formats.plan import read_plan

SEED = 2
#: The point after which something happens to the beam (on the X line).
AFTER = 10


@pytest.fixture(scope="module")
def dry_run(dry_run_of_seed):
    return dry_run_of_seed(SEED, "recovery")[1]


def _measure(machine, workdir, name, lines, on_point):
    """Measure the dry run's plan (its first ``lines``) on the same virtual setup."""
    plan = read_plan(workdir / "plan.json")
    plan.lines = plan.lines[:lines]
    program = write_program(plan, machine, DIALECTS["linuxcnc"]())
    setup = virtual_setup(machine, SEED)
    path = workdir / name

    def on_saved(saved):
        if saved == AFTER:
            on_point(setup.world.interferometer)

    with open_run_output(path, plan, resume=False) as output:
        output.on_saved = on_saved
        run = measure_virtually(setup, plan, program, "linuxcnc", output)
    return plan, setup, run, read_measurements(path)


def _every_point_once(plan, rows):
    expected = [point.key for line in plan.lines for point in capture_sequence(line)]
    return [row.key() for row in rows] == expected


def test_a_knocked_launch_unit_is_found_again_and_the_line_goes_on(dry_run, reference_machine):
    def knock(interferometer):
        interferometer.gamma_rad += 400e-6  # someone bumps the launch unit's tripod

    plan, _, run, rows = _measure(reference_machine, dry_run, "knocked.csv", 1, knock)
    assert len(run.statistics.recovered) == 1
    assert run.statistics.recovered[0].startswith(f"line X run 1 (+) target {AFTER + 1}:")
    assert _every_point_once(plan, rows)
    assert [row.segment for row in rows] == [0] * AFTER + [1] * (len(rows) - AFTER)
    # the datum was set again in the new segment: per run and segment, the linear
    # channel differs from the run without the knock by a constant only
    # (measured here too: the dry run's file holds the air of its drifting shop)
    *_, whole = _measure(reference_machine, dry_run, "whole.csv", 1, lambda interferometer: None)
    for run_number in (1, 2):
        part = [
            (a.channels[0] - b.channels[0])
            for a, b in zip(rows, whole, strict=True)
            if a.run == run_number and a.segment == 1
        ]
        assert np.std(part) < 1.5, run_number
    assert max(abs(row.channels[0]) for row in rows) < 100.0


def test_a_beam_crossed_for_a_moment_is_waited_for_without_moving_the_units(
    dry_run, reference_machine
):
    plan, setup, run, rows = _measure(
        reference_machine, dry_run, "crossed.csv", 1, lambda xm: xm.interrupt(2.5)
    )
    assert len(run.statistics.recovered) == 1
    assert _every_point_once(plan, rows)
    assert {row.segment for row in rows[AFTER:]} == {1}
    start, now = run.statistics.alignments["X"], run.setups["X"]
    moved = np.concatenate(
        [now.launch_rad - start.launch_rad, now.receiver_rad - start.receiver_rad]
    )
    assert np.abs(moved).max() < 20e-6  # the units stayed where they were locked
    # the interferometer lost its count: the new segment's datum was set again
    linear = np.array([row.channels[0] for row in rows])
    assert np.abs(linear).max() < 100.0


def test_a_beam_the_search_cannot_find_asks_for_a_person(dry_run, reference_machine):
    with pytest.raises(BeamLostError, match="not found again by the search.*--manual.*--resume"):
        _measure(reference_machine, dry_run, "blocked.csv", 1, lambda xm: xm.interrupt(1e6))
    rows = read_measurements(dry_run / "blocked.csv")
    assert len(rows) == AFTER  # nothing captured is lost, nothing is captured twice


def test_a_resume_after_a_recovery_goes_on_in_a_segment_of_its_own(dry_run, reference_machine):
    plan = read_plan(dry_run / "plan.json")
    plan.lines = plan.lines[:1]
    program = write_program(plan, reference_machine, DIALECTS["linuxcnc"]())
    setup = virtual_setup(reference_machine, SEED)
    path = dry_run / "recovered-then-stopped.csv"

    def on_saved(saved):
        if saved == AFTER:
            setup.world.interferometer.interrupt(2.5)
        if saved == AFTER + 5:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt), open_run_output(path, plan, False) as output:
        output.on_saved = on_saved
        measure_virtually(setup, plan, program, "linuxcnc", output)
    with open_run_output(path, plan, True) as output:
        run = measure_virtually(setup, plan, program, "linuxcnc", output)
    assert run.statistics.resumed[0].endswith("setup kept; its further rows are setup segment 2")
    rows = read_measurements(path)
    assert _every_point_once(plan, rows)
    assert [row.segment for row in rows] == [0] * AFTER + [1] * 5 + [2] * (len(rows) - AFTER - 5)


def test_a_beam_lost_again_while_the_point_is_captured_again_stops_the_run(
    dry_run, reference_machine
):
    def cross_then_block_at_the_new_datum(interferometer):
        interferometer.interrupt(2.5)  # back by itself (as in the test above)
        set_datum = interferometer.zero

        def zero_then_block():
            set_datum()
            interferometer.zero = set_datum
            interferometer.interrupt(1e6)  # lost again during the capture's dwell

        interferometer.zero = zero_then_block

    with pytest.raises(BeamLostError) as lost:
        _measure(reference_machine, dry_run, "lost-again.csv", 1, cross_then_block_at_the_new_datum)
    message = str(lost.value)
    assert message.startswith(f"beam lost on line X run 1 (+) target {AFTER + 1} (")
    assert message.endswith(
        "the units are locked; check the beam path, re-align and continue with --resume"
    )
    assert len(read_measurements(dry_run / "lost-again.csv")) == AFTER
