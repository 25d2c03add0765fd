"""A virtual laser tracker logging a stream while the machine runs a program (seed 001).

What a real tracker records: its own clock (an offset and a rate error against the
CNC's), a fixed sample rate, and everything the machine did: the program's moves
between the measuring paths at the rapid feed, accelerations and decelerations at
the machine file's ``cnc.acceleration_mm_s2`` (every move straight, stop to stop,
as the G-code the program writes is executed by :func:`sim.cnc.read_program`),
the stops before and after the program, and the servo lag (the axes follow the
command a constant time late). Its noise is the tracker's uncertainty model
(:class:`sim.tracker.VirtualTracker`), correlated in time: a first-order
autoregression per component with the correlation time ``correlation_s``
(stationary variance: the model's).

Nothing here is known to the importer (:mod:`xmalign.post.stream_assign`): not
the clock, not the moves' timing, not the lag.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.signal

from sim.cnc import DEFAULT_ACCELERATION_MM_S2, _Dwell, _Move, read_program
from sim.instrument_errors import angle_coefficients, scale_factor, with_angle_errors
from sim.machine import VirtualMachine
from sim.tracker import VirtualTracker
from trajectories.gcode import make_dialect, resolve_dialect
from trajectories.instruments import InstrumentProgram, program_start_mm, write_instrument_program
from xmalign.formats.tracker_stream import StreamRun
from xmalign.geometry import Vec
from xmalign.machine import Machine


@dataclass(frozen=True)
class StreamOptions:
    """How the virtual tracker logs: rate, clock, servo lag, noise correlation, rests (s),
    and its systematic errors (as the machine file's ``tracker`` keys:
    :meth:`sim.tracker.VirtualTracker.observe`)."""

    rate_hz: float = 100.0
    clock_offset_s: float = 5000.0
    clock_rate_ppm: float = 80.0
    servo_lag_s: float = 0.01
    correlation_s: float = 0.05
    rest_s: float = 2.0
    angle_systematic_urad: float = 0.0
    scale_ppm: float = 0.0


@dataclass(frozen=True)
class Timeline:
    """The program's moves in CNC time: start time, start, end, duration, peak speed, accel."""

    t0_s: Vec
    start_mm: Vec
    end_mm: Vec
    duration_s: Vec
    peak_mm_s: Vec
    accel_mm_s2: float

    @property
    def end_s(self) -> float:
        return float(self.t0_s[-1] + self.duration_s[-1])

    def position_mm(self, time_s: Vec) -> tuple[Vec, Vec]:
        """Commanded tool point at CNC times (N,), and the direction of the last motion (N, 3)."""
        move = np.clip(np.searchsorted(self.t0_s, time_s, side="right") - 1, 0, len(self.t0_s) - 1)
        t = np.clip(time_s - self.t0_s[move], 0.0, self.duration_s[move])
        peak, total = self.peak_mm_s[move], self.duration_s[move]
        ramp = peak / self.accel_mm_s2
        length = np.linalg.norm(self.end_mm[move] - self.start_mm[move], axis=1)
        left = total - t
        distance = np.where(
            t < ramp,
            0.5 * self.accel_mm_s2 * t**2,
            np.where(
                left < ramp,
                length - 0.5 * self.accel_mm_s2 * left**2,
                0.5 * peak * ramp + peak * (t - ramp),
            ),
        )
        fraction = np.where(length > 0, distance / np.maximum(length, 1e-12), 1.0)
        path = self.end_mm[move] - self.start_mm[move]
        approach = np.sign(path) + (path == 0)
        return self.start_mm[move] + fraction[:, None] * path, approach


