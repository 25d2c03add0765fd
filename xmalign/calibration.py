"""Running a measurement plan on the units, the interferometer and the machine (roles only).

Per line: drive the units to the plan's angles, fine-align at the line start,
lock, then follow the machine through the targets and capture the six
channels averaged over each dwell. Every captured point is appended to the
measurement CSV and flushed at once; a resumed run skips the points already
recorded. A device fault stops the line with the units locked.

A beam lost while capturing is searched for like fine alignment does
(:func:`xmalign.alignment.find_beam`: back to the line's locked angles, then
spiral searches within the units' pointing uncertainty); found, both units
align to it, they are locked, the alignment is recorded as a new
setup segment (the interferometer lost its count, and the beam may point a
little differently), the datum is set again and the point is captured again.
Only when the search fails does the run stop and ask a person.

Each alignment of a line is recorded with the locked unit angles. A resumed
line keeps its setup when the units still stand where they were locked;
otherwise it is aligned again and its further rows form a new setup segment,
which ``post`` fits with its own setup terms.

The interferometer reports in its own frame, the launch head's (``u`` from the
launch unit towards the receiver), with the raw displacement since its datum;
the rows are written in the line frame of docs/conventions.md, with ``linear_um`` the actual
minus the commanded displacement from the run's first point (where the datum
is set).
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Protocol

import numpy as np

from xmalign.alignment import FineAlignmentResult, FineAlignmentSettings, find_beam, fine_align
from xmalign.environment import DRIFT_RUN, EnvironmentMonitor
from xmalign.errors import (
    BeamLostError,
    DeviceError,
    InputError,
    TransportError,
    XmalignError,
)
from xmalign.formats.common import refuse_special
from xmalign.formats.measurements import (
    NOMINAL_LIMITS,
    ChannelLimits,
    LineSetup,
    MeasurementFile,
    MeasurementRow,
    MeasurementWriter,
    RunLock,
    check_recorded_plan,
    load_measurements,
    plan_sha256,
)
from xmalign.formats.plan import Plan, PlanLine
from xmalign.geometry import Vec, rot_y, rot_z, wrap_angle
from xmalign.roles import (
    CHANNELS,
    Clock,
    Interferometer,
    InterferometerReading,
    MachineMover,
    MachinePositionSource,
    PositioningUnit,
    ProgramControl,
    ProgramState,
    ReportsProgram,
)
from xmalign.safety import like

#: Fine alignment at a line start turns only the receiver (see FineAlignmentSettings).
LINE_START_ALIGNMENT = FineAlignmentSettings(steer_launch=False)
#: Fine-alignment distance guess when a plan does not give the line's beam distances, mm.
DEFAULT_START_DISTANCE_MM = 500.0
#: While a run waits for the machine, it reads the units this often (a lost link shows), s.
DEVICE_CHECK_S = 1.0
#: The end of what a run following the machine tells the operator once a line's units are set.
PRESS_CYCLE_START = "press cycle start"
#: Time the units may take to reach the plan's angles, s.
UNIT_MOVE_TIMEOUT_S = 120.0
#: Capture waits for settled readings for at most this part of each dwell.
SETTLE_FRACTION = 0.5
#: Averaging ends at this part of each dwell (the rest is margin for the dwell timer).
AVERAGE_END_FRACTION = 0.8
#: Length of each probe of the settling check, s.
SETTLE_PROBE_S = 0.1
#: Readings are settled when two probes' linear means differ less than this, um.
SETTLED_UM = 0.2
#: A beam lost while capturing: wait this long for it to come back (something crossed
#: it) before searching, s; and read this long each time.
BEAM_WAIT_S = 2.0
BEAM_PROBE_S = 0.1
#: Encoder readings averaged to record or check where a locked unit stands.
STANDING_READINGS = 10
#: A resumed line keeps its setup when no unit axis is farther than this from where it
#: was locked, rad (a few times the encoder noise of the mean; a locked unit does not move).
SETUP_KEPT_RAD = 20e-6


@dataclass(frozen=True)
class CapturePoint:
    """One point of the plan to capture, in the order the program visits it."""

    line: PlanLine
    run: int
    direction: str
    index: int

    @property
    def key(self) -> tuple[str, int, str, int]:
        return (self.line.id, self.run, self.direction, self.index)

    @property
    def point_mm(self) -> Vec:
        return self.line.target_points_mm()[self.index]

    @property
    def starts_run(self) -> bool:
        """The run's first point: the interferometer datum is set here."""
        return self.run != DRIFT_RUN and self.direction == "+" and self.index == 0


def capture_sequence(line: PlanLine) -> Iterator[CapturePoint]:
    """The line's points in program order: per run, up the targets, then back if bidirectional.

    Last, the drift check: the first target once more, approached in ``+``, as
    run :data:`~xmalign.environment.DRIFT_RUN` (read against the last run's datum).
    """
    count = len(line.targets_mm)
    for run in range(1, line.runs + 1):
        yield from (CapturePoint(line, run, "+", i) for i in range(count))
        if line.bidirectional:
            yield from (CapturePoint(line, run, "-", i) for i in range(count - 1, -1, -1))
    yield CapturePoint(line, DRIFT_RUN, "+", 0)


def head_frame(line: PlanLine, spindle_angle_rad: float) -> Vec:
    """Axes of the interferometer's frame (the launch head's) for a line, rows u, v, w, (3, 3).

    Taken from the receiver's commanded angles: aligned, its optical axis is
    ``-u`` and its "up" is the launch head's ``w`` (docs/conventions.md, roll 0).
    For any line that is not vertical this is the line frame of the beam.
    """
    phi3, phi4 = line.receiver_rad[:2]
    receiver = rot_z(spindle_angle_rad + phi3) @ rot_y(-phi4)
    u, w = -receiver[:, 0], receiver[:, 2]
    return np.vstack([u, np.cross(w, u), w])


