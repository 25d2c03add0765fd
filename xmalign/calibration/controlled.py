"""The controlled drive: xmalign starts, holds and resumes its program on the controller."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial

import numpy as np

from xmalign.calibration.capture import BEAM_WAIT_S, CalibrationRun, CapturePoint, capture_sequence
from xmalign.calibration.waiting import point_where, stands_at, wait_for
from xmalign.calibration.way import ProgramWay, check_stop_on_way
from xmalign.errors import DeviceError, DriveFaultError, TransportError, XmalignError
from xmalign.formats.plan import PlanLine
from xmalign.geometry import Vec
from xmalign.roles import ProgramControl, ProgramState
from xmalign.safety import like

#: After a resume, a program still paused at rest where it stood this long after is resumed
#: again (LinuxCNC 2.9 takes a feed hold that reached a stop for the stop's pause), s.
RESUME_AGAIN_S = 1.0
#: Resumes sent at one stop before the run stops with one line.
RESUMES = 3
#: A program shown running while the machine stands this long: the controller's task has
#: stopped (or its feed override is at 0 %), s. Longer when the program's slowest feed
#: would take less than ``CREEP_MARGIN`` times this to cross the standing band.
STILL_RUNNING_S = 5.0
#: The machine "stands" while its actual position stays within this many times the capture
#: tolerance of where it stood: a machine at rest that is captured at a point jitters by
#: encoder counts and servo noise within the tolerance of it, so by twice it end to end.
STANDING_BAND = 2.0
#: The program's slowest feed crosses the standing band at least this many times within the
#: time a machine must stand: a slow approach is never taken for a standing machine.
CREEP_MARGIN = 10.0


class MachineStoppedError(DriveFaultError):
    """The machine went into E-stop or off during the run: its controller ended the program."""


@dataclass
class ControlledProgram:
    """xmalign's program on a controller xmalign starts, holds and resumes.

    ``way``: where the program moves the machine (its overrun and safe height).
    ``tolerance_mm``: a point is captured only with the machine at rest within
    this distance of the plan's point. ``timeout_s``: the longest the machine
    may take to its next stop.
    """

    controller: ProgramControl
    path: str
    way: ProgramWay
    tolerance_mm: float = 0.005
    timeout_s: float = 600.0
    poll_s: float = 0.05
    #: The slowest feed the program moves at, mm/min (None: not known, ``STILL_RUNNING_S``).
    slowest_feed_mm_min: float | None = None
    #: Where the machine stood while the program ran, and since when (s): a program shown
    #: running whose machine stays within ``standing_band_mm`` of it for ``standing_s``
    #: has stopped.
    _running_at: tuple[Vec, float] | None = field(default=None, init=False, repr=False)

    @property
    def standing_band_mm(self) -> float:
        """How far the machine may jitter and still stand: ``STANDING_BAND`` tolerances, mm."""
        return STANDING_BAND * self.tolerance_mm

    @property
    def standing_s(self) -> float:
        """How long a machine shown running must stand to be taken for stopped, s.

        ``STILL_RUNNING_S``, or longer when the slowest feed would cross
        ``standing_band_mm`` less than ``CREEP_MARGIN`` times in it.
        """
        if self.slowest_feed_mm_min is None:
            return STILL_RUNNING_S
        crossing_s = self.standing_band_mm / (self.slowest_feed_mm_min / 60.0)
        return max(STILL_RUNNING_S, CREEP_MARGIN * crossing_s)


def control_program(
    run: CalibrationRun, program: ControlledProgram, tell: Callable[[str], None]
) -> None:
    """Run the program on the controller and capture every point, no one at the machine.

    The program is the one ``xmalign program`` writes for ``run.plan`` with a
    programmed stop at each point instead of the dwell. xmalign starts it (a
    program of an earlier run still open is aborted first; another program is
    refused and never touched), sets the units at each line's first stop, and
    resumes it at every stop once the point is captured (at once for points
    already recorded, whose lines pass without the beam watched). A point is
    captured only when the program stands at a
    stop and the machine at rest within ``tolerance_mm`` of the plan's point,
    and recorded only if it still does after the average (someone pressed cycle
    start: the point is missed, ``--resume`` captures it). The program held on
    its way (a feed hold on the controller) is told once and waited for; a stop
    anywhere else, or a program that ends early, stops the run with one line
    (program and plan do not match). While the machine moves between points the
    beam is watched: lost, the feed is held until it comes back (at most
    ``BEAM_WAIT_S``), and the next point is captured as after a beam lost there.
    A program still paused where it stood after a resume is resumed again
    (:func:`_resume`); one shown running while its machine stands (within
    ``standing_band_mm``) for ``standing_s`` stops the run (the controller's task has
    stopped).

    Every fault ends in one line naming it and the way on (``--resume``): a
    machine gone into E-stop or off (its controller has ended the program), a
    fault (the program is aborted), a lost connection or Ctrl-C (SIGTERM,
    SIGHUP): the feed is held where the controller still answers.
    """
    controller = program.controller
    controller.check_ready()
    earlier = _earlier_run(controller, program.path)
    started = run.clock.now()
    try:
        from_mm = controller.position_mm()
        _start_fresh(controller, program.path, earlier, tell)
        for line in run.plan.lines:
            _control_line(run, program, line, from_mm, tell)
            from_mm = line.target_points_mm()[0]  # the drift check
        wait_for(run, _program_ended(run, program), "end the program", program.timeout_s, 0.1, tell)
    except MachineStoppedError:
        raise  # the controller ended the program: nothing to hold or abort
    except TransportError as error:
        note = _try(controller.hold, "the feed is held on the controller")
        raise _noted(error, f"{note}; go on with --resume once it answers again") from error
    except KeyboardInterrupt as error:
        note = _try(controller.hold, "the feed is held on the controller")
        raise _noted(error, note) from error
    except XmalignError as error:
        note = _try(controller.stop_program, "the program was stopped on the controller")
        raise _noted(error, note) from error
    run.statistics.program_s = run.clock.now() - started


def _earlier_run(controller: ProgramControl, path: str) -> ProgramState:
    """The state of xmalign's program left open by an earlier run ("idle": none); another
    program open is refused (DeviceError), before anything is sent to the controller."""
    state = controller.program_state()
    if state != "idle":
        loaded = controller.loaded_program()
        if loaded != path:
            raise DeviceError(
                f"the controller is {state} with another program ({loaded}); stop it first"
            )
    return state


def _start_fresh(
    controller: ProgramControl, path: str, earlier: ProgramState, tell: Callable[[str], None]
) -> None:
    """Start the program; xmalign's program of an earlier run still open is aborted first."""
    if earlier != "idle":
        controller.stop_program()
        tell(f"the program was {earlier} from an earlier run: aborted, started again from the top")
    controller.start_program(path)


