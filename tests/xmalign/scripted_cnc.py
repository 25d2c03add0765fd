"""A controller running xmalign's program, scripted on a virtual clock (no LinuxCNC, no wait).

:class:`ScriptedCnc` implements :class:`xmalign.roles.ProgramControl` the way a
LinuxCNC behind linuxcncrsh behaves towards xmalign: the program moves the
machine along the program's way (``xmalign program``'s: up to the safe height,
across, down to each line's stop, along the line from stop to stop), stands
paused at each stop until resumed, and a feed hold freezes it where it is. A
test scripts what else happens: an operator's feed hold, a cycle start pressed
at the machine, a stale status after a resume, a fault or a lost connection.
Everything runs on :class:`VirtualClock`: a whole run takes milliseconds.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from xmalign.calibration import CalibrationRun, ProgramWay, capture_sequence
from xmalign.errors import DeviceTimeoutError, DriveFaultError
from xmalign.formats.measurements import LineSetup, MeasurementRow
from xmalign.formats.plan import Plan, PlanLine
from xmalign.geometry import Vec, line_frame
from xmalign.roles import InterferometerReading, ProgramState

#: Each leg of the program's way takes this long, s.
LEG_S = 0.5
WAY = ProgramWay(overrun_mm=5.0, safe_z_mm=0.0)
PROGRAM = "/home/cnc/run.ngc"


class VirtualClock:
    def __init__(self) -> None:
        self.now_s = 0.0

    def now(self) -> float:
        return self.now_s

    def sleep(self, seconds: float) -> None:
        self.now_s += max(seconds, 0.0)


def _line(line_id: str, u: tuple[float, float, float], start: tuple[float, ...]) -> PlanLine:
    targets = np.array([0.0, 50.0, 100.0])
    axis = np.array(u)
    return PlanLine(
        id=line_id,
        start_mm=np.array(start),
        end_mm=np.array(start) + targets[-1] * axis,
        frame=line_frame(axis),
        launch_rad=np.zeros(2),
        receiver_rad=np.zeros(2),
        targets_mm=targets,
        dwell_s=1.0,
    )


def two_line_plan() -> Plan:
    """Lines X and Y, three targets each, one run up: 4 points per line (with the drift check)."""
    lines = [_line("X", (1, 0, 0), (100, 100, -300)), _line("Y", (0, 1, 0), (300, 200, -250))]
    return Plan("scripted", np.zeros(3), 0.0, lines)


def _with_z(point: Vec, z_mm: float) -> Vec:
    return np.array([point[0], point[1], z_mm])


def program_route(plan: Plan, start_mm: Vec) -> list[tuple[Vec, bool]]:
    """The program's way as waypoints, each with whether the program stops there."""
    route = [(_with_z(start_mm, WAY.safe_z_mm), False)]
    for line in plan.lines:
        pre = WAY.pre_position_mm(line)
        route += [(_with_z(pre, WAY.safe_z_mm), False), (pre, True)]
        route += [(point.point_mm, True) for point in capture_sequence(line)]
        route.append((_with_z(line.target_points_mm()[0], WAY.safe_z_mm), False))
    return route


