"""The contract every program control passes (``xmalign.roles.ProgramControl``).

A controller that runs xmalign's program lets xmalign start it (open and run
from the top), reports it running, paused at a programmed stop (M0) with the
machine at rest, holds the feed mid-move (the machine stops on its path and
stays), resumes, stops it (aborted, at rest, a new start begins at the top),
reports the program it has open, and refuses a program it cannot open with the
controller's own message. And what LinuxCNC 2.9 does that xmalign must cope with
(seen on a headless LinuxCNC, tests/linuxcnc): a feed hold in the braking
distance before a programmed stop stops the machine at that stop, and one
resume leaves the program paused there (a second goes on); an E-stop ends the
program and is named by the readiness check; a request interrupted before its
reply (Ctrl-C, SIGTERM) does not hand its reply to the next; after its task
dies, the controller keeps reporting its last status and a command is refused
naming the task. The machines brake at 100 mm/s^2 (2 mm from 20 mm/s).

The checks take a ``control_stand`` fixture (the E-stop and the dead task a
``dying_stand``, a controller they may leave broken), a :class:`ControlStand`:
test_program_control_contract.py serves the simulated LinuxCNC over linuxcncrsh
and through the simulated Python module; tests/linuxcnc/test_real_program_control_contract.py
a real headless LinuxCNC over linuxcncrsh (and test_real_linuxcnc_module.py through
LinuxCNC's own module).

The program is LinuxCNC's dialect (every ProgramControl today is a LinuxCNC);
its points lie in the travel of both the simulated machines and the headless
LinuxCNC (X 0..400, Y 0..300, Z -200..0 mm).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from firmware_iface.linuxcncrsh import LinuxcncrshLink
from xmalign.errors import DeviceError, DriveFaultError
from xmalign.roles import ProgramControl

#: To the first stop fast, then 190 mm at 20 mm/s (9.5 s) to the second.
PROGRAM = "G21 G90 G94\nG53 G1 X10 Y20 Z-30 F60000\nM0\nG53 G1 X200 F1200\nM0\nM2\n"
FIRST_STOP_MM = [10.0, 20.0, -30.0]
SECOND_STOP_MM = [200.0, 20.0, -30.0]
WAIT_S = 30.0
#: Stops 20 mm apart approached at 20 mm/s: a machine braking at 100 mm/s^2 needs 2 mm.
NEAR_STOPS_PROGRAM = (
    "G21 G90 G94\nG53 G1 X10 Y20 Z-30 F60000\nM0\nG53 G1 X30 F1200\nM0\nG53 G1 X60 F1200\nM0\nM2\n"
)
#: The contract's machines brake at this rate, mm/s^2 (the program's approach: 2 mm).
ACCELERATION_MM_S2 = 100.0


def _call_then_interrupt(call: Callable[[], object]) -> None:
    call()
    raise KeyboardInterrupt


@dataclass
class ControlStand:
    """One program control, served: the control and where its programs go."""

    control: ProgramControl
    #: A folder the controller reads programs from (as this process writes them).
    folder: Path
    #: E-stop pressed; the controller's task killed (None: not here). A stand either
    #: happened to is not used again (``dying_stand``).
    press_estop: Callable[[], None] | None = None
    kill_task: Callable[[], None] | None = None
    #: Runs a command with a Ctrl-C arriving after its request went out (before any reply).
    interrupted: Callable[[Callable[[], object]], None] = field(default=_call_then_interrupt)


def interrupt_the_reply(control: ProgramControl) -> Callable[[Callable[[], object]], None]:
    """Over linuxcncrsh: a KeyboardInterrupt where the reply is read (it stays unread)."""

    def interrupted(call: Callable[[], object]) -> None:
        link = getattr(control, "link", None)
        assert isinstance(link, LinuxcncrshLink)
        read_line = link._read_line

        def once() -> str:
            link._read_line = read_line  # type: ignore[method-assign]
            raise KeyboardInterrupt

        link._read_line = once  # type: ignore[method-assign]
        call()

    return interrupted


def _wait(condition: Callable[[], bool], timeout_s: float = WAIT_S) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def _program(stand: ControlStand, text: str = PROGRAM) -> str:
    path = stand.folder / "contract.ngc"
    path.write_text(text, encoding="utf-8")
    path.chmod(0o644)  # the controller may run as another user
    return str(path)


def _at_first_stop(stand: ControlStand, text: str = PROGRAM) -> str:
    control = stand.control
    program = _program(stand, text)
    control.start_program(program)
    assert control.program_state() in ("running", "paused")
    _wait(lambda: control.program_state() == "paused" and control.is_standstill())
    return program


def settles_at(control: ProgramControl, point_mm: list[float]) -> None:
    """The actual position reaches ``point_mm`` exactly (1e-6 mm). At rest means within the
    driver's ``in_position_mm`` of the command: a real LinuxCNC's drives may still report
    the last servo period's step of the deceleration (some 0.5 um) when it says so."""
    _wait(lambda: np.allclose(control.position_mm(), point_mm, atol=1e-6), 1.0)


