"""The whole calibration on the virtual machine: identify, program, run, post, comp.

Every step uses the same code as on real hardware (the identification
routine, the planner, the G-code writer, the run orchestration, the
post-processor and the table writers) with the simulated units, interferometer
and CNC behind the roles; at the end the results are compared with the
simulator's truth.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from sim.clock import LockstepClock
from sim.cnc import SimulatedCnc
from sim.environment import SHOPS, attach_shop
from sim.machine import ErrorAmplitudes, VirtualMachine
from sim.units import SimPositioningUnit
from sim.world import World, build_world
from trajectories.planner import MeasurementPlan
from xmalign.calibration import (
    UNIT_MOVE_TIMEOUT_S,
    CalibrationRun,
    RunOutput,
    pre_position_mm,
)
from xmalign.environment import EnvironmentMonitor
from xmalign.errors import InputError
from xmalign.formats.error_tables import ErrorTableSet
from xmalign.formats.plan import Plan
from xmalign.geometry import Vec, wrap_angle
from xmalign.identification_routine import (
    RoutineDevices,
    RoutineEvent,
)
from xmalign.identify import IdentificationResult, IdentificationUncertainty
from xmalign.kinematics import aligned_angles, receiver_cp
from xmalign.machine import Machine
from xmalign.post.compare import grid_points, volumetric_rms_um
from xmalign.post.evaluate import PostResult, post_process
from xmalign.rigid_body import Chain, ErrorTables, RemainingErrors
from xmalign.steps import (
    PROGRAM_SUFFIX,
    Measure,
    ProgramStepResult,
    RunStepDevices,
    StationFiles,
    StationOptions,
    StationStepResult,
    as_left_step,
    comp_step,
    controlled_run_step,
    design_step,
    following_drive,
    identify_step,
    open_measurements_step,
    post_step,
    program_drive,
    run_step,
    station_step,
)

#: How far the simulated launch unit stands from the machine file's coarse guess, mm:
#: anywhere within this horizontally, and up to this much higher (the reference
#: guess sits at the lowest height the receiver reaches, so lower is infeasible).
PLACEMENT_SCATTER_MM = 25.0
#: How often ``run --sim``'s served run reads the position file, s: the served CNC writes
#: it at every step of virtual time, so a short poll finds the machine at a target at once
#: (the live default, 50 ms, would start a 0.5 s dwell's capture up to a tenth of it late).
FOLLOW_POLL_S = 0.01
#: How well a technician aligns the units by hand (standard deviation per axis), rad.
HAND_RAD = 20e-6
STAGES = ("identify", "program", "run", "post", "comp")
#: What a dry run writes into its folder (the program as run.<suffix>).
DRY_RUN_FILES = (
    "session.json",
    "pose.json",
    "plan.json",
    "measurements.csv",
    "errors.csv",
    "truth.csv",
    "comp",
    "verification.csv",
    *(f"run{suffix}" for suffix in PROGRAM_SUFFIX.values()),
)


def check_dry_run_folder(workdir: Path, names: Sequence[str] = DRY_RUN_FILES) -> None:
    """Refuse a folder that is a file or already holds one of a dry run's files ``names``
    (never replaced)."""
    if workdir.exists() and not workdir.is_dir():
        raise InputError(f"{workdir}: is a file; give a folder for the dry run's files")
    found = [name for name in names if (workdir / name).exists()]
    if found:
        raise InputError(
            f"{workdir}/ already holds a dry run ({', '.join(found)}); give another --out"
            " or remove them"
        )


@dataclass(frozen=True)
class DryRunOptions:
    """What a dry run simulates."""

    seed: int = 1
    identification_positions: int = 6
    method: str = "joint"
    dialect: str | None = None
    #: CNC points (N, 3) mm to identify at; default: designed for ``identification_positions``.
    identification_mm: Vec | None = None
    #: How large the virtual machine's errors are drawn; default seed 003 Table 1.
    amplitudes: ErrorAmplitudes | None = None
    #: The shop's air and machine temperature (a name of ``sim.environment.SHOPS``).
    shop: str = "drifting"
    #: Measure again with the controller's tables loaded (as left).
    verify: bool = False
    #: Run the measurement through the real protocol servers (:func:`measure_controlled`)
    #: rather than in-process (:func:`measure_virtually`, the faster shortcut).
    served: bool = False


@dataclass(frozen=True)
class AsLeft:
    """The verification run: the machine measured again with the controller's tables loaded."""

    post: PostResult
    controller: str
    #: Volumetric error left on the virtual machine (truth minus the tables), RMS um.
    volumetric_true_um: float
    #: The same as the verification run measured it, RMS um.
    volumetric_measured_um: float
    #: RMS of the measured minus the true remaining error, um.
    measurement_error_um: float


