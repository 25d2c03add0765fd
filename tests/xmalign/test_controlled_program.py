"""Every path of :func:`xmalign.calibration.control_program`, on a scripted controller.

No LinuxCNC and no real time: :mod:`scripted_cnc` runs xmalign's program on a
virtual clock, and each test scripts one thing that happens on the way (a fault,
a lost connection, Ctrl-C or SIGTERM, another program open, a program that ends
early, the beam lost, an operator's feed hold, a cycle start pressed at the
machine during a capture).
"""

from __future__ import annotations

import signal

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

from xmalign.calibration import ControlledProgram, capture_sequence, control_program
from xmalign.errors import DeviceError, DriveFaultError, TransportError
from xmalign.roles import InterferometerReading
from xmalign.safety import StopSignal

PLAN = two_line_plan()
POINTS = [point.key for line in PLAN.lines for point in capture_sequence(line)]
STOPS = len(PLAN.lines) + len(POINTS)  # each line's pre-position, then its points


class Shop:
    """The scripted controller, interferometer and run, and what the run told."""

    def __init__(self, lost: list[tuple[float, float]] | None = None) -> None:
        self.clock = VirtualClock()
        self.cnc = ScriptedCnc(self.clock, program_route(PLAN, np.array([0.0, 0.0, -100.0])))
        self.interferometer = ScriptedInterferometer(self.clock, lost or [])
        self.run, self.rows = scripted_run(PLAN, self.interferometer)
        self.told: list[str] = []

    def control(self, **settings: float | None) -> None:
        program = ControlledProgram(self.cnc, PROGRAM, WAY, **{"timeout_s": 60.0, **settings})
        control_program(self.run, program, self.told.append)

    def keys(self) -> list[tuple]:
        return [row.key() for row in self.rows]


def _at_stop(number: int, error: BaseException):
    """``on_read``: raise ``error`` once the program has reached stop ``number``."""

    def read(cnc: ScriptedCnc) -> None:
        if cnc.stops_reached > number:
            raise error

    return read


def test_the_whole_program_is_run_and_every_point_captured_at_its_stop():
    shop = Shop()
    shop.control()
    assert shop.keys() == POINTS
    assert shop.cnc.commands == ["start"] + ["resume"] * STOPS
    assert shop.cnc.state == "idle" and shop.run.statistics.program_s is not None
    assert not shop.told


def test_a_fault_aborts_the_program_and_says_so():
    shop = Shop()
    shop.cnc.on_read = _at_stop(3, DriveFaultError("joint 1 following error"))
    with pytest.raises(DriveFaultError) as caught:
        shop.control()
    assert str(caught.value) == (
        "joint 1 following error; the program was stopped on the controller"
    )
    assert shop.cnc.commands[-1] == "stop"
    assert 0 < len(shop.keys()) < len(POINTS) and shop.keys() == POINTS[: len(shop.keys())]


def test_a_lost_connection_holds_the_feed_and_the_run_resumes_from_the_top():
    shop = Shop()
    shop.cnc.on_read = _at_stop(
        3, TransportError("LinuxCNC at 127.0.0.1:5007 closed the connection")
    )
    with pytest.raises(TransportError, match="closed the connection; the feed is held on the"):
        shop.control()
    assert shop.cnc.commands[-1] == "hold" and shop.cnc.state == "paused"
    kept = shop.keys()
    shop.cnc.on_read = lambda cnc: None  # the connection is back: --resume
    shop.run, shop.rows = scripted_run(PLAN, shop.interferometer)
    shop.run.done = set(kept)
    shop.control()
    assert kept + shop.keys() == POINTS
    assert shop.cnc.commands[-STOPS - 2 : -STOPS] == ["stop", "start"]
    assert shop.told == [
        "the program was paused from an earlier run: aborted, started again from the top"
    ]


@pytest.mark.parametrize(
    "interrupt",
    [KeyboardInterrupt(), StopSignal(signal.SIGTERM), StopSignal(signal.SIGHUP)],
    ids=["ctrl-c", "sigterm", "sighup"],
)
def test_ctrl_c_or_a_stop_signal_holds_the_feed_and_keeps_its_kind(interrupt):
    shop = Shop()
    shop.cnc.on_read = _at_stop(4, interrupt)
    with pytest.raises(KeyboardInterrupt) as caught:
        shop.control()
    assert type(caught.value) is type(interrupt)
    assert getattr(caught.value, "signum", None) == getattr(interrupt, "signum", None)
    assert str(caught.value) == "the feed is held on the controller"
    assert shop.cnc.commands[-1] == "hold"


