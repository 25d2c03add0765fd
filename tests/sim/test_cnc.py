from __future__ import annotations

import math

import numpy as np
import pytest

from sim.clock import SimClock
from sim.cnc import SimulatedCnc, run_to_end
from xmalign.errors import InputError, OutOfRangeError
from xmalign.roles import MachineMover


@pytest.fixture
def clock():
    return SimClock()


@pytest.fixture
def cnc(machine, clock):
    return SimulatedCnc(machine, clock, position_mm=[0.0, 0.0, 0.0], acceleration_mm_s2=500.0)


def test_is_a_machine_mover(cnc):
    assert isinstance(cnc, MachineMover)


def test_long_move_follows_a_trapezoidal_profile(cnc, clock):
    duration = cnc.start_move([1000.0, 0.0, 0.0], 3000.0)
    speed, accel = 50.0, 500.0
    assert duration == pytest.approx(1000.0 / speed + speed / accel)
    clock.sleep(0.05)
    assert cnc.position_mm()[0] == pytest.approx(0.5 * accel * 0.05**2)
    assert not cnc.is_standstill()
    clock.sleep(10.0)
    assert cnc.position_mm()[0] == pytest.approx(0.5 * speed**2 / accel + speed * (10.05 - 0.1))
    clock.sleep(duration)
    np.testing.assert_allclose(cnc.position_mm(), [1000.0, 0.0, 0.0])
    assert cnc.is_standstill()


def test_short_move_never_reaches_the_feed(cnc, clock):
    duration = cnc.start_move([0.0, 2.0, 0.0], 6000.0)
    assert duration == pytest.approx(2.0 * math.sqrt(2.0 / 500.0))
    clock.sleep(duration / 2)
    assert cnc.position_mm()[1] == pytest.approx(1.0)


def test_feed_is_limited_to_rapid_and_move_to_waits(machine, cnc, clock):
    cnc.move_to(np.array([2000.0, 0.0, 0.0]), 1e6)
    rapid = machine.feed_mm_min.rapid / 60.0
    assert clock.now() == pytest.approx(2000.0 / rapid + rapid / 500.0)
    assert cnc.is_standstill()


def test_moves_outside_travel_and_zero_feed_are_refused(cnc):
    with pytest.raises(OutOfRangeError):
        cnc.move_to(np.array([0.0, 0.0, 10.0]), 1000.0)
    with pytest.raises(InputError):
        cnc.move_to(np.array([10.0, 0.0, 0.0]), 0.0)


PROGRAM = {
    "iso": "%\nO1000 (T)\nG21 G90 G94 G17\n(A)\nG01 X10.000 F600.0\nG04 P1500\nM30\n%\n",
    "linuxcnc": "%\nG21 G90\n(MSG,hello)\nG1 X10 F600 ; A\nG4 P1.5\nM2\n%\n",
    "sinumerik": 'G71 G90\nMSG("hello")\nG1 X10 F600 ; A\nG4 F1.5\nM30\n',
    "heidenhain": (
        "0 BEGIN PGM T MM\n1 ; A\n2 L X+10.000 R0 F600\n3 CYCL DEF 9.0 DWELL TIME\n"
        "4 CYCL DEF 9.1 DWELL 1.5\n5 L Z+0.000 R0 FMAX M30\n6 END PGM T MM\n"
    ),
}


@pytest.mark.parametrize("dialect", sorted(PROGRAM))
def test_dwell_lasts_its_time_even_when_the_consumer_takes_part_of_it(dialect, cnc, clock):
    seen = []

    def capture(event):
        seen.append(event)
        if event.kind == "dwell":
            clock.sleep(1.0)

    run_to_end(cnc.run_program(PROGRAM[dialect], dialect), capture)
    dwell = next(e for e in seen if e.kind == "dwell")
    assert dwell.dwell_s == pytest.approx(1.5) and dwell.text == "A"
    np.testing.assert_allclose(dwell.position_mm, [10.0, 0.0, 0.0])
    move_s = 10.0 / 10.0 + 10.0 / 500.0
    assert clock.now() == pytest.approx(move_s + 1.5)
    assert seen[-1].kind == "end"


@pytest.mark.parametrize(
    ("dialect", "text", "reason"),
    [
        ("iso", "G21\nG01 X10.000 F100.0 Q5\nM30\n", r"line 2: unknown word Q"),
        ("iso", "G21\nG01 X10.000 F100.0\n", r"program end \(M30 or M2\) missing"),
        ("iso", "G21\nG01 X10.000\nM30\n", r"line 2: .*F missing"),
        ("linuxcnc", "G21\nG1 X10 F0\nM2\n", r"line 2: feed F0 must be greater than zero"),
        ("linuxcnc", "G20\nM2\n", r"line 1: G20: inch units"),
        ("linuxcnc", "G0 X5000\nM2\n", r"line 1: move to .* leaves the travel"),
        ("linuxcnc", "G2 X10 Y10 R5\nM2\n", r"line 1: unsupported G2"),
        ("linuxcnc", "X10\nM2\n", r"line 1: axis words without G0 or G1"),
        ("iso", "G04 P1.5\nM30\n", r"line 1: G04 P takes whole milliseconds"),
        ("sinumerik", "G1 X10 F100\nG4 F1 X3\nM30\n", r"line 2: a dwell must stand alone"),
        ("sinumerik", "G1 X10 F100\nM3\nM30\n", r"line 2: unsupported M3"),
        ("heidenhain", "0 L X+10 R0 F100\n1 END PGM A MM\n", r"line 1: .*BEGIN PGM"),
        ("heidenhain", "0 BEGIN PGM A INCH\n", r"line 1: inch programs"),
        (
            "heidenhain",
            "0 BEGIN PGM A MM\n1 L X+10 RL F100\n2 END PGM A MM\n",
            r"line 2: unknown word 'RL'",
        ),
        (
            "heidenhain",
            "0 BEGIN PGM A MM\n1 CYCL DEF 9.1 DWELL 2\n2 END PGM A MM\n",
            r"line 2: expected CYCL DEF 9.0",
        ),
        ("heidenhain", "0 BEGIN PGM A MM\n1 L X+10 R0 F100\n", r"END PGM\) missing"),
        (
            "heidenhain",
            "0 BEGIN PGM A MM\nL X+10 R0 F100\n2 END PGM A MM\n",
            r"line 2: a block must start with its block number",
        ),
        ("fanuc", "M30\n", r"unknown G-code dialect 'fanuc'"),
    ],
)
def test_what_a_real_control_refuses_is_refused_before_anything_moves(
    cnc, clock, dialect, text, reason
):
    with pytest.raises(InputError, match=reason):
        next(cnc.run_program(text, dialect))
    assert clock.now() == 0.0
    np.testing.assert_allclose(cnc.position_mm(), [0.0, 0.0, 0.0])


def test_programmed_stop_waits_for_the_consumer(cnc):
    events = cnc.run_program("G21\n(MSG,set units)\nM0\nG0 X10\nM2\n", "linuxcnc")
    assert next(events).kind == "message"
    stop = next(events)
    assert stop.kind == "stop" and stop.text == "set units"
    np.testing.assert_allclose(cnc.position_mm(), [0.0, 0.0, 0.0])
    assert next(events).kind == "end"
    np.testing.assert_allclose(cnc.position_mm(), [10.0, 0.0, 0.0])