@dataclass
class LineMargin:
    """Beam margin of one line: predicted (95 %) and seen in the measurement."""

    line: str
    predicted_straightness_um: float
    predicted_angle_urad: float
    measured_straightness_um: float
    measured_angle_urad: float


@dataclass
class DryRunReport:
    """The results of a dry run next to the simulator's truth."""

    identification: IdentificationResult
    truth_launch2mcs_mm: Vec
    truth_gamma_rad: float
    #: The virtual machine that was measured (its errors are the truth of the tables).
    truth: VirtualMachine
    plan: MeasurementPlan
    margins: list[LineMargin]
    volumetric_before_um: float
    volumetric_after_um: float
    #: The same after tables fitted to the readings without the environment compensation.
    volumetric_uncompensated_um: float
    identification_s: float
    alignment_s: float
    measuring_s: float
    points: int
    #: Why the identification design is not as good as planned (shown, never dropped).
    design_warnings: list[str] = field(default_factory=list)
    files: dict[str, Path] = field(default_factory=dict)
    as_left: AsLeft | None = None

    @property
    def position_error_um(self) -> Vec:
        return (self.identification.position_mm - self.truth_launch2mcs_mm) * 1e3

    @property
    def gamma_error_urad(self) -> float:
        return float(wrap_angle(self.identification.gamma_rad - self.truth_gamma_rad)) * 1e6

    @property
    def on_machine_s(self) -> float:
        return self.identification_s + self.alignment_s + self.measuring_s


@dataclass
class VirtualSetup:
    """The virtual machine with its CNC and both units, as a technician finds it on site."""

    world: World
    cnc: SimulatedCnc
    launch: SimPositioningUnit
    receiver: SimPositioningUnit


def placement_scatter_mm(rng: np.random.Generator) -> Vec:
    """How far the launch unit really stands from the machine file's coarse guess, mm (3,).

    Up to :data:`PLACEMENT_SCATTER_MM` per axis, never below the guess in Z (a
    technician sets the unit on the table, not into it).
    """
    scatter = rng.uniform(-PLACEMENT_SCATTER_MM, PLACEMENT_SCATTER_MM, 3)
    scatter[2] = abs(scatter[2])
    return scatter


@dataclass(frozen=True)
class Placement:
    """What the seed of a virtual setup decides: where the launch unit really stands
    (the machine file with its true position), its azimuth and the world's seed."""

    machine: Machine
    gamma_rad: float
    world_seed: int

    @property
    def launch2mcs_mm(self) -> Vec:
        """The launch unit's true position, mm (3,) (the machine file's guess scattered)."""
        if self.machine.launch_unit is None:
            raise InputError(
                f"{self.machine.name}: the machine file has no launch_unit.position_mm"
            )
        return np.asarray(self.machine.launch_unit.position_mm, dtype=float)