def line_channels(reading: InterferometerReading, head2line: Vec, commanded_mm: float) -> Vec:
    """Six channels of docs/conventions.md in the line frame from a head-frame reading, (6,).

    ``head2line`` (3, 3) turns head-frame components into line-frame ones; the
    straightness is a vector across the beam and the angles a rotation vector,
    so both turn with it. ``linear_um`` becomes the displacement along the
    line minus the commanded displacement ``commanded_mm``.
    """
    raw = reading.channels
    straightness = head2line @ np.array([0.0, raw[1], raw[2]])
    angles = head2line @ raw[3:6]
    linear = raw[0] * head2line[0, 0] - commanded_mm * 1e3
    return np.concatenate([[linear], straightness[1:], angles])


def _point_name(point: CapturePoint) -> str:
    return f"line {point.line.id} run {point.run} ({point.direction}) target {point.index + 1}"


def _beam_message(point: CapturePoint, reading: InterferometerReading) -> str:
    values = ", ".join(
        f"{name} {value:.1f}"
        for name, value in zip(CHANNELS[1:], reading.channels[1:], strict=True)
    )
    return (
        f"beam lost on {_point_name(point)} ({values}): the units are locked; check the beam"
        " path, re-align and continue with --resume"
    )


@dataclass
class RunStatistics:
    """Simulated or real time spent, s, and what was captured."""

    alignment_s: float = 0.0
    measuring_s: float = 0.0
    points: int = 0
    skipped: int = 0
    alignments: dict[str, FineAlignmentResult] = field(default_factory=dict)
    #: What a resume did with each line it found started (setup kept or a new segment).
    resumed: list[str] = field(default_factory=list)
    #: Each beam lost while capturing and found again by the search.
    recovered: list[str] = field(default_factory=list)
    #: Points not captured because the machine had gone on while the beam was searched
    #: (``--resume`` captures them).
    missed: list[tuple[str, int, str, int]] = field(default_factory=list)
    #: xmalign ran the program (:func:`control_program`): from its start to its end, s,
    #: and the part of it the machine waited at the programmed stops while the units were set.
    program_s: float | None = None
    stopped_s: float = 0.0