def settled_mm(control: ProgramControl) -> np.ndarray:
    """The actual position once two reads 10 ms (ten servo periods) apart agree: at rest,
    the last servo period's step may still come (see :func:`settles_at`), mm, shape (3,)."""
    reads = [control.position_mm()]

    def same() -> bool:
        reads.append(control.position_mm())
        return bool(np.array_equal(reads[-2], reads[-1]))

    _wait(same, 1.0)
    return reads[-1]


def _on_the_way(stand: ControlStand) -> None:
    """From the first stop, resumed: on the way to the second."""
    control = stand.control
    control.resume()
    _wait(lambda: control.position_mm()[0] > 20.0)
    assert control.program_state() == "running" and not control.is_standstill()


def _stays_put(stand: ControlStand) -> np.ndarray:
    at = settled_mm(stand.control)
    time.sleep(0.2)
    assert np.allclose(stand.control.position_mm(), at, atol=1e-9)
    return at


def test_is_a_program_control(control_stand: ControlStand) -> None:
    assert isinstance(control_stand.control, ProgramControl)
    control_stand.control.check_ready()


def test_a_start_runs_the_program_to_its_stop_at_rest(control_stand: ControlStand) -> None:
    control = control_stand.control
    program = _at_first_stop(control_stand)
    settles_at(control, FIRST_STOP_MM)
    assert control.loaded_program() == program
    control.resume()  # the state lags the command: paused again once at the second stop
    _wait(lambda: control.position_mm()[0] > FIRST_STOP_MM[0] + 1.0)
    _wait(lambda: control.program_state() == "paused" and control.is_standstill())
    settles_at(control, SECOND_STOP_MM)
    control.stop_program()
    _wait(lambda: control.program_state() == "idle")


def test_a_feed_hold_stops_on_the_path_and_a_resume_goes_on(control_stand: ControlStand) -> None:
    control = control_stand.control
    _at_first_stop(control_stand)
    _on_the_way(control_stand)
    control.hold()
    _wait(lambda: control.program_state() == "paused" and control.is_standstill())
    held = _stays_put(control_stand)
    assert 20.0 < held[0] < SECOND_STOP_MM[0]
    assert np.allclose(held[1:], FIRST_STOP_MM[1:], atol=1e-6)
    control.resume()
    _wait(lambda: control.position_mm()[0] > held[0] + 1.0)
    assert control.program_state() == "running"
    control.stop_program()
    _wait(lambda: control.program_state() == "idle")