def placement(machine: Machine, seed: int) -> Placement:
    """The placement of the virtual setup of ``seed`` (:func:`virtual_setup` builds on it;
    the Monte Carlo identification trials take their truth from it)."""
    rng = np.random.default_rng(seed)
    placed = machine
    if machine.launch_unit is not None:
        scatter = placement_scatter_mm(rng)
        launch_unit = machine.launch_unit.model_copy(
            update={"position_mm": list(np.asarray(machine.launch_unit.position_mm) + scatter)}
        )
        placed = machine.model_copy(update={"launch_unit": launch_unit})
    world_seed = int(rng.integers(2**31))
    return Placement(placed, float(rng.uniform(-math.pi, math.pi)), world_seed)


def virtual_setup(
    machine: Machine,
    seed: int,
    amplitudes: ErrorAmplitudes | None = None,
    lockstep: bool = False,
) -> VirtualSetup:
    """The seeded virtual setup: the same seed gives the same machine, units and placement.

    With ``lockstep`` its clock is a :class:`~sim.clock.LockstepClock`, so the
    setup can be served (:func:`measure_served`); in-process it behaves the same.
    """
    placed = placement(machine, seed)
    world = build_world(
        placed.machine,
        seed=placed.world_seed,
        gamma_rad=placed.gamma_rad,
        amplitudes=amplitudes,
        clock=LockstepClock() if lockstep else None,
    )
    cnc = SimulatedCnc(machine, world.clock)
    world.interferometer.position = cnc
    return VirtualSetup(
        world, cnc, SimPositioningUnit(world.launch), SimPositioningUnit(world.receiver)
    )


def _operator(
    setup: VirtualSetup, machine: Machine, rng: np.random.Generator
) -> Callable[[], None]:
    """A simulated technician who jogs the units until the beams are in range.

    Used where no pose guess can point the units (the first alignment, when the
    launch unit's azimuth is unknown): the units end within about 20 µrad of
    alignment (40 µm at 2 m), inside the ranges, as a person watching the
    receiver's range display would leave them.
    """

    def align_by_hand() -> None:
        world = setup.world
        cp = receiver_cp(
            setup.cnc.position_mm(), machine.receiver_offset, machine.spindle_angle_rad
        )
        angles = aligned_angles(
            world.launch2mcs_mm, world.gamma_rad, cp, machine.spindle_angle_rad, world.offsets
        )
        setup.launch.move_to(angles.launch_rad + rng.normal(0, HAND_RAD, 2), UNIT_MOVE_TIMEOUT_S)
        receiver = angles.receiver_rad + np.append(rng.normal(0, HAND_RAD, 2), 0.0)
        setup.receiver.move_to(receiver, UNIT_MOVE_TIMEOUT_S)

    return align_by_hand


def virtual_devices(setup: VirtualSetup) -> RoutineDevices:
    """The virtual setup behind the roles the identification routine uses."""
    world = setup.world
    return RoutineDevices(
        setup.cnc, setup.launch, setup.receiver, world.interferometer, world.clock
    )


def virtual_run_devices(setup: VirtualSetup) -> RunStepDevices:
    """The virtual setup behind the roles a run uses."""
    world = setup.world
    return RunStepDevices(setup.launch, setup.receiver, world.interferometer, world.clock)


def identify_virtually(
    setup: VirtualSetup,
    machine: Machine,
    positions_mm: Vec,
    session_path: Path,
    method: str = "joint",
    seed: int = 0,
    on_event: Callable[[RoutineEvent], None] | None = None,
    uncertainty: IdentificationUncertainty | None = None,
    pose_path: Path | None = None,
) -> IdentificationResult:
    """:func:`~xmalign.steps.identify_step` on the virtual setup, a simulated technician
    aligning by hand where needed (seeded by ``seed``).

    ``uncertainty`` defaults to the machine file's ``uncertainty`` section; with
    ``pose_path`` the pose is written there.
    """
    return identify_step(
        positions_mm,
        machine,
        virtual_devices(setup),
        session_path,
        method,
        uncertainty,
        manual_align=_operator(setup, machine, np.random.default_rng(seed)),
        on_event=on_event,
        pose_path=pose_path,
    ).result