def _control_line(
    run: CalibrationRun,
    program: ControlledProgram,
    line: PlanLine,
    from_mm: Vec,
    tell: Callable[[str], None],
) -> None:
    """Units set at the line's first stop; capture at each point's stop; resume each time.

    A line already recorded (``--resume``) passes at once: its units are not set
    for it, so its beam is not watched."""
    pre_mm = program.way.pre_position_mm(line)
    to_line = program.way.to_line(from_mm, (), line)
    where = f"the pre-position of line {line.id} {np.round(pre_mm, 3).tolist()} mm"
    # on the way to a line the units are not yet set for it: the beam is not watched
    _wait_program(run, program, pre_mm, where, to_line, tell)
    stopped = run.clock.now()
    measured = not run.line_is_done(line)
    if measured:
        run.prepare_line(line)
    _resume(run, program, pre_mm, where, tell)
    run.statistics.stopped_s += run.clock.now() - stopped
    on_line = program.way.on_line(line)
    for point in capture_sequence(line):
        what = point_where(point)
        _wait_program(run, program, point.point_mm, what, on_line, tell, watch_beam=measured)
        held = partial(_held_at, run, program)
        row = run.capture(point, line.dwell_s, held, check_after=True)
        if row is None and point.key in run.statistics.missed and not held(point):
            tell(
                f"{what}: the program went on during the capture (cycle start on"
                " the controller?): the point is not recorded; --resume captures it"
            )
            continue  # the program is no longer at this stop: nothing to resume
        _resume(run, program, point.point_mm, what, tell)


