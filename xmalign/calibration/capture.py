"""Capturing a plan's points: the capture order, the six channels in the line frame, and
:class:`CalibrationRun` (setting the units for a line, the settled average, a lost beam
searched for and captured again)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace

import numpy as np

from xmalign.alignment import FineAlignmentResult, FineAlignmentSettings, find_beam, fine_align
from xmalign.environment import DRIFT_RUN, EnvironmentMonitor
from xmalign.errors import BeamLostError
from xmalign.formats.measurements import LineSetup, MeasurementRow
from xmalign.formats.plan import Plan, PlanLine
from xmalign.geometry import Vec, rot_y, rot_z, wrap_angle
from xmalign.roles import CHANNELS, Clock, Interferometer, InterferometerReading, PositioningUnit

#: Fine alignment at a line start turns only the receiver (see FineAlignmentSettings).
LINE_START_ALIGNMENT = FineAlignmentSettings(steer_launch=False)
#: Fine-alignment distance guess when a plan does not give the line's beam distances, mm.
DEFAULT_START_DISTANCE_MM = 500.0
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

    def stands_at(self, setup: LineSetup) -> bool:
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
        if recorded is not None and self.stands_at(recorded):
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