@dataclass
class CalibrationRun:
    """Captures a plan's points with the units, the interferometer and a clock.

    Parameters
    ----------
    plan : Plan
    launch, receiver : PositioningUnit
    interferometer : Interferometer
    clock : Clock
    record : callable
        Called with every captured row at once (append + flush to the CSV).
    done : set of tuple
        Keys ``(line, run, direction, index)`` already recorded (resume).
    setups : dict of str to LineSetup
        The latest recorded setup of each line (resume).
    last_segment : dict of str to int
        The highest setup segment recorded for each line (resume).
    record_setup : callable
        Called with each new alignment of a line before its rows.
    environment : EnvironmentMonitor, optional
        Sampled at every captured point; its values and flags go into the row.
    """

    plan: Plan
    launch: PositioningUnit
    receiver: PositioningUnit
    interferometer: Interferometer
    clock: Clock
    record: Callable[[MeasurementRow], None]
    done: set[tuple[str, int, str, int]] = field(default_factory=set)
    setups: dict[str, LineSetup] = field(default_factory=dict)
    last_segment: dict[str, int] = field(default_factory=dict)
    record_setup: Callable[[LineSetup], None] = lambda setup: None
    alignment_settings: FineAlignmentSettings | None = None
    statistics: RunStatistics = field(default_factory=RunStatistics)
    environment: EnvironmentMonitor | None = None
    #: Target (mm along the line) where the interferometer's datum counts from.
    _datum_mm: float = field(default=0.0, init=False, repr=False)
    #: The beam was lost since the last capture (seen while the machine moved): the
    #: interferometer lost its count, so the next capture goes as after a beam lost there.
    count_lost: bool = field(default=False, init=False)
    #: The clock when the run started: rows record their time from here (``time_s``).
    _started_s: float = field(default=0.0, init=False, repr=False)

    def __post_init__(self) -> None:
        self._started_s = self.clock.now()

    def line_is_done(self, line: PlanLine) -> bool:
        return all(point.key in self.done for point in capture_sequence(line))

    def _standing_rad(self) -> tuple[Vec, Vec]:
        """Mean encoder angles of the launch and the receiver unit, rad."""

        def mean(unit: PositioningUnit) -> Vec:
            readings = np.array([unit.angles_rad() for _ in range(STANDING_READINGS)])
            return readings[0] + np.mean(wrap_angle(readings - readings[0]), axis=0)

        return mean(self.launch), mean(self.receiver)

    def _stands_at(self, setup: LineSetup) -> bool:
        launch, receiver = self._standing_rad()
        moved = np.concatenate(
            [wrap_angle(launch - setup.launch_rad), wrap_angle(receiver - setup.receiver_rad)]
        )
        return bool(np.max(np.abs(moved)) <= SETUP_KEPT_RAD)

    def prepare_line(self, line: PlanLine) -> None:
        """Set the units for a line, or keep a resumed line's setup if they have not moved.

        A line that has rows but must be aligned again continues in a new segment.
        """
        self.count_lost = False  # the line starts with its own datum
        recorded = self.setups.get(line.id)
        if recorded is not None and self._stands_at(recorded):
            self.launch.lock()
            self.receiver.lock()
            note = f"line {line.id}: the units stand where they were locked; setup kept"
            if recorded.segment > 0:
                # the segment may have begun with a datum set mid-run (a recovered beam),
                # which the run's restart does not repeat: go on with its own constants
                kept = LineSetup(line.id, recorded.segment + 1, *self._standing_rad())
                self._note_setup(kept)
                note += f"; its further rows are setup segment {kept.segment}"
            self.statistics.resumed.append(note)
            return
        if line.id not in self.last_segment:
            self.set_line(line)
            return
        segment = self.last_segment[line.id] + 1
        self.set_line(line, segment)
        self.statistics.resumed.append(
            f"line {line.id}: the units had moved and were aligned again; its further rows"
            f" are setup segment {segment}"
        )

    def _note_setup(self, setup: LineSetup) -> None:
        """Record a line's (new) setup segment before its rows."""
        self.record_setup(setup)
        self.setups[setup.line] = setup
        self.last_segment[setup.line] = setup.segment

    def set_line(self, line: PlanLine, segment: int = 0) -> FineAlignmentResult:
        """Units to the plan's angles, fine alignment at the line start, lock, record."""
        started = self.clock.now()
        self.launch.move_to(line.launch_rad, UNIT_MOVE_TIMEOUT_S)
        self.receiver.move_to(line.receiver_rad, UNIT_MOVE_TIMEOUT_S)
        result = fine_align(
            self.launch,
            self.receiver,
            self.interferometer,
            self.clock,
            _beam_distance_mm(line, 0),
            self.alignment_settings or LINE_START_ALIGNMENT,
        )
        self.launch.lock()
        self.receiver.lock()
        self._note_setup(LineSetup(line.id, segment, *self._standing_rad()))
        self.statistics.alignments[line.id] = result
        self.statistics.alignment_s += self.clock.now() - started
        return result

    def _settle(self, deadline_s: float) -> InterferometerReading | None:
        """Probe until two probes' linear readings agree or ``deadline_s`` comes.

        Returns the last probe when settled (it is already a settled reading), else None.
        """
        previous = None
        while self.clock.now() + SETTLE_PROBE_S <= deadline_s:
            probe = self.interferometer.average(SETTLE_PROBE_S)
            if previous is not None and abs(probe.channels[0] - previous) < SETTLED_UM:
                return probe
            previous = probe.channels[0]
        self.clock.sleep(max(deadline_s - self.clock.now(), 0.0))
        return None

    def _settled_average(self, started_s: float, dwell_s: float) -> InterferometerReading:
        """The mean of the settled readings up to ``AVERAGE_END_FRACTION`` of the dwell."""
        probe = self._settle(started_s + SETTLE_FRACTION * dwell_s)
        left_s = started_s + AVERAGE_END_FRACTION * dwell_s - self.clock.now()
        if probe is not None and left_s < SETTLE_PROBE_S / 2:
            return probe  # the settling took the time (a late start): no average past the dwell
        left_s = max(left_s, 1e-3)
        reading = self.interferometer.average(left_s)
        if probe is None:
            return reading
        weight = SETTLE_PROBE_S / (SETTLE_PROBE_S + left_s)
        return InterferometerReading(
            time_s=reading.time_s,
            channels=weight * probe.channels + (1.0 - weight) * reading.channels,
            beam_ok=probe.beam_ok and reading.beam_ok,
        )

    def capture(
        self,
        point: CapturePoint,
        dwell_s: float,
        still_there: Callable[[CapturePoint], bool] | None = None,
        check_after: bool = False,
    ) -> MeasurementRow | None:
        """Datum at the run's first point; once readings settle, average to 0.8 of the dwell.

        Readings count as settled when two successive 0.1 s probes of the
        linear channel agree within ``SETTLED_UM``; the wait ends at half the
        dwell whatever the readings do, so the capture fits in the dwell.

        A lost beam is searched for and the point captured again
        (:meth:`_recapture`); ``still_there`` says whether the machine still
        stands at the point after the search (default: it waits for the
        capture). With ``check_after`` (a program that waits at each point's stop
        until it is resumed) ``still_there`` is asked again after the average, and a
        point the machine left meanwhile is not recorded. Returns None for a point
        already recorded or one the machine left before the beam was found or the
        average ended (``statistics.missed``).
        """
        started = self.clock.now()
        if point.starts_run:
            self.interferometer.zero()
            self._datum_mm = float(point.line.targets_mm[0])
        if point.key in self.done:
            self.statistics.skipped += 1
            return None
        reading = self._settled_average(started, dwell_s)
        if not reading.beam_ok or self.count_lost:
            recaptured = self._recapture(point, dwell_s, still_there)
            if recaptured is None:
                self.statistics.missed.append(point.key)
                return None
            reading = recaptured
        if check_after and still_there is not None and not still_there(point):
            self.statistics.missed.append(point.key)  # averaged (in part) on the move
            return None
        sample = self.environment.sample() if self.environment else None
        line = point.line
        displacement = float(line.targets_mm[point.index]) - self._datum_mm
        head2line = line.frame @ head_frame(line, self.plan.spindle_angle_rad).T
        row = MeasurementRow(
            line=line.id,
            run=point.run,
            direction=point.direction,
            index=point.index,
            target_mm=float(line.targets_mm[point.index]),
            machine_mm=point.point_mm,
            channels=line_channels(reading, head2line, displacement),
            segment=self.setups[line.id].segment if line.id in self.setups else 0,
            environment=sample.values if sample else {},
            environment_flags=sample.flag_text if sample else "",
            time_s=self.clock.now() - self._started_s,
        )
        self.record(row)
        self.done.add(point.key)
        self.statistics.points += 1
        self.statistics.measuring_s += self.clock.now() - started
        return row

    def _recapture(
        self,
        point: CapturePoint,
        dwell_s: float,
        still_there: Callable[[CapturePoint], bool] | None,
    ) -> InterferometerReading | None:
        """Find the lost beam, align and lock in a new segment, set the datum, capture again.

        Raises BeamLostError (asking a person) when the search does not find the beam.
        """
        started = self.clock.now()
        line = point.line
        settings = self.alignment_settings or LINE_START_ALIGNMENT
        setup = self.setups.get(line.id)
        last_in_range = np.concatenate(
            [setup.launch_rad, setup.receiver_rad] if setup else self._standing_rad()
        )
        try:
            if not self.beam_returns(started + BEAM_WAIT_S):
                self._search(point, last_in_range, settings)
        except BeamLostError as error:
            raise BeamLostError(
                f"beam lost on {_point_name(point)} and not found again by the search"
                f" ({error}); the units are locked: jog them until the beam is in range"
                " (xmalign align --manual) and continue with --resume"
            ) from error
        finally:
            self.launch.lock()
            self.receiver.lock()
            self.statistics.alignment_s += self.clock.now() - started
        self.count_lost = False
        segment = self.last_segment.get(line.id, 0) + 1
        self._note_setup(LineSetup(line.id, segment, *self._standing_rad()))
        self.statistics.recovered.append(
            f"{_point_name(point)}: the beam was lost and found again after"
            f" {self.clock.now() - started:.1f} s; the line goes on in setup segment {segment}"
        )
        if still_there is not None and not still_there(point):
            return None
        # the count was lost: the datum is set again here; the rows stay the error of
        # the displacement, up to a constant of the new segment (post fits one per run)
        self.interferometer.zero()
        self._datum_mm = float(point.line.targets_mm[point.index])
        reading = self._settled_average(self.clock.now(), dwell_s)
        if not reading.beam_ok:
            raise BeamLostError(_beam_message(point, reading))
        return reading

    def beam_returns(self, until_s: float) -> bool:
        """Read at the locked angles until ``until_s``: True when the beam is back by itself."""
        while self.clock.now() + BEAM_PROBE_S <= until_s:
            if self.interferometer.average(BEAM_PROBE_S).beam_ok:
                return True
        return False

    def _search(
        self, point: CapturePoint, last_in_range_rad: Vec, settings: FineAlignmentSettings
    ) -> None:
        """The search of fine alignment around the locked angles, then fine alignment with
        both units (BeamLostError if the search does not find the beam).

        Unlike at the line start, the launch unit steers too: the search finds the
        beam anywhere in the receiver's capture region, and only a beam through
        the receiver at this target (on the line, which passes through the launch
        cp) keeps it in range over the rest of the line.
        """
        distance_mm = _beam_distance_mm(point.line, point.index)
        devices = (self.launch, self.receiver, self.interferometer, self.clock)
        find_beam(*devices, last_in_range_rad, distance_mm, settings)
        fine_align(*devices, distance_mm, replace(settings, steer_launch=True))