def test_ctrl_c_while_the_program_is_started_holds_it():
    shop = Shop()
    start = shop.cnc.start_program

    def interrupted_start(path: str) -> None:
        start(path)
        raise KeyboardInterrupt

    shop.cnc.start_program = interrupted_start  # type: ignore[method-assign]
    with pytest.raises(KeyboardInterrupt, match="the feed is held on the controller"):
        shop.control()
    assert shop.cnc.commands == ["start", "hold"]


def test_another_program_open_is_refused_and_never_touched():
    shop = Shop()
    shop.cnc.state, shop.cnc.loaded = "paused", "/home/cnc/old.ngc"
    with pytest.raises(DeviceError) as caught:
        shop.control()
    assert str(caught.value) == (
        "the controller is paused with another program (/home/cnc/old.ngc); stop it first"
    )
    assert shop.cnc.commands == [] and shop.cnc.state == "paused"


def test_a_program_that_ends_early_stops_the_run_with_one_line():
    shop = Shop()
    shop.cnc.route = program_route(PLAN, np.array([0.0, 0.0, -100.0]))[:8]  # line X only
    with pytest.raises(DeviceError) as caught:
        shop.control()
    assert str(caught.value) == (
        "the program ended before the pre-position of line Y [300.0, 195.0, -250.0] mm: program"
        " and plan do not"
        " match; the program was stopped on the controller"
    )
    assert shop.keys() == POINTS[:4]


def test_a_beam_lost_on_the_way_holds_the_feed_then_resumes_past_a_stale_paused():
    """The beam crosses between X's first two points; after the resume the controller still
    says "paused" for 0.1 s (a stale status): the run does not take it for a stop."""
    shop = Shop()
    arrivals: list[float] = []
    shop.cnc.on_stop = lambda number, arrived_s: arrivals.append(arrived_s)
    shop.cnc.stale_s = 0.1
    # line X's first point is stop 1; the machine leaves it once it is captured
    shop.cnc.on_read = lambda cnc: _lose_beam_after(shop, arrivals, 2)
    shop.control()
    assert shop.keys() == POINTS
    (lost,) = [text for text in shop.told if "beam lost" in text]
    assert lost.startswith("beam lost on the way to line X run 1 target 2")
    assert lost.endswith("beam back; resumed")
    assert shop.cnc.commands.count("hold") == 1
    assert [row.segment for row in shop.rows] == [
        0,
        1,
        1,
        1,
        0,
        0,
        0,
        0,
    ]  # found again: X's segment 1
    assert not [text for text in shop.told if "feed hold on the controller" in text]


def _lose_beam_after(shop: Shop, arrivals: list[float], stops: int) -> None:
    """Once ``stops`` stops are reached and the machine is on its way, cross the beam 0.5 s."""
    if len(arrivals) == stops and shop.cnc.state == "running" and not shop.interferometer.lost:
        now = shop.clock.now()
        shop.interferometer.lost.append((now, now + 0.5))


def _operator_holds(
    shop: Shop, after_stop: int, hold_s: float = 30.0, after_s: float = 1.1
) -> None:
    """The operator holds the feed ``after_s`` after the machine reaches stop ``after_stop``:
    by default on its way to the next one (the capture takes 0.85 s, each leg 0.5 s)."""

    def hold(number: int, arrived_s: float) -> None:
        if number == after_stop:
            shop.cnc.operator_hold_at_s = arrived_s + after_s
            shop.cnc.operator_hold_s = hold_s

    shop.cnc.on_stop = hold


def test_an_operators_feed_hold_on_the_way_is_told_once_and_waited_for():
    shop = Shop()
    _operator_holds(shop, 2)
    shop.control()
    assert shop.keys() == POINTS
    (held,) = [text for text in shop.told if "held" in text]
    assert held.startswith("the program is held at [")
    assert held.endswith(
        "mm on its way to line X run 1 target 3 [200.0, 100.0, -300.0] mm (a feed hold on the"
        " controller): waiting for it to go on"
    )
    assert "hold" not in shop.cnc.commands


