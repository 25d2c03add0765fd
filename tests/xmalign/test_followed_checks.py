"""A followed run (MTConnect, SINUMERIK, a position file): its timeout, and the check of a
program stopped where the plan has no stop, on a scripted controller (no real time)."""

from __future__ import annotations

import numpy as np
import pytest
from scripted_cnc import (
    PROGRAM,
    WAY,
    ScriptedCnc,
    ScriptedInterferometer,
    VirtualClock,
    program_route,
    scripted_run,
    two_line_plan,
)

from xmalign.calibration import capture_sequence, follow_machine
from xmalign.errors import DeviceError
from xmalign.roles import ProgramReport
from xmalign.steps import following_drive

PLAN = two_line_plan()
POINTS = [point.key for line in PLAN.lines for point in capture_sequence(line)]


class FollowedCnc(ScriptedCnc):
    """The operator's program on a controller that reports it: each stop is a dwell of 1 s
    (at a line's stop the operator presses cycle start as soon as the units are set)."""

    def program_report(self) -> ProgramReport:
        return ProgramReport(self.loaded, self.state)


def _followed(route_of=lambda route: route) -> tuple[FollowedCnc, object, list, list[str]]:
    clock = VirtualClock()
    cnc = FollowedCnc(clock, route_of(program_route(PLAN, np.array([0.0, 0.0, -100.0]))))

    def dwell(number: int, arrived_s: float) -> None:
        cnc.cycle_start_at_s = arrived_s + 1.0

    cnc.on_stop = dwell
    cnc.start_program(PROGRAM)
    run, rows = scripted_run(PLAN, ScriptedInterferometer(clock))
    return cnc, run, rows, []


def test_a_followed_program_is_followed_to_its_end():
    cnc, run, rows, told = _followed()
    follow_machine(run, cnc, PLAN.lines, told.append, WAY, timeout_s=60.0)
    assert [row.key() for row in rows] == POINTS


def test_an_operators_feed_hold_on_the_way_is_waited_for():
    cnc, run, rows, told = _followed()
    cnc.operator_hold_at_s = 3.1  # on the way from X's first point to its second
    cnc.operator_hold_s = 20.0
    follow_machine(run, cnc, PLAN.lines, told.append, WAY, timeout_s=60.0)
    assert [row.key() for row in rows] == POINTS
    assert cnc.operator_hold_at_s == np.inf and run.clock.now() > 20.0  # it was held


def test_a_followed_program_stopped_off_its_way_is_not_the_plans():
    def aside(route):  # line Y's stop 0.5 mm aside: a stale program of another calibration
        moved = route[9][0] + np.array([0.5, 0.0, 0.0])  # [8]: above it, [9]: the stop
        return [*route[:8], (moved + [0, 0, 250.0], False), (moved, True), *route[10:]]

    cnc, run, rows, told = _followed(aside)
    with pytest.raises(DeviceError) as caught:
        follow_machine(run, cnc, PLAN.lines, told.append, WAY, timeout_s=60.0)
    assert str(caught.value) == (
        "the program stopped with the machine at [300.5, 195.0, -250.0] mm, 0.5000 mm from"
        " the pre-position of line Y [300.0, 195.0, -250.0] mm (tolerance 0.005 mm):"
        " program and plan do not match"
    )
    assert [row.key() for row in rows] == POINTS[:4]


def test_the_machine_late_at_its_next_stop_is_said_as_such_after_timeouts_machine_s(
    reference_machine,
):
    """The operator never starts the program: after ``timeouts.machine_s`` (here 3 s) the
    run ends with one line saying the machine did not get there (no lost connection)."""
    cnc, run, rows, told = _followed()
    cnc.stop_program()
    drive = following_drive(cnc, told.append, reference_machine, 3.0)
    with pytest.raises(DeviceError) as caught:
        drive(run)
    assert not isinstance(caught.value, ConnectionError)
    assert str(caught.value).startswith("the machine did not stop at the pre-position of line X")
    assert str(caught.value).endswith(" mm within 3 s (timeouts.machine_s)")
    assert run.clock.now() == pytest.approx(3.0, abs=0.1)