def _beam_distance_mm(line: PlanLine, index: int) -> float:
    """The plan's cp-to-cp distance at a target (the line start's guess if it has none)."""
    distances = line.extra.get("beam_distance_mm") or [DEFAULT_START_DISTANCE_MM]
    return float(distances[min(index, len(distances) - 1)])


def step_through(
    run: CalibrationRun,
    mover: MachineMover,
    lines: Iterable[PlanLine],
    feed_mm_min: float,
    overrun_mm: float,
) -> None:
    """Capture by moving the machine to each target in turn (an operator or a driven CNC).

    Each pass approaches its first target from beyond, by ``overrun_mm``, so
    every target of a pass is approached in the pass's direction.
    """
    for line in lines:
        if run.line_is_done(line):
            continue
        u = line.frame[0]
        points = line.target_points_mm()
        mover.move_to(points[0] - overrun_mm * u, feed_mm_min)
        run.prepare_line(line)
        for point in capture_sequence(line):
            if point.index == (0 if point.direction == "+" else len(points) - 1):
                beyond = -overrun_mm if point.direction == "+" else overrun_mm
                mover.move_to(point.point_mm + beyond * u, feed_mm_min)
            mover.move_to(point.point_mm, feed_mm_min)
            run.capture(point, line.dwell_s)