@dataclass
class ScriptedCnc:
    """The program on a controller; the attributes after ``clock`` are the test's script."""

    clock: VirtualClock
    route: list[tuple[Vec, bool]]
    position: Vec = field(default_factory=lambda: np.array([0.0, 0.0, -100.0]))
    state: ProgramState = "idle"
    loaded: str | None = None
    #: What xmalign commanded, in order: start, hold, resume, stop.
    commands: list[str] = field(default_factory=list)
    #: Called at every status read (a test raises from it: a fault, a lost link, Ctrl-C).
    on_read: Callable[[ScriptedCnc], None] = lambda cnc: None
    #: Called with the stop's number (0 the first) and the time the machine arrived there.
    on_stop: Callable[[int, float], None] = lambda number, arrived_s: None
    #: An operator's feed hold at this time (s), released after ``operator_hold_s``.
    operator_hold_at_s: float = math.inf
    operator_hold_s: float = 3.0
    #: Cycle start pressed at the machine at this time (s) while the program is at a stop.
    cycle_start_at_s: float = math.inf
    #: After each resume xmalign sends, the status stays the one before for this long, s.
    stale_s: float = 0.0
    #: The next this many resumes at a stop leave the program paused there (LinuxCNC 2.9
    #: after a feed hold in the last mm before an M0).
    swallowed_resumes: int = 0
    #: From this time (s) the status freezes and no command is taken (a dead task).
    dead_at_s: float = math.inf
    #: From this time (s) the machine is in E-stop: the program ended, at rest.
    estop_at_s: float = math.inf
    #: xmalign's feed hold takes effect this long after it is sent, s; one that finds the
    #: program at a stop by then merges with the stop's pause (LinuxCNC 2.9).
    hold_lag_s: float = 0.0
    #: Each leg at this speed, mm/s (None: each in ``LEG_S``); a test may change it at a stop.
    speed_mm_s: float | None = None
    #: The actual position read jitters by up to this much on each axis (encoder counts,
    #: servo noise), mm; seeded.
    jitter_mm: float = 0.0
    rng: np.random.Generator = field(default_factory=lambda: np.random.default_rng(33))
    stops_reached: int = 0
    _leg: int = 0
    _leg_from: Vec = field(default_factory=lambda: np.zeros(3))
    _leg_start_s: float = 0.0
    _held: bool = False
    _release_at_s: float = math.inf
    _stale: tuple[float, ProgramState, Vec] | None = None
    _hold_on_its_way: bool = False
    _leg_s: float = LEG_S

    # -- the role -----------------------------------------------------------------
    def check_ready(self) -> None:
        if self.clock.now() >= self.estop_at_s:
            raise DriveFaultError("scripted CNC: E-stop is pressed; release it")

    def loaded_program(self) -> str | None:
        return self.loaded

    def program_state(self) -> ProgramState:
        self.on_read(self)
        if self._dead():
            return "running"
        self._advance()
        stale = self._stale_status()
        return stale[1] if stale else self.state

    def position_mm(self) -> Vec:
        return self._position() + self.rng.uniform(-self.jitter_mm, self.jitter_mm, 3)

    def _position(self) -> Vec:
        if self._dead():
            return self._along(self.dead_at_s)
        self._advance()
        stale = self._stale_status()
        if stale:
            return stale[2].copy()
        if self.state != "running":
            return self.position.copy()
        return self._along(self.clock.now())

    def is_standstill(self) -> bool:
        self._advance()
        return self._stale_status() is not None or self.state != "running"

    def start_program(self, path: str) -> None:
        self.commands.append("start")
        self.loaded = path
        self._leg, self._held = 0, False
        self._go(self.clock.now())

    def hold(self) -> None:
        self._refuse_when_dead("set pause")
        self.commands.append("hold")
        self._advance()
        if self.state == "running" and self.hold_lag_s > 0:
            self.operator_hold_at_s = self.clock.now() + self.hold_lag_s
            self.operator_hold_s = math.inf  # held until resumed
            self._hold_on_its_way = True
        elif self.state == "running":
            self._freeze(self.clock.now())

    def resume(self) -> None:
        self.commands.append("resume")
        self._advance()
        if self.state == "paused" and not self._held and self.swallowed_resumes > 0:
            self.swallowed_resumes -= 1
            return
        before = (self.clock.now() + self.stale_s, self.state, self.position.copy())
        if self.state == "paused":
            self._continue(self.clock.now())
        self._stale = before if self.stale_s > 0 else None

    def stop_program(self) -> None:
        self._refuse_when_dead("set abort")
        self.commands.append("stop")
        self._advance()
        if self.state == "running":
            self.position = self._along(self.clock.now())
        self.state, self._held = "idle", False

    # -- the program ----------------------------------------------------------------
    def _stale_status(self) -> tuple[float, ProgramState, Vec] | None:
        if self._stale is not None and self.clock.now() < self._stale[0]:
            return self._stale
        return None

    def _along(self, t_s: float) -> Vec:
        fraction = min(max((t_s - self._leg_start_s) / self._leg_s, 0.0), 1.0)
        target = self.route[self._leg][0]
        return self._leg_from + fraction * (target - self._leg_from)

    def _go(self, t_s: float) -> None:
        if self._leg >= len(self.route):
            self.state = "idle"
            return
        self.state, self._leg_from, self._leg_start_s = "running", self.position.copy(), t_s
        distance_mm = float(np.linalg.norm(self.route[self._leg][0] - self._leg_from))
        self._leg_s = LEG_S if self.speed_mm_s is None else max(distance_mm / self.speed_mm_s, 1e-9)

    def _freeze(self, t_s: float) -> None:
        self.position = self._along(t_s)
        self.state, self._held = "paused", True

    def _continue(self, t_s: float) -> None:
        if not self._held:  # at a stop: on to the next leg
            self._leg += 1
        self._held = False
        self._go(t_s)

    def _refuse_when_dead(self, request: str) -> None:
        if self._dead():
            raise DeviceTimeoutError(f"scripted CNC did not answer '{request}' within 5 s")

    def _dead(self) -> bool:
        return self.clock.now() >= self.dead_at_s and self.state == "running"

    def _advance(self) -> None:
        now = self.clock.now()
        if now >= self.estop_at_s and self.state != "idle":
            self.position = (
                self._along(self.estop_at_s) if self.state == "running" else self.position
            )
            self.state = "idle"
        while True:
            if self.state == "running":
                end_s = self._leg_start_s + self._leg_s
                if self.operator_hold_at_s <= min(end_s, now):
                    held_s = max(self.operator_hold_at_s, self._leg_start_s)
                    self._freeze(held_s)
                    self._release_at_s = held_s + self.operator_hold_s
                    self.operator_hold_at_s, self._hold_on_its_way = math.inf, False
                    continue
                if end_s > now:
                    return
                self._arrive(end_s)
            elif self.state == "paused":
                at_s = self._release_at_s if self._held else self.cycle_start_at_s
                if at_s > now:
                    return
                self._release_at_s = self.cycle_start_at_s = math.inf
                self._continue(at_s)
            else:
                return

    def _arrive(self, t_s: float) -> None:
        self.position, stop = self.route[self._leg][0].copy(), self.route[self._leg][1]
        if stop:
            if self._hold_on_its_way:  # xmalign's hold merges with the stop's pause
                self.operator_hold_at_s, self._hold_on_its_way = math.inf, False
            self.state = "paused"
            self.stops_reached += 1
            self.on_stop(self.stops_reached - 1, t_s)
            return
        self._leg += 1
        self._go(t_s)