@pytest.mark.parametrize(
    ("after_s", "where"),
    [
        (1.1, "[100.0, 100.0, -150.0]"),
        (1.6, "[200.0, 147.5, 0.0]"),
        (2.1, "[300.0, 195.0, -125.0]"),
    ],
    ids=["up", "across", "down"],
)
def test_an_operators_feed_hold_between_lines_is_waited_for(after_s, where):
    """After X's drift check the way to Y's pre-position goes up, across and down."""
    shop = Shop()
    _operator_holds(shop, 4, after_s=after_s)
    shop.control()
    assert shop.keys() == POINTS
    (held,) = [text for text in shop.told if "held" in text]
    assert f"held at {where} mm on its way to the pre-position of line Y" in held


def test_a_feed_hold_longer_than_the_timeout_ends_the_run_with_one_line():
    shop = Shop()
    _operator_holds(shop, 2, hold_s=120.0)
    with pytest.raises(DeviceError) as caught:
        shop.control()
    assert str(caught.value) == (
        "the machine did not stop at line X run 1 target 3 [200.0, 100.0, -300.0] mm within"
        " 60 s (timeouts.machine_s); the program was stopped on the controller"
    )


def test_a_program_stopped_off_its_way_is_not_the_plans():
    shop = Shop()
    route = program_route(PLAN, np.array([0.0, 0.0, -100.0]))
    moved = route[2][0] + np.array([0.0, 0.5, 0.0])  # X's pre-position, 0.5 mm aside
    shop.cnc.route = [route[0], (moved, False), (moved, True), *route[3:]]
    with pytest.raises(DeviceError) as caught:
        shop.control()
    line = str(caught.value)
    assert line.startswith("the program stopped with the machine at [95.0, 100.5, -300.0] mm")
    assert "0.5000 mm from the pre-position of line X [95.0, 100.0, -300.0] mm (tol" in line
    assert line.endswith("program and plan do not match; the program was stopped on the controller")
    assert not shop.rows


def test_a_cycle_start_during_a_capture_records_nothing_of_the_moving_machine():
    """Someone presses cycle start 0.3 s into the capture at X's second point (1 s dwell):
    the point is not recorded (``--resume`` captures it), the run goes on."""
    shop = Shop()

    def press_cycle_start(number: int, arrived_s: float) -> None:
        if number == 2:
            shop.cnc.cycle_start_at_s = arrived_s + 0.3

    shop.cnc.on_stop = press_cycle_start
    shop.control()
    assert shop.keys() == POINTS[:1] + POINTS[2:]
    assert shop.run.statistics.missed == [POINTS[1]]
    (went_on,) = [text for text in shop.told if "went on" in text]
    assert went_on.startswith("line X run 1 target 2")
    assert shop.cnc.commands.count("resume") == STOPS - 1  # the cycle start resumed that one


@pytest.mark.parametrize(
    ("interrupt", "code", "said"),
    [
        (KeyboardInterrupt(), 130, ""),
        (StopSignal(signal.SIGTERM), 143, "SIGTERM: "),
        (StopSignal(signal.SIGHUP), 129, "SIGHUP: "),
    ],
    ids=["ctrl-c", "sigterm", "sighup"],
)
def test_the_command_ends_with_one_line_keeping_the_note_and_the_signals_exit_code(
    interrupt, code, said, tmp_path, capsys
):
    """What ``xmalign run`` makes of it (xmalign.cli.run, then the console entry point)."""
    from xmalign.cli import _stopped as end_the_command
    from xmalign.cli.run import _stopped

    shop = Shop()
    shop.cnc.on_read = _at_stop(4, interrupt)
    with pytest.raises(KeyboardInterrupt) as caught:
        shop.control()
    out = tmp_path / "m.csv"
    with pytest.raises(SystemExit) as ended:
        end_the_command(_stopped(caught.value, out))
    assert ended.value.code == code
    assert capsys.readouterr().err.splitlines() == [
        f"xmalign: {said}stopped: 0 points kept in {out}; go on with --resume; the feed is held"
        " on the controller"
    ]


