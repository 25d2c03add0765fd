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
from sim.tracker_stream import record_stream
from trajectories.gcode import make_dialect, resolve_dialect
from trajectories.instruments import (
    InstrumentProgram,
    fly_paths,
    point_list_csv,
    propose_tracer_places,
    tracer_points,
    tracker_place,
    tracker_points,
    write_instrument_program,
)
from xmalign.errors import InputError
from xmalign.formats.common import atomic_write_text
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
from xmalign.formats.tracker_stream import write_tracker_stream
from xmalign.machine import Machine
from xmalign.post.compare import grid_points, volumetric_rms_um
from xmalign.post.evaluate import Instruments, PostResult, post_stations
from xmalign.rigid_body import Chain, ErrorTables
from xmalign.steps import import_stream_step, post_step

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
    "tracker-stream.csv",
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


def _minutes(machine: Machine, program: InstrumentProgram, path: Path, dialect: str) -> float:
    text, time = write_instrument_program(
        program, machine, make_dialect(dialect, machine, path.stem), "xmalign dry run"
    )
    atomic_write_text(path, text)
    return time.total_s / 60


def _tracker(
    machine: Machine, truth: VirtualMachine, folder: Path, seed: int, dialect: str
) -> tuple[TrackerFile, float]:
    points = tracker_points(machine)
    program = InstrumentProgram(points_mm=points)
    minutes = TRACKER_RUNS * _minutes(machine, program, folder / "tracker.nc", dialect)
    atomic_write_text(folder / "points.csv", point_list_csv(program, machine.smr_offset))
    tracker = VirtualTracker(tracker_place(machine), np.array(TRACKER_ROTATION_DEG), seed=seed)
    rows = measure_tracker(truth, tracker, points, TRACKER_RUNS, machine.smr_offset)
    write_tracker_points(folder / "tracker.csv", rows)
    return read_tracker_points(folder / "tracker.csv"), minutes


def _tracker_on_the_fly(
    machine: Machine, truth: VirtualMachine, folder: Path, seed: int, dialect: str
) -> tuple[TrackerFile, float]:
    """Paths on the fly: the tracker logs its stream, which ``import --tracker-stream`` reads."""
    program = InstrumentProgram(paths_mm=fly_paths(machine))
    minutes = _minutes(machine, program, folder / "tracker.nc", dialect)
    atomic_write_text(folder / "points.csv", point_list_csv(program, machine.smr_offset))
    tracker = VirtualTracker(tracker_place(machine), np.array(TRACKER_ROTATION_DEG), seed=seed)
    stream = record_stream(machine, truth, tracker, program, dialect=dialect)
    write_tracker_stream(folder / "tracker-stream.csv", [stream])
    import_stream_step(
        machine, folder / "tracker-stream.csv", folder / "points.csv", folder / "tracker.csv"
    )
    return read_tracker_points(folder / "tracker.csv"), minutes


def _tracers(
    machine: Machine, truth: VirtualMachine, folder: Path, seed: int, dialect: str
) -> tuple[TracerFile, float]:
    points = tracer_points(machine)
    program = InstrumentProgram(points_mm=points)
    minutes = 0.0
    lengths = []
    for i, pivot in enumerate(propose_tracer_places(machine, TRACER_PLACES)):
        minutes += _minutes(machine, program, folder / "tracer.nc", dialect)
        tracer = VirtualTracer(pivot, seed=seed * 10 + i)
        lengths += measure_tracer(truth, tracer, points, 1, machine.smr_offset, f"P{i + 1}")
    write_tracer_lengths(folder / "tracer.csv", lengths)
    return read_tracer_lengths(folder / "tracer.csv"), minutes


def simulate_instruments(
    machine: Machine,
    folder: Path,
    instrument: str,
    seed: int = 1,
    dialect: str | None = None,
    on_the_fly: bool = False,
) -> InstrumentDryRun:
    """Program, measure and post with ``instrument`` on the seeded virtual machine.

    ``on_the_fly`` (tracker): the program's paths on the fly, the tracker's stream
    (:mod:`sim.tracker_stream`) through the real import.

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
        measure = _tracker_on_the_fly if on_the_fly else _tracker
        tracker_file, minutes = measure(machine, truth, folder, seed, dialect_name)
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
        alone = post_stations(machine, stations).fit.tables.model()
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
