"""Instruments compared on the same random machines (``xmalign mc --mode instruments``).

Seed 003 compares calibration strategies by Monte Carlo; this compares the
instruments: for every trial a new virtual machine (seed 003's error
amplitudes) is measured by

- a laser tracker, seed 000's 250 points twice (``tracker``);
- the tracker on the fly along seed 001's paths (``tracker on the fly``);
- laser tracers from four places, 440 points each (``tracers``);
- one XM-60 station, six lines (``xm60``), and the same with the tracker's
  points in one fit (``xm60+tracker``);

and each gives its RMS volumetric residual over the whole travel (rigid motion
removed; at the SMR without lines, whose tables are the SMR's) and its machine
time. The measurement routines are also those of
``tests/benchmarks/bench_instruments.py``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.interferometer import InterferometerNoise
from sim.machine import ErrorAmplitudes, VirtualMachine
from sim.synthetic import SetupDisturbance, measure
from sim.tracer import VirtualTracer, measure_tracer
from sim.tracker import VirtualTracker, measure_tracker, measure_tracker_on_the_fly
from trajectories.gcode.program import estimate_machine_time
from trajectories.instruments import (
    FLY_FEED_MM_MIN,
    FLY_SPACING_MM,
    InstrumentProgram,
    fly_paths,
    propose_tracer_places,
    tracer_points,
    tracker_place,
    tracker_points,
)
from trajectories.planner import plan_measurement
from xmalign.formats.instruments import TracerFile, TrackerFile
from xmalign.formats.plan import Plan
from xmalign.formats.pose import LaunchPose
from xmalign.machine import Machine
from xmalign.post.compare import grid_points, volumetric_rms_um
from xmalign.post.evaluate import Instruments, PostResult, Station
from xmalign.rigid_body import Chain
from xmalign.steps import fit_step, write_instrument_step

STRATEGIES = ("tracker", "tracker on the fly", "tracers", "xm60", "xm60+tracker")
TRACKER_ROTATION_DEG = (0.5, -1.0, 30.0)
TRACKER_RUNS = 2
TRACER_PLACES = 4
GRID = 8


def _minutes(machine: Machine, program: InstrumentProgram) -> float:
    return (
        write_instrument_step(machine, program, dialect="linuxcnc", title="study")[1].total_s / 60
    )


def _tracker(machine: Machine, seed: int) -> VirtualTracker:
    return VirtualTracker(tracker_place(machine), np.array(TRACKER_ROTATION_DEG), seed=seed)


def tracker_file(machine: Machine, truth: VirtualMachine, seed: int) -> tuple[TrackerFile, float]:
    """The tracker's points (seed 000's strategy, twice) and their machine time, min."""
    points = tracker_points(machine, seed)
    rows = measure_tracker(truth, _tracker(machine, seed), points, TRACKER_RUNS, machine.smr_offset)
    minutes = TRACKER_RUNS * _minutes(machine, InstrumentProgram(points_mm=points))
    return TrackerFile(rows, "tracker.csv"), minutes


def tracker_fly_file(
    machine: Machine, truth: VirtualMachine, seed: int
) -> tuple[TrackerFile, float]:
    """The tracker's samples on the fly along seed 001's paths and their machine time, min."""
    paths = fly_paths(machine, seed)
    rows = measure_tracker_on_the_fly(
        truth,
        _tracker(machine, seed),
        paths,
        FLY_SPACING_MM,
        machine.smr_offset,
        feed_mm_min=FLY_FEED_MM_MIN,
    )
    return TrackerFile(rows, "tracker-fly.csv"), _minutes(
        machine, InstrumentProgram(paths_mm=paths)
    )


def tracer_file(machine: Machine, truth: VirtualMachine, seed: int) -> tuple[TracerFile, float]:
    """The tracers' lengths from four places and their machine time, min."""
    rows = []
    minutes = 0.0
    for i, pivot in enumerate(propose_tracer_places(machine, TRACER_PLACES)):
        points = tracer_points(machine, 10 * seed + i)
        tracer = VirtualTracer(pivot, seed=10 * seed + i)
        rows += measure_tracer(truth, tracer, points, 1, machine.smr_offset, f"P{i + 1}")
        minutes += _minutes(machine, InstrumentProgram(points_mm=points))
    return TracerFile(rows, "tracer.csv"), minutes