def follow_machine(
    run: CalibrationRun,
    position: MachinePositionSource,
    lines: Iterable[PlanLine],
    tell: Callable[[str], None],
    way: ProgramWay,
    tolerance_mm: float = 0.005,
    timeout_s: float = 600.0,
    poll_s: float = 0.05,
    check_program: Callable[[], None] = lambda: None,
) -> None:
    """Capture while the controller runs the program: wait for standstill at each target.

    The units are set for a line once the machine stands at the line's
    pre-position (``way.overrun_mm`` before the first target, where the program
    stops for it): fine alignment needs a machine at rest where the plan
    aligned the beam. ``tell`` gets what the operator is to do: run the
    program while the machine is not there, press cycle start once the units
    are set. Where the program stops twice
    at one place (the last target of a run and the first back; the drift
    check), the machine has to leave it before it counts as there again: the
    program moves on to overrun and approach, and a capture while it does would
    average a moving machine. While waiting, the units are read every
    ``DEVICE_CHECK_S``; the machine not at its next stop within ``timeout_s``
    ends the run with one line. A controller that reports its program
    (:class:`~xmalign.roles.ReportsProgram`) is checked as a controlled run is:
    its program stopped with the machine at rest off the program's way to the
    next stop is a program that is not the plan's (one line); held on that way
    (a feed hold), it is waited for. ``check_program()`` raises when the controller
    runs another program than xmalign's (:class:`xmalign.program_check.ProgramGuard`):
    called first, and again before the units are set and before each capture.
    """
    check_program()
    last_stop_mm = position.position_mm()
    passed: list[PlanLine] = []  # lines done: the program still runs through them
    for line in lines:
        if run.line_is_done(line):
            passed.append(line)
            continue
        pre_mm = way.pre_position_mm(line)
        where = f"the pre-position of line {line.id} {np.round(pre_mm, 3).tolist()} mm"
        to_line = way.to_line(last_stop_mm, passed, line)
        there = _arrived(position, pre_mm, to_line, tolerance_mm, where)
        if not there():
            tell(
                f"line {line.id}: waiting for the machine to stop at {where}"
                " (start the program if it is not running)"
            )
            _wait_for(run, there, f"stop at {where}", timeout_s, poll_s)
        check_program()
        run.prepare_line(line)
        tell(f"line {line.id}: units aligned and locked; {PRESS_CYCLE_START}")
        on_line = way.on_line(line)
        previous: CapturePoint | None = None
        for point in capture_sequence(line):
            if previous is not None and np.allclose(previous.point_mm, point.point_mm):
                _wait_for(
                    run,
                    partial(_has_left, position, previous, tolerance_mm),
                    f"move on from {_where(previous)}",
                    timeout_s,
                    poll_s,
                )
            arrived = _arrived(position, point.point_mm, on_line, tolerance_mm, _where(point))
            _wait_for(run, arrived, f"stop at {_where(point)}", timeout_s, poll_s)
            check_program()
            run.capture(point, line.dwell_s, lambda p: _stands_at(position, p, tolerance_mm))
            previous = point
        last_stop_mm = line.target_points_mm()[0]  # the drift check
        passed = []


@dataclass(frozen=True)
class ProgramWay:
    """Where the program ``xmalign program`` writes moves the machine between its stops.

    Within a line, on the line's axis between the pre-position (``overrun_mm``
    before the first target) and the overrun past the last one. From a line's
    last stop (or wherever the program starts) to the next line's pre-position:
    up to ``safe_z_mm`` (the top of the Z travel), across at that height (a
    rapid, straight or not: anywhere between the two ends in X and Y), down.
    A program stopped (paused, the machine at rest) on this way is held there
    (a feed hold); anywhere else it is not the plan's program.
    """

    overrun_mm: float
    safe_z_mm: float

    def pre_position_mm(self, line: PlanLine) -> Vec:
        return pre_position_mm(line, self.overrun_mm)

    def on_line(self, line: PlanLine) -> Callable[[Vec], float]:
        """Distance from the line's part of the program, mm."""
        points = line.target_points_mm()
        start = self.pre_position_mm(line)
        end = points[-1] + self.overrun_mm * line.frame[0]
        return partial(_off_segment_mm, start=start, end=end)

    def to_line(
        self, from_mm: Vec, passed: Sequence[PlanLine], line: PlanLine
    ) -> Callable[[Vec], float]:
        """Distance from the program's way from a stop at ``from_mm`` to ``line``'s
        pre-position, through the lines ``passed`` (recorded: the program still runs them)."""
        pieces = []
        for done in passed:
            pieces += [self._transit(from_mm, self.pre_position_mm(done)), self.on_line(done)]
            from_mm = done.target_points_mm()[0]  # its drift check
        pieces.append(self._transit(from_mm, self.pre_position_mm(line)))
        return lambda position_mm: min(piece(position_mm) for piece in pieces)

    def _transit(self, from_mm: Vec, to_mm: Vec) -> Callable[[Vec], float]:
        up, down = _with_z(from_mm, self.safe_z_mm), _with_z(to_mm, self.safe_z_mm)

        def off_mm(position_mm: Vec) -> float:
            low, high = np.minimum(up, down), np.maximum(up, down)
            across = float(np.linalg.norm(position_mm - np.clip(position_mm, low, high)))
            return min(
                _off_segment_mm(position_mm, from_mm, up),
                across,
                _off_segment_mm(position_mm, down, to_mm),
            )

        return off_mm


def _with_z(point_mm: Vec, z_mm: float) -> Vec:
    return np.array([point_mm[0], point_mm[1], z_mm])


def _off_segment_mm(position_mm: Vec, start: Vec, end: Vec) -> float:
    """Distance of a point from the segment ``start`` to ``end``, mm."""
    step = end - start
    length2 = float(step @ step)
    along = 0.0 if length2 == 0.0 else float(np.clip((position_mm - start) @ step / length2, 0, 1))
    return float(np.linalg.norm(position_mm - (start + along * step)))


def _arrived(
    position: MachinePositionSource,
    target_mm: Vec,
    way: Callable[[Vec], float],
    tolerance_mm: float,
    what: str,
) -> Callable[[], bool]:
    """Whether a followed machine stands at ``target_mm``; a program it reports stopped at
    rest off ``way`` (distance from it, mm) is not the plan's (:func:`check_stop_on_way`)."""

    def there() -> bool:
        at_mm = position.position_mm()
        if not position.is_standstill():
            return False
        if float(np.linalg.norm(at_mm - target_mm)) <= tolerance_mm:
            return True
        if isinstance(position, ReportsProgram):
            report = position.program_report()
            if report is not None and report.state == "paused":
                check_stop_on_way(at_mm, target_mm, way, tolerance_mm, what)
        return False

    return there