def measure_virtually(
    setup: VirtualSetup, plan: Plan, program: str, dialect: str, output: RunOutput
) -> CalibrationRun:
    """:func:`~xmalign.steps.run_step` with the G-code program running on the virtual CNC.

    The points ``output`` already holds (a resumed file) are not captured again.
    """
    drive = program_drive(setup.cnc.run_program(program, dialect))
    return run_step(plan, virtual_run_devices(setup), output, drive)


def measure_served(
    setup: VirtualSetup,
    machine: Machine,
    plan: Plan,
    program: str,
    dialect: str,
    output: RunOutput,
) -> CalibrationRun:
    """:func:`~xmalign.steps.run_step` over the real protocols, as a live run does it.

    The setup (on a :class:`~sim.clock.LockstepClock`) is served on 127.0.0.1
    (:func:`sim.servers.served_world.serve_world`: Modbus TCP units, the
    interferometer on a pty, a CNC running ``program`` with a position file);
    the host opens the generated ``units.yaml`` with
    :func:`~firmware_iface.config.open_devices` and follows the machine as
    ``xmalign run --config`` does, a simulated operator pressing cycle start.
    """
    from firmware_iface.config import open_devices
    from sim.servers.served_world import serve_world

    for unit in (setup.world.launch, setup.world.receiver):
        unit.keep_heartbeat(False)  # the in-process host of the identification is gone
    with (
        serve_world(setup.world, machine, program, dialect, setup.cnc) as served,
        open_devices(
            served.config, machine, ask=_no_operator, tell=lambda text: None, clock=served.clock
        ) as devices,
    ):
        following = following_drive(
            devices.mover, served.operator, machine, served.config.timeouts.machine_s, FOLLOW_POLL_S
        )

        def drive(run: CalibrationRun) -> None:
            first = next((line for line in plan.lines if not run.line_is_done(line)), None)
            if first is not None:
                served.run_to_stop_at(pre_position_mm(first, machine.measurement.overrun_mm))
            following(run)

        roles = RunStepDevices(
            devices.launch, devices.receiver, devices.interferometer, served.clock
        )
        return run_step(plan, roles, output, drive)


def measure_controlled(
    setup: VirtualSetup, machine: Machine, plan: Plan, output: RunOutput
) -> CalibrationRun:
    """:func:`~xmalign.steps.run_step` with xmalign running its program on a LinuxCNC.

    As ``xmalign run --config`` does with ``source: linuxcncrsh``: the setup
    (on a :class:`~sim.clock.LockstepClock`) is served on 127.0.0.1
    (:func:`sim.servers.served_world.serve_world_with_linuxcnc`: Modbus TCP
    units, the interferometer on a pty, the CNC as a LinuxCNC over
    linuxcncrsh, all on the world's virtual clock); the host opens the
    generated ``units.yaml`` with :func:`~firmware_iface.config.open_devices`,
    writes the controller's program (a stop at each point) and starts, holds
    and resumes it over linuxcncrsh (:func:`~xmalign.steps.controlled_run_step`).
    """
    from firmware_iface.config import open_devices
    from sim.servers.served_world import serve_world_with_linuxcnc

    for unit in (setup.world.launch, setup.world.receiver):
        unit.keep_heartbeat(False)  # the in-process host of the identification is gone
    with (
        serve_world_with_linuxcnc(setup.world, machine, setup.cnc) as served,
        open_devices(
            served.config, machine, ask=_no_operator, tell=_quiet, clock=served.clock
        ) as devices,
    ):
        config = served.config
        rsh = config.machine_position.linuxcncrsh
        assert devices.controller is not None and rsh is not None
        roles = RunStepDevices(
            devices.launch, devices.receiver, devices.interferometer, served.clock
        )
        return controlled_run_step(
            plan, machine, roles, output, devices.controller, rsh, config.timeouts.machine_s, _quiet
        )