def test_a_stop_ends_the_program_mid_move_and_a_start_begins_at_the_top(
    control_stand: ControlStand,
) -> None:
    control = control_stand.control
    _at_first_stop(control_stand)
    _on_the_way(control_stand)
    control.stop_program()
    _wait(lambda: control.program_state() == "idle" and control.is_standstill(), 5.0)
    stopped = _stays_put(control_stand)
    assert stopped[0] < SECOND_STOP_MM[0]
    _at_first_stop(control_stand)  # from the top: back at the first stop
    settles_at(control, FIRST_STOP_MM)
    control.stop_program()


def test_a_program_it_cannot_open_is_refused_with_its_message(
    control_stand: ControlStand,
) -> None:
    control = control_stand.control
    missing = str(control_stand.folder / "nowhere" / "missing.ngc")
    with pytest.raises(DeviceError, match="Unable to open file") as caught:
        control.start_program(missing)
    assert missing in str(caught.value) and "\n" not in str(caught.value)
    assert control.program_state() == "idle"


def _paused_at_rest(control: ProgramControl) -> bool:
    return control.program_state() == "paused" and control.is_standstill()


def test_a_feed_hold_in_the_braking_distance_stops_at_the_stop_and_needs_two_resumes(
    control_stand: ControlStand,
) -> None:
    """LinuxCNC 2.9: a hold 1.5 mm before an M0 (inside the 2 mm the machine needs to
    stop) stops it at the M0; the first resume leaves the program paused there."""
    control = control_stand.control
    _at_first_stop(control_stand, NEAR_STOPS_PROGRAM)
    control.resume()
    _wait(lambda: control.position_mm()[0] >= 28.5)
    control.hold()
    _wait(lambda: _paused_at_rest(control))
    settles_at(control, [30.0, 20.0, -30.0])
    control.resume()
    time.sleep(1.0)
    assert _paused_at_rest(control)
    assert np.allclose(control.position_mm(), [30.0, 20.0, -30.0], atol=1e-6)
    control.resume()
    _wait(lambda: control.position_mm()[0] > 31.0)
    control.stop_program()
    _wait(lambda: control.program_state() == "idle")


def test_an_e_stop_ends_the_program_and_the_readiness_check_names_it(
    dying_stand: ControlStand,
) -> None:
    assert dying_stand.press_estop is not None
    control = dying_stand.control
    _at_first_stop(dying_stand)
    _on_the_way(dying_stand)
    dying_stand.press_estop()
    _wait(lambda: control.program_state() == "idle", 5.0)
    with pytest.raises(DriveFaultError, match="E-stop is pressed") as caught:
        control.check_ready()
    assert "\n" not in str(caught.value)


def test_a_request_interrupted_before_its_reply_does_not_answer_the_next(
    control_stand: ControlStand,
) -> None:
    """SIGTERM while a resume waits for its reply: the feed hold sent next is taken."""
    control = control_stand.control
    _at_first_stop(control_stand)
    with pytest.raises(KeyboardInterrupt):
        control_stand.interrupted(control.resume)
    _wait(lambda: control.position_mm()[0] > 20.0)
    control.hold()
    _wait(lambda: _paused_at_rest(control))
    held = _stays_put(control_stand)
    assert held[0] < SECOND_STOP_MM[0]
    control.stop_program()
    _wait(lambda: control.program_state() == "idle")


def test_a_dead_task_keeps_its_last_status_and_a_command_names_it(
    dying_stand: ControlStand,
) -> None:
    """LinuxCNC 2.9 after milltask dies: RUNNING and the position as they were, and no
    command taken; the driver names the task rather than waiting for ever."""
    assert dying_stand.kill_task is not None
    control = dying_stand.control
    _at_first_stop(dying_stand)
    _on_the_way(dying_stand)
    dying_stand.kill_task()
    time.sleep(0.5)
    at = control.position_mm()
    time.sleep(0.5)
    assert control.program_state() == "running"
    assert np.array_equal(control.position_mm(), at)
    with pytest.raises(DeviceError, match=r"task \(milltask\) has stopped; restart LinuxCNC"):
        control.hold()