def check_stop_on_way(
    position_mm: Vec, target_mm: Vec, way: Callable[[Vec], float], tolerance_mm: float, what: str
) -> None:
    """Refuse a program stopped with the machine at rest off its way to ``target_mm`` (its
    next stop, ``what``): a program that is not the plan's. On the way it is held there."""
    if way(position_mm) <= tolerance_mm:
        return
    miss = float(np.linalg.norm(position_mm - target_mm))
    raise DeviceError(
        f"the program stopped with the machine at {np.round(position_mm, 4).tolist()} mm,"
        f" {miss:.4f} mm from {what} (tolerance {tolerance_mm} mm): program and plan do not"
        " match"
    )


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


def control_program(
    run: CalibrationRun, program: ControlledProgram, tell: Callable[[str], None]
) -> None:
    """Run the program on the controller and capture every point, no one at the machine.

    The program is the one ``xmalign program`` writes for ``run.plan`` with a
    programmed stop at each point instead of the dwell. xmalign starts it (a
    program of an earlier run still open is aborted first; another program is
    refused and never touched), sets the units at each line's first stop, and
    resumes it at every stop once the point is captured (at once for points
    already recorded). A point is captured only when the program stands at a
    stop and the machine at rest within ``tolerance_mm`` of the plan's point,
    and recorded only if it still does after the average (someone pressed cycle
    start: the point is missed, ``--resume`` captures it). The program held on
    its way (a feed hold on the controller) is told once and waited for; a stop
    anywhere else, or a program that ends early, stops the run with one line
    (program and plan do not match). While the machine moves between points the
    beam is watched: lost, the feed is held until it comes back (at most
    ``BEAM_WAIT_S``), and the next point is captured as after a beam lost there.
    On a fault the program is aborted; on a lost connection or Ctrl-C (SIGTERM,
    SIGHUP) the feed is held where the controller still answers; the error says
    which.
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
        _wait_for(run, _program_ended(controller), "end the program", program.timeout_s, 0.1)
    except (TransportError, KeyboardInterrupt) as error:
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
    """Units set at the line's first stop; capture at each point's stop; resume each time."""
    pre_mm = program.way.pre_position_mm(line)
    to_line = program.way.to_line(from_mm, (), line)
    where = f"the pre-position of line {line.id} {np.round(pre_mm, 3).tolist()} mm"
    # on the way to a line the units are not yet set for it: the beam is not watched
    _wait_program(run, program, pre_mm, where, to_line, tell)
    stopped = run.clock.now()
    if not run.line_is_done(line):
        run.prepare_line(line)
    _resume(run, program, pre_mm)
    run.statistics.stopped_s += run.clock.now() - stopped
    on_line = program.way.on_line(line)
    for point in capture_sequence(line):
        _wait_program(run, program, point.point_mm, _where(point), on_line, tell, watch_beam=True)
        held = partial(_held_at, program)
        row = run.capture(point, line.dwell_s, held, check_after=True)
        if row is None and point.key in run.statistics.missed and not held(point):
            tell(
                f"{_where(point)}: the program went on during the capture (cycle start on"
                " the controller?): the point is not recorded; --resume captures it"
            )
            continue  # the program is no longer at this stop: nothing to resume
        _resume(run, program, point.point_mm)


def _held_at(program: ControlledProgram, point: CapturePoint) -> bool:
    """The program still stands at the point's stop, the machine at rest there."""
    controller = program.controller
    if controller.program_state() != "paused":
        return False
    return _stands_at(controller, point, program.tolerance_mm)