def station_plan(machine: Machine) -> Plan:
    """The six lines ``xmalign program`` plans from the machine file's launch position."""
    assert machine.launch_unit is not None, "the machine file needs launch_unit.position_mm"
    position = np.asarray(machine.launch_unit.position_mm, dtype=float)
    covariance = np.diag([0.02**2, 0.02**2, 0.02**2, (20e-6) ** 2])
    return plan_measurement(machine, LaunchPose(position, 0.0, covariance)).plan


def xm60_station(machine: Machine, truth: VirtualMachine, seed: int, plan: Plan) -> Station:
    """One XM-60 station's rows (interferometer noise and setup terms of sim.synthetic)."""
    rng = np.random.default_rng(1000 + seed)
    noise = SetupDisturbance(noise=tuple(InterferometerNoise().sigmas()))
    rows = measure(plan, Chain.parse(machine.chain), truth, rng, setup=noise)
    return Station(plan, rows, "station1.csv")


def trial(
    machine: Machine, seed: int, amplitudes: ErrorAmplitudes | None = None
) -> dict[str, tuple[float, float]]:
    """Every strategy on one random machine: (residual over the travel um, machine time min)."""
    chain = Chain.parse(machine.chain)
    truth = VirtualMachine(machine, amplitudes, seed=seed)
    travel = grid_points(machine.travel_min_mm, machine.travel_max_mm, GRID)

    def rms(result: PostResult, at_smr: bool) -> float:
        offset = machine.smr_offset if at_smr else None
        return volumetric_rms_um(chain, travel, result.fit.tables.model(""), truth, offset)

    trackers, tracker_min = tracker_file(machine, truth, seed)
    fly, fly_min = tracker_fly_file(machine, truth, seed)
    tracers, tracer_min = tracer_file(machine, truth, seed)
    plan = station_plan(machine)
    stations = [xm60_station(machine, truth, seed, plan)]
    xm60_min = estimate_machine_time(plan, machine).total_s / 60
    with_tracker = Instruments(trackers=(trackers,))
    return {
        "tracker": (rms(fit_step(machine, [], instruments=with_tracker), True), tracker_min),
        "tracker on the fly": (
            rms(fit_step(machine, [], instruments=Instruments(trackers=(fly,))), True),
            fly_min,
        ),
        "tracers": (
            rms(fit_step(machine, [], instruments=Instruments(tracers=(tracers,))), True),
            tracer_min,
        ),
        "xm60": (rms(fit_step(machine, stations), False), xm60_min),
        "xm60+tracker": (
            rms(fit_step(machine, stations, instruments=with_tracker), False),
            xm60_min + tracker_min,
        ),
    }


@dataclass(frozen=True)
class StrategyFigures:
    """One strategy over the trials: residual mean, standard deviation, 95th percentile, um."""

    name: str
    residual_um: list[float]
    minutes: float

    @property
    def mean_um(self) -> float:
        return float(np.mean(self.residual_um))

    @property
    def std_um(self) -> float:
        return float(np.std(self.residual_um, ddof=1)) if len(self.residual_um) > 1 else 0.0

    @property
    def p95_um(self) -> float:
        return float(np.percentile(self.residual_um, 95))


def compare_instruments(
    machine: Machine, trials: int, seed: int = 0, amplitudes: ErrorAmplitudes | None = None
) -> list[StrategyFigures]:
    """Every strategy on ``trials`` random machines (seeds ``seed``, ``seed + 1``, ...)."""
    results = [trial(machine, seed + t, amplitudes) for t in range(trials)]
    return [
        StrategyFigures(
            name,
            [r[name][0] for r in results],
            float(np.mean([r[name][1] for r in results])),
        )
        for name in STRATEGIES
    ]