@dataclass
class ScriptedInterferometer:
    """Zero readings; the beam lost over the ``lost`` intervals of the clock, s."""

    clock: VirtualClock
    lost: list[tuple[float, float]] = field(default_factory=list)

    def _ok(self, start_s: float, end_s: float) -> bool:
        return not any(a < end_s and start_s < b for a, b in self.lost)

    def zero(self) -> None:
        pass

    def read(self) -> InterferometerReading:
        now = self.clock.now()
        return InterferometerReading(now, np.zeros(6), self._ok(now, now + 1e-9))

    def average(self, duration_s: float) -> InterferometerReading:
        start = self.clock.now()
        self.clock.sleep(duration_s)
        return InterferometerReading(
            self.clock.now(), np.zeros(6), self._ok(start, start + duration_s)
        )


class StandingUnit:
    """A locked unit that stands where its line was set up (its setup is kept)."""

    angles = np.array([0.1, 0.2])

    def __init__(self) -> None:
        self.locks = 0

    def angles_rad(self) -> Vec:
        return self.angles.copy()

    def lock(self) -> None:
        self.locks += 1

    def move_to(self, angles_rad: Vec, timeout_s: float) -> None:
        raise DriveFaultError("a scripted unit does not move (its setup is kept)")


def scripted_run(
    plan: Plan, interferometer: ScriptedInterferometer
) -> tuple[CalibrationRun, list[MeasurementRow]]:
    """A run on standing units whose every line keeps its recorded setup; its rows."""
    rows: list[MeasurementRow] = []
    unit = StandingUnit()
    setups = {line.id: LineSetup(line.id, 0, unit.angles, unit.angles) for line in plan.lines}
    run = CalibrationRun(
        plan,
        unit,  # type: ignore[arg-type]
        unit,  # type: ignore[arg-type]
        interferometer,
        interferometer.clock,
        rows.append,
        setups=setups,
        last_segment={line.id: 0 for line in plan.lines},
    )
    return run, rows
