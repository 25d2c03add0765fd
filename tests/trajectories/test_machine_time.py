"""Machine time: the program's own estimate against the simulated CNC that executes
the G-code text, and the transit / approach feeds of the measurement program."""

from __future__ import annotations

import re

import numpy as np
import pytest

from sim.clock import SimClock
from sim.cnc import SimulatedCnc
from trajectories.gcode import make_dialect
from trajectories.gcode.machine_time import move_time_s
from trajectories.gcode.program import estimate_machine_time, write_program
from trajectories.planner import plan_measurement

FEED = re.compile(r"G53 G1 X(-?[\d.]+) Y(-?[\d.]+) Z(-?[\d.]+) F([\d.]+)")


def _with(machine, section: str, **updates):
    return machine.model_copy(
        update={section: getattr(machine, section).model_copy(update=updates)}
    )


def _clock_time_s(machine, text: str) -> float:
    """Clock time of the simulated CNC running ``text`` (no time spent at the stops)."""
    clock = SimClock()
    cnc = SimulatedCnc(machine, clock)
    started = clock.now()
    list(cnc.run_program(text, "linuxcnc"))
    return clock.now() - started


@pytest.mark.parametrize("acceleration", [200.0, 1000.0, 5000.0])
def test_estimate_matches_the_simulated_cnc_executing_the_text(machine, pose, acceleration):
    machine = _with(machine, "cnc", acceleration_mm_s2=acceleration)
    plan = plan_measurement(machine, pose).plan
    text = write_program(plan, machine, make_dialect("linuxcnc", machine))
    estimate = estimate_machine_time(plan, machine)
    assert estimate.with_acceleration
    assert estimate.dwells == text.count("G4 P")
    # coordinates are rounded to 1 um in the text
    assert estimate.total_s == pytest.approx(_clock_time_s(machine, text), rel=1e-4)


def test_estimate_without_acceleration_is_length_over_feed():
    assert move_time_s(100.0, 6000.0, None) == pytest.approx(1.0)
    # a short move never reaches its feed: 2 sqrt(L / a)
    assert move_time_s(1.0, 6000.0, 1000.0) == pytest.approx(2 * np.sqrt(1.0 / 1000.0))
    assert move_time_s(0.0, 6000.0, 1000.0) == 0.0


def _feed_moves(text: str) -> list[tuple[np.ndarray, float]]:
    return [
        (np.array([float(v) for v in m.groups()[:3]]), float(m.group(4)))
        for m in FEED.finditer(text)
    ]


@pytest.mark.parametrize("max_speed", [None, 3000.0])
def test_targets_are_approached_at_the_measuring_feed_over_the_last_millimetres_only(
    machine, pose, max_speed
):
    machine = _with(machine, "interferometer", max_speed_mm_min=max_speed)
    plan = plan_measurement(machine, pose).plan
    text = write_program(plan, machine, make_dialect("linuxcnc", machine))
    transit = machine.feed_mm_min.rapid if max_speed is None else max_speed
    measure = machine.feed_mm_min.measure
    moves = _feed_moves(text)
    targets = np.vstack([line.target_points_mm() for line in plan.lines])
    onto_target = 0
    for (before, feed_before), (after, feed) in zip(moves, moves[1:], strict=False):
        if np.min(np.linalg.norm(targets - after, axis=1)) > 1e-3:
            continue
        onto_target += 1
        assert feed == measure
        assert feed_before in (transit, measure)
        if feed_before == transit:
            assert np.linalg.norm(after - before) == pytest.approx(
                machine.measurement.approach_mm, abs=2e-3
            )
    assert onto_target >= len(targets)
    assert {feed for _, feed in moves} == {transit, measure}


def test_faster_feeds_and_shorter_dwells_take_less_machine_time(machine, pose):
    plan = plan_measurement(machine, pose).plan
    base = estimate_machine_time(plan, machine).total_s
    slower = _with(machine, "interferometer", max_speed_mm_min=machine.feed_mm_min.measure)
    assert estimate_machine_time(plan, slower).total_s > base
    shorter = plan_measurement(_with(machine, "measurement", dwell_s=0.1), pose).plan
    assert estimate_machine_time(shorter, machine).total_s < base


def test_cli_program_prints_the_machine_time_of_what_it_writes(tmp_path, machine, pose):
    from tests.cli_helpers import run_cli
    from xmalign.formats.pose import write_pose

    write_pose(tmp_path / "pose.json", pose)
    result = run_cli(
        "program", "--pose", str(tmp_path / "pose.json"), "--out", str(tmp_path / "p.mpf")
    )
    assert result.returncode == 0, result.stderr
    text = " ".join(result.stderr.split())
    found = re.search(r"machine time of the program: ([\d.]+) min", text)
    assert found, text
    expected = estimate_machine_time(plan_measurement(machine, pose).plan, machine)
    assert float(found.group(1)) == pytest.approx(expected.total_s / 60, abs=0.051)
    assert f"{expected.dwells} dwells" in text