def test_a_program_left_paused_at_its_stop_after_a_resume_is_resumed_again():
    """LinuxCNC 2.9 after a feed hold in the last mm before an M0: one resume leaves the
    program paused at the stop. The run sees it and resumes again, within seconds."""
    shop = Shop()
    shop.cnc.on_stop = lambda number, arrived_s: (
        setattr(shop.cnc, "swallowed_resumes", 1) if number == 2 else None
    )
    shop.control()
    assert shop.keys() == POINTS
    assert shop.told == [
        "the program stayed paused at line X run 1 target 2 [150.0, 100.0, -300.0] mm after a"
        " resume: resumed again"
    ]
    assert shop.cnc.commands.count("resume") == STOPS + 1
    assert shop.run.statistics.program_s < 30.0  # not a wait of timeouts.machine_s


def test_a_program_that_never_goes_on_after_resumes_ends_the_run_with_one_line():
    shop = Shop()
    shop.cnc.on_stop = lambda number, arrived_s: (
        setattr(shop.cnc, "swallowed_resumes", 99) if number == 1 else None
    )
    with pytest.raises(DeviceError) as caught:
        shop.control()
    assert str(caught.value).startswith(
        "the program stays paused at line X run 1 target 1 [100.0, 100.0, -300.0] mm after 3"
        " resumes: the controller does not take them (check its messages); go on with --resume"
    )
    assert shop.clock.now() < 30.0


def test_a_beam_hold_that_reaches_the_stop_captures_the_point_before_any_resume():
    """The beam is lost in the last moment before X's second stop and the hold arrives
    when the program already stands there: a resume then would pass the stop uncaptured."""
    shop = Shop()
    arrivals: list[float] = []
    shop.cnc.on_stop = lambda number, arrived_s: arrivals.append(arrived_s)
    shop.cnc.hold_lag_s = 0.2

    def lose_just_before_the_stop(cnc: ScriptedCnc) -> None:
        ends_s = cnc._leg_start_s + 0.5
        now = shop.clock.now()
        late = cnc.state == "running" and 0.0 < ends_s - now < 0.1
        if len(arrivals) == 2 and late and not shop.interferometer.lost:
            shop.interferometer.lost.append((now, now + 0.5))

    shop.cnc.on_read = lose_just_before_the_stop
    shop.control()
    assert shop.keys() == POINTS
    (lost,) = [text for text in shop.told if "beam lost" in text]
    assert lost.startswith("beam lost on the way to line X run 1 target 2")
    assert lost.endswith("beam back; held at the point: captured there")
    assert shop.cnc.commands.count("resume") == STOPS


def test_a_dead_task_is_noticed_within_seconds_and_named():
    """After LinuxCNC's milltask dies, linuxcncrsh keeps saying RUNNING at one position
    and takes no command."""
    shop = Shop()
    shop.cnc.on_stop = lambda number, arrived_s: (
        setattr(shop.cnc, "dead_at_s", arrived_s + 1.1) if number == 2 else None
    )
    with pytest.raises(DeviceError) as caught:
        shop.control()
    line = str(caught.value)
    assert line.startswith(
        "the controller has shown the program running for 5 s on the way to line X run 1"
        " target 3 [200.0, 100.0, -300.0] mm with the machine standing (within 0.01 mm) at ["
    )
    assert "its task has stopped (LinuxCNC: milltask died; restart LinuxCNC)" in line
    assert line.endswith(
        "go on with --resume once it runs; the controller could not be reached to stop the"
        " program (scripted CNC did not answer 'set abort' within 5 s)"
    )
    assert shop.clock.now() < 20.0
    assert shop.keys() == POINTS[:2]


def test_a_dead_task_is_named_though_its_position_jitters():
    """Encoder counts and servo noise: the actual position never reads the same twice (up
    to 2 um on each axis, 3.5 um in all, inside the 5 um tolerance), yet the machine stands."""
    shop = Shop()
    shop.cnc.jitter_mm = 0.002
    shop.cnc.on_stop = lambda number, arrived_s: (
        setattr(shop.cnc, "dead_at_s", arrived_s + 1.1) if number == 2 else None
    )
    with pytest.raises(DeviceError, match=r"running for 5 s on the way to line X run 1 target 3"):
        shop.control()
    assert shop.clock.now() < 20.0
    assert shop.keys() == POINTS[:2]


def _creep_to_target_3(shop: Shop, speed_mm_s: float) -> None:
    """From target 2 of line X to target 3 (50 mm) at ``speed_mm_s``; the rest at full speed."""
    speeds = {2: speed_mm_s, 3: None}
    shop.cnc.on_stop = lambda number, arrived_s: (
        setattr(shop.cnc, "speed_mm_s", speeds[number]) if number in speeds else None
    )