def _state(
    run: CalibrationRun, program: ControlledProgram, what: str, ending: bool = False
) -> ProgramState:
    """The program's state; ``idle`` with the machine in E-stop or off raises
    MachineStoppedError (unless the program is ``ending``), ``running`` with the
    machine standing (within ``standing_band_mm`` of where it stood) for
    ``standing_s`` a DeviceError (the controller's task has stopped)."""
    controller = program.controller
    state = controller.program_state()
    if state == "idle" and not ending:
        _check_machine(controller, what)
    if state != "running":
        program._running_at = None
        return state
    position, now_s = controller.position_mm(), run.clock.now()
    seen = program._running_at
    band_mm = program.standing_band_mm
    if seen is None or float(np.linalg.norm(position - seen[0])) > band_mm:
        program._running_at = (position, now_s)
    elif now_s - seen[1] >= program.standing_s:
        raise DeviceError(
            f"the controller has shown the program running for {now_s - seen[1]:.0f} s on"
            f" the way to {what} with the machine standing (within {band_mm:g} mm) at"
            f" {np.round(seen[0], 3).tolist()} mm: its task has stopped (LinuxCNC: milltask"
            " died; restart LinuxCNC) or its feed override is at 0 %; go on with --resume"
            " once it runs"
        )
    return state


def _check_machine(controller: ProgramControl, what: str) -> None:
    """MachineStoppedError when the controller is not ready (E-stop, off): it has ended the
    program on the way to ``what``."""
    try:
        controller.check_ready()
    except DriveFaultError as error:
        raise MachineStoppedError(
            f"{error}; the program ended on the way to {what}; go on with --resume when the"
            " machine is back"
        ) from error


def _held_at(run: CalibrationRun, program: ControlledProgram, point: CapturePoint) -> bool:
    """The program still stands at the point's stop, the machine at rest there."""
    if _state(run, program, point_where(point)) != "paused":
        return False
    return stands_at(program.controller, point, program.tolerance_mm)


def _resume(
    run: CalibrationRun,
    program: ControlledProgram,
    stop_mm: Vec,
    what: str,
    tell: Callable[[str], None],
) -> None:
    """Resume, and wait until the controller shows it (running, or gone from the stop): a
    stale 'paused' must not count as the next stop.

    Still paused at rest at ``stop_mm`` ``RESUME_AGAIN_S`` after the resume, the
    program is resumed again (told): LinuxCNC 2.9 leaves a program paused at a
    stop after one resume when a feed hold came in its last mm. After ``RESUMES``
    resumes, DeviceError.
    """
    for _ in range(RESUMES):
        if _resumed(run, program, stop_mm, what, tell):
            return
        tell(f"the program stayed paused at {what} after a resume: resumed again")
    raise DeviceError(
        f"the program stays paused at {what} after {RESUMES} resumes: the controller does"
        " not take them (check its messages); go on with --resume"
    )