def _quiet(message: str) -> None:
    """What a run tells the technician: nobody reads it in a dry run."""


def _no_operator(prompt: str) -> str:
    raise EOFError(prompt)


def station_measure(
    setup: VirtualSetup,
    machine: Machine,
    served: bool,
    on_point: Callable[[int], None] | None = None,
) -> Measure:
    """How a dry run's station captures its plan: over the served devices with xmalign
    running its program on a simulated LinuxCNC (:func:`measure_controlled`), or
    in-process with the G-code on the virtual CNC (:func:`measure_virtually`)."""

    def measure(programmed: ProgramStepResult, output: RunOutput) -> CalibrationRun:
        if on_point is not None:
            output.on_saved = on_point
        if served:
            return measure_controlled(setup, machine, programmed.plan, output)
        plan, program, dialect = programmed.plan, programmed.program, programmed.dialect
        return measure_virtually(setup, plan, program, dialect, output)

    return measure


def simulate_station(
    setup: VirtualSetup,
    machine: Machine,
    positions_mm: Vec,
    files: StationFiles,
    options: DryRunOptions,
    monitor: EnvironmentMonitor,
    line_ids: tuple[str, ...] | None = None,
    on_stage: Callable[[str], None] | None = None,
    on_point: Callable[[int], None] | None = None,
) -> StationStepResult:
    """One station of a dry run through :func:`~xmalign.steps.station_step`: identified at
    ``positions_mm`` with a simulated technician aligning by hand where needed (seeded by
    ``options.seed``), programmed, and measured as :func:`station_measure` says."""
    return station_step(
        machine,
        positions_mm,
        virtual_devices(setup),
        files,
        station_measure(setup, machine, options.served, on_point),
        StationOptions(options.method, options.dialect, line_ids, options.seed),
        manual_align=_operator(setup, machine, np.random.default_rng(options.seed)),
        environment=monitor,
        on_stage=on_stage,
    )


def _margins(plan: MeasurementPlan, rows: list, machine: Machine) -> list[LineMargin]:
    """Room left in the straightness and angle ranges: predicted (95 %) and measured."""
    ranges = machine.interferometer
    margins = []
    for planned in plan.lines:
        channels = np.array([r.channels for r in rows if r.line == planned.line.id])
        envelope = planned.line.extra.get("envelope", {})
        margins.append(
            LineMargin(
                line=planned.line.id,
                predicted_straightness_um=ranges.straightness_range_um
                - float(envelope.get("straightness_95_um", math.nan)),
                predicted_angle_urad=ranges.angle_range_urad
                - float(envelope.get("angle_95_urad", math.nan)),
                measured_straightness_um=ranges.straightness_range_um
                - float(np.max(np.hypot(channels[:, 1], channels[:, 2]))),
                measured_angle_urad=ranges.angle_range_urad
                - float(np.max(np.abs(channels[:, 3:6]))),
            )
        )
    return margins


def measured_strokes(plan: MeasurementPlan) -> tuple[Vec, Vec]:
    """Per axis, the stretch its own axis line measured: lower and upper CNC limits, (3,) each.

    Compensation tables exist only there; the diagonals reach further, but
    outside the strokes the tables hold their end values and predict nothing.
    """
    low, high = np.empty(3), np.empty(3)
    for k, axis in enumerate("XYZ"):
        points = plan.plan.line(axis).target_points_mm()[:, k]
        low[k], high[k] = points.min(), points.max()
    return low, high


