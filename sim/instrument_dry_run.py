"""``xmalign dry-run --instrument tracker|tracer|xm60+tracker``: the whole chain simulated.

Program, measure, post, against the truth, for a laser tracker (seed 000), laser
tracers from four places (seed 004), or one XM-60 station (the dry run of
:mod:`sim.dry_run`) with a tracker measuring the same virtual machine. The
instruments are :mod:`sim.tracker` and :mod:`sim.tracer`; the virtual machine is
the one the XM-60 dry run with the same seed measures. Every file goes into the
dry run's folder, as a user's would.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sim.dry_run import DryRunOptions, check_dry_run_folder, simulate_calibration, virtual_setup
from sim.machine import VirtualMachine
from sim.tracer import VirtualTracer, measure_tracer
from sim.tracker import VirtualTracker, measure_tracker
from trajectories.gcode import resolve_dialect
from trajectories.instruments import (
    InstrumentProgram,
    propose_tracer_places,
    tracer_points,
    tracker_place,
    tracker_points,
)
from xmalign.errors import InputError
from xmalign.formats.instruments import (
    TracerFile,
    TrackerFile,
    read_tracer_lengths,
    read_tracker_points,
    write_tracer_lengths,
    write_tracker_points,
)
from xmalign.formats.plan import Plan, read_plan
from xmalign.formats.provenance import FileSource
from xmalign.machine import Machine
from xmalign.post.compare import grid_points, volumetric_rms_um
from xmalign.post.evaluate import Instruments, PostResult
from xmalign.rigid_body import Chain, ErrorTables
from xmalign.steps import fit_step, post_step, write_instrument_step

INSTRUMENTS = ("xm60", "tracker", "tracer", "xm60+tracker")
#: The tracker stands turned and tilted: the fit's start must not need it level.
TRACKER_ROTATION_DEG = (0.5, -1.0, 30.0)
TRACKER_RUNS = 2
TRACER_PLACES = 4
#: What an instrument dry run writes (never replaced).
FILES = (
    "tracker.nc",
    "tracker.csv",
    "tracer.nc",
    "tracer.csv",
    "points.csv",
    "errors-instruments.csv",
)


@dataclass
class InstrumentDryRun:
    """An instrument dry run's results next to the truth (whole travel, 8 x 8 x 8 grid)."""

    instrument: str
    volumetric_before_um: float
    volumetric_after_um: float
    #: Machine time of the instrument's programs (all runs and places), min.
    instrument_min: float
    result: PostResult
    functional_point: str
    #: The XM-60 station's measuring time, min, and its residual alone over the travel, um.
    xm60_min: float = 0.0
    xm60_after_um: float | None = None
    files: dict[str, Path] = field(default_factory=dict)


def _minutes(
    machine: Machine,
    program: InstrumentProgram,
    path: Path,
    dialect: str,
    points_path: Path | None = None,
) -> float:
    """Write the program (and the point list) as ``xmalign program --instrument`` does;
    its machine time, min."""
    _, machine_time, _ = write_instrument_step(
        machine, program, path, points_path, dialect, "xmalign dry run"
    )
    return machine_time.total_s / 60


def _tracker(
    machine: Machine, truth: VirtualMachine, folder: Path, seed: int, dialect: str
) -> tuple[TrackerFile, float]:
    points = tracker_points(machine)
    program = InstrumentProgram(points_mm=points)
    minutes = TRACKER_RUNS * _minutes(
        machine, program, folder / "tracker.nc", dialect, folder / "points.csv"
    )
    tracker = VirtualTracker(tracker_place(machine), np.array(TRACKER_ROTATION_DEG), seed=seed)
    rows = measure_tracker(truth, tracker, points, TRACKER_RUNS, machine.smr_offset)
    write_tracker_points(folder / "tracker.csv", rows)
    return read_tracker_points(folder / "tracker.csv"), minutes


def _tracers(
    machine: Machine, truth: VirtualMachine, folder: Path, seed: int, dialect: str
) -> tuple[TracerFile, float]:
    points = tracer_points(machine)
    program = InstrumentProgram(points_mm=points)
    places = propose_tracer_places(machine, TRACER_PLACES)
    minutes = len(places) * _minutes(machine, program, folder / "tracer.nc", dialect)
    lengths = []
    for i, pivot in enumerate(places):
        tracer = VirtualTracer(pivot, seed=seed * 10 + i)
        lengths += measure_tracer(truth, tracer, points, 1, machine.smr_offset, f"P{i + 1}")
    write_tracer_lengths(folder / "tracer.csv", lengths)
    return read_tracer_lengths(folder / "tracer.csv"), minutes


def simulate_instruments(
    machine: Machine, folder: Path, instrument: str, seed: int = 1, dialect: str | None = None
) -> InstrumentDryRun:
    """Program, measure and post with ``instrument`` on the seeded virtual machine.

    Raises
    ------
    InputError
        An unknown instrument, or a folder that already holds these files.
    """
    if instrument not in INSTRUMENTS[1:]:
        raise InputError(f"--instrument '{instrument}' is not known ({', '.join(INSTRUMENTS)})")
    check_dry_run_folder(folder)
    found = [name for name in FILES if (folder / name).exists()]
    if found:
        raise InputError(f"{folder}/ already holds {', '.join(found)}; give another --out")
    folder.mkdir(parents=True, exist_ok=True)
    dialect_name = resolve_dialect(machine, dialect)
    pairs: list[tuple[Plan, Path]] = []
    xm60_min, xm60_after = 0.0, None
    if instrument == "xm60+tracker":
        options = DryRunOptions(seed=seed, dialect=dialect, served=False)
        report = simulate_calibration(machine, folder, options)
        xm60_min = report.measuring_s / 60
        pairs = [(read_plan(folder / "plan.json"), folder / "measurements.csv")]
    truth = virtual_setup(machine, seed).world.machine
    if "tracker" in instrument:
        tracker_file, minutes = _tracker(machine, truth, folder, seed, dialect_name)
        instruments = Instruments(trackers=(tracker_file,))
        files = [FileSource.of("tracker", folder / "tracker.csv")]
    else:
        tracer_file, minutes = _tracers(machine, truth, folder, seed, dialect_name)
        instruments = Instruments(tracers=(tracer_file,))
        files = [FileSource.of("tracer", folder / "tracer.csv")]
    posted = post_step(
        machine,
        pairs,
        folder / "errors-instruments.csv",
        instruments=instruments,
        instrument_files=files,
    )
    result, stations = posted.post, posted.stations
    chain = Chain.parse(machine.chain)
    grid = grid_points(machine.travel_min_mm, machine.travel_max_mm, 8)
    offset = None if stations else machine.smr_offset
    if stations:
        alone = fit_step(machine, stations).fit.tables.model()
        xm60_after = volumetric_rms_um(chain, grid, alone, truth)
    assert result.instruments is not None
    return InstrumentDryRun(
        instrument=instrument,
        volumetric_before_um=volumetric_rms_um(chain, grid, ErrorTables(), truth, offset),
        volumetric_after_um=volumetric_rms_um(
            chain, grid, result.fit.tables.model(), truth, offset
        ),
        instrument_min=minutes,
        result=result,
        functional_point=result.instruments.functional_point,
        xm60_min=xm60_min,
        xm60_after_um=xm60_after,
        files={name: folder / name for name in FILES if (folder / name).exists()},
    )
