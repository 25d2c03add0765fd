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
from sim.instrument_errors import MaterialDrift
from sim.machine import VirtualMachine
from sim.tracer import VirtualTracer, measure_tracers_at_once
from sim.tracker import VirtualTracker, measure_tracker
from trajectories.gcode import make_dialect, resolve_dialect
from trajectories.instruments import (
    InstrumentProgram,
    plan_instrument,
    plan_smr_positions,
    point_list_csv,
    tracker_place,
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
from xmalign.geometry import Vec
from xmalign.machine import Machine
from xmalign.post.compare import grid_points, volumetric_rms_um
from xmalign.post.evaluate import Instruments, PostResult, post_stations
from xmalign.rigid_body import Chain, ErrorTables
from xmalign.steps import post_step

INSTRUMENTS = ("xm60", "tracker", "tracer", "xm60+tracker")
#: The tracker stands turned and tilted: the fit's start must not need it level.
TRACKER_ROTATION_DEG = (0.5, -1.0, 30.0)
TRACER_PLACES = 4
#: The dry run's systematic instrument errors where the machine file states none: a
#: tracker's angle errors (RMS, urad; a sixth of the transverse MPE's 6 um/m ... 15 um at
#: 2.5 m, the part that repeats at a station) and scale (1 K of air: 1 ppm), a tracer's
#: scale (0.5 K of air).
TRACKER_ANGLE_URAD = 5.0
TRACKER_SCALE_PPM = 1.0
TRACER_SCALE_PPM = 0.5
#: The machine's scale temperature through each run of the dry run, deg C.
MATERIAL_C = (20.6, 21.4)
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
    #: The machine file as the dry run completed it (:func:`dry_run_machine`).
    machine: Machine | None = None
    #: Tracers all at once; the machine time the other way (one place after another,
    #: or all at once), min.
    simultaneous: bool = False
    other_way_min: float | None = None


def _minutes(machine: Machine, program: InstrumentProgram, path: Path, dialect: str) -> float:
    text, time = write_instrument_program(
        program, machine, make_dialect(dialect, machine, path.stem), "xmalign dry run"
    )
    atomic_write_text(path, text)
    return time.total_s / 60


def dry_run_machine(machine: Machine, smr_offsets_mm: dict[str, Vec]) -> Machine:
    """The machine file as a user would complete it for the dry run: the SMR positions the
    plan mounts, and realistic systematic instrument errors where it states none
    (:data:`TRACKER_ANGLE_URAD`, :data:`TRACKER_SCALE_PPM`, :data:`TRACER_SCALE_PPM`):
    the virtual instruments have them, the fit takes them as the machine file says."""
    tracker, tracer = machine.tracker, machine.tracer
    return machine.model_copy(
        update={
            "smr_offsets_mm": {k: [float(v) for v in o] for k, o in smr_offsets_mm.items()},
            "tracker": tracker.model_copy(
                update={
                    "angle_systematic_urad": tracker.angle_systematic_urad or TRACKER_ANGLE_URAD,
                    "scale_ppm": tracker.scale_ppm or TRACKER_SCALE_PPM,
                }
            ),
            "tracer": tracer.model_copy(update={"scale_ppm": tracer.scale_ppm or TRACER_SCALE_PPM}),
        }
    )


def _material(machine: Machine) -> MaterialDrift:
    return MaterialDrift(*MATERIAL_C, machine.thermal.expansion_ppm_per_k)


def _tracker(
    machine: Machine, truth: VirtualMachine, folder: Path, seed: int, dialect: str
) -> tuple[TrackerFile, float]:
    plan = plan_instrument(machine, "tracker")
    program = plan.program
    minutes = plan.runs * _minutes(machine, program, folder / "tracker.nc", dialect)
    atomic_write_text(folder / "points.csv", point_list_csv(program, machine.smr_offset))
    tracker = VirtualTracker(tracker_place(machine), np.array(TRACKER_ROTATION_DEG), seed=seed)
    rows = measure_tracker(
        truth, tracker, program.points_mm, plan.runs, machine.smr_offset,
        angle_systematic_urad=machine.tracker.angle_systematic_urad,
        scale_ppm=machine.tracker.scale_ppm,
        smr_offsets_mm=program.smr_offsets_mm or None,
        smr_of_point=program.smr_names or None,
        material=_material(machine),
    )  # fmt: skip
    write_tracker_points(folder / "tracker.csv", rows)
    return read_tracker_points(folder / "tracker.csv"), minutes


def _tracers(
    machine: Machine,
    truth: VirtualMachine,
    folder: Path,
    seed: int,
    dialect: str,
    simultaneous: bool,
) -> tuple[TracerFile, float, float]:
    """The tracer lengths, the machine time of this way and of the other way, min."""
    plan = plan_instrument(machine, "tracer", places=TRACER_PLACES, simultaneous=simultaneous)
    program = plan.program
    per_run = _minutes(machine, program, folder / "tracer.nc", dialect)
    tracers = {
        f"P{i + 1}": VirtualTracer(pivot, seed=seed * 10 + i)
        for i, pivot in enumerate(plan.pivots_mm)
    }
    lengths = []
    for group in [tracers] if simultaneous else [{s: t} for s, t in tracers.items()]:
        lengths += measure_tracers_at_once(
            truth, group, program.points_mm, 1, machine.smr_offset,
            scale_ppm=machine.tracer.scale_ppm,
            smr_offsets_mm=program.smr_offsets_mm or None,
            smr_of_point=program.smr_names or None,
            material=_material(machine),
        )  # fmt: skip
    write_tracer_lengths(folder / "tracer.csv", lengths)
    other = per_run * (len(tracers) if simultaneous else 1)
    return read_tracer_lengths(folder / "tracer.csv"), per_run * plan.runs, other


def simulate_instruments(
    machine: Machine,
    folder: Path,
    instrument: str,
    seed: int = 1,
    dialect: str | None = None,
    simultaneous: bool = False,
) -> InstrumentDryRun:
    """Program, measure and post with ``instrument`` on the seeded virtual machine.

    The plan is ``xmalign program --instrument``'s (its SMR positions; tracers one
    place after another, or all at once with ``simultaneous``); the instruments have
    the systematic errors of :func:`dry_run_machine` and the machine a material
    temperature drifting through each run (:data:`MATERIAL_C`).

    Raises
    ------
    InputError
        An unknown instrument, tracers at once for another instrument, or a folder
        that already holds these files.
    """
    if instrument not in INSTRUMENTS[1:]:
        raise InputError(f"--instrument '{instrument}' is not known ({', '.join(INSTRUMENTS)})")
    if simultaneous and instrument != "tracer":
        raise InputError("--simultaneous is for --instrument tracer")
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
    completed = dry_run_machine(machine, plan_smr_positions(machine)[0])
    other_min = None
    if "tracker" in instrument:
        tracker_file, minutes = _tracker(completed, truth, folder, seed, dialect_name)
        instruments = Instruments(trackers=(tracker_file,))
        files = [FileSource.of("tracker", folder / "tracker.csv")]
    else:
        tracer_file, minutes, other_min = _tracers(
            completed, truth, folder, seed, dialect_name, simultaneous
        )
        instruments = Instruments(tracers=(tracer_file,))
        files = [FileSource.of("tracer", folder / "tracer.csv")]
    posted = post_step(
        completed,
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
        machine=completed,
        simultaneous=simultaneous,
        other_way_min=other_min,
    )
