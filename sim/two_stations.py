"""The calibration from two launch-unit stations on the virtual machine, end to end.

Station 1 is the dry run's (identify, program, run); then the technician moves
the launch unit to where :func:`trajectories.stations.propose_second_station`
says (within the dry run's placement scatter, at a new azimuth), and the
routine identifies it again and measures that station's lines. ``post`` fits
one set of tables to both measurements. The machine, its errors and the units
stay the same; only the launch unit's pose changes.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sim.dry_run import (
    PLACEMENT_SCATTER_MM,
    DryRunOptions,
    VirtualSetup,
    check_dry_run_folder,
    measured_strokes,
    simulate_station,
    virtual_setup,
)
from sim.environment import SHOPS, attach_shop
from sim.units import SimPositioningUnit
from trajectories.lines import LINE_IDS
from trajectories.planner import MeasurementPlan
from trajectories.stations import StationProposal, propose_second_station
from xmalign.environment import EnvironmentMonitor
from xmalign.errors import InputError
from xmalign.formats.plan import read_plan
from xmalign.machine import LaunchUnitGuess, Machine
from xmalign.post.compare import grid_points, volumetric_rms_um
from xmalign.post.evaluate import PostResult
from xmalign.rigid_body import Chain
from xmalign.steps import (
    PROGRAM_STEM,
    PROGRAM_SUFFIX,
    StationFiles,
    design_step,
    post_step,
    program_file,
)

#: The stations' file names (each prefixed ``station1-`` and ``station2-``).
STATION_FILES = (
    "session.json",
    "pose.json",
    "plan.json",
    "measurements.csv",
    *(f"{PROGRAM_STEM}{suffix}" for suffix in PROGRAM_SUFFIX.values()),
)
#: What a two-station dry run writes into its folder.
TWO_STATION_FILES = (
    *(f"station{n}-{name}" for n in (1, 2) for name in STATION_FILES),
    "errors.csv",
)


@dataclass
class StationRun:
    """One station's plan and the file of its measurement."""

    plan: MeasurementPlan
    measurements: Path
    on_machine_s: float
    #: Why the identification design is not as good as planned (shown, never dropped).
    design_warnings: list[str] = field(default_factory=list)


@dataclass
class TwoStationReport:
    """Both stations and the tables from both, next to the simulator's truth.

    ``strokes_um`` is the RMS volumetric difference over the station-1 axis
    lines' strokes, ``travel_um`` over the whole travel (rigid motion removed).
    """

    stations: list[StationRun]
    proposal: StationProposal
    post: PostResult
    strokes_um: float
    travel_um: float


def _measure_station(
    setup: VirtualSetup,
    machine: Machine,
    workdir: Path,
    name: str,
    options: DryRunOptions,
    monitor: EnvironmentMonitor,
    line_ids: tuple[str, ...] | None = None,
) -> StationRun:
    """Identify, program and run one station as the one-station dry run does
    (:func:`sim.dry_run.simulate_station`: served, xmalign runs its program on a
    simulated LinuxCNC; or in-process), its files prefixed with ``name``."""
    design = design_step(machine, options.identification_positions)
    plan_path = workdir / f"{name}-plan.json"
    program = program_file(plan_path, machine, options.dialect)
    files = StationFiles(
        session=workdir / f"{name}-session.json",
        pose=workdir / f"{name}-pose.json",
        plan=plan_path,
        measurements=workdir / f"{name}-measurements.csv",
        program=program.with_name(f"{name}-{program.name}"),
    )
    measured = simulate_station(
        setup, machine, design.machine_mm, files, options, monitor, line_ids or LINE_IDS
    )
    return StationRun(
        measured.programmed.measurement,
        files.measurements,
        measured.identify_s + measured.run_s,
        list(design.warnings),
    )


def _move_launch_unit(setup: VirtualSetup, position_mm: np.ndarray, seed: int) -> VirtualSetup:
    """The same machine and units with the launch unit placed near ``position_mm``."""
    rng = np.random.default_rng(seed + 7919)
    scatter = rng.uniform(-PLACEMENT_SCATTER_MM, PLACEMENT_SCATTER_MM, 3)
    scatter[2] = -abs(scatter[2])  # a low station must stay at least its stand-off low
    gamma = float(rng.uniform(-math.pi, math.pi))
    interferometer = setup.world.interferometer
    interferometer.launch2mcs_mm = np.asarray(position_mm, dtype=float) + scatter
    interferometer.gamma_rad = gamma
    world = dataclasses.replace(
        setup.world, launch2mcs_mm=interferometer.launch2mcs_mm, gamma_rad=gamma
    )
    # the technician's host connects again: a served run stopped the in-process heartbeat
    launch, receiver = SimPositioningUnit(world.launch), SimPositioningUnit(world.receiver)
    return dataclasses.replace(setup, world=world, launch=launch, receiver=receiver)


def simulate_two_stations(
    machine: Machine, workdir: Path, options: DryRunOptions | None = None
) -> TwoStationReport:
    """Identify, program and run both stations, post both together, compare with the truth.

    Files go to ``workdir`` with the prefixes ``station1-`` and ``station2-``,
    and ``errors.csv`` (:data:`TWO_STATION_FILES`); a folder holding one of them is
    refused (never replaced, nor an earlier session resumed), and so is
    ``options.verify`` (a verification run is one station's).
    """
    options = options or DryRunOptions()
    if options.verify:  # the verification run is one station's (sim.dry_run)
        raise InputError("--verify is for one station (give --stations 1)")
    check_dry_run_folder(workdir, TWO_STATION_FILES)
    workdir.mkdir(parents=True, exist_ok=True)
    setup = virtual_setup(machine, options.seed, options.amplitudes, lockstep=options.served)
    station = attach_shop(setup.world, SHOPS[options.shop](), options.seed)
    monitor = EnvironmentMonitor(station, "simulated weather station")
    first = _measure_station(setup, machine, workdir, "station1", options, monitor)
    launch = first.plan.plan.extra["launch_position_mm"]
    proposal = propose_second_station(machine, np.asarray(launch, dtype=float))
    placed = machine.model_copy(
        update={
            "launch_unit": LaunchUnitGuess(position_mm=[float(v) for v in proposal.position_mm])
        }
    )
    setup = _move_launch_unit(setup, proposal.position_mm, options.seed)
    second = _measure_station(
        setup, placed, workdir, "station2", options, monitor, proposal.line_ids
    )
    plans = [read_plan(workdir / f"{name}-plan.json") for name in ("station1", "station2")]
    measured = [run.measurements for run in (first, second)]
    post = post_step(machine, list(zip(plans, measured, strict=True)), workdir / "errors.csv").post
    chain = Chain.parse(machine.chain)
    truth = setup.world.machine
    model = post.fit.tables.model()
    low, high = measured_strokes(first.plan)
    return TwoStationReport(
        stations=[first, second],
        proposal=proposal,
        post=post,
        strokes_um=volumetric_rms_um(chain, grid_points(low, high), model, truth),
        travel_um=volumetric_rms_um(
            chain, grid_points(machine.travel_min_mm, machine.travel_max_mm), model, truth
        ),
    )