def simulate_calibration(
    machine: Machine,
    workdir: Path,
    options: DryRunOptions | None = None,
    on_stage: Callable[[str], None] | None = None,
    on_point: Callable[[int], None] | None = None,
) -> DryRunReport:
    """Run identify, program, run, post and comp on a seeded virtual machine.

    Files (session, pose, plan, program, measurements, errors, compensation
    tables, truth tables) are written into ``workdir``, which must not hold
    an earlier dry run. ``on_stage`` is called with each stage's name as it
    starts, ``on_point`` with the number of points saved after each one.
    """
    options = options or DryRunOptions()
    stage = on_stage or (lambda name: None)
    check_dry_run_folder(workdir)
    setup = virtual_setup(machine, options.seed, options.amplitudes, lockstep=options.served)
    station = attach_shop(setup.world, SHOPS[options.shop](), options.seed)

    positions = options.identification_mm
    design_warnings: list[str] = []
    if positions is None:
        design = design_step(machine, options.identification_positions)
        positions, design_warnings = design.machine_mm, list(design.warnings)
    # only now, with the options found good, is the folder made
    workdir.mkdir(parents=True, exist_ok=True)
    monitor = EnvironmentMonitor(station, "simulated weather station")
    files = StationFiles(
        workdir / "session.json",
        workdir / "pose.json",
        workdir / "plan.json",
        workdir / "measurements.csv",
    )
    measured = simulate_station(
        setup, machine, positions, files, options, monitor, on_stage=stage, on_point=on_point
    )
    result, programmed, run = measured.identification, measured.programmed, measured.run
    measurement_plan, plan, csv_path = programmed.measurement, programmed.plan, files.measurements

    stage("post")
    posted = post_step(machine, [(plan, csv_path)], workdir / "errors.csv")
    tables: ErrorTableSet = posted.tables
    rows = posted.stations[0].rows
    setup.world.machine.write_truth_tables(str(workdir / "truth.csv"), 50.0)

    stage("comp")
    chain = Chain.parse(machine.chain)
    compensation = comp_step(machine, tables, workdir / "comp")

    low, high = measured_strokes(measurement_plan)
    points = grid_points(low, high)
    truth = setup.world.machine
    as_left = None
    if options.verify:
        stage("verify")
        applied = compensation.fit.mean
        setup.world.machine.load_compensation(applied)
        verification = workdir / "verification.csv"
        with open_measurements_step(verification, plan, machine, environment=monitor) as output:
            station_measure(setup, machine, options.served)(programmed, output)
        left = as_left_step(machine, plan, verification, applied)
        remaining = RemainingErrors(truth, applied)
        as_left = AsLeft(
            left,
            compensation.controller,
            volumetric_rms_um(chain, points, remaining, ErrorTables()),
            volumetric_rms_um(chain, points, left.tool_point_errors(), ErrorTables()),
            volumetric_rms_um(chain, points, left.tool_point_errors(), remaining),
        )
    raw = [replace(row, environment={}) for row in rows]
    uncompensated = post_process(machine, plan, raw, "measurements.csv").fit.tables
    return DryRunReport(
        identification=result,
        truth_launch2mcs_mm=setup.world.launch2mcs_mm,
        truth_gamma_rad=setup.world.gamma_rad,
        truth=truth,
        plan=measurement_plan,
        margins=_margins(measurement_plan, rows, machine),
        volumetric_before_um=volumetric_rms_um(chain, points, truth, ErrorTables()),
        volumetric_after_um=volumetric_rms_um(chain, points, truth, tables.model()),
        volumetric_uncompensated_um=volumetric_rms_um(chain, points, truth, uncompensated.model()),
        identification_s=measured.identify_s,
        alignment_s=run.statistics.alignment_s,
        measuring_s=measured.run_s - run.statistics.alignment_s,
        points=run.statistics.points,
        design_warnings=design_warnings,
        files={
            "session": workdir / "session.json",
            "pose": workdir / "pose.json",
            "plan": workdir / "plan.json",
            "program": programmed.files["program"],
            "measurements": workdir / "measurements.csv",
            "errors": workdir / "errors.csv",
            "truth": workdir / "truth.csv",
            "comp": workdir / "comp",
        }
        | ({"verification": workdir / "verification.csv"} if as_left else {}),
        as_left=as_left,
    )