def _resumed(
    run: CalibrationRun,
    program: ControlledProgram,
    stop_mm: Vec,
    what: str,
    tell: Callable[[str], None],
) -> bool:
    """Resume once; True once the program goes on, False when it is still paused at rest
    at ``stop_mm`` ``RESUME_AGAIN_S`` after."""
    controller = program.controller
    controller.resume()
    resumed_s = run.clock.now()
    stuck = False

    def going() -> bool:
        nonlocal stuck
        moved = float(np.linalg.norm(controller.position_mm() - stop_mm))
        if _state(run, program, what) != "paused" or moved > program.tolerance_mm:
            return True
        stuck = run.clock.now() - resumed_s >= RESUME_AGAIN_S and controller.is_standstill()
        return stuck

    wait_for(run, going, f"go on after {what}", program.timeout_s, 0.01, tell)
    return not stuck


def _wait_program(
    run: CalibrationRun,
    program: ControlledProgram,
    target_mm: Vec,
    what: str,
    way: Callable[[Vec], float],
    tell: Callable[[str], None],
    watch_beam: bool = False,
) -> None:
    """Until the program stands at a stop with the machine at rest at ``target_mm``.

    DeviceError when the program ends first, or stands at a stop with the
    machine at rest off its ``way`` (distance from it, mm): program and plan do
    not match (MachineStoppedError when it ended with the machine in E-stop or
    off). Held on the way (a feed hold on the controller), it is told once
    and waited for. With ``watch_beam``, while the program runs, a lost beam
    holds the feed (:func:`_hold_for_beam`).
    """
    controller = program.controller
    told = False

    def there() -> bool:
        nonlocal told
        state = _state(run, program, what)
        if state == "idle":
            raise DeviceError(f"the program ended before {what}: program and plan do not match")
        if state == "running":
            told = False
            if watch_beam and not run.interferometer.read().beam_ok:
                _hold_for_beam(run, program, target_mm, what, tell)
            return False
        if not controller.is_standstill():
            return False
        position = controller.position_mm()
        if float(np.linalg.norm(position - target_mm)) <= program.tolerance_mm:
            return True
        check_stop_on_way(position, target_mm, way, program.tolerance_mm, what)
        if not told:
            told = True
            tell(
                f"the program is held at {np.round(position, 3).tolist()} mm on its way to"
                f" {what} (a feed hold on the controller): waiting for it to go on"
            )
        return False

    wait_for(run, there, f"stop at {what}", program.timeout_s, program.poll_s, tell)


def _hold_for_beam(
    run: CalibrationRun,
    program: ControlledProgram,
    target_mm: Vec,
    what: str,
    tell: Callable[[str], None],
) -> None:
    """The beam is lost while the machine moves: hold the feed until it is back (at most
    ``BEAM_WAIT_S``), resume; the next capture counts the beam as lost there.

    Held at rest at ``target_mm`` (the hold came as the program reached its stop),
    it is not resumed: a resume would pass the stop before the point is captured.
    """
    controller = program.controller
    controller.hold()
    held = run.clock.now()
    back = run.beam_returns(held + BEAM_WAIT_S)
    run.count_lost = True
    position = controller.position_mm()
    at_stop = (
        float(np.linalg.norm(position - target_mm)) <= program.tolerance_mm
        and controller.is_standstill()
    )
    tell(
        f"beam lost on the way to {what}: feed held {run.clock.now() - held:.1f} s,"
        f" {'beam back' if back else 'beam still lost (searched for at the point)'};"
        f" {'held at the point: captured there' if at_stop else 'resumed'}"
    )
    if not at_stop:
        _resume(run, program, position, f"the feed hold on the way to {what}", tell)


def _program_ended(run: CalibrationRun, program: ControlledProgram) -> Callable[[], bool]:
    return lambda: _state(run, program, "the end of the program", ending=True) == "idle"


def _try(action: Callable[[], None], done: str) -> str:
    """Do ``action`` after a failure; what happened, for the error line."""
    try:
        action()
    except XmalignError as error:
        return f"the controller could not be reached to stop the program ({error})"
    return done


def _noted(error: BaseException, note: str) -> BaseException:
    """The same error (a StopSignal keeps its signal) with ``note`` added to its one line."""
    return like(error, "; ".join(part for part in (str(error), note) if part))