def _resume(run: CalibrationRun, program: ControlledProgram, stop_mm: Vec) -> None:
    """Resume, and wait until the controller shows it (running, or gone from the stop): a
    stale 'paused' must not count as the next stop."""
    controller = program.controller
    controller.resume()

    def going() -> bool:
        moved = float(np.linalg.norm(controller.position_mm() - stop_mm))
        return controller.program_state() != "paused" or moved > program.tolerance_mm

    _wait_for(run, going, "go on after the stop", program.timeout_s, 0.01)


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
    not match. Held on the way (a feed hold on the controller), it is told once
    and waited for. With ``watch_beam``, while the program runs, a lost beam
    holds the feed (:func:`_hold_for_beam`).
    """
    controller = program.controller
    told = False

    def there() -> bool:
        nonlocal told
        state = controller.program_state()
        if state == "idle":
            raise DeviceError(f"the program ended before {what}: program and plan do not match")
        if state == "running":
            told = False
            if watch_beam and not run.interferometer.read().beam_ok:
                _hold_for_beam(run, program, what, tell)
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

    _wait_for(run, there, f"stop at {what}", program.timeout_s, program.poll_s)


def _hold_for_beam(
    run: CalibrationRun, program: ControlledProgram, what: str, tell: Callable[[str], None]
) -> None:
    """The beam is lost while the machine moves: hold the feed until it is back (at most
    ``BEAM_WAIT_S``), resume; the next capture counts the beam as lost there."""
    controller = program.controller
    controller.hold()
    held = run.clock.now()
    back = run.beam_returns(held + BEAM_WAIT_S)
    run.count_lost = True
    tell(
        f"beam lost on the way to {what}: feed held {run.clock.now() - held:.1f} s,"
        f" {'beam back' if back else 'beam still lost (searched for at the point)'}; resumed"
    )
    _resume(run, program, controller.position_mm())


def _program_ended(controller: ProgramControl) -> Callable[[], bool]:
    return lambda: controller.program_state() == "idle"


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


def pre_position_mm(line: PlanLine, overrun_mm: float) -> Vec:
    """Where the program stops before a line: its first target less the overrun, mm (3,)."""
    return line.target_points_mm()[0] - overrun_mm * line.frame[0]


def _stands_at(position: MachinePositionSource, point: CapturePoint, tolerance_mm: float) -> bool:
    """The machine stands still at the point (it has not gone on with the program)."""
    miss = float(np.linalg.norm(position.position_mm() - point.point_mm))
    return position.is_standstill() and miss <= tolerance_mm


def _has_left(position: MachinePositionSource, point: CapturePoint, tolerance_mm: float) -> bool:
    return not _stands_at(position, point, tolerance_mm)


def _where(point: CapturePoint) -> str:
    return (
        f"line {point.line.id} run {point.run} target {point.index + 1}"
        f" {np.round(point.point_mm, 3).tolist()} mm"
    )


def _wait_for(
    run: CalibrationRun, done: Callable[[], bool], what: str, timeout_s: float, poll_s: float
) -> None:
    """Poll ``done`` until it holds; read the units every ``DEVICE_CHECK_S`` meanwhile."""
    clock = run.clock
    deadline = clock.now() + timeout_s
    checked_s = clock.now()
    while clock.now() < deadline:
        if done():
            return
        if clock.now() - checked_s >= DEVICE_CHECK_S:
            run.launch.angles_rad()
            run.receiver.angles_rad()
            checked_s = clock.now()
        clock.sleep(poll_s)
    # the controller answers all along: the machine is late, no connection is lost
    raise DeviceError(f"the machine did not {what} within {timeout_s:.0f} s (timeouts.machine_s)")


def check_program_position(point: CapturePoint, position_mm: Vec, tolerance_mm: float) -> None:
    """Refuse a dwell that is not where the plan expects the next capture."""
    miss = float(np.linalg.norm(np.asarray(position_mm) - point.point_mm))
    if miss > tolerance_mm:
        raise InputError(
            f"the program dwells at {np.round(position_mm, 3).tolist()} mm but the plan expects "
            f"line {point.line.id} run {point.run} target {point.index + 1} at "
            f"{np.round(point.point_mm, 3).tolist()} mm: program and plan do not match"
        )


#: A programmed stop farther than this from its plan line's axis is for another line, mm.
STOP_OFF_LINE_MM = 1.0


def check_program_stop(line: PlanLine, position_mm: Vec) -> None:
    """Refuse a programmed stop that is not on the plan's next line (a program for other
    lines): setting the units for a line the machine is not on would only lose the beam.

    ``xmalign program`` stops each line at its pre-position, on the line's axis.
    """
    offset = np.asarray(position_mm, dtype=float) - line.start_mm
    u = line.frame[0]
    off_mm = float(np.linalg.norm(offset - (offset @ u) * u))
    if off_mm > STOP_OFF_LINE_MM:
        raise InputError(
            f"the program stops at {np.round(position_mm, 3).tolist()} mm, {off_mm:.0f} mm off"
            f" the plan's line {line.id}: program and plan do not match (a program for other"
            " lines?)"
        )


class ProgramEvent(Protocol):
    """What a controller running the program reports (the simulated CNC's events)."""

    @property
    def kind(self) -> str: ...

    @property
    def position_mm(self) -> Vec: ...

    @property
    def dwell_s(self) -> float: ...


def capture_program(
    run: CalibrationRun, events: Iterable[ProgramEvent], tolerance_mm: float = 1e-3
) -> None:
    """Capture while a program runs: set the units at each programmed stop, capture at each dwell.

    The program is the one ``xmalign program`` writes for ``run.plan``: one
    stop per line (before its first run) and one dwell per capture point, in
    the order of :func:`capture_sequence`.
    """
    lines = iter(run.plan.lines)
    points: Iterator[CapturePoint] = iter(())
    for event in events:
        if event.kind == "stop":
            line = next(lines, None)
            if line is None:
                raise InputError("the program stops for more lines than the plan has")
            check_program_stop(line, event.position_mm)
            if not run.line_is_done(line):
                run.prepare_line(line)
            points = capture_sequence(line)
        elif event.kind == "dwell":
            point = next(points, None)
            if point is None:
                raise InputError("the program dwells at more points than the plan has")
            check_program_position(point, event.position_mm, tolerance_mm)
            run.capture(point, event.dwell_s)


@dataclass
class RunOutput:
    """The measurement CSV a run appends to, and what it already held."""

    writer: MeasurementWriter
    recorded: MeasurementFile | None = None
    warnings: list[str] = field(default_factory=list)
    #: Called with the number of rows in the file after each one is saved (progress).
    on_saved: Callable[[int], None] = lambda saved: None
    #: Sampled at every point when the run records the environment.
    environment: EnvironmentMonitor | None = None
    #: Held for the whole run: no other run appends to the file meanwhile.
    lock: RunLock | None = None

    def append(self, row: MeasurementRow) -> None:
        self.writer.append(row)
        self.on_saved(self.writer.saved)

    def calibration_run(
        self,
        plan: Plan,
        launch: PositioningUnit,
        receiver: PositioningUnit,
        interferometer: Interferometer,
        clock: Clock,
    ) -> CalibrationRun:
        """A CalibrationRun recording into this file and skipping what it already holds."""
        recorded = self.recorded
        return CalibrationRun(
            plan,
            launch,
            receiver,
            interferometer,
            clock,
            record=self.append,
            record_setup=self.writer.note_setup,
            done={row.key() for row in recorded.rows} if recorded else set(),
            setups=recorded.last_setups() if recorded else {},
            last_segment=recorded.last_segments() if recorded else {},
            environment=self.environment,
        )

    def close(self) -> None:
        self.writer.close()
        if self.lock is not None:
            self.lock.release()

    def __enter__(self) -> RunOutput:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _holds_no_points(path: Path) -> bool:
    """A measurement file with a header and not one point (a run that failed at its start)."""
    if not path.is_file() or path.stat().st_size == 0:
        return False
    try:
        recorded = load_measurements(path, torn_ok=True)
    except InputError:
        return False
    return not recorded.rows and recorded.torn is None


def check_run_output(path: Path, resume: bool) -> None:
    """Refuse an ``--out`` a run cannot use, before anything is read, created or connected."""
    if path.is_dir():
        raise InputError(f"{path}: is a folder; give a file name for --out")
    refuse_special(path, "--out")
    if resume and not path.exists():
        raise InputError(f"--resume: {path} does not exist yet; run without --resume")
    if path.exists() and path.stat().st_size > 0:
        _refuse_other_kinds(path)
    if not resume and path.exists() and path.stat().st_size > 0 and not _holds_no_points(path):
        raise InputError(
            f"{path} already holds measurements and is never replaced: add --resume to"
            " go on with it, or give another --out"
        )


def _refuse_other_kinds(path: Path) -> None:
    """An xmalign JSON file (a plan, a pose) given as ``--out`` is named for what it is."""
    with path.open("rb") as handle:
        start = handle.read(4096)
    if not start.lstrip().startswith(b"{"):
        return
    found = re.search(rb'"format"\s*:\s*"([^"]+)"', start)
    kind = found.group(1).decode("utf-8", "replace") if found else "JSON"
    name = kind.removeprefix("xmalign.").partition("/")[0]
    what = f"a {name} file ({kind})" if found else "a JSON file"
    raise InputError(
        f"{path}: --out: is {what}, not a measurement CSV; give the name of the measurement"
        " file to write (e.g. --out measurements.csv)"
    )


def _check_seed(path: Path, recorded: int | None, sim_seed: int | None) -> None:
    """A simulated run is resumed on the same virtual machine (the same ``--seed``).

    A live run is not checked: the hardware may be a served virtual machine.
    """
    if recorded is None or sim_seed is None or recorded == sim_seed:
        return
    raise InputError(
        f"--seed {sim_seed}: {path} was measured on the virtual machine of --seed {recorded};"
        f" resume it with --seed {recorded}"
    )


def _check_environment_columns(
    path: Path, recorded: tuple[str, ...], environment: EnvironmentMonitor | None
) -> None:
    """A resumed file keeps the environment columns it was started with."""
    sampled = environment.columns if environment else ()
    if set(recorded) == set(sampled):
        return
    if not sampled:
        raise InputError(
            f"{path}: was recorded with the environment ({', '.join(recorded)}); resume it"
            " with the same environment source"
        )
    raise InputError(
        f"{path}: was recorded with environment columns ({', '.join(recorded) or 'none'}),"
        f" the environment source now gives {', '.join(sampled)}; go on with another --out"
    )


def open_run_output(
    path: Path,
    plan: Plan,
    resume: bool,
    limits: ChannelLimits = NOMINAL_LIMITS,
    environment: EnvironmentMonitor | None = None,
    sim_seed: int | None = None,
) -> RunOutput:
    """Open the measurement CSV of a run: a new file, or (``resume``) the one to go on with.

    Raw measurements are never replaced: without ``resume`` an existing file is
    refused unless it holds not one point. With ``resume`` the file must have
    been recorded for ``plan`` (and, on the virtual machine, with ``sim_seed``);
    a torn last row is cut off with a warning and its point is measured again.
    With ``environment`` its first reading is taken (complete and in range, or a
    one-line error) before the file is touched, and every row records it. The
    file is locked (:class:`RunLock`) before it is read or written, until the
    output is closed.
    """
    path = Path(path)
    check_run_output(path, resume)
    if environment is not None:
        environment.prime()
    lock = RunLock(path)
    try:
        output = _open_locked(path, plan, resume, limits, environment, sim_seed)
    except BaseException:
        lock.release()
        raise
    output.lock = lock
    return output


def _open_locked(
    path: Path,
    plan: Plan,
    resume: bool,
    limits: ChannelLimits,
    environment: EnvironmentMonitor | None,
    sim_seed: int | None,
) -> RunOutput:
    columns = environment.columns if environment else ()
    if not resume or path.stat().st_size == 0:
        if _holds_no_points(path):
            os.truncate(path, 0)
        inputs = [plan.source] if plan.source is not None else []
        writer = MeasurementWriter.create(
            path, plan_sha256(plan), columns, sim_seed=sim_seed, inputs=inputs
        )
        return RunOutput(writer, environment=environment)
    recorded = load_measurements(path, limits, torn_ok=True)
    _check_seed(path, recorded.sim_seed, sim_seed)
    _check_environment_columns(path, recorded.environment_columns, environment)
    warnings = check_recorded_plan(recorded, plan)
    if recorded.torn is not None:
        warnings.append(
            f"{path}: line {recorded.torn.line_number} was cut short when the run stopped"
            f" ({recorded.torn.text[:40]!r}); it is dropped and its point measured again"
        )
    return RunOutput(
        MeasurementWriter.resume(recorded), recorded, warnings, environment=environment
    )