def test_a_slow_approach_at_the_programs_feed_is_not_taken_for_a_dead_task():
    """10 um/s (0.6 mm/min), the program's slowest feed, with a 0.1 mm band: 0.05 mm in 5 s,
    inside the band; the machine must stand 100 s (ten crossings of the band) to count as
    stopped. Unknown feeds, the same creep is taken for a dead task after 5 s."""
    settings = {"tolerance_mm": 0.05, "timeout_s": 6000.0, "poll_s": 0.5}
    shop = Shop()
    shop.cnc.jitter_mm = 0.002
    _creep_to_target_3(shop, 0.01)
    shop.control(**settings, slowest_feed_mm_min=0.6)
    assert shop.keys() == POINTS
    assert shop.clock.now() > 5000.0  # 50 mm at 10 um/s
    assert not [text for text in shop.told if "task" in text]
    unknown = Shop()
    _creep_to_target_3(unknown, 0.01)
    with pytest.raises(DeviceError, match=r"running for 5 s on the way to line X run 1 target 3"):
        unknown.control(**settings)


def test_the_time_a_machine_must_stand_follows_the_slowest_feed():
    """5 s for any plausible feed; ten crossings of the band for a slower one."""
    program = ControlledProgram(ScriptedCnc(VirtualClock(), []), PROGRAM, WAY)
    assert program.standing_band_mm == pytest.approx(0.01)
    assert program.standing_s == 5.0
    program.slowest_feed_mm_min = 1.2  # 0.01 mm in 0.5 s
    assert program.standing_s == 5.0
    program.slowest_feed_mm_min = 0.06  # 0.01 mm in 10 s
    assert program.standing_s == pytest.approx(100.0)


@pytest.mark.parametrize("on_the_way", [True, False], ids=["moving", "at-a-stop"])
def test_an_e_stop_is_named_with_the_way_on_and_no_abort_is_sent(on_the_way):
    shop = Shop()
    shop.cnc.on_stop = lambda number, arrived_s: (
        setattr(shop.cnc, "estop_at_s", arrived_s + (1.1 if on_the_way else 0.3))
        if number == 2
        else None
    )
    with pytest.raises(DriveFaultError) as caught:
        shop.control()
    assert str(caught.value).startswith("scripted CNC: E-stop is pressed; release it; the")
    assert str(caught.value).endswith("go on with --resume when the machine is back")
    assert "line X run 1 target" in str(caught.value)
    assert "stop" not in shop.cnc.commands and "hold" not in shop.cnc.commands
    assert not [text for text in shop.told if "cycle start" in text]


def test_a_lost_connection_says_how_to_go_on():
    shop = Shop()
    shop.cnc.on_read = _at_stop(3, TransportError("LinuxCNC at 127.0.0.1:5007 closed it"))
    with pytest.raises(TransportError) as caught:
        shop.control()
    assert str(caught.value).endswith("go on with --resume once it answers again")


def test_recorded_lines_pass_without_feed_holds_or_beam_messages():
    """--resume with line X recorded: its units are aimed elsewhere, no beam along X."""
    shop = Shop()
    shop.run.done = {key for key in POINTS if key[0] == "X"}
    read = shop.interferometer.read

    def no_beam_on_x() -> InterferometerReading:
        reading = read()
        on_x = shop.cnc.position_mm()[1] < 150.0
        return InterferometerReading(reading.time_s, reading.channels, not on_x)

    shop.interferometer.read = no_beam_on_x  # type: ignore[method-assign]
    shop.control()
    assert shop.keys() == [key for key in POINTS if key[0] == "Y"]
    assert shop.cnc.commands == ["start"] + ["resume"] * STOPS
    assert not shop.told


def test_a_long_wait_says_what_it_waits_for():
    shop = Shop()
    _operator_holds(shop, 2, hold_s=25.0)
    shop.control()
    waiting = [text for text in shop.told if text.startswith("still waiting")]
    assert waiting == [
        "still waiting for the machine to stop at line X run 1 target 3 [200.0, 100.0, -300.0]"
        " mm (10 s so far; at most 60 s, timeouts.machine_s)"
    ]