def program_timeline(machine: Machine, program: InstrumentProgram, dialect: str | None) -> Timeline:
    """The program's G-code as the CNC runs it: straight moves, stop to stop, and dwells."""
    name = resolve_dialect(machine, dialect)
    text, _ = write_instrument_program(
        program, machine, make_dialect(name, machine, "STREAM"), "xmalign stream"
    )
    here = program_start_mm(machine)
    steps = read_program(text, name, machine, here, machine.feed_mm_min.rapid)
    accel = machine.cnc.acceleration_mm_s2 or DEFAULT_ACCELERATION_MM_S2
    rows, clock = [], 0.0
    for step in steps:
        if isinstance(step, _Dwell):
            rows.append((clock, here, here, step.seconds, 1.0))
            clock += step.seconds
        elif isinstance(step, _Move):
            length = float(np.linalg.norm(step.target_mm - here))
            speed = min(step.feed_mm_min, machine.feed_mm_min.rapid) / 60.0
            peak = min(speed, float(np.sqrt(length * accel))) if length > 0 else 1.0
            duration = 0.0 if length == 0 else 2 * peak / accel + (length - peak**2 / accel) / peak
            rows.append((clock, here, step.target_mm, duration, peak))
            clock += duration
            here = np.asarray(step.target_mm, dtype=float)
    t0, starts, ends, durations, peaks = zip(*rows, strict=True)
    return Timeline(
        np.array(t0), np.array(starts), np.array(ends), np.array(durations), np.array(peaks), accel
    )


def correlated_noise(n: int, rate_hz: float, correlation_s: float, rng: np.random.Generator) -> Vec:
    """Unit-variance AR(1) noise, (n, 3): ``e_k = phi e_(k-1) + sqrt(1 - phi**2) w_k``."""
    white = rng.normal(size=(n, 3))
    if correlation_s <= 0:
        return white
    phi = float(np.exp(-1.0 / (rate_hz * correlation_s)))
    start = white[:1]
    filtered = scipy.signal.lfilter([np.sqrt(1 - phi**2)], [1.0, -phi], white[1:], axis=0)
    filtered += np.outer(phi ** np.arange(1, n), start[0])  # the stationary start
    return np.vstack([start, filtered])


def record_stream(
    machine: Machine,
    truth: VirtualMachine,
    tracker: VirtualTracker,
    program: InstrumentProgram,
    options: StreamOptions = StreamOptions(),
    station: str = "T1",
    run: int = 0,
    dialect: str | None = None,
) -> StreamRun:
    """What ``tracker`` logs while ``truth`` runs ``program`` once (rests before and after)."""
    timeline = program_timeline(machine, program, dialect)
    n = int((timeline.end_s + 2 * options.rest_s) * options.rate_hz)
    cnc_s = np.arange(n) / options.rate_hz - options.rest_s
    commanded, approach = timeline.position_mm(cnc_s - options.servo_lag_s)
    actual, _ = truth.actual_functional_point(commanded, approach, machine.smr_offset)
    frame = (actual - tracker.position_mm) @ tracker.rotation
    coefficients = angle_coefficients(tracker.seed)
    frame = with_angle_errors(frame, coefficients, options.angle_systematic_urad)
    frame = frame * scale_factor(tracker.seed, run, options.scale_ppm)
    distance = np.linalg.norm(frame, axis=1)
    beam = frame / distance[:, None]
    rng = np.random.default_rng([tracker.seed, run, 31])
    draw = correlated_noise(n, options.rate_hz, options.correlation_s, rng)
    along = np.sum(draw * beam, axis=1)
    radial = tracker.uncertainty.radial_sigma_mm(distance)
    transverse = tracker.uncertainty.transverse_sigma_mm(distance)
    seen = frame + (draw - along[:, None] * beam) * transverse[:, None]
    seen += (along * radial)[:, None] * beam
    tracker_s = options.clock_offset_s + cnc_s * (1.0 + options.clock_rate_ppm * 1e-6)
    return StreamRun(
        station=station,
        run=run,
        time_s=tracker_s,
        tracker_mm=seen,
        u_radial_um=np.full(n, np.nan),
        u_transverse_um=np.full(n, np.nan),
        line=np.arange(n),
    )
